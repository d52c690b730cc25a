"""Dislocation simulator (Han et al. 2020, section 2.3.2): move an innominate, with ground truth.

Patterns (after Mulhall et al. 2002, Cicek et al. 2015):

* ``"si"`` - sacroiliac disruption: the bone turns about its pubic-symphysis face and its
  sacroiliac side moves;
* ``"ps"`` - pubic symphysis disruption: the bone turns about its sacroiliac face;
* ``"open-book"`` - both: external rotation about a near-vertical axis through the sacroiliac
  joint, opening the symphysis, plus translation.

Magnitudes are uniform in 0-20 mm and 0-10 degrees (configurable). A draw that makes the bone
collide with another (more of its vertices inside another bone than before) is rejected and
redrawn. The moved bone is resampled into the CT (trilinear), its old place infilled from the
adjacent soft tissue (normalised convolution), and the label map updated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import transforms as tf
from pelvicnav.phantom.ctsynth import SynthCT, _winding_inside, bone_mask, paint_beads

__all__ = [
    "PATTERNS",
    "Dislocation",
    "apply_dislocation",
    "draw_dislocation",
    "move_bone_voxels",
    "reduction_stages",
]

BONES = ("sacrum", "left_hip", "right_hip")
PATTERNS = ("si", "ps", "open-book")


@dataclass(frozen=True)
class Dislocation:
    """A rigid dislocation of one bone.

    Attributes
    ----------
    bone : str
    pattern : str
    transform : (4, 4) float64
        ``dislocated_from_original`` in world (CT) mm.
    translation_mm, rotation_deg : float
        Drawn magnitudes (translation of the pivot, rotation angle).
    pivot : (3,) float64
    attempts : int
        Draws until one did not collide.
    """

    bone: str
    pattern: str
    transform: NDArray[np.float64]
    translation_mm: float
    rotation_deg: float
    pivot: NDArray[np.float64]
    attempts: int


def _joint_centre(mover: NDArray, other: NDArray, distance: float = 8.0) -> NDArray[np.float64]:
    from scipy.spatial import cKDTree

    d, _ = cKDTree(other).query(mover)
    near = d <= distance
    if near.sum() < 3:
        near = d <= np.quantile(d, 0.02)
    return mover[near].mean(axis=0)


def _unit(rng: np.random.Generator) -> NDArray[np.float64]:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def draw_dislocation(
    vertices: ArrayLike,
    faces: tuple[ArrayLike, ...],
    *,
    bone: str = "left_hip",
    pattern: str = "open-book",
    rng: np.random.Generator,
    max_mm: float = 20.0,
    max_deg: float = 10.0,
    max_attempts: int = 50,
    tolerance_vertices: int = 5,
) -> Dislocation:
    """Draw a collision-free dislocation of ``bone``.

    Parameters
    ----------
    vertices : (3, n_vertices, 3) float, mm
    faces : three (m_l, 3) int arrays
    bone : {"left_hip", "right_hip"}
    pattern : {"si", "ps", "open-book"}
    rng : numpy.random.Generator
    max_mm, max_deg : float
        Magnitudes are uniform in [0, max].

    Raises
    ------
    ValueError
        Unknown bone or pattern, or no collision-free draw in ``max_attempts``.
    """
    if bone not in ("left_hip", "right_hip"):
        raise ValueError(f"only an innominate can be dislocated, got bone {bone!r}")
    if pattern not in PATTERNS:
        raise ValueError(f"unknown dislocation pattern {pattern!r}; expected one of {PATTERNS}")
    V = np.asarray(vertices, dtype=np.float64)
    b = BONES.index(bone)
    other_hip = 3 - b
    side = 1.0 if bone == "left_hip" else -1.0
    si = _joint_centre(V[b], V[0])
    ps = _joint_centre(V[b], V[other_hip])
    others = [l for l in range(3) if l != b]
    baseline = sum(int(_winding_inside(V[l], faces[l], V[b]).sum()) for l in others)
    for attempt in range(1, max_attempts + 1):
        t_mag = rng.uniform(0.0, max_mm)
        r_mag = rng.uniform(0.0, max_deg)
        if pattern == "si":
            pivot, axis, direction = ps, _unit(rng), _unit(rng)
        elif pattern == "ps":
            pivot, axis, direction = si, _unit(rng), _unit(rng)
        else:
            # External rotation about a near-vertical axis through the SI joint opens the front.
            axis = np.array([0.0, 0.0, -side]) + 0.25 * rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            pivot = si
            direction = np.array([side, -0.5, 0.0]) + 0.4 * rng.normal(size=3)
            direction /= np.linalg.norm(direction)
        R = tf.matrix_from_rotvec(np.deg2rad(r_mag) * axis)
        D = np.eye(4)
        D[:3, :3] = R
        D[:3, 3] = pivot - R @ pivot + t_mag * direction
        moved = tf.apply(D, V[b])
        inside = sum(int(_winding_inside(V[l], faces[l], moved).sum()) for l in others)
        if inside <= baseline + tolerance_vertices:
            return Dislocation(bone, pattern, D, float(t_mag), float(r_mag), pivot, attempt)
    raise ValueError(
        f"no collision-free {pattern} dislocation of {bone} in {max_attempts} draws "
        f"(up to {max_mm} mm / {max_deg} deg)"
    )


def reduction_stages(transform: ArrayLike, fractions: ArrayLike) -> NDArray[np.float64]:
    """Intermediate poses between reduced (0) and fully dislocated (1) along the SE(3) geodesic."""
    xi = tf.se3_log(np.asarray(transform, dtype=np.float64))
    f = np.asarray(fractions, dtype=np.float64)
    return tf.se3_exp(f[..., None] * xi)


def apply_dislocation(
    ct: SynthCT,
    vertices: ArrayLike,
    faces: tuple[ArrayLike, ...],
    dislocation: Dislocation,
    *,
    rng: np.random.Generator,
) -> tuple[SynthCT, NDArray[np.float64]]:
    """Move the bone in the CT and the label map.

    Returns
    -------
    SynthCT
        The dislocated CT (same grid).
    (3, n_vertices, 3) float64
        The dislocated meshes.
    """
    from scipy.ndimage import gaussian_filter, map_coordinates

    V = np.asarray(vertices, dtype=np.float64)
    b = BONES.index(dislocation.bone)
    label = b + 1
    moved = V.copy()
    moved[b] = tf.apply(dislocation.transform, V[b])
    A = ct.hu.world_from_ijk
    shape = ct.labels.shape
    new_mask = bone_mask(moved[b], faces[b], shape, A)
    old_mask = ct.labels == label
    hu = ct.hu.data.copy()

    # Infill the vacated region from adjacent soft tissue (normalised convolution), computed in
    # the vacated region's bounding box only.
    vacated = old_mask & ~new_mask
    if vacated.any():
        sp = np.linalg.norm(A[:3, :3], axis=0)
        sigma = 5.0 / sp
        pad = np.ceil(4 * sigma).astype(int) + 1
        where = np.argwhere(vacated)
        lo = np.maximum(where.min(axis=0) - pad, 0)
        hi = np.minimum(where.max(axis=0) + pad + 1, shape)
        box = tuple(slice(lo[d], hi[d]) for d in range(3))
        sub = hu[box]
        soft = (ct.labels[box] == 0) & (sub > -500) & (sub < 300)
        num = gaussian_filter(np.where(soft, sub, 0.0).astype(np.float32), sigma)
        den = gaussian_filter(soft.astype(np.float32), sigma)
        fill = np.where(den > 1e-3, num / np.maximum(den, 1e-3), 40.0)
        vac = vacated[box]
        sub[vac] = fill[vac] + rng.normal(0, 8, int(vac.sum())).astype(np.float32)

    # Resample the bone at its new place: HU(x) = HU_original(D^-1 x), trilinear.
    idx = np.argwhere(new_mask).astype(np.float64)
    world = idx @ A[:3, :3].T + A[:3, 3]
    back = tf.apply(tf.invert(dislocation.transform), world)
    ijk = (back - A[:3, 3]) @ np.linalg.inv(A[:3, :3]).T
    hu[new_mask] = map_coordinates(ct.hu.data, ijk.T, order=1, mode="nearest")

    # Beads glued to the moved bone move with it: erase, then paint at the new place.
    beads = ct.beads.copy()
    on_bone = ct.bead_bones == label
    if on_bone.any():
        paint_beads(hu, A, beads[on_bone], ct.bead_radius + 0.5, value=40.0)
        beads[on_bone] = tf.apply(dislocation.transform, beads[on_bone])
        paint_beads(hu, A, beads[on_bone], ct.bead_radius)
    labels = ct.labels.copy()
    labels[old_mask] = 0
    labels[new_mask & (labels == 0)] = label
    moved_ct = SynthCT(
        Volume(hu, A),
        labels,
        ct.femoral_heads.copy(),
        beads=beads,
        bead_bones=ct.bead_bones.copy(),
        bead_radius=ct.bead_radius,
    )
    return moved_ct, moved


def move_bone_voxels(
    hu: ArrayLike,
    labels: ArrayLike,
    world_from_ijk: ArrayLike,
    label: int,
    transform: ArrayLike,
    *,
    rng: np.random.Generator,
    margin_mm: float = 30.0,
) -> tuple[NDArray[np.float32], NDArray[np.uint8], float]:
    """Move one labelled bone of a CT by a rigid ``transform`` (world mm), voxel-wise.

    For CTs without meshes (the real CTs): the bone's CT numbers are resampled at its new place
    (trilinear; its label nearest), the voxels it leaves become soft tissue (40 HU, noise 8 HU).
    Only the bone's bounding box grown by ``margin_mm`` is touched.

    Returns
    -------
    hu : float32, labels : uint8
        The moved CT and label map (same grid).
    overlap : float
        Fraction of the moved bone's voxels that landed on another bone (kept as the other bone).
    """
    from scipy.ndimage import map_coordinates

    data = np.asarray(hu, dtype=np.float32)
    lab = np.asarray(labels)
    A = np.asarray(world_from_ijk, dtype=np.float64)
    mask = lab == label
    if not mask.any():
        raise ValueError(f"no voxel of label {label} to move")
    sp = np.linalg.norm(A[:3, :3], axis=0)
    where = np.argwhere(mask)
    pad = np.ceil(margin_mm / sp).astype(int)
    lo = np.maximum(where.min(axis=0) - pad, 0)
    hi = np.minimum(where.max(axis=0) + pad + 1, lab.shape)
    box = tuple(slice(lo[d], hi[d]) for d in range(3))
    grid = np.stack(np.meshgrid(*[np.arange(lo[d], hi[d]) for d in range(3)], indexing="ij"), -1)
    M = np.linalg.inv(A) @ tf.invert(np.asarray(transform, dtype=np.float64)) @ A
    src = grid.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]  # ijk the new voxel comes from
    new_mask = map_coordinates(mask.astype(np.float32), src.T, order=0, cval=0.0) > 0.5
    new_hu = map_coordinates(data, src.T, order=1, cval=0.0)
    new_mask = new_mask.reshape(grid.shape[:3])
    out_hu, out_lab = data.copy(), lab.astype(np.uint8).copy()
    sub_hu, sub_lab = out_hu[box], out_lab[box]
    others = (sub_lab > 0) & (sub_lab != label)
    vacated = (sub_lab == label) & ~new_mask
    sub_hu[vacated] = 40.0 + rng.normal(0, 8, int(vacated.sum())).astype(np.float32)
    sub_lab[sub_lab == label] = 0
    placed = new_mask & ~others
    sub_hu[placed] = new_hu.reshape(grid.shape[:3])[placed]
    sub_lab[placed] = label
    overlap = float((new_mask & others).sum() / max(int(new_mask.sum()), 1))
    return out_hu, out_lab, overlap
