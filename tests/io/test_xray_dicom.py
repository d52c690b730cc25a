"""X-ray DICOM into views: geometry from the tags, written here by an independent pydicom writer.

The writer below works from PS3.3 C.8.7.5 directly: the positioner angles are the longitude and
latitude of the direction from the isocentre to the detector (0/0: the patient faces the
detector, +90 primary at the patient's left, +90 secondary cranial), taken from the source
position of a projection matrix; the image axes from its RQ decomposition. It shares no code
with pelvicnav's writer.
"""

from __future__ import annotations

import json

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

from pelvicnav.geometry import projection as pj
from pelvicnav.io.views import read_views
from pelvicnav.io.xray_dicom import (
    CArmProfile,
    XrayFileError,
    convert_views,
    read_profile,
    read_xray,
    write_xray_dicom,
)

ISO = (12.5, -30.25, 101.75)


def _letters(v):
    names = {0: "RL", 1: "AP", 2: "FH"}
    return "".join(names[a][int(v[a] > 0)] for a in np.argsort(-np.abs(v)) if abs(v[a]) > 1e-3)


def _independent_dicom(path, carm: pj.CArm, pixels, *, frames=None, drop=(), extra=None,
                       orientation=True, mirrored=False):  # fmt: skip
    """A DICOM XA file for ``carm``'s view, from first principles."""
    P = carm.projection_matrix
    dec = pj.decompose_projection(P)
    beam = np.asarray(carm.isocenter) - dec.source
    d = beam / np.linalg.norm(beam)  # isocentre -> detector
    primary = np.degrees(np.arctan2(d[0], -d[1]))
    secondary = np.degrees(np.arcsin(d[2]))
    row_dir, col_dir = (
        dec.carm_from_world[0],
        dec.carm_from_world[1],
    )  # world axes of columns and rows
    if mirrored:
        row_dir = -row_dir
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.12.1"
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = meta.MediaStorageSOPClassUID, generate_uid()
    ds.Modality, ds.PatientID, ds.PatientName = "XA", "TEST-1", "TEST^PATIENT"
    ds.StudyInstanceUID, ds.SeriesInstanceUID = generate_uid(), generate_uid()
    values = {
        "PositionerPrimaryAngle": f"{round(primary, 10) + 0.0:.12g}",
        "PositionerSecondaryAngle": f"{round(secondary, 10) + 0.0:.12g}",
        "DistanceSourceToDetector": f"{carm.source_to_detector:.12g}",
        "DistanceSourceToPatient": f"{carm.source_to_isocenter:.12g}",
        "ImagerPixelSpacing": [f"{x:.12g}" for x in carm.pixel_spacing],
        "PatientPosition": "HFS",
    }
    if orientation:
        values["PatientOrientation"] = [_letters(row_dir), _letters(col_dir)]
    for key, value in values.items():
        if key not in drop:
            setattr(ds, key, value)
    pixels = np.asarray(pixels)
    n = 1 if pixels.ndim == 2 else pixels.shape[0]
    ds.Rows, ds.Columns = pixels.shape[-2:]
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME1"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.PixelIntensityRelationship = "LIN"
    if n > 1:
        ds.NumberOfFrames = n
    for key, value in (extra or {}).items():
        setattr(ds, key, value)
    ds.PixelData = np.ascontiguousarray(pixels, dtype=np.uint16).tobytes()
    ds.save_as(path, enforce_file_format=True)
    return path


def _line_integrals(rows, cols, rng):
    """A phantom's line integrals with air around it (what a flat-field estimate needs)."""
    r, c = np.mgrid[0:rows, 0:cols]
    p = 3.0 * np.exp(-(((r - rows / 2) / (rows / 4)) ** 2 + ((c - cols / 2) / (cols / 5)) ** 2))
    p = p + 0.2 * rng.random((rows, cols)) * (p > 0.05)
    return np.where(p > 0.05, p, 0.0)


def _raw(p, i0=40000.0):
    return np.round(i0 * np.exp(-p))


CARMS = [
    pj.CArm(rows=48, cols=64, isocenter=ISO),  # AP
    pj.CArm(rows=48, cols=64, isocenter=ISO, orbit_deg=30, tilt_deg=-20),  # the paper's 2nd
    pj.CArm(rows=48, cols=64, isocenter=ISO, tilt_deg=40),  # inlet
    pj.CArm(rows=48, cols=64, isocenter=ISO, orbit_deg=90),  # lateral
    pj.CArm(rows=48, cols=64, isocenter=ISO, orbit_deg=-135, tilt_deg=25,
            source_to_detector=1200, source_to_isocenter=700, pixel_spacing=(0.4, 0.45)),
]  # fmt: skip


@pytest.mark.parametrize("carm", CARMS, ids=["ap", "oblique30", "inlet", "lateral", "compound"])
def test_independent_dicom_gives_the_simulators_projection(tmp_path, carm):
    rng = np.random.default_rng(0)
    p = _line_integrals(carm.rows, carm.cols, rng)
    f = _independent_dicom(tmp_path / "x.dcm", carm, _raw(p))
    (view,) = read_xray(f, isocenter=ISO)
    P0, P1 = (pj.normalize_projection(P) for P in (carm.projection_matrix, view.projection_matrix))
    assert np.abs(P1 - P0).max() <= 1e-6 * np.abs(P0).max()
    # LIN, MONOCHROME1 raw intensities -> -ln(I / I0), I0 from the air.
    np.testing.assert_allclose(view.image, p, atol=2e-3)
    assert view.meta["dicom"]["patient_id"] == "TEST-1"
    assert "principal point at the detector centre" in view.meta["assumed"]
    assert view.meta["flipped"] == []


def test_mirrored_image_is_flipped_back(tmp_path):
    carm = CARMS[1]
    p = _line_integrals(carm.rows, carm.cols, np.random.default_rng(1))
    f = _independent_dicom(tmp_path / "x.dcm", carm, _raw(p)[:, ::-1], mirrored=True)
    (view,) = read_xray(f, isocenter=ISO)
    assert view.meta["flipped"] == ["columns"]
    np.testing.assert_allclose(view.image, p, atol=2e-3)
    np.testing.assert_allclose(view.projection_matrix, carm.projection_matrix, rtol=1e-9, atol=1e-9)


def test_multiframe_run_with_angle_increments(tmp_path):
    carm = CARMS[0]
    p = _line_integrals(carm.rows, carm.cols, np.random.default_rng(2))
    frames = np.stack([_raw(p)] * 3)
    f = _independent_dicom(tmp_path / "run.dcm", carm, frames, orientation=False,
                           extra={"PositionerMotion": "DYNAMIC",
                                  "PositionerPrimaryAngleIncrement": ["0", "10", "25"],
                                  "PositionerSecondaryAngleIncrement": "-5"})  # fmt: skip
    views = read_xray(f, isocenter=ISO)
    assert [v.name for v in views] == ["run_f000", "run_f001", "run_f002"]
    for v, (do, dt) in zip(views, [(0, 0), (10, 5), (25, 10)], strict=True):
        expected = pj.CArm(rows=48, cols=64, isocenter=ISO, orbit_deg=do, tilt_deg=dt)
        np.testing.assert_allclose(v.projection_matrix, expected.projection_matrix, atol=1e-6)
    bad = _independent_dicom(tmp_path / "bad.dcm", carm, frames,
                             extra={"PositionerPrimaryAngleIncrement": ["0", "10"]})  # fmt: skip
    with pytest.raises(
        XrayFileError, match=r"bad\.dcm: inconsistent geometry.*\(0018,1520\) has 2"
    ):
        read_xray(bad, isocenter=ISO)
    dyn = _independent_dicom(tmp_path / "dyn.dcm", carm, frames,
                             extra={"PositionerMotion": "DYNAMIC"})  # fmt: skip
    with pytest.raises(XrayFileError, match=r"dyn\.dcm: Positioner Motion is DYNAMIC"):
        read_xray(dyn, isocenter=ISO)


def test_missing_geometry_needs_a_profile(tmp_path):
    carm = CARMS[1]
    raw = _raw(_line_integrals(carm.rows, carm.cols, np.random.default_rng(3)))
    no_spacing = _independent_dicom(tmp_path / "a.dcm", carm, raw, drop=("ImagerPixelSpacing",))
    with pytest.raises(XrayFileError, match=r"a\.dcm: no ImagerPixelSpacing \(0018,1164\)"):
        read_xray(no_spacing, isocenter=ISO)
    no_sdd = _independent_dicom(tmp_path / "b.dcm", carm, raw, drop=("DistanceSourceToDetector",))
    with pytest.raises(XrayFileError, match=r"b\.dcm: no DistanceSourceToDetector \(0018,1110\)"):
        read_xray(no_sdd, isocenter=ISO)
    profile_path = tmp_path / "carm.json"
    profile_path.write_text(json.dumps({"source_to_detector_mm": carm.source_to_detector,
                                        "pixel_spacing_mm": list(carm.pixel_spacing)}))  # fmt: skip
    profile = read_profile(profile_path)
    for f in (no_spacing, no_sdd):
        (view,) = read_xray(f, isocenter=ISO, profile=profile)
        np.testing.assert_allclose(view.projection_matrix, carm.projection_matrix, atol=1e-6)
        assert any("from the profile" in a for a in view.meta["assumed"])
    no_angles = _independent_dicom(tmp_path / "c.dcm", carm, raw, drop=("PositionerPrimaryAngle",))
    with pytest.raises(XrayFileError, match=r"PositionerPrimaryAngle \(0018,1510\)"):
        read_xray(no_angles, isocenter=ISO)


def test_bad_profiles_and_files(tmp_path):
    with pytest.raises(XrayFileError, match="unknown keys"):
        CArmProfile.from_dict({"sdd": 1000}, "p.json")
    with pytest.raises(XrayFileError, match="pixel_spacing_mm must be 2"):
        CArmProfile.from_dict({"pixel_spacing_mm": 0.3}, "p.json")
    (tmp_path / "junk.dcm").write_bytes(b"not dicom at all")
    with pytest.raises(XrayFileError, match=r"junk\.dcm: not a readable DICOM image"):
        read_xray(tmp_path / "junk.dcm", isocenter=ISO)
    with pytest.raises(XrayFileError, match="file not found"):
        read_xray(tmp_path / "missing.dcm", isocenter=ISO)
    carm = CARMS[0]
    raw = _raw(_line_integrals(carm.rows, carm.cols, np.random.default_rng(4)))
    f = _independent_dicom(tmp_path / "odd.dcm", carm, raw)
    ds = pydicom.dcmread(f)
    ds.PatientOrientation = ["F", "L"]  # rows and columns swapped: a detector turned 90 deg
    ds.save_as(f)
    with pytest.raises(XrayFileError, match=r"odd\.dcm: Patient Orientation .* roll_deg"):
        read_xray(f, isocenter=ISO)


def test_pelvicnav_writer_round_trip_and_view_set(tmp_path):
    rng = np.random.default_rng(5)
    files = []
    for n, carm in enumerate(CARMS[:2]):
        p = _line_integrals(carm.rows, carm.cols, rng)
        files.append(write_xray_dicom(tmp_path / f"v{n}.dcm", p, carm, dose_ugy=5.0))
    views = convert_views(files, tmp_path / "set" / "views.json", isocenter=ISO)
    back, dof = read_views(tmp_path / "set" / "views.json")
    assert dof == 6 and [v.name for v in back] == ["v0", "v1"]
    for v, carm in zip(back, CARMS[:2], strict=True):
        np.testing.assert_allclose(v.projection_matrix, carm.projection_matrix, rtol=1e-9)
    assert views[0].meta["dicom"]["modality"] == "XA"
    with pytest.raises(ValueError, match="does not match the detector"):
        write_xray_dicom(tmp_path / "bad.dcm", np.zeros((3, 3)), CARMS[0])
    with pytest.raises(ValueError, match="roll"):
        write_xray_dicom(
            tmp_path / "bad.dcm", np.zeros((48, 64)), pj.CArm(rows=48, cols=64, roll_deg=5)
        )


def test_png_with_sidecar(tmp_path):
    from PIL import Image

    carm = CARMS[1]
    p = _line_integrals(carm.rows, carm.cols, np.random.default_rng(6))
    Image.fromarray(np.round(p * 10000).astype(np.uint16)).save(tmp_path / "shot.png")
    primary, secondary = 30.0 - 180.0, 20.0
    (tmp_path / "shot.json").write_text(json.dumps({
        "source_to_detector_mm": 1100, "source_to_isocenter_mm": 600,
        "pixel_spacing_mm": list(carm.pixel_spacing), "primary_angle_deg": primary,
        "secondary_angle_deg": secondary, "intensity": "log",
    }))  # fmt: skip
    (view,) = read_xray(tmp_path / "shot.png", isocenter=ISO)
    np.testing.assert_allclose(view.projection_matrix, carm.projection_matrix, atol=1e-6)
    np.testing.assert_allclose(view.image, np.round(p * 10000), atol=1e-3)
    (tmp_path / "lonely.png").write_bytes((tmp_path / "shot.png").read_bytes())
    with pytest.raises(XrayFileError, match=r"lonely\.png: a PNG/TIFF needs its geometry"):
        read_xray(tmp_path / "lonely.png", isocenter=ISO)
