"""Simulation speed: one atlas CT (target < 20 s) and one 512 x 512 radiograph (< 2 s)."""

from __future__ import annotations

import os

import numpy as np

from benchmarks.harness import measure


def run() -> dict:
    from pelvicnav.io.atlas import AtlasNotFoundError, load_atlas
    from pelvicnav.phantom.ctsynth import synthesize_ct
    from pelvicnav.phantom.xray import simulate_radiograph, standard_view

    try:
        atlas = load_atlas(os.environ.get("PELVICNAV_ATLAS"))
    except AtlasNotFoundError as err:
        return {"skipped": str(err)}
    V = atlas.vertices[0]
    ct = synthesize_ct(V, atlas.faces, rng=np.random.default_rng(0))
    out = {
        "ct_synthesis": measure(
            lambda: synthesize_ct(V, atlas.faces, rng=np.random.default_rng(0)), repeats=3
        )
        | {"target_s": 20.0, "shape": list(ct.hu.shape), "spacing_mm": [1.0, 1.0, 2.0]},
    }
    iso = tuple(V.reshape(-1, 3).mean(axis=0))
    for name in ("ap", "inlet"):
        carm = standard_view(name, isocenter=iso)
        simulate_radiograph(ct.hu, carm, dose_ugy=5.0, rng=np.random.default_rng(0))  # warm up
        t = measure(
            lambda carm=carm: simulate_radiograph(
                ct.hu, carm, dose_ugy=5.0, rng=np.random.default_rng(0)
            ),
            repeats=5,
        )
        out[f"radiograph_512_{name}"] = t | {"target_s": 2.0, "meets_target": t["median_s"] < 2}
    out["ct_synthesis"]["meets_target"] = out["ct_synthesis"]["median_s"] < 20.0
    return out
