"""`--dislocated auto`: the side of a simulated dislocation, "none" for an intact pelvis, and a
given side overriding the decision. (The leave-one-out measure: docs/workflow.md.)"""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.model import load_model
from pelvicnav.phantom.dislocate import draw_dislocation
from pelvicnav.phantom.sampled import sampled_population
from pelvicnav.workflow.plan import decide_dislocated


@pytest.fixture(scope="module")
def patients():
    model = load_model()
    return model, sampled_population(seed=11, subject_ids=(1, 2, 3)).vertices


def test_intact_pelvises_are_not_dislocated(patients):
    model, V = patients
    for subject in V:
        decision, targets = decide_dislocated(dict(zip(BONES, subject, strict=True)), model)
        assert decision.dislocated == () and targets == {}, decision.describe()
        assert decision.margin < 0


@pytest.mark.parametrize("bone", ["left_hip", "right_hip"])
def test_a_dislocated_hip_is_found(patients, bone):
    model, V = patients
    rng = np.random.default_rng(3)
    for subject in V:
        d = draw_dislocation(subject, model.faces, bone=bone, pattern="open-book", rng=rng,
                             max_mm=15.0)  # fmt: skip
        d_big = tf.se3_exp(tf.se3_log(d.transform) * max(1.0, 10.0 / d.translation_mm))
        W = subject.copy()
        W[BONES.index(bone)] = tf.apply(d_big, W[BONES.index(bone)])
        decision, targets = decide_dislocated(dict(zip(BONES, W, strict=True)), model)
        assert decision.dislocated == (bone,), decision.describe()
        assert decision.margin > 0 and decision.side_margin > 0
        c = W[BONES.index(bone)].mean(axis=0)
        back = tf.apply(targets[bone], c[None])[0]
        truth = tf.apply(tf.invert(d_big), c[None])[0]
        assert np.linalg.norm(back - truth) < np.linalg.norm(c - truth)  # towards the truth


def test_a_given_side_overrides(patients):
    model, V = patients
    meshes = dict(zip(BONES, V[0], strict=True))
    decision, targets = decide_dislocated(meshes, model, "right_hip")
    assert decision.dislocated == ("right_hip",) and decision.mode == "given"
    assert set(targets) == {"right_hip"}
    decision, targets = decide_dislocated(meshes, model, "both")
    assert set(targets) == {"left_hip", "right_hip"}
    with pytest.raises(ValueError, match="--dislocated must be"):
        decide_dislocated(meshes, model, "sacrum")
