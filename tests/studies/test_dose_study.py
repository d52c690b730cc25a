"""The dose study: a patient with fiducial beads registered at a low dose, TRE at the beads."""

from __future__ import annotations

import pytest

from pelvicnav.phantom.population import load_population
from pelvicnav.studies.dose import DoseSettings, lowest_good_dose, run_dose_study


@pytest.mark.slow
def test_low_dose_case_is_registered_and_its_tre_read_at_the_beads(tmp_path):
    pop = load_population("model", subject_ids=(4,))
    settings = DoseSettings(doses=(2.0,), repeats=1, beads=8, seed=3)
    summary = run_dose_study(pop, tmp_path, settings, workers=0)
    assert [s["dose_ugy"] for s in summary] == [2.0]
    assert summary[0]["n"] == 1
    # Shipped defaults at 2 uGy/frame: the case is a success (every bead under the study's
    # 4 mm), its median TRE well under. Its worst bead is 1.61 mm (session 28; it moved between
    # 1.4 and 2.2 mm with whether numba had just compiled the adjoint splat or loaded it from its
    # cache, fixed then), so the test holds the study's criterion, not 2 mm.
    assert summary[0]["tre_worst_mm"] < settings.success_mm, summary
    assert summary[0]["tre_median_mm"] < 1.0, summary
    assert lowest_good_dose(summary, settings) == 2.0
    text = (tmp_path / "summary.md").read_text()
    assert "| 2 | 1 |" in text and "Paper" in text
    assert (tmp_path / "dose.png").read_bytes()[:4] == b"\x89PNG"
    rows = (tmp_path / "results.csv").read_text().splitlines()
    assert rows[0].startswith("case_id,") and len(rows) == 2
    assert ",8," in rows[1]  # all eight beads were read
