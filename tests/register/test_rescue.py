"""The rescue's judgement: did it move the pelvis, or only search the dislocated bone again?"""

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

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


def test_a_second_attempt_at_the_same_answer_settles_an_unsettled_stage_1(monkeypatch):
    # judged: converged when settled and without warnings or doubts; similarity from the hip
    def judged(run, a, settled):
        return _Judged(
            settled and not (a.warnings or a.doubts), 1.0 + a.poses["left_hip"][0, 3] / 100
        )

    monkeypatch.setattr(mb, "_judged", judged)
    run = _run()
    at = {b: np.eye(4) for b in BONES}
    near = {**at, "left_hip": tf.from_params([-1.0, 0.0, 0.0], [0.0, 0.0, 0.0])}
    far = {**at, "left_hip": tf.from_params([9.0, 0.0, 0.0], [0.0, 0.0, 0.0])}
    got = _confirmed(run, (_attempt(at), False), (_attempt(near), False))
    assert got is not None and got.converged and got.similarity == 1.0  # the first scored better
    assert "stage 1 did not settle" in got.warnings[0]
    assert _confirmed(run, (_attempt(at), False), (_attempt(far), True)) is None
    assert _confirmed(run, (_attempt(at, warnings=["x"]), False), (_attempt(near), True)) is None
    assert _confirmed(run, (_attempt(at), True), (_attempt(near), True)) is None  # nothing to ask


def test_a_clean_better_rescue_answers_doubts_and_an_unsettled_stage_1(monkeypatch):
    # judged: converged unless the attempt has warnings or doubts or stage 1 did not settle
    monkeypatch.setattr(mb, "_judged", lambda run, a, settled: _Judged(
        settled and not (a.warnings or a.doubts), 1.0))  # fmt: skip
    run = _run()
    at = {b: np.eye(4) for b in BONES}
    doubted = _attempt(at, doubts=["found once, an implausible other answer among them"])
    clean, flagged = _Judged(True, 1.015), _Judged(False, 1.015)
    assert mb._answered(run, doubted, clean)
    assert mb._answered(run, _attempt(at), clean)  # flagged only as unsettled
    # the rescue's answer flagged on its own (its joints, an ambiguity, a doubt): the doubts stand
    assert not mb._answered(run, doubted, flagged)
    # the first attempt flagged by a warning (an ambiguity with a plausible other answer)
    both = _attempt(at, warnings=["ambiguous"], doubts=["an implausible other answer"])
    assert not mb._answered(run, both, clean)
    assert not mb._answered(run, _attempt(at, warnings=["ambiguous"]), clean)
    # settled and without its doubts the first attempt is still flagged (a similarity floor)
    monkeypatch.setattr(mb, "_judged", lambda run, a, settled: _Judged(False, 1.0))
    assert not mb._answered(run, doubted, clean)


def _intact(moved: dict, init=None, run=None, n_views=2):
    """The intact-joint warnings of stage-2 ``poses``: the pelvis moved by ``pelvis`` (every
    bone), then each bone of ``moved`` by its (mm, deg) about its centroid."""
    run = run or _run()
    init = init or {b: np.eye(4) for b in BONES}
    pelvis = tf.from_params([12.0, -30.0, 5.0], np.deg2rad([4.0, -2.0, 7.0]))
    poses = {b: pelvis @ init[b] for b in BONES}
    for bone, (mm, deg) in moved.items():
        c = tf.apply(poses[bone], run.renderer.centroid(bone)[None])[0]
        shift = tf.from_params(list(c), [0.0, 0.0, 0.0])
        poses[bone] = (
            shift @ tf.from_params(list(mm), np.deg2rad(deg)) @ tf.invert(shift) @ poses[bone]
        )
    first = _first(poses, n_views)
    return mb._intact_warnings(run, poses, first.views, first.fine)


def test_a_kept_bone_moved_off_the_sacrum_is_an_intact_joint_warning():
    assert _intact({}) == []  # the whole pelvis moved as one: nothing
    assert _intact({"right_hip": ((4.0, 2.0, 0.0), (3.0, 0.0, 2.5))}) == []  # within 5 mm / 5 deg
    (w,) = _intact({"right_hip": ((0.0, 9.5, 0.0), (0.0, 0.0, 0.0))})
    assert w.startswith("right_hip ended 9.5 mm / 0.0 deg from where the sacrum puts it")
    assert len(_intact({"right_hip": ((0.0, 0.0, 0.0), (0.0, 6.0, 0.0))})) == 1  # turned 6 deg
    # the dislocated bone moves as it likes; without a plan, or switched off, nothing is judged
    assert _intact({"left_hip": ((40.0, 0.0, 0.0), (20.0, 0.0, 0.0))}) == []
    assert _intact({"right_hip": ((0.0, 9.5, 0.0), (0.0, 0.0, 0.0))}, run=_run(None)) == []
    off = _run()
    off.cfg = RegistrationSettings(intact_limits=None)
    assert _intact({"right_hip": ((0.0, 9.5, 0.0), (0.0, 0.0, 0.0))}, run=off) == []


def test_the_intact_joints_are_the_ct_not_the_start():
    # a start whose right hip is 6 mm / 10 deg from the sacrum's pose (a tracked frame starts
    # from the previous frame's answer): ending there is a warning, ending on the sacrum's
    # pose (the CT's relation) is not
    init = {b: np.eye(4) for b in BONES}
    init["right_hip"] = tf.from_params([6.0, 0.0, 0.0], np.deg2rad([0.0, 10.0, 0.0]))
    assert len(_intact({}, init=init)) == 1
    assert _intact({}) == []


def test_with_one_view_the_intact_joint_is_measured_at_the_detector():
    # depth is not seen with one view: a hip moved 9.5 mm along the view axis (y, an AP view)
    # measures less at the detector (magnification only) than one moved 9.5 mm sideways
    run = _run()
    run.cfg = RegistrationSettings(intact_limits=(0.01, 0.01))  # every move reported

    def mm(move, n_views):
        (w,) = _intact({"right_hip": (move, (0.0, 0.0, 0.0))}, run=run, n_views=n_views)
        return float(w.split(" ended ")[1].split(" mm")[0])

    assert mm((0.0, 9.5, 0.0), 2) == 9.5
    assert mm((0.0, 9.5, 0.0), 1) < 0.6 * mm((9.5, 0.0, 0.0), 1)


def test_intact_limits_are_validated():
    with pytest.raises(ValueError, match="intact_limits"):
        RegistrationSettings(intact_limits=(0.0, 3.0))
    with pytest.raises(ValueError, match="intact_limits"):
        RegistrationSettings(intact_limits=(3.0,))


def test_a_result_flagged_by_its_joints_is_implausible_not_only_in_question():
    from pelvicnav.register.result import MultiBodyResult

    base = {"poses": {}, "projections": (), "similarity": 1.0}
    assert MultiBodyResult(**base, converged=True).verdict == "converged"
    doubted = MultiBodyResult(**base, converged=False, warnings=("two answers within 0.01",))
    assert doubted.verdict == "in question" and doubted.to_json()["implausible"] == []
    joints = "left_hip ends with 21% of its joint samples inside another bone: no dislocation"
    bad = MultiBodyResult(**base, converged=False, warnings=(joints,), implausible=(joints,))
    assert bad.verdict == "implausible"
    assert bad.to_json()["verdict"] == "implausible" and bad.to_json()["implausible"] == [joints]


def test_a_rescue_that_kept_the_pelvis_marks_the_first_attempts_warnings_as_its_own():
    """The returned answer is the rescue's; the first attempt's warnings (its joints among
    them) speak of another answer and say so, and the verdict is the returned answer's."""
    from pelvicnav.register.result import MultiBodyResult

    base = {"poses": {}, "projections": ()}
    joints = "left_hip ends with 20% of its joint samples inside another bone: no dislocation"
    first = MultiBodyResult(**base, similarity=0.874, converged=False, warnings=(joints,),
                            implausible=(joints,))  # fmt: skip
    again = MultiBodyResult(**base, similarity=0.885, converged=True, warnings=("own",))
    got = mb._doubts_stand(_run(), first, again)
    assert not got.converged and got.similarity == 0.885
    assert got.warnings[0].startswith("rescued: the first attempt was flagged (similarity 0.874)")
    assert "the first attempt's doubts stand" in got.warnings[0]
    assert got.warnings[1:] == (f"first attempt: {joints}", "own")
    assert got.implausible == () and got.verdict == "in question"
