"""Baselines: symmetry plane, ICP, SSM_single and contralateral mirroring."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.pose.baselines import (
    MirrorEstimator,
    SinglePelvisEstimator,
    icp,
    reflection,
    symmetry_plane,
)


def test_reflection_is_an_involution_across_the_plane():
    n = np.array([1.0, 0.2, -0.1])
    M = reflection(n, 12.0)
    np.testing.assert_allclose(M @ M, np.eye(4), atol=1e-12)
    assert np.linalg.det(M[:3, :3]) == pytest.approx(-1.0)
    on_plane = 12.0 * n / np.linalg.norm(n)
    np.testing.assert_allclose(tf.apply(M, on_plane[None])[0], on_plane, atol=1e-12)


def test_symmetry_plane_of_a_symmetric_cloud_with_asymmetric_clutter():
    rng = np.random.default_rng(0)
    normal = np.array([0.97, 0.2, 0.1])
    normal /= np.linalg.norm(normal)
    half = rng.normal(size=(800, 3)) * [15, 30, 40] + [25, 0, 0]
    cloud = np.vstack([half, tf.apply(reflection(normal, 5.0), half)])
    clutter = rng.normal(size=(60, 3)) * 5 + [30, 10, 60]  # on one side only
    n, d = symmetry_plane(np.vstack([cloud, clutter]))
    assert np.degrees(np.arccos(min(1.0, abs(n @ normal)))) < 1.0  # |cos| can round above 1
    assert d == pytest.approx(5.0, abs=1.0)


def test_icp_recovers_a_small_rigid_motion():
    rng = np.random.default_rng(1)
    target = rng.normal(size=(2000, 3)) * [40, 30, 20]
    T = tf.from_params([3.0, -2.0, 1.0], np.deg2rad([3.0, -2.0, 4.0]))
    source = tf.apply(tf.invert(T), target)
    np.testing.assert_allclose(icp(source, target, trim=1.0), T, atol=1e-3)


def test_ssm_single_on_a_population_with_known_modes(pose_population):
    V, *_ = pose_population
    est = SinglePelvisEstimator.fit(V[1:], noise_variance=0.01)
    moved = tf.apply(tf.from_params([10.0, 0, 0], [0, 0.1, 0]), V[0, 1])
    T = est.estimate({"sacrum": V[0, 0], "right_hip": V[0, 2]}, {"left_hip": moved})["left_hip"]
    assert np.linalg.norm(tf.apply(T, moved) - V[0, 1], axis=1).mean() < 1.0


def test_mirroring_a_symmetric_pelvis_recovers_the_dislocated_side():
    from helpers.synthetic import make_population

    # No pose variation: every subject is exactly symmetric about x = 0.
    V, *_ = make_population(12, mode_sd=(0.0, 0.0), shape_sd=0.02, seed=3)
    V[:, 2] = V[:, 1] * [-1, 1, 1]  # right hip = mirrored left hip, same vertex order
    est = MirrorEstimator.fit(V[1:])
    np.testing.assert_array_equal(est.left_from_right, np.arange(V.shape[2]))
    moved = tf.apply(tf.from_params([0, 8.0, 3.0], [0.05, 0, 0.1]), V[0, 1])
    T = est.estimate({"sacrum": V[0, 0], "right_hip": V[0, 2]}, {"left_hip": moved})["left_hip"]
    assert np.linalg.norm(tf.apply(T, moved) - V[0, 1], axis=1).mean() < 0.3


def test_mirroring_refuses_bilateral_cases(pose_population):
    V, *_ = pose_population
    est = MirrorEstimator.fit(V[1:])
    with pytest.raises(ValueError, match="cannot|needs the sacrum and one innominate"):
        est.estimate({"sacrum": V[0, 0]}, {"left_hip": V[0, 1], "right_hip": V[0, 2]})
    with pytest.raises(ValueError, match="at least one bone must be observed"):
        SinglePelvisEstimator.fit(V[1:]).estimate({}, {"left_hip": V[0, 1]})
