"""Radiographs from a CT at a given dose: line integrals, Beer-Lambert, quantum and detector noise.

Image formation (Han et al. 2020, section 2.3.3; noise model after Wang et al. 2014, "Soft-tissue
imaging with C-arm cone-beam CT using statistical reconstruction", and the dose-dependent noise
injection they validated):

1. ``mu = mu_water * max(0, 1 + HU / 1000)`` at an effective energy (1/mm), one monoenergetic
   beam: no beam hardening or scatter.
2. Line integrals ``p`` through the CT along every detector ray (:func:`pelvicnav.drr.render`).
3. Incident quanta per pixel from the dose. The dose is the air kerma per frame at the isocentre,
   free in air (the usual C-arm reference point). Fluence per air kerma at energy ``E`` is
   ``Phi/K = 1 / (E (mu_en/rho)_air)``: at 60 keV, (mu_en/rho)_air = 0.03041 cm^2/g (NIST), so
   1 uGy gives 3.42e4 photons/mm^2. The fluence falls as ``(SID/SDD)^2`` to the detector, times
   the pixel area and the detector's quantum efficiency.
4. Quantum noise ``N ~ Poisson(N0 exp(-p))``, detector blur (Gaussian, correlating the noise),
   electronic noise (Gaussian, in quanta).
5. Log transform ``-ln(I / N0)`` back to line integrals (what DRRs are compared with).

At 50 uGy/frame and the default C-arm (SID 600, SDD 1100 mm, 0.586 mm pixels) a pixel receives
about 1e5 quanta unattenuated; at 0.5 uGy/frame, 1e3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pelvicnav.drr.attenuation import MU_WATER_PER_MM, mu_from_hu
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj

__all__ = [
    "MU_WATER_PER_MM",
    "PHOTONS_PER_MM2_PER_UGY",
    "STANDARD_VIEWS",
    "DetectorModel",
    "Radiograph",
    "crop",
    "mu_from_hu",
    "quanta_per_pixel",
    "simulate_radiograph",
    "standard_view",
]

_E_J = 60e3 * 1.602176634e-19
_MU_EN_RHO_AIR_CM2_G = 0.03041
PHOTONS_PER_MM2_PER_UGY = 1e-6 / (_E_J * _MU_EN_RHO_AIR_CM2_G * 1000.0) / 100.0  # ~3.42e4

# name -> (orbit, tilt) in degrees, in the C-arm convention of pelvicnav.geometry.projection.
STANDARD_VIEWS: dict[str, tuple[float, float]] = {
    "ap": (0.0, 0.0),
    "lateral": (90.0, 0.0),
    "inlet": (0.0, 40.0),  # beam angled 40 deg caudally
    "outlet": (0.0, -40.0),  # beam angled 40 deg cranially
    "iliac": (45.0, 0.0),  # Judet obliques
    "obturator": (-45.0, 0.0),
    "oblique30": (30.0, -20.0),  # the paper's second view (orbit 30, tilt -20)
}


def standard_view(name: str, **carm_kwargs) -> pj.CArm:
    """A named standard pelvic view as a :class:`~pelvicnav.geometry.projection.CArm`.

    Raises
    ------
    ValueError
        For an unknown name (the message lists the known ones).
    """
    key = name.strip().lower()
    if key not in STANDARD_VIEWS:
        raise ValueError(f"unknown view {name!r}; expected one of {sorted(STANDARD_VIEWS)}")
    orbit, tilt = STANDARD_VIEWS[key]
    return pj.CArm(orbit_deg=orbit, tilt_deg=tilt, **carm_kwargs)


@dataclass(frozen=True)
class DetectorModel:
    """Flat-panel detector response.

    Attributes
    ----------
    efficiency : float
        Fraction of incident quanta detected (quantum efficiency).
    blur_sigma_px : float
        Gaussian system blur (pixels), applied after quantum noise so it correlates the noise.
    electronic_sigma : float
        Additive electronic noise (standard deviation, in detected-quanta units).
    """

    efficiency: float = 0.6
    blur_sigma_px: float = 0.6
    electronic_sigma: float = 3.0


def quanta_per_pixel(dose_ugy: float, carm: pj.CArm, detector: DetectorModel) -> float:
    """Detected quanta per pixel with nothing in the beam for ``dose_ugy`` at the isocentre."""
    if not np.isfinite(dose_ugy) or dose_ugy <= 0:
        raise ValueError(f"dose must be a positive number of uGy/frame, got {dose_ugy}")
    fluence_iso = dose_ugy * PHOTONS_PER_MM2_PER_UGY
    fluence_det = fluence_iso * (carm.source_to_isocenter / carm.source_to_detector) ** 2
    area = carm.pixel_spacing[0] * carm.pixel_spacing[1]
    return float(fluence_det * area * detector.efficiency)


@dataclass(frozen=True, eq=False)
class Radiograph:
    """A simulated view.

    Attributes
    ----------
    line_integrals : (rows, cols) float32
        ``-ln(I / N0)`` (log-transformed, noisy).
    quanta : (rows, cols) float32
        Detected signal ``I`` (after blur and electronic noise), quanta.
    incident_quanta : float
        ``N0`` per pixel.
    carm : CArm
    dose_ugy : float
    """

    line_integrals: NDArray[np.float32]
    quanta: NDArray[np.float32]
    incident_quanta: float
    carm: pj.CArm
    dose_ugy: float

    @property
    def projection_matrix(self) -> NDArray[np.float64]:
        return self.carm.projection_matrix


def simulate_radiograph(
    ct_hu: Volume,
    carm: pj.CArm,
    *,
    dose_ugy: float,
    rng: np.random.Generator,
    detector: DetectorModel | None = None,
    step_mm: float | None = None,
) -> Radiograph:
    """Simulate one radiograph of a CT (HU) at a dose.

    Parameters
    ----------
    ct_hu : Volume
        CT in Hounsfield units, placed in the world by its ``world_from_ijk``.
    carm : CArm
    dose_ugy : float
        Air kerma per frame at the isocentre (uGy), > 0.
    rng : numpy.random.Generator
        Seeded generator for the noise.
    detector : DetectorModel, optional
    step_mm : float, optional
        Ray sampling step (default the smallest voxel spacing). On a 1 x 1 x 2 mm patient CT, AP
        view, the line integrals at 1 mm steps differ from those at 0.25 mm by at most 0.0013
        (99th percentile 0.0005; at 0.5 mm 0.0004), below the quantum noise of every pixel at
        50 uGy/frame (>= 0.003 before the detector blur), in 0.67 s instead of 1.58 s.

    Raises
    ------
    ValueError
        Non-positive dose, or a view that misses the volume entirely.
    """
    from scipy.ndimage import gaussian_filter

    from pelvicnav.drr.projector import render

    det = detector or DetectorModel()
    n0 = quanta_per_pixel(dose_ugy, carm, det)
    _check_volume_in_view(ct_hu, carm)
    mu = Volume(mu_from_hu(ct_hu.data), ct_hu.world_from_ijk)
    step = float(np.min(ct_hu.spacing)) if step_mm is None else step_mm
    p = render(
        [mu], np.eye(4)[None, None], carm.projection_matrix[None], (carm.rows, carm.cols),
        step_mm=step,
    )[0, 0].astype(np.float64)  # fmt: skip
    counts = rng.poisson(n0 * np.exp(-p)).astype(np.float64)
    if det.blur_sigma_px > 0:
        counts = gaussian_filter(counts, det.blur_sigma_px, mode="nearest")
    if det.electronic_sigma > 0:
        counts = counts + rng.normal(0.0, det.electronic_sigma, counts.shape)
    floor = 0.5  # below half a quantum the log is undefined: clip, as detectors do
    log_image = -np.log(np.maximum(counts, floor) / n0)
    return Radiograph(
        line_integrals=log_image.astype(np.float32),
        quanta=counts.astype(np.float32),
        incident_quanta=n0,
        carm=carm,
        dose_ugy=float(dose_ugy),
    )


def _check_volume_in_view(volume: Volume, carm: pj.CArm) -> None:
    """Raise unless the volume's bounding box projects onto the detector."""
    n = np.asarray(volume.shape) - 1
    corners = np.array([[i, j, k] for i in (0, n[0]) for j in (0, n[1]) for k in (0, n[2])], float)
    uv = pj.project(carm.projection_matrix, volume.world_points(corners))
    ok = np.all(np.isfinite(uv), axis=1)
    if ok.any():
        lo, hi = uv[ok].min(axis=0), uv[ok].max(axis=0)
        if (
            hi[0] >= -0.5
            and lo[0] <= carm.cols - 0.5
            and hi[1] >= -0.5
            and lo[1] <= carm.rows - 0.5
        ):
            return
    raise ValueError(
        "the view misses the CT volume entirely (no ray crosses it): check the isocentre "
        f"{carm.isocenter} and the angles (orbit {carm.orbit_deg}, tilt {carm.tilt_deg})"
    )


def crop(
    image: NDArray, P: NDArray, *, top: int, left: int, rows: int, cols: int
) -> tuple[NDArray, NDArray[np.float64]]:
    """Crop an image (field of view) and shift its projection matrix to match.

    Returns the ``(rows, cols)`` sub-image starting at ``(top, left)`` and ``P`` for it: a world
    point projects to the same physical pixel, now indexed from the crop's corner.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image must be 2D, got shape {img.shape}")
    if not (0 <= top and 0 <= left and rows > 0 and cols > 0):
        raise ValueError(f"invalid crop top={top}, left={left}, rows={rows}, cols={cols}")
    if top + rows > img.shape[0] or left + cols > img.shape[1]:
        raise ValueError(f"crop {rows}x{cols} at ({top}, {left}) exceeds the image {img.shape}")
    shift = np.array([[1.0, 0.0, -left], [0.0, 1.0, -top], [0.0, 0.0, 1.0]])
    return img[top : top + rows, left : left + cols].copy(), shift @ pj.normalize_projection(P)
