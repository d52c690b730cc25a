"""Local refinement (closed-form quadratic) and the joint-aware prior (known interpenetration)."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.drr.renderer import SplatRenderer
from pelvicnav.drr.splat import PointModel
from pelvicnav.geometry import transforms as tf
from pelvicnav.register.local import refine_local
from pelvicnav.register.prior import joint_prior


def test_local_refinement_finds_the_minimum_of_a_coupled_quadratic():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    H = A @ A.T + 6 * np.eye(6)  # positive definite, coupled
    x_star = np.array([1.5, -0.8, 2.0, 0.5, -1.0, 0.3])

    def f(X):
        D = X - x_star
        return 0.5 * np.einsum("ni,ij,nj->n", D, H, D)

    res = refine_local(f, np.zeros(6), step=1.0, iterations=40, tol_fun=1e-10, min_step=1e-3)
    assert np.linalg.norm(res.x - x_star) < 0.05
    assert res.converged and res.evaluations == res.generations * 17
    box = np.full(6, 1.0)
    bounded = refine_local(f, np.zeros(6), iterations=40, bounds=(-box, box))
    assert np.all(np.abs(bounded.x) <= 1.0 + 1e-12)


def _slab(x0: float) -> PointModel:
    g = np.arange(0.0, 10.0, 1.0)
    pts = np.stack(np.meshgrid(g + x0, g, g, indexing="ij"), -1).reshape(-1, 3)
    return PointModel(pts, np.ones(len(pts)), 1.0)


def test_joint_prior_is_zero_at_the_ct_pose_and_penalises_interpenetration():
    # two 10 mm cubes of samples with a 5 mm gap between them (x 0-9 and 14-23)
    renderer = SplatRenderer(({"a": _slab(0.0), "b": _slab(14.0)},))
    prior = joint_prior(renderer, "b", clearance=0.6, weight=1.0)
    assert prior is not None and len(prior.points) > 0
    others = {"a": np.eye(4)}
    into = tf.from_params([-8.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # b pushed 3 mm into a
    away = tf.from_params([3.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # the joint opens
    p = prior.penalty(np.stack([np.eye(4), into, away]), others, n_views=2)
    assert p[0] == 0.0 and p[2] == 0.0
    assert p[1] > 0.1
    # a bone far from every other has no joint samples
    far = SplatRenderer(({"a": _slab(0.0), "b": _slab(100.0)},))
    assert joint_prior(far, "b") is None


def test_joint_gap_term_is_flat_within_the_slack_then_linear_in_the_opening():
    renderer = SplatRenderer(({"a": _slab(0.0), "b": _slab(14.0)},))
    prior = joint_prior(renderer, "b", clearance=0.6, weight=1.0, gap_weight=0.01, gap_slack=3.0)
    assert prior is not None
    # b's samples lie 5-14 mm from a's nearest face (x = 9): the CT's 90th percentile
    d_ct = prior.points[:, 0] - 9.0
    assert np.isclose(prior.gap_ct, np.percentile(d_ct, 90.0))
    others = {"a": np.eye(4)}
    shifts = [0.0, 1.0, 5.0, 8.0]  # b moved away from a along x (every distance grows)
    poses = np.stack([tf.from_params([s, 0.0, 0.0], [0.0, 0.0, 0.0]) for s in shifts])
    p = prior.penalty(poses, others, n_views=2)
    assert p[0] == 0.0 and p[1] == 0.0  # within the slack
    # beyond it, 2 views x 0.01 per mm (the distance field is good to about 1 mm)
    np.testing.assert_allclose(p[2:], [2 * 0.01 * 2.0, 2 * 0.01 * 5.0], atol=0.02)
    assert p[3] > p[2]
    # closing the joint costs nothing until it passes through (then the interpenetration term)
    closer = prior.penalty(tf.from_params([-3.0, 0.0, 0.0], [0.0, 0.0, 0.0])[None], others, 2)
    assert closer[0] == 0.0
    # without a gap weight the term is off whatever the opening
    off = joint_prior(renderer, "b", clearance=0.6, weight=1.0)
    assert off.gap_weight == 0.0 and np.all(off.penalty(poses, others, n_views=2) == 0.0)


def test_joint_measure_reads_interpenetration_and_opening_without_a_penalty():
    # the plausibility check (ResearchSettings.joint_limits) measures with no term in the
    # objective: the fields are built, the prior is inactive and adds nothing
    renderer = SplatRenderer(({"a": _slab(0.0), "b": _slab(14.0)},))
    prior = joint_prior(renderer, "b", clearance=0.6, weight=0.0, fields=20.0)
    assert prior is not None and prior.fields and not prior.active
    others = {"a": np.eye(4)}
    shifts = [0.0, -8.0, 6.0, 30.0]  # at the CT, 3 mm into a, opened 6 mm, opened past the cap
    poses = np.stack([tf.from_params([s, 0.0, 0.0], [0.0, 0.0, 0.0]) for s in shifts])
    inside, opening = prior.measure(poses, others)
    assert inside[0] == 0.0 and inside[2] == 0.0 and inside[1] > 0.2
    assert abs(opening[0]) < 1e-6
    assert opening[2] == pytest.approx(6.0, abs=1.0)  # the field is good to about 1 mm
    assert opening[3] > 20.0  # read up to the cap (20 mm + GAP_REACH_MM past the CT's gap)
    assert np.all(prior.penalty(poses, others, n_views=2) == 0.0)
