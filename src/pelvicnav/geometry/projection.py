"""The C-arm: projection matrices, their decomposition, and the 6- and 9-DoF parameterisations.

Conventions
-----------
* World frame: LPS millimetres (x to the patient's left, y posterior, z superior).
* A view's 3x4 projection matrix ``P`` maps homogeneous world points ``(x, y, z, 1)`` (mm) to
  homogeneous pixel coordinates ``(u, v, w)``: column ``u / w``, row ``v / w``, pixel centres at
  integers, ``(0, 0)`` the centre of the first pixel of the first row. Images are ``(rows, cols)``.
* ``P`` is normalised so that ``det(P[:, :3]) > 0`` and ``|P[2, :3]| = 1``; then ``w`` is the depth
  of the point along the central ray, in mm from the source.
* The C-arm frame ("carm"): origin at the x-ray source, x along increasing detector columns, y along
  increasing rows, z along the central ray from the source towards the detector (right-handed).
  ``P = K [R | t]`` with ``[R | t] = carm_from_world`` and ``K`` the intrinsics (focal lengths
  ``SDD / pixel spacing`` in pixels, principal point ``(u0, v0)`` where the central ray meets the
  detector).
* Gantry angles. At orbit = tilt = roll = 0 the view is AP: the source is anterior to the isocentre,
  the detector posterior, and the image is in the radiological display convention (patient's right
  on the image's left, head at the top). ``world_from_carm`` rotation is
  ``Rz(orbit) @ Rx(-tilt) @ R_ap @ Rz(roll)``: *orbit* rotates the gantry about the patient's long
  (superior) axis, +90 deg puts the source on the patient's left (lateral view); *tilt* moves the
  source cranially for positive angles (an inlet view has the beam angled caudally, tilt > 0; an
  outlet view tilt < 0); *roll* turns the detector about the central ray.
  (An under-table C-arm has the source posterior and flips its display to this same convention.)

The 9-DoF parameterisation follows equation 9 of Han et al. (2020): the source position relative to
the detector (``[s_x, s_y, s_z]``: ``s_z`` the source-detector distance, ``(s_x, s_y)`` the
principal point relative to the detector centre, mm, in detector axes) plus the detector's rigid
pose (3 translations, 3 rotations). The 6-DoF parameterisation keeps ``P`` fixed and moves the
object.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import transforms as tf

__all__ = [
    "CArm",
    "NineDof",
    "ProjectionDecomposition",
    "backproject",
    "decompose_projection",
    "depth",
    "magnification",
    "nine_dof_from_projection",
    "normalize_projection",
    "project",
    "projection_from_nine_dof",
    "six_dof_params",
    "six_dof_pose",
]

# world_from_carm rotation of the AP view; its columns are the C-arm axes in world (LPS):
# x (columns) -> patient's left, y (rows) -> inferior, z (beam) -> posterior.
R_AP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _rot_x(a: float) -> NDArray[np.float64]:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_z(a: float) -> NDArray[np.float64]:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _pixel_spacing(pixel_spacing: ArrayLike) -> tuple[float, float]:
    ps = np.asarray(pixel_spacing, dtype=np.float64).reshape(-1)
    if ps.shape == (1,):
        ps = np.repeat(ps, 2)
    if ps.shape != (2,) or not np.all(np.isfinite(ps)) or np.any(ps <= 0):
        raise ValueError(
            f"pixel spacing must be two positive numbers (row, column) in mm, got {pixel_spacing}"
        )
    return float(ps[0]), float(ps[1])


def _check_detector(rows: int, cols: int) -> None:
    if int(rows) != rows or int(cols) != cols or rows < 1 or cols < 1:
        raise ValueError(f"detector size must be positive integers, got rows={rows}, cols={cols}")


@dataclass(frozen=True)
class CArm:
    """An isocentric C-arm view.

    Parameters
    ----------
    source_to_detector : float, mm
        Source-to-detector distance (SDD), along the central ray.
    source_to_isocenter : float, mm
        Source-to-isocentre distance (SID); the isocentre lies on the central ray.
    rows, cols : int
        Detector size in pixels (an image is ``(rows, cols)``).
    pixel_spacing : (2,) float, mm
        ``(row spacing, column spacing)``.
    principal_point : (2,) float or None, pixels
        ``(u0, v0)`` = (column, row) where the central ray meets the detector; ``None`` for the
        detector centre ``((cols - 1) / 2, (rows - 1) / 2)``.
    orbit_deg, tilt_deg, roll_deg : float, degrees
        Gantry angles (see the module docstring).
    isocenter : (3,) float, mm
        World (LPS) position of the isocentre.

    The defaults are the mobile C-arm of the paper: SID 600 mm, SDD 1100 mm, ~300 x 300 mm detector.
    """

    source_to_detector: float = 1100.0
    source_to_isocenter: float = 600.0
    rows: int = 512
    cols: int = 512
    pixel_spacing: tuple[float, float] = (300.0 / 512, 300.0 / 512)
    principal_point: tuple[float, float] | None = None
    orbit_deg: float = 0.0
    tilt_deg: float = 0.0
    roll_deg: float = 0.0
    isocenter: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        sdd, sid = self.source_to_detector, self.source_to_isocenter
        if not (np.isfinite(sdd) and np.isfinite(sid) and 0 < sid < sdd):
            raise ValueError(
                "C-arm distances must satisfy 0 < source_to_isocenter < source_to_detector, "
                f"got SID={sid}, SDD={sdd}"
            )
        _check_detector(self.rows, self.cols)
        object.__setattr__(self, "pixel_spacing", _pixel_spacing(self.pixel_spacing))
        iso = np.asarray(self.isocenter, dtype=np.float64)
        if iso.shape != (3,) or not np.all(np.isfinite(iso)):
            raise ValueError(f"isocenter must be 3 finite numbers (mm), got {self.isocenter}")
        object.__setattr__(self, "isocenter", tuple(float(x) for x in iso))
        for name in ("orbit_deg", "tilt_deg", "roll_deg"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)}")
        if self.principal_point is not None:
            pp = np.asarray(self.principal_point, dtype=np.float64)
            if pp.shape != (2,) or not np.all(np.isfinite(pp)):
                raise ValueError(f"principal_point must be (u0, v0) pixels, got {pp}")
            object.__setattr__(self, "principal_point", (float(pp[0]), float(pp[1])))

    # ---- derived geometry -------------------------------------------------------------------
    @property
    def principal_point_px(self) -> tuple[float, float]:
        """``(u0, v0)`` in pixels."""
        if self.principal_point is not None:
            return self.principal_point
        return ((self.cols - 1) / 2.0, (self.rows - 1) / 2.0)

    @property
    def rotation(self) -> NDArray[np.float64]:
        """Rotation of ``world_from_carm``, (3, 3)."""
        o, t, r = np.deg2rad([self.orbit_deg, self.tilt_deg, self.roll_deg])
        return _rot_z(o) @ _rot_x(-t) @ R_AP @ _rot_z(r)

    @property
    def source(self) -> NDArray[np.float64]:
        """Source position in world mm, (3,)."""
        return np.asarray(self.isocenter) - self.source_to_isocenter * self.rotation[:, 2]

    @property
    def world_from_carm(self) -> NDArray[np.float64]:
        """Rigid (4, 4) transform from the C-arm frame (origin at the source) to world."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.source
        return T

    @property
    def intrinsics(self) -> NDArray[np.float64]:
        """(3, 3) ``K``: focal lengths ``SDD / spacing`` (pixels) and the principal point."""
        dr, dc = self.pixel_spacing
        u0, v0 = self.principal_point_px
        f = self.source_to_detector
        return np.array([[f / dc, 0.0, u0], [0.0, f / dr, v0], [0.0, 0.0, 1.0]])

    @property
    def projection_matrix(self) -> NDArray[np.float64]:
        """(3, 4) ``P = K [R | t]`` mapping world mm to pixels (normalised, see module doc)."""
        carm_from_world = tf.invert(self.world_from_carm)
        return self.intrinsics @ carm_from_world[:3, :]

    @property
    def magnification_at_isocenter(self) -> float:
        """``SDD / SID``."""
        return self.source_to_detector / self.source_to_isocenter

    @property
    def detector_center(self) -> NDArray[np.float64]:
        """World position (mm) of the centre of the pixel array, (3,)."""
        return self.nine_dof().world_from_detector[:3, 3]

    def nine_dof(self) -> NineDof:
        """This view in the 9-DoF parameterisation of equation 9."""
        dr, dc = self.pixel_spacing
        u0, v0 = self.principal_point_px
        sx = (u0 - (self.cols - 1) / 2.0) * dc
        sy = (v0 - (self.rows - 1) / 2.0) * dr
        sz = self.source_to_detector
        R = self.rotation
        world_from_detector = np.eye(4)
        world_from_detector[:3, :3] = R
        # The detector centre is the source, plus SDD along the beam, minus the source offset.
        world_from_detector[:3, 3] = self.source + R @ np.array([-sx, -sy, sz])
        return NineDof(source_in_detector=(sx, sy, sz), world_from_detector=world_from_detector)

    def magnification(self, points: ArrayLike) -> NDArray[np.float64]:
        """Magnification ``SDD / depth`` of points (mm), ``(..., 3) -> (...)``."""
        return magnification(self.projection_matrix, points, pixel_spacing=self.pixel_spacing)

    @classmethod
    def from_projection_matrix(
        cls,
        P: ArrayLike,
        *,
        rows: int,
        cols: int,
        pixel_spacing: ArrayLike,
        source_to_isocenter: float,
        atol: float = 1e-6,
    ) -> CArm:
        """Recover the C-arm parameters from a projection matrix.

        ``P`` fixes the source, the detector orientation and the intrinsics; the detector size,
        pixel spacing and the source-isocentre distance are not in ``P`` and must be given.

        Raises
        ------
        ValueError
            If ``P`` is singular, has skew, or non-square pixels disagree with ``pixel_spacing``.
        """
        dr, dc = _pixel_spacing(pixel_spacing)
        dec = decompose_projection(P)
        K = dec.intrinsics
        if abs(K[0, 1]) > atol * K[0, 0]:
            raise ValueError(f"projection matrix has skew {K[0, 1]:.3g}: not a C-arm detector")
        sdd_u, sdd_v = K[0, 0] * dc, K[1, 1] * dr
        if abs(sdd_u - sdd_v) > 1e-6 * max(sdd_u, 1.0) + atol:
            raise ValueError(
                f"focal lengths give different SDDs along columns ({sdd_u:.6g} mm) and rows "
                f"({sdd_v:.6g} mm) for pixel spacing ({dr}, {dc}): wrong pixel spacing?"
            )
        R = dec.carm_from_world.T  # world_from_carm rotation
        ang = tf.euler_from_matrix("ZXY", R @ R_AP.T, degrees=True)
        orbit, tilt, roll = float(ang[0]), float(-ang[1]), float(ang[2])
        iso = dec.source + source_to_isocenter * R[:, 2]
        return cls(
            source_to_detector=float(sdd_u),
            source_to_isocenter=float(source_to_isocenter),
            rows=rows,
            cols=cols,
            pixel_spacing=(dr, dc),
            principal_point=(float(K[0, 2]), float(K[1, 2])),
            orbit_deg=orbit,
            tilt_deg=tilt,
            roll_deg=roll,
            isocenter=tuple(iso),
        )


@dataclass(frozen=True)
class ProjectionDecomposition:
    """``P ~ K [R | -R C]``.

    Attributes
    ----------
    intrinsics : (3, 3) float64
        Upper triangular ``K`` with positive diagonal and ``K[2, 2] = 1`` (pixels).
    carm_from_world : (3, 3) float64
        Rotation ``R`` (world to C-arm axes).
    source : (3,) float64
        Source (camera centre) ``C`` in world mm.
    """

    intrinsics: NDArray[np.float64]
    carm_from_world: NDArray[np.float64]
    source: NDArray[np.float64]


def _check_projection(P: ArrayLike) -> NDArray[np.float64]:
    P = np.asarray(P, dtype=np.float64)
    if P.shape != (3, 4):
        raise ValueError(f"projection matrix must have shape (3, 4), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError("projection matrix contains NaN or infinity")
    M = P[:, :3]
    sv = np.linalg.svd(M, compute_uv=False)
    if sv[-1] <= 1e-12 * max(sv[0], 1e-300):
        raise ValueError(
            "projection matrix is singular: its left 3x3 block has rank < 3 "
            f"(singular values {np.array2string(sv, precision=3)}), so it has no source position"
        )
    return P


def normalize_projection(P: ArrayLike) -> NDArray[np.float64]:
    """Scale ``P`` so that ``det(P[:, :3]) > 0`` and ``|P[2, :3]| = 1`` (``w`` = depth in mm)."""
    P = _check_projection(P)
    scale = np.linalg.norm(P[2, :3])
    if np.linalg.det(P[:, :3]) < 0:
        scale = -scale
    return P / scale


def normalize_projections(Ps: ArrayLike) -> NDArray[np.float64]:
    """:func:`normalize_projection` of each matrix of a stack ``(N, 3, 4)``, vectorised.

    The batch is checked at once (finite, ``|det| > 1e-12 |M|^3``); a stack that fails is
    checked matrix by matrix, so the error (or the result) is exactly the one-matrix function's.
    """
    P = np.asarray(Ps, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (3, 4):
        raise ValueError(f"projection matrices must have shape (N, 3, 4), got {P.shape}")
    M = P[:, :, :3]
    with np.errstate(invalid="ignore"):  # a NaN matrix is reported below
        det = np.linalg.det(M)
    size = np.sqrt(np.einsum("nij,nij->n", M, M))
    clear = np.isfinite(P).all(axis=(1, 2)) & (np.abs(det) > 1e-12 * size**3)
    if not clear.all():
        return np.stack([normalize_projection(p) for p in P])
    scale = np.linalg.norm(M[:, 2], axis=1) * np.sign(det)
    return P / scale[:, None, None]


def intrinsics_of(Ps: ArrayLike) -> NDArray[np.float64]:
    """Intrinsics ``K`` (``K[2, 2] = 1``, positive diagonal) of projections ``(..., 3, 4)``.

    The closed form of :func:`decompose_projection`'s RQ decomposition (Gram-Schmidt from the
    last row of ``M = K R``), vectorised: for many matrices (a 9-DoF search renders every
    candidate through its own geometry) it is ~1000x faster than one RQ each.

    Returns
    -------
    (..., 3, 3) float64
    """
    P = np.asarray(Ps, dtype=np.float64)
    if P.shape[-2:] != (3, 4):
        raise ValueError(f"projection matrices must have shape (..., 3, 4), got {P.shape}")
    return normalized_with_intrinsics(P.reshape(-1, 3, 4))[1].reshape(*P.shape[:-2], 3, 3)


def normalized_with_intrinsics(Ps: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`normalize_projections` of ``(N, 3, 4)`` and their :func:`intrinsics_of`
    ``(N, 3, 3)``, normalising once."""
    P = normalize_projections(Ps)
    m1, m2, r3 = P[:, 0, :3], P[:, 1, :3], P[:, 2, :3]  # |r3| = 1 after normalisation
    cy = np.einsum("ni,ni->n", m2, r3)
    q2 = m2 - cy[:, None] * r3
    fy = np.linalg.norm(q2, axis=1)
    r2 = q2 / fy[:, None]
    cx = np.einsum("ni,ni->n", m1, r3)
    skew = np.einsum("ni,ni->n", m1, r2)
    fx = np.linalg.norm(m1 - skew[:, None] * r2 - cx[:, None] * r3, axis=1)
    K = np.zeros((len(P), 3, 3))
    K[:, 0] = np.stack([fx, skew, cx], axis=1)
    K[:, 1, 1:] = np.stack([fy, cy], axis=1)
    K[:, 2, 2] = 1.0
    return P, K


def decompose_projection(P: ArrayLike) -> ProjectionDecomposition:
    """RQ-decompose a projection matrix into intrinsics, rotation and source position.

    Raises
    ------
    ValueError
        If ``P`` is not (3, 4), not finite, or singular.
    """
    from scipy.linalg import rq

    P = normalize_projection(P)
    M = P[:, :3]
    K, R = rq(M)
    # Make the diagonal of K positive; R picks up the same signs (det stays +1 since det M > 0).
    signs = np.sign(np.diag(K))
    K = K * signs[None, :]
    R = signs[:, None] * R
    K = K / K[2, 2]
    source = -np.linalg.solve(M, P[:, 3])
    return ProjectionDecomposition(intrinsics=K, carm_from_world=R, source=source)


def project(P: ArrayLike, points: ArrayLike) -> NDArray[np.float64]:
    """Project world points (mm) to pixel coordinates ``(u, v)`` = (column, row).

    Parameters
    ----------
    P : (3, 4) float
    points : (..., 3) float, mm

    Returns
    -------
    (..., 2) float64
        Pixel coordinates; NaN for points at or behind the source plane.
    """
    P = normalize_projection(P)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 0 or p.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3), got {p.shape}")
    h = p @ P[:, :3].T + P[:, 3]
    w = h[..., 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.where(w > 0, h[..., :2] / w, np.nan)
    return uv


def depth(P: ArrayLike, points: ArrayLike) -> NDArray[np.float64]:
    """Depth of points along the central ray (mm from the source plane), ``(..., 3) -> (...)``."""
    P = normalize_projection(P)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 0 or p.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3), got {p.shape}")
    return p @ P[2, :3] + P[2, 3]


def backproject(P: ArrayLike, pixels: ArrayLike) -> tuple[NDArray[np.float64], NDArray]:
    """Rays from the source through pixel positions.

    Parameters
    ----------
    P : (3, 4) float
    pixels : (..., 2) float, ``(u, v)`` = (column, row)

    Returns
    -------
    source : (3,) float64, mm
    directions : (..., 3) float64
        Unit vectors from the source towards the detector through each pixel.
    """
    P = normalize_projection(P)
    px = np.asarray(pixels, dtype=np.float64)
    if px.ndim == 0 or px.shape[-1] != 2:
        raise ValueError(f"pixels must have shape (..., 2), got {px.shape}")
    M = P[:, :3]
    source = -np.linalg.solve(M, P[:, 3])
    h = np.concatenate([px, np.ones((*px.shape[:-1], 1))], axis=-1)
    d = h @ np.linalg.inv(M).T
    # w = m3 . d must be positive for a ray travelling towards the detector.
    d = np.where((d @ M[2])[..., None] < 0, -d, d)
    return source, d / np.linalg.norm(d, axis=-1, keepdims=True)


def magnification(P: ArrayLike, points: ArrayLike, *, pixel_spacing: ArrayLike) -> NDArray:
    """Geometric magnification ``SDD / depth`` at world points.

    For a point on the central ray this is SDD / (source-to-point distance). The SDD is read from
    ``P`` (column focal length times column pixel spacing).
    """
    _, dc = _pixel_spacing(pixel_spacing)
    K = decompose_projection(P).intrinsics
    return K[0, 0] * dc / depth(P, points)


# ---------------------------------------------------------------------------------------------
# 9-DoF (equation 9) and 6-DoF parameterisations


@dataclass(frozen=True)
class NineDof:
    """System geometry in the 9-DoF form of equation 9.

    Attributes
    ----------
    source_in_detector : (3,) float, mm
        Source position in detector axes relative to the detector centre, sign-flipped along z:
        ``(s_x, s_y, s_z)`` with the source at ``(s_x, s_y, -s_z)``; ``s_z`` is the SDD and
        ``(s_x, s_y)`` the principal point offset from the detector centre.
    world_from_detector : (4, 4) float
        Rigid pose of the detector: origin at the centre of the pixel array, x along columns,
        y along rows, z away from the source.
    """

    source_in_detector: tuple[float, float, float]
    world_from_detector: NDArray[np.float64]

    def __post_init__(self) -> None:
        s = np.asarray(self.source_in_detector, dtype=np.float64)
        if s.shape != (3,) or not np.all(np.isfinite(s)) or s[2] <= 0:
            raise ValueError(
                f"source_in_detector must be 3 finite numbers with s_z > 0 (mm), got {s.tolist()}"
            )
        T = np.asarray(self.world_from_detector, dtype=np.float64)
        tf.se3_log(T)  # validates: finite, rigid
        object.__setattr__(self, "source_in_detector", tuple(float(x) for x in s))
        object.__setattr__(self, "world_from_detector", T)

    def vector(self) -> NDArray[np.float64]:
        """``[s_x, s_y, s_z, t_x, t_y, t_z, r_x, r_y, r_z]`` (mm, mm, rad): detector pose decoupled,
        translation in world mm, rotation vector in radians."""
        t, r, _ = tf.to_params(self.world_from_detector)
        return np.concatenate([self.source_in_detector, t, r])

    @classmethod
    def from_vector(cls, v: ArrayLike) -> NineDof:
        v = np.asarray(v, dtype=np.float64)
        if v.shape != (9,):
            raise ValueError(f"a 9-DoF vector has shape (9,), got {v.shape}")
        return cls(
            source_in_detector=tuple(v[:3]), world_from_detector=tf.from_params(v[3:6], v[6:9])
        )


def projection_from_nine_dof(
    geometry: NineDof, *, rows: int, cols: int, pixel_spacing: ArrayLike
) -> NDArray[np.float64]:
    """Equation 9: ``P = A K(T_s) [I | -s] detector_from_world`` (normalised).

    ``K(T_s) = [[s_z, 0, s_x], [0, s_z, s_y], [0, 0, 1]]`` projects onto the detector in mm relative
    to its centre; ``A`` converts mm to pixels (spacing and the centre pixel).
    """
    return projections_from_sources(
        np.asarray(geometry.source_in_detector)[None], geometry.world_from_detector,
        rows=rows, cols=cols, pixel_spacing=pixel_spacing,
    )[0]  # fmt: skip


def projections_from_sources(
    sources: ArrayLike, world_from_detector: ArrayLike, *, rows: int, cols: int,
    pixel_spacing: ArrayLike,
) -> NDArray[np.float64]:  # fmt: skip
    """:func:`projection_from_nine_dof` for N source positions of one detector pose, vectorised.

    Parameters
    ----------
    sources : (N, 3) float, mm
        ``source_in_detector`` of each geometry (``s_z > 0``).
    world_from_detector : (4, 4) float
        The detector's rigid pose, shared.

    Returns
    -------
    (N, 3, 4) float64
        Normalised projection matrices.
    """
    _check_detector(rows, cols)
    dr, dc = _pixel_spacing(pixel_spacing)
    s = np.asarray(sources, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3 or not np.all(np.isfinite(s)) or np.any(s[:, 2] <= 0):
        raise ValueError("source positions must be (N, 3) finite numbers with s_z > 0 (mm)")
    T = np.asarray(world_from_detector, dtype=np.float64)
    tf.se3_log(T)  # validates: finite, rigid
    K = np.zeros((len(s), 3, 3))
    K[:, 0, 0] = K[:, 1, 1] = s[:, 2]
    K[:, :2, 2] = s[:, :2]
    K[:, 2, 2] = 1.0
    shift = np.zeros((len(s), 3, 4))
    shift[:, :, :3] = np.eye(3)
    shift[:, :, 3] = -s * np.array([1.0, 1.0, -1.0])
    A = np.array([[1 / dc, 0.0, (cols - 1) / 2.0], [0.0, 1 / dr, (rows - 1) / 2.0], [0, 0, 1.0]])
    return normalize_projections(A @ K @ shift @ tf.invert(T))


def nine_dof_from_projection(
    P: ArrayLike, *, rows: int, cols: int, pixel_spacing: ArrayLike
) -> NineDof:
    """Inverse of :func:`projection_from_nine_dof` (requires zero skew and square focal lengths)."""
    _check_detector(rows, cols)
    dr, dc = _pixel_spacing(pixel_spacing)
    dec = decompose_projection(P)
    K = dec.intrinsics
    sz = K[0, 0] * dc
    if abs(K[1, 1] * dr - sz) > 1e-6 * sz or abs(K[0, 1]) > 1e-9 * K[0, 0]:
        raise ValueError("projection matrix has skew or unequal SDD along rows and columns")
    sx = (K[0, 2] - (cols - 1) / 2.0) * dc
    sy = (K[1, 2] - (rows - 1) / 2.0) * dr
    R = dec.carm_from_world.T
    world_from_detector = np.eye(4)
    world_from_detector[:3, :3] = R
    world_from_detector[:3, 3] = dec.source + R @ np.array([-sx, -sy, sz])
    return NineDof(source_in_detector=(sx, sy, sz), world_from_detector=world_from_detector)


def six_dof_pose(params: ArrayLike, *, center: ArrayLike = (0.0, 0.0, 0.0)) -> NDArray:
    """Rigid pose from 6-DoF parameters ``[t_x, t_y, t_z (mm), r_x, r_y, r_z (deg)]``.

    The rotation (a rotation vector in degrees) turns the object about ``center`` (mm, e.g. its
    centroid) and the translation then moves it, so a step of 1 mm or 1 degree moves the object by
    comparable amounts near ``center``. Batched over leading axes: ``(..., 6) -> (..., 4, 4)``.
    """
    p = np.asarray(params, dtype=np.float64)
    if p.ndim == 0 or p.shape[-1] != 6:
        raise ValueError(f"6-DoF parameters must have shape (..., 6), got {p.shape}")
    c = np.asarray(center, dtype=np.float64)
    if c.shape != (3,):
        raise ValueError(f"center must have shape (3,), got {c.shape}")
    R = tf.matrix_from_rotvec(np.deg2rad(p[..., 3:]))
    T = np.zeros((*p.shape[:-1], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = c + p[..., :3] - R @ c
    T[..., 3, 3] = 1.0
    return T


def six_dof_params(T: ArrayLike, *, center: ArrayLike = (0.0, 0.0, 0.0)) -> NDArray:
    """Inverse of :func:`six_dof_pose`: ``(..., 4, 4) -> (..., 6)``."""
    T = np.asarray(T, dtype=np.float64)
    tf.se3_log(T)  # validates rigidity with a clear message
    c = np.asarray(center, dtype=np.float64)
    r = tf.rotvec_from_matrix(T[..., :3, :3])
    t = T[..., :3, 3] - c + T[..., :3, :3] @ c
    return np.concatenate([t, np.rad2deg(r)], axis=-1)
