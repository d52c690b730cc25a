"""Splatting DRRs: mass conservation, closed-form ellipsoid, agreement with the ray caster."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from helpers.ellipsoids import MU, chords, ellipsoid_volume
from pelvicnav.drr.projector import ray_directions, render
from pelvicnav.drr.splat import PointModel, point_model, splat
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf


def test_point_model_conserves_mass_and_first_moment():
    rng = np.random.default_rng(0)
    data = (rng.random((9, 10, 7)) * (rng.random((9, 10, 7)) > 0.5)).astype(np.float32)
    A = tf.from_params([3.0, -2.0, 1.0], [0.1, 0.2, -0.1]) @ np.diag([1.0, 1.0, 2.0, 1.0])
    vol = Volume(data, A)
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in data.shape], indexing="ij"), -1)
    world = vol.world_points(ijk.reshape(-1, 3))
    w = data.reshape(-1).astype(np.float64) * 2.0  # voxel volume 2 mm^3
    for factors in ((1, 1, 1), (2, 2, 1), (3, 4, 2)):
        m = point_model(vol, factors)
        assert m.mass.sum() == pytest.approx(w.sum(), rel=1e-9)
        np.testing.assert_allclose(m.centroid, (w @ world) / w.sum(), atol=1e-9)
    assert point_model(vol, (2, 2, 1)).spacing == pytest.approx(2.0)


@pytest.mark.parametrize("method", ["tent", "fast"])
def test_uniform_ellipsoid_matches_the_closed_form(method):
    radii, centre = (60.0, 40.0, 30.0), np.array([5.0, -3.0, 2.0])
    model = point_model(ellipsoid_volume(radii, centre))
    for orbit, tilt in ((0, 0), (20, -10), (60, 25)):
        carm = pj.CArm(rows=48, cols=48, pixel_spacing=(4.0, 4.0), orbit_deg=orbit, tilt_deg=tilt)
        P = carm.projection_matrix[None]
        img = splat([model], np.eye(4)[None, None], P, (48, 48), method=method)[0, 0]
        source, dirs = ray_directions(carm.projection_matrix, 48, 48)
        exact = MU * chords(source, dirs, radii, centre)
        # the splat is a DRR blurred by about one sample: compare with the blurred closed form
        interior = exact > 0.6 * exact.max()
        rel = (img[interior] - exact[interior]) / exact[interior]
        # a blurred lattice of samples: small ripple (the ray caster in drr.projector is the
        # 1%-accurate reference; this is the fast approximation the optimiser uses)
        assert np.median(np.abs(rel)) < 0.005 and np.abs(rel).max() < 0.025, (orbit, tilt)
        # total mass seen by the detector: sum of pixel values x pixel area / magnification^2
        assert img.sum() == pytest.approx(exact.sum(), rel=0.01)


@pytest.mark.parametrize("method", ["tent", "fast"])
def test_agrees_with_the_ray_caster_for_posed_batched_bones(method):
    rng = np.random.default_rng(1)
    vols = []
    for c in ((-30.0, 0.0, 0.0), (30.0, 10.0, -5.0)):
        v = ellipsoid_volume((25.0, 18.0, 30.0), np.asarray(c), extent=40.0)
        tex = gaussian_filter(rng.random(v.shape), 5.0).astype(np.float32)
        tex = (tex - tex.min()) / np.ptp(tex)
        vols.append(Volume(v.data * (0.5 + tex), v.world_from_ijk))
    models = [point_model(v) for v in vols]
    carm = pj.CArm(rows=64, cols=64, pixel_spacing=(3.0, 3.0), orbit_deg=30, tilt_deg=-20)
    P = np.stack([carm.projection_matrix, pj.CArm(rows=64, cols=64, pixel_spacing=(3.0, 3.0))
                  .projection_matrix])  # fmt: skip
    poses = np.stack(
        [
            np.stack([np.eye(4), tf.from_params([3.0, -4.0, 2.0], [0.05, 0.1, -0.08])]),
            np.stack([tf.from_params([0.0, 5.0, 0.0], [0.0, 0.0, 0.2]), np.eye(4)]),
        ]
    )
    fast = splat(models, poses, P, (64, 64), method=method)
    slow = render(vols, poses, P, (64, 64), step_mm=0.5)
    assert fast.shape == slow.shape == (2, 2, 64, 64)
    for b in range(2):
        for k in range(2):
            ref = slow[b, k]
            inner = ref > 0.3 * ref.max()
            # the splat is blurred by one pixel, the ray caster is not: close inside
            rel = np.abs(fast[b, k][inner] - ref[inner]) / ref[inner]
            # "fast" blurs with one kernel width per image (the first bone's depth)
            tol = 0.01 if method == "tent" else 0.025
            assert np.median(rel) < tol and np.percentile(rel, 95) < 4 * tol + 0.01
            assert fast[b, k].sum() == pytest.approx(ref.sum(), rel=0.01)


def test_bad_input():
    m = PointModel(np.zeros((1, 3)), np.ones(1), 1.0)
    with pytest.raises(ValueError, match="poses"):
        splat([m], np.eye(4)[None], np.zeros((1, 3, 4)), (4, 4))
    with pytest.raises(ValueError, match="singular"):
        splat([m], np.eye(4)[None, None], np.zeros((1, 3, 4)), (4, 4))
    with pytest.raises(ValueError, match="at least one sample"):
        PointModel(np.zeros((0, 3)), np.zeros(0), 1.0)
    with pytest.raises(ValueError, match="factors"):
        point_model(Volume(np.ones((2, 2, 2), np.float32), np.eye(4)), (0, 1, 1))


def test_per_candidate_projections_match_shared_ones():
    model = point_model(ellipsoid_volume((20.0, 15.0, 25.0), np.zeros(3), extent=30.0))
    P1 = pj.CArm(rows=32, cols=32, pixel_spacing=(6.0, 6.0)).projection_matrix
    P2 = pj.CArm(rows=32, cols=32, pixel_spacing=(6.0, 6.0), orbit_deg=40).projection_matrix
    poses = np.stack([np.eye(4)[None], tf.from_params([5.0, 0, 0], [0, 0, 0.1])[None]])
    shared = splat([model], poses, np.stack([P1, P2]), (32, 32))
    per = splat([model], poses, np.stack([[P1, P2], [P1, P2]]), (32, 32))
    np.testing.assert_allclose(per, shared, rtol=1e-6, atol=1e-7)
    swapped = splat([model], poses, np.stack([[P1, P2], [P2, P1]]), (32, 32))
    np.testing.assert_allclose(swapped[1, 0], shared[1, 1], rtol=1e-6, atol=1e-7)


def test_fast_splat_is_the_same_however_the_samples_are_split_among_bodies():
    """The fast splat projects samples in chunks that stop at each body's end: the same samples
    at the same pose, as one body or split into two (chunks ending elsewhere), splat bitwise
    alike; the first body, which sets the blur, is the same in both."""
    rng = np.random.default_rng(3)
    first = PointModel(rng.normal(0, 30, (1300, 3)), rng.uniform(0.1, 1, 1300), 1.5)
    pts, mass = rng.normal(20, 25, (1100, 3)), rng.uniform(0.1, 1, 1100)
    whole = PointModel(pts, mass, 1.5)
    halves = [PointModel(pts[:611], mass[:611], 1.5), PointModel(pts[611:], mass[611:], 1.5)]
    P = pj.CArm(rows=64, cols=64, pixel_spacing=(3.0, 3.0), orbit_deg=30).projection_matrix
    pose = tf.from_params([4.0, -2.0, 1.0], [0.05, -0.1, 0.2])
    one = splat([first, whole], np.stack([pose] * 2)[None], P[None], (64, 64))
    two = splat([first, *halves], np.stack([pose] * 3)[None], P[None], (64, 64))
    assert one.max() > 0 and np.array_equal(one, two)


_KERNELS_SCRIPT = """
import hashlib, sys
import numpy as np
from pelvicnav.drr.splat import PointModel, splat_pullback
rng = np.random.default_rng(0)
models = [PointModel(rng.normal(0, 40, (5000, 3)), rng.uniform(0.1, 1, 5000), 1.5)
          for _ in range(2)]
T = np.stack([np.eye(4)] * 2)
P = np.array([[900.0, 0, 64, 900 * 64], [0, 900, 64, 900 * 64], [0, 0, 1, 900]])
Q = P.copy()
Q[0, 3] += 200
Ps = np.stack([P, Q])
G = rng.normal(size=(2, 128, 128))
sys.stdout.write(hashlib.md5(splat_pullback(models, T, Ps, G).tobytes()).hexdigest())
"""


@pytest.mark.slow
def test_the_adjoint_compiled_here_and_loaded_from_the_cache_agree_bitwise(tmp_path):
    """The adjoint splat compiled with fastmath gave other last bits when numba loaded it from
    its cache than when it had just compiled it, and a tracked frame took another path (see
    ``_compile_pullback``): the first process here compiles into an empty cache, the second
    loads from it."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    run = [sys.executable, "-c", _KERNELS_SCRIPT]
    fresh = subprocess.run(run, env=env, capture_output=True, text=True, check=True).stdout
    assert any(tmp_path.rglob("*.nbi")), "nothing was cached"
    cached = subprocess.run(run, env=env, capture_output=True, text=True, check=True).stdout
    assert fresh == cached
