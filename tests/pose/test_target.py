"""Target-pose estimation: no leak of the dislocated bone's pose, collision refinement, errors."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.pose.collision import joint_gaps, ray_triangle_distances
from pelvicnav.pose.target import TargetEstimate, TargetPlanner

BONES = ("sacrum", "left_hip", "right_hip")


@pytest.fixture(scope="module")
def planner_case(pose_population):
    V, faces, *_ = pose_population
    planner = TargetPlanner.fit(V[1:], faces, observed=("sacrum", "right_hip"), prior=0.1)
    return planner, V[0], faces


def test_estimate_ignores_where_the_dislocated_bone_is(planner_case):
    planner, subject, _ = planner_case
    observed = {"sacrum": subject[0], "right_hip": subject[2]}
    rng = np.random.default_rng(5)
    results = []
    for _ in range(3):
        D = tf.from_params(rng.uniform(-20, 20, 3), np.deg2rad(rng.uniform(-10, 10, 3)))
        est = planner.estimate(observed, {"left_hip": tf.apply(D, subject[1])})
        results.append(est["left_hip"].vertices)
    # Only the observed bones decide the target: moving the dislocated bone changes nothing.
    np.testing.assert_allclose(results[1], results[0], atol=1e-8)
    np.testing.assert_allclose(results[2], results[0], atol=1e-8)


def test_estimate_changes_with_the_observed_bones(planner_case):
    planner, subject, _ = planner_case
    a = planner.estimate({"sacrum": subject[0], "right_hip": subject[2]}, {"left_hip": subject[1]})
    shifted = tf.apply(tf.from_params([0, 0, 5.0], [0, 0, 0]), subject[2])
    b = planner.estimate({"sacrum": subject[0], "right_hip": shifted}, {"left_hip": subject[1]})
    assert np.abs(a["left_hip"].vertices - b["left_hip"].vertices).max() > 0.1


def test_estimate_is_accurate_on_a_population_with_known_modes(pose_population):
    V, faces, *_ = pose_population
    errors = []
    for n in range(5):
        train = np.delete(V, n, axis=0)
        planner = TargetPlanner.fit(train, faces, observed=("sacrum", "right_hip"), prior=0.01)
        est = planner.estimate(
            {"sacrum": V[n, 0], "right_hip": V[n, 2]}, {"left_hip": V[n, 1]}, refine="none"
        )
        errors.append(np.linalg.norm(est["left_hip"].vertices - V[n, 1], axis=1).mean())
    # Two pose modes, both seen through the right hip: the left hip follows (mm).
    assert np.median(errors) < 0.5


def test_collision_refinement_removes_overlap_and_keeps_clean_cases(planner_case):
    planner, subject, faces = planner_case
    observed = {"sacrum": subject[0], "right_hip": subject[2]}
    true_left = subject[1]
    joint = planner.joints[("sacrum", "left_hip")]

    def si_gaps(left):
        return joint_gaps(left, faces[1], joint.vertices[1], subject[0], faces[0], joint.faces[0])

    clean = TargetEstimate("left_hip", np.eye(4), true_left, true_left)
    refined = planner._refine({"left_hip": clean}, observed)["left_hip"]
    np.testing.assert_array_equal(refined.refinement, np.zeros(3))
    np.testing.assert_array_equal(refined.vertices, true_left)

    # Push the left hip 4 mm into the sacrum (towards +y, posterior): it must come back out.
    push = tf.from_params([0.0, 4.0, 0.0], [0, 0, 0])
    colliding = TargetEstimate("left_hip", push, tf.apply(push, true_left), true_left)
    before = si_gaps(colliding.vertices)
    assert np.nanmin(before) < planner.min_gap[(("sacrum", "left_hip"), "left_hip")] - 1.0
    refined = planner._refine({"left_hip": colliding}, observed)["left_hip"]
    after = si_gaps(refined.vertices)
    min_gap = planner.min_gap[(("sacrum", "left_hip"), "left_hip")]
    assert np.nanquantile(after, planner.gap_quantile) >= min_gap - 0.02
    assert 0.5 < np.linalg.norm(refined.refinement) < 6.0
    np.testing.assert_allclose(refined.target_from_current[:3, 3], push[:3, 3] + refined.refinement)


def test_ray_triangle_distances_closed_form():
    tri = np.array([[[0.0, 0, 5], [10, 0, 5], [0, 10, 5]]])
    o = np.array([[1.0, 1, 0], [1.0, 1, 8], [20.0, 20, 0]])
    d = np.array([[0.0, 0, 1], [0.0, 0, 1], [0.0, 0, 1]])
    t = ray_triangle_distances(o, d, tri)
    np.testing.assert_allclose(t[:2], [5.0, -3.0])
    assert np.isnan(t[2])


def test_bad_input(pose_population, planner_case):
    V, faces, *_ = pose_population
    with pytest.raises(ValueError, match="all bones are marked dislocated"):
        TargetPlanner.fit(V, faces, observed=())
    with pytest.raises(ValueError, match="unknown observed bone 'coccyx'"):
        TargetPlanner.fit(V, faces, observed=("coccyx",))
    with pytest.raises(ValueError, match="no bone is marked dislocated"):
        TargetPlanner.fit(V, faces, observed=BONES)
    with pytest.raises(ValueError, match="at most 29 modes"):
        TargetPlanner.fit(V, faces, observed=("sacrum",), n_modes=35)
    planner, subject, _ = planner_case
    with pytest.raises(
        ValueError, match=r"observed bones must be exactly \['sacrum', 'right_hip'\]"
    ):
        planner.estimate({"sacrum": subject[0]}, {"left_hip": subject[1]})
    with pytest.raises(ValueError, match="dislocated mesh left_hip must have shape"):
        planner.estimate(
            {"sacrum": subject[0], "right_hip": subject[2]}, {"left_hip": subject[1, :5]}
        )
    with pytest.raises(ValueError, match="unknown dislocated bone 'femur'"):
        planner.estimate({"sacrum": subject[0], "right_hip": subject[2]}, {"femur": subject[1]})
