"""An independent voxelisation for tests: ray parity along z through voxel-centre columns."""

from __future__ import annotations

import numpy as np


def parity_voxelize(vertices, faces, shape, world_from_ijk):
    """Inside mask of a closed(ish) mesh by counting z-ray crossings below each voxel centre."""
    A = np.asarray(world_from_ijk, dtype=np.float64)
    Ainv = np.linalg.inv(A)
    ijk = vertices @ Ainv[:3, :3].T + Ainv[:3, 3]  # axis-aligned grids only
    crossings: dict[tuple[int, int], list[float]] = {}
    tri = ijk[np.asarray(faces)]
    for t in tri:
        lo = np.ceil(t[:, :2].min(axis=0)).astype(int)
        hi = np.floor(t[:, :2].max(axis=0)).astype(int)
        if np.any(hi < lo):
            continue
        ii, jj = np.meshgrid(
            np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij"
        )
        p = np.stack([ii.ravel(), jj.ravel()], -1).astype(float)
        a, b, c = t[0, :2], t[1, :2], t[2, :2]
        det = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1])
        if abs(det) < 1e-12:
            continue
        w1 = ((p[:, 0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (p[:, 1] - a[1])) / det
        w2 = ((b[0] - a[0]) * (p[:, 1] - a[1]) - (p[:, 0] - a[0]) * (b[1] - a[1])) / det
        w0 = 1 - w1 - w2
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        zs = w0 * t[0, 2] + w1 * t[1, 2] + w2 * t[2, 2]
        for (i, j), z in zip(p[inside].astype(int), zs[inside], strict=True):
            crossings.setdefault((i, j), []).append(z)
    mask = np.zeros(shape, dtype=bool)
    k = np.arange(shape[2])
    for (i, j), zs in crossings.items():
        if not (0 <= i < shape[0] and 0 <= j < shape[1]):
            continue
        zs = np.sort(np.unique(np.round(zs, 9)))
        mask[i, j] = (np.searchsorted(zs, k) % 2) == 1
    return mask


def dice(a, b) -> float:
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    return float(2 * (a & b).sum() / max(a.sum() + b.sum(), 1))
