"""Sim(3)/SE(3) exponential and logarithm, compose, inverse, distance, conversions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from pelvicnav.geometry import transforms as tf

TOL = 1e-9


@st.composite
def sim3_vectors(draw, angle=None):
    """7-vectors with translations up to 200 mm, any axis, angles spanning [0, pi) with extra
    weight on the delicate ends (near 0 and near pi), scales in [0.5, 2]."""
    t = np.array(draw(st.lists(st.floats(-200, 200), min_size=3, max_size=3)))
    axis = np.array(draw(st.lists(st.floats(-1, 1), min_size=3, max_size=3)))
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 0.0, 1.0])
    axis /= np.linalg.norm(axis)
    if angle is None:
        angle = draw(
            st.one_of(
                st.floats(0.0, np.pi - 1e-6),
                st.floats(0.0, 1e-3),  # near the identity (Taylor branches)
                st.floats(1e-12, 1e-6),
                st.floats(np.pi - 1e-3, np.pi - 1e-7),  # near pi
            )
        )
    log_s = draw(st.floats(np.log(0.5), np.log(2.0)))
    return np.concatenate([t, axis * angle, [log_s]])


@given(sim3_vectors())
def test_log_of_exp_is_identity(b):
    np.testing.assert_allclose(tf.sim3_log(tf.sim3_exp(b)), b, atol=TOL, rtol=0)


@given(sim3_vectors())
def test_exp_of_log_is_identity(b):
    T = tf.sim3_exp(b)
    np.testing.assert_allclose(tf.sim3_exp(tf.sim3_log(T)), T, atol=TOL, rtol=0)


@given(sim3_vectors(angle=np.pi))
def test_exp_of_log_at_exactly_pi(b):
    # At pi the rotation vector's sign is ambiguous, but the transform must come back.
    T = tf.sim3_exp(b)
    np.testing.assert_allclose(tf.sim3_exp(tf.sim3_log(T)), T, atol=TOL, rtol=0)
    np.testing.assert_allclose(np.linalg.norm(tf.sim3_log(T)[3:6]), np.pi, atol=1e-7)


@given(sim3_vectors())
def test_exp_matches_scipy_expm_of_generator(b):
    np.testing.assert_allclose(tf.sim3_exp(b), expm(tf.hat(b)), atol=TOL, rtol=0)


@given(sim3_vectors())
def test_rotation_part_matches_scipy_rotation(b):
    T = tf.sim3_exp(b)
    s = np.exp(b[6])
    np.testing.assert_allclose(T[:3, :3] / s, Rotation.from_rotvec(b[3:6]).as_matrix(), atol=TOL)
    np.testing.assert_allclose(tf.scale_of(T), s, rtol=1e-12)


@given(sim3_vectors())
def test_rotvec_conversions_match_scipy(b):
    r = b[3:6]
    R = tf.matrix_from_rotvec(r)
    np.testing.assert_allclose(R, Rotation.from_rotvec(r).as_matrix(), atol=1e-12)
    got = tf.rotvec_from_matrix(R)
    ref = Rotation.from_matrix(R).as_rotvec()
    if np.linalg.norm(r) < np.pi - 1e-6:  # away from pi the vector is unique
        np.testing.assert_allclose(got, ref, atol=TOL)
    np.testing.assert_allclose(tf.matrix_from_rotvec(got), R, atol=1e-12)


def test_translation_is_coupled_through_v():
    # Rotation about z by theta, no scale: V t for t along x is ((sin th)/th, (1-cos th)/th, 0).
    theta = 0.7
    T = tf.sim3_exp([1.0, 0, 0, 0, 0, theta, 0])
    np.testing.assert_allclose(
        T[:3, 3], [np.sin(theta) / theta, (1 - np.cos(theta)) / theta, 0], atol=1e-15
    )
    # Pure scale: V = (s - 1) / log s.
    T = tf.sim3_exp([2.0, 0, 0, 0, 0, 0, np.log(3.0)])
    np.testing.assert_allclose(T[:3, 3], [2.0 * 2 / np.log(3.0), 0, 0], atol=1e-14)
    # The generators of equation 4b alone give equations 2a-2c.
    np.testing.assert_allclose(tf.sim3_exp([1, 2, 3, 0, 0, 0, 0])[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(tf.sim3_exp([0, 0, 0, 0, 0, 0, np.log(2)])[:3, :3], 2 * np.eye(3))


def test_hat_vee_round_trip_and_generators():
    rng = np.random.default_rng(1)
    b = rng.normal(size=(5, 7))
    np.testing.assert_array_equal(tf.vee(tf.hat(b)), b)
    # Equation 4b, entries written as [row, col] (the paper's text swaps the words).
    B = tf.hat(np.eye(7))
    assert B[0, 0, 3] == B[1, 1, 3] == B[2, 2, 3] == 1
    assert B[3, 2, 1] == B[4, 0, 2] == B[5, 1, 0] == 1
    assert B[3, 1, 2] == B[4, 2, 0] == B[5, 0, 1] == -1
    np.testing.assert_array_equal(B[6], np.diag([1.0, 1, 1, 0]))


def test_batched_shapes():
    rng = np.random.default_rng(2)
    b = rng.normal(size=(2, 3, 7)) * [10, 10, 10, 0.5, 0.5, 0.5, 0.1]
    T = tf.sim3_exp(b)
    assert T.shape == (2, 3, 4, 4)
    np.testing.assert_allclose(tf.sim3_log(T), b, atol=TOL)
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(T[i, j], tf.sim3_exp(b[i, j]), atol=1e-14)
    assert tf.distance(T[0], T[1]).shape == (3,)
    assert tf.apply(T, np.zeros((2, 3, 5, 3))).shape == (2, 3, 5, 3)


@given(sim3_vectors())
def test_se3_is_the_unit_scale_case(b):
    xi = b[:6]
    T = tf.se3_exp(xi)
    np.testing.assert_allclose(T, tf.sim3_exp(np.append(xi, 0.0)), atol=1e-15)
    np.testing.assert_allclose(tf.se3_log(T), xi, atol=TOL)
    np.testing.assert_allclose(np.linalg.det(T[:3, :3]), 1.0, atol=1e-12)


@given(sim3_vectors(), sim3_vectors())
def test_compose_inverse_and_distance(b1, b2):
    T1, T2 = tf.sim3_exp(b1), tf.sim3_exp(b2)
    np.testing.assert_allclose(tf.invert(T1) @ T1, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(tf.invert(T1 @ T2), tf.invert(T2) @ tf.invert(T1), atol=1e-9)
    np.testing.assert_allclose(tf.invert(T1), np.linalg.inv(T1), atol=1e-9)
    assert tf.distance(T1, T1) < 1e-9
    # Left invariance of the geodesic distance: D(G T1, G T2) = D(T1, T2).
    G = tf.sim3_exp([5.0, -3.0, 2.0, 0.3, -0.2, 0.1, 0.2])
    np.testing.assert_allclose(tf.distance(G @ T1, G @ T2), tf.distance(T1, T2), atol=1e-7)


def test_distance_closed_forms():
    t = tf.from_params([3.0, 4.0, 0.0], [0, 0, 0])
    assert tf.distance(np.eye(4), t) == pytest.approx(5.0)
    r = tf.from_params([0, 0, 0], [0, 0.4, 0])
    assert tf.distance(np.eye(4), r) == pytest.approx(0.4)
    s = tf.from_params([0, 0, 0], [0, 0, 0], np.log(1.5))
    assert tf.distance(s, np.eye(4)) == pytest.approx(np.log(1.5))
    w = tf.distance(np.eye(4), r, weights=[1, 1, 1, 100, 100, 100, 100])
    assert w == pytest.approx(40.0)


@given(sim3_vectors())
def test_decoupled_params_round_trip(b):
    t, r, ls = b[:3], b[3:6], b[6]
    T = tf.from_params(t, r, ls)
    np.testing.assert_allclose(T[:3, 3], t)  # translation used as is, unlike exp
    t2, r2, ls2 = tf.to_params(T)
    np.testing.assert_allclose(tf.from_params(t2, r2, ls2), T, atol=TOL)
    np.testing.assert_allclose(ls2, ls, atol=1e-12)


@pytest.mark.parametrize("seq", ["ZXY", "xyz", "ZYX"])
def test_euler_round_trip(seq):
    rng = np.random.default_rng(3)
    angles = rng.uniform(-60, 60, size=(20, 3))
    R = tf.matrix_from_euler(seq, angles, degrees=True)
    np.testing.assert_allclose(tf.euler_from_matrix(seq, R, degrees=True), angles, atol=1e-9)
    np.testing.assert_allclose(R, Rotation.from_euler(seq, angles, degrees=True).as_matrix())


def test_apply_matches_homogeneous_product():
    rng = np.random.default_rng(4)
    T = tf.sim3_exp([10, -5, 3, 0.2, 0.1, -0.3, 0.1])
    p = rng.normal(size=(7, 3)) * 50
    h = np.hstack([p, np.ones((7, 1))]) @ T.T
    np.testing.assert_allclose(tf.apply(T, p), h[:, :3], atol=1e-12)


# ---- bad input ---------------------------------------------------------------------------------


def test_log_rejects_non_finite():
    T = np.eye(4)
    T[1, 3] = np.nan
    with pytest.raises(ValueError, match="NaN or infinity"):
        tf.se3_log(T)
    with pytest.raises(ValueError, match="NaN or infinity"):
        tf.sim3_exp([0, 0, np.inf, 0, 0, 0, 0])


def test_se3_log_rejects_non_rigid():
    shear = np.eye(4)
    shear[0, 1] = 0.2
    with pytest.raises(ValueError, match="shear or anisotropic scale"):
        tf.se3_log(shear)
    aniso = np.diag([1.0, 2.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="not a similarity"):
        tf.sim3_log(aniso)
    scaled = np.diag([2.0, 2.0, 2.0, 1.0])
    with pytest.raises(ValueError, match="not rigid: its scale is 2"):
        tf.se3_log(scaled)
    reflection = np.diag([-1.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="reflection"):
        tf.se3_log(reflection)
    projective = np.eye(4)
    projective[3, 0] = 0.1
    with pytest.raises(ValueError, match="last row"):
        tf.sim3_log(projective)


def test_batched_error_names_the_bad_matrix():
    T = np.tile(np.eye(4), (3, 1, 1))
    T[2, 0, 1] = 0.5
    with pytest.raises(ValueError, match=r"T\[2\]"):
        tf.sim3_log(T)


def test_wrong_shapes():
    with pytest.raises(ValueError, match=r"\(\.\.\., 7\)"):
        tf.sim3_exp([1, 2, 3])
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 4\)"):
        tf.sim3_log(np.eye(3))
    with pytest.raises(ValueError, match="not orthonormal"):
        tf.rotvec_from_matrix(np.diag([1.0, 1.0, 1.1]))
    with pytest.raises(ValueError, match=r"weights must have shape \(7,\)"):
        tf.distance(np.eye(4), np.eye(4), weights=[1, 1])
