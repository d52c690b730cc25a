"""A pelvis that stage 2 pushed to the edge of its box: stage 1 misplaced it; stage 2 runs
again from its answer, and a pelvis still at the edge flags the result."""

from types import SimpleNamespace

import numpy as np

from pelvicnav.register import multibody as mb
from pelvicnav.register.settings import RegistrationSettings


def _problem(dislocated="left_hip"):
    from pelvicnav.register.stage2 import Stage2Problem

    blocks = SimpleNamespace(bones=("sacrum", "left_hip", "right_hip"))
    problem = SimpleNamespace(blocks=blocks, dislocated=dislocated,
                              settings=RegistrationSettings())  # fmt: skip
    problem.box = lambda i: Stage2Problem.box(problem, i)
    return problem


def test_a_pelvis_bone_at_the_edge_of_its_box_is_a_fault():
    t, r = RegistrationSettings().stage2.range_attached
    y = np.zeros(18)
    assert mb._edges(_problem(), y) == []
    y[6:12] = [20.0, 0, 0, 11.0, 0, 0]  # the dislocated bone: its own, wider box
    y[3 + 0] = 0.9 * r  # the sacrum's first rotation, inside
    y[12 + 1] = -0.5 * t  # the right hip's y shift, inside
    assert mb._edges(_problem(), y) == []
    y[5] = -r  # the sacrum's third rotation at the bound
    y[12] = t  # the right hip's x shift at the bound
    faults = mb._edges(_problem(), y)
    assert [f.split()[3] for f in faults] == ["sacrum", "right_hip"]
    assert all("stage 1 misplaced the pelvis" in f for f in faults)
    assert mb._edges(_problem(dislocated=None), y) == []  # no plan: every bone has the full box


def _outcome(tag, faults):
    return SimpleNamespace(poses={"sacrum": tag}, disagreement={}, warnings=[], doubts=[],
                           implausible=[], found={"left_hip": [tag]}, faults=list(faults),
                           result=SimpleNamespace(name=f"stage 2 ({tag})"))  # fmt: skip


def _attempt_with(monkeypatch, outcomes, recentre=3):
    calls = []

    def stage2(views, levels, renderer, poses, cfg, seed, progress, dislocated):
        calls.append(poses)
        return outcomes[len(calls) - 1]

    monkeypatch.setattr(mb, "_stage2", stage2)
    monkeypatch.setattr(mb, "_intact_warnings", lambda run, poses, views, fine: [])
    cfg = RegistrationSettings()
    cfg = cfg.__class__(stage2=cfg.stage2.__class__(recentre=recentre))
    run = SimpleNamespace(views=None, levels=[None], renderer=SimpleNamespace(bones=("sacrum",)),
                          cfg=cfg, seed=0, progress=None, dislocated="left_hip", found={},
                          body=lambda init: SimpleNamespace(name="pelvis"))  # fmt: skip
    s1 = SimpleNamespace(projections=None, delta=np.eye(4), result="stage 1")
    a = mb._attempt(run, {"sacrum": np.eye(4)}, s1)
    return a, calls, run.found.get("left_hip")


def test_a_pelvis_at_the_edge_gets_stage_2_again_from_its_answer(monkeypatch):
    edge = ["stage 2 moved sacrum to the edge of its box ..."]
    runs = [_outcome(1, edge), _outcome(2, edge), _outcome(3, [])]
    a, calls, found = _attempt_with(monkeypatch, runs)
    assert len(calls) == 3 and calls[1] == {"sacrum": 1} and calls[2] == {"sacrum": 2}
    assert a.poses == {"sacrum": 3} and a.faults == []
    assert found == [1, 2, 3]  # every run's other answers, for the second opinion
    a, calls, found = _attempt_with(monkeypatch, [_outcome(1, [])])
    assert len(calls) == 1 and a.poses == {"sacrum": 1}


def test_a_pelvis_still_at_the_edge_after_the_last_try_keeps_its_fault(monkeypatch):
    edge = ["stage 2 moved sacrum to the edge of its box ..."]
    a, calls, found = _attempt_with(monkeypatch, [_outcome(k, edge) for k in range(3)], recentre=2)
    assert len(calls) == 3 and a.faults == edge and a.poses == {"sacrum": 2}
    a, calls, found = _attempt_with(monkeypatch, [_outcome(0, edge)], recentre=0)
    assert len(calls) == 1 and a.faults == edge
