"""Residual reduction: closed forms and the anatomical reading."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.guide.residual import residual_reduction


def test_residual_moves_the_bone_onto_the_target():
    rng = np.random.default_rng(0)
    T_O = tf.se3_exp(rng.normal(size=6) * [20, 20, 20, 0.2, 0.2, 0.2])
    T_X = tf.se3_exp(rng.normal(size=6) * [20, 20, 20, 0.2, 0.2, 0.2])
    T_t = tf.se3_exp(rng.normal(size=6) * [5, 5, 5, 0.05, 0.05, 0.05])
    r = residual_reduction(T_O, T_X, T_t, [10.0, 20.0, -30.0])
    np.testing.assert_allclose(r.transform @ T_X, T_O @ T_t, atol=1e-9)


def test_reduced_bone_has_no_residual():
    T_O = tf.from_params([5.0, 0, 0], [0.1, 0.2, 0.0])
    T_t = tf.from_params([3.0, -2.0, 1.0], [0.0, 0.05, 0.0])
    r = residual_reduction(T_O, T_O @ T_t, T_t, [0.0, 0.0, 0.0])
    assert r.distance_mm < 1e-9
    assert r.angle_deg < 1e-7
    assert r.describe() == "reduced: no residual motion"


def test_translation_is_read_in_patient_axes_whatever_the_setup():
    # The patient lies rotated 90 deg about the vertical axis under the C-arm; the bone must still
    # move 4 mm to the patient's left and 2 mm superior.
    setup = tf.from_params([100.0, 50.0, 0.0], [0.0, 0.0, np.pi / 2])
    plan = tf.from_params([4.0, 0.0, 2.0], [0.0, 0.0, 0.0])
    r = residual_reduction(setup, setup, plan, [60.0, -20.0, -400.0])
    np.testing.assert_allclose(r.translation_mm, [4.0, 0.0, 2.0], atol=1e-9)
    np.testing.assert_allclose(r.rotation_deg, 0.0, atol=1e-9)
    assert r.describe() == "move 4.0 mm left, 2.0 mm superior"


def test_rotation_about_the_centroid():
    centroid = np.array([70.0, -30.0, -400.0])
    turn = tf.from_params(centroid - tf.matrix_from_rotvec([0, 0, 0.1]) @ centroid, [0, 0, 0.1])
    r = residual_reduction(np.eye(4), np.eye(4), turn, centroid)
    np.testing.assert_allclose(r.translation_mm, 0.0, atol=1e-9)
    np.testing.assert_allclose(r.rotation_deg, [0, 0, np.degrees(0.1)], atol=1e-9)
    assert "about the superior-inferior axis" in r.describe()


def test_bad_poses():
    with pytest.raises(ValueError, match="dislocated pose: .*not rigid"):
        residual_reduction(np.eye(4), np.diag([2.0, 2, 2, 1]), np.eye(4), [0, 0, 0])
    nan = np.eye(4)
    nan[0, 3] = np.nan
    with pytest.raises(ValueError, match="observed pose: .*NaN"):
        residual_reduction(nan, np.eye(4), np.eye(4), [0, 0, 0])
