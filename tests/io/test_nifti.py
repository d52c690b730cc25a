"""The gzipped-NIfTI fast path (header parsed without nibabel) against nibabel itself."""

from __future__ import annotations

import gzip

import nibabel as nib
import numpy as np
import pytest

from pelvicnav.io.nifti import LPS_TO_RAS, _read_gz_unscaled, read_nifti

A_RAS = np.array([[-0.8, 0.01, 0, 100.0], [0, -0.8, 0, 50.0], [0, 0.02, 2.0, -700.0], [0, 0, 0, 1]])


def _nibabel(path):
    img = nib.load(path)
    return np.asarray(img.dataobj), img.affine


def _image(dtype, shape=(5, 6, 7), seed=0):
    rng = np.random.default_rng(seed)
    data = rng.integers(0, 120, size=shape).astype(dtype)
    img = nib.Nifti1Image(data, A_RAS)
    img.set_sform(A_RAS, code=1)
    return img


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.int32, np.float32, np.float64])
def test_plain_files_read_without_nibabel_as_nibabel_reads_them(tmp_path, dtype):
    path = tmp_path / "v.nii.gz"
    nib.save(_image(dtype), path)
    fast = _read_gz_unscaled(path)
    assert fast is not None  # the plain case takes the fast path
    data, affine = _nibabel(path)
    np.testing.assert_array_equal(fast[0], data)
    assert fast[0].dtype == data.dtype and fast[0].flags.writeable and fast[0].flags.f_contiguous
    np.testing.assert_array_equal(fast[1], affine)
    back, world_from_ijk = read_nifti(path)
    np.testing.assert_allclose(world_from_ijk, LPS_TO_RAS @ affine)


def test_big_endian_file_is_read_with_its_byte_order(tmp_path):
    img = _image(np.int16)
    be = nib.Nifti1Image(
        np.asarray(img.dataobj).astype(">i2"), A_RAS, img.header.as_byteswapped(">")
    )
    be.set_sform(A_RAS, code=1)
    path = tmp_path / "be.nii.gz"
    nib.save(be, path)
    assert be.header.endianness == ">"
    fast = _read_gz_unscaled(path)
    assert fast is not None
    np.testing.assert_array_equal(fast[0], _nibabel(path)[0])
    np.testing.assert_array_equal(fast[1], _nibabel(path)[1])


def test_other_files_go_to_nibabel_and_read_the_same(tmp_path):
    qform_only = _image(np.int16)
    qform_only.set_sform(None, code=0)
    qform_only.set_qform(A_RAS @ np.diag([1, 1, 1, 1.0]), code=1)
    scaled = _image(np.int16)
    scaled.header.set_slope_inter(2.0, -1024.0)
    nifti2 = nib.Nifti2Image(np.asarray(_image(np.int16).dataobj), A_RAS)
    for name, img in (("qform.nii.gz", qform_only), ("scaled.nii.gz", scaled),
                      ("two.nii.gz", nifti2)):  # fmt: skip
        path = tmp_path / name
        nib.save(img, path)
        assert _read_gz_unscaled(path) is None, name
        data, affine = _nibabel(path)
        back, world_from_ijk = read_nifti(path)
        np.testing.assert_array_equal(back, data)
        np.testing.assert_allclose(world_from_ijk, LPS_TO_RAS @ affine)


def test_two_gzip_members_and_truncated_files(tmp_path):
    path = tmp_path / "v.nii.gz"
    nib.save(_image(np.int16), path)
    raw = gzip.decompress(path.read_bytes())
    two = tmp_path / "two_members.nii.gz"  # valid gzip; its trailer states the second member
    two.write_bytes(gzip.compress(raw[:500]) + gzip.compress(raw[500:]))
    assert _read_gz_unscaled(two) is None
    np.testing.assert_array_equal(read_nifti(two)[0], _nibabel(path)[0])
    cut = tmp_path / "cut.nii.gz"
    cut.write_bytes(path.read_bytes()[:-40])
    with pytest.raises(ValueError, match=r"cut\.nii\.gz: not a readable NIfTI"):
        read_nifti(cut)
    four_d = tmp_path / "four.nii.gz"
    nib.save(_image(np.int16, shape=(4, 5, 6, 2)), four_d)
    with pytest.raises(ValueError, match=r"four\.nii\.gz: expected a 3D volume"):
        read_nifti(four_d)
