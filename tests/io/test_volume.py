"""One volume reader: DICOM series (written here with pydicom), NIfTI, NRRD, MHA; clear refusals."""

from __future__ import annotations

import warnings

import numpy as np
import pydicom
import pytest
from scipy.spatial.transform import Rotation

from pelvicnav.geometry import transforms as tf
from pelvicnav.io.dicom_ct import write_ct_series
from pelvicnav.io.volume import (
    VolumeFileError,
    check_ct_hu,
    read_ct,
    read_volume,
    write_volume,
)


def _affine(angles_deg, spacing, origin, flips=(1, 1, 1)):
    R = Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix() * np.asarray(flips)
    A = np.eye(4)
    A[:3, :3] = R * np.asarray(spacing)
    A[:3, 3] = origin
    return A


def _ct(rng, shape=(9, 7, 5)):
    return rng.integers(-1024, 2500, shape).astype(np.int16)


@pytest.mark.parametrize(
    ("angles", "flips"),
    [
        ((0, 0, 0), (1, 1, 1)),  # axial, the usual
        ((10, -20, 35), (1, 1, 1)),  # oblique
        ((0, 0, 0), (-1, -1, 1)),  # i towards the right, j anterior (a RAS-stored volume)
        ((5, 80, -30), (-1, 1, -1)),  # oblique and flipped
    ],
)
def test_dicom_series_round_trip(tmp_path, angles, flips):
    rng = np.random.default_rng(0)
    data = _ct(rng)
    A = _affine(angles, (0.7, 0.9, 2.5), (-100.123456789, 50.5, -1200.25), flips)
    write_ct_series(tmp_path / "ct", data, A)
    back, A2 = read_volume(tmp_path / "ct")
    assert back.dtype == np.int16
    np.testing.assert_array_equal(back, data)
    np.testing.assert_allclose(A2, A, atol=1e-6)
    # One file of the series reads the whole series.
    back1, A3 = read_volume(sorted((tmp_path / "ct").iterdir())[2])
    np.testing.assert_array_equal(back1, data)
    np.testing.assert_allclose(A3, A, atol=1e-6)


def test_dicom_slice_axis_against_the_normal_reads_back_as_the_same_voxels(tmp_path):
    rng = np.random.default_rng(1)
    data = _ct(rng)
    A = _affine((3, -4, 20), (0.8, 0.8, 2.0), (10.0, -20.0, 30.0), (1, 1, -1))  # det < 0
    write_ct_series(tmp_path / "ct", data, A)
    back, A2 = read_volume(tmp_path / "ct")
    assert np.linalg.det(A2[:3, :3]) > 0
    # Same voxels at the same world positions: index k of the file is nk - 1 - k of ours.
    np.testing.assert_array_equal(back, data[:, :, ::-1])
    ijk = np.argwhere(np.ones(data.shape, bool))
    ours = ijk.copy()
    ours[:, 2] = data.shape[2] - 1 - ours[:, 2]
    np.testing.assert_allclose(tf.apply(A2, ijk), tf.apply(A, ours), atol=1e-6)


@pytest.mark.parametrize("suffix", [".nrrd", ".mha", ".nii.gz"])
def test_other_formats_round_trip(tmp_path, suffix):
    rng = np.random.default_rng(2)
    data = _ct(rng)
    A = _affine((10, 0, -15), (0.6, 0.6, 1.25), (1.5, -2.5, 3.5), (-1, 1, 1))
    path = write_volume(tmp_path / f"ct{suffix}", data, A)
    back, A2 = read_volume(path)
    np.testing.assert_array_equal(back, data)
    np.testing.assert_allclose(A2, A, atol=1e-5 if suffix == ".nii.gz" else 1e-9)
    assert not list(tmp_path.glob("*.part*"))


def _two_series(folder, rng, sizes):
    A = _affine((0, 0, 0), (1, 1, 2), (0, 0, 0))
    uids = []
    for n, k in enumerate(sizes):
        files = write_ct_series(folder / f"s{n}", _ct(rng, (6, 6, k)), A)
        for f in files:
            f.rename(folder / f"s{n}_{f.name}")
        (folder / f"s{n}").rmdir()
        uids.append(str(pydicom.dcmread(folder / f"s{n}_{files[0].name}").SeriesInstanceUID))
    return uids


def test_largest_series_is_read_and_a_tie_is_refused(tmp_path):
    rng = np.random.default_rng(4)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    uids = _two_series(mixed, rng, (8, 2))
    (mixed / "README.txt").write_text("not DICOM")
    with pytest.warns(UserWarning, match="several series; reading the largest"):
        data, _ = read_volume(mixed)
    assert data.shape == (6, 6, 8)
    data, _ = read_volume(mixed, series=uids[1])
    assert data.shape == (6, 6, 2)
    with pytest.raises(VolumeFileError, match="no series 1.2.3"):
        read_volume(mixed, series="1.2.3")
    tie = tmp_path / "tie"
    tie.mkdir()
    _two_series(tie, rng, (4, 4))
    with pytest.raises(VolumeFileError, match=r"several image series of the same size.*--series"):
        read_volume(tie)


def test_dicom_refusals_name_the_folder(tmp_path):
    rng = np.random.default_rng(5)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("hello")
    with pytest.raises(VolumeFileError, match=r"empty: no DICOM image series"):
        read_volume(empty)
    A = _affine((0, 0, 0), (1, 1, 2), (0, 0, 0))
    one = tmp_path / "one"
    write_ct_series(one, _ct(rng, (6, 6, 1)), A)
    with pytest.raises(VolumeFileError, match="a single slice is not a 3D volume"):
        read_volume(one)
    tilted = tmp_path / "tilted"
    files = write_ct_series(tilted, _ct(rng, (6, 6, 5)), A)
    for k, f in enumerate(files):  # gantry tilt: each slice shifted along y
        ds = pydicom.dcmread(f)
        x, y, z = (float(v) for v in ds.ImagePositionPatient)
        ds.ImagePositionPatient = [x, y + 0.35 * k * 2, z]
        ds.save_as(f)
    with pytest.raises(VolumeFileError, match=r"tilted.*gantry tilt"):
        read_volume(tilted)
    dup = tmp_path / "dup"
    files = write_ct_series(dup, _ct(rng, (6, 6, 3)), A)
    ds = pydicom.dcmread(files[1])
    ds.ImagePositionPatient = pydicom.dcmread(files[0]).ImagePositionPatient
    ds.save_as(files[1])
    with pytest.raises(VolumeFileError, match="same position"):
        read_volume(dup)
    with pytest.raises(VolumeFileError, match="not found"):
        read_volume(tmp_path / "missing.nii.gz")
    (tmp_path / "x.vol").write_text("?")
    with pytest.raises(VolumeFileError, match="unknown volume format"):
        read_volume(tmp_path / "x.vol")
    (tmp_path / "broken.nrrd").write_text("NRRD0004\nbroken")
    with pytest.raises(VolumeFileError, match=r"broken\.nrrd: not a readable"):
        read_volume(tmp_path / "broken.nrrd")


def test_uneven_slices_are_resampled_with_a_warning(tmp_path):
    k = np.arange(6, dtype=np.float64)
    data = np.broadcast_to(k * 100, (4, 4, 6)).astype(np.int16)  # value = 100 * slice
    A = _affine((0, 0, 0), (1, 1, 2), (0, 0, 0))
    files = write_ct_series(tmp_path / "ct", data, A)
    files[3].unlink()  # a missing slice
    with pytest.warns(UserWarning, match="uneven slice spacing"):
        back, A2 = read_volume(tmp_path / "ct")
    assert back.shape == (4, 4, 6)
    np.testing.assert_allclose(back[0, 0], k * 100, atol=1e-3)  # slice 3 interpolated
    np.testing.assert_allclose(A2, A, atol=1e-6)


def test_not_3d_is_refused(tmp_path):
    import nibabel as nib
    import SimpleITK as sitk

    nib.save(nib.Nifti1Image(np.zeros((4, 5), np.int16), np.eye(4)), tmp_path / "flat.nii.gz")
    with pytest.raises(VolumeFileError, match="expected a 3D volume"):
        read_volume(tmp_path / "flat.nii.gz")
    sitk.WriteImage(sitk.Image(4, 5, sitk.sitkInt16), str(tmp_path / "flat.mha"))
    with pytest.raises(VolumeFileError, match=r"flat\.mha: expected a scalar 3D volume"):
        read_volume(tmp_path / "flat.mha")


def test_ct_hu_checks():
    rng = np.random.default_rng(6)
    body = rng.normal(40, 20, (20, 20, 20))
    body[:3] = -1000
    body[8:12, 8:12, 8:12] = 700
    check_ct_hu(body)  # a CT
    check_ct_hu(np.where(body > 200, body, 0))  # masked to a constant
    check_ct_hu(np.where(np.arange(20)[:, None, None] < 2, -3024, body))  # padding
    with pytest.raises(VolumeFileError, match="no bone"):
        check_ct_hu(np.clip(body, -1000, 100), source="soft.nii.gz")
    with pytest.raises(VolumeFileError, match="without the rescale"):
        check_ct_hu(body + 1024, source="raw.nii.gz")
    with pytest.raises(VolumeFileError, match="not Hounsfield units"):
        check_ct_hu(body * 100)


def test_read_ct_checks_hu(tmp_path):
    A = _affine((0, 0, 0), (1, 1, 1), (0, 0, 0))
    write_volume(tmp_path / "water.nrrd", np.zeros((5, 5, 5), np.int16), A)
    with pytest.raises(VolumeFileError, match=r"water\.nrrd: no bone"):
        read_ct(tmp_path / "water.nrrd")


def test_no_warning_for_a_clean_series(tmp_path):
    rng = np.random.default_rng(7)
    write_ct_series(tmp_path / "ct", _ct(rng), _affine((0, 0, 0), (1, 1, 2), (0, 0, 0)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_volume(tmp_path / "ct")


def test_an_independently_written_series_with_rescale_and_shuffled_files(tmp_path):
    """Slices written here with pydicom alone: unsigned stored values, Rescale Intercept -1024,
    a coronal orientation, file names in no particular order."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    rng = np.random.default_rng(8)
    hu = rng.integers(-1024, 2000, (6, 5, 7)).astype(np.int16)
    row_dir, col_dir = np.array([1.0, 0, 0]), np.array([0, 0, -1.0])  # coronal slices
    normal = np.cross(row_dir, col_dir)  # (0, 1, 0): posterior
    origin, (dr, dc, dz) = np.array([-50.0, -80.0, 120.0]), (0.75, 0.6, 1.5)
    series, study = generate_uid(), generate_uid()
    for k in rng.permutation(hu.shape[2]):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2"
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = meta.MediaStorageSOPClassUID, generate_uid()
        ds.Modality, ds.SeriesInstanceUID, ds.StudyInstanceUID = "CT", series, study
        ds.ImagePositionPatient = [f"{x:.6f}" for x in origin + k * dz * normal]
        ds.ImageOrientationPatient = [f"{x:g}" for x in (*row_dir, *col_dir)]
        ds.PixelSpacing = [f"{dr:g}", f"{dc:g}"]
        ds.Rows, ds.Columns = hu.shape[1], hu.shape[0]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
        ds.RescaleIntercept, ds.RescaleSlope = "-1024", "1"
        ds.PixelData = np.ascontiguousarray((hu[:, :, k].T + 1024).astype(np.uint16)).tobytes()
        ds.save_as(tmp_path / f"IM{rng.integers(1e6):06d}", enforce_file_format=True)
    data, A = read_volume(tmp_path)
    np.testing.assert_array_equal(data, hu)
    expected = np.eye(4)
    expected[:3, 0], expected[:3, 1], expected[:3, 2] = row_dir * dc, col_dir * dr, normal * dz
    expected[:3, 3] = origin
    np.testing.assert_allclose(A, expected, atol=1e-6)


def test_labels_stored_with_other_axes_are_put_on_the_cts_grid(tmp_path):
    from pelvicnav.io.volume import read_labels

    rng = np.random.default_rng(9)
    labels = rng.integers(0, 4, (6, 5, 4)).astype(np.uint8)
    A = _affine((0, 0, 0), (0.8, 0.8, 2.0), (-10.0, 20.0, 30.0))
    # the same grid, stored RAS-wise with i and j reversed and the axes permuted
    flipped = labels[::-1, ::-1, :].transpose(2, 0, 1)
    B = np.eye(4)
    B[:3, 0] = A[:3, 2]  # stored axis 0 = our k
    B[:3, 1] = -A[:3, 0]  # stored axis 1 = our i reversed
    B[:3, 2] = -A[:3, 1]  # stored axis 2 = our j reversed
    B[:3, 3] = A[:3, 3] + 5 * A[:3, 0] + 4 * A[:3, 1]
    write_volume(tmp_path / "ts.nii.gz", flipped, B)
    np.testing.assert_array_equal(read_labels(tmp_path / "ts.nii.gz", labels.shape, A), labels)
    write_volume(tmp_path / "same.nrrd", labels, A)
    np.testing.assert_array_equal(read_labels(tmp_path / "same.nrrd", labels.shape, A), labels)
    shifted = A.copy()
    shifted[:3, 3] += 0.4  # a fraction of a voxel off: another grid
    write_volume(tmp_path / "off.nrrd", labels, shifted)
    with pytest.raises(VolumeFileError, match=r"off\.nrrd: label map grid .* does not match"):
        read_labels(tmp_path / "off.nrrd", labels.shape, A)
    with pytest.raises(VolumeFileError, match="does not match"):
        read_labels(tmp_path / "same.nrrd", (6, 5, 5), A)


def test_label_boxes_match_a_direct_search_on_any_strides():
    from pelvicnav.io.volume import label_boxes

    rng = np.random.default_rng(3)
    lab = np.zeros((30, 25, 20), dtype=np.uint8)
    lab[3:9, 4:20, 2:5] = 1
    lab[10:28, 1:3, 7:19] = 2
    lab[rng.integers(0, 30), rng.integers(0, 25), rng.integers(0, 20)] = 7
    for view in (lab, np.asfortranarray(lab), lab.transpose(2, 0, 1), lab[::-1, :, ::-1]):
        boxes = label_boxes(view, [1, 2, 3, 7])
        assert boxes[3] is None
        for v in (1, 2, 7):
            ijk = np.argwhere(view == v)
            lo, hi = ijk.min(0), ijk.max(0)
            expected = tuple(slice(int(a), int(b) + 1) for a, b in zip(lo, hi, strict=True))
            assert boxes[v] == expected
    assert label_boxes(lab.astype(np.int32) - 1, [-1, 0])[-1] == (slice(0, 30), slice(0, 25),
                                                                  slice(0, 20))  # fmt: skip


def test_label_stats_match_numpy_on_any_strides():
    from pelvicnav.io.volume import label_stats

    rng = np.random.default_rng(4)
    lab = np.zeros((30, 25, 20), dtype=np.uint8)
    lab[3:9, 4:20, 2:5] = 1
    lab[10:28, 1:3, 7:19] = 2
    hu = rng.integers(-1000, 1500, size=lab.shape).astype(np.int16)
    pairs = [(lab, hu), (np.asfortranarray(lab), np.asfortranarray(hu)),
             (lab.transpose(2, 0, 1), hu.transpose(2, 0, 1)),
             (lab[::-1, :, ::-1], hu[::-1, :, ::-1].astype(np.float32))]  # fmt: skip
    for view, ct in pairs:
        stats = label_stats(view, ct, [1, 2, 3])
        assert stats[3].count == 0 and stats[3].box is None
        for v in (1, 2):
            mask = view == v
            ijk = np.argwhere(mask)
            assert stats[v].count == mask.sum()
            np.testing.assert_allclose(stats[v].centroid_ijk, ijk.mean(0), atol=1e-9)
            assert stats[v].median_hu == np.median(ct[mask])
            box = tuple(slice(int(a), int(b) + 1) for a, b in zip(ijk.min(0), ijk.max(0),
                                                                  strict=True))  # fmt: skip
            assert stats[v].box == box
    with pytest.raises(ValueError, match="same 3D grid"):
        label_stats(lab, hu[:-1], [1])


def test_gzipped_nifti_1_and_2_read_as_nibabel_reads_them(tmp_path):
    import nibabel as nib

    rng = np.random.default_rng(5)
    data = rng.integers(-1000, 2000, size=(7, 6, 5)).astype(np.int16)
    affine = np.diag([-0.8, -0.8, 1.5, 1.0])
    for image_class in (nib.Nifti1Image, nib.Nifti2Image):
        path = tmp_path / f"{image_class.__name__}.nii.gz"
        nib.save(image_class(data, affine), path)
        got, A = read_volume(path)
        expected = nib.load(path)
        np.testing.assert_array_equal(got, np.asarray(expected.dataobj))
        assert got.dtype == np.int16
        np.testing.assert_allclose(A, np.diag([-1, -1, 1, 1.0]) @ expected.affine)
    (tmp_path / "broken.nii.gz").write_bytes(b"not gzip at all")
    with pytest.raises(VolumeFileError, match=r"broken.nii.gz: not a readable NIfTI"):
        read_volume(tmp_path / "broken.nii.gz")
