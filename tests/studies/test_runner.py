"""The study runner and its store: resumable, exactly once, parallel = serial, clear refusals."""

from __future__ import annotations

import csv
import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from tests.helpers import toy_study as toy

from pelvicnav.studies.runner import Study, run_study
from pelvicnav.studies.store import ResultStore, StoreMismatch

ROOT = Path(__file__).resolve().parents[2]


def _values(results):
    return [(cid, r) for cid, r, _ in results]


def test_store_keys_rows_by_settings(tmp_path):
    with ResultStore(tmp_path / "s.sqlite", "toy", {"a": 1}) as store:
        assert store.put("001", {"x": 1.5}, 0.1)
        assert not store.put("001", {"x": 9.9}, 0.1)  # a case is stored once
        assert store.done() == {"001"}
    with pytest.raises(StoreMismatch, match="run with other settings.*--force"):
        ResultStore(tmp_path / "s.sqlite", "toy", {"a": 2})
    with ResultStore(tmp_path / "s.sqlite", "toy", {"a": 2}, force=True) as store:
        assert store.done() == set()
    with ResultStore(tmp_path / "s.sqlite", "other", {"a": 1}) as store:  # another study: fine
        assert store.done() == set()


def test_serial_run_resumes_and_exports_csv(tmp_path):
    results = run_study(toy.toy_study(5), tmp_path, workers=0)
    assert [cid for cid, _, _ in results] == ["000", "001", "002", "003", "004"]
    again = run_study(toy.toy_study(5), tmp_path, workers=0)  # nothing left to run
    assert _values(again) == _values(results)
    with open(tmp_path / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["case_id"] for r in rows] == ["000", "001", "002", "003", "004"]
    assert float(rows[2]["value"]) == results[2][1]["value"]
    with pytest.raises(StoreMismatch):
        run_study(toy.toy_study(5, scale=2.0), tmp_path, workers=0)
    with pytest.raises(ValueError, match="unique string case_id"):
        Study("bad", {}, ({"case_id": "a"}, {"case_id": "a"}), toy.run_toy)


@pytest.mark.slow
def test_a_killed_study_resumes_with_every_case_once(tmp_path):
    code = (
        "import sys; from tests.helpers.toy_study import toy_study; "
        "from pelvicnav.studies.runner import run_study; "
        "run_study(toy_study(12, sleep=0.25), sys.argv[1], workers=0)"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(tmp_path / "killed")], cwd=ROOT, env=env
    )
    store = tmp_path / "killed" / "store.sqlite"
    deadline = time.time() + 60
    while time.time() < deadline:
        if store.exists():
            with sqlite3.connect(store) as db:
                try:
                    if db.execute("SELECT COUNT(*) FROM cases").fetchone()[0] >= 4:
                        break
                except sqlite3.OperationalError:  # the tables are being created
                    pass
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    with sqlite3.connect(store) as db:
        partial = db.execute("SELECT COUNT(*) FROM cases").fetchone()[0]
    assert 4 <= partial < 12, partial
    resumed = run_study(toy.toy_study(12, sleep=0.25), tmp_path / "killed", workers=0)
    with sqlite3.connect(store) as db:
        ids = [r[0] for r in db.execute("SELECT case_id FROM cases")]
    assert sorted(ids) == [f"{i:03d}" for i in range(12)]  # every case exactly once
    fresh = run_study(toy.toy_study(12, sleep=0.25), tmp_path / "fresh", workers=0)
    assert _values(resumed) == _values(fresh)


@pytest.mark.slow
def test_local_cluster_equals_serial(tmp_path):
    import cloudpickle

    cloudpickle.register_pickle_by_value(toy)  # workers need not import the tests
    serial = run_study(toy.toy_study(6), tmp_path / "serial", workers=0)
    parallel = run_study(toy.toy_study(6), tmp_path / "parallel", workers=2)
    assert _values(parallel) == _values(serial)


def test_unreachable_scheduler_is_a_clear_error(tmp_path):
    started = time.perf_counter()
    with pytest.raises(ValueError, match="cannot reach the dask scheduler at tcp://127.0.0.1:9"):
        run_study(toy.toy_study(2), tmp_path, scheduler="tcp://127.0.0.1:9")
    assert time.perf_counter() - started < 10
