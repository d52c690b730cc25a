"""The leave-one-out target-pose study: outputs, determinism, and (with the atlas) accuracy."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from helpers.synthetic import make_population
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.atlas import Atlas, load_atlas
from pelvicnav.studies.target_pose import (
    SUMMARY_FIELDS,
    TargetPoseSettings,
    run_target_pose_study,
)


def _read(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def synthetic_atlas():
    V, faces, *_ = make_population(16, seed=1, shape_sd=0.01)
    return Atlas(subject_ids=tuple(range(1, 17)), vertices=V, faces=faces, source="synthetic")


def test_study_outputs_on_a_synthetic_population(synthetic_atlas, tmp_path):
    settings = TargetPoseSettings(subjects=(1, 2), seed=3)
    rows = run_target_pose_study(synthetic_atlas, tmp_path, settings)
    for name in ("cases.csv", "summary.csv", "comparisons.csv", "settings.json"):
        assert (tmp_path / name).is_file()
    assert (tmp_path / "target_pose_boxplot.png").read_bytes()[:4] == b"\x89PNG"
    assert not list(tmp_path.glob("*.part*"))
    cases = _read(tmp_path / "cases.csv")
    assert len(cases) == len(rows)
    # 2 subjects x (2 unilateral x 5 methods + bilateral x 4 methods x 2 bones)
    assert len(cases) == 2 * (2 * 5 + 4 * 2)
    summary = _read(tmp_path / "summary.csv")
    assert tuple(summary[0]) == SUMMARY_FIELDS
    assert {r["method"] for r in summary} == {"SSM_single", "CM", "SPM", "SPM_CC", "SPM_collision"}
    assert {r["dislocated_bone"] for r in summary} == {"left_hip", "right_hip", "both_hips"}
    cm_both = next(
        r for r in summary if r["method"] == "CM" and r["dislocated_bone"] == "both_hips"
    )
    assert cm_both["n"] == "0"  # mirroring cannot do bilateral dislocations
    # Anyone can recompute the errors from the poses written to cases.csv.
    for r in cases[:6]:
        T_true = np.array([float(r[f"true_{i}{j}"]) for i in range(4) for j in range(4)]).reshape(
            4, 4
        )
        T_est = np.array([float(r[f"est_{i}{j}"]) for i in range(4) for j in range(4)]).reshape(
            4, 4
        )
        eps = tf.invert(T_true) @ T_est
        assert np.linalg.norm(eps[:3, 3]) == pytest.approx(float(r["translation_mm"]), abs=1e-3)
        angle = np.degrees(np.linalg.norm(tf.rotvec_from_matrix(eps[:3, :3])))
        assert angle == pytest.approx(float(r["rotation_deg"]), abs=1e-3)


def test_study_is_deterministic(synthetic_atlas, tmp_path):
    settings = TargetPoseSettings(subjects=(4,), seed=9, methods=("SPM", "SPM_CC"))
    run_target_pose_study(synthetic_atlas, tmp_path / "a", settings)
    run_target_pose_study(synthetic_atlas, tmp_path / "b", settings)
    assert (tmp_path / "a" / "cases.csv").read_text() == (tmp_path / "b" / "cases.csv").read_text()


def test_bad_settings(synthetic_atlas, tmp_path):
    with pytest.raises(ValueError, match="unknown method 'ICP'"):
        TargetPoseSettings(methods=("ICP",))
    with pytest.raises(ValueError, match="unknown scenario"):
        TargetPoseSettings(scenarios=("sacrum",))
    with pytest.raises(ValueError, match="unknown subject id 99"):
        run_target_pose_study(synthetic_atlas, tmp_path, TargetPoseSettings(subjects=(99,)))
    with pytest.raises(ValueError, match="at least 5 subjects"):
        run_target_pose_study(synthetic_atlas.subset([0, 1, 2]), tmp_path, TargetPoseSettings())


@pytest.mark.atlas
@pytest.mark.slow
def test_reduced_study_on_the_real_atlas(real_atlas_path, tmp_path):
    """CI's reduced version of `make study-target-pose`: 6 test subjects, models from 39."""
    atlas = load_atlas(real_atlas_path)
    settings = TargetPoseSettings(subjects=atlas.subject_ids[:6], workers=2)
    run_target_pose_study(atlas, tmp_path, settings)
    summary = {(r["method"], r["dislocated_bone"]): r for r in _read(tmp_path / "summary.csv")}
    spm_cc = summary[("SPM_CC", "left_hip")]
    assert int(spm_cc["n"]) == 6
    # Generous bounds: the full study's medians are in the closing notes and docs.
    assert float(spm_cc["translation_median_mm"]) < 4.0
    assert float(spm_cc["rotation_median_deg"]) < 4.0
    # Sub-millimetre errors would mean the true pose leaked into the estimate.
    cases = _read(tmp_path / "cases.csv")
    assert np.median([float(r["translation_mm"]) for r in cases if r["method"] == "SPM_CC"]) > 0.8


@pytest.mark.atlas
def test_estimate_does_not_move_with_the_true_pose_on_the_atlas(real_atlas_path):
    from pelvicnav.pose.target import TargetPlanner

    atlas = load_atlas(real_atlas_path)
    V = atlas.vertices
    planner = TargetPlanner.fit(V[1:], atlas.faces, observed=("sacrum", "left_hip"))
    observed = {"sacrum": V[0, 0], "left_hip": V[0, 1]}
    a = planner.estimate(observed, {"right_hip": V[0, 2]})["right_hip"].vertices
    moved = tf.apply(tf.from_params([15.0, -5.0, 8.0], np.deg2rad([4.0, -7.0, 2.0])), V[0, 2])
    b = planner.estimate(observed, {"right_hip": moved})["right_hip"].vertices
    np.testing.assert_allclose(a, b, atol=1e-6)


@pytest.mark.atlas
def test_our_ssm_matches_the_atlas_statismo_models(real_atlas_path):
    from pelvicnav.io.atlas import BONE_FILES
    from pelvicnav.io.statismo import read_statismo
    from pelvicnav.shape.reference import compare_with_reference
    from pelvicnav.shape.ssm import ShapeModel

    atlas = load_atlas(real_atlas_path)
    for b, bone in enumerate(atlas.bones):
        ref = read_statismo(real_atlas_path / "SSM" / f"{BONE_FILES[bone][1]}.h5")
        np.testing.assert_array_equal(ref.faces, atlas.faces[b])
        c = compare_with_reference(ShapeModel.fit(atlas.vertices[:, b]), ref.mean, ref.variances)
        assert c["mean_rms_relative"] < 0.02  # < 2% of the bone's RMS radius
        assert c["spectrum_correlation"] > 0.99
        assert c["max_fraction_difference"] < 0.05


def test_study_fits_per_fold_models_never_the_packaged_one(synthetic_atlas, tmp_path, monkeypatch):
    """The packaged model was fitted on every atlas subject: scoring it on them would leak."""

    def refuse(*args, **kwargs):
        raise AssertionError("the leave-one-out study must not load the packaged pelvis model")

    monkeypatch.setattr("pelvicnav.model.file._read", refuse)
    monkeypatch.setattr("pelvicnav.model.load_model", refuse)
    monkeypatch.setattr("pelvicnav.model.file.load_model", refuse)
    settings = TargetPoseSettings(subjects=(1,), seed=0, methods=("SPM_CC",))
    rows = run_target_pose_study(synthetic_atlas, tmp_path, settings)
    assert rows and all(r["method"] == "SPM_CC" for r in rows)


def test_study_runs_on_the_runner_resumable_and_parallel_alike(synthetic_atlas, tmp_path):
    import sqlite3

    from pelvicnav.studies.store import StoreMismatch

    settings = TargetPoseSettings(subjects=(2, 5), seed=4, methods=("SPM_CC",))
    run_target_pose_study(synthetic_atlas, tmp_path / "serial", settings)
    serial = (tmp_path / "serial" / "cases.csv").read_text()
    # A fold lost from the store (a killed run) is run again; the others are not.
    store = tmp_path / "serial" / "store.sqlite"
    with sqlite3.connect(store) as db:
        db.execute("DELETE FROM cases WHERE study = 'target-pose' AND case_id = 'subject-005'")
    run_target_pose_study(synthetic_atlas, tmp_path / "serial", settings)
    assert (tmp_path / "serial" / "cases.csv").read_text() == serial
    parallel = TargetPoseSettings(subjects=(2, 5), seed=4, methods=("SPM_CC",), workers=2)
    run_target_pose_study(synthetic_atlas, tmp_path / "parallel", parallel)
    assert (tmp_path / "parallel" / "cases.csv").read_text() == serial
    with pytest.raises(StoreMismatch, match="other settings"):
        other = TargetPoseSettings(subjects=(2, 5), seed=5, methods=("SPM_CC",))
        run_target_pose_study(synthetic_atlas, tmp_path / "serial", other)
