"""``pelvicnav segment``: with a label map and with the ASM alone; outputs, fit quality, and
refusal of bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from pelvicnav import BONES
from pelvicnav.cli import app
from pelvicnav.io.nifti import write_nifti

runner = CliRunner()


def one_slice(volume):
    k = volume.shape[2] // 2
    return volume[:, :, k : k + 1].astype(np.int16)


@pytest.fixture(scope="module")
def patient(tmp_path_factory):
    """A sampled patient voxelised at 2 mm: CT (bone 300 HU in soft tissue) and labels."""
    from pelvicnav.model import load_model
    from pelvicnav.phantom.ctsynth import bone_labels, voxel_grid
    from pelvicnav.phantom.sampled import sampled_population

    model = load_model()
    truth = sampled_population(seed=5, subject_ids=(1,)).vertices[0]
    shape, A = voxel_grid(truth, (2.0, 2.0, 2.0), np.full((3, 2), 12.0))
    labels = bone_labels(truth, model.faces, shape, A)
    root = tmp_path_factory.mktemp("patient")
    write_nifti(root / "ct.nii.gz", np.where(labels > 0, 300, 40).astype(np.int16), A)
    write_nifti(root / "labels.nii.gz", labels, A)
    ts = np.select([labels == 1, labels == 2, labels == 3], [25, 77, 78], 0).astype(np.int16)
    write_nifti(root / "ts.nii.gz", ts, A)
    write_nifti(root / "other.nii.gz", labels[:-1], A)
    write_nifti(root / "nobone.nii.gz", np.full(labels.shape, 40, np.int16), A)
    write_nifti(root / "flat.nii.gz", one_slice(np.where(labels > 0, 300, 40)), A)
    return root, truth


@pytest.mark.slow
def test_segment_from_a_totalsegmentator_map(patient, tmp_path):
    from pelvicnav.io.vtk_legacy import read_polydata

    root, truth = patient
    out = tmp_path / "seg"
    args = ["segment", str(root / "ct.nii.gz"), "--out", str(out), "--labels",
            str(root / "ts.nii.gz"), "--label-scheme", "totalsegmentator"]  # fmt: skip
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    record = json.loads((out / "segmentation.json").read_text())
    for b, bone in enumerate(BONES):
        assert record["bones"][bone]["dice_surface_vs_labels"] > 0.9, record["bones"][bone]
        points, faces = read_polydata(out / f"{bone}.vtk")
        assert points.shape == truth[b].shape
        assert np.median(np.linalg.norm(points - truth[b], axis=1)) < 1.5
        assert (out / f"{bone}.stl").stat().st_size > 80 + 50 * len(faces)
    assert record["model"]["doi"] == "10.1088/1361-6560/ab1456"
    assert (out / "contours.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "labels.nii.gz").is_file()
    assert not list(tmp_path.glob(".seg-*"))


def test_segment_refuses_bad_input_and_writes_nothing(patient, tmp_path):
    root, _ = patient
    out = tmp_path / "seg"
    ct = str(root / "ct.nii.gz")
    for image, args, message in (
        (str(root / "nobone.nii.gz"), [], "no bone"),
        (str(root / "flat.nii.gz"), [], "3D volume"),
        (ct, ["--labels", str(root / "ts.nii.gz")], "totalsegmentator"),
        (ct, ["--labels", str(root / "other.nii.gz")], "does not match the CT"),
        (
            ct,
            ["--labels", str(root / "labels.nii.gz"), "--label-scheme", "sacrum=1"],
            "no label for",
        ),
        (ct, ["--labels", str(root / "missing.nii.gz")], "file not found"),
    ):
        res = runner.invoke(app, ["segment", image, "--out", str(out), *args])
        assert res.exit_code == 2, (args, res.output)
        assert message in res.output, res.output
        assert image in res.output.replace("\n", "") or "--labels" in args, res.output
        assert not out.exists()
