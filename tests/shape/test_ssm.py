"""Generalised Procrustes and shape models: recover known shapes, modes and partial fits."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.shape.ssm import ShapeModel, generalized_procrustes


def _population(n=40, nv=60, k=3, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(nv, 3)) * 30
    modes, _ = np.linalg.qr(rng.normal(size=(3 * nv, k)))
    sd = np.array([6.0, 3.0, 1.5])[:k]
    w = rng.normal(size=(n, k)) * sd
    shapes = base + (w @ modes.T).reshape(n, nv, 3)
    return base, modes, sd, shapes, rng


def test_gpa_removes_similarity_transforms():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(100, 3)) * 30
    Ts = tf.sim3_exp(rng.normal(size=(10, 7)) * [50, 50, 50, 1, 1, 1, 0.2])
    shapes = tf.apply(Ts, np.broadcast_to(base, (10, 100, 3)))
    res = generalized_procrustes(shapes, scale=True)
    assert np.abs(res.aligned - res.mean).max() < 1e-8
    # The mean is the base shape up to a similarity, in mm (mean centroid size of the inputs).
    size = np.sqrt(np.sum((shapes - shapes.mean(axis=1, keepdims=True)) ** 2, axis=(1, 2)))
    np.testing.assert_allclose(np.sqrt(np.sum(res.mean**2)), size.mean(), rtol=1e-9)
    np.testing.assert_allclose(res.mean.mean(axis=0), 0, atol=1e-9)


def test_shape_model_recovers_modes_and_variances():
    base, modes, sd, shapes, _ = _population(n=400)
    m = ShapeModel.fit(shapes, align="none")
    assert m.n_modes == 3
    np.testing.assert_allclose(np.sqrt(m.variances), sd, rtol=0.15)
    cos = np.linalg.svd(modes.T @ m.modes, compute_uv=False)
    assert cos.min() > 0.999
    np.testing.assert_allclose(m.mean, shapes.mean(axis=0))
    # Projection and instance are inverse on the model's span.
    w = np.array([1.0, -2.0, 0.5])
    np.testing.assert_allclose(m.project(m.instance(w)), w, atol=1e-9)


def test_fit_partial_predicts_unobserved_vertices():
    base, modes, sd, shapes, rng = _population(n=60)
    m = ShapeModel.fit(shapes[:-1], align="similarity")
    truth = shapes[-1]
    T = tf.sim3_exp([20.0, -10.0, 5.0, 0.2, 0.1, -0.3, 0.1])
    observed = np.arange(40)  # 40 of 60 vertices seen, in another frame
    fit = m.fit_partial(tf.apply(T, truth[observed]), observed, noise_variance=1e-4)
    predicted = tf.apply(tf.invert(T), fit.vertices)
    hidden_err = np.linalg.norm(predicted[40:] - truth[40:], axis=1).max()
    assert hidden_err < 0.05  # mm, against shape variation of several mm
    assert fit.rms < 0.05


def test_bad_input():
    _, _, _, shapes, _ = _population(n=5)
    with pytest.raises(ValueError, match="at most 4 modes"):
        ShapeModel.fit(shapes, n_modes=10)
    with pytest.raises(ValueError, match="align must be"):
        ShapeModel.fit(shapes, align="affine")
    with pytest.raises(ValueError, match=r"shape \(n_shapes, n_vertices, 3\)"):
        ShapeModel.fit(shapes[0])
    with pytest.raises(ValueError, match="at least 2 shapes"):
        generalized_procrustes(shapes[:1])
    m = ShapeModel.fit(shapes)
    with pytest.raises(ValueError, match="out of range"):
        m.fit_partial(np.zeros((2, 3)), [0, 999])
    with pytest.raises(ValueError, match="weights must have shape"):
        m.instance(np.zeros(9))
