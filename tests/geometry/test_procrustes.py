"""Procrustes fits recover known transforms."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform, rms_distance


@pytest.mark.parametrize("scale", [False, True])
def test_recovers_known_transform(scale):
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3)) * 40
    T = tf.from_params([10.0, -20.0, 5.0], [0.3, -0.2, 1.1], np.log(1.3) if scale else 0.0)
    dst = tf.apply(T, src)
    np.testing.assert_allclose(fit_transform(src, dst, scale=scale), T, atol=1e-10)
    assert rms_distance(tf.apply(fit_transform(src, dst, scale=scale), src), dst) < 1e-9


def test_batched_broadcast_and_weights():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3)) * 10
    Ts = tf.se3_exp(rng.normal(size=(4, 6)) * [5, 5, 5, 0.3, 0.3, 0.3])
    dst = tf.apply(Ts, np.broadcast_to(src, (4, 20, 3)))
    np.testing.assert_allclose(fit_transform(src[None], dst), Ts, atol=1e-10)
    # Zero weight on corrupted points: they are ignored.
    bad = dst[0].copy()
    bad[:5] += 100.0
    w = np.r_[np.zeros(5), np.ones(15)]
    np.testing.assert_allclose(fit_transform(src, bad, weights=w), Ts[0], atol=1e-10)


def test_never_returns_a_reflection():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(30, 3))
    mirrored = src * [-1, 1, 1]
    T = fit_transform(src, mirrored)
    assert np.linalg.det(T[:3, :3]) > 0


def test_bad_input():
    with pytest.raises(ValueError, match="at least 3"):
        fit_transform(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., n, 3\)"):
        fit_transform(np.zeros((5, 3)), np.zeros((6, 3)))
    with pytest.raises(ValueError, match="coincident"):
        fit_transform(np.ones((5, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="collinear"):
        line = np.outer(np.arange(5.0), [1, 2, 3])
        fit_transform(line, line)
    x = np.random.default_rng(0).normal(size=(5, 3))
    with pytest.raises(ValueError, match="NaN"):
        fit_transform(x, np.where(x > 1, np.nan, x))
    with pytest.raises(ValueError, match="non-negative"):
        fit_transform(x, x, weights=-np.ones(5))
