"""Simulation speed: one atlas CT (target < 20 s) and one 512 x 512 radiograph (< 2 s)."""

from __future__ import annotations

import os

import numpy as np

from benchmarks.harness import measure


def run() -> dict:
    from pelvicnav.phantom.ctsynth import synthesize_ct
    from pelvicnav.phantom.population import load_population, procedural_population, template_bones
    from pelvicnav.phantom.xray import simulate_radiograph, standard_view

    def population() -> None:
        template_bones.cache_clear()
        procedural_population(40, seed=0)

    pop = {"procedural_population_40_cold": measure(population, repeats=3)}
    atlas = load_population(os.environ.get("PELVICNAV_ATLAS") or None, n_subjects=1)
    V = atlas.vertices[0]
    ct = synthesize_ct(V, atlas.faces, rng=np.random.default_rng(0))
    out = pop | {
        "source": atlas.source,
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
