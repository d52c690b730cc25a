"""Run seeds: deterministic, independent per path, valid for pycma."""

from __future__ import annotations

import pytest

from pelvicnav.register.seeds import RESEARCH, STAGE1, SWEEP, run_seed


def test_run_seeds_are_deterministic_distinct_and_in_range():
    assert run_seed(3, STAGE1, 0) == run_seed(3, STAGE1, 0)
    seeds = {run_seed(s, st, *p) for s in range(20) for st, p in
             ((STAGE1, (0,)), (STAGE1, (1,)), (SWEEP, (0, 0, 1)), (SWEEP, (1, 0, 0)),
              (RESEARCH, (0, 1, 1)))}  # fmt: skip
    assert len(seeds) == 100  # arithmetic (seed + level) would collide across seeds and levels
    assert all(0 <= s < 2**32 for s in seeds)
    with pytest.raises(ValueError, match="seed"):
        run_seed(-1, STAGE1, 0)
