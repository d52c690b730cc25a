"""Batched Sim(3) exp/log and point projection throughput (one BLAS thread)."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_limits

from benchmarks.harness import measure


def run() -> dict:
    from pelvicnav.geometry import projection as pj
    from pelvicnav.geometry import transforms as tf

    rng = np.random.default_rng(0)
    n = 100_000
    b = np.concatenate(
        [rng.normal(0, 20, (n, 3)), rng.normal(0, 0.5, (n, 3)), rng.normal(0, 0.1, (n, 1))], 1
    )
    T = tf.sim3_exp(b)
    P = pj.CArm(orbit_deg=30, tilt_deg=-20).projection_matrix
    pts = rng.normal(0, 100, (15_000, 3))  # three bones of 5000 vertices
    out = {}
    with threadpool_limits(1):
        for name, fn in {
            "sim3_exp_100k": lambda: tf.sim3_exp(b),
            "sim3_log_100k": lambda: tf.sim3_log(T),
            "project_15k_points": lambda: pj.project(P, pts),
            "carm_projection_matrix": lambda: pj.CArm(orbit_deg=30).projection_matrix,
        }.items():
            out[name] = measure(fn, repeats=9)
    out["sim3_exp_100k"]["per_transform_us"] = out["sim3_exp_100k"]["median_s"] / n * 1e6
    out["sim3_log_100k"]["per_transform_us"] = out["sim3_log_100k"]["median_s"] / n * 1e6
    return out
