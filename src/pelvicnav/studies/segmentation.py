"""Segmentation accuracy of the active shape model (Han et al. 2020, section 2.1.1 and 3.1).

Cases:

* **atlas** - leave-one-out on CTs synthesised from atlas subjects: the shape prior is fitted
  from the other subjects (:meth:`~pelvicnav.shape.asm.ShapePrior.from_subjects`), the CT from
  the subject's meshes (:func:`~pelvicnav.phantom.ctsynth.synthesize_ct`, femurs and bowel in the
  field), ``intact`` or ``dislocated`` (one innominate moved by the simulator's patterns, 0-20 mm
  and 0-10 deg);
* **real** - the three real CTs (``shared/data/real-ct``) against their manual labels, with the
  shipped model (never fitted on them): ``masked`` as they come (bone CT numbers, 0 elsewhere),
  and ``body``, their bones put into a synthetic body so that nothing tells bone from
  non-bone but CT numbers.

Per bone: Dice of the label map against the truth's, Dice of the fitted surface's interior alone
(``surface_dice``: no help from the CT's bone voxels), and the symmetric surface RMSD between the
fitted mesh and the truth (the subject's mesh, or the marching-cubes surface of a real label).
The fitted meshes are kept in ``OUT/meshes/<case_id>.npz`` for the downstream studies.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pelvicnav import BONES
from pelvicnav.studies.runner import Study, flatten, run_study

__all__ = ["SegmentationStudySettings", "run_segmentation_case", "run_segmentation_study",
           "segmentation_study", "segmented_population", "summarise_segmentation"]  # fmt: skip

PAPER = {"rmsd_mm": 1.8, "dice": 0.95}
GOALS = {"atlas": {"rmsd_mm": 1.2, "dice": 0.96}, "real": {"dice": 0.93}}


@dataclass(frozen=True)
class SegmentationStudySettings:
    """Subjects (leave-one-out, the first ``n_subjects`` of the population), conditions, the
    real CTs, seed."""

    n_subjects: int = 20
    dislocated: bool = True
    real_ct: bool = True
    seed: int = 0
    ct_spacing: tuple[float, float, float] | None = None  # mm; None: the CT simulator's own

    @classmethod
    def quick(cls, seed: int = 0) -> SegmentationStudySettings:
        """One subject, intact, the quick CT spacing, no real CTs (for CI)."""
        from pelvicnav.studies.registration import QUICK_CT_SPACING

        return cls(n_subjects=1, dislocated=False, real_ct=False, seed=seed,
                   ct_spacing=QUICK_CT_SPACING)  # fmt: skip


def segmentation_study(
    population, out: str | os.PathLike, settings: SegmentationStudySettings | None = None,
    real_ct_dir: str | os.PathLike | None = None,
) -> Study:  # fmt: skip
    """The runner's study. Cases carry where their population comes from (the atlas folder, or
    how to regenerate a sampled one), not its meshes: the leave-one-out prior needs them all."""
    from pelvicnav.io.real_ct import REAL_CT_CASES, default_real_ct_dir

    cfg = settings or SegmentationStudySettings()
    if not 1 <= cfg.n_subjects <= population.n_subjects:
        raise ValueError(f"n_subjects must be in 1..{population.n_subjects}, got {cfg.n_subjects}")
    meshes = str(Path(out) / "meshes")
    source = {"source": population.source, "n_subjects": population.n_subjects}
    cases = []
    conditions = ("intact", "dislocated") if cfg.dislocated else ("intact",)
    for s in range(cfg.n_subjects):
        sid = int(population.subject_ids[s])
        for cond in conditions:
            cases.append({"case_id": f"atlas-{sid:03d}-{cond}", "kind": "atlas", "subject": sid,
                          "condition": cond, "population": source, "seed": cfg.seed,
                          "meshes": meshes, "ct_spacing": cfg.ct_spacing})  # fmt: skip
    real = Path(real_ct_dir) if real_ct_dir else default_real_ct_dir()
    if cfg.real_ct:
        if real is None or not real.is_dir():
            raise ValueError(
                "the real CTs are not found: set PELVICNAV_REAL_CT to the fracsegnet folder "
                "or run without them (--no-real-ct)"
            )
        for name in REAL_CT_CASES:
            for cond in ("masked", "body"):
                cases.append({"case_id": f"real-{name}-{cond}", "kind": "real",
                              "folder": str(real / name), "condition": cond, "seed": cfg.seed,
                              "meshes": meshes})  # fmt: skip
    meta = {"study": asdict(cfg), "population": population.source,
            "subjects": [int(x) for x in population.subject_ids[: cfg.n_subjects]]}  # fmt: skip
    return Study("segmentation", meta, tuple(cases), run_segmentation_case)


_CACHE: dict = {}


def _population(source: dict):
    from pelvicnav.phantom.population import load_population

    key = ("population", source["source"], source["n_subjects"])
    if key not in _CACHE:
        _CACHE[key] = load_population(source["source"], n_subjects=source["n_subjects"])
    return _CACHE[key]


def _leave_one_out(source: dict, subject: int):
    """The subject's meshes and the prior fitted from the others (kept per worker)."""
    from pelvicnav.shape.asm import ShapePrior

    pop = _population(source)
    s = pop.subject_index(subject)
    key = ("prior", source["source"], source["n_subjects"], subject)
    if key not in _CACHE:
        _CACHE.pop(next((k for k in _CACHE if k[0] == "prior"), None), None)
        train = np.delete(pop.vertices, s, axis=0)
        _CACHE[key] = ShapePrior.from_subjects(train, pop.faces)
    return pop.vertices[s], _CACHE[key]


def run_segmentation_case(case: dict) -> list[dict]:
    """Segment one CT; one row per bone. A CT the ASM refuses (it finds no placement) is a
    failed case, stored as such (Dice 0, no RMSD, the reason), not a crashed study."""
    try:
        return _atlas_case(case) if case["kind"] == "atlas" else _real_case(case)
    except ValueError as err:
        return [{"kind": case["kind"], "condition": case["condition"],
                 "subject": str(case.get("subject", Path(case.get("folder", "")).name)),
                 "bone": bone, "dice": 0.0, "rmsd_mm": float("nan"), "seconds": float("nan"),
                 "error": str(err)} for bone in BONES]  # fmt: skip


def _atlas_case(case: dict) -> list[dict]:
    from pelvicnav.phantom.ctsynth import CTOptions, synthesize_ct
    from pelvicnav.phantom.dislocate import PATTERNS, apply_dislocation, draw_dislocation
    from pelvicnav.shape.asm import segment_ct

    V, prior = _leave_one_out(case["population"], case["subject"])
    rng = np.random.default_rng([case["seed"], case["subject"]])
    spacing = case.get("ct_spacing")
    options = CTOptions() if spacing is None else CTOptions(spacing=tuple(spacing))
    ct = synthesize_ct(V, prior.faces, rng=rng, options=options)
    truth = V
    extra = {}
    if case["condition"] == "dislocated":
        bone = ("left_hip", "right_hip")[int(rng.integers(2))]
        pattern = PATTERNS[int(rng.integers(len(PATTERNS)))]
        disl = draw_dislocation(V, prior.faces, bone=bone, pattern=pattern, rng=rng)
        ct, truth = apply_dislocation(ct, V, prior.faces, disl, rng=rng)
        extra = {"moved_bone": bone, "pattern": pattern,
                 "moved_mm": disl.translation_mm, "moved_deg": disl.rotation_deg}  # fmt: skip
    res = segment_ct(ct.hu.data, ct.hu.world_from_ijk, prior)
    _save_meshes(case, res.vertices)
    return _rows(case, res, ct.labels, truth, prior.faces, None, extra)


def _real_case(case: dict) -> list[dict]:
    from pelvicnav.io.real_ct import read_real_ct
    from pelvicnav.model import load_model
    from pelvicnav.phantom.body import embed_in_body
    from pelvicnav.shape.asm import ShapePrior, segment_ct

    real = read_real_ct(case["folder"])
    if "shipped" not in _CACHE:
        _CACHE["shipped"] = ShapePrior.from_model(load_model())
    prior = _CACHE["shipped"]
    hu = real.hu
    if case["condition"] == "body":
        rng = np.random.default_rng([case["seed"], int(real.name)])
        hu = embed_in_body(real.hu, real.labels, real.world_from_ijk, rng=rng)
    res = segment_ct(hu, real.world_from_ijk, prior)
    _save_meshes(case, res.vertices)
    return _rows(case, res, real.labels, None, prior.faces, real.world_from_ijk, {})


def _rows(case, res, truth_labels, truth_vertices, faces, world_from_ijk, extra) -> list[dict]:
    from pelvicnav.metrics.overlap import dice, surface_rmsd

    rows = []
    for b, bone in enumerate(BONES):
        truth = truth_labels == b + 1
        if truth_vertices is not None:
            rmsd = surface_rmsd(res.vertices[b], faces[b], truth_vertices[b], faces[b])
        else:
            rmsd = _rmsd_to_label(res.vertices[b], faces[b], truth, world_from_ijk)
        rows.append({
            "kind": case["kind"], "condition": case["condition"],
            "subject": str(case.get("subject", Path(case.get("folder", "")).name)), "bone": bone,
            "dice": dice(res.labels == b + 1, truth), "rmsd_mm": rmsd,
            **{f"quality_{k}": v for k, v in res.quality[bone].items()},
            "seconds": res.seconds["total"], **extra,
        })  # fmt: skip
    return rows


def _rmsd_to_label(vertices, faces, mask, world_from_ijk) -> float:
    """Symmetric RMS distance between a mesh and a label's marching-cubes surface."""
    from skimage.measure import marching_cubes

    from pelvicnav.metrics.overlap import surface_rmsd

    m = np.pad(mask.astype(np.float32), 1)
    verts, tri, _, _ = marching_cubes(m, level=0.5)
    A = np.asarray(world_from_ijk, dtype=np.float64)
    world = (verts - 1.0) @ A[:3, :3].T + A[:3, 3]
    return surface_rmsd(vertices, faces, world, tri)


def _save_meshes(case: dict, vertices) -> None:
    import io

    from pelvicnav.io.atomic import write_bytes

    folder = Path(case["meshes"])
    folder.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    np.savez_compressed(buf, vertices=np.asarray(vertices, dtype=np.float64))
    write_bytes(folder / f"{case['case_id']}.npz", buf.getvalue())


def summarise_segmentation(rows: list[dict]) -> list[dict]:
    """Per group (atlas intact/dislocated, real masked/body) and bone: medians and extremes."""
    out = []
    groups = dict.fromkeys((r["kind"], r["condition"]) for r in rows)
    for kind, cond in groups:
        for bone in BONES:
            sel = [r for r in rows if (r["kind"], r["condition"], r["bone"]) == (kind, cond, bone)]
            if not sel:
                continue
            d = np.array([r["dice"] for r in sel])
            e = np.array([r["rmsd_mm"] for r in sel], dtype=np.float64)
            e = np.where(np.isfinite(e), e, np.inf)  # a failed case: no surface at all
            seconds = float(np.nanmedian([r["seconds"] for r in sel]))
            out.append({"kind": kind, "condition": cond, "bone": bone, "n": len(sel),
                        "dice_median": float(np.median(d)), "dice_min": float(d.min()),
                        "rmsd_median_mm": float(np.median(e)), "rmsd_max_mm": float(e.max()),
                        "seconds_median": seconds})  # fmt: skip
    return out


def run_segmentation_study(
    population, out: str | os.PathLike, settings: SegmentationStudySettings | None = None,
    *, real_ct_dir: str | os.PathLike | None = None, **runner,
) -> list[dict]:  # fmt: skip
    """Run the study (runner options: ``workers``, ``scheduler``, ``force``, ``progress``) and
    write ``results.csv``, ``summary.md`` (goals and the paper side by side) and
    ``segmentation.png`` (box plots); returns the summary rows."""
    from pelvicnav.io.atomic import write_text

    cfg = settings or SegmentationStudySettings()
    study = segmentation_study(population, out, cfg, real_ct_dir)
    rows = flatten(run_study(study, out, **runner))
    summary = summarise_segmentation(rows)
    out = Path(out)
    lines = ["# Segmentation (active shape model)", "",
             "| cases | bone | n | Dice median (min) | RMSD median (max), mm | s per CT |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for s in summary:
        lines.append(
            f"| {s['kind']} {s['condition']} | {s['bone']} | {s['n']} | "
            f"{s['dice_median']:.3f} ({s['dice_min']:.3f}) | "
            f"{s['rmsd_median_mm']:.2f} ({s['rmsd_max_mm']:.2f}) | {s['seconds_median']:.1f} |"
        )
    lines += [
        "",
        f"Goals: atlas median RMSD <= {GOALS['atlas']['rmsd_mm']} mm and Dice >= "
        f"{GOALS['atlas']['dice']} per bone; real CTs Dice >= {GOALS['real']['dice']} per bone.",
        f"Paper (Han et al. 2020): RMSD {PAPER['rmsd_mm']} mm, Dice {PAPER['dice']}.",
        "Real CTs, masked: the CT holds bone only, so the label map takes its bone voxels; "
        "body: bones in a synthetic body, bone told from tissue by CT number alone.",
        "",
    ]
    write_text(out / "summary.md", "\n".join(lines))
    _figure(rows, out / "segmentation.png")
    return summary


def _figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pelvicnav.io.atomic import save_figure

    groups = list(dict.fromkeys(f"{r['kind']} {r['condition']}" for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, key, label in ((axes[0], "dice", "Dice"), (axes[1], "rmsd_mm", "surface RMSD (mm)")):
        data, names = [], []
        for g in groups:
            for bone in BONES:
                vals = [r[key] for r in rows if f"{r['kind']} {r['condition']}" == g
                        and r["bone"] == bone and np.isfinite(r[key])]  # fmt: skip
                if vals:
                    data.append(vals)
                    names.append(f"{g}\n{bone}")
        ax.boxplot(data)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=60, fontsize=7)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle("ASM segmentation: atlas leave-one-out and the real CTs")
    fig.tight_layout()
    save_figure(fig, path)


def segmented_population(
    population, out: str | os.PathLike, n_subjects: int, *, seed: int = 0, **runner
) -> np.ndarray:
    """The first ``n_subjects`` subjects as the ASM segments them (leave-one-out prior, intact
    CTs; the segmentation study run in ``out``, resumable); the others as they are.

    Returns
    -------
    (population.n_subjects, 3, n_vertices, 3) float64
    """
    cfg = SegmentationStudySettings(n_subjects=n_subjects, dislocated=False, real_ct=False,
                                    seed=seed)  # fmt: skip
    run_segmentation_study(population, out, cfg, **runner)
    V = np.array(population.vertices, dtype=np.float64)
    for s in range(n_subjects):
        sid = int(population.subject_ids[s])
        with np.load(Path(out) / "meshes" / f"atlas-{sid:03d}-intact.npz") as f:
            V[s] = f["vertices"]
    return V
