"""Registration accuracy on simulated cases (Han et al. 2020, section 3.1 and 3.4).

Each case: a subject's CT is synthesised (the preoperative CT), one innominate is dislocated
(open book, 0-20 mm / 0-10 deg), the patient is placed on the table with a set-up error (up to
20 mm and 5 deg about the isocentre), and radiographs are simulated from the dislocated patient
at the nominal dose. Registration starts from the CT at the nominal isocentre; errors are read at
each bone's centroid, split into in-plane and out-of-plane parts with respect to the first
view's principal ray.

With ``dof=9`` the case has one view whose true source position differs from the nominal one
(SDD and principal point off by up to 15 mm); the nominal geometry is given to the registration
and the error is the projection distance of landmarks at the detector (PDE, mm).
"""

from __future__ import annotations

import csv
import io
import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pelvicnav import BONES
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.atlas import Atlas
from pelvicnav.io.atomic import write_text
from pelvicnav.studies.runner import Study, flatten, run_study

__all__ = [
    "QUICK_CT_SPACING",
    "RegistrationStudySettings",
    "registration_study",
    "run_registration_case",
    "run_registration_study",
    "simulate_registration_case",
]


# The synthesised CT's voxel size (mm) in every study's --quick preset: 1.5 x 1.5 x 2 instead of
# 1 x 1 x 2 makes the simulation and the bone models cheaper, which CI's two-minute budget for all
# quick studies needs. Not 2 mm in plane: DRRs of such a CT match the radiographs less well, and
# GO at the true poses fell from 0.93-1.10 to 0.75-1.04 (two views, 5-50 uGy/frame, 2 patients),
# close to the 0.8 floor of the flag, which flagged good registrations and sent them through the
# rescue (3-4x the time); at 1.5 mm 0.91-1.10. The full studies keep the default.
QUICK_CT_SPACING = (1.5, 1.5, 2.0)


@dataclass(frozen=True)
class RegistrationStudySettings:
    n_cases: int = 20
    seed: int = 0
    dof: int = 6
    views: tuple[str, ...] = ("ap", "oblique30")
    dose_ugy: float = 50.0
    setup_mm: float = 20.0
    setup_deg: float = 5.0
    source_error_mm: float = 15.0
    segmentation: str = "truth"
    beads: int = 0
    carm: tuple[tuple[str, float], ...] = ()
    real_ct: int = 0  # > 0: that many cases from each real CT instead of atlas cases
    real_ct_dir: str = ""
    ct_spacing: tuple[float, float, float] | None = None  # mm; None: the CT simulator's own
    # (low, high) along x, y, z, mm; None: the CT simulator's own. The simulated patient must
    # fill the detector's field: where the field reaches past the CT, the radiograph shows the
    # CT's end as a hard edge that no patient has, and registration aligns bones to it.
    ct_margin_mm: tuple[tuple[float, float], ...] | None = None

    @classmethod
    def for_dof(cls, dof: int, **kwargs) -> RegistrationStudySettings:
        """Two views (AP, oblique 30) for 6 DoF; the AP view alone for 9 DoF."""
        return cls(dof=dof, views=("ap", "oblique30") if dof == 6 else ("ap",), **kwargs)


def _random_rigid(rng, max_mm, max_deg, centre) -> NDArray[np.float64]:
    """A rigid motion about ``centre`` with |t| <= max_mm and angle <= max_deg (uniform)."""
    d = rng.normal(size=3)
    t = d / np.linalg.norm(d) * rng.uniform(0, max_mm)
    a = rng.normal(size=3)
    r = a / np.linalg.norm(a) * np.deg2rad(rng.uniform(0, max_deg))
    c = np.asarray(centre, dtype=np.float64)
    return (
        tf.from_params(c + t, [0, 0, 0])
        @ tf.from_params([0, 0, 0], r)
        @ tf.from_params(-c, [0, 0, 0])
    )


def simulate_registration_case(vertices, faces, *, seed: int, settings: RegistrationStudySettings):
    """Preoperative CT + labels, registration views (nominal geometry) and the true poses."""
    from pelvicnav.drr.volume import Volume
    from pelvicnav.io.views import ViewSet
    from pelvicnav.phantom.ctsynth import CTOptions, synthesize_ct
    from pelvicnav.phantom.dislocate import apply_dislocation, draw_dislocation

    rng = np.random.default_rng(seed)
    V = np.asarray(vertices, dtype=np.float64)
    bone = ("left_hip", "right_hip")[int(rng.integers(2))]
    disl = draw_dislocation(V, faces, bone=bone, pattern="open-book", rng=rng)
    grid = {} if settings.ct_spacing is None else {"spacing": tuple(settings.ct_spacing)}
    if settings.ct_margin_mm is not None:
        grid["margin_mm"] = tuple(tuple(m) for m in settings.ct_margin_mm)
    options = CTOptions(beads=settings.beads, **grid)
    ct = synthesize_ct(V, faces, rng=rng, options=options)
    moved, _ = apply_dislocation(ct, V, faces, disl, rng=rng)
    iso = V.reshape(-1, 3).mean(axis=0)
    setup = _random_rigid(rng, settings.setup_mm, settings.setup_deg, iso)
    patient = Volume(moved.hu.data, setup @ moved.hu.world_from_ijk)
    images, nominal, spacing, true_P = _radiographs(patient, iso, settings, rng)
    truth = {b: setup.copy() for b in BONES}
    truth[bone] = setup @ disl.transform
    return {
        "ct": ct.hu,
        "labels": ct.labels,
        "views": ViewSet.from_arrays(images, nominal, spacing),
        "true_projections": true_P,
        "truth": truth,
        "bone": bone,
        "dislocation": (disl.translation_mm, disl.rotation_deg),
        "setup": (float(np.linalg.norm(setup[:3, 3] - (iso - setup[:3, :3] @ iso))),),
        "centroids": {b: V[i].mean(axis=0) for i, b in enumerate(BONES)},
        "landmarks": {b: V[i][:: max(1, len(V[i]) // 50)] for i, b in enumerate(BONES)},
        "beads": ct.beads,
        "bead_bones": ct.bead_bones,
    }


def _radiographs(patient, iso, settings: RegistrationStudySettings, rng):
    """Each view's radiograph of ``patient`` (HU volume) and its nominal and true geometry (9 DoF:
    the true source is off by up to ``source_error_mm``)."""
    from pelvicnav.phantom.xray import simulate_radiograph, standard_view

    images, nominal, spacing, true_P = [], [], [], []
    for name in settings.views:
        carm = standard_view(name, isocenter=tuple(iso), **dict(settings.carm))
        true = carm
        if settings.dof == 9:
            e = rng.uniform(-1, 1, 3) * settings.source_error_mm / np.sqrt(3)
            centre = ((carm.cols - 1) / 2.0, (carm.rows - 1) / 2.0)
            pp = (
                np.asarray(carm.principal_point or centre)
                + e[:2] / np.asarray(carm.pixel_spacing)[::-1]
            )
            true = replace(
                carm, source_to_detector=carm.source_to_detector + e[2], principal_point=tuple(pp)
            )
        images.append(
            simulate_radiograph(patient, true, dose_ugy=settings.dose_ugy, rng=rng).line_integrals
        )
        nominal.append(carm.projection_matrix)
        true_P.append(true.projection_matrix)
        spacing.append(tuple(carm.pixel_spacing))
    return images, nominal, spacing, true_P


def simulate_real_ct_case(folder, *, seed: int, settings: RegistrationStudySettings) -> dict:
    """A registration case from a real CT (``shared/data/real-ct``): the bones in a synthetic
    body (:func:`~pelvicnav.phantom.body.embed_in_body`) are the preoperative CT; for the X-ray a
    random hip moves 10-20 mm / 5-10 deg about its centroid (redrawn while it would overlap
    another bone by more than 0.5% of its voxels), the patient gets the set-up error, and the
    views are simulated with quantum noise. Same keys as :func:`simulate_registration_case`."""
    from pelvicnav.drr.volume import Volume
    from pelvicnav.io.real_ct import read_real_ct
    from pelvicnav.io.views import ViewSet
    from pelvicnav.phantom.body import embed_in_body
    from pelvicnav.phantom.dislocate import move_bone_voxels

    rng = np.random.default_rng(seed)
    real = read_real_ct(folder)
    A = real.world_from_ijk
    hu = embed_in_body(real.hu, real.labels, A, rng=rng)
    pts = {b: Volume(hu, A).world_points(np.argwhere(real.labels == k + 1))
           for k, b in enumerate(BONES)}  # fmt: skip
    bone = ("left_hip", "right_hip")[int(rng.integers(2))]
    c = pts[bone].mean(axis=0)
    for _ in range(20):
        move = _random_rigid_between(rng, (10.0, 20.0), (5.0, 10.0), c)
        moved, _, overlap = move_bone_voxels(hu, real.labels, A, BONES.index(bone) + 1, move,
                                             rng=rng)  # fmt: skip
        if overlap <= 0.005:
            break
    iso = np.concatenate(list(pts.values())).mean(axis=0)
    setup = _random_rigid(rng, settings.setup_mm, settings.setup_deg, iso)
    images, nominal, spacing, true_P = _radiographs(Volume(moved, setup @ A), iso, settings, rng)
    truth = {b: setup.copy() for b in BONES}
    truth[bone] = setup @ move
    D = move[:3, :3]
    return {
        "ct": Volume(hu, A), "labels": real.labels, "bone": bone, "truth": truth,
        "views": ViewSet.from_arrays(images, nominal, spacing), "true_projections": true_P,
        "dislocation": (float(np.linalg.norm(tf.apply(move, c[None])[0] - c)),
                        float(np.rad2deg(np.linalg.norm(tf.rotvec_from_matrix(D))))),
        "setup": (float(np.linalg.norm(setup[:3, 3] - (iso - setup[:3, :3] @ iso))),),
        "centroids": {b: p.mean(axis=0) for b, p in pts.items()},
        "landmarks": {b: p[:: max(1, len(p) // 50)] for b, p in pts.items()},
        "beads": np.zeros((0, 3)), "bead_bones": np.zeros(0, dtype=int), "real_ct": real.name,
    }  # fmt: skip


def _random_rigid_between(rng, mm: tuple, deg: tuple, centre) -> NDArray[np.float64]:
    """A rigid motion about ``centre``: |t| uniform in ``mm``, angle uniform in ``deg``."""
    d, a = rng.normal(size=3), rng.normal(size=3)
    t = d / np.linalg.norm(d) * rng.uniform(*mm)
    r = a / np.linalg.norm(a) * rng.uniform(*deg)
    return pj.six_dof_pose(np.r_[t, r], center=centre)


def _errors(case, result) -> list[dict]:
    P0 = pj.normalize_projection(case["views"].projections[0])
    ray = pj.decompose_projection(P0).carm_from_world[2]  # principal axis (world)
    rows = []
    for b in BONES:
        c = case["centroids"][b]
        e = tf.apply(result.poses[b], c[None])[0] - tf.apply(case["truth"][b], c[None])[0]
        out = float(abs(e @ ray))
        E = result.poses[b] @ tf.invert(case["truth"][b])
        row = {
            "bone": b,
            "dislocated": b == case["bone"],
            "error_mm": float(np.linalg.norm(e)),
            "in_plane_mm": float(np.linalg.norm(e - (e @ ray) * ray)),
            "out_of_plane_mm": out,
            "rotation_deg": float(np.rad2deg(np.linalg.norm(tf.rotvec_from_matrix(E[:3, :3])))),
        }
        if len(result.projections) == 1 and "true_projections" in case:
            L = case["landmarks"][b]
            true_px = pj.project(case["true_projections"][0], tf.apply(case["truth"][b], L))
            est_px = pj.project(result.projections[0], tf.apply(result.poses[b], L))
            dr, dc = case["views"].pixel_spacing[0]
            d = (true_px - est_px) * np.array([dc, dr])
            row["pde_mm"] = float(np.median(np.linalg.norm(d, axis=1)))
        rows.append(row)
    return rows


def registration_study(atlas: Atlas, settings: RegistrationStudySettings | None = None,
                       registration=None) -> Study:  # fmt: skip
    """The study as the runner takes it: one self-contained case per simulated patient (the
    subject's meshes travel with the case, so workers need no atlas)."""
    from pelvicnav.register.settings import RegistrationSettings

    cfg = settings or RegistrationStudySettings()
    if cfg.segmentation not in ("truth", "asm"):
        raise ValueError(f"segmentation must be 'truth' or 'asm', got {cfg.segmentation!r}")
    if cfg.dof == 9 and len(cfg.views) != 1:
        cfg = replace(cfg, views=cfg.views[:1])
    reg = registration or RegistrationSettings.for_dof(cfg.dof)
    if cfg.real_ct:
        return _real_ct_study(cfg, reg)
    cases = []
    for i in range(cfg.n_cases):
        s = i % atlas.n_subjects
        cases.append({
            "case_id": f"{i:04d}", "index": i, "subject": int(atlas.subject_ids[s]),
            "vertices": atlas.vertices[s], "faces": atlas.faces, "seed": cfg.seed * 1000 + i,
            "registration_seed": cfg.seed + i, "settings": cfg, "registration": reg,
            "population": {"source": atlas.source, "n_subjects": atlas.n_subjects},
        })  # fmt: skip
    meta = {"study": asdict(cfg), "registration": asdict(reg), "population": atlas.source,
            "subjects": [int(x) for x in atlas.subject_ids]}  # fmt: skip
    return Study("registration", meta, tuple(cases), run_registration_case)


def _real_ct_study(cfg: RegistrationStudySettings, reg) -> Study:
    """``cfg.real_ct`` cases from each real CT (``shared/data/real-ct``)."""
    from pelvicnav.io.real_ct import REAL_CT_CASES, default_real_ct_dir

    if cfg.segmentation != "truth":
        raise ValueError("the real-CT cases register with their manual labels (segmentation truth)")
    root = Path(cfg.real_ct_dir) if cfg.real_ct_dir else default_real_ct_dir()
    if root is None or not all((root / n).is_dir() for n in REAL_CT_CASES):
        raise ValueError(f"real CTs not found (looked in {root}; set PELVICNAV_REAL_CT to the "
                         "folder holding 002, 004, 005)")  # fmt: skip
    cases = []
    for i in range(cfg.real_ct * len(REAL_CT_CASES)):
        name = REAL_CT_CASES[i % len(REAL_CT_CASES)]
        cases.append({"case_id": f"real-{name}-{i // len(REAL_CT_CASES):03d}", "index": i,
                      "subject": name, "real_ct": str(root / name), "seed": cfg.seed * 1000 + i,
                      "registration_seed": cfg.seed + i, "settings": cfg,
                      "registration": reg})  # fmt: skip
    meta = {"study": asdict(cfg), "registration": asdict(reg), "real_ct": list(REAL_CT_CASES)}
    return Study("registration", meta, tuple(cases), run_registration_case)


def run_registration_case(case: dict) -> list[dict]:
    """Simulate one case (atlas subject or real CT) and register it; one row per bone."""
    from pelvicnav.register.multibody import register_multibody

    t0 = time.perf_counter()
    if "real_ct" in case:
        sim = simulate_real_ct_case(case["real_ct"], seed=case["seed"], settings=case["settings"])
    else:
        sim = simulate_registration_case(case["vertices"], case["faces"], seed=case["seed"],
                                         settings=case["settings"])  # fmt: skip
    t_sim = time.perf_counter() - t0
    labels, seg = sim["labels"], {}
    if case["settings"].segmentation == "asm":
        labels, seg = _asm_labels(case, sim)
    res = register_multibody(
        sim["ct"], labels, sim["views"], seed=case["registration_seed"],
        settings=case["registration"], dislocated=sim["bone"],  # known from the plan
    )  # fmt: skip
    rows = []
    for r in _errors(sim, res):
        rows.append({
            "case": case["index"], "subject": case["subject"], **r,
            "dislocation_mm": sim["dislocation"][0], "dislocation_deg": sim["dislocation"][1],
            "converged": res.converged, "implausible": bool(res.implausible),
            "settled": res.settled,  # by the second opinion
            "restart_disagreement_mm": res.restart_disagreement.get(r["bone"], ""),
            "warnings": "; ".join(res.warnings), "similarity": res.similarity,
            "seconds": res.seconds, "stage1_s": res.stages[0].seconds,
            "stage2_s": res.stages[1].seconds if len(res.stages) > 1 else 0.0,
            "simulation_s": t_sim, **seg,
        })  # fmt: skip
    return rows


def _asm_labels(case: dict, sim: dict) -> tuple[np.ndarray, dict]:
    """The preoperative CT segmented by the ASM, prior fitted from the other subjects."""
    from pelvicnav.metrics.overlap import dice
    from pelvicnav.shape.asm import segment_ct
    from pelvicnav.studies.segmentation import _leave_one_out

    _, prior = _leave_one_out(case["population"], case["subject"])
    res = segment_ct(sim["ct"].data, sim["ct"].world_from_ijk, prior)
    seg = {f"asm_dice_{b}": dice(res.labels == k + 1, sim["labels"] == k + 1)
           for k, b in enumerate(BONES)}  # fmt: skip
    return res.labels, {**seg, "asm_s": res.seconds["total"]}


def run_registration_study(
    atlas: Atlas,
    out: str | os.PathLike,
    settings: RegistrationStudySettings | None = None,
    *,
    registration=None,
    progress: Callable[[int, int], None] | None = None,
    workers: int | None = 0,
    scheduler: str | None = None,
    force: bool = False,
) -> list[dict]:
    """Simulate and register the cases on the study runner; write ``store.sqlite``,
    ``results.csv`` (one row per bone, a ``case_id`` column), ``summary.csv``, ``settings.json``.
    ``workers=0`` (the default here) runs in this process; None is one worker per core."""
    study = registration_study(atlas, settings, registration)
    results = run_study(study, out, scheduler=scheduler, workers=workers, force=force,
                        progress=progress)  # fmt: skip
    rows = flatten(results)
    out = Path(out)
    summary = summarise(rows)
    write_text(out / "summary.csv", _csv(summary))
    write_text(out / "summary.md", _markdown(summary, rows))
    write_text(out / "settings.json", json.dumps(study.settings, indent=2, default=str))
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for b in (*BONES, "all"):
        sel = [r for r in rows if b in ("all", r["bone"])]
        if not sel:
            continue
        row = {"bone": b, "n": len(sel)}
        for key in ("in_plane_mm", "out_of_plane_mm", "error_mm", "rotation_deg", "pde_mm"):
            v = np.array([r[key] for r in sel if key in r])
            if len(v):
                q1, q2, q3 = np.percentile(v, [25, 50, 75])
                row |= {f"{key}_median": round(q2, 3), f"{key}_iqr": round(q3 - q1, 3),
                        f"{key}_max": round(float(v.max()), 3)}  # fmt: skip
        row["converged"] = int(sum(bool(r["converged"]) for r in sel))
        row["seconds_median"] = round(float(np.median([r["seconds"] for r in sel])), 1)
        out.append(row)
    return out


def _markdown(summary: list[dict], rows: list[dict]) -> str:
    """``summary.md``: medians per bone, the flag's record."""
    from pelvicnav.studies.flags import flag_counts, flag_line

    key = "pde_mm" if any("pde_mm" in r for r in rows) else "error_mm"
    lines = ["# Registration accuracy", "",
             "| bone | n | in-plane median (max), mm | out-of-plane median (max), mm | "
             f"{key} median (max) | converged |", "|---|---|---|---|---|---|"]  # fmt: skip
    for s in summary:
        cells = [f"{s.get(f'{k}_median', float('nan')):.2f} ({s.get(f'{k}_max', float('nan')):.2f})"
                 for k in ("in_plane_mm", "out_of_plane_mm", key)]  # fmt: skip
        lines.append(f"| {s['bone']} | {s['n']} | " + " | ".join(cells) + f" | {s['converged']} |")
    lines += ["", flag_line(flag_counts(rows, key)), ""]
    return "\n".join(lines)


def _csv(rows: list[dict]) -> str:
    fields = list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields)
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()
