"""Fitting the shape models to a label map recovers a known pelvis's corresponded meshes."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.model import load_model
from pelvicnav.phantom.ctsynth import bone_labels, voxel_grid
from pelvicnav.phantom.sampled import sampled_population
from pelvicnav.shape.fit import fit_labels


def _reference(model):
    pop = model.population
    return tf.apply(pop.poses_from_vector(pop.mean), pop.mean_shapes)


@pytest.mark.slow
def test_fit_recovers_the_vertices_of_a_voxelised_patient():
    model = load_model()
    truth = sampled_population(seed=11, subject_ids=(2,)).vertices[0]
    shape, A = voxel_grid(truth, (1.5, 1.5, 1.5), np.full((3, 2), 10.0))
    labels = bone_labels(truth, model.faces, shape, A)
    fits = fit_labels(labels, A, model.shapes, model.faces, _reference(model))
    for b, bone in enumerate(BONES):
        err = np.linalg.norm(fits[bone].vertices - truth[b], axis=1)
        assert np.median(err) < 1.0 and err.max() < 5.0, (bone, np.median(err), err.max())
        assert fits[bone].rms_mm < 2.0


def test_fit_refuses_a_missing_bone_and_a_bad_reference():
    model = load_model()
    labels = np.zeros((10, 10, 10), dtype=np.uint8)
    labels[2:5], labels[6:9] = 1, 2
    with pytest.raises(ValueError, match="no voxel of right_hip"):
        fit_labels(labels, np.eye(4), model.shapes, model.faces, _reference(model))
    with pytest.raises(ValueError, match="reference must have shape"):
        fit_labels(labels, np.eye(4), model.shapes, model.faces, np.zeros((3, 10, 3)))
