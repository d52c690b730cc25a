"""The registration study on the runner: one simulated case end to end, stored and resumable."""

from __future__ import annotations

import csv

import pytest

from pelvicnav.phantom.population import load_population
from pelvicnav.studies.registration import RegistrationStudySettings, run_registration_study


@pytest.mark.slow
def test_one_case_is_registered_stored_and_not_rerun(tmp_path):
    pop = load_population("model", subject_ids=(4,))
    settings = RegistrationStudySettings(n_cases=1, seed=5)
    rows = run_registration_study(pop, tmp_path, settings, workers=0)
    assert [r["bone"] for r in rows] == ["sacrum", "left_hip", "right_hip"]
    assert all(r["case_id"] == "0000" for r in rows)
    for r in rows:  # shipped defaults, a sampled patient: every bone found
        assert r["error_mm"] < 2.0, r
    with open(tmp_path / "results.csv") as fh:
        assert [r["bone"] for r in csv.DictReader(fh)] == ["sacrum", "left_hip", "right_hip"]
    assert (tmp_path / "summary.csv").is_file() and (tmp_path / "store.sqlite").is_file()
    again = run_registration_study(pop, tmp_path, settings, workers=0)  # from the store
    assert [r["error_mm"] for r in again] == [r["error_mm"] for r in rows]
    assert [r["case_seconds"] for r in again] == [r["case_seconds"] for r in rows]


def test_real_ct_cases_are_named_by_ct_and_bad_settings_refused(tmp_path):
    from pelvicnav.studies.registration import RegistrationStudySettings, registration_study

    missing = RegistrationStudySettings(real_ct=1, real_ct_dir=str(tmp_path))
    with pytest.raises(ValueError, match="real CTs not found"):
        registration_study(None, missing)
    for name in ("002", "004", "005"):
        (tmp_path / name).mkdir()
    study = registration_study(
        None, RegistrationStudySettings(real_ct=2, real_ct_dir=str(tmp_path))
    )
    assert [c["case_id"] for c in study.cases[:4]] == [
        "real-002-000", "real-004-000", "real-005-000", "real-002-001"]  # fmt: skip
    assert len(study.cases) == 6 and study.cases[0]["real_ct"] == str(tmp_path / "002")
    asm = RegistrationStudySettings(real_ct=1, real_ct_dir=str(tmp_path), segmentation="asm")
    with pytest.raises(ValueError, match="manual labels"):
        registration_study(None, asm)
