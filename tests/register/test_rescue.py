"""The rescue's judgement: did it move the pelvis, or only search the dislocated bone again?"""

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.register import multibody as mb
from pelvicnav.register.multibody import _Attempt, _confirmed, _kept, _moved_pelvis
from pelvicnav.register.settings import RegistrationSettings

BONES = ("sacrum", "left_hip", "right_hip")


def _run(dislocated="left_hip"):
    rng = np.random.default_rng(0)
    pts = {b: rng.normal(scale=40.0, size=(300, 3)) + 100.0 * k for k, b in enumerate(BONES)}
    renderer = SimpleNamespace(
        bones=BONES, points=lambda b, lv=-1: pts[b], centroid=lambda b, lv=-1: pts[b].mean(0)
    )
    return SimpleNamespace(renderer=renderer, dislocated=dislocated, cfg=RegistrationSettings())


def _first(poses, n_views=2):
    carms = [pj.CArm(rows=64, cols=64), pj.CArm(rows=64, cols=64, orbit_deg=30)][:n_views]
    views = SimpleNamespace(projections=tuple(c.projection_matrix for c in carms),
                            pixel_spacing=tuple(c.pixel_spacing for c in carms))  # fmt: skip
    return SimpleNamespace(fine=SimpleNamespace(index=1), poses=poses, views=views)


def _moved(bone, mm=(0.0, 0.0, 0.0), deg=(0.0, 0.0, 0.0), run=None):
    run = run or _run()
    first = {b: np.eye(4) for b in BONES}
    again = dict(first)
    c = run.renderer.centroid(bone)
    T = tf.from_params(list(mm), np.deg2rad(deg))
    shift = np.eye(4)
    shift[:3, 3] = c
    again[bone] = shift @ T @ tf.invert(shift)  # turned about the bone's centroid
    return _moved_pelvis(run, _first(first), SimpleNamespace(poses=again))


def test_kept_bones_are_those_stage_1_places():
    assert _kept(_run("left_hip")) == ["sacrum", "right_hip"]
    assert _kept(_run(None)) == list(BONES)


def test_a_rescue_that_moves_a_kept_bone_moved_the_pelvis():
    assert _moved("sacrum", mm=(3.5, 0, 0))  # beyond the 3 mm ambiguity
    assert _moved("right_hip", deg=(0, 0, 3.5))  # beyond 3 deg
    assert not _moved("sacrum", mm=(2.0, 1.0, 0), deg=(1.0, 0, 0))  # within both


def test_the_dislocated_bone_alone_does_not_count():
    assert not _moved("left_hip", mm=(40.0, -20.0, 10.0), deg=(15.0, 0, 0))
    # without a plan every bone is stage 1's
    assert _moved("left_hip", mm=(40.0, 0, 0), run=_run(None))


@dataclass(frozen=True)
class _Judged:
    converged: bool
    similarity: float
    warnings: tuple = ()


def _attempt(poses, warnings=(), doubts=()):
    first = _first(poses)
    return _Attempt(first.views, first.fine, poses, [], list(warnings), {}, "pelvis", list(doubts))


def test_a_second_attempt_at_the_same_answer_settles_doubts_only(monkeypatch):
    # judged: converged unless the attempt has warnings or doubts; similarity from its hip's x
    monkeypatch.setattr(mb, "_judged", lambda run, a, settled: _Judged(
        not (a.warnings or a.doubts), 1.0 + a.poses["left_hip"][0, 3] / 100.0))  # fmt: skip
    run = _run()
    at = {b: np.eye(4) for b in BONES}
    near = {**at, "left_hip": tf.from_params([1.0, 0.0, 0.0], [0.0, 0.0, 0.0])}
    far = {**at, "left_hip": tf.from_params([9.0, 0.0, 0.0], [0.0, 0.0, 0.0])}
    doubted = _attempt(at, doubts=["an implausible other answer"])
    got = _confirmed(run, (doubted, True), (_attempt(near), True))
    assert got is not None and got.converged and got.similarity == 1.01  # the better of the two
    assert got.warnings[0].startswith("confirmed:")
    # the second attempt ended elsewhere, or has a warning of its own, or the first has a
    # warning besides its doubts, or no doubts at all: not settled here
    assert _confirmed(run, (doubted, True), (_attempt(far), True)) is None
    assert _confirmed(run, (doubted, True), (_attempt(near, warnings=["x"]), True)) is None
    both = _attempt(at, warnings=["ambiguous"], doubts=["an implausible other answer"])
    assert _confirmed(run, (both, True), (_attempt(near), True)) is None
    assert _confirmed(run, (_attempt(at, warnings=["x"]), True), (_attempt(near), True)) is None
