"""Exact gradients for the local refinement: the gradient NCC's image gradient and the splat's
adjoint against finite differences, and the L-BFGS refinement recovering a known pose."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from tests.helpers.bodies import blob, views_4x

from pelvicnav.drr.splat import splat, splat_pullback
from pelvicnav.geometry import transforms as tf
from pelvicnav.metrics.similarity import GradientNCC, gradient_ncc
from pelvicnav.register.gradient import GradientProblem, left_jacobian, refine_gradient
from pelvicnav.register.initial import best_shift, initial_translation


def test_gradient_ncc_image_gradient_matches_central_differences():
    rng = np.random.default_rng(0)
    fixed = gaussian_filter(rng.normal(size=(30, 41)), 2)
    moving = gaussian_filter(rng.normal(size=(30, 41)), 2) + 0.5 * fixed
    value, grad = GradientNCC(fixed).value_and_gradient(moving)
    assert value == pytest.approx(gradient_ncc(fixed, moving), abs=1e-12)
    h = 1e-6
    for r, c in [(0, 0), (0, 40), (29, 17), (12, 0), (15, 20)]:  # corners, edges, inside
        up, down = moving.copy(), moving.copy()
        up[r, c] += h
        down[r, c] -= h
        fd = (gradient_ncc(fixed, up) - gradient_ncc(fixed, down)) / (2 * h)
        assert grad[r, c] == pytest.approx(fd, rel=1e-5, abs=1e-10)


def test_left_jacobian_is_the_derivative_of_the_rotation():
    r = np.array([0.3, -0.5, 0.2])
    dr = np.array([1e-6, 2e-6, -1e-6])
    R = tf.matrix_from_rotvec
    W = (R(r + dr) - R(r - dr)) @ R(r).T / 2  # [J dr]x to first order
    w = np.array([W[2, 1], W[0, 2], W[1, 0]])
    np.testing.assert_allclose(w, left_jacobian(r) @ dr, rtol=1e-6, atol=1e-14)


def test_splat_pullback_matches_finite_differences_of_a_linear_scalar():
    rng = np.random.default_rng(1)
    models = [blob([0, 0, 0], 4000, rng), blob([45, 10, 5], 3000, rng)]
    Ps, shape = views_4x(), (128, 128)
    T = np.stack([tf.from_params([1, 2, 3], [0.05, 0.02, -0.03]),
                  tf.from_params([-2, 0, 1], [0.0, 0.04, 0.01])])  # fmt: skip
    G = np.stack([gaussian_filter(rng.normal(size=shape), 4) for _ in range(2)])

    def S(T):
        return float(np.sum(splat(models, T[None], Ps, shape)[0].astype(np.float64) * G))

    wrench = splat_pullback(models, T, Ps, G)
    h = 2e-3
    for bone in range(2):
        fd = np.empty(6)
        for k in range(6):
            d = np.zeros(6)
            d[k] = h
            Tp, Tm = T.copy(), T.copy()
            Tp[bone] = tf.from_params(d[:3], d[3:]) @ T[bone]  # X -> X + t + w x X
            Tm[bone] = tf.from_params(-d[:3], -d[3:]) @ T[bone]
            fd[k] = (S(Tp) - S(Tm)) / (2 * h)
        np.testing.assert_allclose(wrench[bone], fd, rtol=0.05, atol=0.02 * np.abs(fd).max())


def test_refinement_recovers_a_known_pose_of_two_bodies(two_bodies):
    renderer, levels, truth = two_bodies
    moves = [tf.from_params([2.0, -1.5, 1.0], [0.0, 0.02, 0.0]),
             tf.from_params([-1.5, 0.5, 2.0], [0.02, 0.0, -0.02])]  # fmt: skip
    start = np.stack([m @ truth[b] for m, b in zip(moves, renderer.bones, strict=True)])
    centres = np.stack([tf.apply(start[i], renderer.centroid(b)[None])[0]
                        for i, b in enumerate(renderer.bones)])  # fmt: skip
    y = np.zeros(12)
    for lv in levels:
        problem = GradientProblem(renderer, lv, start, centres, y, (0, 1))
        box = np.full(12, 20.0)
        res = refine_gradient(problem, bounds=(-box, box), iterations=60)
        y = problem.full(res.x)
    final = problem.poses(y)
    for i, b in enumerate(renderer.bones):
        c = renderer.centroid(b)[None]
        err = np.linalg.norm(tf.apply(final[i], c) - tf.apply(truth[b], c))
        assert err < 0.2, (b, err)
    assert res.converged and res.evaluations < 100


def test_best_shift_finds_a_known_shift_of_the_edges():
    rng = np.random.default_rng(6)
    base = gaussian_filter(rng.normal(size=(96, 112)), 3)
    fixed = np.roll(base, (7, -12), axis=(0, 1))  # rows down 7, columns left 12
    shift, score = best_shift(base, fixed, max_shift=30)
    np.testing.assert_array_equal(shift, [-12, 7])
    assert score > 0.6  # the shifted images overlap on about 80% of their area
    limited, _ = best_shift(base, fixed, max_shift=5)  # the true shift is outside the search
    assert np.abs(limited).max() <= 5


def test_initial_translation_brings_a_far_start_back(two_bodies):
    renderer, levels, truth = two_bodies
    bones = renderer.bones
    for offset in ([90.0, -60.0, 0.0], [0.0, 40.0, 120.0]):  # in plane; mostly along the AP beam
        away = tf.from_params(offset, [0.0, 0.0, 0.0])
        poses = np.stack([away @ truth[b] for b in bones])
        c = renderer.centroid(bones[0])
        centre = tf.apply(poses[0], c[None])[0]
        delta = initial_translation(levels[0], renderer, bones, poses, centre, max_mm=200.0)
        err = tf.apply(delta @ poses[0], c[None]) - tf.apply(truth[bones[0]], c[None])
        assert np.linalg.norm(err) < 6.0, (offset, err)
