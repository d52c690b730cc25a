"""CT synthesis and dislocation: label maps against independent voxelisations, tissue values."""

from __future__ import annotations

import numpy as np
import pytest

from helpers.synthetic import icosphere, make_population
from helpers.voxelize import dice, parity_voxelize
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.atlas import load_atlas
from pelvicnav.phantom.ctsynth import (
    CTOptions,
    _winding_inside,
    femoral_head,
    synthesize_ct,
    voxel_grid,
)
from pelvicnav.phantom.dislocate import (
    apply_dislocation,
    draw_dislocation,
    reduction_stages,
)

NO_FEMURS = CTOptions(femurs=False, margin_mm=((40, 40), (40, 40), (20, 20)))


@pytest.fixture(scope="module")
def ellipsoid_subject():
    V, faces, *_ = make_population(3, seed=4)
    return V[0], faces


@pytest.fixture(scope="module")
def ellipsoid_ct(ellipsoid_subject):
    V, faces = ellipsoid_subject
    return synthesize_ct(V, faces, rng=np.random.default_rng(0), options=NO_FEMURS)


def _supersampled_reference(vertices, faces, shape, A, label_mask):
    """Majority of 8 winding-number samples per voxel, around one bone."""
    idx = np.argwhere(label_mask)
    lo, hi = np.maximum(idx.min(0) - 2, 0), np.minimum(idx.max(0) + 3, shape)
    axes = [np.arange(lo[d], hi[d]) for d in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(float)
    count = np.zeros(len(g))
    for o in np.array(
        [[x, y, z] for x in (-0.25, 0.25) for y in (-0.25, 0.25) for z in (-0.25, 0.25)]
    ):
        count += _winding_inside(vertices, faces, (g + o) @ A[:3, :3].T + A[:3, 3])
    ref = np.zeros(shape, bool)
    ref[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = (count >= 4).reshape([len(a) for a in axes])
    return ref


def test_labels_match_independent_voxelisations(ellipsoid_subject, ellipsoid_ct):
    V, faces = ellipsoid_subject
    ct = ellipsoid_ct
    A = ct.hu.world_from_ijk
    for l in range(3):
        mask = ct.labels == l + 1
        assert dice(parity_voxelize(V[l], faces[l], ct.labels.shape, A), mask) > 0.97
        assert dice(_supersampled_reference(V[l], faces[l], ct.labels.shape, A, mask), mask) > 0.97


def test_tissue_values(ellipsoid_ct):
    ct = ellipsoid_ct
    hu, labels = ct.hu.data, ct.labels
    bone = labels > 0
    assert np.percentile(hu[bone], 95) > 900  # a cortical shell
    assert 100 < np.median(hu[bone]) < 1700
    assert hu[0, 0, 0] == pytest.approx(-1000, abs=1)  # air in the corner, outside the body
    soft = (~bone) & (hu > -200) & (hu < 200)
    assert soft.sum() > 0.2 * hu.size
    gas = (hu < -800) & ~bone
    body_gas = gas[:, :, :] & (np.abs(hu) < 1e9)
    assert body_gas.sum() > 0  # bowel gas pockets exist...
    assert not np.any(gas & bone)  # ...never inside bone


def test_femoral_head_of_a_cup():
    sphere, faces = icosphere(3)
    outer = sphere * 40.0
    inner = sphere * 25.0 + [0.3, -0.2, 0.1]
    V = np.vstack([outer, inner])
    F = np.vstack([faces, faces[:, ::-1] + len(sphere)])  # inner surface faces the cavity
    c, r = femoral_head(V, F)
    np.testing.assert_allclose(c, [0.3, -0.2, 0.1], atol=0.3)
    assert r == pytest.approx(25.0, abs=0.3)
    with pytest.raises(ValueError, match="no acetabulum"):
        femoral_head(outer, faces)  # a convex ball has no cup


def test_dislocation_is_collision_free_and_invertible(ellipsoid_subject, ellipsoid_ct):
    from scipy.ndimage import map_coordinates

    V, faces = ellipsoid_subject
    ct = ellipsoid_ct
    A = ct.hu.world_from_ijk
    for k, pattern in enumerate(("si", "ps", "open-book")):
        d = draw_dislocation(V, faces, pattern=pattern, rng=np.random.default_rng(k), max_mm=8.0)
        assert 0 <= d.translation_mm <= 8.0
        assert 0 <= d.rotation_deg <= 10.0
        moved_ct, moved = apply_dislocation(ct, V, faces, d, rng=np.random.default_rng(9))
        # No new overlap: the moved bone's vertices are not inside the others.
        for l in (0, 2):
            assert _winding_inside(V[l], faces[l], moved[1]).sum() <= 5
        # Pull the moved label map back through the inverse dislocation: original voxels return.
        idx = np.indices(ct.labels.shape).reshape(3, -1).T.astype(float)
        world = idx @ A[:3, :3].T + A[:3, 3]
        ijk = (tf.apply(d.transform, world) - A[:3, 3]) @ np.linalg.inv(A[:3, :3]).T
        back = map_coordinates((moved_ct.labels == 2).astype(float), ijk.T, order=1) > 0.5
        assert dice(back.reshape(ct.labels.shape), ct.labels == 2) > 0.98
        # The vacated region holds soft tissue now, not bone.
        vacated = (ct.labels == 2) & (moved_ct.labels != 2)
        assert np.median(moved_ct.hu.data[vacated]) < 200


def test_beads_move_with_their_bone(ellipsoid_subject):
    V, faces = ellipsoid_subject
    opts = CTOptions(femurs=False, bowel_gas=False, beads=8, margin_mm=NO_FEMURS.margin_mm)
    ct = synthesize_ct(V, faces, rng=np.random.default_rng(3), options=opts)
    A = ct.hu.world_from_ijk

    def hu_at(points):
        ijk = np.rint((points - A[:3, 3]) @ np.linalg.inv(A[:3, :3]).T).astype(int)
        return ct_now.hu.data[tuple(ijk.T)]

    ct_now = ct
    assert ct.beads.shape == (8, 3)
    assert np.all(hu_at(ct.beads) == 3000)
    d = draw_dislocation(V, faces, pattern="ps", rng=np.random.default_rng(5), max_mm=8.0)
    moved_ct, _ = apply_dislocation(ct, V, faces, d, rng=np.random.default_rng(6))
    ct_now = moved_ct
    on_left = ct.bead_bones == 2
    np.testing.assert_allclose(moved_ct.beads[on_left], tf.apply(d.transform, ct.beads[on_left]))
    np.testing.assert_array_equal(moved_ct.beads[~on_left], ct.beads[~on_left])
    assert np.all(hu_at(moved_ct.beads) == 3000)


def test_reduction_stages_interpolate_on_the_geodesic():
    D = tf.from_params([10.0, -4.0, 2.0], np.deg2rad([3.0, 5.0, -2.0]))
    S = reduction_stages(D, [0.0, 0.5, 1.0])
    np.testing.assert_allclose(S[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(S[2], D, atol=1e-12)
    np.testing.assert_allclose(S[1] @ S[1], D, atol=1e-10)


def test_bad_input(ellipsoid_subject):
    V, faces = ellipsoid_subject
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="unknown dislocation pattern 'twist'"):
        draw_dislocation(V, faces, pattern="twist", rng=rng)
    with pytest.raises(ValueError, match="only an innominate"):
        draw_dislocation(V, faces, bone="sacrum", rng=rng)
    with pytest.raises(ValueError, match=r"shape \(3, n_vertices, 3\)"):
        synthesize_ct(V[:2], faces, rng=rng)
    shape, A = voxel_grid(V, (2.0, 2.0, 2.0), ((0, 0), (0, 0), (0, 0)))
    assert all(s > 10 for s in shape)


@pytest.mark.atlas
def test_atlas_subject_ct(real_atlas_path):
    atlas = load_atlas(real_atlas_path)
    V = atlas.vertices[3]
    ct = synthesize_ct(V, atlas.faces, rng=np.random.default_rng(1))
    A = ct.hu.world_from_ijk
    # The innominate meshes are closed enough for ray parity; the sacrum's (open at S3) is not,
    # so it is checked against a supersampled winding-number voxelisation.
    for l in (1, 2):
        ref = parity_voxelize(V[l], atlas.faces[l], ct.labels.shape, A)
        assert dice(ref, ct.labels == l + 1) >= 0.97
    mask = ct.labels == 1
    assert (
        dice(_supersampled_reference(V[0], atlas.faces[0], ct.labels.shape, A, mask), mask) >= 0.97
    )
    # Femoral heads seated in both acetabula, of adult size, lateral to the sacrum.
    (lx, *_, lr), (rx, *_, rr) = ct.femoral_heads
    assert 20 < lr < 30
    assert 20 < rr < 30
    assert lx > V[0, :, 0].max() > V[0, :, 0].min() > rx
