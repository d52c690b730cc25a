"""Similarity and rigid transforms as float64 ``(..., 4, 4)`` matrices, with their Lie algebra.

Conventions (used everywhere in pelvicnav)
------------------------------------------
* A transform is a float64 homogeneous matrix ``T = [[s R, d], [0, 1]]`` acting on column
  vectors: ``p' = s R p + d``. Batches carry leading axes: ``(..., 4, 4)``.
* Transforms are named by the frames they map, and compose right to left:
  ``c_from_a = c_from_b @ b_from_a``.
* The tangent vector of Sim(3) is the 7-vector of Han et al. (2021), equation 3::

      b = [t_x, t_y, t_z, r_x, r_y, r_z, log s]

  with translation in mm, rotation in radians and ``log s`` dimensionless. ``exp`` is the *true*
  matrix exponential of ``sum_i b_i B_i`` (equation 4a), so the translation of ``exp(b)`` is
  ``V t`` (coupled through the V matrix below), not ``t`` itself. SE(3) is the ``log s = 0`` case
  and uses the 6-vector ``[t_x, t_y, t_z, r_x, r_y, r_z]``.
* A *decoupled* parameterisation, ``T = [[exp(log s) R(r), t], [0, 1]]``, is offered separately
  (:func:`from_params` / :func:`to_params`). It is what optimisers and the C-arm use, because
  there a parameter in mm must move the object by exactly that many mm. The statistical pose model
  uses the exact exponential map, where the geodesic distance of equation 5 is defined.

References
----------
R. Han et al., "Multi-body 3D-2D registration for image-guided reduction of pelvic dislocation in
orthopaedic trauma surgery", Phys. Med. Biol. 65 (2020) 135009. doi:10.1088/1361-6560/ab843c
E. Eade, "Lie groups for computer vision", section on Sim(3) (closed forms of V).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "apply",
    "distance",
    "euler_from_matrix",
    "from_params",
    "hat",
    "invert",
    "is_similarity",
    "matrix_from_euler",
    "matrix_from_rotvec",
    "rotvec_from_matrix",
    "scale_of",
    "se3_exp",
    "se3_log",
    "sim3_exp",
    "sim3_log",
    "skew",
    "to_params",
    "vee",
]

# Threshold below which the rotation-angle dependent coefficients switch to Taylor series.
# With the series truncated after theta**4 the remainder is below theta**6 / 5040 < 2e-16.
_SMALL_ANGLE = 1e-2
# Tolerance for accepting a matrix as a similarity (relative to its scale).
_DEFAULT_ATOL = 1e-6


def skew(v: ArrayLike) -> NDArray[np.float64]:
    """Cross-product matrix: ``skew(v) @ w == cross(v, w)``.

    Parameters
    ----------
    v : (..., 3) float

    Returns
    -------
    (..., 3, 3) float64
    """
    v = np.asarray(v, dtype=np.float64)
    _check_last(v, 3, "v")
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def hat(b: ArrayLike) -> NDArray[np.float64]:
    """Generator matrix ``sum_i b_i B_i`` of equation 4b.

    Parameters
    ----------
    b : (..., 7) or (..., 6) float
        Sim(3) (``[t, r, log s]``) or SE(3) (``[t, r]``) tangent vector.

    Returns
    -------
    (..., 4, 4) float64
    """
    b = np.asarray(b, dtype=np.float64)
    if b.ndim == 0 or b.shape[-1] not in (6, 7):
        raise ValueError(f"tangent vector must have shape (..., 6) or (..., 7), got {b.shape}")
    out = np.zeros((*b.shape[:-1], 4, 4))
    out[..., :3, :3] = skew(b[..., 3:6])
    if b.shape[-1] == 7:
        out[..., :3, :3] += b[..., 6, None, None] * np.eye(3)
    out[..., :3, 3] = b[..., :3]
    return out


def vee(X: ArrayLike) -> NDArray[np.float64]:
    """Inverse of :func:`hat` for Sim(3): ``(..., 4, 4) -> (..., 7)``.

    The skew part is read from the antisymmetric part of the upper-left block and ``log s`` from its
    trace, so ``vee(hat(b)) == b`` exactly.
    """
    X = np.asarray(X, dtype=np.float64)
    _check_matrix(X, "X")
    A = X[..., :3, :3]
    W = 0.5 * (A - np.swapaxes(A, -1, -2))
    lam = np.trace(A, axis1=-2, axis2=-1) / 3.0
    return np.concatenate(
        [X[..., :3, 3], np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], -1), lam[..., None]],
        axis=-1,
    )


def _moment(n: int, lam: NDArray[np.float64]) -> NDArray[np.float64]:
    """``m_n(lam) = int_0^1 s^n exp(lam s) ds``, accurate for all ``lam``."""
    lam = np.asarray(lam, dtype=np.float64)
    out = np.empty_like(lam)
    small = np.abs(lam) <= 7.0
    if np.any(small):
        x = lam[small]
        # Power series sum_j x^j / (j! (n + j + 1)); 70 terms reach 1e-17 for |x| <= 7.
        term = np.ones_like(x)
        acc = term / (n + 1)
        for j in range(1, 70):
            term = term * x / j
            acc = acc + term / (n + j + 1)
        out[small] = acc
    if np.any(~small):
        x = lam[~small]
        # Upward recurrence m_k = (e^x - k m_{k-1}) / x is stable for |x| > n.
        m = np.expm1(x) / x
        for k in range(1, n + 1):
            m = (np.exp(x) - k * m) / x
        out[~small] = m
    return out


def _v_coefficients(
    lam: NDArray[np.float64], theta: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Coefficients of ``V = a I + b W + c W^2`` with ``W = skew(omega)``, ``|omega| = theta``.

    ``V = int_0^1 exp(s (lam I + W)) ds`` couples the translation of the Sim(3) exponential:
    ``a = int e^{lam s}``, ``b = int e^{lam s} sin(theta s) / theta``,
    ``c = int e^{lam s} (1 - cos(theta s)) / theta^2`` (all over ``s`` in [0, 1]).
    """
    a = _moment(0, lam)
    b = np.empty_like(lam)
    c = np.empty_like(lam)
    small = theta < _SMALL_ANGLE
    if np.any(small):
        lt, t2 = lam[small], theta[small] ** 2
        # Taylor series in theta of sin(theta s)/theta and (1 - cos(theta s))/theta^2.
        b[small] = _moment(1, lt) - t2 * _moment(3, lt) / 6.0 + t2**2 * _moment(5, lt) / 120.0
        c[small] = _moment(2, lt) / 2.0 - t2 * _moment(4, lt) / 24.0 + t2**2 * _moment(6, lt) / 720
    big = ~small
    if np.any(big):
        lb, tb, ab = lam[big], theta[big], a[big]
        el, st, ct = np.exp(lb), np.sin(tb), np.cos(tb)
        den = lb**2 + tb**2
        int_sin = (el * (lb * st - tb * ct) + tb) / den
        int_cos = (el * (lb * ct + tb * st) - lb) / den
        b[big] = int_sin / tb
        c[big] = (ab - int_cos) / tb**2
    return a, b, c


def _rotation_coefficients(
    theta: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``sin(theta)/theta`` and ``(1 - cos(theta))/theta^2`` for Rodrigues' formula."""
    small = theta < _SMALL_ANGLE
    t2 = theta**2
    safe = np.where(small, 1.0, theta)
    A = np.where(small, 1 - t2 / 6 + t2**2 / 120, np.sin(safe) / safe)
    B = np.where(small, 0.5 - t2 / 24 + t2**2 / 720, (1 - np.cos(safe)) / safe**2)
    return A, B


def matrix_from_rotvec(rotvec: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix from a rotation vector (axis times angle, radians), by Rodrigues' formula.

    Parameters
    ----------
    rotvec : (..., 3) float, radians

    Returns
    -------
    (..., 3, 3) float64 rotation matrices.
    """
    rotvec = np.asarray(rotvec, dtype=np.float64)
    _check_last(rotvec, 3, "rotvec")
    _check_finite(rotvec, "rotvec")
    theta = np.linalg.norm(rotvec, axis=-1)
    A, B = _rotation_coefficients(theta)
    W = skew(rotvec)
    return np.eye(3) + A[..., None, None] * W + B[..., None, None] * (W @ W)


def rotvec_from_matrix(R: ArrayLike, *, atol: float = _DEFAULT_ATOL) -> NDArray[np.float64]:
    """Rotation vector (radians, angle in [0, pi]) of rotation matrices.

    Goes through a unit quaternion (Shepperd's method), which is accurate at every angle including
    0 and pi, where the usual ``arccos``-of-the-trace formula loses precision.

    Parameters
    ----------
    R : (..., 3, 3) float
        Proper rotation matrices; orthonormality is checked to ``atol``.

    Returns
    -------
    (..., 3) float64

    Raises
    ------
    ValueError
        If ``R`` is not finite, not orthonormal or has determinant -1.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape (..., 3, 3), got {R.shape}")
    _check_finite(R, "rotation matrix")
    _check_rotation(R, atol, "rotation matrix")
    q = _quaternion_from_matrix(R)  # (..., 4) as (w, x, y, z), w >= 0
    w, v = q[..., 0], q[..., 1:]
    norm_v = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(norm_v, w)
    # angle / |v| -> 2 / w as |v| -> 0; w >= 0 so this is well defined near the identity.
    factor = np.where(norm_v > 1e-12, angle / np.where(norm_v > 1e-12, norm_v, 1.0), 2.0 / w)
    return factor[..., None] * v


def _quaternion_from_matrix(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion (w, x, y, z), w >= 0, by Shepperd's largest-pivot method."""
    m = R
    tr = np.trace(m, axis1=-2, axis2=-1)
    diag = np.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    pivot = np.argmax(diag, axis=-1)
    q = np.empty((*R.shape[:-2], 4))
    # Largest of (w, x, y, z) first (the pivot), the others from off-diagonal sums/differences.
    for k in range(4):
        sel = pivot == k
        if not np.any(sel):
            continue
        r = m[sel]
        if k == 0:
            s = 2.0 * np.sqrt(np.maximum(1 + np.trace(r, axis1=-2, axis2=-1), 0.0))
            qk = np.stack(
                [
                    s / 4,
                    (r[:, 2, 1] - r[:, 1, 2]) / s,
                    (r[:, 0, 2] - r[:, 2, 0]) / s,
                    (r[:, 1, 0] - r[:, 0, 1]) / s,
                ],
                -1,
            )
        elif k == 1:
            s = 2.0 * np.sqrt(np.maximum(1 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2], 0.0))
            qk = np.stack(
                [
                    (r[:, 2, 1] - r[:, 1, 2]) / s,
                    s / 4,
                    (r[:, 0, 1] + r[:, 1, 0]) / s,
                    (r[:, 0, 2] + r[:, 2, 0]) / s,
                ],
                -1,
            )
        elif k == 2:
            s = 2.0 * np.sqrt(np.maximum(1 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2], 0.0))
            qk = np.stack(
                [
                    (r[:, 0, 2] - r[:, 2, 0]) / s,
                    (r[:, 0, 1] + r[:, 1, 0]) / s,
                    s / 4,
                    (r[:, 1, 2] + r[:, 2, 1]) / s,
                ],
                -1,
            )
        else:
            s = 2.0 * np.sqrt(np.maximum(1 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1], 0.0))
            qk = np.stack(
                [
                    (r[:, 1, 0] - r[:, 0, 1]) / s,
                    (r[:, 0, 2] + r[:, 2, 0]) / s,
                    (r[:, 1, 2] + r[:, 2, 1]) / s,
                    s / 4,
                ],
                -1,
            )
        q[sel] = qk
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def sim3_exp(b: ArrayLike) -> NDArray[np.float64]:
    """Exact Sim(3) exponential, equation 4a: ``exp(sum_i b_i B_i)``.

    Parameters
    ----------
    b : (..., 7) float
        ``[t_x, t_y, t_z (mm), r_x, r_y, r_z (rad), log s]``.

    Returns
    -------
    (..., 4, 4) float64
        ``[[s R, V t], [0, 1]]`` with ``R = exp(skew(r))``, ``s = e^{log s}`` and
        ``V = int_0^1 exp(u (log s I + skew(r))) du``.
    """
    b = np.asarray(b, dtype=np.float64)
    _check_last(b, 7, "Sim(3) tangent vector b")
    _check_finite(b, "Sim(3) tangent vector b")
    t, r, lam = b[..., :3], b[..., 3:6], b[..., 6]
    theta = np.linalg.norm(r, axis=-1)
    W = skew(r)
    W2 = W @ W
    A, B = _rotation_coefficients(theta)
    R = np.eye(3) + A[..., None, None] * W + B[..., None, None] * W2
    a, bb, c = _v_coefficients(lam, theta)
    V = a[..., None, None] * np.eye(3) + bb[..., None, None] * W + c[..., None, None] * W2
    out = np.zeros((*b.shape[:-1], 4, 4))
    out[..., :3, :3] = np.exp(lam)[..., None, None] * R
    out[..., :3, 3] = (V @ t[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def sim3_log(T: ArrayLike, *, atol: float = _DEFAULT_ATOL) -> NDArray[np.float64]:
    """Exact Sim(3) logarithm, the inverse of :func:`sim3_exp` (rotation angle in [0, pi]).

    Parameters
    ----------
    T : (..., 4, 4) float
        Similarity transforms ``[[s R, d], [0, 1]]``, ``s > 0``.
    atol : float
        Tolerance on ``R R^T = I`` and on the last row.

    Returns
    -------
    (..., 7) float64

    Raises
    ------
    ValueError
        If ``T`` has NaN/inf, a wrong shape, a last row other than ``[0, 0, 0, 1]``, a reflection or
        a non-similarity linear part (shear, anisotropic scale).
    """
    T = _as_similarity(T, atol, "T")
    M = T[..., :3, :3]
    s = np.cbrt(np.linalg.det(M))
    R = M / s[..., None, None]
    r = rotvec_from_matrix(R, atol=atol)
    lam = np.log(s)
    theta = np.linalg.norm(r, axis=-1)
    W = skew(r)
    a, bb, c = _v_coefficients(lam, theta)
    V = a[..., None, None] * np.eye(3) + bb[..., None, None] * W + c[..., None, None] * (W @ W)
    t = np.linalg.solve(V, T[..., :3, 3:4])[..., 0]
    return np.concatenate([t, r, lam[..., None]], axis=-1)


def se3_exp(xi: ArrayLike) -> NDArray[np.float64]:
    """Exact SE(3) exponential of ``xi = [t (mm), r (rad)]``, shape ``(..., 6) -> (..., 4, 4)``."""
    xi = np.asarray(xi, dtype=np.float64)
    _check_last(xi, 6, "SE(3) tangent vector xi")
    return sim3_exp(np.concatenate([xi, np.zeros((*xi.shape[:-1], 1))], axis=-1))


def se3_log(T: ArrayLike, *, atol: float = _DEFAULT_ATOL) -> NDArray[np.float64]:
    """Exact SE(3) logarithm ``(..., 4, 4) -> (..., 6)``.

    Raises
    ------
    ValueError
        If ``T`` is not a finite rigid transform (scale must be 1 within ``atol``).
    """
    T = _as_similarity(T, atol, "rigid transform T")
    s = np.cbrt(np.linalg.det(T[..., :3, :3]))
    bad = np.abs(s - 1.0) > atol
    if np.any(bad):
        idx = _first_index(bad)
        raise ValueError(
            f"rigid transform T{idx} is not rigid: its scale is {float(s[idx]):.9g}, expected 1"
        )
    return sim3_log(T, atol=atol)[..., :6]


def invert(T: ArrayLike, *, atol: float = _DEFAULT_ATOL) -> NDArray[np.float64]:
    """Inverse of similarity transforms in closed form: ``[[R^T/s, -R^T d/s], [0, 1]]``."""
    T = _as_similarity(T, atol, "T")
    M = T[..., :3, :3]
    s2 = np.cbrt(np.linalg.det(M)) ** 2
    Minv = np.swapaxes(M, -1, -2) / s2[..., None, None]
    out = np.zeros_like(T)
    out[..., :3, :3] = Minv
    out[..., :3, 3] = -(Minv @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def distance(T1: ArrayLike, T2: ArrayLike, *, weights: ArrayLike | None = None) -> NDArray:
    """Geodesic distance of equation 5: ``|| log(T1^{-1} T2) ||``.

    The plain norm mixes mm, radians and log-scale; ``weights`` (7,) scales each component first
    (e.g. ``[1, 1, 1, r, r, r, r]`` with ``r`` a characteristic radius in mm).

    Parameters
    ----------
    T1, T2 : (..., 4, 4) float, broadcastable similarity transforms.
    weights : (7,) float, optional

    Returns
    -------
    (...,) float64
    """
    b = sim3_log(invert(T1) @ np.asarray(T2, dtype=np.float64))
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (7,):
            raise ValueError(f"weights must have shape (7,), got {w.shape}")
        b = b * w
    return np.linalg.norm(b, axis=-1)


def apply(T: ArrayLike, points: ArrayLike) -> NDArray[np.float64]:
    """Apply transforms to points: ``(..., 4, 4)`` and ``(..., n, 3)`` -> ``(..., n, 3)`` (mm)."""
    T = np.asarray(T, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    _check_matrix(T, "T")
    _check_last(p, 3, "points")
    return p @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def scale_of(T: ArrayLike) -> NDArray[np.float64]:
    """Isotropic scale ``s`` of similarity transforms, ``(..., 4, 4) -> (...)``."""
    T = np.asarray(T, dtype=np.float64)
    _check_matrix(T, "T")
    return np.cbrt(np.linalg.det(T[..., :3, :3]))


def is_similarity(T: ArrayLike, *, atol: float = _DEFAULT_ATOL) -> NDArray[np.bool_]:
    """Whether each matrix is a finite, orientation-preserving similarity transform."""
    T = np.asarray(T, dtype=np.float64)
    _check_matrix(T, "T")
    return _similarity_mask(T, atol)


def from_params(
    translation: ArrayLike, rotvec: ArrayLike, log_scale: ArrayLike = 0.0
) -> NDArray[np.float64]:
    """Decoupled parameterisation ``[[e^{log_scale} R(rotvec), translation], [0, 1]]``.

    Unlike :func:`sim3_exp`, the translation is used as is (mm), which is what an optimiser or a
    C-arm parameter needs. ``to_params(from_params(t, r, l)) == (t, r, l)``.

    Parameters
    ----------
    translation : (..., 3) float, mm
    rotvec : (..., 3) float, radians
    log_scale : (...) float
    """
    t = np.asarray(translation, dtype=np.float64)
    r = np.asarray(rotvec, dtype=np.float64)
    _check_last(t, 3, "translation")
    _check_finite(t, "translation")
    ls = np.asarray(log_scale, dtype=np.float64)
    _check_finite(ls, "log_scale")
    shape = np.broadcast_shapes(t.shape[:-1], r.shape[:-1], ls.shape)
    out = np.zeros((*shape, 4, 4))
    out[..., :3, :3] = np.exp(ls)[..., None, None] * matrix_from_rotvec(r)
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def to_params(
    T: ArrayLike, *, atol: float = _DEFAULT_ATOL
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Inverse of :func:`from_params`.

    Returns
    -------
    translation : (..., 3) float64, mm
    rotvec : (..., 3) float64, radians
    log_scale : (...) float64
    """
    T = _as_similarity(T, atol, "T")
    s = np.cbrt(np.linalg.det(T[..., :3, :3]))
    r = rotvec_from_matrix(T[..., :3, :3] / s[..., None, None], atol=atol)
    return T[..., :3, 3].copy(), r, np.log(s)


def matrix_from_euler(seq: str, angles: ArrayLike, *, degrees: bool = False) -> NDArray:
    """Rotation matrices from Euler angles (scipy convention: upper case = intrinsic axes).

    Parameters
    ----------
    seq : str
        e.g. ``"ZXY"`` (intrinsic) or ``"zxy"`` (extrinsic), as in
        :meth:`scipy.spatial.transform.Rotation.from_euler`.
    angles : (..., 3) float
    degrees : bool

    Returns
    -------
    (..., 3, 3) float64
    """
    from scipy.spatial.transform import Rotation

    a = np.asarray(angles, dtype=np.float64)
    _check_last(a, len(seq), "angles")
    _check_finite(a, "angles")
    flat = a.reshape(-1, len(seq))
    R = Rotation.from_euler(seq, flat, degrees=degrees).as_matrix()
    return R.reshape(*a.shape[:-1], 3, 3)


def euler_from_matrix(seq: str, R: ArrayLike, *, degrees: bool = False) -> NDArray:
    """Euler angles ``(..., 3)`` of rotation matrices ``(..., 3, 3)``; inverse of
    :func:`matrix_from_euler` away from gimbal lock."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape (..., 3, 3), got {R.shape}")
    _check_finite(R, "rotation matrix")
    _check_rotation(R, _DEFAULT_ATOL, "rotation matrix")
    flat = R.reshape(-1, 3, 3)
    ang = Rotation.from_matrix(flat).as_euler(seq, degrees=degrees)
    return ang.reshape(*R.shape[:-2], 3)


# --------------------------------------------------------------------------------------------
# validation helpers


def _check_last(a: NDArray, n: int, name: str) -> None:
    if a.ndim == 0 or a.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}), got {a.shape}")


def _check_matrix(T: NDArray, name: str) -> None:
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4), got {T.shape}")


def _check_finite(a: NDArray, name: str) -> None:
    if not np.all(np.isfinite(a)):
        idx = _first_index(~np.isfinite(a))
        raise ValueError(f"{name} contains NaN or infinity (first at index {idx})")


def _first_index(mask: NDArray[np.bool_]) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(mask)[0])


def _check_rotation(R: NDArray, atol: float, name: str) -> None:
    err = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(axis=(-2, -1))
    if np.any(err > atol):
        idx = _first_index(err > atol)
        raise ValueError(f"{name}{idx or ''} is not orthonormal: max |R R^T - I| = {err[idx]:.3g}")
    det = np.linalg.det(R)
    if np.any(det < 0):
        idx = _first_index(det < 0)
        raise ValueError(f"{name}{idx or ''} is a reflection (determinant {det[idx]:.3g})")


def _similarity_mask(T: NDArray, atol: float) -> NDArray[np.bool_]:
    finite = np.all(np.isfinite(T), axis=(-2, -1))
    Tf = np.where(finite[..., None, None], T, np.eye(4))
    last_row = np.all(np.abs(Tf[..., 3, :] - np.array([0, 0, 0, 1.0])) <= atol, axis=-1)
    M = Tf[..., :3, :3]
    det = np.linalg.det(M)
    s = np.cbrt(det)
    pos = det > 0
    safe = np.where(pos, s, 1.0)
    R = M / safe[..., None, None]
    ortho = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(axis=(-2, -1)) <= atol
    return finite & last_row & pos & ortho


def _as_similarity(T: ArrayLike, atol: float, name: str) -> NDArray[np.float64]:
    """Validate similarity transforms and say exactly what is wrong with the first bad one."""
    T = np.asarray(T, dtype=np.float64)
    _check_matrix(T, name)
    _check_finite(T, name)
    ok = _similarity_mask(T, atol)
    if np.all(ok):
        return T
    idx = _first_index(~ok)
    bad = T[idx] if idx else T
    label = f"{name}{list(idx) if idx else ''}"
    if np.abs(bad[3] - [0, 0, 0, 1]).max() > atol:
        raise ValueError(
            f"{label} is not homogeneous: last row is {bad[3].tolist()}, not [0,0,0,1]"
        )
    det = np.linalg.det(bad[:3, :3])
    if det <= 0:
        raise ValueError(
            f"{label} is not a similarity transform: determinant {det:.3g} "
            "(a reflection or a singular matrix)"
        )
    R = bad[:3, :3] / np.cbrt(det)
    err = np.abs(R @ R.T - np.eye(3)).max()
    raise ValueError(
        f"{label} is not a similarity transform (shear or anisotropic scale): "
        f"max |R R^T - I| = {err:.3g} > {atol:g}"
    )
