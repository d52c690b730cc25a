"""``scripts/rerun_registration_cases.py`` refuses bad arguments by name, before any work."""

import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "rerun_registration_cases.py"


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["269-28"], "cases must be SEED:CASE"),
        (["269:-1"], "cases must be SEED:CASE"),
        (["269:28", "--without", "no_such_switch"], "no_such_switch"),
    ],
)
def test_bad_arguments_are_named(tmp_path, args, said):
    run = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "rows.csv"), *args],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert run.returncode == 2
    assert said in run.stderr
    assert not (tmp_path / "rows.csv").exists()
