"""Label schemes and the check that a label map's bones are bone, on their sides."""

from __future__ import annotations

import numpy as np
import pytest

from helpers.labels import label_phantom
from pelvicnav.shape.labels import check_bone_labels, parse_scheme, to_bone_labels


def _phantom():
    hu, ours, total, _ = label_phantom()
    return hu, ours, total


AFFINE = label_phantom()[3]


def test_our_labels_pass_and_totalsegmentator_maps_convert():
    hu, ours, total = _phantom()
    check_bone_labels(hu, ours, AFFINE, source="ours.nii.gz")
    converted = to_bone_labels(total, parse_scheme("totalsegmentator"))
    np.testing.assert_array_equal(converted, ours)
    check_bone_labels(hu, converted, AFFINE, source="ts.nii.gz")
    mapped = to_bone_labels(total, parse_scheme("sacrum=25,26; left_hip=77; right_hip=78"))
    np.testing.assert_array_equal(mapped, ours)


def test_a_totalsegmentator_map_passed_as_ours_is_refused_naming_the_scheme():
    hu, _, total = _phantom()
    with pytest.raises(ValueError, match="totalsegmentator") as err:
        check_bone_labels(hu, to_bone_labels(total, parse_scheme("ours")), AFFINE,
                          source="seg.nii.gz", raw_labels=total)  # fmt: skip
    assert "seg.nii.gz" in str(err.value) and "soft tissue" in str(err.value)


def test_swapped_sides_missing_bones_and_soft_tissue_are_refused():
    hu, ours, _ = _phantom()
    swapped = ours.copy()
    swapped[ours == 2], swapped[ours == 3] = 3, 2
    with pytest.raises(ValueError, match="patient's left"):
        check_bone_labels(hu, swapped, AFFINE, source="x.nii.gz")
    with pytest.raises(ValueError, match="right_hip .* mm\\^3"):
        check_bone_labels(hu, np.where(ours == 3, 0, ours), AFFINE, source="x.nii.gz")
    with pytest.raises(ValueError, match="median 40 HU"):
        check_bone_labels(np.full(hu.shape, 40.0), ours, AFFINE, source="x.nii.gz")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("nnunet", "expected 'ours'"),
        ("sacrum=25;left_hip=77", "no label for right_hip"),
        ("sacrum=25;left_hip=x;right_hip=78", "not integers"),
        ("sacrum=25;left_hip=25;right_hip=78", "two bones"),
        ("coccyx=1;sacrum=2;left_hip=3;right_hip=4", "expected 'ours'"),
    ],
)
def test_bad_schemes(text, message):
    with pytest.raises(ValueError, match=message):
        parse_scheme(text)


def test_relabelling_by_table_matches_the_per_value_path():
    lab = np.random.default_rng(0).integers(0, 100, (20, 16, 12)).astype(np.int16)
    scheme = parse_scheme("totalsegmentator")
    fast = to_bone_labels(lab, scheme)
    slow = to_bone_labels(lab.astype(np.float32), scheme)  # floats take the np.isin path
    assert fast.dtype == np.uint8 and np.array_equal(fast, slow)
    assert np.array_equal(fast == 3, lab == 78) and np.array_equal(
        fast == 1, np.isin(lab, (25, 26))
    )
