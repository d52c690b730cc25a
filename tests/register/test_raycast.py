"""The ray-cast reference renderer through the same driver: render from a known pose, perturb,
register one rigid body, check the error."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from pelvicnav.drr.projector import render
from pelvicnav.drr.renderer import RayCastRenderer, Renderer
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.views import ViewSet
from pelvicnav.register.multibody import register
from pelvicnav.register.pyramid import downsample_image
from pelvicnav.register.settings import (
    PyramidSettings,
    RegistrationSettings,
    Stage1Settings,
    Stage2Settings,
)


@pytest.fixture(scope="module")
def bone():
    """A textured bone-like body: an ellipsoid shell with a few internal struts, 2 mm voxels."""
    rng = np.random.default_rng(0)
    n = (30, 24, 36)
    ijk = np.indices(n).astype(float)
    c = (np.array(n)[:, None, None, None] - 1) / 2
    r = np.array([13.0, 10.0, 16.0])[:, None, None, None]
    q = np.sum(((ijk - c) / r) ** 2, axis=0)
    data = 0.02 * ((q < 1) & (q > 0.6)) + 0.008 * (q < 0.6)
    data += 0.01 * (np.abs(ijk[0] - c[0] - 3) < 1.5) * (q < 1)
    # Asymmetric features (a knob and an off-axis strut) so every rotation shows in the images.
    knob = np.sum(((ijk - c - np.array([8.0, 5.0, 10.0])[:, None, None, None]) / 3.5) ** 2, 0) < 1
    data += 0.025 * knob
    data += 0.012 * (np.abs(ijk[1] - c[1] + 4) < 1.2) * (np.abs(ijk[2] - c[2] - 6) < 1.2) * (q < 1)
    data = gaussian_filter(data + 0.002 * rng.random(n) * (q < 1), 0.7)
    return Volume.from_spacing(data, [2.0] * 3, [-29.0, -23.0, -35.0])


def test_downsample_image_block_means():
    img = np.arange(36.0).reshape(6, 6)
    np.testing.assert_allclose(downsample_image(img, 2)[0, 0], np.mean([0, 1, 6, 7]))
    assert downsample_image(np.ones((7, 9)), 2).shape == (3, 4)


def test_recovers_a_known_pose_from_three_views(bone):
    # AP and lateral alone leave rotation about the vertical axis out of plane in both; a tilted
    # third view pins it.
    views = [
        pj.CArm(rows=64, cols=64, pixel_spacing=(3.0, 3.0)),
        pj.CArm(rows=64, cols=64, pixel_spacing=(3.0, 3.0), orbit_deg=90),
        pj.CArm(rows=64, cols=64, pixel_spacing=(3.0, 3.0), tilt_deg=45),
    ]
    Ps = [v.projection_matrix for v in views]
    truth = tf.from_params([4.0, -3.0, 5.0], np.deg2rad([3.0, -2.0, 4.0]))
    images = render([bone], truth[None, None], np.stack(Ps), (64, 64))[0]
    settings = RegistrationSettings(
        pyramid=PyramidSettings(factors=(2, 1), metrics=("go", "go")),  # the paper's GO
        stage1=Stage1Settings(populations=(24, 24), max_generations=(40, 40)),
        stage2=Stage2Settings(enabled=False, max_generations=(0, 0)),
    )
    renderer = RayCastRenderer({"body": bone}, levels=2)
    assert isinstance(renderer, Renderer)
    views = ViewSet.from_arrays(list(images), Ps, [v.pixel_spacing for v in views])
    res = register(views, renderer, seed=3, settings=settings)
    err = tf.invert(truth) @ res.poses["body"]
    assert np.linalg.norm(err[:3, 3]) < 0.5  # mm
    assert np.degrees(np.linalg.norm(tf.rotvec_from_matrix(err[:3, :3]))) < 0.5
    assert res.similarity > 2.4  # three views, each near its maximum
    assert res.converged, res.warnings
    assert len(res.stages[0].levels) == 2


def test_bad_input(bone):
    P = pj.CArm(rows=16, cols=16).projection_matrix
    img = np.zeros((16, 16))
    with pytest.raises(ValueError, match="one projection matrix and pixel spacing per image"):
        ViewSet.from_arrays([img, img], [P], [(1.0, 1.0)])
    bad = img.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ViewSet.from_arrays([bad], [P], [(1.0, 1.0)])
    with pytest.raises(ValueError, match="singular"):
        ViewSet.from_arrays([img], [np.zeros((3, 4))], [(1.0, 1.0)])
    with pytest.raises(ValueError, match="one value per level"):
        PyramidSettings(factors=(4, 2), sigmas=(4.0,))
    with pytest.raises(ValueError, match="renderer has 1 levels"):
        register(ViewSet.from_arrays([img], [P], [(1.0, 1.0)]), RayCastRenderer({"body": bone}))
