"""``pelvicnav demo`` (``make demo``): the whole workflow on a simulated patient, offline.

1. A patient: an atlas subject when ``$PELVICNAV_ATLAS`` (or ``--atlas``) is set, else one sampled
   from the packaged pelvis model; an open-book dislocation of the left innominate of at least
   8 mm; its CT and label map (``pelvicnav simulate``).
2. ``pelvicnav plan`` on that CT with ``--dislocated auto``.
3. Two intraoperative frames, the bone reduced 40 % and then 80 % of the way back to its true
   place, the patient placed on the table with a set-up error that drifts 2 mm / 1 deg between the
   frames; AP and inlet radiographs at 20 uGy/frame.
4. ``pelvicnav guide`` twice into one session; each frame's registration error and residual are
   compared with the truth (``frame-NNN/evaluation.json``) and the report is rewritten.

Everything lands in ``out``; the report is ``out/session/report.html``, copied to
``out/report.html``.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np

from pelvicnav import BONES, LABELS
from pelvicnav.geometry import transforms as tf

__all__ = ["run_demo"]

FRACTIONS = (0.4, 0.8)
DOSE_UGY = 20.0
VIEWS = ("ap", "inlet")


def _setups() -> list[np.ndarray]:
    """Patient placement per frame (``world_from_table``): a set-up error, then a drift."""
    first = tf.from_params([8.0, -6.0, 5.0], np.deg2rad([2.0, -1.5, 1.0]))
    drift = tf.from_params([1.5, 1.0, -1.0], np.deg2rad([0.5, 0.8, -0.4]))
    return [first, drift @ first]


def _pick_seed(vertices, faces, subject_id: int, min_mm: float = 8.0) -> int:
    """The first seed whose drawn open-book dislocation is at least ``min_mm`` (the simulator
    draws it first from ``default_rng([seed, subject_id])``)."""
    from pelvicnav.phantom.dislocate import draw_dislocation

    for seed in range(100):
        rng = np.random.default_rng([seed, subject_id])
        d = draw_dislocation(vertices, faces, bone="left_hip", pattern="open-book", rng=rng)
        if d.translation_mm >= min_mm and d.rotation_deg >= 3.0:
            return seed
    raise ValueError("no dislocation of 8 mm in 100 seeds")  # cannot happen: uniform to 20 mm


def run_demo(out: str | os.PathLike, *, atlas: str | os.PathLike | None = None, say=print) -> dict:
    """Run the demo into ``out``; returns a summary (errors against the truth, paths, seconds)."""
    from pelvicnav.phantom.case import simulate_case
    from pelvicnav.phantom.population import load_population
    from pelvicnav.workflow.guide import guide_frame
    from pelvicnav.workflow.plan import make_plan

    started = time.perf_counter()
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    location = atlas if atlas is not None else os.environ.get("PELVICNAV_ATLAS") or "model"
    subject = 10 if location != "model" else 1
    pop = load_population(location, subject_ids=(subject,))
    vertices = pop.vertices[pop.subject_index(subject)]
    seed = _pick_seed(vertices, pop.faces, subject)
    say(f"patient: subject {subject} ({pop.source}), open-book dislocation of the left hip")
    truth = simulate_case(vertices, pop.faces, out / "case", subject_id=subject,
                          pattern="open-book", bone="left_hip", views=("ap",),
                          seed=seed)  # fmt: skip
    d = truth["dislocation"]
    say(f"  dislocated by {d['translation_mm']:.1f} mm / {d['rotation_deg']:.1f} deg")
    say("plan (pelvicnav plan --dislocated auto) ...")
    plan = make_plan(out / "case" / "ct.nii.gz", out / "plan",
                     labels=out / "case" / "labels.nii.gz", dislocated="auto")  # fmt: skip
    say(f"  {plan.decision['description']}")
    if plan.dislocated != ("left_hip",):
        say("  the automatic decision missed the left hip: planning it as given instead")
        plan = make_plan(out / "case" / "ct.nii.gz", out / "plan",
                         labels=out / "case" / "labels.nii.gz", dislocated="left_hip")  # fmt: skip
    frames = _frames(out, truth, pop.faces)
    summary = {"subject": subject, "population": pop.source, "dislocation": d, "frames": []}
    for k, frame in enumerate(frames, start=1):
        say(f"guide frame {k} (bone reduced {FRACTIONS[k - 1]:.0%}) ...")
        result = guide_frame(out / "plan", frame["views"], out / "session", seed=0)
        evaluation = _evaluate(result.record, frame, plan, out)
        (result.folder / "evaluation.json").write_text(json.dumps(evaluation, indent=2) + "\n")
        say(f"  {result.mode}, {'reliable' if result.converged else 'UNRELIABLE'}, "
            f"{result.seconds:.1f} s; worst bone error {evaluation['worst bone error (mm)']:.2f} "
            f"mm; residual {result.residual['left_hip']['description']}")  # fmt: skip
        summary["frames"].append(evaluation | {"mode": result.mode, "seconds": result.seconds})
    from pelvicnav.guide.report import write_report

    report = write_report(out / "session")
    shutil.copyfile(report, out / "report.html")
    summary["report"] = str((out / "report.html").resolve())
    summary["seconds"] = time.perf_counter() - started
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    return summary


def _frames(out: Path, truth: dict, pop_faces) -> list[dict]:
    """Intraoperative radiographs of the patient at two stages of reduction."""
    from pelvicnav.drr.volume import Volume
    from pelvicnav.io.nifti import read_nifti
    from pelvicnav.io.views import View, write_views
    from pelvicnav.phantom.ctsynth import SynthCT
    from pelvicnav.phantom.dislocate import Dislocation, apply_dislocation
    from pelvicnav.phantom.xray import simulate_radiograph, standard_view

    hu, A = read_nifti(out / "case" / "ct.nii.gz")
    labels, _ = read_nifti(out / "case" / "labels.nii.gz")
    ct = SynthCT(Volume(hu.astype(np.float32), A), labels.astype(np.uint8), np.zeros((2, 4)))
    V = np.asarray(truth["moved_vertices"])
    faces = tuple(np.asarray(f) for f in pop_faces)
    true_reduction = tf.invert(np.asarray(truth["poses_world_from_ct"]["left_hip"]))
    iso = tuple(truth["views"]["ap"]["isocenter"])
    rng = np.random.default_rng(1)
    frames = []
    for k, (fraction, setup) in enumerate(zip(FRACTIONS, _setups(), strict=True), start=1):
        moved = tf.se3_exp(fraction * tf.se3_log(true_reduction))
        reduced, _ = apply_dislocation(ct, V, faces, Dislocation("left_hip", "reduction", moved,
                                       0.0, 0.0, np.zeros(3), 0), rng=rng)  # fmt: skip
        placed = Volume(reduced.hu.data, tf.invert(setup) @ A)
        views = []
        for name in VIEWS:
            carm = standard_view(name, isocenter=iso)
            rad = simulate_radiograph(placed, carm, dose_ugy=DOSE_UGY, rng=rng)
            views.append(View(name, rad.line_integrals, carm.projection_matrix, carm.pixel_spacing,
                              {"dose_ugy": DOSE_UGY}))  # fmt: skip
        folder = out / "intraop" / f"frame-{k}"
        path = write_views(folder, views)
        poses = {b: tf.invert(setup) for b in BONES}
        poses["left_hip"] = tf.invert(setup) @ moved
        frames.append({"views": path, "poses": poses, "fraction": fraction})
    return frames


def _evaluate(record: dict, frame: dict, plan, out: Path) -> dict:
    """Registration error per bone (at its centroid, mm and deg) and the residual against the
    residual computed from the true poses."""
    from pelvicnav.guide.residual import residual_reduction
    from pelvicnav.io.nifti import read_nifti

    labels, A = read_nifti(out / "plan" / "labels.nii.gz")
    ev = {}
    worst = 0.0
    for b in BONES:
        c = A[:3, :3] @ np.argwhere(labels == LABELS[b]).mean(axis=0) + A[:3, 3]
        T, T_true = np.asarray(record["poses"][b]), frame["poses"][b]
        err = float(np.linalg.norm(tf.apply(T, c[None]) - tf.apply(T_true, c[None])))
        deg = float(np.degrees(np.linalg.norm(tf.rotvec_from_matrix(T[:3, :3] @ T_true[:3, :3].T))))
        ev[f"{b} error (mm)"], ev[f"{b} error (deg)"] = err, deg
        worst = max(worst, err)
        if b == "left_hip":
            centroid = c
    true = residual_reduction(frame["poses"][plan.reference_bone], frame["poses"]["left_hip"],
                              plan.targets["left_hip"], centroid)  # fmt: skip
    reported = record["residual"]["left_hip"]
    ev["worst bone error (mm)"] = worst
    ev["true residual"] = true.describe()
    ev["residual error (mm)"] = float(
        np.linalg.norm(np.asarray(reported["translation_mm"]) - true.translation_mm)
    )
    ev["residual error (deg)"] = float(
        np.linalg.norm(np.asarray(reported["rotation_deg"]) - true.rotation_deg)
    )
    return ev
