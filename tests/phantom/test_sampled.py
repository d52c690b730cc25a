"""Patients sampled from the packaged pelvis model."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav import BONES
from pelvicnav.model import load_model
from pelvicnav.phantom.sampled import (
    SamplingOptions,
    sample_subject,
    sampled_population,
    weights_from_combined,
)
from pelvicnav.shape.mesh import is_closed, self_intersections, signed_volume


@pytest.fixture(scope="module")
def model():
    return load_model()


def _check_meshes(model, vertices):
    for b in range(3):
        assert is_closed(model.faces[b])
        assert signed_volume(vertices[b], model.faces[b]) > 0  # outward
        assert len(self_intersections(vertices[b], model.faces[b])) == 0, BONES[b]


def test_population_is_seeded_per_subject_with_exact_correspondence(model):
    pop = sampled_population(3, seed=4)
    assert pop.source == "model" and pop.subject_ids == (1, 2, 3)
    assert pop.vertices.shape == (3, 3, model.n_vertices, 3)
    assert all(np.array_equal(f, g) for f, g in zip(pop.faces, model.faces, strict=True))
    alone = sampled_population(seed=4, subject_ids=(3,))
    np.testing.assert_array_equal(alone.vertices[0], pop.vertices[2])
    other = sampled_population(seed=5, subject_ids=(3,))
    assert np.abs(other.vertices[0] - pop.vertices[2]).max() > 1.0
    for s in range(3):
        _check_meshes(model, pop.vertices[s])


@pytest.mark.slow
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_meshes_at_the_clipped_extremes(model, sign):
    """Every combined mode at +-2.5 sd at once, far beyond any draw.

    The innominates come out free of crossings. The sacrum does not quite (a known gap, see
    docs/model.md): a few triangle pairs remain at the sacral base, where the atlas's own sacra
    fold and have two slits. (Drawn patients are redrawn in that case, so they are all free.)
    """
    clip = SamplingOptions().clip
    pose, shape = weights_from_combined(model, np.full(model.combined.n_modes, sign * clip))
    vertices, crossings = sample_subject(model, pose, shape)
    for b in (1, 2):
        assert len(self_intersections(vertices[b], model.faces[b])) == 0, BONES[b]
    pairs = self_intersections(vertices[0], model.faces[0])
    assert len(pairs) == crossings <= 20
    for b in range(3):
        assert signed_volume(vertices[b], model.faces[b]) > 0


def test_bad_requests_are_refused():
    with pytest.raises(ValueError, match="n_subjects"):
        sampled_population(0)
    with pytest.raises(ValueError, match="subject ids"):
        sampled_population(subject_ids=(0,))
    with pytest.raises(ValueError, match="clip"):
        sampled_population(2, options=SamplingOptions(clip=0.0))
    with pytest.raises(ValueError, match="max_draws"):
        sampled_population(2, options=SamplingOptions(max_draws=0))


@pytest.mark.atlas
@pytest.mark.slow
def test_forty_sampled_subjects_are_sized_like_the_atlas(real_atlas_path):
    from pelvicnav.io.atlas import load_atlas
    from pelvicnav.phantom.population import atlas_statistics
    from pelvicnav.studies.population import size_table

    rows = size_table(
        atlas_statistics(sampled_population(40, seed=0)),
        atlas_statistics(load_atlas(real_atlas_path)),
    )
    for row in rows:
        assert abs(row["sampled_mean"] / row["atlas_mean"] - 1) <= 0.03, row
        assert row["inside"], row
        # Not a shrunken population: its spread is most of the atlas's.
        assert row["sampled_sd"] >= 0.6 * row["atlas_sd"], row
