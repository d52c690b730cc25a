"""Voxels inside a closed triangle mesh, by signed ray crossings along the grid's k axis.

For each (i, j) column of voxel centres, every triangle the column passes through is a crossing
at some k, +1 where the surface's outward normal faces -k (the ray enters) and -1 where it faces
+k (the ray leaves). A voxel's winding number is the sum of the crossings below it; it is inside
where that is positive. On a closed mesh this is the exact winding number, so self-intersecting
patches (a deformed thin wall) still give a sensible answer, unlike parity. Columns are offset by
a tiny irrational amount so that no column meets an edge or vertex exactly.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["inside_mask"]

_OFFSET = (1e-4 * np.sqrt(2.0), 1e-4 * np.sqrt(3.0))


def _kernel():
    import numba

    @numba.njit(cache=True, nogil=True)
    def crossings(tri, ni, nj, nk, delta):  # pragma: no cover - compiled
        oi, oj = 1.4142135623730951e-4, 1.7320508075688772e-4
        for t in range(tri.shape[0]):
            a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
            lo_i = max(int(np.ceil(min(a[0], b[0], c[0]) - oi)), 0)
            hi_i = min(int(np.floor(max(a[0], b[0], c[0]) - oi)), ni - 1)
            lo_j = max(int(np.ceil(min(a[1], b[1], c[1]) - oj)), 0)
            hi_j = min(int(np.floor(max(a[1], b[1], c[1]) - oj)), nj - 1)
            # Signed area in (i, j): its sign is the normal's k component.
            area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
            if area == 0.0:
                continue
            sign = -1 if area > 0 else 1  # outward normal along +k: the ray leaves
            for i in range(lo_i, hi_i + 1):
                x = i + oi
                for j in range(lo_j, hi_j + 1):
                    y = j + oj
                    w0 = (b[0] - x) * (c[1] - y) - (b[1] - y) * (c[0] - x)
                    w1 = (c[0] - x) * (a[1] - y) - (c[1] - y) * (a[0] - x)
                    w2 = (a[0] - x) * (b[1] - y) - (a[1] - y) * (b[0] - x)
                    if (
                        (w0 >= 0) == (area > 0)
                        and (w1 >= 0) == (area > 0)
                        and (w2 >= 0) == (area > 0)
                    ):
                        z = (w0 * a[2] + w1 * b[2] + w2 * c[2]) / area
                        k = int(np.ceil(z))
                        if k < 0:
                            k = 0
                        if k <= nk:
                            delta[i, j, k] += sign

    return crossings


_CROSSINGS = None


def inside_mask(
    vertices: ArrayLike, faces: ArrayLike, world_from_ijk: ArrayLike, shape: tuple[int, int, int]
) -> NDArray[np.bool_]:
    """Voxels of a grid whose centres lie inside a closed, outward mesh.

    Parameters
    ----------
    vertices : (n, 3) float, mm (world)
    faces : (m, 3) int
        Closed and consistently oriented (outward normals).
    world_from_ijk : (4, 4) float
    shape : (ni, nj, nk)

    Returns
    -------
    (ni, nj, nk) bool
    """
    global _CROSSINGS
    if _CROSSINGS is None:
        _CROSSINGS = _kernel()
    A = np.asarray(world_from_ijk, dtype=np.float64)
    v = np.asarray(vertices, dtype=np.float64)
    ijk = (v - A[:3, 3]) @ np.linalg.inv(A[:3, :3]).T
    f = np.asarray(faces, dtype=np.int64)
    # A left-handed grid (det < 0) flips the orientation of every triangle.
    flip = np.linalg.det(A[:3, :3]) < 0
    tri = np.ascontiguousarray(ijk[f[:, ::-1] if flip else f])
    out = np.zeros(shape, dtype=bool)
    lo = np.maximum(np.floor(ijk.min(axis=0)).astype(int), 0)
    hi = np.minimum(np.ceil(ijk.max(axis=0)).astype(int) + 1, shape)
    if np.any(hi <= lo):
        return out
    tri -= lo
    sub = tuple(int(h - l) for h, l in zip(hi, lo, strict=True))
    delta = np.zeros((sub[0], sub[1], sub[2] + 1), dtype=np.int16)
    _CROSSINGS(tri, sub[0], sub[1], sub[2], delta)
    winding = np.cumsum(delta[:, :, : sub[2]], axis=2, dtype=np.int16)
    out[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = winding > 0
    return out
