"""Building the model: planners from the file equal planners fitted on the same subjects."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.model import build_model, load_model, save_model
from pelvicnav.pose.target import TargetPlanner


def _dislocated(V, observed, seed):
    from pelvicnav.studies.target_pose import random_dislocation

    rng = np.random.default_rng(seed)
    obs = {b: V[BONES.index(b)] for b in observed}
    current = {}
    for b in BONES:
        if b not in observed:
            D, _, _ = random_dislocation(rng, V[BONES.index(b)].mean(axis=0), 20.0, 10.0)
            current[b] = tf.apply(D, V[BONES.index(b)])
    return obs, current


def _pose_difference(a, b):
    d = tf.invert(a) @ b
    return np.linalg.norm(d[:3, 3]), np.degrees(np.linalg.norm(tf.rotvec_from_matrix(d[:3, :3])))


@pytest.mark.atlas
def test_packaged_planners_equal_planners_fitted_on_the_atlas(real_atlas_path):
    from pelvicnav.io.atlas import load_atlas

    real_atlas = load_atlas(real_atlas_path)
    model = load_model()
    assert model.subject_ids == real_atlas.subject_ids
    prior = model.provenance["planner_prior"]
    # A pelvis the model never saw: an atlas subject deformed, so the estimate is non-trivial.
    test = real_atlas.vertices[7] * 1.03
    for observed in (("sacrum", "right_hip"), ("sacrum",)):
        fitted = TargetPlanner.fit(real_atlas.vertices, model.faces, observed=observed, prior=prior)
        obs, current = _dislocated(test, observed, seed=3)
        ours = model.planner(observed).estimate(obs, current)
        theirs = fitted.estimate(obs, current)
        for bone, est in ours.items():
            mm, deg = _pose_difference(est.target_from_current, theirs[bone].target_from_current)
            assert mm <= 0.05 and deg <= 0.05, (observed, bone, mm, deg)


def test_build_model_on_a_synthetic_population_round_trips(tmp_path):
    from helpers.synthetic import make_population
    from pelvicnav.io.atlas import Atlas

    V, faces, *_ = make_population(12, seed=2, shape_sd=0.01)
    atlas = Atlas(subject_ids=tuple(range(1, 13)), vertices=V, faces=faces, source="synthetic")
    model = build_model(atlas, variance_kept=0.95)
    assert model.subject_ids == atlas.subject_ids
    again = load_model(save_model(model, tmp_path / "m.npz"))
    obs, current = _dislocated(V[0] * 1.01, ("sacrum", "left_hip"), seed=1)
    direct = TargetPlanner.fit(V, model.faces, observed=("sacrum", "left_hip"), prior=0.1)
    a = again.planner(("sacrum", "left_hip")).estimate(obs, current)["right_hip"]
    b = direct.estimate(obs, current)["right_hip"]
    mm, deg = _pose_difference(a.target_from_current, b.target_from_current)
    assert mm <= 0.05 and deg <= 0.05
    total = sum(np.sum(s.variances) for s in model.shapes.values())
    assert total > 0
    with pytest.raises(ValueError, match="variance_kept"):
        build_model(atlas, variance_kept=1.5)
    with pytest.raises(ValueError, match="at least 10 subjects"):
        build_model(atlas.subset(range(5)))
