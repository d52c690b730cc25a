"""The second opinion on an answer in question: gradient NCC of the kept answer against the
other answers the searches found, and what the registration's verdict does with it."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.register import multibody as mb
from pelvicnav.register.opinion import SecondOpinion, second_opinion
from pelvicnav.register.result import MultiBodyResult
from pelvicnav.register.settings import RegistrationSettings

FAR = RegistrationSettings().research.ambiguity  # (3 mm, 3 deg)


def _shifted(T, mm):
    return tf.from_params(list(mm), [0.0, 0.0, 0.0]) @ T


def _turned(T, deg, centre):
    """``T`` turned by ``deg`` about the world z axis through ``centre`` (world mm)."""
    c = np.asarray(centre, dtype=np.float64)
    R = tf.from_params([0.0, 0.0, 0.0], [0.0, 0.0, float(np.deg2rad(deg))])
    return _shifted(R, c - R[:3, :3] @ c) @ T


class _Views(SimpleNamespace):
    def __len__(self):
        return len(self.projections)


def _views(levels):
    """The fixture's two views as far as the distances and the verdict read them."""
    return _Views(projections=tuple(levels[-1].projections), pixel_spacing=((1, 1),) * 2)


def test_the_true_pose_leads_every_far_answer(two_bodies):
    renderer, levels, truth = two_bodies
    far = [_shifted(truth["a"], (9.0, 0.0, 0.0)), _shifted(truth["a"], (0.0, -6.0, 4.0))]
    near = [_shifted(truth["a"], (1.5, 0.0, 0.0))]  # within FAR: not compared
    found = far + near + far[:1]  # a repeat counts once
    op = second_opinion(levels[-1], renderer, _views(levels), truth, "a", found, FAR)
    assert op.compared == 2
    assert op.lead > 0.02 and op.lead_level > 0.02
    # the lead is over the best of them, and names it
    each = [second_opinion(levels[-1], renderer, _views(levels), truth, "a", [T], FAR)
            for T in far]  # fmt: skip
    best = min(each, key=lambda o: min(o.lead, o.lead_level))
    assert (op.lead, op.rival_mm) == pytest.approx((min(o.lead for o in each), best.rival_mm))
    assert op.lead_level == pytest.approx(min(o.lead_level for o in each))


def test_a_wrong_answer_trails_the_truth_found_elsewhere(two_bodies):
    renderer, levels, truth = two_bodies
    wrong = {**truth, "a": _shifted(truth["a"], (8.0, 3.0, 0.0))}
    op = second_opinion(levels[-1], renderer, _views(levels), wrong, "a", [truth["a"]], FAR)
    assert op.compared == 1
    assert op.lead < -0.02 and op.lead_level < -0.02
    assert op.rival_mm == pytest.approx(np.hypot(8.0, 3.0), abs=1e-6)


def test_nothing_far_is_nothing_compared(two_bodies):
    renderer, levels, truth = two_bodies
    op = second_opinion(levels[-1], renderer, _views(levels), truth, "a",
                        [_shifted(truth["a"], (2.0, 0.0, 0.0))], FAR)  # fmt: skip
    assert op.compared == 0 and np.isnan(op.lead) and np.isnan(op.lead_level)


@pytest.mark.parametrize("far", [4.0, (4.0,), (4.0, "x"), (-1.0, 3.0), (3.0, float("nan"))])
def test_the_limits_must_be_mm_and_degrees(two_bodies, far):
    renderer, levels, truth = two_bodies
    with pytest.raises(ValueError, match=r"far must be \(mm, deg\)"):
        second_opinion(levels[-1], renderer, _views(levels), truth, "a", [truth["a"]], far)


def test_an_answer_turned_beyond_the_limit_is_compared_however_near(two_bodies):
    # fresh seed 487 case 20: a hip 0.92 mm off was in question for an answer 2.0 mm / 3.3 deg
    # away, which the second opinion (answers more than 4 mm away) did not compare
    renderer, levels, truth = two_bodies
    centre = tf.apply(truth["a"], renderer.centroid("a", levels[-1].index)[None])[0]
    turned, slight = _turned(truth["a"], 8.0, centre), _turned(truth["a"], 2.0, centre)
    op = second_opinion(levels[-1], renderer, _views(levels), truth, "a", [turned, slight], FAR)
    assert op.compared == 1
    assert op.rival_mm == pytest.approx(0.0, abs=1e-6) and op.rival_deg == pytest.approx(8.0)
    assert op.lead > 0 and op.lead_level > 0


def test_the_seconds_count_the_second_opinion(two_body_views, monkeypatch):
    """``seconds`` is the whole call: what runs after the answer was judged (a probe or rescue
    that changed nothing, the second opinion) counted as time outside the registration."""
    import time

    renderer, views, truth = two_body_views
    judged = mb._second_opinion

    calls = []

    def slow(run, result):
        calls.append(run)
        time.sleep(0.3)
        return judged(run, result)

    monkeypatch.setattr(mb, "_second_opinion", slow)
    t0 = time.perf_counter()
    res = mb.register(views, renderer, init_poses=truth, settings=RegistrationSettings.tracking())
    wall = time.perf_counter() - t0
    assert len(calls) == 1  # a tracked frame gets its second opinion too
    assert wall - 0.1 < res.seconds <= wall  # not wall - 0.3


# --- the verdict -------------------------------------------------------------------------


def _result(**kw):
    base = {
        "poses": {"left_hip": np.eye(4)},
        "projections": (np.eye(3, 4),) * 2,
        "similarity": 0.9,
        "converged": False,
        "warnings": ("two searches for left_hip ... the images do not pin its pose down",),
        "questions": ("two searches for left_hip ... the images do not pin its pose down",),
    }
    return MultiBodyResult(**{**base, **kw})  # fmt: skip


def _run(cfg=None, n_views=2, dislocated="left_hip"):
    return SimpleNamespace(cfg=cfg or RegistrationSettings(), dislocated=dislocated,
                           views=[None] * n_views, levels=[None], renderer=None,
                           found={"left_hip": [np.eye(4)]})  # fmt: skip


@pytest.fixture
def opinion(monkeypatch):
    """Replace the second opinion by a canned one; records its calls."""
    calls = []

    def give(lead, compared=3, lead_level=None):
        def fake(level, renderer, views, poses, bone, found, far):
            calls.append((bone, len(found), far))
            own = lead if lead_level is None else lead_level
            return SecondOpinion(bone, compared, lead, own, 12.0, 5.0)

        monkeypatch.setattr(mb, "second_opinion", fake)
        return calls

    return give


def test_a_lead_settles_a_result_in_question(opinion):
    calls = opinion(0.03)
    result = _result()
    out = mb._second_opinion(_run(), result)
    assert out.converged and out.verdict == "converged"
    assert out.poses is result.poses  # the poses are never changed
    assert out.warnings[0].startswith("settled by a second opinion")
    assert out.warnings[1:] == _result().warnings and out.questions == _result().questions
    assert calls == [("left_hip", 1, RegistrationSettings().research.ambiguity)]


def test_a_better_other_answer_keeps_the_flag_and_says_where(opinion):
    opinion(-0.02)
    out = mb._second_opinion(_run(), _result())
    assert not out.converged and out.verdict == "in question"
    assert "12.0 mm / 5.0 deg away" in out.warnings[-1]
    assert ("in gradient correlation (to within 0.01) and the searches' own similarity"
            in out.warnings[-1])  # fmt: skip


def test_both_similarities_must_prefer_the_answer(opinion):
    # seed 389 case 4: a hip 13.6 mm off led the others found in gradient NCC (0.021), but GO
    # at the finest level put one of them 0.015 above it; the truth was never found
    opinion(0.021, lead_level=-0.015)
    out = mb._second_opinion(_run(), _result())
    assert not out.converged
    assert out.warnings[-1].endswith("in the searches' own similarity")
    opinion(-0.01, lead_level=0.02)
    assert (
        mb._second_opinion(_run(), _result())
        .warnings[-1]
        .endswith("gradient correlation (to within 0.01)")
    )


def test_a_tie_at_the_margin_keeps_the_flag(opinion):
    opinion(0.0)
    assert not mb._second_opinion(_run(), _result()).converged
    opinion(0.004)
    cfg = replace(RegistrationSettings(), second_opinion=(0.005, 0.005))
    assert not mb._second_opinion(_run(cfg), _result()).converged


def test_gradient_ncc_must_lead_by_its_margin(opinion):
    # real-CT seed 17 case 2: a hip 6.73 mm off whose truth no search found led the answers
    # found by 0.005 in gradient NCC and 0.003 in GO; the shipped margins keep it flagged
    opinion(0.005, lead_level=0.003)
    out = mb._second_opinion(_run(), _result())
    assert not out.converged
    assert out.warnings[-1].endswith("gradient correlation (to within 0.01)")
    # the smallest leads of a fine registration recorded (347/36 in gradient NCC, 239/33 in GO)
    opinion(0.0106, lead_level=0.0012)
    assert mb._second_opinion(_run(), _result()).converged


@pytest.mark.parametrize("bad", [(0.01,), (-0.01, 0.0), (0.01, 0.0, 0.0), 0.01])
def test_margins_are_two_and_not_negative(bad):
    with pytest.raises(ValueError, match="second_opinion must be"):
        RegistrationSettings(second_opinion=bad)


def test_nothing_to_compare_keeps_the_flag(opinion):
    opinion(float("nan"), compared=0)
    result = _result()
    assert mb._second_opinion(_run(), result) is result


@pytest.mark.parametrize("case", ["converged", "implausible", "faulted", "one view", "no plan",
                                  "off"])  # fmt: skip
def test_only_a_result_flagged_by_questions_alone_is_reconsidered(opinion, case):
    calls = opinion(0.5)
    result = {"converged": _result(converged=True, questions=()),
              "implausible": _result(implausible=("left_hip ends with ...",)),
              "faulted": _result(questions=())}.get(case, _result())  # fmt: skip
    run = {
        "one view": _run(n_views=1),
        "no plan": _run(dislocated=None),
        "off": _run(replace(RegistrationSettings(), second_opinion=None)),
    }.get(case, _run())
    assert mb._second_opinion(run, result) is result
    assert calls == []


def test_doubts_that_stand_are_questions_only_when_both_attempts_were_questioned():
    bones = SimpleNamespace(bones=("sacrum", "left_hip", "right_hip"))
    run = SimpleNamespace(cfg=RegistrationSettings(), dislocated="left_hip", renderer=bones)
    first = _result(similarity=0.90)
    clean = _result(similarity=0.91, converged=True, warnings=(), questions=())
    out = mb._doubts_stand(run, first, clean)
    assert not out.converged and out.questions == out.warnings
    faulted = _result(similarity=0.91, warnings=("final similarity ...",), questions=())
    assert mb._doubts_stand(run, first, faulted).questions == ()
    # a first attempt whose answer was implausible as well (seed 419 case 15: the rescue's
    # answer 0.3 mm off, every other answer below it in both similarities)
    likely_wrong = replace(first, implausible=("left_hip ends with ...",))
    assert mb._doubts_stand(run, likely_wrong, clean).questions != ()
    assert mb._doubts_stand(run, replace(first, questions=()), clean).questions == ()


def _judged(two_bodies, ambiguous=(), faults=()):
    from pelvicnav.register.cmaes import CMAESResult
    from pelvicnav.register.result import StageResult
    from pelvicnav.register.settings import PyramidSettings

    renderer, levels, truth = two_bodies
    cma = CMAESResult(x=np.zeros(6), f=-1.0, evaluations=10, generations=5, converged=True,
                      history=np.linspace(0.0, -1.0, 5), final_std=0.1)  # fmt: skip
    cfg = RegistrationSettings(pyramid=PyramidSettings(metrics=("gncc", "gncc")))
    views = _views(levels)
    return mb._judge(views, levels[-1], renderer, truth, [StageResult("stage 2", [cma], 0.0)],
                     list(ambiguous), {}, cfg, "pelvis", True, list(faults))  # fmt: skip


def test_questions_are_kept_only_when_nothing_else_flags(two_bodies):
    clean = _judged(two_bodies)
    assert clean.converged and clean.questions == ()
    asked = _judged(two_bodies, ambiguous=["two searches ... do not pin its pose down"])
    assert not asked.converged and asked.questions == asked.warnings
    faulted = _judged(two_bodies, ambiguous=["two searches ... do not pin its pose down"],
                      faults=["stage 2 moved b to the edge of its box ..."])  # fmt: skip
    assert not faulted.converged and faulted.questions == ()
    assert faulted.warnings[0].startswith("stage 2 moved b to the edge")
