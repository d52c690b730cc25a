"""Active shape model on CTs: known answers (a sampled patient, dislocated, cut, thick slices,
masked), the voxeliser against winding numbers, and refusal of bad input."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.metrics.overlap import dice, surface_rmsd
from pelvicnav.shape.asm import ShapePrior, bone_threshold, segment_ct
from pelvicnav.shape.voxelize import inside_mask


def test_inside_mask_matches_winding_numbers_on_any_axis_order():
    from pelvicnav.model import load_model
    from pelvicnav.phantom.ctsynth import _winding_inside, voxel_grid

    model = load_model()
    v, f = model.shapes["left_hip"].mean, model.faces[1]
    shape, A = voxel_grid(v[None], (1.5, 1.5, 2.5), np.full((3, 2), 4.0))
    flipped = A.copy()
    flipped[:3, :3] = A[:3, :3] @ np.diag([-1.0, 1.0, 1.0])
    flipped[0, 3] = A[0, 3] + 1.5 * (shape[0] - 1)
    for grid in (A, flipped):
        ours = inside_mask(v, f, grid, shape)
        ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
        points = ijk.reshape(-1, 3) @ grid[:3, :3].T + grid[:3, 3]
        reference = _winding_inside(v, f, points).reshape(shape)  # generalised winding number
        assert ours.sum() > 10_000
        assert np.sum(ours != reference) <= 1e-3 * reference.sum()


def test_bone_threshold_tells_a_masked_ct_from_air_around_a_body():
    rng = np.random.default_rng(0)
    masked = np.zeros((40, 40, 40), np.float32)
    masked[10:20, 10:20, 10:20] = rng.uniform(100, 900, (10, 10, 10))
    assert bone_threshold(masked, 150.0) == (1.0, 0.0)
    body = np.full((40, 40, 40), -1000.0, np.float32)
    body[5:35, 5:35] = rng.normal(40, 8, (30, 30, 40))
    body[15:20, 15:20] = 700.0
    assert bone_threshold(body, 150.0) == (150.0, None)


def test_a_joint_surface_goes_to_the_bone_it_faces_though_the_partner_is_nearer():
    """Two bones across a 1 mm joint: A's boundary at z = 0 faces +z, B's at z = 1 faces -z.
    A's mesh is recessed to z = -3, so B's mesh is the nearest to A's boundary. A's vertices at
    the joint still take A's boundary (it faces the way A's surface faces); B takes its own; a
    third bone far off takes nothing. Without ``joint`` (the model's levels), the nearest mesh
    alone decides, as before: A gets nothing."""
    from scipy.spatial import cKDTree

    from pelvicnav.shape.asm import _data_pairs, _facing, _nearest_bones, _Surface

    g = np.stack(np.meshgrid(np.arange(-5.0, 6.0), np.arange(-5.0, 6.0)), -1).reshape(-1, 2)
    flat = lambda z: np.column_stack([g, np.full(len(g), z)])  # noqa: E731
    meshes = [flat(-3.0), flat(1.0), flat(60.0)]
    up, down = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])
    normals = [np.tile(up, (len(g), 1)), np.tile(down, (len(g), 1)), np.tile(up, (len(g), 1))]
    points = np.vstack([flat(0.0), flat(1.0)])
    directions = np.vstack([np.tile(up, (len(g), 1)), np.tile(down, (len(g), 1))])
    surface = _Surface(points, directions)
    nearest = _nearest_bones([cKDTree(m) for m in meshes], surface, 6.0)
    facing = _facing(normals, nearest, surface)
    joint = np.ones(len(g), dtype=bool)
    j_a, pts_a = _data_pairs(0, facing, nearest, surface, joint)
    assert len(pts_a) == len(g) and np.all(pts_a[:, 2] == 0.0)  # A's boundary, none of B's
    assert np.all(np.linalg.norm(meshes[0][j_a][:, :2] - pts_a[:, :2], axis=1) == 0)
    assert len(_data_pairs(0, facing, nearest, surface)[0]) == 0
    j_b, pts_b = _data_pairs(1, facing, nearest, surface, joint)
    assert len(pts_b) == len(g) and np.all(pts_b[:, 2] == 1.0)
    assert len(_data_pairs(2, facing, nearest, surface, joint)[0]) == 0  # out of reach


@pytest.fixture(scope="module")
def patient():
    """A patient sampled from the model, its left hip dislocated by a known 12 mm / 6 deg, as a
    synthetic CT (femurs, bowel gas, 1 x 1 x 2 mm)."""
    from pelvicnav.model import load_model
    from pelvicnav.phantom.ctsynth import synthesize_ct
    from pelvicnav.phantom.dislocate import Dislocation, apply_dislocation
    from pelvicnav.phantom.sampled import sampled_population

    model = load_model()
    V = sampled_population(seed=11, subject_ids=(3,)).vertices[0]
    rng = np.random.default_rng(4)
    ct = synthesize_ct(V, model.faces, rng=rng)
    c = V[1].mean(axis=0)
    shift = c + np.array([8.0, -6.0, 6.0])
    move = tf.from_params(shift, [0.0, 0.0, np.deg2rad(6.0)]) @ tf.from_params(-c, [0, 0, 0])
    disl = Dislocation("left_hip", "test", move, 12.0, 6.0, c, 1)
    moved, truth = apply_dislocation(ct, V, model.faces, disl, rng=rng)
    return moved, truth, ShapePrior.from_model(model)


def _scores(res, labels, truth, faces):
    return [
        (dice(res.labels == b + 1, labels == b + 1),
         surface_rmsd(res.vertices[b], faces[b], truth[b], faces[b]))
        for b in range(3)
    ]  # fmt: skip


@pytest.mark.slow
def test_asm_finds_the_three_bones_and_the_dislocated_one(patient):
    ct, truth, prior = patient
    res = segment_ct(ct.hu.data, ct.hu.world_from_ijk, prior)
    for bone, (d, rmsd) in zip(BONES, _scores(res, ct.labels, truth, prior.faces), strict=True):
        assert d > 0.96, (bone, d)
        assert rmsd < 1.2, (bone, rmsd)
        assert res.quality[bone]["edge_fraction"] > 0.9
    # The dislocated hip is found with its own pose (it moved 12 mm): its label's centroid.
    found, true = (np.argwhere(lab == 2).mean(axis=0) for lab in (res.labels, ct.labels))
    assert np.linalg.norm((found - true) * np.diag(ct.hu.world_from_ijk)[:3]) < 1.0
    assert res.labels.shape == ct.labels.shape and res.labels.dtype == np.uint8
    assert all(q["overlap_vertices"] < 20 for q in res.quality.values())


def _thick_slices(ct, factor: int):
    """Every ``factor``-th slice averaged (thicker slices, coarser spacing along k)."""
    n = ct.hu.data.shape[2] // factor * factor
    hu = ct.hu.data[:, :, :n].reshape(*ct.hu.data.shape[:2], -1, factor).mean(axis=3)
    A = ct.hu.world_from_ijk.copy()
    A[:3, 2] *= factor
    A[:3, 3] += ct.hu.world_from_ijk[:3, 2] * (factor - 1) / 2
    return hu, A


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["masked and cut below the femoral heads", "4 mm slices"])
def test_asm_is_robust_to_field_of_view_slices_and_masking(patient, variant):
    ct, truth, prior = patient
    hu, A, labels = ct.hu.data, ct.hu.world_from_ijk, ct.labels
    if variant == "4 mm slices":
        hu, A = _thick_slices(ct, 2)
        labels = None
    else:  # non-bone voxels set to 0 (as the real CTs come), the ischia partly out of the field
        hu = np.where(labels > 0, hu, 0.0).astype(np.float32)
        heads = ct.femoral_heads[:, 2].min() - ct.femoral_heads[:, 3].max()
        k0 = int(np.ceil((heads - A[2, 3]) / A[2, 2]))
        hu, labels = hu[:, :, k0:], labels[:, :, k0:]
        A = A.copy()
        A[:3, 3] += A[:3, 2] * k0
    res = segment_ct(hu, A, prior)
    for b, bone in enumerate(BONES):
        rmsd = surface_rmsd(res.vertices[b], prior.faces[b], truth[b], prior.faces[b])
        assert rmsd < (2.0 if variant == "4 mm slices" else 1.5), (variant, bone, rmsd)
        if labels is not None:
            assert dice(res.labels == b + 1, labels == b + 1) > 0.94, (variant, bone)


def test_asm_refuses_a_ct_that_is_not_3d_or_has_no_bone():
    from pelvicnav.model import load_model

    prior = ShapePrior.from_model(load_model())
    with pytest.raises(ValueError, match="3D volume"):
        segment_ct(np.zeros((64, 64)), np.eye(4), prior)
    with pytest.raises(ValueError, match="no bone"):
        segment_ct(np.full((40, 40, 40), 40.0, np.float32), np.eye(4), prior)


@pytest.mark.parametrize("bad", [{"joint_search_mm": 0.0}, {"free_form_search_mm": -1.0},
                                 {"joint_reach_mm": -2.0}])  # fmt: skip
def test_asm_settings_refuse_searches_that_reach_nowhere(bad):
    from pelvicnav.shape.asm import ASMSettings

    with pytest.raises(ValueError, match="joint_reach_mm at least 0"):
        ASMSettings(**bad)
    ASMSettings(joint_reach_mm=0.0)  # no joint search: allowed
