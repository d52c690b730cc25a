"""The typed plan: versioned JSON round trip, validation naming the file, the CT fingerprint."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.io.plan import CTReference, Plan, fingerprint, read_plan, write_plan


def _plan(tmp_path, data=None):
    data = np.arange(24, dtype=np.int16).reshape(2, 3, 4) if data is None else data
    A = np.diag([0.8, 0.8, 2.0, 1.0])
    (tmp_path / "labels.nii.gz").write_bytes(b"x")
    (tmp_path / "meshes").mkdir(exist_ok=True)
    (tmp_path / "meshes" / "left_hip.vtk").write_bytes(b"x")
    T = tf.from_params([3.0, -2.0, 1.0], np.deg2rad([2.0, 1.0, -3.0]))
    return Plan(ct=CTReference.of(tmp_path / "ct.nii.gz", data, A), dislocated=("left_hip",),
                targets={"left_hip": T}, meshes={"left_hip": "meshes/left_hip.vtk"},
                decision={"mode": "given"}, method="test")  # fmt: skip


def test_plan_round_trip_and_register_keys(tmp_path):
    plan = _plan(tmp_path)
    path = write_plan(tmp_path, plan)
    back = read_plan(tmp_path)
    assert back.identity == plan.identity
    assert back.dislocated == ("left_hip",) and back.reference_bone == "sacrum"
    np.testing.assert_allclose(back.targets["left_hip"], plan.targets["left_hip"])
    np.testing.assert_allclose(back.ct.world_from_ijk, plan.ct.world_from_ijk)
    doc = json.loads(path.read_text())
    assert doc["dislocated_bone"] == "left_hip"  # what `pelvicnav register --plan` reads
    np.testing.assert_allclose(doc["target_from_current"], plan.targets["left_hip"])


def test_plan_validation_names_the_file(tmp_path):
    path = write_plan(tmp_path, _plan(tmp_path))
    doc = json.loads(path.read_text())
    cases = (
        ({"format": "other"}, "not a pelvicnav plan"),
        ({"version": 2}, "plan version 2"),
        ({"targets_from_current": {"left_hip": np.diag([2.0, 2, 2, 1]).tolist()}}, "must be rigid"),
        ({"targets_from_current": {"left_hip": [[1, 2]]}}, "4 x 4"),
        ({"dislocated": ["femur"]}, "must be left_hip or right_hip"),
        ({"dislocated": ["left_hip", "right_hip"]}, "one target per dislocated bone"),
        ({"reference_bone": "left_hip"}, "reference bone"),
        ({"ct": {"path": "x"}}, "missing 'fingerprint'"),
    )
    for change, message in cases:
        (tmp_path / "bad.json").write_text(json.dumps(doc | change))
        with pytest.raises(ValueError, match=message) as err:
            read_plan(tmp_path / "bad.json")
        assert "bad.json" in str(err.value)
    (tmp_path / "meshes" / "left_hip.vtk").unlink()
    with pytest.raises(ValueError, match=r"meshes/left_hip\.vtk is missing"):
        read_plan(tmp_path)


def test_ct_fingerprint_refuses_another_ct(tmp_path):
    data = np.arange(24, dtype=np.int16).reshape(2, 3, 4)
    plan = _plan(tmp_path, data)
    A = plan.ct.world_from_ijk
    plan.ct.check(data.copy(), A, source="same.nii.gz")
    other = data.copy()
    other[0, 0, 0] += 1
    for d, M in ((other, A), (data, A @ np.diag([1, 1, 1.01, 1])), (data.astype(np.int32), A)):
        with pytest.raises(ValueError, match=r"other\.nii\.gz: this is not the CT the plan"):
            plan.ct.check(d, M, source="other.nii.gz")
    assert fingerprint(data, A) == plan.ct.fingerprint
