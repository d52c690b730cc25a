"""Moving a labelled bone voxel-wise (the real CTs have no meshes)."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.phantom.dislocate import move_bone_voxels


def test_move_bone_voxels_translates_a_labelled_block_and_reports_overlap():
    hu = np.full((30, 20, 20), 50.0, dtype=np.float32)
    labels = np.zeros(hu.shape, dtype=np.uint8)
    labels[2:8, 5:15, 5:15] = 1
    labels[12:18, 5:15, 5:15] = 2
    hu[12:18, 5:15, 5:15] = np.linspace(300, 900, 6)[:, None, None]  # a gradient along i
    A = np.diag([2.0, 2.0, 2.0, 1.0])
    move = tf.from_params([8.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # 4 voxels along +i
    rng = np.random.default_rng(0)
    new_hu, new_lab, overlap = move_bone_voxels(hu, labels, A, 2, move, rng=rng)
    assert overlap == 0.0
    assert np.array_equal(np.argwhere(new_lab == 2), np.argwhere(labels == 2) + np.array([4, 0, 0]))
    np.testing.assert_allclose(new_hu[16:22, 10, 10], np.linspace(300, 900, 6), atol=1e-3)
    vacated = (labels == 2) & (new_lab == 0)
    assert vacated.sum() == 4 * 100 and abs(np.median(new_hu[vacated]) - 40.0) < 5
    assert np.array_equal(new_lab == 1, labels == 1)  # the other bone is untouched
    into = tf.from_params([-12.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # 6 voxels: 2 layers into bone 1
    _, lab2, overlap2 = move_bone_voxels(hu, labels, A, 2, into, rng=rng)
    assert overlap2 == pytest.approx(2 / 6)
    assert np.array_equal(lab2 == 1, labels == 1)
    with pytest.raises(ValueError, match="no voxel of label 3"):
        move_bone_voxels(hu, labels, A, 3, move, rng=rng)
