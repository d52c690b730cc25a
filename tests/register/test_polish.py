"""The last local search of the dislocated bone in gradient NCC (``RegistrationSettings.polish``,
on by default): it recovers a bone left off its optimum, never takes a worse pose, and leaves
the verdict alone."""

from types import SimpleNamespace

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.register import multibody as mb
from pelvicnav.register.polish import polish
from pelvicnav.register.result import MultiBodyResult
from pelvicnav.register.settings import RegistrationSettings

POLISH = RegistrationSettings().polish  # the shipped budget


def _centre_error(renderer, bone, T, truth):
    c = renderer.centroid(bone)[None]
    return float(np.linalg.norm(tf.apply(T, c) - tf.apply(truth[bone], c)))


def test_polish_recovers_a_bone_left_off_its_optimum(two_bodies):
    renderer, levels, truth = two_bodies
    off = {**truth, "a": tf.from_params([1.5, -1.0, 1.0], [0.01, -0.02, 0.0]) @ truth["a"]}
    before = _centre_error(renderer, "a", off["a"], truth)
    found = polish(levels[-1], renderer, off, "a", POLISH, seed=3)
    assert found.lead > 0 and found.evaluations <= 12 * 25
    assert _centre_error(renderer, "a", found.pose, truth) < 0.25 * before


def test_polish_keeps_the_optimum(two_bodies):
    """From the true pose (the radiographs' own), nothing scores better: the pose stays."""
    renderer, levels, truth = two_bodies
    found = polish(levels[-1], renderer, truth, "a", POLISH, seed=3)
    assert found.lead == 0.0 and np.array_equal(found.pose, truth["a"])


def test_the_verdict_and_warnings_stay_the_answers(two_bodies):
    renderer, levels, truth = two_bodies
    off = {**truth, "a": tf.from_params([1.5, -1.0, 1.0], [0.0, 0.0, 0.0]) @ truth["a"]}
    result = MultiBodyResult(poses=off, projections=tuple(levels[-1].projections),
                             similarity=0.5, converged=False, warnings=("in question",),
                             questions=("in question",))  # fmt: skip
    run = SimpleNamespace(cfg=RegistrationSettings(polish=POLISH), dislocated="a",
                          views=[None, None], levels=levels, renderer=renderer, seed=0)  # fmt: skip
    out = mb._polished(run, result)
    assert not out.converged and out.warnings == result.warnings
    assert np.array_equal(out.poses["b"], off["b"])
    assert _centre_error(renderer, "a", out.poses["a"], truth) < 0.5
    assert out.similarity != result.similarity  # read at the polished pose
    # switched off, and with one view
    off, on = RegistrationSettings(polish=None), RegistrationSettings(polish=POLISH)
    for cfg, n in ((off, 2), (on, 1)):
        run = SimpleNamespace(cfg=cfg, dislocated="a", views=[None] * n, levels=levels,
                              renderer=renderer, seed=0)  # fmt: skip
        assert mb._polished(run, result) is result


NAN = float("nan")


@pytest.mark.parametrize("bad", [(0.0, 12, 25, 4.0), (2.0, 1, 25, 4.0), (2.0, 12, 0, 4.0),
                                 (2.0, 12, 25, 0.0), (2.0, 12.5, 25, 4.0), (NAN, 12, 25, 4.0),
                                 3.0, (2.0, 12)])  # fmt: skip
def test_bad_polish_settings_are_refused(bad):
    with pytest.raises(ValueError, match="polish must be"):
        RegistrationSettings(polish=bad)
