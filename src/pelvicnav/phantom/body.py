"""A synthetic body around bones that came without one (the bone-masked real CTs).

The real CTs in ``shared/data/real-ct`` hold the bones' CT numbers and 0 everywhere else. To
segment or register them as if they were whole CTs, :func:`embed_in_body` fills the non-bone
voxels with an elliptic body like :func:`pelvicnav.phantom.ctsynth.synthesize_ct`'s: skin,
subcutaneous fat, muscle with noise, air outside. Femurs and spine stay absent.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["embed_in_body"]


def embed_in_body(
    hu: ArrayLike, labels: ArrayLike, world_from_ijk: ArrayLike, *, rng: np.random.Generator
) -> NDArray[np.float32]:
    """CT numbers with the voxels outside ``labels > 0`` replaced by a synthetic body.

    Parameters
    ----------
    hu : (ni, nj, nk) float
        Bone CT numbers (HU) where ``labels > 0``; anything elsewhere.
    labels : (ni, nj, nk) int
    world_from_ijk : (4, 4) float
        Axis-aligned grid (LPS); the body's cross-section is the same along k.
    rng : numpy.random.Generator

    Returns
    -------
    (ni, nj, nk) float32
    """
    data = np.asarray(hu, dtype=np.float32)
    bone = np.asarray(labels) > 0
    if not bone.any():
        raise ValueError("the label map holds no bone to build a body around")
    A = np.asarray(world_from_ijk, dtype=np.float64)
    where = np.argwhere(bone.any(axis=2))
    xy = (where @ A[:2, :2].T) + A[:2, 3]
    centre = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    half_width = 0.5 * np.ptp(xy[:, 0]) + rng.uniform(35, 60)
    half_depth = 0.5 * np.ptp(xy[:, 1]) + rng.uniform(45, 70)
    fat = rng.uniform(10, 30)
    i, j = np.meshgrid(np.arange(data.shape[0]), np.arange(data.shape[1]), indexing="ij")
    X = A[0, 0] * i + A[0, 1] * j + A[0, 3] - centre[0]
    Y = A[1, 0] * i + A[1, 1] * j + A[1, 3] - centre[1] + rng.uniform(-5, 5)
    rho = np.sqrt((X / half_width) ** 2 + (Y / half_depth) ** 2)
    depth = (1 - rho) * 0.5 * (half_width + half_depth)
    tissue = np.full(X.shape, -1000.0, dtype=np.float32)
    tissue[depth >= 0] = 30.0
    tissue[depth >= 2] = -100.0
    tissue[depth >= 2 + fat] = 50.0
    body = np.broadcast_to(tissue[:, :, None], data.shape).astype(np.float32)
    body += (depth >= 0)[:, :, None] * rng.normal(0, 8, data.shape).astype(np.float32)
    return np.where(bone, data, body).astype(np.float32)
