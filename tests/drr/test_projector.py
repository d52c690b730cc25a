"""DRR projector: closed-form ellipsoid, slow reference line integrals, poses, batching."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from helpers.ellipsoids import MU, chords, ellipsoid_volume
from pelvicnav.drr.projector import ray_directions, render
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.register.pyramid import downsample_projection


def test_uniform_ellipsoid_matches_the_closed_form():
    radii, centre = (60.0, 40.0, 30.0), np.array([5.0, -3.0, 2.0])
    vol = ellipsoid_volume(radii, centre)
    carm = pj.CArm(rows=48, cols=48, pixel_spacing=(4.0, 4.0), orbit_deg=20, tilt_deg=-10)
    drr = render([vol], np.eye(4)[None, None], carm.projection_matrix[None], (48, 48))[0, 0]
    source, dirs = ray_directions(carm.projection_matrix, 48, 48)
    exact = MU * chords(source, dirs, radii, centre)
    # Interior pixels: rays that cross the body well away from grazing incidence, where the 1 mm
    # voxelisation of the surface (not the projector) dominates the difference.
    interior = exact > 0.6 * exact.max()
    assert interior.sum() > 200
    rel = (drr[interior] - exact[interior]) / exact[interior]
    assert np.abs(rel).max() < 0.01
    assert abs(rel.mean()) < 0.002
    # Rays that miss the body by more than two voxels see nothing at all.
    far = chords(source, dirs, np.asarray(radii) + 2.0, centre) == 0
    assert far.sum() > 100
    assert np.abs(drr[far]).max() == 0.0


def test_matches_slow_reference_line_integrals():
    rng = np.random.default_rng(0)
    data = rng.random((30, 25, 20)).astype(np.float32) * 0.03
    A = tf.from_params([-20.0, -15.0, -10.0], [0.1, -0.2, 0.3]) @ np.diag([1.2, 1.5, 2.0, 1.0])
    vol = Volume(data, A)
    carm = pj.CArm(rows=12, cols=16, pixel_spacing=(6.0, 6.0), orbit_deg=35, tilt_deg=15)
    P = carm.projection_matrix
    drr = render([vol], np.eye(4)[None, None], P[None], (12, 16), step_mm=0.25)[0, 0]
    source, dirs = ray_directions(P, 12, 16)
    ijk_from_world = vol.ijk_from_world
    h = 0.02
    t = np.arange(400.0, 800.0, h) + h / 2
    ref = np.zeros((12, 16))
    for r in range(12):
        for c in range(16):
            pts = source + t[:, None] * dirs[r, c]
            ijk = tf.apply(ijk_from_world, pts).T
            ref[r, c] = map_coordinates(data, ijk, order=1, mode="grid-constant").sum() * h
    inside = ref > 0.2 * ref.max()
    assert inside.sum() > 50
    np.testing.assert_allclose(drr[inside], ref[inside], rtol=0.01)


def test_pose_moves_the_bone():
    rng = np.random.default_rng(1)
    vol = Volume.from_spacing(rng.random((20, 20, 20)) * 0.02, [2.0] * 3, [-20, -20, -20])
    T = tf.from_params([5.0, -8.0, 3.0], [0.2, 0.1, -0.3])
    moved = Volume(vol.data, T @ vol.world_from_ijk)
    P = pj.CArm(rows=24, cols=24, pixel_spacing=(5.0, 5.0)).projection_matrix
    a = render([vol], T[None, None], P[None], (24, 24))
    b = render([moved], np.eye(4)[None, None], P[None], (24, 24))
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_batches_and_bones_add_up():
    rng = np.random.default_rng(2)
    v1 = Volume.from_spacing(rng.random((16, 16, 16)) * 0.02, [2.0] * 3, [-40, -16, -16])
    v2 = Volume.from_spacing(rng.random((12, 14, 10)) * 0.02, [2.5] * 3, [10, -16, -12])
    Ps = np.stack(
        [
            pj.CArm(rows=20, cols=20, pixel_spacing=(6.0, 6.0), orbit_deg=a).projection_matrix
            for a in (0, 30)
        ]
    )
    poses = np.stack(
        [np.stack([np.eye(4), tf.from_params([0, 0, d], [0, 0, 0])]) for d in (0.0, 7.0, -4.0)]
    )
    both = render([v1, v2], poses, Ps, (20, 20), step_mm=0.5)
    assert both.shape == (3, 2, 20, 20)
    only1 = render([v1], poses[:, :1], Ps, (20, 20), step_mm=0.5)
    only2 = render([v2], poses[:, 1:], Ps, (20, 20), step_mm=0.5)
    np.testing.assert_allclose(both, only1 + only2, rtol=1e-5, atol=1e-6)
    single = render([v1, v2], poses[2:], Ps[1:], (20, 20), step_mm=0.5)
    np.testing.assert_allclose(both[2:, 1:], single, rtol=1e-6)


def test_downsampled_projection_bins_pixels():
    P = pj.CArm().projection_matrix
    x = np.array([[12.0, -30.0, 40.0]])
    u = pj.project(P, x)
    for f in (2, 4):
        np.testing.assert_allclose(
            pj.project(downsample_projection(P, f), x), (u - (f - 1) / 2) / f, atol=1e-9
        )


def test_bad_input():
    vol = Volume.from_spacing(np.ones((4, 4, 4)), [1.0] * 3)
    P = pj.CArm(rows=8, cols=8).projection_matrix
    with pytest.raises(ValueError, match=r"poses must have shape \(B, 1, 4, 4\)"):
        render([vol], np.eye(4), P, (8, 8))
    with pytest.raises(ValueError, match="singular"):
        render([vol], np.eye(4)[None, None], np.zeros((3, 4)), (8, 8))
    with pytest.raises(ValueError, match="NaN"):
        Volume.from_spacing(np.full((2, 2, 2), np.nan), [1.0] * 3)
    with pytest.raises(ValueError, match="invertible"):
        Volume(np.ones((2, 2, 2)), np.diag([1.0, 0.0, 1.0, 1.0]))
