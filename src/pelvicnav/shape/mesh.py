"""Triangle-mesh utilities: normals, topology checks, hole closing and self-intersection tests.

Meshes are ``(vertices (n, 3) float mm, faces (m, 3) int)`` pairs; every function here keeps the
vertex array (and so the vertex correspondence of a shape model) untouched and only reads or
rewrites the triangles.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "boundary_edges",
    "close_mesh",
    "edge_adjacency",
    "edge_counts",
    "face_normals",
    "inpaint_vertices",
    "is_closed",
    "self_intersections",
    "signed_volume",
    "spike_vertices",
    "untangle",
    "vertex_normals",
]


def signed_volume(vertices: ArrayLike, faces: ArrayLike) -> float:
    """Enclosed volume (mm^3) by the divergence theorem; positive for outward-facing triangles."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.sum(np.einsum("ij,ij->i", a - v.mean(axis=0), np.cross(b - a, c - a))) / 6.0)


def face_normals(vertices: ArrayLike, faces: ArrayLike) -> NDArray[np.float64]:
    """Unit triangle normals, oriented outwards (positive enclosed volume); ``(m, 3)``."""
    fn = _area_normals(np.asarray(vertices, dtype=np.float64), np.asarray(faces))
    norm = np.linalg.norm(fn, axis=1, keepdims=True)
    return fn / np.maximum(norm, 1e-12)


def _area_normals(v: NDArray, f: NDArray) -> NDArray[np.float64]:
    """Triangle normals times twice their area, oriented outwards."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    fn = np.cross(b - a, c - a)
    # The sign of the volume is reliable even on meshes with small holes (the raw atlas meshes).
    return -fn if signed_volume(v, f) < 0 else fn


def vertex_normals(vertices: ArrayLike, faces: ArrayLike) -> NDArray[np.float64]:
    """Area-weighted unit vertex normals, oriented outwards (positive enclosed volume).

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int

    Returns
    -------
    (n, 3) float64
        Zero for vertices that no triangle uses.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    fn = _area_normals(v, f)
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


def _undirected(faces: NDArray) -> NDArray[np.int64]:
    f = np.asarray(faces, dtype=np.int64)
    return np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)


def edge_counts(faces: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Unique undirected edges ``(k, 2)`` and how many triangles share each ``(k,)``."""
    return np.unique(_undirected(np.asarray(faces)), axis=0, return_counts=True)


def boundary_edges(faces: ArrayLike) -> NDArray[np.int64]:
    """Directed edges ``(k, 2)`` that only one triangle has, in that triangle's orientation."""
    f = np.asarray(faces, dtype=np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edges, counts = edge_counts(f)
    single = {tuple(e) for e in edges[counts == 1]}
    return np.array([e for e in directed if (min(e), max(e)) in single], dtype=np.int64).reshape(
        -1, 2
    )


def is_closed(faces: ArrayLike) -> bool:
    """Every edge shared by exactly two triangles, traversed once in each direction."""
    f = np.asarray(faces, dtype=np.int64)
    _, counts = edge_counts(f)
    if not np.all(counts == 2):
        return False
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return len(np.unique(directed, axis=0)) == len(directed)


def _loops(edges: NDArray[np.int64]) -> list[list[int]]:
    """Split directed boundary edges into simple closed loops (vertex lists).

    Two holes that touch at a vertex give that vertex two outgoing boundary edges; the walk cuts
    a loop off whenever it comes back to a vertex already on its path.
    """
    from collections import defaultdict

    out: dict[int, list[int]] = defaultdict(list)
    for a, b in edges:
        out[int(a)].append(int(b))
    loops: list[list[int]] = []
    while any(out.values()):
        start = next(a for a, targets in out.items() if targets)
        path, where = [start], {start: 0}
        while path:
            v = path[-1]
            if not out[v]:
                raise ValueError(f"boundary at vertex {v} does not close into a loop")
            w = out[v].pop()
            if w in where:
                i = where[w]
                loops.append(path[i:])
                for u in path[i + 1 :]:
                    del where[u]
                path = path[: i + 1]
                if len(path) == 1 and not out[w]:
                    break
            else:
                where[w] = len(path)
                path.append(w)
    return loops


def _fill_loop(points: NDArray, loop: list[int]) -> list[tuple[int, int, int]]:
    """Minimum-area triangulation of a hole (dynamic programming over the loop).

    The loop runs the way the mesh's boundary edges do, so the new triangles go the other way
    round to keep the orientation consistent.
    """
    n = len(loop)
    p = points[loop]
    area = np.zeros((n, n))
    split = np.zeros((n, n), dtype=np.int64)
    for length in range(2, n):
        for i in range(n - length):
            j = i + length
            ks = np.arange(i + 1, j)
            tri = 0.5 * np.linalg.norm(np.cross(p[ks] - p[i], p[j] - p[i]), axis=1)
            cost = area[i, ks] + area[ks, j] + tri
            area[i, j], split[i, j] = cost.min(), ks[np.argmin(cost)]
    out, stack = [], [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i >= 2:
            k = int(split[i, j])
            out.append((loop[j], loop[k], loop[i]))
            stack += [(i, k), (k, j)]
    return out


def close_mesh(vertices: ArrayLike, faces: ArrayLike) -> NDArray[np.int64]:
    """Triangles of a closed, consistently outward-oriented version of a mesh.

    Repairs what the atlas's meshes need: flap triangles whose edges are shared by more than two
    triangles are removed, and every hole (boundary loop) is closed by a minimum-area
    triangulation of its own vertices. No vertex is added or moved; where the atlas's surface
    crosses itself near a hole, :func:`untangle` is the remedy.

    Parameters
    ----------
    vertices : (n, 3) float, mm
    faces : (m, 3) int

    Returns
    -------
    (m', 3) int64

    Raises
    ------
    ValueError
        The mesh cannot be closed this way (a boundary that is not a set of simple loops).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    edges, counts = edge_counts(f)
    crowded = {tuple(e) for e in edges[counts > 2]}
    if crowded:
        und = _undirected(f).reshape(3, -1, 2).transpose(1, 0, 2)
        n_crowded = np.array([sum((int(a), int(b)) in crowded for a, b in tri) for tri in und])
        f = f[n_crowded < 2]
    for loop in _loops(boundary_edges(f)):
        f = np.vstack([f, np.asarray(_fill_loop(v, loop), dtype=np.int64)])
    if not is_closed(f):
        raise ValueError("mesh could not be closed: non-manifold edges remain after repair")
    if signed_volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return f


def self_intersections(
    vertices: ArrayLike, faces: ArrayLike, *, tolerance: float = 1e-9
) -> NDArray[np.int64]:
    """Pairs of triangles that cross each other (pairs sharing a vertex are not tested).

    Candidates come from a k-d tree on the triangle centroids (within the sum of the two
    circumscribing radii); each is decided by the separating-axis test.

    Parameters
    ----------
    vertices : (n, 3) float, mm
    faces : (m, 3) int
    tolerance : float, mm
        Triangles closer than this without crossing count as touching, not intersecting.

    Returns
    -------
    (k, 2) int64
        Face index pairs ``i < j``; empty for a mesh without self-intersection.
    """
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = v[f]
    centre = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)
    # Pairs of ordinary triangles from one radius query; the few large ones (hole fills) each
    # query their own neighbourhood, so they do not inflate everybody's search radius.
    big = radius > np.quantile(radius, 0.99)
    tree = cKDTree(centre)
    small = tree.query_pairs(2.0 * float(radius[~big].max()), output_type="ndarray")
    pairs = [small]
    for i in np.flatnonzero(big):
        near = np.asarray(tree.query_ball_point(centre[i], radius[i] + radius.max()), dtype=int)
        near = near[~big[near] | (near > i)]  # a pair of two large triangles once
        pairs.append(np.column_stack([np.full(len(near), i), near]))
    pairs = np.concatenate(pairs).reshape(-1, 2).astype(np.int64)
    pairs = pairs[_candidate_kernel()(f, centre, radius, big, pairs, len(small))]
    hit = _tri_tri_kernel()(tri, pairs, tolerance)
    return np.sort(pairs[hit], axis=1)


def edge_adjacency(faces: ArrayLike, n: int):
    """Vertex adjacency over the mesh's edges: ``(sparse (n, n) 0/1 matrix, degree (n,))``.

    The degree is at least 1, so dividing by it is safe for unused vertices.
    """
    import scipy.sparse as sp

    edges, _ = edge_counts(np.asarray(faces))
    ring = sp.coo_matrix(
        (np.ones(2 * len(edges)), (edges.ravel(), edges[:, ::-1].ravel())), shape=(n, n)
    ).tocsr()
    return ring, np.maximum(np.asarray(ring.sum(axis=1)).ravel(), 1.0)


def spike_vertices(
    shapes: ArrayLike, faces: ArrayLike, *, ratio: float = 4.0, min_length: float = 10.0
) -> NDArray[np.bool_]:
    """Vertices that a population's correspondence placed far from their neighbours.

    An edge is stretched in one shape when it is longer than ``min_length`` mm and ``ratio`` times
    its median length over the population; both ends of a stretched edge are flagged.

    Parameters
    ----------
    shapes : (n_shapes, n_vertices, 3) float, mm
    faces : (m, 3) int

    Returns
    -------
    (n_shapes, n_vertices) bool
    """
    x = np.asarray(shapes, dtype=np.float64)
    edges, _ = edge_counts(np.asarray(faces))
    length = np.linalg.norm(x[:, edges[:, 0]] - x[:, edges[:, 1]], axis=2)
    stretched = (length > min_length) & (length > ratio * np.median(length, axis=0))
    out = np.zeros(x.shape[:2], dtype=bool)
    for s, k in zip(*np.nonzero(stretched), strict=True):
        out[s, edges[k]] = True
    return out


def inpaint_vertices(
    vertices: ArrayLike, faces: ArrayLike, missing: ArrayLike, reference: ArrayLike
) -> NDArray[np.float64]:
    """Re-place ``missing`` vertices so the surface there has the reference's local shape.

    Solves for the missing positions with the others fixed, so that every missing vertex keeps
    the reference's Laplacian coordinate (its offset from the mean of its neighbours).

    Parameters
    ----------
    vertices : (n, 3) float, mm
    faces : (m, 3) int
    missing : (n,) bool
    reference : (n, 3) float, mm
        A shape of the same topology in the same frame and scale (e.g. the population mean
        aligned onto this shape).

    Returns
    -------
    (n, 3) float64
    """
    from scipy.sparse import diags
    from scipy.sparse.linalg import spsolve

    v = np.array(vertices, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    miss = np.asarray(missing, dtype=bool)
    if not miss.any():
        return v
    ring, degree = edge_adjacency(faces, len(v))
    laplacian = (diags(np.ones(len(v))) - diags(1.0 / degree) @ ring).tocsr()
    delta = laplacian @ ref
    L_mm = laplacian[miss][:, miss].tocsc()
    L_mk = laplacian[miss][:, ~miss]
    rhs = delta[miss] - L_mk @ v[~miss]
    v[miss] = np.column_stack([spsolve(L_mm, rhs[:, k]) for k in range(3)])
    return v


def untangle(
    vertices: ArrayLike,
    faces: ArrayLike,
    *,
    max_iter: int = 60,
    patience: int = 15,
    schedule: tuple[tuple[float, float], ...] = ((0.9, 0.3), (0.5, 0.1)),
) -> tuple[NDArray[np.float64], int]:
    """Remove self-intersections by moving only the vertices of crossing triangles.

    Each round finds the crossing triangles (:func:`self_intersections`). Where the two triangles
    face away from each other, two sheets of a thin plate (the iliac wing, the sacral ala) have
    passed through each other: their vertices are pushed along their outward normals, which
    separates the sheets. Elsewhere the surface folds over itself: the vertices and one ring
    around them are Laplace-smoothed. Vertices elsewhere and the vertex order (the
    correspondence) are untouched.

    Parameters
    ----------
    vertices : (n, 3) float, mm
    faces : (m, 3) int
        A closed mesh (:func:`close_mesh`).
    max_iter : int
        Rounds per attempt.
    patience : int
        An attempt stops after this many rounds without fewer crossings than the best so far.
    schedule : sequence of (smoothing, inflation mm)
        Attempts, each from the input shape, until one leaves no crossing; smoothing is the step
        towards the neighbours' mean (0-1), inflation the push along the normal per round.

    Returns
    -------
    vertices : (n, 3) float64
        The attempt with the fewest crossings left.
    crossings : int
        Triangle pairs that still cross (0 when untangled).
    """
    x = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    ring, degree = edge_adjacency(f, len(x))
    best, best_left = x.copy(), len(self_intersections(x, f))
    for smoothing, inflation in schedule:
        if best_left == 0:
            break
        v, stalled = x.copy(), 0
        for _ in range(max_iter):
            pairs = self_intersections(v, f)
            stalled = 0 if len(pairs) < best_left else stalled + 1
            if len(pairs) < best_left:
                best, best_left = v.copy(), len(pairs)
            if len(pairs) == 0 or stalled > patience:
                break
            _untangle_step(v, f, pairs, ring, degree, smoothing, inflation)
        else:
            left = len(self_intersections(v, f))
            if left < best_left:
                best, best_left = v, left
    return best, best_left


def _untangle_step(v, f, pairs, ring, degree, smoothing: float, inflation: float) -> None:
    """One round of :func:`untangle`, in place."""
    n = len(v)
    tri = v[f]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face_n /= np.linalg.norm(face_n, axis=1, keepdims=True) + 1e-12
    opposed = np.einsum("ij,ij->i", face_n[pairs[:, 0]], face_n[pairs[:, 1]]) < 0.0
    sheets = np.zeros(n, dtype=bool)
    sheets[f[pairs[opposed]].ravel()] = True
    folds = np.zeros(n, dtype=bool)
    folds[f[pairs[~opposed]].ravel()] = True
    folds |= ring @ folds.astype(np.float64) > 0
    normals = vertex_normals(v, f)
    laplace = (ring @ v) / degree[:, None] - v
    v[folds] += smoothing * laplace[folds]
    v[sheets] += inflation * normals[sheets]


@functools.cache
def _candidate_kernel():
    """Which candidate pairs to test, in one pass (a numpy chain of masks took 40% of
    :func:`self_intersections`): two triangles, close enough for their circumscribing spheres to
    meet, sharing no vertex; of the first ``n_small`` (the radius query's), only pairs of two
    ordinary triangles."""
    import numba

    @numba.njit(cache=True, nogil=True)
    def kernel(f, centre, radius, big, pairs, n_small):  # pragma: no cover - compiled
        keep = np.zeros(len(pairs), dtype=np.bool_)
        for p in range(len(pairs)):
            i, j = pairs[p, 0], pairs[p, 1]
            if i == j or (p < n_small and (big[i] or big[j])):
                continue
            d2 = 0.0
            for a in range(3):
                d2 += (centre[i, a] - centre[j, a]) ** 2
            if d2 > (radius[i] + radius[j]) ** 2:
                continue
            shared = False
            for a in range(3):
                for b in range(3):
                    shared |= f[i, a] == f[j, b]
            keep[p] = not shared
        return keep

    return kernel


@functools.cache
def _tri_tri_kernel():
    """Separating-axis test over candidate pairs (one jitted function, so numba caches it)."""
    import numba

    @numba.njit(cache=True, nogil=True)
    def kernel(tri, pairs, tol):  # pragma: no cover - compiled
        out = np.zeros(len(pairs), dtype=np.bool_)
        axes = np.empty((17, 3))
        for p in range(len(pairs)):
            a, b = tri[pairs[p, 0]], tri[pairs[p, 1]]
            ea = np.empty((3, 3))
            eb = np.empty((3, 3))
            for k in range(3):
                ea[k] = a[(k + 1) % 3] - a[k]
                eb[k] = b[(k + 1) % 3] - b[k]
            na = np.cross(ea[0], ea[1])
            nb = np.cross(eb[0], eb[1])
            axes[0], axes[1] = na, nb
            for i in range(3):
                for j in range(3):
                    axes[2 + 3 * i + j] = np.cross(ea[i], eb[j])
                # Coplanar triangles: the in-plane edge normals separate them if anything does.
                axes[11 + i] = np.cross(na, ea[i])
                axes[14 + i] = np.cross(nb, eb[i])
            apart = False
            for k in range(17):
                norm = np.sqrt(axes[k, 0] ** 2 + axes[k, 1] ** 2 + axes[k, 2] ** 2)
                if norm < 1e-12:
                    continue
                amin, amax, bmin, bmax = np.inf, -np.inf, np.inf, -np.inf
                for q in range(3):
                    pa = (a[q, 0] * axes[k, 0] + a[q, 1] * axes[k, 1] + a[q, 2] * axes[k, 2]) / norm
                    pb = (b[q, 0] * axes[k, 0] + b[q, 1] * axes[k, 1] + b[q, 2] * axes[k, 2]) / norm
                    amin, amax = min(amin, pa), max(amax, pa)
                    bmin, bmax = min(bmin, pb), max(bmax, pb)
                if amax <= bmin + tol or bmax <= amin + tol:
                    apart = True
                    break
            out[p] = not apart
        return out

    return kernel
