"""Fixtures of the registration tests."""

from __future__ import annotations

import numpy as np
import pytest
from tests.helpers.bodies import blob

from pelvicnav.drr.renderer import SplatRenderer
from pelvicnav.drr.splat import PointModel, splat
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.views import ViewSet
from pelvicnav.register.pyramid import build_levels
from pelvicnav.register.settings import PyramidSettings


@pytest.fixture(scope="module")
def two_bodies(two_body_views):
    """Two point bodies, their DRRs at a known pose as the radiographs, a 2-level pyramid."""
    renderer, views, truth = two_body_views
    levels = build_levels(views, renderer, PyramidSettings(metrics=("gncc", "gncc")))
    return renderer, levels, truth


@pytest.fixture(scope="module")
def two_body_views():
    """Two point bodies (a renderer of two levels), their DRRs in two views at a known pose as
    the radiographs, and that pose."""
    rng = np.random.default_rng(2)
    fine = {"a": blob([0, 0, 0], 6000, rng, 1.5), "b": blob([50, 0, 10], 6000, rng, 1.5)}
    coarse = {k: PointModel(m.points[::4], 4 * m.mass[::4], 3.0) for k, m in fine.items()}
    renderer = SplatRenderer((coarse, fine))
    truth = {"a": tf.from_params([2.0, -1.0, 1.5], [0.02, 0.0, 0.01]),
             "b": tf.from_params([-1.0, 2.0, 0.0], [0.0, -0.03, 0.02])}  # fmt: skip
    carms = [pj.CArm(orbit_deg=a, tilt_deg=t) for a, t in ((0, 0), (35, -15))]
    Ps = np.stack([c.projection_matrix for c in carms])
    imgs = splat([fine["a"], fine["b"]], np.stack([truth["a"], truth["b"]])[None], Ps, (512, 512))
    views = ViewSet.from_arrays([np.asarray(i, dtype=np.float64) for i in imgs[0]], list(Ps),
                                [c.pixel_spacing for c in carms])  # fmt: skip
    return renderer, views, truth
