"""The pelvicnav command line: help, atlas commands, demo, and clear errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from pelvicnav.cli import app

runner = CliRunner()


def test_help_runs_without_heavy_imports():
    # --help must not import numpy/scipy (kept inside commands so it answers at once).
    code = (
        "import sys; from pelvicnav.cli import app; "
        "print('numpy' in sys.modules, 'scipy' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]
    res = runner.invoke(app, ["--help"])
    assert res.exit_code == 0
    assert "atlas" in res.output and "demo" in res.output


def test_atlas_info(tiny_atlas):
    res = runner.invoke(app, ["atlas", "info", "--atlas", str(tiny_atlas)])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())  # rich wraps long paths at the terminal's width
    assert "3 subjects" in text
    assert "left_hip" in text and "subjects: 1, 2, 3" in text


def test_atlas_info_bad_input(tiny_atlas, tmp_path):
    res = runner.invoke(app, ["atlas", "info", "--atlas", str(tmp_path / "nowhere")])
    assert res.exit_code == 2
    assert "no pelvis atlas" in res.output
    (tiny_atlas / "surface" / "left" / "LeftHip1_cpd.vtk").write_text("garbage")
    res = runner.invoke(app, ["atlas", "info", "--atlas", str(tiny_atlas)])
    assert res.exit_code == 2
    assert "LeftHip1_cpd.vtk" in res.output and "Traceback" not in res.output


def test_atlas_download_from_url(tiny_atlas, tmp_path):
    import zipfile

    archive = tmp_path / "a.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        for f in tiny_atlas.rglob("*"):
            if f.is_file():
                zf.write(f, "repo-main/" + f.relative_to(tiny_atlas).as_posix())
    dest = tmp_path / "installed"
    # A 3-subject archive is not the 40-subject atlas: validation must refuse it.
    res = runner.invoke(app, ["atlas", "download", "--dest", str(dest), "--url", archive.as_uri()])
    assert res.exit_code == 2
    assert "lists 3 subjects, expected 40" in res.output
    assert not dest.exists()


@pytest.mark.atlas
def test_atlas_info_real(real_atlas_path):
    res = runner.invoke(app, ["atlas", "info", "--atlas", str(real_atlas_path)])
    assert res.exit_code == 0, res.output
    assert "40 subjects, 5000 vertices/bone" in " ".join(res.output.split())


def test_demo_without_atlas_runs_on_the_packaged_model(tmp_path, monkeypatch):
    monkeypatch.delenv("PELVICNAV_ATLAS", raising=False)
    monkeypatch.setenv("COLUMNS", "200")  # rich wraps at the terminal width
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    res = runner.invoke(app, ["demo", "--tour", "--out", str(tmp_path / "demo")])
    assert res.exit_code == 0, res.output
    assert "C-arm views" in res.output and "from model" in res.output
    assert "the packaged pelvis model" in res.output
    assert "SPM_CC  target error" in res.output
    for name in ("atlas_projection.png", "target_pose.png"):
        assert (tmp_path / "demo" / name).read_bytes()[:4] == b"\x89PNG"


def test_demo_with_atlas_writes_figure(tiny_atlas, tmp_path):
    out = tmp_path / "demo"
    res = runner.invoke(app, ["demo", "--tour", "--out", str(out), "--atlas", str(tiny_atlas)])
    assert res.exit_code == 0, res.output
    png = out / "atlas_projection.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert os.path.getsize(png) > 10_000


def test_study_commands_report_missing_atlas(tmp_path, monkeypatch):
    monkeypatch.delenv("PELVICNAV_ATLAS", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    missing = ["--atlas", str(tmp_path / "nowhere")]
    for args in (
        ["study", "target-pose", "--out", str(tmp_path / "o"), *missing],
        ["study", "spm-modes", "--out", str(tmp_path / "m.png"), *missing],
        ["study", "population", "--out", str(tmp_path / "p"), *missing],
        ["simulate", "--subject", "1", "--out", str(tmp_path / "c"), *missing],
        ["study", "ssm-reference"],  # needs the atlas's statismo models: no fallback
    ):
        res = runner.invoke(app, args)
        assert res.exit_code == 2, args
        assert "no pelvis atlas" in res.output
    res = runner.invoke(
        app, ["study", "target-pose", "--out", str(tmp_path / "o"), "--segmentation", "labels"]
    )
    assert res.exit_code == 2
    assert "'truth' or 'asm'" in res.output
    assert not (tmp_path / "o").exists()


def test_population_study_and_spm_modes_offline(tmp_path, monkeypatch):
    monkeypatch.delenv("PELVICNAV_ATLAS", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    res = runner.invoke(
        app, ["study", "population", "--out", str(tmp_path / "p"), "--subjects", "3"]
    )
    assert res.exit_code == 0, res.output
    assert "pelvic width" in (tmp_path / "p" / "sizes.md").read_text()
    assert (tmp_path / "p" / "population.png").read_bytes()[:4] == b"\x89PNG"
    out = tmp_path / "modes.png"
    res = runner.invoke(app, ["study", "spm-modes", "--atlas", "procedural", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert out.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.atlas
def test_population_study_against_the_atlas(real_atlas_path, tmp_path):
    res = runner.invoke(
        app, ["study", "population", "--out", str(tmp_path), "--atlas", str(real_atlas_path),
              "--subjects", "12"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    text = (tmp_path / "sizes.md").read_text()
    assert "atlas range" in text and "| NO |" not in text


@pytest.mark.atlas
def test_spm_modes_figure_on_real_atlas(real_atlas_path, tmp_path):
    out = tmp_path / "modes.png"
    res = runner.invoke(
        app, ["study", "spm-modes", "--atlas", str(real_atlas_path), "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert out.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.atlas
def test_demo_plans_a_reduction_on_the_real_atlas(real_atlas_path, tmp_path):
    res = runner.invoke(
        app, ["demo", "--tour", "--out", str(tmp_path), "--atlas", str(real_atlas_path)]
    )
    assert res.exit_code == 0, res.output
    assert "SPM_CC  target error" in res.output
    assert (tmp_path / "target_pose.png").read_bytes()[:4] == b"\x89PNG"


def test_simulate_bad_input(tiny_atlas, tmp_path):
    out = tmp_path / "case"
    base = ["simulate", "--atlas", str(tiny_atlas), "--out", str(out)]
    for args, message in (
        (["--subject", "99"], "unknown subject id 99"),
        (["--subject", "1", "--dose", "0"], "dose must be a positive"),
        (["--subject", "1", "--views", "ap,sideways"], "unknown view 'sideways'"),
        (["--subject", "1", "--pattern", "twist"], "unknown dislocation pattern 'twist'"),
        (["--subject", "1", "--bone", "sacrum"], "only an innominate"),
    ):
        res = runner.invoke(app, base + args)
        assert res.exit_code == 2, (args, res.output)
        assert message in res.output
        assert not out.exists()


@pytest.mark.slow
def test_simulate_without_atlas_samples_the_packaged_model(tmp_path, monkeypatch):
    import numpy as np

    from pelvicnav.io.nifti import read_nifti
    from pelvicnav.io.vtk_legacy import read_polydata
    from pelvicnav.model import load_model
    from pelvicnav.phantom.sampled import sampled_population

    monkeypatch.delenv("PELVICNAV_ATLAS", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "case"
    res = runner.invoke(
        app, ["simulate", "--subject", "3", "--out", str(out), "--views", "ap", "--seed", "1"]
    )
    assert res.exit_code == 0, res.output
    assert "sampled from the pelvis model" in res.output
    labels, _ = read_nifti(out / "labels.nii.gz")
    assert set(np.unique(labels)) == {0, 1, 2, 3}
    truth = json.loads((out / "truth.json").read_text())
    assert truth["subject_id"] == 3
    # The ground-truth meshes: the sampled subject 3, as it lies in the written CT.
    model = load_model()
    subject = sampled_population(subject_ids=(3,)).vertices[0]
    moved = truth["dislocation"]["bone"]
    for b, bone in enumerate(("sacrum", "left_hip", "right_hip")):
        points, faces = read_polydata(out / "meshes" / f"{bone}.vtk")
        np.testing.assert_array_equal(faces, model.faces[b])
        T = np.asarray(truth["poses_world_from_ct"][bone])
        expected = subject[b] @ T[:3, :3].T + T[:3, 3]
        np.testing.assert_allclose(points, expected, atol=1e-9)
        assert (bone == moved) == (not np.allclose(T, np.eye(4)))


@pytest.mark.atlas
@pytest.mark.slow
def test_simulate_writes_a_case(real_atlas_path, tmp_path):
    import numpy as np

    from pelvicnav.geometry import transforms as tf
    from pelvicnav.io.nifti import read_nifti
    from pelvicnav.io.views import read_views

    out = tmp_path / "case"
    res = runner.invoke(
        app,
        ["simulate", "--atlas", str(real_atlas_path), "--subject", "10", "--out", str(out),
         "--dose", "5", "--views", "ap,inlet", "--seed", "3"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    views, dof = read_views(out / "views.json")
    assert [v.name for v in views] == ["ap", "inlet"]
    assert dof == 6
    ct, A = read_nifti(out / "ct.nii.gz")
    labels, _ = read_nifti(out / "labels.nii.gz")
    assert ct.shape == labels.shape
    assert set(np.unique(labels)) == {0, 1, 2, 3}
    truth = json.loads((out / "truth.json").read_text())
    D = np.array(truth["poses_world_from_ct"]["left_hip"])
    moved = np.linalg.norm(tf.se3_log(D))  # a real (rigid) dislocation, not the identity
    assert moved > 0.1
    np.testing.assert_allclose(truth["poses_world_from_ct"]["sacrum"], np.eye(4))
    assert truth["dislocation"]["pattern"] == "open-book"


def test_register_bad_input_writes_nothing(tmp_path):
    import numpy as np

    from pelvicnav.geometry import projection as pj
    from pelvicnav.io.nifti import write_nifti
    from pelvicnav.io.views import View, write_views

    A = np.diag([2.0, 2.0, 2.0, 1.0])
    ct = np.full((20, 20, 20), 300, dtype=np.int16)
    labels = np.zeros((20, 20, 20), dtype=np.uint8)
    labels[8:12], labels[14:18], labels[2:6] = 1, 2, 3  # sacrum between, left hip at +x (LPS)
    write_nifti(tmp_path / "ct.nii.gz", ct, A)
    write_nifti(tmp_path / "labels.nii.gz", labels, A)
    write_nifti(tmp_path / "two.nii.gz", np.where(labels == 3, 0, labels).astype(np.uint8), A)
    carm = pj.CArm(rows=32, cols=32)
    write_views(tmp_path, [View("ap", np.zeros((32, 32), np.float32), carm.projection_matrix,
                                carm.pixel_spacing)])  # fmt: skip
    (tmp_path / "broken.json").write_text("{not json")
    (tmp_path / "femur.json").write_text(
        json.dumps({"dislocated_bone": "femur", "target_from_current": np.eye(4).tolist()})
    )
    from pelvicnav.workflow.register import ct_fingerprint

    eye, P = np.eye(4).tolist(), carm.projection_matrix.tolist()
    fingerprint = ct_fingerprint(ct, A)
    for name, poses, ct_record, Ps in (
        ("other_bones", {"sacrum": eye, "left_hip": eye}, fingerprint, [P]),
        ("other_ct", dict.fromkeys(("sacrum", "left_hip", "right_hip"), eye),
         ct_fingerprint(ct + 1, A), [P]),
        ("two_views", dict.fromkeys(("sacrum", "left_hip", "right_hip"), eye), fingerprint, [P, P]),
    ):  # fmt: skip
        (tmp_path / f"{name}.json").write_text(
            json.dumps({"poses": poses, "ct": ct_record, "projection_matrices": Ps})
        )
    out = tmp_path / "result.json"
    base = ["register", "--ct", str(tmp_path / "ct.nii.gz"), "--out", str(out)]
    views = ["--views", str(tmp_path / "views.json")]
    for args, message in (
        (["--labels", str(tmp_path / "two.nii.gz"), *views], "right_hip (label 3) has 0 mm^3"),
        (["--labels", str(tmp_path / "labels.nii.gz"), "--views", str(tmp_path / "broken.json")],
         "not valid JSON"),
        (["--labels", str(tmp_path / "labels.nii.gz"), *views, "--dof", "7"], "--dof must be"),
        (["--labels", str(tmp_path / "labels.nii.gz"), *views, "--plan",
          str(tmp_path / "broken.json")], "not valid JSON"),
        (["--labels", str(tmp_path / "labels.nii.gz"), *views, "--plan",
          str(tmp_path / "femur.json")], "dislocated_bone 'femur' is not one of"),
        (["--labels", str(tmp_path / "labels.nii.gz"), *views, "--init",
          str(tmp_path / "other_bones.json")], "a result for the bones"),
        (["--labels", str(tmp_path / "labels.nii.gz"), *views, "--init",
          str(tmp_path / "other_ct.json")], "is for another CT"),
        (["--labels", str(tmp_path / "labels.nii.gz"), *views, "--init",
          str(tmp_path / "two_views.json")], "has 2 view(s), this view set 1"),
        (["--labels", str(tmp_path / "labels.nii.gz"), *views, "--init",
          str(tmp_path / "femur.json")], "not a pelvicnav result"),
    ):  # fmt: skip
        res = runner.invoke(app, base + args)
        assert res.exit_code == 2, (args, res.output)
        assert message in res.output, res.output
        assert not out.exists()


def test_register_a_simulated_case_end_to_end(tmp_path, monkeypatch):
    """`pelvicnav simulate --dicom` then `pelvicnav register --plan --overlay`: the DICOM CT and
    `views from-dicom` read as the NIfTI and .npy files do, and every bone is found from them."""
    import numpy as np
    import pydicom

    from pelvicnav.geometry import projection as pj
    from pelvicnav.geometry import transforms as tf
    from pelvicnav.io.itk_transform import read_pose_tfm
    from pelvicnav.io.nifti import read_nifti
    from pelvicnav.io.views import read_views

    monkeypatch.delenv("PELVICNAV_ATLAS", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    case = tmp_path / "case"
    res = runner.invoke(
        app, ["simulate", "--subject", "1", "--out", str(case), "--seed", "0", "--dicom"]
    )
    assert res.exit_code == 0, res.output
    truth = json.loads((case / "truth.json").read_text())
    # the same radiographs through DICOM: XA files whose tags carry the geometry
    iso = ",".join(repr(x) for x in truth["views"]["ap"]["isocenter"])
    xrays = [str(case / "dicom" / "xray" / f"{v}.dcm") for v in ("ap", "oblique30")]
    res = runner.invoke(app, ["views", "from-dicom", *xrays, "--out",
                              str(case / "dicom" / "views.json"), "--isocenter", iso])  # fmt: skip
    assert res.exit_code == 0, res.output
    # the patient moved by M after the images were set up: P' = P M, so each bone is at M^-1
    M = tf.from_params([6.0, -5.0, 4.0], np.deg2rad([2.0, -1.0, 2.5]))
    for path in (case / "views.json", case / "dicom" / "views.json"):
        views = json.loads(path.read_text())
        for v in views["views"]:
            v["projection_matrix"] = (np.asarray(v["projection_matrix"]) @ M).tolist()
            v.pop("source_mm", None)
        path.write_text(json.dumps(views))
    npy, dcm = (read_views(p)[0] for p in (case / "views.json", case / "dicom" / "views.json"))
    for a, b in zip(npy, dcm, strict=True):
        P, Q = (pj.normalize_projection(v.projection_matrix) for v in (a, b))
        assert np.abs(P - Q).max() <= 1e-6 * np.abs(P).max()
    plan = tmp_path / "plan.json"
    plan.write_text(
        json.dumps({"dislocated_bone": truth["dislocation"]["bone"],
                    "target_from_current": np.eye(4).tolist()})
    )  # fmt: skip
    # The DICOM CT reads as the NIfTI one (same voxels, affines within the NIfTI's float32), the
    # DICOM X-rays as the .npy ones (up to the constant of the flat-field estimate, and 16-bit
    # quantisation): one registration from DICOM stands for both.
    from pelvicnav.io.volume import read_ct

    (hu_n, A_n), (hu_d, A_d) = (read_ct(p) for p in (case / "ct.nii.gz", case / "dicom" / "ct"))
    assert np.array_equal(hu_n, hu_d) and np.abs(A_n - A_d).max() < 1e-3
    for a, b in zip(npy, dcm, strict=True):
        assert np.ptp(a.image - b.image) <= 1e-3 * np.abs(a.image).max()
    out = tmp_path / "dicom" / "result.json"
    res = runner.invoke(app, [
        "register", "--ct", str(case / "dicom" / "ct"), "--labels", str(case / "labels.nii.gz"),
        "--views", str(case / "dicom" / "views.json"), "--plan", str(plan), "--out", str(out),
        "--overlay", str(tmp_path / "dicom" / "overlays"), "--overlay-dicom", "--seed", "0",
    ])  # fmt: skip
    assert res.exit_code == 0, res.output
    result = json.loads(out.read_text())
    assert result["converged"], result["warnings"]
    # the CT is the patient as imaged (truth: the sacrum's pose), then moved by M^-1
    labels, world_from_ijk = read_nifti(case / "labels.nii.gz")
    setup = tf.invert(M) @ np.asarray(truth["poses_world_from_ct"]["sacrum"])
    for value, bone in enumerate(("sacrum", "left_hip", "right_hip"), start=1):
        c = tf.apply(world_from_ijk, np.argwhere(labels == value).mean(axis=0)[None])
        err = np.linalg.norm(tf.apply(np.asarray(result["poses"][bone]), c) - tf.apply(setup, c))
        assert err < 1.5, (bone, err)
    assert "residual" in result and [s["name"] for s in result["stages"]] == ["stage 1", "stage 2"]
    assert sorted(p.name for p in (tmp_path / "dicom" / "overlays").iterdir()) == [
        "overlay_ap.dcm", "overlay_ap.png", "overlay_oblique30.dcm", "overlay_oblique30.png",
    ]  # fmt: skip
    # transforms/{bone}.tfm beside result.json: ITK convention, the inverse is the pose
    for bone in ("sacrum", "left_hip", "right_hip"):
        np.testing.assert_allclose(read_pose_tfm(tmp_path / "dicom" / "transforms" / f"{bone}.tfm"),
                                   result["poses"][bone], atol=1e-9)  # fmt: skip
    assert (tmp_path / "dicom" / "transforms" / "residual.tfm").is_file()
    sc = pydicom.dcmread(tmp_path / "dicom" / "overlays" / "overlay_ap.dcm")
    xa = pydicom.dcmread(xrays[0])
    assert sc.PhotometricInterpretation == "RGB" and sc.Modality == "OT"
    assert (sc.PatientID, sc.StudyInstanceUID) == (xa.PatientID, xa.StudyInstanceUID)
    assert sc.SourceImageSequence[0].ReferencedSOPInstanceUID == xa.SOPInstanceUID
    # A later frame (the patient moved another 3 mm / 2 deg): --init tracks from this result.
    assert result["mode"] == "first"
    M2 = tf.from_params([2.0, -1.5, 1.5], np.deg2rad([1.0, 1.0, -1.0])) @ M
    views = json.loads((case / "dicom" / "views.json").read_text())
    for v in views["views"]:
        v["projection_matrix"] = (np.asarray(v["projection_matrix"]) @ tf.invert(M) @ M2).tolist()
    (case / "dicom" / "views.json").write_text(json.dumps(views))
    frame2 = tmp_path / "dicom" / "frame2.json"
    res = runner.invoke(app, [
        "register", "--ct", str(case / "dicom" / "ct"), "--labels", str(case / "labels.nii.gz"),
        "--views", str(case / "dicom" / "views.json"), "--plan", str(plan), "--out", str(frame2),
        "--init", str(out),
    ])  # fmt: skip
    assert res.exit_code == 0, res.output
    second = json.loads(frame2.read_text())
    assert second["mode"] == "tracking", second["warnings"]
    # the same CT folder and labels: the bone models came from the first call's cache
    assert (result["models_cached"], second["models_cached"]) == (False, True)
    assert second["ct"] == result["ct"]
    setup = tf.invert(M2) @ np.asarray(truth["poses_world_from_ct"]["sacrum"])
    for value, bone in enumerate(("sacrum", "left_hip", "right_hip"), start=1):
        c = tf.apply(world_from_ijk, np.argwhere(labels == value).mean(axis=0)[None])
        err = np.linalg.norm(tf.apply(np.asarray(second["poses"][bone]), c) - tf.apply(setup, c))
        assert err < 1.5, (bone, err)


def test_model_info_and_bad_model_files(tmp_path):
    res = runner.invoke(app, ["model", "info"])
    assert res.exit_code == 0, res.output
    assert "10.1088/1361-6560/ab1456" in res.output and "not for clinical use" in res.output
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    res = runner.invoke(app, ["model", "info", "--model", str(bad)])
    assert res.exit_code == 2
    assert "not a readable pelvis model" in res.output
    res = runner.invoke(app, ["model", "info", "--model", str(tmp_path / "none.npz")])
    assert res.exit_code == 2 and "no pelvis model file" in res.output


def test_model_build_needs_an_atlas(tmp_path, monkeypatch):
    monkeypatch.delenv("PELVICNAV_ATLAS", raising=False)
    out = tmp_path / "m.npz"
    res = runner.invoke(
        app, ["model", "build", "--out", str(out), "--atlas", str(tmp_path / "nowhere")]
    )
    assert res.exit_code == 2 and "no pelvis atlas" in res.output
    assert not out.exists()


def test_register_refuses_a_totalsegmentator_map_passed_as_ours(tmp_path):
    """Its labels 1-3 are the spleen and kidneys: registering them as bones is silent garbage."""
    import numpy as np

    from helpers.labels import label_phantom
    from pelvicnav.geometry.projection import CArm
    from pelvicnav.io.nifti import write_nifti
    from pelvicnav.io.views import View, write_views

    hu, _, total, affine = label_phantom()
    write_nifti(tmp_path / "ct.nii.gz", hu.astype(np.int16), affine)
    write_nifti(tmp_path / "seg.nii.gz", total, affine)
    carm = CArm()
    write_views(tmp_path, [View("ap", np.zeros((16, 16), np.float32), carm.projection_matrix,
                                carm.pixel_spacing)])  # fmt: skip
    out = tmp_path / "result.json"
    args = ["register", "--ct", str(tmp_path / "ct.nii.gz"), "--labels",
            str(tmp_path / "seg.nii.gz"), "--views", str(tmp_path / "views.json"),
            "--out", str(out)]  # fmt: skip
    res = runner.invoke(app, args)
    assert res.exit_code == 2, res.output
    assert "seg.nii.gz" in res.output and "totalsegmentator" in res.output
    assert not out.exists()
    res = runner.invoke(app, [*args, "--label-scheme", "sacrum=25;left_hip=77"])
    assert res.exit_code == 2 and "no label for right_hip" in res.output


def test_views_from_dicom_bad_input_writes_nothing(tmp_path):
    import numpy as np

    from pelvicnav.geometry import projection as pj
    from pelvicnav.io.xray_dicom import write_xray_dicom

    carm = pj.CArm(rows=16, cols=20)
    good = write_xray_dicom(tmp_path / "ap.dcm", np.zeros((16, 20)), carm)
    import pydicom

    ds = pydicom.dcmread(good)
    del ds.ImagerPixelSpacing
    ds.save_as(tmp_path / "nospacing.dcm")
    out = tmp_path / "set" / "views.json"
    base = ["views", "from-dicom", "--out", str(out)]
    for args, message in (
        ([str(good)], "give the isocentre's place"),
        ([str(good), "--isocenter", "1,2"], "must be 3 finite numbers"),
        ([str(good), "--isocenter", "a,b,c"], "--isocenter must be 'x,y,z'"),
        ([str(tmp_path / "nospacing.dcm"), "--isocenter", "0,0,0"], "(0018,1164)"),
        ([str(good), str(tmp_path / "missing.dcm"), "--isocenter", "0,0,0"], "file not found"),
        ([str(good), "--isocenter", "0,0,0", "--dof", "7"], "6 or 9"),
    ):
        res = runner.invoke(app, base + args)
        assert res.exit_code == 2, (args, res.output)
        assert message in res.output.replace("\n", ""), res.output
        assert not out.parent.exists()
    res = runner.invoke(app, [*base, str(good), "--isocenter", "0,0,0"])
    assert res.exit_code == 0, res.output
    assert "assumed: principal point at the detector centre" in " ".join(res.output.split())


def test_register_names_a_bad_dicom_folder(tmp_path):
    import numpy as np

    from pelvicnav.geometry import projection as pj
    from pelvicnav.io.views import View, write_views

    carm = pj.CArm(rows=8, cols=8)
    write_views(tmp_path, [View("ap", np.zeros((8, 8)), carm.projection_matrix, (1.0, 1.0))])
    (tmp_path / "ct").mkdir()
    (tmp_path / "ct" / "notes.txt").write_text("no images here")
    res = runner.invoke(app, [
        "register", "--ct", str(tmp_path / "ct"), "--labels", str(tmp_path / "ct"),
        "--views", str(tmp_path / "views.json"), "--out", str(tmp_path / "r.json"),
    ])  # fmt: skip
    assert res.exit_code == 2
    assert "no DICOM image series" in res.output


def test_study_registration_refuses_a_negative_real_ct_count(tmp_path):
    res = runner.invoke(app, ["study", "registration", "--out", str(tmp_path / "r"),
                              "--real-ct", "-1"])  # fmt: skip
    assert res.exit_code != 0 and "--real-ct must be >= 0" in res.output
    assert not (tmp_path / "r").exists()
