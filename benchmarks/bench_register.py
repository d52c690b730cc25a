"""Registration speed against issue 13's targets, on 2 cores, two views (AP + oblique 30).

A simulated case (first atlas subject when configured, else a sampled patient): an open-book
dislocation, 20 mm / 5 deg set-up error, radiographs at 50 uGy. Its CT and labels are resampled
to a clinical grid, 512 x 512 x 400 at 0.8 mm (air and label 0 around), for the timings:

* ``first_registration`` — bone models built from the 0.8 mm CT plus the default two-stage
  registration (target <= 5 s); median of 3 seeds, with the error of each bone's centroid;
* ``subsequent_frame`` — every bone moved 3 mm / 2 deg from the first answer, then the tracking
  registration (``RegistrationSettings.tracking()``), ``FRAMES`` times, with the models kept
  (target <= 0.5 s, median centroid error <= 0.3 mm);
* ``command_overhead`` — ``pelvicnav register`` on NIfTI files (the CT as int16 HU, as scanners
  store it) with a plan, in a fresh process: wall time minus the registration's own seconds and
  the bone models' (``models_seconds`` of ``result.json``; issue 13 counts the models in the
  first registration): imports, reading and checking, compiled kernels from cache, writing
  (target <= 1.5 s); cold (a CT's first command) and warm (the same files again: the bone
  models from the cache). ``wall_s`` is the whole command;
* kernel throughput: splatted DRRs and similarity evaluations per second per level.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import measure

TARGETS = {"first_s": 5.0, "frame_s": 0.5, "frame_error_mm": 0.3, "overhead_s": 1.5}
# Tracked frames per benchmark (each its own 3 mm / 2 deg move): with 3, the median moved by
# 10 % between runs on one machine (0.51-0.56 s, session 28); a frame is about 0.5 s.
FRAMES = 12


def clinical_case() -> dict:
    """The simulated case with its CT and labels on a 512 x 512 x 400 grid at 0.8 mm."""
    from scipy.ndimage import affine_transform

    from pelvicnav.drr.volume import Volume
    from pelvicnav.phantom.population import load_population
    from pelvicnav.studies.registration import (
        RegistrationStudySettings,
        simulate_registration_case,
    )

    pop = load_population(os.environ.get("PELVICNAV_ATLAS") or "model", n_subjects=1)
    case = simulate_registration_case(pop.vertices[0], pop.faces, seed=0,
                                      settings=RegistrationStudySettings())  # fmt: skip
    A = case["ct"].world_from_ijk
    centre = A[:3, :3] @ ((np.array(case["ct"].shape) - 1) / 2) + A[:3, 3]
    shape = np.array([512, 512, 400])
    B = np.diag([0.8, 0.8, 0.8, 1.0])
    B[:3, 3] = centre - 0.8 * (shape - 1) / 2
    M = np.linalg.inv(A) @ B  # source ijk from clinical ijk
    hu = affine_transform(case["ct"].data, M[:3, :3], M[:3, 3], output_shape=tuple(shape),
                          order=1, cval=-1000.0)  # fmt: skip
    labels = affine_transform(case["labels"], M[:3, :3], M[:3, 3], output_shape=tuple(shape),
                              order=0, cval=0)  # fmt: skip
    case["ct"], case["labels"] = Volume(hu.astype(np.float32), B), labels.astype(np.uint8)
    case["centroids"] = {b: case["ct"].world_points(np.argwhere(labels == k + 1)).mean(axis=0)
                         for k, b in enumerate(("sacrum", "left_hip", "right_hip"))}  # fmt: skip
    return case


def _errors(poses: dict, case: dict) -> list[float]:
    from pelvicnav.geometry import transforms as tf

    return [float(np.linalg.norm(tf.apply(poses[b], c[None]) - tf.apply(case["truth"][b], c[None])))
            for b, c in case["centroids"].items()]  # fmt: skip


def _registrations(case: dict) -> tuple[dict, dict, dict]:
    from pelvicnav.register.multibody import register_multibody
    from pelvicnav.register.pyramid import splat_renderer
    from pelvicnav.register.settings import RegistrationSettings
    from pelvicnav.studies.runtime import nudged_poses

    cfg = RegistrationSettings()
    runs, renderer, res = [], None, None
    for seed in range(3):
        t0 = time.perf_counter()
        renderer = splat_renderer(case["ct"], case["labels"], cfg.factors)
        t_models = time.perf_counter() - t0
        res = register_multibody(case["ct"], case["labels"], case["views"], seed=seed,
                                 renderer=renderer, dislocated=case["bone"])  # fmt: skip
        runs.append({"seconds": time.perf_counter() - t0, "models_s": t_models,
                     "stages_s": [s.seconds for s in res.stages],
                     "evaluations": [s.evaluations for s in res.stages],
                     "errors_mm": _errors(res.poses, case),
                     "converged": res.converged})  # fmt: skip
    first = {"median_s": float(np.median([r["seconds"] for r in runs])), "runs": runs,
             "target_s": TARGETS["first_s"]}  # fmt: skip
    first["meets_target"] = first["median_s"] <= TARGETS["first_s"]
    frames, rng = [], np.random.default_rng(0)
    for seed in range(FRAMES):
        start = nudged_poses(res.poses, case["centroids"], rng)
        t0 = time.perf_counter()
        again = register_multibody(case["ct"], case["labels"], case["views"], seed=seed,
                                   init_poses=start, settings=RegistrationSettings.tracking(),
                                   renderer=renderer, dislocated=case["bone"])  # fmt: skip
        frames.append({"seconds": time.perf_counter() - t0, "converged": again.converged,
                       "errors_mm": _errors(again.poses, case)})  # fmt: skip
    med_s = float(np.median([f["seconds"] for f in frames]))
    med_e = float(np.median([e for f in frames for e in f["errors_mm"]]))
    frame = {"median_s": med_s, "median_error_mm": med_e, "runs": frames,
             "target_s": TARGETS["frame_s"], "target_error_mm": TARGETS["frame_error_mm"],
             "meets_target": bool(med_s <= TARGETS["frame_s"]
                                  and med_e <= TARGETS["frame_error_mm"])}  # fmt: skip
    return first, frame, {"renderer": renderer}


def _overhead(case: dict) -> dict:
    """``pelvicnav register`` (with a plan naming the dislocated bone) in fresh processes: wall
    time minus the registration's and the bone models' seconds. Cold: an empty cache of bone
    models (the CT read, checked and sampled: a CT's first command); warm: the same files again
    (the models from the cache, :mod:`pelvicnav.workflow.bone_cache`: every later frame of a
    guidance run). Three of each, the median reported (the smallest beside it: the cores are
    shared)."""
    from pelvicnav.io.views import View, write_views
    from pelvicnav.io.volume import write_volume

    runs = {"cold": [], "warm": []}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        hu = np.clip(np.round(case["ct"].data), -32768, 32767).astype(np.int16)  # as scanners
        write_volume(d / "ct.nii.gz", hu, case["ct"].world_from_ijk)  # store it (float32: 4x)
        write_volume(d / "labels.nii.gz", case["labels"], case["ct"].world_from_ijk)
        (d / "plan.json").write_text(
            json.dumps({"dislocated_bone": case["bone"], "target_from_current": np.eye(4).tolist()})
        )
        views = case["views"]
        write_views(d, [View(f"v{k}", img.astype(np.float32), P, ps) for k, (img, P, ps)
                        in enumerate(zip(views.images, views.projections, views.pixel_spacing,
                                         strict=True))])  # fmt: skip
        exe = Path(sys.executable).with_name("pelvicnav")
        cmd = [str(exe), "register", "--ct", str(d / "ct.nii.gz"), "--labels",
               str(d / "labels.nii.gz"), "--views", str(d / "views.json"), "--plan",
               str(d / "plan.json"), "--out", str(d / "result.json")]  # fmt: skip
        for kind in ("cold",) * 3 + ("warm",) * 3:
            cache = d / "cache"
            if kind == "cold":
                shutil.rmtree(cache, ignore_errors=True)
            env = {**os.environ, "PELVICNAV_CACHE": str(cache)}
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True, env=env)
            wall = time.perf_counter() - t0
            record = json.loads((d / "result.json").read_text())
            reg, models = record["seconds"], record["models_seconds"]
            assert record["models_cached"] == (kind == "warm")
            runs[kind].append({"wall_s": wall, "registration_s": reg, "models_s": models,
                               "overhead_s": wall - reg - models})  # fmt: skip
    out = {f"{k}_overhead_s": float(np.median([r["overhead_s"] for r in v]))
           for k, v in runs.items()}  # fmt: skip
    out |= {f"{k}_overhead_min_s": float(min(r["overhead_s"] for r in v)) for k, v in runs.items()}
    return out | {"runs": runs, "target_s": TARGETS["overhead_s"],
                  "meets_target_cold": out["cold_overhead_s"] <= TARGETS["overhead_s"],
                  "meets_target_warm": out["warm_overhead_s"] <= TARGETS["overhead_s"]}  # fmt: skip


def _kernels(case: dict, renderer) -> dict:
    from pelvicnav.register.pyramid import build_levels
    from pelvicnav.register.settings import PyramidSettings

    out, B = {}, 100
    for lv in build_levels(case["views"], renderer, PyramidSettings()):
        for bones in (("left_hip",), renderer.bones):
            poses = np.tile(np.eye(4), (B, len(bones), 1, 1))
            t = measure(lambda lv=lv, b=bones, p=poses: renderer.render(lv.index, b, p,
                        lv.projections, lv.shape), repeats=5)  # fmt: skip
            out[f"splat_{lv.factor}x_{len(bones)}bones"] = t | {
                "drrs_per_s": B * len(lv.projections) / t["median_s"]
            }
        drrs = renderer.render(lv.index, renderer.bones, poses, lv.projections, lv.shape)
        t = measure(lambda lv=lv, d=drrs: lv.score(d), repeats=5)
        out[f"similarity_{lv.factor}x"] = t | {"candidates_per_s": B / t["median_s"]}
    return out


def run() -> dict:
    import numba

    case = clinical_case()
    first, frame, keep = _registrations(case)
    return {
        "ct_shape": list(case["ct"].shape),
        "numba_threads": numba.get_num_threads(),
        "first_registration": first,
        "subsequent_frame": frame,
        "command_overhead": _overhead(case),
        **_kernels(case, keep["renderer"]),
    }
