"""Two point bodies, their DRRs at a known pose as radiographs: a small registration problem."""

from __future__ import annotations

import numpy as np

from pelvicnav.drr.splat import PointModel
from pelvicnav.geometry import projection as pj
from pelvicnav.register.pyramid import downsample_projection


def blob(centre, n, rng, spacing=2.0) -> PointModel:
    pts = np.asarray(centre) + rng.normal(size=(n, 3)) * [25.0, 18.0, 12.0]
    return PointModel(pts, rng.uniform(0.2, 1.0, n), spacing)


def views_4x(shape=(128, 128)):
    return np.stack([downsample_projection(pj.CArm(orbit_deg=a, tilt_deg=t).projection_matrix, 4)
                     for a, t in ((0, 0), (35, -15))])  # fmt: skip
