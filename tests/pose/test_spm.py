"""Statistical pose model: PGA recovers known pose modes; exp/log round trips."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.pose.spm import PoseModel, frechet_mean
from pelvicnav.pose.target import solve_weights


def test_pga_recovers_known_modes(pose_population):
    V, _, modes, b = pose_population
    model = PoseModel.fit(V, frame_bones=("sacrum",), metric="plain")
    # Two generating modes: the rest of the spectrum is numerically empty.
    assert model.n_modes == 2 or model.variances[2] < 1e-4 * model.variances[1]
    # The fitted principal subspace is the generating one (cosines of principal angles ~ 1).
    cos = np.linalg.svd(modes.T @ model.modes[:, :2], compute_uv=False)
    assert cos.min() > 0.999
    # The per-subject tangent vectors are the generating ones (up to the common mean).
    np.testing.assert_allclose(model.training - model.mean, b - b.mean(axis=0), atol=0.05)


def test_tangent_round_trip(pose_population):
    V, *_ = pose_population
    model = PoseModel.fit(V, frame_bones=("sacrum", "right_hip"))
    # exp(log) through the model: poses from a subject's vector reproduce its fitted poses.
    n = 4
    G = model.normalised_from_subject(V[n, [0, 2]])
    for l, bone in enumerate(("sacrum", "left_hip", "right_hip")):
        x = model.tangent(bone, tf.apply(G, V[n, l]))
        np.testing.assert_allclose(x, model.training[n, 7 * l : 7 * l + 7], atol=1e-9)
    poses = model.poses_from_vector(model.training[n])
    for l in range(3):
        placed = tf.apply(poses[l], model.mean_shapes[l])
        # The model's mean shape placed by the subject's pose lies on the subject's bone.
        assert np.sqrt(np.mean(np.sum((placed - tf.apply(G, V[n, l])) ** 2, -1))) < 0.5


def test_all_bones_observed_returns_own_pose(pose_population):
    V, *_ = pose_population
    model = PoseModel.fit(V, frame_bones=("sacrum",))
    for n in (0, 7, 19):
        v = solve_weights(model.training[n] - model.mean, model.modes, model.variances, prior=1e-12)
        np.testing.assert_allclose(model.mean + model.modes @ v, model.training[n], atol=1e-6)
        np.testing.assert_allclose(
            model.poses_from_vector(model.mean + model.modes @ v),
            model.poses_from_vector(model.training[n]),
            atol=1e-6,
        )


def test_trust_region_matches_closed_form():
    rng = np.random.default_rng(0)
    P = np.linalg.qr(rng.normal(size=(14, 6)))[0]
    lam = np.array([9.0, 4.0, 2.0, 1.0, 0.1, 0.01])
    r = rng.normal(size=14)
    for prior in (0.0, 0.1, 10.0):
        a = solve_weights(r, P, lam, prior=prior, method="trust-ncg")
        b = solve_weights(r, P, lam, prior=prior, method="direct")
        np.testing.assert_allclose(a, b, atol=1e-8)


def test_frechet_mean_of_symmetric_set_is_the_centre():
    centre = tf.sim3_exp([5.0, 1.0, -2.0, 0.1, 0.2, 0.3, 0.05])
    d = np.array([[3.0, 0, 0, 0, 0.2, 0, 0.1]])
    T = np.concatenate([centre @ tf.sim3_exp(d), centre @ tf.sim3_exp(-d)])
    np.testing.assert_allclose(frechet_mean(T), centre, atol=1e-10)


def test_bad_input(pose_population):
    V, *_ = pose_population
    with pytest.raises(ValueError, match="unknown frame bone 'femur'"):
        PoseModel.fit(V, frame_bones=("femur",))
    with pytest.raises(ValueError, match="at most 29 modes"):
        PoseModel.fit(V, n_modes=40)
    with pytest.raises(ValueError, match="n_subjects, 3, n_vertices, 3"):
        PoseModel.fit(V[:, :2])
    bad = V.copy()
    bad[3, 1, 5, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        PoseModel.fit(bad)
    with pytest.raises(ValueError, match="metric"):
        PoseModel.fit(V, metric="euclid")
