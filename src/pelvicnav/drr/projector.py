"""Batched DRR forward projector: B candidate poses x K views x L bone volumes in one call.

``render`` computes, for every pose set ``b`` and view ``k``, the radiograph of line integrals

    DRR[b, k](u, v) = sum_l  integral  mu_l( ijk_from_world_l @ inv(T[b, l]) @ x ) dx

along the ray from view ``k``'s source through pixel ``(u, v)`` (exact perspective geometry from the
projection matrix ``P_k``), where ``T[b, l]`` is bone ``l``'s pose (``world_from_ct``) in candidate
``b``. Volumes are sampled trilinearly (zero outside) at a fixed step in mm (midpoint rule inside
each volume's clipped extent). The kernel is numba-parallel over ``(b, k, row)``.

Pixel convention: ``(u, v)`` = (column, row), pixel centres at integers (see
:mod:`pelvicnav.geometry.projection`). Units: ``mu`` in 1/mm gives dimensionless line integrals.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj

__all__ = ["ray_directions", "render"]


def ray_directions(P: ArrayLike, rows: int, cols: int) -> tuple[NDArray, NDArray]:
    """Source (3,) and unit ray directions ``(rows, cols, 3)`` through every pixel centre."""
    v, u = np.meshgrid(
        np.arange(rows, dtype=np.float64), np.arange(cols, dtype=np.float64), indexing="ij"
    )
    source, d = pj.backproject(P, np.stack([u, v], axis=-1))
    return source, d


def render(
    volumes: Sequence[Volume],
    poses: ArrayLike,
    projections: ArrayLike,
    shape: tuple[int, int],
    *,
    step_mm: float | None = None,
) -> NDArray[np.float32]:
    """Render DRRs for a batch of pose sets and views.

    Parameters
    ----------
    volumes : sequence of L Volume
        Bone models (attenuation per voxel, 1/mm), each in its CT frame.
    poses : (B, L, 4, 4) float
        ``world_from_ct`` of every bone in every candidate (identity = as in the CT).
    projections : (K, 3, 4) float
        One projection matrix per view (world mm -> pixels).
    shape : (rows, cols)
        Detector size of the views (the same for all views).
    step_mm : float, optional
        Sampling step along rays; default half the smallest voxel spacing.

    Returns
    -------
    (B, K, rows, cols) float32
        Sum over bones of the line integrals.

    Raises
    ------
    ValueError
        Shape mismatches, non-rigid-invertible poses, singular projection matrices.
    """
    if len(volumes) == 0:
        raise ValueError("at least one volume is needed")
    T = np.asarray(poses, dtype=np.float64)
    L = len(volumes)
    if T.ndim != 4 or T.shape[1:] != (L, 4, 4):
        raise ValueError(f"poses must have shape (B, {L}, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError("poses contain NaN or infinity")
    Ps = np.asarray(projections, dtype=np.float64)
    if Ps.ndim == 2:
        Ps = Ps[None]
    if Ps.ndim != 3 or Ps.shape[1:] != (3, 4):
        raise ValueError(f"projections must have shape (K, 3, 4), got {Ps.shape}")
    rows, cols = (int(shape[0]), int(shape[1]))
    if rows < 1 or cols < 1:
        raise ValueError(f"detector shape must be positive, got {shape}")
    spacing = min(float(v.spacing.min()) for v in volumes)
    h = 0.5 * spacing if step_mm is None else float(step_mm)
    if not h > 0:
        raise ValueError(f"step_mm must be positive, got {step_mm}")

    sources = np.empty((len(Ps), 3))
    dirs = np.empty((len(Ps), rows, cols, 3))
    for k, P in enumerate(Ps):
        sources[k], dirs[k] = ray_directions(P, rows, cols)
    # ijk_from_world of each bone in each candidate: ijk_from_ct @ inv(world_from_ct).
    ijk_from_ct = np.stack([v.ijk_from_world for v in volumes])  # CT frame = the volume's world
    try:
        ct_from_world = np.linalg.inv(T)
    except np.linalg.LinAlgError:
        raise ValueError("a pose is singular") from None
    M = ijk_from_ct[None] @ ct_from_world  # (B, L, 4, 4)
    flat = np.concatenate([v.data.reshape(-1) for v in volumes])
    offsets = np.cumsum([0] + [v.data.size for v in volumes[:-1]]).astype(np.int64)
    dims = np.array([v.shape for v in volumes], dtype=np.int64)
    out = np.zeros((T.shape[0], len(Ps), rows, cols), dtype=np.float32)
    _compile()(flat, offsets, dims, M, sources, dirs, h, out)
    return out


@functools.cache  # compile once per process, on first use
def _compile():  # pragma: no cover - compiled code
    import numba

    # The sampler is written out in the loop: numba does not cache a kernel that calls a jitted
    # closure (6 s of compiling in every process that renders).
    @numba.njit(parallel=True, fastmath=True, cache=True)
    def kernel(flat, offsets, dims, M, sources, dirs, h, out):
        B, K, R, C = out.shape
        L = dims.shape[0]
        for job in numba.prange(B * K * R):
            b = job // (K * R)
            k = (job // R) % K
            r = job % R
            sx, sy, sz = sources[k, 0], sources[k, 1], sources[k, 2]
            for c in range(C):
                dx, dy, dz = dirs[k, r, c, 0], dirs[k, r, c, 1], dirs[k, r, c, 2]
                total = 0.0
                for l in range(L):
                    m = M[b, l]
                    ox = m[0, 0] * sx + m[0, 1] * sy + m[0, 2] * sz + m[0, 3]
                    oy = m[1, 0] * sx + m[1, 1] * sy + m[1, 2] * sz + m[1, 3]
                    oz = m[2, 0] * sx + m[2, 1] * sy + m[2, 2] * sz + m[2, 3]
                    ex = m[0, 0] * dx + m[0, 1] * dy + m[0, 2] * dz
                    ey = m[1, 0] * dx + m[1, 1] * dy + m[1, 2] * dz
                    ez = m[2, 0] * dx + m[2, 1] * dy + m[2, 2] * dz
                    ni, nj, nk = dims[l, 0], dims[l, 1], dims[l, 2]
                    # Clip the ray to the support of the trilinear interpolant: [-1, n] per axis.
                    t0, t1 = 0.0, 1e30
                    ok = True
                    for o, e, n in ((ox, ex, ni), (oy, ey, nj), (oz, ez, nk)):
                        lo, hi = -1.0, float(n)
                        if abs(e) < 1e-12:
                            if o <= lo or o >= hi:
                                ok = False
                        else:
                            a = (lo - o) / e
                            bb = (hi - o) / e
                            if a > bb:
                                a, bb = bb, a
                            t0 = max(t0, a)
                            t1 = min(t1, bb)
                    if not ok or t1 <= t0:
                        continue
                    n_steps = int(np.ceil((t1 - t0) / h))
                    hh = (t1 - t0) / n_steps
                    acc = 0.0
                    off = offsets[l]
                    for s in range(n_steps):  # trilinear samples, written out (see above)
                        t = t0 + (s + 0.5) * hh
                        x, y, z = ox + t * ex, oy + t * ey, oz + t * ez
                        i0, j0, k0 = int(np.floor(x)), int(np.floor(y)), int(np.floor(z))
                        fx, fy, fz = x - i0, y - j0, z - k0
                        if 0 <= i0 < ni - 1 and 0 <= j0 < nj - 1 and 0 <= k0 < nk - 1:
                            # inside: all eight corners, no bounds to check (most samples)
                            b00 = off + (i0 * nj + j0) * nk + k0
                            b01 = b00 + nk
                            b10 = b00 + nj * nk
                            b11 = b10 + nk
                            c00 = flat[b00] + fz * (flat[b00 + 1] - flat[b00])
                            c01 = flat[b01] + fz * (flat[b01 + 1] - flat[b01])
                            c10 = flat[b10] + fz * (flat[b10 + 1] - flat[b10])
                            c11 = flat[b11] + fz * (flat[b11 + 1] - flat[b11])
                            c0 = c00 + fy * (c01 - c00)
                            c1 = c10 + fy * (c11 - c10)
                            acc += c0 + fx * (c1 - c0)
                            continue
                        for di in range(2):
                            ii = i0 + di
                            if ii < 0 or ii >= ni:
                                continue
                            wx = fx if di else 1.0 - fx
                            for dj in range(2):
                                jj = j0 + dj
                                if jj < 0 or jj >= nj:
                                    continue
                                wxy = wx * (fy if dj else 1.0 - fy)
                                base = off + (ii * nj + jj) * nk
                                for dk in range(2):
                                    kk = k0 + dk
                                    if kk < 0 or kk >= nk:
                                        continue
                                    acc += wxy * (fz if dk else 1.0 - fz) * flat[base + kk]
                    total += acc * hh
                out[b, k, r, c] = total

    return kernel
