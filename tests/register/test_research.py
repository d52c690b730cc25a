"""The re-search's rules on scripted outcomes: when it retries, when it flags, who wins."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from pelvicnav.register import research as rs
from pelvicnav.register.settings import RegistrationSettings

BONES = ("sacrum", "left_hip", "right_hip")


def _run(monkeypatch, outcomes, n_views=2, count=1):
    """Re-search with each search returning (f_alt, d_mm) from ``outcomes``; the answer scores
    -1.0 (objectives are minimised)."""
    calls = []

    def search(problem, i, y, r, seed):
        f_alt, d_mm = outcomes[len(calls)]
        calls.append(r)
        return np.full(6, float(len(calls))), [SimpleNamespace(f=f_alt)]

    def compare(problem, i, y, x_alt, views):
        return -1.0, outcomes[len(calls) - 1][1], 0.0

    monkeypatch.setattr(rs, "_search_from_stage1", search)
    monkeypatch.setattr(rs, "_compare", compare)
    monkeypatch.setattr(rs, "_repass", lambda problem, y, r, seed, out: y)
    problem = SimpleNamespace(blocks=SimpleNamespace(bones=BONES), dislocated="left_hip",
                              settings=RegistrationSettings())  # fmt: skip
    out = rs.research(problem, np.zeros(18), [None] * n_views, seed=0, count=count)
    return out, calls


def test_a_re_search_that_agrees_is_the_only_one(monkeypatch):
    out, calls = _run(monkeypatch, [(-0.99, 0.5)])
    assert calls == [0] and not out.warnings


def test_a_far_losing_re_search_earns_one_more_and_a_second_miss_flags(monkeypatch):
    out, calls = _run(monkeypatch, [(-0.9, 13.5), (-0.95, 0.4)])
    assert calls == [0, 1] and not out.warnings  # the second found the answer again
    out, calls = _run(monkeypatch, [(-0.9, 13.5), (-0.8, 9.0), (-0.7, 1.0)])
    assert calls == [0, 1]  # one retry only
    assert any("found once only" in w for w in out.warnings)
    assert out.disagreement["left_hip"] == pytest.approx(13.5)


def test_a_far_winning_re_search_takes_over_without_a_retry(monkeypatch):
    out, calls = _run(monkeypatch, [(-1.2, 13.5)])
    assert calls == [0] and not out.warnings
    assert np.all(out.y[6:12] == 1.0)  # the left hip's block is the re-search's


def test_one_view_keeps_its_distance_rule_without_retries(monkeypatch):
    out, calls = _run(monkeypatch, [(-0.9, 5.0), (-0.95, 0.3)], n_views=1, count=2)
    assert calls == [0, 1]
    assert len(out.warnings) == 1 and "not determined" in out.warnings[0]
