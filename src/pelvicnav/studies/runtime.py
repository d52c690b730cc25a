"""Runtime (Han et al. 2020, table 2): each step of planning and guidance, timed over cases.

Each case is a simulated patient (the registration study's simulation, two views):

* **segmentation** - the active shape model on the preoperative CT (shipped model);
* **planning** - which hip is dislocated and its SPM_CC target from the segmented meshes;
* **bone models** - the registration's per-level bone models from the CT and labels;
* **stage 1**, **stage 2** - the first registration's two stages (shipped defaults);
* **augmentation** - the registered bones' and the target's edges drawn on each view;
* **subsequent frame** - a tracking registration (stage 2 only, as ``pelvicnav guide`` does it)
  started 3 mm / 2 deg from the first frame's answer.

Medians and IQR per step; the paper's means (single GPU) side by side.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.studies.runner import Study, flatten, run_study

__all__ = [
    "STEPS",
    "RuntimeSettings",
    "nudged_poses",
    "run_runtime_case",
    "run_runtime_study",
    "runtime_study",
]

STEPS = ("segmentation_s", "planning_s", "bone_models_s", "stage1_s", "stage2_s",
         "augmentation_s", "subsequent_frame_s")  # fmt: skip
PAPER = {"segmentation_s": "122.0 ± 5.7", "planning_s": "116.2 ± 10.5",
         "stage1_s": "78.6 ± 29.2", "stage2_s": "40.0 ± 11.5", "augmentation_s": "0.2 ± 0.1",
         "subsequent_frame_s": "~40 (stage 2 only)"}  # fmt: skip


@dataclass(frozen=True)
class RuntimeSettings:
    n_cases: int = 10
    seed: int = 0
    ct_spacing: tuple[float, float, float] | None = None  # mm; None: the CT simulator's own

    @classmethod
    def quick(cls, seed: int = 0) -> RuntimeSettings:
        from pelvicnav.studies.registration import QUICK_CT_SPACING

        return cls(n_cases=1, seed=seed, ct_spacing=QUICK_CT_SPACING)


def runtime_study(population, settings: RuntimeSettings | None = None) -> Study:
    cfg = settings or RuntimeSettings()
    cases = []
    for i in range(cfg.n_cases):
        s = i % population.n_subjects
        cases.append({"case_id": f"{i:04d}", "index": i, "subject": int(population.subject_ids[s]),
                      "vertices": population.vertices[s], "faces": population.faces,
                      "seed": cfg.seed * 1000 + i,
                      "ct_spacing": cfg.ct_spacing})  # fmt: skip
    meta = {"study": asdict(cfg), "population": population.source,
            "subjects": [int(x) for x in population.subject_ids]}  # fmt: skip
    return Study("runtime", meta, tuple(cases), run_runtime_case)


def run_runtime_case(case: dict) -> dict:
    """Time every step on one simulated patient."""
    from pelvicnav.model import load_model
    from pelvicnav.shape.asm import ShapePrior, segment_ct
    from pelvicnav.studies.registration import (
        RegistrationStudySettings,
        simulate_registration_case,
    )
    from pelvicnav.workflow.plan import decide_dislocated

    sim = simulate_registration_case(case["vertices"], case["faces"], seed=case["seed"],
                                     settings=RegistrationStudySettings(
                                         ct_spacing=case["ct_spacing"]))  # fmt: skip
    model = load_model()
    row: dict = {"subject": case["subject"]}
    t = time.perf_counter()
    seg = segment_ct(sim["ct"].data, sim["ct"].world_from_ijk, ShapePrior.from_model(model))
    row["segmentation_s"] = time.perf_counter() - t
    t = time.perf_counter()
    decision, _ = decide_dislocated({b: seg.vertices[k] for k, b in enumerate(BONES)}, model)
    row["planning_s"] = time.perf_counter() - t
    row["planned_dislocated"] = ",".join(decision.dislocated) or "none"
    row.update(_registration_times(case, sim))
    return row


def nudged_poses(poses: dict, centroids: dict, rng: np.random.Generator,
                 mm: float = 3.0, deg: float = 2.0) -> dict:  # fmt: skip
    """Every bone's pose moved by ``mm`` and turned by ``deg`` about its centroid (CT frame, mm),
    a random direction each: the motion between two tracked frames."""
    out = {}
    for b, c0 in centroids.items():
        c = tf.apply(poses[b], np.asarray(c0)[None])[0]
        d, a = rng.normal(size=3), rng.normal(size=3)
        step = tf.from_params(
            c + mm * d / np.linalg.norm(d), np.deg2rad(deg) * a / np.linalg.norm(a)
        )
        out[b] = step @ tf.from_params(-c, [0, 0, 0]) @ poses[b]
    return out


def _registration_times(case: dict, sim: dict) -> dict:
    from pelvicnav.guide.overlay import bone_edges, overlay_rgb
    from pelvicnav.register.multibody import register_multibody
    from pelvicnav.register.pyramid import splat_renderer
    from pelvicnav.register.settings import RegistrationSettings

    out = {}
    full = RegistrationSettings()
    t = time.perf_counter()
    models = splat_renderer(sim["ct"], sim["labels"], full.factors)
    out["bone_models_s"] = time.perf_counter() - t
    res = register_multibody(sim["ct"], sim["labels"], sim["views"], seed=case["seed"],
                             settings=full, renderer=models, dislocated=sim["bone"])  # fmt: skip
    out["stage1_s"] = res.stages[0].seconds
    out["stage2_s"] = res.stages[1].seconds if len(res.stages) > 1 else 0.0
    t = time.perf_counter()
    for k, image in enumerate(sim["views"].images):
        P = res.projections[k]
        edges = {b: bone_edges(models.models[-1][b], res.poses[b], P, image.shape) for b in BONES}
        overlay_rgb(image, edges, target=edges[sim["bone"]])
    out["augmentation_s"] = time.perf_counter() - t
    nudge = nudged_poses(res.poses, sim["centroids"], np.random.default_rng(case["seed"]))
    warm = RegistrationSettings.tracking()
    t = time.perf_counter()
    again = register_multibody(sim["ct"], sim["labels"], sim["views"], init_poses=nudge,
                               seed=case["seed"] + 1, settings=warm, renderer=models,
                               dislocated=sim["bone"])  # fmt: skip
    out["subsequent_frame_s"] = time.perf_counter() - t
    for name, r in (("first", res), ("subsequent", again)):
        errors = [np.linalg.norm(tf.apply(r.poses[b], sim["centroids"][b][None])
                                 - tf.apply(sim["truth"][b], sim["centroids"][b][None]))
                  for b in BONES]  # fmt: skip
        out[f"{name}_worst_error_mm"] = float(max(errors))
    return out


def summarise_runtime(rows: list[dict]) -> list[dict]:
    out = []
    for step in STEPS:
        v = np.array([r[step] for r in rows if step in r], dtype=np.float64)
        q1, med, q3 = np.percentile(v, [25, 50, 75])
        out.append({"step": step.removesuffix("_s"), "n": len(v), "median_s": float(med),
                    "iqr_s": float(q3 - q1), "paper_s": PAPER.get(step, "")})  # fmt: skip
    return out


def run_runtime_study(
    population, out: str | os.PathLike, settings: RuntimeSettings | None = None, **runner
) -> list[dict]:
    """Run the study (one worker by default: timings are per core) and write ``results.csv`` and
    ``summary.md``."""
    from pelvicnav.io.atomic import write_text

    runner.setdefault("workers", 0)
    cfg = settings or RuntimeSettings()
    rows = flatten(run_study(runtime_study(population, cfg), out, **runner))
    summary = summarise_runtime(rows)
    lines = [
        "# Runtime (table 2)",
        "",
        "| step | n | median (IQR), s | paper (GPU), mean ± sd, s |",
        "|---|---|---|---|",
    ]
    for s in summary:
        lines.append(f"| {s['step']} | {s['n']} | {s['median_s']:.2f} ({s['iqr_s']:.2f}) | "
                     f"{s['paper_s']} |")  # fmt: skip
    lines += ["", f"Measured on {os.cpu_count()} CPU cores, one case at a time, no GPU.", ""]
    write_text(Path(out) / "summary.md", "\n".join(lines))
    return summary
