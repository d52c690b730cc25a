"""``make studies-quick``'s driver: one shared cluster, each study as its own command."""

from __future__ import annotations

import pytest

from pelvicnav.studies.quick import QUICK_STUDIES, _command, run_quick


def test_each_study_is_its_command_on_the_shared_scheduler(tmp_path):
    for study in QUICK_STUDIES:
        cmd = _command(study, tmp_path, "tcp://127.0.0.1:1")
        assert cmd[cmd.index("study") + 1] == study and "--quick" in cmd
        assert ("--scheduler" in cmd) == (study != "runtime")  # runtime times in its process


def test_a_failing_study_stops_the_run_with_its_log(tmp_path):
    with pytest.raises(RuntimeError, match="no-such-study") as err:
        run_quick(tmp_path, workers=1, studies=("no-such-study",))
    assert "no-such-study.log" in str(err.value)
    assert not (tmp_path / "timings.md").exists()
