"""Synthetic CT volumes (HU) and label maps from the three bone meshes of a subject.

The atlas has surfaces but no CT; this builds a plausible pelvic CT around them, seeded:

* **Bones** - inside tests by generalised winding numbers (libigl's fast winding number; the atlas
  meshes are not watertight), label 1 sacrum, 2 left and 3 right innominate. A cortical shell
  (1.5-3 mm, 1000-1600 HU) over cancellous bone (150-400 HU with smooth texture).
* **Femurs** - heads seated in the acetabula (a sphere found by normal voting and fitted to the
  concave articular surface), with neck and proximal shaft; in the image, not in the label map.
* **Soft tissue** - an elliptic body: skin, subcutaneous fat (about -100 HU), muscle (about
  50 HU), and air outside.
* **Bowel** - gas pockets (about -900 HU) and optionally contrast-filled loops, in front of the
  sacrum and above the pubis, never inside bone.

Grids default to 1 x 1 x 2 mm (i along x, j along y, k along z, LPS).

References: A. Jacobson, L. Kavan, O. Sorkine-Hornung, "Robust inside-outside segmentation using
generalized winding numbers", ACM TOG 32 (2013); G. Barill et al., "Fast winding numbers for
soups and clouds", ACM TOG 37 (2018).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.drr.volume import Volume

__all__ = [
    "CTOptions",
    "SynthCT",
    "bone_labels",
    "bone_mask",
    "femoral_head",
    "paint_beads",
    "synthesize_ct",
    "voxel_grid",
]

BONES = ("sacrum", "left_hip", "right_hip")


@dataclass(frozen=True)
class CTOptions:
    """What goes into a synthetic CT (all ranges are sampled per case from the seed).

    Attributes
    ----------
    spacing : (3,) float, mm
    margin_mm : (3, 2) float
        Grid margin around the bones: (low, high) along x, y, z; the low z margin makes room for
        the femoral shafts.
    cortical_mm, cortical_hu, cancellous_hu : (float, float)
        Ranges of cortical thickness, cortical HU and cancellous HU.
    femurs, bowel_gas, contrast : bool
    beads : int
        Metal fiducial beads (radius ``bead_radius_mm``, 3000 HU) glued to random points of the
        bone surfaces, for target registration error as in the paper's phantom study.
    """

    spacing: tuple[float, float, float] = (1.0, 1.0, 2.0)
    margin_mm: tuple[tuple[float, float], ...] = ((60.0, 60.0), (60.0, 60.0), (90.0, 20.0))
    cortical_mm: tuple[float, float] = (1.5, 3.0)
    cortical_hu: tuple[float, float] = (1000.0, 1600.0)
    cancellous_hu: tuple[float, float] = (150.0, 400.0)
    femurs: bool = True
    bowel_gas: bool = True
    contrast: bool = False
    beads: int = 0
    bead_radius_mm: float = 1.0


@dataclass(frozen=True, eq=False)
class SynthCT:
    """A synthetic CT with ground truth.

    Attributes
    ----------
    hu : Volume
        CT in Hounsfield units (float32), placed by ``world_from_ijk``.
    labels : (ni, nj, nk) uint8
        1 sacrum, 2 left innominate, 3 right innominate, 0 elsewhere (same grid as ``hu``).
    femoral_heads : (2, 4) float64
        Centre (mm) and radius (mm) of the left and right femoral heads.
    beads : (n, 3) float64
        Fiducial bead centres (mm), empty without beads.
    bead_bones : (n,) int64
        Label (1, 2, 3) of the bone each bead is glued to.
    bead_radius : float
    """

    hu: Volume
    labels: NDArray[np.uint8]
    femoral_heads: NDArray[np.float64]
    beads: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    bead_bones: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    bead_radius: float = 1.0


def voxel_grid(
    vertices: ArrayLike, spacing: ArrayLike, margin_mm: ArrayLike
) -> tuple[tuple[int, int, int], NDArray[np.float64]]:
    """Axis-aligned grid covering the bones plus margins: ``(shape, world_from_ijk)``."""
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    sp = np.asarray(spacing, dtype=np.float64)
    m = np.asarray(margin_mm, dtype=np.float64)
    lo = V.min(axis=0) - m[:, 0]
    hi = V.max(axis=0) + m[:, 1]
    shape = tuple(int(n) for n in np.ceil((hi - lo) / sp).astype(int) + 1)
    A = np.eye(4)
    A[:3, :3] = np.diag(sp)
    A[:3, 3] = lo
    return shape, A  # type: ignore[return-value]


def _winding_inside(vertices, faces, points) -> NDArray[np.bool_]:
    import igl

    w = igl.fast_winding_number(
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64),
        np.ascontiguousarray(points, dtype=np.float64),
    )
    return np.asarray(w) > 0.5


def bone_mask(
    vertices: ArrayLike,
    faces: ArrayLike,
    shape: tuple[int, int, int],
    world_from_ijk: ArrayLike,
) -> NDArray[np.bool_]:
    """Voxels of a grid inside one closed, outward mesh (its winding number > 1/2, counted by
    signed ray crossings: :func:`pelvicnav.shape.voxelize.inside_mask`; the generalised winding
    number of every voxel, as before, took 0.5-2 s per bone against 10 ms, and agreed to a few
    voxels in 10^5)."""
    from pelvicnav.shape.voxelize import inside_mask

    return inside_mask(vertices, faces, world_from_ijk, shape)


def bone_labels(
    vertices: ArrayLike,
    faces: tuple[ArrayLike, ...],
    shape: tuple[int, int, int],
    world_from_ijk: ArrayLike,
) -> NDArray[np.uint8]:
    """Label map of the three bones on a grid (:func:`bone_mask` of each).

    Where bones overlap (segmented joints touch), the later bone in ``sacrum, left_hip,
    right_hip`` order does not overwrite an earlier one.
    """
    V = np.asarray(vertices, dtype=np.float64)
    labels = np.zeros(shape, dtype=np.uint8)
    for l in range(3):
        labels[bone_mask(V[l], faces[l], shape, world_from_ijk) & (labels == 0)] = l + 1
    return labels


def _fit_sphere(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    A = np.hstack([2 * p, np.ones((len(p), 1))])
    x = np.linalg.lstsq(A, np.sum(p**2, axis=1), rcond=None)[0]
    c = x[:3]
    return c, float(np.sqrt(max(x[3] + c @ c, 0.0)))


def femoral_head(
    hip_vertices: ArrayLike,
    hip_faces: ArrayLike,
    *,
    radius_range: tuple[float, float] = (18, 32),
    lateral: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], float]:
    """Centre and radius of the acetabular sphere of an innominate bone (mm).

    Every vertex votes for centres along its outward normal at plausible radii (the articular
    cup's normals point at the femoral head's centre); the densest vote starts an iterative sphere
    fit to the vertices whose normals point at the centre. With ``lateral`` (the direction away
    from the midline, e.g. +x for a left innominate in LPS) only centres lateral to the bone's
    centroid are considered: the obturator foramen's rim is concave too, but medial.

    Raises
    ------
    ValueError
        If no concave spherical patch of plausible size is found.
    """
    from pelvicnav.shape.mesh import vertex_normals

    V = np.asarray(hip_vertices, dtype=np.float64)
    N = vertex_normals(V, hip_faces)
    rs = np.arange(radius_range[0], radius_range[1], 1.0)
    votes = (V[:, None, :] + rs[None, :, None] * N[:, None, :]).reshape(-1, 3)
    lo = votes.min(axis=0)
    keys, counts = np.unique(np.floor((votes - lo) / 3.0).astype(int), axis=0, return_counts=True)
    centres = lo + (keys + 0.5) * 3.0
    if lateral is not None:
        side = (centres - V.mean(axis=0)) @ np.asarray(lateral, dtype=np.float64)
        counts = np.where(side > 0, counts, 0)
    c = centres[np.argmax(counts)]
    r = float(np.mean(radius_range))
    for _ in range(6):
        d = np.linalg.norm(V - c, axis=1)
        towards = np.einsum("ij,ij->i", N, (c - V) / np.maximum(d, 1e-9)[:, None])
        near = (towards > 0.8) & (d < radius_range[1] + 5)
        if near.sum() < 20:
            break
        r = float(np.median(d[near]))
        sel = near & (np.abs(d - r) < 3.0)
        if sel.sum() < 20:
            break
        c, r = _fit_sphere(V[sel])
    # The cup must be concave towards the centre: enough vertices on the sphere facing it.
    d = np.linalg.norm(V - c, axis=1)
    towards = np.einsum("ij,ij->i", N, (c - V) / np.maximum(d, 1e-9)[:, None])
    support = int(np.sum((towards > 0.8) & (np.abs(d - r) < 3.0)))
    if not radius_range[0] <= r <= radius_range[1] + 3 or support < 30:
        raise ValueError(
            f"no acetabulum found: best sphere radius {r:.1f} mm with {support} supporting vertices"
        )
    return c, r


def _capsule(points, a, b, radius) -> NDArray[np.bool_]:
    """Points within ``radius`` of segment ``a``-``b``."""
    ab = b - a
    t = np.clip(((points - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1) <= radius


def synthesize_ct(
    vertices: ArrayLike,
    faces: tuple[ArrayLike, ...],
    *,
    rng: np.random.Generator,
    options: CTOptions | None = None,
) -> SynthCT:
    """Build a CT (HU) and label map from one subject's three bone meshes.

    Parameters
    ----------
    vertices : (3, n_vertices, 3) float, mm (LPS)
        Sacrum, left and right innominate.
    faces : three (m_l, 3) int arrays
    rng : numpy.random.Generator
        Everything random (tissue thicknesses, textures, gas) comes from it, in this order:
        the body, the femurs, the bowel, the bones, the beads.
    options : CTOptions, optional

    Returns
    -------
    SynthCT
    """
    opt = options or CTOptions()
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 3 or V.shape[0] != 3 or V.shape[2] != 3:
        raise ValueError(f"vertices must have shape (3, n_vertices, 3), got {V.shape}")
    if not np.all(np.isfinite(V)):
        raise ValueError("vertices contain NaN or infinity")
    shape, A = voxel_grid(V, opt.spacing, opt.margin_mm)
    labels = bone_labels(V, faces, shape, A)
    axes = tuple(A[d, 3] + opt.spacing[d] * np.arange(shape[d]) for d in range(3))
    hu, depth_mm = _body(V, axes, shape, rng)
    heads = np.zeros((2, 4))
    if opt.femurs:
        heads = _paint_femurs(hu, labels, V, faces, axes, opt, rng)
    _paint_bowel(hu, labels, depth_mm[:, :, None] > 15, V[0].mean(axis=0), axes, opt, rng)
    _paint_bones(hu, labels, opt, rng)
    beads, bead_bones = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    if opt.beads > 0:
        beads, bead_bones = _bead_centres(V, faces, opt, rng)
        paint_beads(hu, A, beads, opt.bead_radius_mm)
    return SynthCT(hu=Volume(hu, A), labels=labels, femoral_heads=heads, beads=beads,
                   bead_bones=bead_bones, bead_radius=opt.bead_radius_mm)  # fmt: skip


def _box(axes: tuple[NDArray, ...], lo: ArrayLike, hi: ArrayLike) -> tuple[slice, ...]:
    """The voxel slices of the world box ``[lo, hi]`` (mm) on a grid's ``axes``."""
    return tuple(slice(*np.clip(np.searchsorted(ax, [a, b]), 0, len(ax)))
                 for ax, a, b in zip(axes, lo, hi, strict=True))  # fmt: skip


def _body(V: NDArray, axes: tuple[NDArray, ...], shape: tuple[int, ...],
          rng: np.random.Generator) -> tuple[NDArray[np.float32], NDArray]:  # fmt: skip
    """Soft tissue: an elliptic body, the same cross-section along z (skin, fat, muscle), with
    noise inside it. Returns the volume (HU) and each column's depth below the skin (mm)."""
    x, y, _ = axes
    centre = V.reshape(-1, 3).mean(axis=0)
    half_width = 0.5 * np.ptp(V[..., 0]) + rng.uniform(35, 60)
    half_depth = 0.5 * np.ptp(V[..., 1]) + rng.uniform(45, 70)
    fat = rng.uniform(10, 30)
    X, Y = np.meshgrid(x - centre[0], y - centre[1] + rng.uniform(-5, 5), indexing="ij")
    rho = np.sqrt((X / half_width) ** 2 + (Y / half_depth) ** 2)  # 1 at the skin
    depth_mm = (1 - rho) * 0.5 * (half_width + half_depth)  # approximate depth below the skin
    tissue = np.full(X.shape, -1000.0, dtype=np.float32)
    tissue[depth_mm >= 0] = 30.0  # skin
    tissue[depth_mm >= 2] = -100.0  # subcutaneous fat
    tissue[depth_mm >= 2 + fat] = 50.0  # muscle and viscera
    hu = np.broadcast_to(tissue[:, :, None], shape).astype(np.float32)
    hu += (depth_mm >= 0)[:, :, None] * rng.normal(0, 8, shape).astype(np.float32)
    return hu, depth_mm


def _paint_femurs(hu: NDArray, labels: NDArray, V: NDArray, faces, axes: tuple[NDArray, ...],
                  opt: CTOptions, rng: np.random.Generator) -> NDArray:  # fmt: skip
    """Both femurs (head, neck and shaft capsules; image only, outside the labels) painted into
    ``hu``; returns the femoral heads (2, 4): centre (mm) and radius."""
    from scipy.ndimage import distance_transform_edt

    sp = np.asarray(opt.spacing, dtype=np.float64)
    heads = np.zeros((2, 4))
    for h, (b, side) in enumerate(((1, 1.0), (2, -1.0))):
        c, r = femoral_head(V[b], faces[b], lateral=(side, 0.0, 0.0))
        heads[h] = [*c, r]
        r_head = max(r - 2.0, 10.0)  # joint space of ~2 mm
        neck_end = c + np.array([side * 0.75, 0.1, -0.65]) * 50.0
        shaft_end = neck_end + np.array([-side * 0.15, 0.0, -1.0]) * 400.0
        sl = _box(axes, np.minimum(c - 40, np.minimum(neck_end, shaft_end) - 25),
                  np.maximum(c + 40, np.maximum(neck_end, shaft_end) + 25))  # fmt: skip
        sub = np.stack(np.meshgrid(*(ax[s] for ax, s in zip(axes, sl, strict=True)),
                                   indexing="ij"), -1)  # fmt: skip
        pts = sub.reshape(-1, 3)
        femur = (
            (np.linalg.norm(pts - c, axis=1) <= r_head)
            | _capsule(pts, c, neck_end, rng.uniform(14, 17))
            | _capsule(pts, neck_end, shaft_end, rng.uniform(13, 16))
        )
        femur = femur.reshape(sub.shape[:3]) & (labels[sl] == 0)
        region = hu[sl]
        depth = distance_transform_edt(femur, sampling=sp)
        cort = rng.uniform(*opt.cortical_hu)
        region[femur] = np.where(depth[femur] < 3.0, cort, rng.uniform(200, 350))
        hu[sl] = region
    return heads


def _paint_bowel(hu: NDArray, labels: NDArray, body: NDArray, sacrum_c: NDArray,
                 axes: tuple[NDArray, ...], opt: CTOptions,
                 rng: np.random.Generator) -> None:  # fmt: skip
    """Bowel gas pockets and contrast (ellipsoids anterior to the sacrum, above the pubis,
    inside the ``body`` columns and outside the bones) painted into ``hu``."""
    x, y, z = axes
    for kind, enabled, value, count in (
        ("gas", opt.bowel_gas, -900.0, rng.integers(3, 9)),
        ("contrast", opt.contrast, 250.0, rng.integers(2, 5)),
    ):
        if not enabled:
            continue
        for _ in range(int(count)):
            ctr = sacrum_c + np.array(
                [rng.uniform(-50, 50), rng.uniform(-90, -30), rng.uniform(-10, 60)]
            )
            radii = rng.uniform(8, 25, 3) if kind == "gas" else rng.uniform(10, 30, 3)
            sl = _box(axes, ctr - radii, ctr + radii)
            gx, gy, gz = np.meshgrid(x[sl[0]], y[sl[1]], z[sl[2]], indexing="ij")
            inside = ((gx - ctr[0]) / radii[0]) ** 2 + ((gy - ctr[1]) / radii[1]) ** 2 + (
                (gz - ctr[2]) / radii[2]
            ) ** 2 <= 1
            inside &= body[sl[0], sl[1]] & (labels[sl] == 0)
            region = hu[sl]
            region[inside] = value + rng.normal(0, 20, inside.sum())
            hu[sl] = region


def _paint_bones(hu: NDArray, labels: NDArray, opt: CTOptions, rng: np.random.Generator) -> None:
    """Each labelled bone painted into ``hu``: a cortical shell over textured cancellous bone."""
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    sp = np.asarray(opt.spacing, dtype=np.float64)
    for l in range(3):
        mask = labels == l + 1
        if not mask.any():
            continue
        idx = np.argwhere(mask)
        lo, hi = np.maximum(idx.min(0) - 2, 0), np.minimum(idx.max(0) + 3, labels.shape)
        box = (slice(lo[0], hi[0]), slice(lo[1], hi[1]), slice(lo[2], hi[2]))
        m = mask[box]
        depth = distance_transform_edt(m, sampling=sp)
        t_cort = rng.uniform(*opt.cortical_mm)
        c_hu = rng.uniform(*opt.cortical_hu)
        base = rng.uniform(*opt.cancellous_hu)
        texture = gaussian_filter(rng.normal(0, 1, m.shape), 1.5 / sp) * 4.0
        cancellous = base + 60.0 * texture
        region = hu[box]
        region[m] = np.where(
            depth[m] <= t_cort, c_hu + rng.normal(0, 40, m.sum()), cancellous[m]
        ).astype(np.float32)
        hu[box] = region


def _bead_centres(V: NDArray, faces, opt: CTOptions,
                  rng: np.random.Generator) -> tuple[NDArray, NDArray]:  # fmt: skip
    """``opt.beads`` fiducial bead centres (mm) one radius outside random vertices of random
    bones, and their bones (labels 1-3)."""
    from pelvicnav.shape.mesh import vertex_normals

    bead_bones = rng.integers(0, 3, opt.beads) + 1
    beads = np.empty((opt.beads, 3))
    for n, lab in enumerate(bead_bones):
        normals = vertex_normals(V[lab - 1], faces[lab - 1])
        i = rng.integers(0, V.shape[1])
        beads[n] = V[lab - 1, i] + normals[i] * opt.bead_radius_mm
    return beads, bead_bones


def paint_beads(
    hu: NDArray[np.float32],
    world_from_ijk: NDArray[np.float64],
    centres: NDArray[np.float64],
    radius: float,
    value: float | NDArray = 3000.0,
) -> None:
    """Set voxels whose centres lie within ``radius`` of each centre (at least the nearest)."""
    A = np.asarray(world_from_ijk)
    Ainv = np.linalg.inv(A)
    sp = np.linalg.norm(A[:3, :3], axis=0)
    reach = np.ceil(radius / sp).astype(int) + 1
    for n, c in enumerate(np.asarray(centres, dtype=np.float64)):
        ijk = np.rint(Ainv[:3, :3] @ c + Ainv[:3, 3]).astype(int)
        lo = np.maximum(ijk - reach, 0)
        hi = np.minimum(ijk + reach + 1, hu.shape)
        if np.any(hi <= lo):
            continue
        g = np.stack(
            np.meshgrid(*[np.arange(lo[d], hi[d]) for d in range(3)], indexing="ij"), -1
        ).astype(np.float64)
        w = g @ A[:3, :3].T + A[:3, 3]
        # A bead smaller than a voxel still marks the voxel it sits in (half the voxel diagonal).
        inside = np.linalg.norm(w - c, axis=-1) <= max(radius, 0.5 * np.linalg.norm(sp))
        box = hu[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        box[inside] = value if np.ndim(value) == 0 else value[n]
