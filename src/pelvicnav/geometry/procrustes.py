"""Least-squares alignment of corresponding point sets (Procrustes / Kabsch / Umeyama).

``fit_transform(source, target)`` returns the 4x4 transform ``T`` minimising
``sum_i w_i |T(source_i) - target_i|^2`` over rigid (``scale=False``) or similarity
(``scale=True``) transforms, always a proper rotation (no reflection).

Reference: S. Umeyama, "Least-squares estimation of transformation parameters between two point
patterns", IEEE TPAMI 13 (1991) 376-380, doi:10.1109/34.88573.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["fit_transform", "rms_distance"]


def fit_transform(
    source: ArrayLike,
    target: ArrayLike,
    *,
    scale: bool = False,
    weights: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Best rigid or similarity transform mapping ``source`` onto ``target``.

    Parameters
    ----------
    source, target : (..., n, 3) float, mm
        Corresponding points (batched over broadcastable leading axes).
    scale : bool
        Also fit an isotropic scale (similarity); otherwise rigid.
    weights : (n,) float, optional
        Non-negative weights per point.

    Returns
    -------
    (..., 4, 4) float64
        ``target_from_source``.

    Raises
    ------
    ValueError
        On mismatched shapes, fewer than 3 points, non-finite input or degenerate (collinear or
        coincident) source points.
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.ndim < 2 or dst.ndim < 2 or src.shape[-2:] != dst.shape[-2:] or src.shape[-1] != 3:
        raise ValueError(
            f"source and target must both have shape (..., n, 3); got {src.shape} and {dst.shape}"
        )
    try:
        src, dst = np.broadcast_arrays(src, dst)
    except ValueError:
        raise ValueError(
            f"source {src.shape} and target {dst.shape} batch shapes do not broadcast"
        ) from None
    n = src.shape[-2]
    if n < 3:
        raise ValueError(f"need at least 3 corresponding points, got {n}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise ValueError("source or target points contain NaN or infinity")
    if weights is None:
        w = np.full(n, 1.0 / n)
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (n,) or np.any(w < 0) or not np.all(np.isfinite(w)) or w.sum() <= 0:
            raise ValueError(f"weights must be {n} non-negative finite numbers, not all zero")
        w = w / w.sum()
    mu_s = np.einsum("n,...nj->...j", w, src)
    mu_d = np.einsum("n,...nj->...j", w, dst)
    xs = src - mu_s[..., None, :]
    xd = dst - mu_d[..., None, :]
    cov = np.einsum("n,...ni,...nj->...ij", w, xd, xs)  # (..., 3, 3) target x source
    var_s = np.einsum("n,...ni,...ni->...", w, xs, xs)
    if np.any(var_s <= 1e-20):
        raise ValueError("source points are coincident: no transform is defined")
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones((*cov.shape[:-2], 3))
    D[..., 2] = np.where(d == 0, 1.0, d)
    R = U @ (D[..., :, None] * Vt)
    if np.any(S[..., 1] <= 1e-12 * np.maximum(S[..., 0], 1e-300)):
        raise ValueError("source points are collinear: the rotation is not determined")
    s = np.sum(S * D, axis=-1) / var_s if scale else np.ones(var_s.shape)
    T = np.zeros((*cov.shape[:-2], 4, 4))
    T[..., :3, :3] = s[..., None, None] * R
    T[..., :3, 3] = mu_d - s[..., None] * (R @ mu_s[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def rms_distance(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Root-mean-square distance between corresponding points, ``(..., n, 3) -> (...)``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1), axis=-1))
