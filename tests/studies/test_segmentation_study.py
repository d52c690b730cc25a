"""The segmentation study on the runner: leave-one-out on a sampled population, end to end."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from pelvicnav import BONES
from pelvicnav.studies.segmentation import (
    SegmentationStudySettings,
    _population,
    run_segmentation_study,
    segmented_population,
)


@pytest.mark.slow
def test_leave_one_out_case_is_segmented_stored_and_its_meshes_kept(tmp_path):
    pop = _population({"source": "model", "n_subjects": 6})  # what the case will load (cached)
    settings = SegmentationStudySettings(n_subjects=1, dislocated=False, real_ct=False, seed=2)
    summary = run_segmentation_study(pop, tmp_path, settings, workers=0)
    assert [s["bone"] for s in summary] == list(BONES)
    for s in summary:  # a prior from 5 others only: a weak model (the 39-subject one: 0.98)
        assert s["dice_median"] > 0.9, s
        assert s["rmsd_median_mm"] < 3.0, s  # a failed fit is off by centimetres
    with open(tmp_path / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    case = f"atlas-{int(pop.subject_ids[0]):03d}-intact"
    assert [r["case_id"] for r in rows] == [case] * 3
    for name in ("summary.md", "segmentation.png", "store.sqlite", f"meshes/{case}.npz"):
        assert (tmp_path / name).is_file(), name
    # The downstream studies read the kept meshes (and the store: nothing is segmented again).
    V = segmented_population(pop, tmp_path, 1, seed=2, workers=0)
    assert V.shape == pop.vertices.shape
    assert np.array_equal(V[1:], pop.vertices[1:])
    # segmented, not the truth: near it, vertex for vertex, as far as a 5-subject prior allows
    assert 0 < np.median(np.linalg.norm(V[0] - pop.vertices[0], axis=-1)) < 10.0
