"""Joint surfaces and the collision refinement of SPM_CC (Han et al. 2020, section 2.1.2).

* Joint surfaces (sacroiliac: sacrum <-> each innominate; pubic symphysis: left <-> right
  innominate) are found once on the mean shapes: vertices of one bone whose nearest vertex on the
  other lies within ``max_distance`` and whose outward normal faces it. They are kept as vertex
  index sets, so they transfer to any subject through the vertex correspondence.
* The joint space is measured by casting rays from one surface's joint vertices along their outward
  normals against the opposing joint triangles (Moller-Trumbore): a positive distance is a gap, a
  negative one means the vertex lies inside the other bone (overlap).
* The refinement translates the moving bone along the joint normal by the smallest amount that
  restores a minimum joint space on every joint vertex.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.shape.mesh import vertex_normals

__all__ = [
    "JOINTS",
    "JointSurface",
    "as_gap_array",
    "find_joint_surfaces",
    "joint_gaps",
    "ray_triangle_distances",
    "refine_translation",
    "vertex_normals",  # re-exported from pelvicnav.shape.mesh
]

# (bone a, bone b) pairs that articulate, in canonical bone order.
JOINTS: tuple[tuple[str, str], ...] = (
    ("sacrum", "left_hip"),
    ("sacrum", "right_hip"),
    ("left_hip", "right_hip"),
)


def as_gap_array(gaps, n_subjects: int, n_vertices: int, name: str) -> NDArray[np.float64]:
    """Validate per-subject joint-gap arrays: ``(n_subjects, 3 joints, 2 sides, n_vertices)``."""
    g = np.asarray(gaps, dtype=np.float64)
    expected = (n_subjects, len(JOINTS), 2, n_vertices)
    if g.shape != expected:
        raise ValueError(f"{name} must have shape {expected}, got {g.shape}")
    return g


@dataclass(frozen=True)
class JointSurface:
    """Opposing joint surfaces of two bones, as vertex and triangle index sets.

    Attributes
    ----------
    bones : (str, str)
    vertices : (ndarray, ndarray)
        Joint vertex indices on each bone.
    faces : (ndarray, ndarray)
        Indices of the triangles (into each bone's face array) touching the joint vertices.
    """

    bones: tuple[str, str]
    vertices: tuple[NDArray[np.int64], NDArray[np.int64]]
    faces: tuple[NDArray[np.int64], NDArray[np.int64]]

    def side(self, bone: str) -> int:
        if bone not in self.bones:
            raise ValueError(f"{bone} is not part of the joint {self.bones}")
        return self.bones.index(bone)


def find_joint_surfaces(
    vertices: ArrayLike,
    faces: tuple[ArrayLike, ArrayLike, ArrayLike],
    *,
    max_distance: float = 8.0,
    bones: tuple[str, ...] = ("sacrum", "left_hip", "right_hip"),
) -> dict[tuple[str, str], JointSurface]:
    """Find the articulating surfaces on (mean) shapes placed in a common frame.

    Parameters
    ----------
    vertices : (3, n_vertices, 3) float, mm
        The three bones in one frame (e.g. the SPM's mean shapes at their mean poses).
    faces : three (m_l, 3) int arrays
    max_distance : float, mm
        A vertex belongs to a joint if the other bone has a vertex this close and the vertex's
        normal points towards it.

    Returns
    -------
    dict mapping each pair in :data:`JOINTS` to its :class:`JointSurface`.
    """
    from scipy.spatial import cKDTree

    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 3 or V.shape[0] != 3 or V.shape[2] != 3:
        raise ValueError(f"vertices must have shape (3, n_vertices, 3), got {V.shape}")
    normals = [vertex_normals(V[l], faces[l]) for l in range(3)]
    trees = [cKDTree(V[l]) for l in range(3)]
    out = {}
    for a, b in JOINTS:
        ia, ib = bones.index(a), bones.index(b)
        sets, face_sets = [], []
        for this, other in ((ia, ib), (ib, ia)):
            d, j = trees[other].query(V[this])
            facing = np.einsum("ij,ij->i", normals[this], V[other][j] - V[this]) > 0
            idx = np.flatnonzero((d <= max_distance) & facing)
            if len(idx) < 3:
                raise ValueError(
                    f"no joint surface between {a} and {b} within {max_distance} mm "
                    f"({len(idx)} vertices on {bones[this]}); are the bones in one frame?"
                )
            sets.append(idx.astype(np.int64))
            f = np.asarray(faces[this])
            face_sets.append(np.flatnonzero(np.isin(f, idx).any(axis=1)).astype(np.int64))
        out[(a, b)] = JointSurface(bones=(a, b), vertices=tuple(sets), faces=tuple(face_sets))
    return out


def ray_triangle_distances(
    origins: ArrayLike, directions: ArrayLike, triangles: ArrayLike
) -> NDArray[np.float64]:
    """Signed distance along each line to the nearest triangle it crosses (Moller-Trumbore).

    Parameters
    ----------
    origins, directions : (n, 3) float
        Lines ``o + t d`` with unit ``d``; both directions are searched.
    triangles : (m, 3, 3) float

    Returns
    -------
    (n,) float64
        ``t`` of the hit with the smallest ``|t|``; NaN where the line misses every triangle.
    """
    o = np.ascontiguousarray(origins, dtype=np.float64)
    d = np.ascontiguousarray(directions, dtype=np.float64)
    tri = np.ascontiguousarray(triangles, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins and directions must be (n, 3), got {o.shape} and {d.shape}")
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (m, 3, 3), got {tri.shape}")
    return _ray_kernel()(o, d, tri)


_KERNEL = None


def _ray_kernel():
    """Compile the Moller-Trumbore loop once (numba, cached on disk)."""
    global _KERNEL
    if _KERNEL is None:
        import numba

        @numba.njit(cache=True, nogil=True)
        def kernel(o, d, tri):  # pragma: no cover - compiled
            n, m = o.shape[0], tri.shape[0]
            out = np.full(n, np.nan)
            for i in range(n):
                best = np.inf
                for j in range(m):
                    e1x = tri[j, 1, 0] - tri[j, 0, 0]
                    e1y = tri[j, 1, 1] - tri[j, 0, 1]
                    e1z = tri[j, 1, 2] - tri[j, 0, 2]
                    e2x = tri[j, 2, 0] - tri[j, 0, 0]
                    e2y = tri[j, 2, 1] - tri[j, 0, 1]
                    e2z = tri[j, 2, 2] - tri[j, 0, 2]
                    px = d[i, 1] * e2z - d[i, 2] * e2y
                    py = d[i, 2] * e2x - d[i, 0] * e2z
                    pz = d[i, 0] * e2y - d[i, 1] * e2x
                    det = e1x * px + e1y * py + e1z * pz
                    if abs(det) < 1e-12:
                        continue
                    inv = 1.0 / det
                    tx = o[i, 0] - tri[j, 0, 0]
                    ty = o[i, 1] - tri[j, 0, 1]
                    tz = o[i, 2] - tri[j, 0, 2]
                    u = (tx * px + ty * py + tz * pz) * inv
                    if u < 0.0 or u > 1.0:
                        continue
                    qx = ty * e1z - tz * e1y
                    qy = tz * e1x - tx * e1z
                    qz = tx * e1y - ty * e1x
                    v = (d[i, 0] * qx + d[i, 1] * qy + d[i, 2] * qz) * inv
                    if v < 0.0 or u + v > 1.0:
                        continue
                    t = (e2x * qx + e2y * qy + e2z * qz) * inv
                    if abs(t) < best:
                        best = abs(t)
                        out[i] = t
            return out

        _KERNEL = kernel
    return _KERNEL


def joint_gaps(
    moving_vertices: ArrayLike,
    moving_faces: ArrayLike,
    moving_joint: ArrayLike,
    fixed_vertices: ArrayLike,
    fixed_faces: ArrayLike,
    fixed_joint_faces: ArrayLike,
) -> NDArray[np.float64]:
    """Joint space (mm) at each joint vertex of the moving bone, along its outward normal.

    Positive: gap to the opposing surface; negative: overlap depth; NaN: the ray misses it.
    """
    mv = np.asarray(moving_vertices, dtype=np.float64)
    normals = vertex_normals(mv, moving_faces)[moving_joint]
    fv = np.asarray(fixed_vertices, dtype=np.float64)
    tris = fv[np.asarray(fixed_faces)[fixed_joint_faces]]
    return ray_triangle_distances(mv[moving_joint], normals, tris)


def refine_translation(
    gaps_after: callable,
    direction: ArrayLike,
    *,
    min_gap: float,
    max_shift: float = 3.0,
    tol: float = 0.01,
    quantile: float = 0.05,
) -> float:
    """Smallest shift ``delta >= 0`` along ``direction`` that restores the joint space.

    Parameters
    ----------
    gaps_after : callable(shift (3,)) -> (k,) gaps
        Joint gaps after translating the moving bone by ``shift`` (mm).
    direction : (3,) float
        Unit direction that opens the joint (away from the opposing bone).
    min_gap : float, mm
        Required joint space.
    quantile : float
        The ``quantile``-th lowest gap must reach ``min_gap`` (robust to a few stray rays).
    max_shift : float, mm
        Largest correction considered. An overlap that this cannot clear is taken as the meshes'
        own interpenetration at the joint (segmented surfaces of the sacroiliac joint often
        overlap), not a pose error, and left alone.

    Returns
    -------
    float
        ``delta`` in mm (0 when the joint is already clear or cannot be cleared within
        ``max_shift``).
    """
    u = np.asarray(direction, dtype=np.float64)

    def clearance(delta: float) -> float:
        g = gaps_after(delta * u)
        g = g[np.isfinite(g)]
        return np.inf if len(g) == 0 else float(np.quantile(g, quantile))

    if clearance(0.0) >= min_gap:
        return 0.0
    lo, hi = 0.0, max_shift
    if clearance(hi) < min_gap:
        return 0.0
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if clearance(mid) >= min_gap:
            hi = mid
        else:
            lo = mid
    return hi


def subject_joint_gaps(
    vertices: ArrayLike,
    faces: tuple[ArrayLike, ArrayLike, ArrayLike],
    *,
    candidate_distance: float = 15.0,
    bones: tuple[str, ...] = ("sacrum", "left_hip", "right_hip"),
) -> NDArray[np.float64]:
    """Joint space at every vertex near a joint, for one subject (used to calibrate SPM_CC).

    For each joint in :data:`JOINTS` and each side, rays are cast from that bone's vertices that lie
    within ``candidate_distance`` of the other bone, along their outward normals, against the other
    bone's nearby triangles. Depends on this subject's meshes only, so it can be computed once per
    subject and reused across cross-validation folds without leaking anything.

    Parameters
    ----------
    vertices : (3, n_vertices, 3) float, mm
    faces : three (m_l, 3) int arrays

    Returns
    -------
    (3, 2, n_vertices) float64
        ``[joint, side, vertex]`` gap in mm (negative = overlap); NaN away from the joint or where
        the ray misses.
    """
    from scipy.spatial import cKDTree

    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 3 or V.shape[0] != 3 or V.shape[2] != 3:
        raise ValueError(f"vertices must have shape (3, n_vertices, 3), got {V.shape}")
    nv = V.shape[1]
    normals = [vertex_normals(V[l], faces[l]) for l in range(3)]
    trees = [cKDTree(V[l]) for l in range(3)]
    out = np.full((len(JOINTS), 2, nv), np.nan)
    for k, (a, b) in enumerate(JOINTS):
        ia, ib = bones.index(a), bones.index(b)
        for side, (this, other) in enumerate(((ia, ib), (ib, ia))):
            d_this, _ = trees[other].query(V[this], distance_upper_bound=candidate_distance)
            near = np.flatnonzero(np.isfinite(d_this))
            if len(near) == 0:
                continue
            d_other, _ = trees[this].query(V[other], distance_upper_bound=candidate_distance + 5.0)
            f = np.asarray(faces[other])
            near_other = np.isfinite(d_other)
            tri_idx = np.flatnonzero(near_other[f].any(axis=1))
            out[k, side, near] = ray_triangle_distances(
                V[this][near], normals[this][near], V[other][f[tri_idx]]
            )
    return out
