"""Multi-resolution active shape model of the three pelvic bones on a CT (no label map needed).

Han et al. (2020) section 2.1.1 and Han et al. (2019), doi:10.1088/1361-6560/ab1456; T. F.
Cootes et al., "Active shape models", CVIU 61 (1995) 38-59. The stages:

1. **Pyramid.** The CT is block-averaged to about 4, 2 and 1 mm (never finer than it is).
2. **Bone content.** Bone is CT number above :attr:`ASMSettings.bone_hu`; a CT whose non-bone
   voxels are masked to one constant (most voxels share one value) takes everything above it.
3. **Initialisation** (:func:`initial_pose`), on the coarsest level: the model's mean pelvis is
   placed on the bone content by trimmed iterated closest points (a similarity, scale bounded),
   started at several heights along the patient axis and kept at the lowest trimmed cost, so
   femurs and lumbar spine in the field do not capture it. Model points outside the scanned
   field (a scan cut below the femoral heads) take no part. Then each bone on its own (its
   similarity and SSM weights), so a dislocated bone is found with its own pose.
4. **Profile search**, coarse to fine: along each vertex's outward normal, the strongest fall
   of CT number (bone inside, soft tissue outside) within the level's search range, penalised
   by distance; MAP fit of a similarity and the SSM weights to the found edges
   (:meth:`~pelvicnav.shape.ssm.ShapeModel.fit_partial`), weights clamped to +-3 sigma.
5. **Free-form refinement**: edge displacements smoothed over the mesh, then the bones pushed
   apart where they overlap at the sacroiliac joints and the symphysis.
6. **Correspondence**: each bone's vertices re-placed on its fitted surface where the model
   expects them (:mod:`pelvicnav.shape.correspond`; the free-form stage lets them slide).
7. **Label map** on the CT's grid: a voxel belongs to the bone whose fitted surface it lies in,
   or within :attr:`ASMSettings.label_band_mm` outside of it where the CT holds bone there.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.shape.mesh import edge_adjacency, vertex_normals
from pelvicnav.shape.ssm import ShapeModel

__all__ = ["ASMResult", "ASMSettings", "ShapePrior", "initial_pose", "segment_ct"]


@dataclass(frozen=True)
class ASMSettings:
    """Settings of :func:`segment_ct` (the defaults are what the segmentation study measures).

    Attributes
    ----------
    levels_mm : tuple of float
        Target voxel size of each pyramid level, coarse to fine.
    search_level_mm : float
        Voxel size of the global placement search (:func:`initial_pose`).
    search_mm : tuple of float
        Half-length of the profile search along the normal, per level.
    iterations : tuple of int
        Search-and-fit rounds per level.
    noise_mm2 : tuple of float
        Edge noise variance of the MAP fit per level (larger trusts the mean shape more).
    max_sigma : float
        SSM weights are clamped to +- this many standard deviations.
    bone_hu : float
        CT number above which a voxel is bone (unmasked CTs).
    min_edge_hu : float
        Smallest fall of CT number across an edge that counts as the bone's boundary.
    free_form_rounds : int
        Rounds of the free-form refinement (0: the model's instance only).
    joint_search_mm, joint_reach_mm : float
        Where a vertex is within ``joint_reach_mm`` of another bone (the sacroiliac joints, the
        symphysis), the free-form stage searches ``joint_search_mm`` instead: the model's fit
        leaves parts of a joint surface 4-6 mm inside the bone (the profile search at 2 mm does
        not resolve a 1-3 mm joint space), out of the 2.5 mm search's reach. Atlas leave-one-out
        (40 subjects, median): the left hips' sacroiliac surfaces' 90th-percentile error 2.05 ->
        1.3 mm, their surface RMSD 0.75 -> 0.71 mm; the target pose from these meshes 2.94 mm /
        2.63 deg -> 2.45 / 2.54 (docs/segmentation.md).
    correspondence_rounds, correspondence_noise_mm2 : int, float
        The final correspondence stage (:func:`pelvicnav.shape.correspond.refine_correspondence`):
        rounds (0: none) and point-to-plane noise variance (mm^2).
    label_band_mm : float
        Bone voxels this far outside a fitted surface still belong to it.
    masked_reach_mm : float
        The same reach on a CT whose non-bone voxels are masked to a constant: every voxel left
        is bone of the pelvis, so bone the model misses (a coccyx, a displaced fragment) goes to
        the nearest fitted surface within this distance.
    """

    levels_mm: tuple[float, ...] = (4.0, 2.0, 1.0)
    search_level_mm: float = 6.0
    search_mm: tuple[float, ...] = (10.0, 5.0, 2.5)
    iterations: tuple[int, ...] = (12, 10, 8)
    noise_mm2: tuple[float, ...] = (16.0, 4.0, 1.0)
    max_sigma: float = 3.0
    bone_hu: float = 150.0
    min_edge_hu: float = 80.0
    free_form_rounds: int = 16
    free_form_search_mm: float = 2.5
    joint_search_mm: float = 6.0
    joint_reach_mm: float = 10.0
    free_form_smooth: int = 4
    correspondence_rounds: int = 20
    correspondence_noise_mm2: float = 0.5
    label_band_mm: float = 1.5
    masked_reach_mm: float = 25.0

    def __post_init__(self) -> None:
        n = len(self.levels_mm)
        if n < 1 or len(self.search_mm) != n or len(self.iterations) != n:
            raise ValueError("levels_mm, search_mm and iterations must have one entry per level")
        if len(self.noise_mm2) != n:
            raise ValueError("noise_mm2 must have one entry per level")
        if not (self.free_form_search_mm > 0 and self.joint_search_mm > 0
                and self.joint_reach_mm >= 0):  # fmt: skip
            raise ValueError("free_form_search_mm and joint_search_mm must be positive and "
                             f"joint_reach_mm at least 0; got {self.free_form_search_mm}, "
                             f"{self.joint_search_mm} and {self.joint_reach_mm}")  # fmt: skip


@dataclass(frozen=True, eq=False)
class ShapePrior:
    """What the ASM needs of a pelvis model: the SSMs, their faces and a mean configuration.

    Attributes
    ----------
    shapes : dict bone -> ShapeModel
    faces : tuple of three (m_l, 3) int
        Closed, outward triangulations.
    reference : (3, n_vertices, 3) float64, mm
        The three bones in one configuration (the population's mean pelvis, patient axes LPS).
    """

    shapes: Mapping[str, ShapeModel]
    faces: tuple[NDArray[np.int64], ...]
    reference: NDArray[np.float64]

    @classmethod
    def from_model(cls, model) -> ShapePrior:
        """From a :class:`pelvicnav.model.pelvis.PelvisModel`."""
        pop = model.population
        reference = tf.apply(pop.poses_from_vector(pop.mean), pop.mean_shapes)
        return cls(shapes=dict(model.shapes), faces=tuple(model.faces), reference=reference)

    @classmethod
    def from_subjects(cls, vertices: ArrayLike, faces: tuple[ArrayLike, ...]) -> ShapePrior:
        """Fit from corresponded subjects ``(n, 3, n_vertices, 3)`` (e.g. an atlas less the
        subject to segment): SSMs keeping 99 % of the variance, the faces closed on the mean,
        the population's mean configuration. No repair of the meshes (the shipped model has
        it), so a few seconds instead of minutes: what leave-one-out needs."""
        from pelvicnav.model.pelvis import _shape_model
        from pelvicnav.pose.spm import PoseModel
        from pelvicnav.shape.mesh import close_mesh

        V = np.asarray(vertices, dtype=np.float64)
        closed = tuple(close_mesh(V[:, b].mean(axis=0), faces[b]) for b in range(3))
        shapes = {bone: _shape_model(V[:, b], closed[b], 0.99) for b, bone in enumerate(BONES)}
        pop = PoseModel.fit(V, frame_bones=BONES, frame_scale=False)
        reference = tf.apply(pop.poses_from_vector(pop.mean), pop.mean_shapes)
        return cls(shapes=shapes, faces=closed, reference=reference)


@dataclass(frozen=True, eq=False)
class ASMResult:
    """The three bones segmented on a CT.

    Attributes
    ----------
    vertices : (3, n_vertices, 3) float64, mm (world)
        Fitted meshes in the model's topology (bone order :data:`pelvicnav.BONES`).
    weights : dict bone -> (n_modes,) float64
        SSM weights of the model stage (before the free-form refinement).
    labels : (ni, nj, nk) uint8
        1 sacrum, 2 left hip, 3 right hip on the CT's grid.
    quality : dict bone -> dict
        ``edge_rms_mm`` (RMS distance of the final surface to the edges found along its
        normals), ``edge_fraction`` (vertices with an edge within reach), ``overlap_vertices``
        (vertices left inside another bone), ``weights_at_limit`` (modes clamped at +-3 sigma),
        ``scale`` (of the bone's similarity).
    seconds : dict
        Time per stage.
    """

    vertices: NDArray[np.float64]
    weights: dict[str, NDArray[np.float64]]
    labels: NDArray[np.uint8]
    quality: dict[str, dict[str, float]]
    seconds: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class _Level:
    """One pyramid level: CT numbers on a coarser grid."""

    data: NDArray[np.float32]
    world_from_ijk: NDArray[np.float64]
    spacing_mm: float

    @property
    def ijk_from_world(self) -> NDArray[np.float64]:
        return np.linalg.inv(self.world_from_ijk)


def _block_mean(data: NDArray, factors: tuple[int, int, int]) -> NDArray[np.float32]:
    """Mean over ``factors`` blocks (the grid cropped to whole blocks)."""
    f = factors
    n = [s // k for s, k in zip(data.shape, f, strict=True)]
    crop = data[: n[0] * f[0], : n[1] * f[1], : n[2] * f[2]]
    out = crop.reshape(n[0], f[0], n[1], f[1], n[2], f[2]).mean(axis=(1, 3, 5), dtype=np.float32)
    return np.ascontiguousarray(out, dtype=np.float32)


def _pyramid(hu: NDArray, world_from_ijk: NDArray, levels_mm) -> list[_Level]:
    A = np.asarray(world_from_ijk, dtype=np.float64)
    spacing = np.linalg.norm(A[:3, :3], axis=0)
    out = []
    for mm in levels_mm:
        f = tuple(int(max(1, round(mm / s))) for s in spacing)
        data = hu.astype(np.float32, copy=False) if f == (1, 1, 1) else _block_mean(hu, f)
        B = A.copy()
        B[:3, :3] = A[:3, :3] * np.asarray(f, dtype=np.float64)
        B[:3, 3] = A[:3, :3] @ ((np.asarray(f) - 1) / 2.0) + A[:3, 3]
        out.append(_Level(data, B, float(np.mean(spacing * np.asarray(f)))))
    return out


def bone_threshold(hu: NDArray, bone_hu: float) -> tuple[float, float | None]:
    """``(threshold, masked_value)``: CT numbers above the threshold are bone.

    A CT whose non-bone voxels were set to one constant takes everything above that constant;
    ``masked_value`` is then the constant. Masked means: at least 40 % of a sample share one
    value below ``bone_hu`` and the other voxels are mostly bone (median above ``bone_hu``), so
    a CT with much air at -1000 HU around a body is not taken for a masked one.
    """
    sample = np.asarray(hu).ravel()[:: max(1, hu.size // 2_000_000)]
    values, counts = np.unique(sample, return_counts=True)
    k = int(np.argmax(counts))
    rest = sample[sample != values[k]]
    if (
        counts[k] >= 0.4 * len(sample)
        and values[k] < bone_hu
        and len(rest)
        and np.median(rest) > bone_hu
    ):
        return float(values[k]) + 1.0, float(values[k])
    return float(bone_hu), None


def _inside_grid(level: _Level, points: NDArray, margin: float = 1.0) -> NDArray[np.bool_]:
    ijk = tf.apply(level.ijk_from_world, points)
    shape = np.asarray(level.data.shape)
    return np.all((ijk >= margin) & (ijk <= shape - 1 - margin), axis=1)


def _closest_bone(level: _Level, threshold: float):
    """Closest-bone lookup on a level: ``points -> (distance mm, closest bone point)``."""
    from scipy.ndimage import distance_transform_edt

    bone = level.data > threshold
    if not bone.any():
        raise ValueError("the CT holds no bone (no voxel above the bone threshold)")
    spacing = np.linalg.norm(level.world_from_ijk[:3, :3], axis=0)
    dist, ind = distance_transform_edt(~bone, sampling=spacing, return_indices=True)
    inv = level.ijk_from_world
    shape = np.asarray(bone.shape)

    def lookup(points: NDArray) -> tuple[NDArray, NDArray]:
        ijk = np.clip(np.rint(tf.apply(inv, points)).astype(int), 0, shape - 1)
        i, j, k = ijk.T
        near = np.stack([ind[0][i, j, k], ind[1][i, j, k], ind[2][i, j, k]], axis=1)
        target = tf.apply(level.world_from_ijk, near.astype(np.float64))
        return np.linalg.norm(target - points, axis=1), target

    return lookup


def _trimmed_icp(source, lookup, inside, start, *, iterations=20, keep=0.8, scale=(0.8, 1.25)):
    """Similarity ``T`` (world_from_source) by trimmed ICP; ``(T, trimmed RMS mm)``."""
    T = start.copy()
    cost = np.inf
    for _ in range(iterations):
        moved = tf.apply(T, source)
        ok = inside(moved)
        if ok.sum() < 30:
            return T, np.inf
        d, target = lookup(moved[ok])
        cut = np.quantile(d, keep)
        use = d <= cut
        cost = float(np.sqrt(np.mean(d[use] ** 2)))
        step = fit_transform(moved[ok][use], target[use], scale=True)
        T = step @ T
        s = np.cbrt(np.linalg.det(T[:3, :3]))
        if not scale[0] <= s <= scale[1]:
            c = np.clip(s, *scale) / s
            centre = tf.apply(T, source).mean(axis=0)
            S = np.eye(4)
            S[:3, :3] *= c
            S[:3, 3] = centre - c * centre
            T = S @ T
    return T, cost


def _rotation_about(axis: int, degrees: float, centre: NDArray) -> NDArray[np.float64]:
    rotvec = np.zeros(3)
    rotvec[axis] = np.deg2rad(degrees)
    T = np.eye(4)
    T[:3, :3] = tf.matrix_from_rotvec(rotvec)
    T[:3, 3] = centre - T[:3, :3] @ centre
    return T


def _template(level: _Level, bones: list[NDArray], faces) -> tuple[NDArray, NDArray]:
    """Inside mask of meshes on a box of the level's grid: ``(mask, lo)``, ``lo`` the box's
    first voxel (level ijk)."""
    from pelvicnav.shape.voxelize import inside_mask

    ijk = tf.apply(level.ijk_from_world, np.concatenate(bones))
    lo = np.floor(ijk.min(axis=0)).astype(int) - 1
    shape = tuple(int(n) for n in np.ceil(ijk.max(axis=0)).astype(int) - lo + 2)
    B = level.world_from_ijk.copy()
    B[:3, 3] = level.world_from_ijk[:3, :3] @ lo + level.world_from_ijk[:3, 3]
    mask = np.zeros(shape, dtype=bool)
    for v, f in zip(bones, faces, strict=True):
        mask |= inside_mask(v, f, B, shape)
    return mask, lo


def _best_shift(signed: NDArray, mask: NDArray, lo: NDArray, window: NDArray | None = None):
    """Translation (level ijk) of a template that best matches a +-1 bone map by FFT
    correlation, within ``window`` voxels of no shift if given; ``(shift, score)``, the score
    being the mean of the map over the shifted template (1: all bone, -1: none; beyond the
    grid counts as -1)."""
    from scipy.signal import fftconvolve

    kernel = mask[::-1, ::-1, ::-1].astype(np.float32)
    corr = fftconvolve(signed, kernel, mode="full")
    # Template voxels beyond the grid count as not bone: no escape off the scanned field.
    inside = fftconvolve(np.ones_like(signed), kernel, mode="full")
    corr -= float(mask.sum()) - inside
    L = np.asarray(mask.shape)
    if window is not None:
        n0 = lo + L - 1  # the index of no shift
        lo_w = np.maximum(n0 - window, 0)
        hi_w = np.minimum(n0 + window + 1, corr.shape)
        box = tuple(slice(a, b) for a, b in zip(lo_w, hi_w, strict=True))
        sub = corr[box]
        n = np.asarray(np.unravel_index(np.argmax(sub), sub.shape)) + lo_w
    else:
        n = np.asarray(np.unravel_index(np.argmax(corr), corr.shape))
    return (n - (L - 1)) - lo, float(corr[tuple(n)] / max(mask.sum(), 1))


def _shift_world(level: _Level, shift: NDArray) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, 3] = level.world_from_ijk[:3, :3] @ shift
    return T


def initial_pose(
    search: _Level, level: _Level, reference: NDArray, faces, threshold: float
) -> tuple[NDArray[np.float64], float]:
    """``(world_from_reference, trimmed RMS mm)``: the mean pelvis placed on the bone content.

    A global search on the coarse ``search`` level: the mean pelvis, tilted about the
    left-right axis (-12 to 12 deg) and scaled (0.9-1.1), rasterised and correlated with the CT's
    bone map (+1 bone, -1 not) over all translations by FFT; the best placement is refined by
    trimmed closest-bone ICP on ``level``.

    Raises
    ------
    ValueError
        No bone in the CT, or no placement that overlaps it.
    """
    bone = search.data > threshold
    if not bone.any():
        raise ValueError("the CT holds no bone (no voxel above the bone threshold)")
    signed = np.where(bone, 1.0, -1.0).astype(np.float32)
    pts = tf.apply(search.world_from_ijk, np.argwhere(bone).astype(np.float64))
    centre = reference.reshape(-1, 3).mean(axis=0)
    place = np.eye(4)
    place[:3, 3] = np.median(pts, axis=0) - centre
    best = (-np.inf, np.eye(4))
    for tilt in (-12.0, -6.0, 0.0, 6.0, 12.0):
        for scale in (0.9, 1.0, 1.1):
            S = np.eye(4)
            S[:3, :3] *= scale
            S[:3, 3] = centre - scale * centre
            T = place @ _rotation_about(0, tilt, centre) @ S
            mask, lo = _template(search, [tf.apply(T, v) for v in reference], faces)
            shift, score = _best_shift(signed, mask, lo)
            if score > best[0]:
                best = (score, _shift_world(search, shift) @ T)
    lookup = _closest_bone(level, threshold)
    ref = reference.reshape(-1, 3)[::7]
    T, cost = _trimmed_icp(ref, lookup, lambda p: _inside_grid(level, p), best[1])
    if not np.isfinite(cost):
        raise ValueError("could not place the pelvis model on the CT's bone content")
    return T, cost


def _bone_search(search: _Level, V: NDArray, faces, threshold: float, reach_mm: float = 25.0):
    """Each bone's own translation: its template correlated with the bone map within
    ``reach_mm`` of where the pelvis put it (a dislocated bone moved up to 20 mm)."""
    signed = np.where(search.data > threshold, 1.0, -1.0).astype(np.float32)
    window = np.ceil(reach_mm / np.linalg.norm(search.world_from_ijk[:3, :3], axis=0)).astype(int)
    out = V.copy()
    for b in range(len(V)):
        mask, lo = _template(search, [V[b]], [faces[b]])
        shift, _ = _best_shift(signed, mask, lo, window)
        out[b] = tf.apply(_shift_world(search, shift), V[b])
    return out


def _clamped_fit(ssm: ShapeModel, points, indices, noise: float, max_sigma: float):
    """MAP similarity + weights fit with the weights clamped to +-max_sigma; (vertices, w, T)."""
    fit = ssm.fit_partial(points, indices, noise_variance=noise, max_iter=5)
    limit = max_sigma * np.sqrt(ssm.variances)
    w = np.clip(fit.weights, -limit, limit)
    if np.any(w != fit.weights):
        shape = ssm.instance(w)
        T = fit_transform(shape[indices], points, scale=True)
        return tf.apply(T, shape), w, T
    return fit.vertices, w, fit.subject_from_model


def _edges(level: _Level, vertices, normals, search_mm, min_edge, inside, threshold):
    """Edge offsets along the normals: ``(found (n,) bool, offset (n,) mm)``.

    An edge is where the profile crosses the bone threshold going outwards (bone inside, not
    bone outside) with a fall of at least ``min_edge`` across two samples; of several, the
    steepest, less 20 HU per mm of distance. The inner edge of a neighbour's cortex (a femoral
    head's, cancellous bone beyond) does not cross the threshold, so it is never taken.
    """
    from scipy.ndimage import map_coordinates

    h = 0.5 * level.spacing_mm
    t = np.arange(-search_mm, search_mm + 1e-9, h)
    pts = vertices[:, None, :] + t[None, :, None] * normals[:, None, :]
    ijk = tf.apply(level.ijk_from_world, pts.reshape(-1, 3))
    prof = map_coordinates(level.data, ijk.T, order=1, mode="nearest").reshape(len(vertices), -1)
    inner, outer = prof[:, :-2], prof[:, 2:]
    fall = inner - outer  # I(t - h) - I(t + h)
    crossing = (inner > threshold) & (outer <= threshold) & (fall >= min_edge)
    tc = t[1:-1]
    score = np.where(crossing, fall - 20.0 * np.abs(tc), -np.inf)
    best = np.argmax(score, axis=1)
    found = np.isfinite(score[np.arange(len(vertices)), best]) & inside(vertices)
    return found, tc[best]


@dataclass(frozen=True, eq=False)
class _Surface:
    """Bone-boundary voxels of a level: ``points`` (k, 3) mm and outward unit ``directions``."""

    points: NDArray[np.float64]
    directions: NDArray[np.float64]


def _bone_surface(
    level: _Level, threshold: float, near: NDArray, reach: float, max_points: int = 60_000
) -> _Surface:
    """The bone content's boundary on a level within ``reach`` mm of the box around ``near``
    (current meshes), moved half a voxel out, with the outward direction of the CT number's
    fall (central differences over 1.5 voxels)."""
    from scipy.ndimage import binary_erosion, map_coordinates

    A = level.world_from_ijk
    spacing = np.linalg.norm(A[:3, :3], axis=0)
    box, lo = _box(near, A, level.data.shape, reach / spacing + 2)
    bone = level.data[box] > threshold
    edge = bone & ~binary_erosion(bone)
    where = np.argwhere(edge)
    if len(where) > max_points:
        where = where[:: int(np.ceil(len(where) / max_points))]
    ijk = (where + lo).astype(np.float64)
    grad = np.empty_like(ijk)
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = 1.5
        up = map_coordinates(level.data, (ijk + step).T, order=1, mode="nearest")
        down = map_coordinates(level.data, (ijk - step).T, order=1, mode="nearest")
        grad[:, axis] = (up - down) / 3.0
    g_world = grad @ np.linalg.inv(A[:3, :3])
    norm = np.linalg.norm(g_world, axis=1, keepdims=True)
    ok = norm[:, 0] > 0
    out_dir = -g_world[ok] / norm[ok]
    pts = tf.apply(A, ijk[ok]) + 0.5 * level.spacing_mm * out_dir
    return _Surface(pts, out_dir)


def _nearest_bones(trees, surface: _Surface, reach: float):
    """For each boundary point: distance to each bone's nearest vertex (inf beyond ``reach``)
    and that vertex; ``((3, k), (3, k))``."""
    found = [t.query(surface.points, distance_upper_bound=reach) for t in trees]
    return np.stack([f[0] for f in found]), np.stack([f[1] for f in found])


def _facing(normals, nearest, surface: _Surface) -> NDArray[np.float64]:
    """(3, k): each boundary point's distance to each bone's nearest vertex (``nearest``) where
    that vertex's normal (``normals``: every bone's) faces the point's way, else inf."""
    d, j_all = nearest
    facing = np.full(d.shape, np.inf)
    for c in range(len(d)):
        ok = np.isfinite(d[c])
        agree = np.zeros(len(ok), dtype=bool)
        agree[ok] = np.einsum("ij,ij->i", surface.directions[ok], normals[c][j_all[c][ok]]) > 0.5
        facing[c] = np.where(agree, d[c], np.inf)
    return facing


def _data_pairs(b, facing, nearest, surface: _Surface, joint=None):
    """Bone-boundary points that bone ``b``'s surface should cover: within reach of it, nearer
    to it than to the other bones, facing the same way (``facing``: :func:`_facing`);
    ``(vertex indices, points)``. ``joint`` ((n_vertices,) bool, optional): bone ``b``'s
    vertices at a joint, which also take a point that another bone's mesh is nearer to when that
    mesh faces back (the point is not its boundary) and ``b``'s is the nearest facing the point's
    way: across a joint space the two boundaries face each other, and a joint surface fitted
    short of its boundary has the other bone's mesh nearer."""
    d, j_all = nearest
    near = np.isfinite(facing[b]) & (facing[b] <= facing.min(axis=0))
    mine = d[b] <= d.min(axis=0)
    if joint is not None:
        mine |= np.append(joint, False)[j_all[b]]  # j_all is n_vertices where out of reach
    return j_all[b][near & mine], surface.points[near & mine]


def _fit_level(prior, V, level, surface, k, opt, inside, weights, threshold):
    """Search-and-fit rounds of one level for the three bones; returns the bones' scales."""
    from scipy.spatial import cKDTree

    scales = {}
    for _ in range(opt.iterations[k]):
        normals = [vertex_normals(V[b], prior.faces[b]) for b in range(3)]
        nearest = _nearest_bones([cKDTree(V[b]) for b in range(3)], surface, opt.search_mm[k])
        facing = _facing(normals, nearest, surface)
        for b, bone in enumerate(BONES):
            found, off = _edges(
                level, V[b], normals[b], opt.search_mm[k], opt.min_edge_hu, inside, threshold
            )
            if found.sum() < 0.1 * len(V[b]):
                continue
            idx = np.flatnonzero(found)
            targets = V[b][idx] + off[idx, None] * normals[b][idx]
            j, pts = _data_pairs(b, facing, nearest, surface)
            V[b], weights[bone], T = _clamped_fit(
                prior.shapes[bone], np.concatenate([targets, pts]), np.concatenate([idx, j]),
                opt.noise_mm2[k], opt.max_sigma,
            )  # fmt: skip
            scales[bone] = float(np.cbrt(abs(np.linalg.det(T[:3, :3]))))
    return scales


def _bone_icp(ssm, v, lookup, inside, noise, max_sigma, iterations=10):
    """Per-bone closest-bone ICP with the SSM (the coarse level): its own pose and shape."""
    w = np.zeros(ssm.n_modes)
    for _ in range(iterations):
        ok = inside(v)
        if ok.sum() < 50:
            break
        d, target = lookup(v[ok])
        use = d <= np.quantile(d, 0.85)
        idx = np.flatnonzero(ok)[use]
        v, w, _ = _clamped_fit(ssm, target[use], idx, noise, max_sigma)
    return v, w


def _free_form(V, faces, level, surface, opt, inside, threshold):
    """Edge and uncovered-boundary displacements, smoothed over each mesh, ``rounds`` times.
    Vertices within ``joint_reach_mm`` of another bone search ``joint_search_mm`` (see
    :class:`ASMSettings`), the others ``free_form_search_mm``."""
    from scipy.spatial import cKDTree

    rings = [edge_adjacency(f, V.shape[1]) for f in faces]
    wide = max(opt.free_form_search_mm, opt.joint_search_mm)
    for _ in range(opt.free_form_rounds):
        normals = [vertex_normals(V[b], faces[b]) for b in range(3)]
        trees = [cKDTree(V[b]) for b in range(3)]
        nearest = _nearest_bones(trees, surface, wide)
        facing = _facing(normals, nearest, surface)
        for b in range(3):
            reach = _search_reach(V, trees, b, opt)
            found, off = _joint_edges(level, V[b], normals[b], reach, opt, inside, threshold)
            disp = np.where(found[:, None], off[:, None] * normals[b], 0.0)
            weight = found.astype(np.float64)
            j, pts = _data_pairs(b, facing, nearest, surface, reach > opt.free_form_search_mm)
            keep = np.linalg.norm(pts - V[b][j], axis=1) <= reach[j]
            np.add.at(disp, j[keep], pts[keep] - V[b][j[keep]])
            np.add.at(weight, j[keep], 1.0)
            disp = disp / np.maximum(weight, 1.0)[:, None]
            weight = np.minimum(weight, 1.0)
            ring, degree = rings[b]
            for _ in range(opt.free_form_smooth):
                disp = 0.5 * disp + 0.5 * (ring @ disp) / degree[:, None]
                weight = 0.5 * weight + 0.5 * (ring @ weight) / degree
            gain = np.minimum(weight, 1.0) / np.maximum(weight, 0.25)
            V[b] = V[b] + disp * gain[:, None]
    return V


def _search_reach(V: NDArray, trees, b: int, opt) -> NDArray[np.float64]:
    """Per vertex of bone ``b``: how far the free-form stage looks, ``joint_search_mm`` where
    another bone's mesh is within ``joint_reach_mm``, else ``free_form_search_mm``."""
    others = [trees[c].query(V[b], distance_upper_bound=opt.joint_reach_mm)[0]
              for c in range(len(V)) if c != b]  # fmt: skip
    at_joint = np.isfinite(np.min(others, axis=0))
    return np.where(at_joint, opt.joint_search_mm, opt.free_form_search_mm)


def _joint_edges(level, vertices, normals, reach, opt, inside, threshold):
    """:func:`_edges` with the search of ``reach`` (n,): ``joint_search_mm`` where it is wider
    than ``free_form_search_mm``, each vertex's profile sampled once."""
    found, off = np.zeros(len(vertices), dtype=bool), np.zeros(len(vertices))
    wide = reach > opt.free_form_search_mm
    for sel, search in ((~wide, opt.free_form_search_mm), (wide, opt.joint_search_mm)):
        if sel.any():
            found[sel], off[sel] = _edges(level, vertices[sel], normals[sel], search,
                                          opt.min_edge_hu, inside, threshold)  # fmt: skip
    return found, off


def _inside_mesh(vertices, faces, points) -> NDArray[np.bool_]:
    from pelvicnav.phantom.ctsynth import _winding_inside

    return _winding_inside(vertices, faces, points)


def separate_bones(vertices: NDArray, faces, *, margin_mm: float = 0.3, rounds: int = 4):
    """Push apart bones that overlap: vertices of one bone inside another move out, half the
    depth each side, displacements smoothed over the mesh. Returns ``(vertices, overlaps)``
    with the vertices left inside another bone per bone."""
    from scipy.spatial import cKDTree

    V = np.array(vertices, dtype=np.float64)
    rings = [edge_adjacency(f, V.shape[1]) for f in faces]
    for _ in range(rounds):
        normals = [vertex_normals(V[b], faces[b]) for b in range(3)]
        trees = [cKDTree(V[b]) for b in range(3)]
        disp = np.zeros_like(V)
        moved = False
        for a in range(3):
            for b in range(3):
                if a == b:
                    continue
                inside = _inside_mesh(V[b], faces[b], V[a])
                if not inside.any():
                    continue
                moved = True
                _, j = trees[b].query(V[a][inside])
                depth = np.einsum("ij,ij->i", V[b][j] - V[a][inside], normals[b][j])
                push = (np.maximum(depth, 0.0) * 0.5 + margin_mm)[:, None] * normals[b][j]
                disp[a][inside] += push
        if not moved:
            break
        for a in range(3):
            ring, degree = rings[a]
            d = disp[a]
            for _ in range(2):
                d = 0.5 * d + 0.5 * (ring @ d) / degree[:, None]
            V[a] += np.where(np.linalg.norm(d, axis=1, keepdims=True) > 0, d, 0.0)
            V[a] += disp[a] * 0.5
    overlaps = [
        int(sum(_inside_mesh(V[b], faces[b], V[a]).sum() for b in range(3) if b != a))
        for a in range(3)
    ]
    return V, overlaps


def rasterise_labels(
    hu: NDArray,
    world_from_ijk: NDArray,
    vertices: NDArray,
    faces,
    threshold: float,
    band: float,
    masked_value: float | None = None,
) -> NDArray[np.uint8]:
    """Label map of fitted meshes on the CT grid.

    A voxel inside a fitted surface (:func:`pelvicnav.shape.voxelize.inside_mask`) belongs to
    that bone; a bone voxel (CT number above ``threshold``) outside every surface but within
    ``band`` mm of one belongs to the nearest. Where surfaces overlap the first bone keeps it.
    On a masked CT (``masked_value`` given) only voxels other than the mask's constant are
    labelled, inside a surface or not.
    """
    from scipy.spatial import cKDTree

    from pelvicnav.shape.voxelize import inside_mask

    A = np.asarray(world_from_ijk, dtype=np.float64)
    spacing = np.linalg.norm(A[:3, :3], axis=0)
    box, lo = _box(vertices.reshape(-1, 3), A, hu.shape, band / spacing + 2)
    sub_shape = tuple(s.stop - s.start for s in box)
    B = A.copy()
    B[:3, 3] = A[:3, :3] @ lo + A[:3, 3]
    out = np.zeros(sub_shape, dtype=np.uint8)
    for b in range(3):
        out[inside_mask(vertices[b], faces[b], B, sub_shape) & (out == 0)] = b + 1
    sub = hu[box]
    bone = sub > threshold if masked_value is None else sub != masked_value
    if masked_value is not None:
        out[~bone] = 0
    where = np.argwhere((out == 0) & bone)
    if len(where) and band > 0:
        samples = [_surface_samples(vertices[b], faces[b]) for b in range(3)]
        owner = np.concatenate([np.full(len(x), b + 1, np.uint8) for b, x in enumerate(samples)])
        d, i = cKDTree(np.concatenate(samples)).query(
            tf.apply(B, where.astype(np.float64)), distance_upper_bound=band
        )
        near = np.isfinite(d)
        out[tuple(where[near].T)] = owner[i[near]]
    labels = np.zeros(hu.shape, dtype=np.uint8)
    labels[box] = out
    return labels


def _box(points, A, shape, pad_voxels):
    ijk = tf.apply(np.linalg.inv(A), points)
    lo = np.maximum(np.floor(ijk.min(axis=0) - pad_voxels).astype(int), 0)
    hi = np.minimum(np.ceil(ijk.max(axis=0) + pad_voxels).astype(int) + 1, shape)
    return tuple(slice(lo[d], hi[d]) for d in range(3)), lo


def _surface_samples(vertices, faces) -> NDArray[np.float64]:
    """Vertices, edge midpoints and face centroids of a mesh (about 1 mm apart on the atlas)."""
    f = np.asarray(faces)
    tri = vertices[f]
    mids = 0.5 * (tri + np.roll(tri, 1, axis=1))
    return np.concatenate([vertices, mids.reshape(-1, 3), tri.mean(axis=1)])


def segment_ct(
    hu: ArrayLike,
    world_from_ijk: ArrayLike,
    prior: ShapePrior,
    settings: ASMSettings | None = None,
    *,
    progress: Callable[[str], None] | None = None,
) -> ASMResult:
    """Segment the sacrum and both innominates of a CT with the multi-resolution ASM.

    Parameters
    ----------
    hu : (ni, nj, nk) float
        CT numbers (HU), patient axes LPS through ``world_from_ijk``.
    world_from_ijk : (4, 4) float
    prior : ShapePrior
    settings : ASMSettings, optional
    progress : callable(str), optional
        Told each stage as it starts.

    Returns
    -------
    ASMResult

    Raises
    ------
    ValueError
        A CT that is not 3D, holds no bone, or on which the model cannot be placed.
    """
    opt = settings or ASMSettings()
    say = progress or (lambda _: None)
    data = np.asarray(hu)
    if data.ndim != 3 or min(data.shape) < 8:
        raise ValueError(f"the CT must be a 3D volume, at least 8 voxels a side; got {data.shape}")
    A = np.asarray(world_from_ijk, dtype=np.float64)
    clock = {"start": time.perf_counter()}

    def lap(name: str) -> None:
        now = time.perf_counter()
        clock[name] = now - clock.pop("_last", clock["start"])
        clock["_last"] = now

    say("pyramid")
    threshold, masked = bone_threshold(data, opt.bone_hu)
    image, threshold_fit = _fit_image(data, threshold, masked)
    levels = _pyramid(image, A, opt.levels_mm)
    search = _pyramid(image, A, (opt.search_level_mm,))[0]
    lap("pyramid")
    say("initialisation")
    V, weights = _place(search, levels[0], prior, threshold_fit, opt)
    lap("initialisation")
    scales = {}
    for k, level in enumerate(levels):
        say(f"profile search at {level.spacing_mm:.1f} mm")
        inside = lambda p, level=level: _inside_grid(level, p, margin=2.0)  # noqa: E731
        surface = _bone_surface(level, threshold_fit, V.reshape(-1, 3), 2 * opt.search_mm[k])
        scales.update(_fit_level(prior, V, level, surface, k, opt, inside, weights, threshold_fit))
    lap("model")
    say("free-form refinement")
    inside = lambda p: _inside_grid(levels[-1], p, margin=2.0)  # noqa: E731
    V = _free_form(V, prior.faces, levels[-1], surface, opt, inside, threshold_fit)
    V, overlaps = separate_bones(V, prior.faces)
    lap("free_form")
    if opt.correspondence_rounds:
        say("correspondence")
        V = _correspond(V, prior, opt)
        lap("correspondence")
    say("label map")
    band = opt.label_band_mm if masked is None else opt.masked_reach_mm
    labels = rasterise_labels(data, A, V, prior.faces, threshold, band, masked)
    lap("labels")
    quality = _quality(V, prior, levels[-1], opt, weights, overlaps, scales, threshold_fit)
    clock.pop("_last", None)
    clock.pop("start")
    clock["total"] = float(sum(clock.values()))
    return ASMResult(vertices=V, weights=weights, labels=labels, quality=quality, seconds=clock)


def _correspond(V: NDArray, prior: ShapePrior, opt: ASMSettings) -> NDArray[np.float64]:
    """Each bone's vertices re-placed on its fitted surface by the model's point-to-plane MAP
    fit (the surface stays; the free-form stage's slides along it go)."""
    from pelvicnav.shape.correspond import refine_correspondence

    return np.stack([
        refine_correspondence(prior.shapes[bone], V[b], prior.faces[b],
                              noise_mm2=opt.correspondence_noise_mm2,
                              iterations=opt.correspondence_rounds, max_sigma=opt.max_sigma)
        for b, bone in enumerate(BONES)
    ])  # fmt: skip


def _fit_image(data: NDArray, threshold: float, masked: float | None):
    """The image the model is fitted to and its bone threshold. A masked CT tells the bones'
    boundary by its mask alone (inside, low-density bone can sit at the constant's level), so
    the mask itself is fitted to."""
    if masked is None:
        return data, threshold
    return np.where(data != masked, 1000.0, 0.0).astype(np.float32), 500.0


def _place(search: _Level, coarse: _Level, prior: ShapePrior, threshold: float, opt):
    """The mean pelvis placed (:func:`initial_pose`), each bone's translation searched, then each
    bone's similarity and SSM weights by closest-bone ICP on the coarse level."""
    world_from_ref, _ = initial_pose(search, coarse, prior.reference, prior.faces, threshold)
    V = _bone_search(search, tf.apply(world_from_ref, prior.reference), prior.faces, threshold)
    lookup = _closest_bone(coarse, threshold)
    weights = {}
    for b, bone in enumerate(BONES):
        ssm = prior.shapes[bone]
        start = tf.apply(fit_transform(ssm.mean, V[b], scale=True), ssm.mean)
        V[b], weights[bone] = _bone_icp(
            ssm, start, lookup, lambda p: _inside_grid(coarse, p), opt.noise_mm2[0], opt.max_sigma
        )
    return V, weights


def _quality(V, prior, fine, opt, weights, overlaps, scales, threshold) -> dict:
    out = {}
    for b, bone in enumerate(BONES):
        n = vertex_normals(V[b], prior.faces[b])
        found, off = _edges(
            fine, V[b], n, opt.search_mm[-1], opt.min_edge_hu, lambda p: _inside_grid(fine, p),
            threshold,
        )  # fmt: skip
        limit = opt.max_sigma * np.sqrt(prior.shapes[bone].variances)
        out[bone] = {
            "edge_rms_mm": float(np.sqrt(np.mean(off[found] ** 2))) if found.any() else np.inf,
            "edge_fraction": float(found.mean()),
            "overlap_vertices": int(overlaps[b]),
            "weights_at_limit": int(np.sum(np.abs(weights[bone]) >= limit - 1e-9)),
            "scale": scales.get(bone, 1.0),
        }
    return out
