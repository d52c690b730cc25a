"""Capture-range study: its cases, and the capture range read from success rates."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from pelvicnav.studies.capture_range import (
    AXES,
    CaptureRangeSettings,
    capture_range_study,
    summarise_capture,
)


def test_cases_cover_every_axis_offset_and_repeat():
    pop = SimpleNamespace(n_subjects=2, subject_ids=(7, 9), source="test",
                          vertices=np.zeros((2, 3, 4, 3)), faces=())  # fmt: skip
    cfg = CaptureRangeSettings(translations=(-50, 50, 100), rotations=(-20, 20), repeats=2)
    study = capture_range_study(pop, cfg)
    assert len(study.cases) == 3 * 3 * 2 + 3 * 2 * 2
    assert {c["axis"] for c in study.cases} == set(AXES)
    # repeat r is patient r, whatever the offset: offsets of one repeat share a simulation
    assert {c["seed"] for c in study.cases if c["repeat"] == 1} == {1}
    assert len(CaptureRangeSettings.quick().translations) == 2


def test_capture_range_is_the_largest_offset_passed_on_both_sides():
    cfg = CaptureRangeSettings(success_rate=0.5)
    rows = []
    for off, ok in ((-100, False), (-50, True), (-25, True), (25, True), (50, True), (100, True)):
        rows.append({"axis": "x", "offset": float(off), "success": ok})
    for off, ok in ((-20, True), (20, False), (-10, True), (10, True)):
        rows.append({"axis": "rz", "offset": float(off), "success": ok})
    s = summarise_capture(rows, cfg)
    assert s["x"]["capture"] == 50.0  # -100 failed
    assert s["rz"]["capture"] == 10.0
    assert s["y"]["capture"] == 0.0 and s["y"]["rates"] == {}


def test_axes_subset_and_the_quick_preset():
    pop = SimpleNamespace(n_subjects=1, subject_ids=(7,), source="test",
                          vertices=np.zeros((1, 3, 4, 3)), faces=())  # fmt: skip
    quick = CaptureRangeSettings.quick()
    study = capture_range_study(pop, quick)
    assert sorted((c["axis"], c["offset"]) for c in study.cases) == [("x", -20.0), ("x", 20.0)]
    rows = [{"axis": c["axis"], "offset": c["offset"], "success": True} for c in study.cases]
    assert {a: s["capture"] for a, s in summarise_capture(rows, quick).items()} == {"x": 20.0}
    wide = CaptureRangeSettings(axes=("x", "rx"), translations=(-100, 100), rotations=(-30, 30))
    rows = [{"axis": c["axis"], "offset": c["offset"], "success": True}
            for c in capture_range_study(pop, wide).cases]  # fmt: skip
    assert {a: s["capture"] for a, s in summarise_capture(rows, wide).items()} == {
        "x": 100.0, "rx": 30.0}  # fmt: skip
    with pytest.raises(ValueError, match="axes"):
        CaptureRangeSettings(axes=("x", "pitch"))
