"""Reading a CT and its bone labels (the two files in threads): the same arrays as reading them
one after the other, and on bad input the same error, the CT's first."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from helpers.labels import label_phantom
from pelvicnav.io.nifti import write_nifti
from pelvicnav.io.volume import read_ct, read_labels
from pelvicnav.workflow.inputs import read_ct_and_bones


def _write(tmp_path, hu, labels, affine, labels_affine=None):
    write_nifti(tmp_path / "ct.nii.gz", hu.astype(np.int16), affine)
    write_nifti(tmp_path / "labels.nii.gz", labels, affine if labels_affine is None
                else labels_affine)  # fmt: skip
    return tmp_path / "ct.nii.gz", tmp_path / "labels.nii.gz"


def test_the_threaded_read_gives_what_the_readers_give_one_after_the_other(tmp_path):
    hu, ours, _, affine = label_phantom()
    ct, labels = _write(tmp_path, hu, ours, affine)
    before = threading.active_count()
    got_hu, got_A, got_ours, centroids = read_ct_and_bones(ct, labels)
    assert threading.active_count() == before  # the readers are joined
    want_hu, want_A = read_ct(ct)
    np.testing.assert_array_equal(got_hu, want_hu)
    np.testing.assert_array_equal(got_A, want_A)
    np.testing.assert_array_equal(got_ours, read_labels(labels, want_hu.shape, want_A))
    for value, bone in enumerate(("sacrum", "left_hip", "right_hip"), start=1):
        ijk = np.argwhere(ours == value).mean(axis=0)
        np.testing.assert_allclose(centroids[bone], affine[:3, :3] @ ijk + affine[:3, 3])


def test_bad_files_are_refused_naming_them_the_cts_error_first(tmp_path):
    hu, ours, _, affine = label_phantom()
    shifted = affine.copy()
    shifted[:3, 3] += 1.0  # half a voxel: another grid
    ct, labels = _write(tmp_path, hu, ours, affine, shifted)
    with pytest.raises(ValueError, match=r"labels\.nii\.gz: label map grid .* does not match"):
        read_ct_and_bones(ct, labels)
    with pytest.raises(ValueError, match=r"missing\.nii\.gz: file not found"):
        read_ct_and_bones(ct, tmp_path / "missing.nii.gz")
    write_nifti(tmp_path / "ct.nii.gz", np.zeros((4, 4), np.int16), affine)  # not 3D
    with pytest.raises(ValueError, match=r"ct\.nii\.gz: expected a 3D volume"):
        read_ct_and_bones(ct, tmp_path / "missing.nii.gz")  # both bad: the CT's error
