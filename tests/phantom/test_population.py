"""The procedural pelvis population: correspondence, topology, anatomy, joints, sizes."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.io.atlas import ATLAS_ENV, AtlasNotFoundError
from pelvicnav.phantom.ctsynth import femoral_head
from pelvicnav.phantom.population import (
    PS_GAP_MM,
    SI_GAP_MM,
    atlas_statistics,
    load_population,
    procedural_population,
    template_bones,
)
from pelvicnav.pose.collision import find_joint_surfaces

# Ranges measured on the real Han atlas (40 subjects; `pelvicnav study population` prints them):
# per-bone x/y/z extents in each subject's CT frame and the pelvic width, mm.
ATLAS_RANGES = {
    "sacrum_extent": [(102.0, 129.4), (67.9, 102.5), (57.4, 93.5)],
    "left_hip_extent": [(116.2, 167.8), (130.3, 180.2), (175.9, 233.4)],
    "right_hip_extent": [(114.4, 163.4), (126.5, 180.7), (178.4, 233.7)],
    "pelvic_width": [(233.0, 326.6)],
}


@pytest.fixture(scope="module")
def population():
    return procedural_population(40, seed=0)


def _signed_volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0


def _edges(f):
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def test_templates_are_closed_oriented_meshes_of_the_right_genus():
    verts, faces = template_bones()
    for bone, v, f, genus in zip(("sacrum", "left", "right"), verts, faces, (0, 1, 1), strict=True):
        assert v.shape == (5000, 3), bone
        edges, counts = _edges(f)
        assert np.all(counts == 2), f"{bone}: every edge must have exactly two faces (closed)"
        assert len(np.unique(f)) == 5000, f"{bone}: unreferenced vertices"
        assert len(v) - len(edges) + len(f) == 2 - 2 * genus, bone  # obturator foramen: genus 1
        assert _signed_volume(v, f) > 1e5, f"{bone}: outward orientation, > 100 cm3"
    # right innominate = mirror of the left
    np.testing.assert_allclose(verts[2], verts[1] * [-1, 1, 1])


def test_correspondence_is_exact(population):
    V = population.vertices
    assert V.shape == (40, 3, 5000, 3)
    assert population.source == "procedural"
    tv, _ = template_bones()
    for b in range(3):
        # every subject is a smooth, near-similarity deformation of the template: vertex i stays
        # the same anatomical point (residual after a similarity fit is a few mm, never a swap)
        T = fit_transform(V[:, b], np.broadcast_to(tv[b], V[:, b].shape), scale=True)
        moved = np.einsum("sij,svj->svi", T[:, :3, :3], V[:, b]) + T[:, None, :3, 3]
        res = np.linalg.norm(moved - tv[b], axis=-1)
        assert res.max() < 12.0
        assert np.median(res) < 4.0
        assert res.max() > 0.1  # shapes do vary


def test_population_is_reproducible_and_seeded():
    a = procedural_population(3, seed=7)
    b = procedural_population(3, seed=7)
    c = procedural_population(3, seed=8)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert np.abs(a.vertices - c.vertices).max() > 1.0
    # inter-subject variation of both shape and relative pose
    assert np.abs(a.vertices[0] - a.vertices[1]).max() > 1.0


def test_acetabulum_is_found_on_every_subject(population):
    for s in range(0, 40, 5):
        for b, lateral in ((1, (1, 0, 0)), (2, (-1, 0, 0))):
            V = population.vertices[s, b]
            c, r = femoral_head(V, population.faces[b], lateral=lateral)
            assert 20.0 < r < 31.0
            # the cup is on the lateral side, at mid height of the bone
            lo, hi = V.min(axis=0), V.max(axis=0)
            assert lateral[0] * (c[0] - V[:, 0].mean()) > 0.0
            assert lo[2] + 0.25 * (hi[2] - lo[2]) < c[2] < lo[2] + 0.65 * (hi[2] - lo[2])


def test_joints_are_narrow_and_do_not_collide(population):
    import igl
    from scipy.spatial import cKDTree

    for s in (0, 13, 27):
        V, F = population.vertices[s], population.faces
        js = find_joint_surfaces(V, F)
        for (a, b), surface in js.items():
            ia, ib = population.bones.index(a), population.bones.index(b)
            nominal = PS_GAP_MM if a.endswith("hip") and b.endswith("hip") else SI_GAP_MM
            assert min(len(x) for x in surface.vertices) >= 30, (a, b)
            d, _ = cKDTree(V[ib]).query(V[ia][surface.vertices[0]])
            assert 0.5 * nominal < np.median(d) < nominal + 3.0, (s, a, b)
        for ia in range(3):
            for ib in range(3):
                if ia != ib:
                    w = igl.fast_winding_number(V[ib], F[ib], V[ia])
                    assert np.max(w) < 0.5, f"subject {s}: bone {ia} enters bone {ib}"


def test_sizes_inside_the_atlas_ranges(population):
    stats = atlas_statistics(population)
    for key, ranges in ATLAS_RANGES.items():
        values = np.asarray(stats[key]).reshape(40, -1)
        for axis, (lo, hi) in enumerate(ranges):
            assert lo <= values[:, axis].min() and values[:, axis].max() <= hi, (key, axis)
            # and not a degenerate population: a real spread inside the range
            assert values[:, axis].std() > 0.15 * (hi - lo) / 4


def test_sizes_match_the_real_atlas(real_atlas_path, population):
    from pelvicnav.io.atlas import load_atlas

    real = atlas_statistics(load_atlas(real_atlas_path))
    ours = atlas_statistics(population)
    for key in ATLAS_RANGES:
        r, o = np.asarray(real[key]).reshape(40, -1), np.asarray(ours[key]).reshape(40, -1)
        assert np.all(o.min(axis=0) >= r.min(axis=0)) and np.all(o.max(axis=0) <= r.max(axis=0))
        np.testing.assert_allclose(o.mean(axis=0), r.mean(axis=0), rtol=0.06)


def test_bad_arguments():
    with pytest.raises(ValueError, match="n_subjects"):
        procedural_population(0)
    with pytest.raises(ValueError, match="n_vertices"):
        procedural_population(2, n_vertices=10)


def test_load_population_falls_back_only_without_a_configured_atlas(tmp_path, monkeypatch):
    monkeypatch.delenv(ATLAS_ENV, raising=False)
    monkeypatch.setattr("pelvicnav.io.atlas.default_atlas_dir", lambda: tmp_path / "none")
    assert load_population(n_subjects=2).source == "model"
    assert load_population("procedural", n_subjects=2).source == "procedural"
    assert load_population("model", subject_ids=(5,)).subject_ids == (5,)
    with pytest.raises(AtlasNotFoundError):
        load_population(tmp_path / "missing")
    monkeypatch.setenv(ATLAS_ENV, str(tmp_path / "missing"))
    with pytest.raises(AtlasNotFoundError):
        load_population()
