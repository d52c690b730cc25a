"""DRR throughput: a CMA-ES generation (100 candidates x 2 views) at the 4x and 2x pyramid levels.

Bone volumes are bone-sized ellipsoids with texture (hip ~140 x 150 x 210 mm, sacrum ~110 x 80 x
120 mm) at 2 mm voxels for 4x and 1 mm for 2x, the resolution each level needs. The detector is
the paper's 300 mm C-arm detector binned from 512 x 512 to 128 x 128 (4x) or 256 x 256 (2x).
"""

from __future__ import annotations

import os

import numpy as np

from benchmarks.harness import measure


def _bone(rng, radii, centre, spacing):
    from pelvicnav.drr.volume import Volume

    n = np.ceil(2 * np.asarray(radii) / spacing).astype(int) + 1
    ax = [np.arange(k) * spacing - r for k, r in zip(n, radii, strict=True)]
    x, y, z = np.meshgrid(*ax, indexing="ij")
    inside = (x / radii[0]) ** 2 + (y / radii[1]) ** 2 + (z / radii[2]) ** 2 <= 1
    data = inside * (0.02 + 0.01 * rng.random(inside.shape))
    return Volume.from_spacing(data, [spacing] * 3, np.asarray(centre) - np.asarray(radii))


def run() -> dict:
    import numba

    from pelvicnav.drr.projector import render
    from pelvicnav.geometry import projection as pj
    from pelvicnav.register.pyramid import downsample_projection

    rng = np.random.default_rng(0)
    views = [pj.CArm(), pj.CArm(orbit_deg=30, tilt_deg=-20)]
    out = {
        "numba_threads": numba.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
    }
    B = 100
    for level, spacing in ((4, 2.0), (2, 1.0)):
        bones = [
            _bone(rng, (70.0, 75.0, 105.0), (75.0, 0.0, 0.0), spacing),
            _bone(rng, (55.0, 40.0, 60.0), (0.0, 40.0, 20.0), spacing),
            _bone(rng, (70.0, 75.0, 105.0), (-75.0, 0.0, 0.0), spacing),
        ]
        Ps = np.stack([downsample_projection(v.projection_matrix, level) for v in views])
        shape = (512 // level, 512 // level)
        for L in (1, 3):
            poses = np.tile(np.eye(4), (B, L, 1, 1))
            poses[:, :, :3, 3] = rng.normal(0, 2, (B, L, 3))
            render(bones[:L], poses[:1], Ps, shape)  # compile and warm up
            args = (bones[:L], poses, Ps, shape)
            t = measure(lambda args=args: render(*args), repeats=3)
            t["drrs_per_second"] = B * len(views) / t["median_s"]
            t["batch"] = f"{B} candidates x {len(views)} views x {L} bones, {shape[0]}x{shape[1]}"
            out[f"level_{level}x_{L}_bones"] = t
    return out
