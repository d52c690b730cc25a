"""The cache of CT-derived bone models: hits only on the same bytes, never trusts a damaged
entry, can be switched off, and stores nothing for refused input."""

from __future__ import annotations

import numpy as np
import pytest

from helpers.labels import label_phantom
from pelvicnav.io.nifti import write_nifti
from pelvicnav.workflow import bone_cache
from pelvicnav.workflow.register import bones_of_files

FACTORS = (4, 2)


def _files(tmp_path, hu=None):
    phantom_hu, ours, total, affine = label_phantom()
    hu = phantom_hu if hu is None else hu
    write_nifti(tmp_path / "ct.nii.gz", hu.astype(np.int16), affine)
    write_nifti(tmp_path / "labels.nii.gz", ours, affine)
    write_nifti(tmp_path / "total.nii.gz", total, affine)
    return tmp_path / "ct.nii.gz", tmp_path / "labels.nii.gz"


def _entries():
    return sorted(bone_cache.cache_dir().glob("bones-*.npz"))


def test_the_same_files_read_from_the_cache_give_the_same_bones(tmp_path):
    ct, labels = _files(tmp_path)
    first, _, cached = bones_of_files(ct, labels, "ours", None, FACTORS)
    assert not cached and len(_entries()) == 1
    again, _, cached = bones_of_files(ct, labels, "ours", None, FACTORS)
    assert cached
    assert again.fingerprint == first.fingerprint
    for b in first.centroids:
        np.testing.assert_array_equal(again.centroids[b], first.centroids[b])
    for level_a, level_b in zip(first.models.models, again.models.models, strict=True):
        for b, m in level_a.items():
            np.testing.assert_array_equal(level_b[b].points, m.points)
            np.testing.assert_array_equal(level_b[b].mass, m.mass)
            assert level_b[b].spacing == m.spacing
    # another label scheme or other levels are other entries
    assert not bones_of_files(ct, labels, "sacrum=1;left_hip=2;right_hip=3", None, FACTORS)[2]
    assert not bones_of_files(ct, labels, "ours", None, (4,))[2]


def test_the_files_are_read_once_on_a_miss_and_not_at_all_on_a_hit(tmp_path, monkeypatch):
    """The reads start as soon as the key says they are needed (while the engine imports), and
    only then: a damaged entry (stored but refused) is read afresh too."""
    import pelvicnav.io.volume as volume

    calls = []
    read_ct = volume.read_ct
    monkeypatch.setattr(volume, "read_ct", lambda *a, **k: calls.append(a[0]) or read_ct(*a, **k))
    ct, labels = _files(tmp_path)
    assert not bones_of_files(ct, labels, "ours", None, FACTORS)[2]
    assert calls == [ct]
    assert bones_of_files(ct, labels, "ours", None, FACTORS)[2]
    assert calls == [ct]  # a hit reads nothing
    _entries()[0].write_bytes(b"damaged")
    assert not bones_of_files(ct, labels, "ours", None, FACTORS)[2]
    assert calls == [ct, ct]


def test_changed_bytes_or_a_damaged_entry_are_read_afresh(tmp_path):
    ct, labels = _files(tmp_path)
    bones_of_files(ct, labels, "ours", None, FACTORS)
    hu = label_phantom()[0]
    hu[30, 25, 20] += 100.0  # one voxel of the sacrum
    _files(tmp_path, hu)
    changed, _, cached = bones_of_files(ct, labels, "ours", None, FACTORS)
    assert not cached and len(_entries()) == 2
    for entry in _entries():
        entry.write_bytes(entry.read_bytes()[:100])  # truncated
    again, _, cached = bones_of_files(ct, labels, "ours", None, FACTORS)
    assert not cached and again.fingerprint == changed.fingerprint
    assert bones_of_files(ct, labels, "ours", None, FACTORS)[2]  # rewritten, whole again


def test_the_cache_switched_off_stores_nothing(tmp_path, monkeypatch):
    ct, labels = _files(tmp_path)
    monkeypatch.setenv("PELVICNAV_CACHE", "0")
    assert bone_cache.cache_dir() is None
    assert not bones_of_files(ct, labels, "ours", None, FACTORS)[2]
    assert not bones_of_files(ct, labels, "ours", None, FACTORS)[2]


def test_refused_input_is_refused_again_and_never_cached(tmp_path):
    ct, _ = _files(tmp_path)
    for _ in range(2):
        with pytest.raises(ValueError, match="totalsegmentator"):
            bones_of_files(ct, tmp_path / "total.nii.gz", "ours", None, FACTORS)
    assert _entries() == []
    with pytest.raises(ValueError, match="not found"):
        bones_of_files(tmp_path / "missing.nii.gz", tmp_path / "labels.nii.gz", "ours", None,
                       FACTORS)  # fmt: skip


def test_a_guided_frame_still_refuses_a_changed_ct_after_the_cache_holds_the_plans(tmp_path):
    """The guide's check that the CT is the plan's holds through the cache: the plan's CT read
    once (cached with its voxel digest), then the file changed: refused, naming it."""
    import shutil

    from pelvicnav.io.nifti import read_nifti
    from pelvicnav.io.plan import CTReference, Plan, read_plan, write_plan
    from pelvicnav.workflow.guide import _plan_bones

    ct, labels = _files(tmp_path)
    plan_dir = tmp_path / "plan"
    plan_dir.mkdir()
    shutil.copyfile(labels, plan_dir / "labels.nii.gz")
    data, A = read_nifti(ct)
    write_plan(plan_dir, Plan(ct=CTReference.of(ct, data, A), dislocated=("left_hip",),
                              targets={"left_hip": np.eye(4)}))  # fmt: skip
    plan = read_plan(plan_dir)
    first = _plan_bones(plan, plan_dir, 6)
    assert first.voxel_digest == plan.ct.fingerprint
    assert _plan_bones(plan, plan_dir, 6).voxel_digest == plan.ct.fingerprint  # from the cache
    hu = label_phantom()[0]
    hu[30, 25, 20] += 100.0
    _files(tmp_path, hu)
    with pytest.raises(ValueError, match="not the CT the plan was made from"):
        _plan_bones(plan, plan_dir, 6)
