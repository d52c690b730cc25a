"""views.json and NIfTI I/O: round trips and clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pelvicnav.geometry import projection as pj
from pelvicnav.io.nifti import read_nifti, write_nifti
from pelvicnav.io.views import View, read_views, write_views


def _view(name="ap", rows=8, cols=10):
    carm = pj.CArm(rows=rows, cols=cols)
    img = np.arange(rows * cols, dtype=np.float32).reshape(rows, cols)
    return View(name, img, carm.projection_matrix, carm.pixel_spacing, {"dose_ugy": 5.0}), carm


def test_views_round_trip(tmp_path):
    v, carm = _view()
    w, _ = _view("oblique30", 6, 7)
    path = write_views(tmp_path, [v, w], degrees_of_freedom=9)
    views, dof = read_views(path)
    assert dof == 9
    assert [x.name for x in views] == ["ap", "oblique30"]
    np.testing.assert_array_equal(views[0].image, v.image)
    np.testing.assert_allclose(views[0].projection_matrix, carm.projection_matrix)
    np.testing.assert_allclose(views[0].source, carm.source, atol=1e-9)
    assert views[0].meta["dose_ugy"] == 5.0
    assert not list(tmp_path.glob("*.part"))


def test_views_bad_files(tmp_path):
    v, _ = _view()
    path = write_views(tmp_path, [v])
    doc = json.loads(path.read_text())
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"broken\.json: not valid JSON"):
        read_views(tmp_path / "broken.json")
    with pytest.raises(ValueError, match="file not found"):
        read_views(tmp_path / "missing.json")
    bad = dict(doc)
    bad["views"] = [dict(doc["views"][0], rows=99)]
    (tmp_path / "shape.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"shape.json, view 0: image ap.npy has shape \(8, 10\)"):
        read_views(tmp_path / "shape.json")
    bad["views"] = [dict(doc["views"][0], projection_matrix=np.zeros((3, 4)).tolist())]
    (tmp_path / "singular.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="singular"):
        read_views(tmp_path / "singular.json")
    nan = v.image.copy()
    nan[0, 0] = np.nan
    np.save(tmp_path / "ap.npy", nan)
    with pytest.raises(ValueError, match="NaN"):
        read_views(path)
    bad["views"] = [{"image": "ap.npy"}]
    (tmp_path / "missing_key.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="missing 'projection_matrix'"):
        read_views(tmp_path / "missing_key.json")


def test_nifti_round_trip_keeps_lps(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.integers(-1000, 2000, size=(5, 6, 7)).astype(np.int16)
    A = np.array([[0.8, 0, 0, -100.0], [0, 0.8, 0, -50.0], [0, 0, 2.0, -700.0], [0, 0, 0, 1]])
    write_nifti(tmp_path / "ct.nii.gz", data, A)
    back, A2 = read_nifti(tmp_path / "ct.nii.gz")
    np.testing.assert_array_equal(back, data)
    np.testing.assert_allclose(A2, A, atol=1e-5)
    (tmp_path / "junk.nii.gz").write_bytes(b"junk")
    with pytest.raises(ValueError, match=r"junk\.nii\.gz: not a readable NIfTI"):
        read_nifti(tmp_path / "junk.nii.gz")
