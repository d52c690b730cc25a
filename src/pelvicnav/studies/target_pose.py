"""Leave-one-out study of target-pose estimation (Han et al. 2020, sections 2.3.1-2.3.2, figure 5).

For every test subject, the models are built from the other subjects only. Each innominate in turn
(and both at once) is the dislocated bone: it is moved by a random rigid dislocation (uniform in
0-20 mm and 0-10 degrees about its centroid, seeded) and every method estimates where it belongs
from the observed bones. The ground-truth meshes stand in for the segmentations (or, with
``segmentation="asm"``, the active shape model's).

Error of an estimate: ``eps = T_true^-1 T_est`` with each bone's pose taken as the CT axes placed at
the true centroid; translation = displacement of the bone's centroid, rotation = angle of ``eps``;
also the mean vertex displacement.

Outputs (in ``out``): the runner's ``store.sqlite`` and ``results.csv`` (one row per fold and
estimate, resumable), ``cases.csv`` (one row per subject x scenario x method x estimated bone, with
the true and estimated 4x4 poses flattened row-major), ``summary.csv``, ``comparisons.csv`` (paired
Wilcoxon signed-rank and t-tests), ``target_pose_boxplot.png`` and ``settings.json``.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pelvicnav.geometry import transforms as tf
from pelvicnav.io.atomic import save_figure, write_text

__all__ = [
    "METHODS",
    "PAPER_MEDIANS",
    "SCENARIOS",
    "TargetPoseSettings",
    "run_target_pose_study",
    "summarise",
]

BONES = ("sacrum", "left_hip", "right_hip")
# SPM_CC is SPM plus the joint-space refinement and the collision check; SPM_collision is the
# paper's collision-only refinement, kept for comparison.
METHODS = ("SSM_single", "CM", "SPM", "SPM_CC", "SPM_collision")
SCENARIOS: dict[str, tuple[str, ...]] = {
    "left_hip": ("left_hip",),
    "right_hip": ("right_hip",),
    "both_hips": ("left_hip", "right_hip"),
}
# Median translation (mm) / rotation (deg) reported by Han et al. (2020), figure 5.
PAPER_MEDIANS = {
    "SSM_single": (7.7, 5.5),
    "CM": (4.6, 4.8),
    "SPM": (3.8, 2.2),
    "SPM_CC": (2.3, 2.1),
    "SPM_collision": (2.3, 2.1),
}
CASE_FIELDS = (
    "subject_id",
    "dislocated_bone",
    "evaluated_bone",
    "method",
    "translation_mm",
    "rotation_deg",
    "mean_vertex_mm",
    "refinement_mm",
    "dislocation_mm",
    "dislocation_deg",
)
SUMMARY_FIELDS = (
    "method",
    "dislocated_bone",
    "n",
    "translation_median_mm",
    "translation_iqr_mm",
    "rotation_median_deg",
    "rotation_iqr_deg",
    "mean_vertex_median_mm",
)


@dataclass(frozen=True)
class TargetPoseSettings:
    """Everything that decides the study's numbers (written to ``settings.json``).

    Attributes
    ----------
    seed : int
        Seeds the dislocations (per subject and scenario).
    subjects : tuple of int or None
        Atlas ids to test (default all); models always use all the other subjects.
    scenarios, methods : tuples of names
    prior : float
        SPM: Tikhonov weight of the mode-weight prior (eq. 8a), scaled tangent units.
    metric : str
        SPM tangent metric, ``"radius"`` or ``"plain"``.
    n_modes : int or None
        SPM modes (default all).
    ssm_noise_variance : float, mm^2
        SSM_single: observation noise of the partial fit.
    max_dislocation_mm, max_dislocation_deg : float
        Dislocation magnitudes are uniform in [0, max].
    workers : int
        Processes over test subjects.
    frame_scale : bool or None
        SPM global frame: similarity, rigid, or (None) similarity unless only the sacrum is seen.
    segmentation : {"truth", "asm"}
        What the planner sees of the test subject: its atlas meshes, or its bones segmented by
        the ASM on a CT synthesised from it (prior from the other subjects; the segmentation
        study's meshes). The error is always against the atlas meshes.
    """

    seed: int = 0
    subjects: tuple[int, ...] | None = None
    scenarios: tuple[str, ...] = tuple(SCENARIOS)
    methods: tuple[str, ...] = METHODS
    prior: float = 0.1
    metric: str = "radius"
    n_modes: int | None = None
    ssm_noise_variance: float = 4.0
    max_dislocation_mm: float = 20.0
    max_dislocation_deg: float = 10.0
    workers: int = 1
    frame_scale: bool | None = None
    segmentation: str = "truth"

    @classmethod
    def quick(cls, subject_ids, seed: int = 0, **kw) -> TargetPoseSettings:
        """The first two of ``subject_ids`` tested, the left hip, SPM and SPM_CC (for CI)."""
        ids = tuple(int(i) for i in subject_ids[:2])
        return cls(seed=seed, subjects=ids, scenarios=("left_hip",), methods=("SPM", "SPM_CC"),
                   **kw)  # fmt: skip

    def __post_init__(self) -> None:
        for s in self.scenarios:
            if s not in SCENARIOS:
                raise ValueError(f"unknown scenario {s!r}; expected one of {tuple(SCENARIOS)}")
        for m in self.methods:
            if m not in METHODS:
                raise ValueError(f"unknown method {m!r}; expected one of {METHODS}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.segmentation not in ("truth", "asm"):
            raise ValueError(f"segmentation must be 'truth' or 'asm', got {self.segmentation!r}")


def bone_pose(centroid: NDArray[np.float64]) -> NDArray[np.float64]:
    """A bone's reference pose: CT axes placed at its (true) centroid."""
    T = np.eye(4)
    T[:3, 3] = centroid
    return T


def pose_errors(true_vertices: NDArray, estimated_vertices: NDArray) -> tuple[float, float, float]:
    """(centroid translation mm, rotation deg, mean vertex displacement mm) of a rigid estimate."""
    from pelvicnav.geometry.procrustes import fit_transform

    E = fit_transform(true_vertices, estimated_vertices)  # estimated = E(true)
    t = float(np.linalg.norm(estimated_vertices.mean(axis=0) - true_vertices.mean(axis=0)))
    r = float(np.degrees(np.linalg.norm(tf.rotvec_from_matrix(E[:3, :3]))))
    mv = float(np.linalg.norm(estimated_vertices - true_vertices, axis=1).mean())
    return t, r, mv


def random_dislocation(
    rng: np.random.Generator, centroid: NDArray, max_mm: float, max_deg: float
) -> tuple[NDArray[np.float64], float, float]:
    """Rigid dislocation about ``centroid``: uniform magnitudes, uniformly random directions."""
    t_dir = rng.normal(size=3)
    r_dir = rng.normal(size=3)
    t_mag = rng.uniform(0.0, max_mm)
    r_mag = rng.uniform(0.0, max_deg)
    R = tf.matrix_from_rotvec(np.deg2rad(r_mag) * r_dir / np.linalg.norm(r_dir))
    D = np.eye(4)
    D[:3, :3] = R
    D[:3, 3] = centroid - R @ centroid + t_mag * t_dir / np.linalg.norm(t_dir)
    return D, float(t_mag), float(r_mag)


def _fold(
    vertices: NDArray[np.float64],
    faces: tuple[NDArray, ...],
    subject_ids: tuple[int, ...],
    test: int,
    settings: TargetPoseSettings,
    gaps: tuple[NDArray[np.float64], NDArray[np.float64]],
    segmented: NDArray[np.float64] | None = None,
) -> list[dict]:
    """All scenarios and methods for one left-out subject (seen as ``segmented[test]`` when
    given, else as its atlas meshes)."""
    from threadpoolctl import threadpool_limits

    from pelvicnav.pose.baselines import MirrorEstimator, SinglePelvisEstimator

    with threadpool_limits(1):
        train = np.delete(vertices, test, axis=0)
        train_gaps = (np.delete(gaps[0], test, axis=0), np.delete(gaps[1], test, axis=0))
        subject = vertices[test]
        seen = subject if segmented is None else segmented[test]
        baselines = {
            "SSM_single": SinglePelvisEstimator.fit(
                train, noise_variance=settings.ssm_noise_variance
            ) if "SSM_single" in settings.methods else None,
            "CM": MirrorEstimator.fit(train) if "CM" in settings.methods else None,
        }  # fmt: skip
        rows: list[dict] = []
        for s_index, scenario in enumerate(settings.scenarios):
            dislocated = SCENARIOS[scenario]
            observed = tuple(b for b in BONES if b not in dislocated)
            rng = np.random.default_rng([settings.seed, subject_ids[test], s_index])
            current, disl = _dislocated(subject, seen, dislocated, rng, settings)
            obs = {b: seen[BONES.index(b)] for b in observed}
            estimates = _estimates(obs, current, baselines, train, faces, train_gaps, settings)
            for method in settings.methods:
                for b, (C, refinement) in estimates.get(method, {}).items():
                    scored = _scored(subject[BONES.index(b)], C, refinement, disl[b])
                    rows.append({"subject_id": subject_ids[test], "dislocated_bone": scenario,
                                 "evaluated_bone": b, "method": method, **scored})  # fmt: skip
    return rows


def _dislocated(subject: NDArray, seen: NDArray, dislocated: tuple[str, ...],
                rng: np.random.Generator,
                settings: TargetPoseSettings) -> tuple[dict, dict]:  # fmt: skip
    """Each ``dislocated`` bone moved by a random dislocation about its true centroid: the
    moved meshes as the planner sees them (``seen``), and bone -> (D, mm, deg)."""
    current, disl = {}, {}
    for b in dislocated:
        true = subject[BONES.index(b)]
        D, dmm, ddeg = random_dislocation(rng, true.mean(axis=0), settings.max_dislocation_mm,
                                          settings.max_dislocation_deg)  # fmt: skip
        current[b] = tf.apply(D, seen[BONES.index(b)])
        disl[b] = (D, dmm, ddeg)
    return current, disl


def _estimates(obs: dict, current: dict, baselines: dict, train: NDArray, faces: tuple,
               train_gaps: tuple, settings: TargetPoseSettings) -> dict[str, dict]:  # fmt: skip
    """method -> bone -> (target_from_current, refinement) of every method of ``settings``
    that applies (the mirror needs a single dislocated bone)."""
    from pelvicnav.pose.target import TargetPlanner

    estimates: dict[str, dict[str, tuple[NDArray, NDArray]]] = {}
    for name, estimator in baselines.items():
        if estimator is not None and (name != "CM" or len(current) == 1):
            est = estimator.estimate(obs, current)
            estimates[name] = {b: (T, np.zeros(3)) for b, T in est.items()}
    refinements = (("SPM", "none"), ("SPM_CC", "joint"), ("SPM_collision", "collision"))
    spm = [(n, r) for n, r in refinements if n in settings.methods]
    if spm:  # obs is keyed by the observed bones in BONES order
        planner = TargetPlanner.fit(train, faces, observed=tuple(obs), prior=settings.prior,
                                    n_modes=settings.n_modes, metric=settings.metric,
                                    frame_scale=settings.frame_scale, training_gaps=train_gaps[0],
                                    training_plane_gaps=train_gaps[1])  # fmt: skip
        for name, refine in spm:
            est = planner.estimate(obs, current, refine=refine)
            estimates[name] = {b: (e.target_from_current, e.refinement) for b, e in est.items()}
    return estimates


def _scored(true: NDArray, C: NDArray, refinement: NDArray, disl: tuple) -> dict:
    """One estimate's errors: where the planned correction ``C`` puts the real bone ``true``
    (its CT vertices) after its dislocation ``disl`` (D, mm, deg). With ASM input the mesh the
    planner saw carries the segmentation's own vertex error; the bone does not."""
    D, dmm, ddeg = disl
    t, r, mv = pose_errors(true, tf.apply(C @ D, true))
    T_true = bone_pose(true.mean(axis=0))
    T_est = C @ D @ T_true
    return {"translation_mm": t, "rotation_deg": r, "mean_vertex_mm": mv,
            "refinement_mm": float(np.linalg.norm(refinement)), "dislocation_mm": dmm,
            "dislocation_deg": ddeg,
            **{f"true_{i}{j}": T_true[i, j] for i in range(4) for j in range(4)},
            **{f"est_{i}{j}": T_est[i, j] for i in range(4) for j in range(4)}}  # fmt: skip


_CACHE: dict = {}


def _inputs(path: str, digest: str) -> dict:
    """The study's input arrays (``OUT/inputs.npz``), read once per worker."""
    key = ("inputs", path, digest)
    if key not in _CACHE:
        _CACHE.clear()  # one study's inputs at a time
        with np.load(path) as f:
            _CACHE[key] = {k: f[k] for k in f.files}
    return _CACHE[key]


def run_gaps_case(case: dict) -> dict:
    """Joint gaps of one subject (they depend on it alone), saved to ``case["folder"]``."""
    from pelvicnav.io.atomic import write_bytes
    from pelvicnav.pose.collision import subject_joint_gaps
    from pelvicnav.pose.joint_space import subject_plane_gaps

    data = _inputs(case["inputs"], case["digest"])
    faces = tuple(data[f"faces_{b}"] for b in range(3))
    V = data["vertices"][case["index"]]
    buf = io.BytesIO()
    np.savez(buf, joint=subject_joint_gaps(V, faces), plane=subject_plane_gaps(V, faces))
    write_bytes(Path(case["folder"]) / f"{case['index']:03d}.npz", buf.getvalue())
    return {"subject_id": int(data["subject_ids"][case["index"]])}


def _gaps(folder: str, n: int, digest: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    key = ("gaps", folder, digest)
    if key not in _CACHE:
        pairs = []
        for k in range(n):
            with np.load(Path(folder) / f"{k:03d}.npz") as f:
                pairs.append((f["joint"], f["plane"]))
        _CACHE[key] = (np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]))
    return _CACHE[key]


def run_target_pose_case(case: dict) -> list[dict]:
    """One left-out subject: every scenario and method (the runner's case function)."""
    data = _inputs(case["inputs"], case["digest"])
    V = data["vertices"]
    faces = tuple(data[f"faces_{b}"] for b in range(3))
    ids = tuple(int(i) for i in data["subject_ids"])
    settings = TargetPoseSettings(**case["settings"])
    gaps = _gaps(case["gaps"], len(V), case["digest"])
    return _fold(V, faces, ids, case["test"], settings, gaps, data.get("segmented"))


def _write_inputs(out: Path, atlas, segmented: NDArray | None) -> str:
    """Write the arrays every case reads; returns their digest (part of the store's key)."""
    from pelvicnav.io.atomic import write_bytes

    arrays = {
        "vertices": np.asarray(atlas.vertices, dtype=np.float64),
        "subject_ids": np.asarray(atlas.subject_ids, dtype=np.int64),
        **{f"faces_{b}": np.asarray(atlas.faces[b], dtype=np.int64) for b in range(3)},
    }
    if segmented is not None:
        arrays["segmented"] = np.asarray(segmented, dtype=np.float64)
    digest = hashlib.sha256()
    for k in sorted(arrays):
        digest.update(k.encode())
        digest.update(np.ascontiguousarray(arrays[k]).tobytes())
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    write_bytes(out / "inputs.npz", buf.getvalue())
    return digest.hexdigest()[:16]


def target_pose_studies(atlas, out: Path, settings: TargetPoseSettings, segmented=None):
    """The runner's two studies: joint gaps per subject, then one case per left-out subject."""
    from pelvicnav.studies.runner import Study

    tests = (
        list(range(atlas.n_subjects))
        if settings.subjects is None
        else [atlas.subject_index(s) for s in settings.subjects]
    )
    digest = _write_inputs(out, atlas, segmented)
    inputs, folder = str(out / "inputs.npz"), out / "gaps"
    folder.mkdir(parents=True, exist_ok=True)
    gaps = Study("target-pose-gaps", {"inputs": digest},
                 tuple({"case_id": f"gaps-{k:03d}", "inputs": inputs, "digest": digest, "index": k,
                        "folder": str(folder)} for k in range(atlas.n_subjects)),
                 run_gaps_case)  # fmt: skip
    cfg = {k: v for k, v in asdict(settings).items() if k != "workers"}
    cases = tuple({"case_id": f"subject-{atlas.subject_ids[t]:03d}", "inputs": inputs,
                   "digest": digest, "gaps": str(folder), "test": t, "settings": asdict(settings)}
                  for t in tests)  # fmt: skip
    main = Study("target-pose", {**cfg, "inputs": digest}, cases, run_target_pose_case)
    return gaps, main, tests


def run_target_pose_study(
    atlas,
    out: str | os.PathLike,
    settings: TargetPoseSettings,
    *,
    progress: Callable[[int, int], None] | None = None,
    segmented: NDArray[np.float64] | None = None,
    scheduler: str | None = None,
    force: bool = False,
) -> list[dict]:
    """Run the leave-one-out study on the study runner and write its outputs.

    Every fold is a case of :mod:`pelvicnav.studies.runner`: stored in ``OUT/store.sqlite`` as it
    finishes (a re-run skips it), on a dask ``LocalCluster`` of ``settings.workers`` processes
    (one: in this process) or on ``scheduler``. The cases read ``OUT/inputs.npz`` (a cluster's
    workers need ``OUT`` on a shared file system).

    Parameters
    ----------
    atlas : pelvicnav.io.atlas.Atlas
    out : path-like
        Output folder (created).
    settings : TargetPoseSettings
    progress : callable(done, total), optional
        Folds done (after the joint gaps of every subject).
    segmented : (n_subjects, 3, n_vertices, 3) float, optional
        With ``settings.segmentation == "asm"``: each tested subject's segmented meshes.
    scheduler : str, optional
        Address of a running dask scheduler.
    force : bool
        Start afresh when ``OUT`` holds the study run with other settings.

    Returns
    -------
    list of dict
        The rows of ``cases.csv``.
    """
    from pelvicnav.studies.runner import flatten, run_study

    if (segmented is None) != (settings.segmentation == "truth"):
        raise ValueError("segmented meshes go with segmentation='asm', and only with it")
    if atlas.n_subjects < 5:
        raise ValueError(f"the study needs at least 5 subjects, the atlas has {atlas.n_subjects}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    gaps, study, tests = target_pose_studies(atlas, out, settings, segmented)
    serial = settings.workers == 1 and scheduler is None
    runner = {"scheduler": scheduler, "force": force, "workers": 0 if serial else settings.workers}
    run_study(gaps, out / "gaps", **runner)
    results = run_study(study, out, progress=progress, **runner)
    rows = [{k: v for k, v in r.items() if k != "case_seconds"} for r in flatten(results)]
    seconds = time.perf_counter() - t0
    summary = summarise(rows, settings)
    comparisons = compare_methods(rows, settings)
    _write_csv(out / "cases.csv", rows)
    _write_csv(out / "summary.csv", summary, SUMMARY_FIELDS)
    _write_csv(out / "comparisons.csv", comparisons)
    _boxplot(rows, settings, out / "target_pose_boxplot.png")
    meta = {
        "settings": asdict(settings),
        "atlas": atlas.source,
        "n_subjects_in_atlas": atlas.n_subjects,
        "test_subjects": [atlas.subject_ids[t] for t in tests],
        "seconds": seconds,
        "paper_medians_mm_deg": PAPER_MEDIANS,
    }
    write_text(out / "settings.json", json.dumps(meta, indent=2) + "\n")
    return rows


def summarise(rows: Sequence[dict], settings: TargetPoseSettings) -> list[dict]:
    """Median and IQR per method and scenario (``n`` = estimated bones)."""
    out = []
    for method in settings.methods:
        for scenario in settings.scenarios:
            sel = [r for r in rows if r["method"] == method and r["dislocated_bone"] == scenario]
            row = {"method": method, "dislocated_bone": scenario, "n": len(sel)}
            for key, col in (
                ("translation_mm", "translation"),
                ("rotation_deg", "rotation"),
            ):
                unit = "mm" if key.endswith("mm") else "deg"
                vals = np.array([r[key] for r in sel])
                if len(vals):
                    q1, med, q3 = np.percentile(vals, [25, 50, 75])
                    row[f"{col}_median_{unit}"] = round(float(med), 4)
                    row[f"{col}_iqr_{unit}"] = round(float(q3 - q1), 4)
                else:
                    row[f"{col}_median_{unit}"] = row[f"{col}_iqr_{unit}"] = ""
            mv = [r["mean_vertex_mm"] for r in sel]
            row["mean_vertex_median_mm"] = round(float(np.median(mv)), 4) if mv else ""
            out.append(row)
    return out


def compare_methods(rows: Sequence[dict], settings: TargetPoseSettings) -> list[dict]:
    """Paired tests between every pair of methods, per scenario and error measure."""
    from scipy import stats

    out = []
    for scenario in settings.scenarios:
        for metric in ("translation_mm", "rotation_deg"):
            by_method = {}
            for m in settings.methods:
                by_method[m] = {
                    (r["subject_id"], r["evaluated_bone"]): r[metric]
                    for r in rows
                    if r["method"] == m and r["dislocated_bone"] == scenario
                }
            methods = [m for m in settings.methods if by_method[m]]
            for i, a in enumerate(methods):
                for b in methods[i + 1 :]:
                    keys = sorted(set(by_method[a]) & set(by_method[b]))
                    if len(keys) < 3:
                        continue
                    x = np.array([by_method[a][k] for k in keys])
                    y = np.array([by_method[b][k] for k in keys])
                    d = x - y
                    w = stats.wilcoxon(x, y) if np.any(d != 0) else None
                    t = stats.ttest_rel(x, y) if np.any(d != 0) else None
                    out.append(
                        {
                            "dislocated_bone": scenario,
                            "metric": metric,
                            "method_a": a,
                            "method_b": b,
                            "n": len(keys),
                            "median_a": round(float(np.median(x)), 4),
                            "median_b": round(float(np.median(y)), 4),
                            "median_difference": round(float(np.median(d)), 4),
                            "wilcoxon_p": float(w.pvalue) if w else 1.0,
                            "ttest_p": float(t.pvalue) if t else 1.0,
                        }
                    )
    return out


def _write_csv(path: Path, rows: Sequence[dict], fields: Sequence[str] | None = None) -> None:
    if fields is None:
        fields = list(rows[0]) if rows else []
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(fields))
        writer.writeheader()
        for r in rows:
            writer.writerow(
                {
                    k: (f"{v:.6g}" if isinstance(v, float) else v)
                    for k, v in r.items()
                    if k in fields
                }
            )
    os.replace(tmp, path)


def _boxplot(rows: Sequence[dict], settings: TargetPoseSettings, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {
        "SSM_single": "#8c8c8c",
        "CM": "#dd8452",
        "SPM": "#4c72b0",
        "SPM_CC": "#55a868",
        "SPM_collision": "#8172b3",
    }
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, (key, label) in zip(
        axes,
        (("translation_mm", "translation error (mm)"), ("rotation_deg", "rotation error (deg)")),
        strict=True,
    ):
        width = 0.8 / len(settings.methods)
        for k, method in enumerate(settings.methods):
            data, pos = [], []
            for s_i, scenario in enumerate(settings.scenarios):
                vals = [
                    r[key]
                    for r in rows
                    if r["method"] == method and r["dislocated_bone"] == scenario
                ]
                if vals:
                    data.append(vals)
                    pos.append(s_i + (k - (len(settings.methods) - 1) / 2) * width)
            if data:
                bp = ax.boxplot(
                    data, positions=pos, widths=width * 0.9, patch_artist=True, showfliers=True
                )
                for patch in bp["boxes"]:
                    patch.set_facecolor(colours.get(method, "#cccccc"))
                ax.plot([], [], "s", color=colours.get(method, "#cccccc"), label=method)
        ax.set_xticks(range(len(settings.scenarios)))
        ax.set_xticklabels([s.replace("_", " ") for s in settings.scenarios])
        ax.set_ylabel(label)
        ax.set_xlabel("dislocated bone")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle(
        "Target reduction pose, leave-one-out over the atlas (cf. Han et al. 2020, fig. 5)"
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
