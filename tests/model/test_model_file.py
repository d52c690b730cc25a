"""The packaged pelvis model: contents, round trip, the wheel, and refusal of bad files."""

from __future__ import annotations

import zipfile
from importlib.resources import files

import numpy as np
import pytest

from pelvicnav import BONES
from pelvicnav.model import (
    MODEL_ENV,
    OBSERVED_SETS,
    ModelFileError,
    load_model,
    resolve_model_path,
    save_model,
)
from pelvicnav.shape.mesh import is_closed, signed_volume


@pytest.fixture(scope="module")
def model():
    return load_model()


def test_packaged_model_is_found_through_importlib_resources(monkeypatch):
    monkeypatch.delenv(MODEL_ENV, raising=False)
    packaged = files("pelvicnav.data").joinpath("pelvis_model_v1.npz")
    assert packaged.is_file()
    assert resolve_model_path() == resolve_model_path(str(packaged))
    notice = files("pelvicnav.data").joinpath("NOTICE").read_text()
    assert "10.1088/1361-6560/ab1456" in notice and "CC BY 4.0" in notice
    assert "NOT FOR CLINICAL USE" in notice


def test_packaged_model_contents(model):
    p = model.provenance
    assert p["doi"] == "10.1088/1361-6560/ab1456" and p["licence"] == "CC BY 4.0"
    assert p["note"] == "not for clinical use"
    assert len(model.subject_ids) == 40 and p["pelvicnav_version"] and p["created"]
    assert set(model.planners) == set(OBSERVED_SETS)
    for b, bone in enumerate(BONES):
        ssm = model.shapes[bone]
        assert ssm.mean.shape == (model.n_vertices, 3)
        gram = ssm.modes.T @ ssm.modes
        np.testing.assert_allclose(gram, np.eye(ssm.n_modes), atol=1e-4)
        assert np.all(np.diff(ssm.variances) <= 0)
        assert is_closed(model.faces[b]) and signed_volume(ssm.mean, model.faces[b]) > 0
    # Order does not matter when asking for a planner; an impossible set is refused.
    assert model.planner(("right_hip", "sacrum")) is model.planners[("sacrum", "right_hip")]
    with pytest.raises(ValueError, match="no planner"):
        model.planner(("left_hip",))


def test_round_trip(model, tmp_path):
    path = save_model(model, tmp_path / "copy.npz")
    again = load_model(path)
    for bone in BONES:
        np.testing.assert_allclose(again.shapes[bone].modes, model.shapes[bone].modes, atol=1e-7)
    for key, planner in model.planners.items():
        other = again.planners[key]
        np.testing.assert_allclose(other.model.modes, planner.model.modes)
        assert other.min_gap == planner.min_gap
    assert again.provenance == model.provenance


def test_environment_variable_chooses_the_file(model, tmp_path, monkeypatch):
    path = save_model(model, tmp_path / "mine.npz")
    monkeypatch.setenv(MODEL_ENV, str(path))
    assert resolve_model_path() == path
    monkeypatch.setenv(MODEL_ENV, str(tmp_path / "absent.npz"))
    with pytest.raises(FileNotFoundError, match="absent.npz"):
        load_model()


def _rewrite(src, dst, change):
    with np.load(src) as npz:
        arrays = {k: npz[k] for k in npz.files}
    change(arrays)
    np.savez_compressed(dst, **arrays)
    return dst


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda a: a.update(format_version=np.array(99)), "format version"),
        (lambda a: [a.pop(k) for k in list(a) if k.startswith("ssm/left_hip/")], "ssm/left_hip"),
        (lambda a: a.update({"ssm/sacrum/modes": a["ssm/sacrum/modes"][:-3]}), "shape"),
        (lambda a: a.update({"faces/sacrum": a["faces/sacrum"] + 10**6}), "indices"),
        (lambda a: a.update(provenance=np.array("{not json")), "JSON"),
    ],
    ids=["version", "missing-bone", "mode-shape", "faces", "provenance"],
)
def test_bad_model_files_are_refused_naming_the_file(tmp_path, change, message):
    bad = _rewrite(resolve_model_path(), tmp_path / "bad.npz", change)
    with pytest.raises(ModelFileError, match=message) as err:
        load_model(bad)
    assert str(bad) in str(err.value)


def test_truncated_and_corrupt_files_are_refused(tmp_path):
    data = resolve_model_path().read_bytes()
    for name, content in (("truncated.npz", data[: len(data) // 2]), ("noise.npz", b"\x00" * 999)):
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(ModelFileError, match="not a readable pelvis model") as err:
            load_model(path)
        assert str(path) in str(err.value)


@pytest.mark.slow
def test_the_built_wheel_contains_the_model(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(tmp_path), str(root)],
        check=True, capture_output=True,
    )  # fmt: skip
    (wheel,) = tmp_path.glob("pelvicnav-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "pelvicnav/data/pelvis_model_v1.npz" in names
    assert "pelvicnav/data/NOTICE" in names
