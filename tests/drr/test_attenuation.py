"""Bone attenuation models: the fused HU -> point-model pass against the two-step reference."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.drr.attenuation import bone_point_models, bone_volumes, sample_volumes
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import transforms as tf


def _ct_and_labels(rng):
    """A CT as scanners store it (int16 HU, Fortran order as NIfTI reads it) with three bones, a
    fourth label that is not a bone, and a bone voxel below -1000 HU (attenuation 0)."""
    shape = (23, 19, 17)
    hu = rng.integers(-1100, 1800, size=shape).astype(np.int16)
    labels = np.zeros(shape, dtype=np.uint8)
    labels[2:9, 3:15, 1:12] = 1
    labels[10:17, 1:9, 4:16] = 2
    labels[10:21, 10:18, 2:9] = 3
    labels[18:, :4, :3] = 7
    hu[3, 4, 2] = -1024
    A = tf.from_params([10.0, -20.0, 5.0], [0.05, -0.1, 0.2]) @ np.diag([0.8, 0.9, 1.25, 1.0])
    return Volume(np.asfortranarray(hu), A), np.asfortranarray(labels)


def test_the_fused_pass_gives_the_two_step_models_bitwise():
    ct, labels = _ct_and_labels(np.random.default_rng(3))
    spacings = (3.0, 1.5, 0.5)
    fused = bone_point_models(ct, labels, spacings)
    volumes = bone_volumes(ct, labels)
    for mm, models in zip(spacings, fused, strict=True):
        reference = sample_volumes(volumes, mm)
        assert set(models) == {"sacrum", "left_hip", "right_hip"}
        for bone, m in models.items():
            np.testing.assert_array_equal(m.points, reference[bone].points)
            np.testing.assert_array_equal(m.mass, reference[bone].mass)
            assert m.spacing == reference[bone].spacing


def test_the_fused_pass_refuses_what_the_reference_refuses():
    ct, labels = _ct_and_labels(np.random.default_rng(4))
    with pytest.raises(ValueError, match="differs from the CT"):
        bone_point_models(ct, labels[:-1], (1.5,))
    no_sacrum = np.where(labels == 1, 0, labels)
    with pytest.raises(ValueError, match="no voxel of sacrum"):
        bone_point_models(ct, no_sacrum, (1.5,))
