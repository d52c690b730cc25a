"""Rigid 6-DoF 3D-2D registration of one body to K views on a multi-resolution pyramid.

This is stage 1 of Han et al. (2020) (section 2.2.1, equation 11b) when ``P`` is known: the pose of
one bone is found by maximising the gradient-orientation similarity (summed over views, equation
12 with one body) between the radiographs and DRRs, with CMA-ES on a [4x, 2x] pyramid (population
[100, 100], sigma [4, 1] mm and degrees). Parameters are ``[t (mm), r (deg)]`` about the body's
centre (:func:`pelvicnav.geometry.projection.six_dof_pose`), applied on top of the initial pose.

DRRs come from the ray-casting reference projector, so this is the exact (and slow) single-body
registration of arbitrary attenuation volumes. The workflow's fast multi-body path (splatted
bone models) is :func:`~pelvicnav.register.multibody.register_multibody`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.drr.projector import downsample_image, downsample_projection, render
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.metrics.similarity import gradient_orientation
from pelvicnav.register.cmaes import CMAESResult, minimize_cmaes

__all__ = ["PyramidSettings", "RigidResult", "register_rigid"]


@dataclass(frozen=True)
class PyramidSettings:
    """Per-level settings (coarse to fine); defaults are the paper's."""

    factors: tuple[int, ...] = (4, 2)
    populations: tuple[int, ...] = (100, 100)
    sigmas: tuple[float, ...] = (4.0, 1.0)
    max_generations: tuple[int, ...] = (60, 40)

    def __post_init__(self) -> None:
        n = len(self.factors)
        if not (len(self.populations) == len(self.sigmas) == len(self.max_generations) == n):
            raise ValueError("pyramid settings need one value per level in every field")
        if any(f < 1 or int(f) != f for f in self.factors):
            raise ValueError(f"pyramid factors must be positive integers, got {self.factors}")


@dataclass(frozen=True)
class RigidResult:
    """Registered pose and diagnostics.

    Attributes
    ----------
    pose : (4, 4) float64
        ``world_from_ct`` of the body.
    params : (6,) float64
        ``[t (mm), r (deg)]`` relative to the initial pose, about the body's centre.
    similarity : float
        Summed GO at the finest level.
    converged : bool
        Every level stopped on a tolerance.
    levels : list of CMAESResult
    seconds : float
    """

    pose: NDArray[np.float64]
    params: NDArray[np.float64]
    similarity: float
    converged: bool
    levels: list[CMAESResult] = field(default_factory=list)
    seconds: float = 0.0


def register_rigid(
    volumes: Sequence[Volume],
    radiographs: Sequence[ArrayLike],
    projections: Sequence[ArrayLike],
    *,
    init_pose: ArrayLike,
    center: ArrayLike,
    seed: int,
    settings: PyramidSettings | None = None,
) -> RigidResult:
    """Register one rigid body (its volumes move together) to K radiographs.

    Parameters
    ----------
    volumes : sequence of Volume
        The body's attenuation model(s), in the CT frame.
    radiographs : K arrays (H, W)
        Line-integral images.
    projections : K (3, 4) arrays
        Their projection matrices (world mm -> pixels of the full-resolution image).
    init_pose : (4, 4) float
        Starting ``world_from_ct``.
    center : (3,) float, mm
        Rotation centre in the CT frame (e.g. the bone's centroid).
    seed : int
    settings : PyramidSettings, optional

    Raises
    ------
    ValueError
        Mismatched view counts, images that do not match, a singular P, NaN images.
    """
    t0 = time.perf_counter()
    cfg = settings or PyramidSettings()
    if len(radiographs) != len(projections) or not radiographs:
        raise ValueError(
            f"need one projection matrix per radiograph, got {len(radiographs)} and "
            f"{len(projections)}"
        )
    images = [np.asarray(r, dtype=np.float64) for r in radiographs]
    for k, img in enumerate(images):
        if img.ndim != 2 or not np.all(np.isfinite(img)):
            raise ValueError(f"radiograph {k} must be a finite 2D image, got shape {img.shape}")
    Ps = [pj.normalize_projection(P) for P in projections]
    T0 = np.asarray(init_pose, dtype=np.float64)
    tf.se3_log(T0)  # a rigid initial pose, or a clear error
    c_world = tf.apply(T0, np.asarray(center, dtype=np.float64)[None])[0]

    def poses(params: NDArray) -> NDArray:
        return pj.six_dof_pose(params, center=c_world) @ T0

    x = np.zeros(6)
    levels = []
    score = -np.inf
    for level, factor in enumerate(cfg.factors):
        imgs = [downsample_image(img, factor) for img in images]
        shapes = {im.shape for im in imgs}
        if len(shapes) != 1:
            raise ValueError(f"all radiographs must have the same shape, got {shapes}")
        shape = imgs[0].shape
        P_level = np.stack([downsample_projection(P, factor) for P in Ps])

        def objective(X, imgs=imgs, P_level=P_level, shape=shape):
            T = poses(X)[:, None].repeat(len(volumes), axis=1)
            drrs = render(volumes, T, P_level, shape)
            total = np.zeros(len(X))
            for k, img in enumerate(imgs):
                total += gradient_orientation(img, drrs[:, k])
            return -total

        res = minimize_cmaes(
            objective,
            x,
            sigma=cfg.sigmas[level],
            population=cfg.populations[level],
            seed=seed + level,
            max_generations=cfg.max_generations[level],
        )
        levels.append(res)
        x = res.x
        score = -res.f
    return RigidResult(
        pose=poses(x[None])[0],
        params=x,
        similarity=float(score),
        converged=all(r.converged for r in levels),
        levels=levels,
        seconds=time.perf_counter() - t0,
    )
