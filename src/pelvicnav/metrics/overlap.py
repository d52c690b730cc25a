"""Segmentation agreement: Dice overlap of label maps and symmetric surface RMSD of meshes."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["dice", "surface_rmsd"]


def dice(a: ArrayLike, b: ArrayLike) -> float:
    """``2 |a & b| / (|a| + |b|)`` of two boolean masks (1.0 when both are empty)."""
    x, y = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    total = int(x.sum()) + int(y.sum())
    return 1.0 if total == 0 else float(2 * np.sum(x & y) / total)


def surface_rmsd(
    vertices_a: ArrayLike, faces_a: ArrayLike, vertices_b: ArrayLike, faces_b: ArrayLike
) -> float:
    """Symmetric RMS surface distance (mm): each mesh's vertices to the other's triangles
    (exact point-to-triangle distances, libigl), pooled."""
    import igl

    va, vb = (np.ascontiguousarray(v, dtype=np.float64) for v in (vertices_a, vertices_b))
    fa, fb = (np.ascontiguousarray(f, dtype=np.int64) for f in (faces_a, faces_b))
    d_ab = np.asarray(igl.point_mesh_squared_distance(va, vb, fb)[0])
    d_ba = np.asarray(igl.point_mesh_squared_distance(vb, va, fa)[0])
    return float(np.sqrt((d_ab.sum() + d_ba.sum()) / (len(d_ab) + len(d_ba))))
