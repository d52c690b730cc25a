"""Pyramid levels: the radiographs binned and blurred like the DRRs, their geometry and similarity.

A :class:`Level` is one resolution of the whole view set: the binned projection matrices, one
similarity per view built from the blurred radiograph, and the image shape. Stages score
candidates with :meth:`Level.score`. Binning keeps pixel centres at integers
(:func:`downsample_projection`, :func:`downsample_image`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter, gaussian_gradient_magnitude

from pelvicnav.drr.attenuation import bone_point_models
from pelvicnav.drr.renderer import Renderer, SplatRenderer
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj
from pelvicnav.io.views import ViewSet
from pelvicnav.metrics.similarity import GradientNCC, GradientOrientation
from pelvicnav.register.settings import SAMPLE_MM_PER_FACTOR, PyramidSettings

__all__ = [
    "SAMPLE_MM_PER_FACTOR",
    "Level",
    "build_levels",
    "downsample_image",
    "downsample_projection",
    "level_blur",
    "noise_to_edge",
    "splat_renderer",
]

_METRICS = {"go": GradientOrientation, "gncc": GradientNCC}


def downsample_projection(P: ArrayLike, factor: float) -> NDArray[np.float64]:
    """Projection matrix of the same view on a detector binned by ``factor`` (``(3, 4)`` or a
    stack ``(..., 3, 4)``).

    Pixel centres stay at integers: a binned pixel ``u'`` covers original pixels
    ``factor * u' ... factor * u' + factor - 1``, so ``u' = (u - (factor - 1) / 2) / factor``.
    """
    if factor <= 0:
        raise ValueError(f"factor must be positive, got {factor}")
    S = np.array(
        [
            [1 / factor, 0, -(factor - 1) / (2 * factor)],
            [0, 1 / factor, -(factor - 1) / (2 * factor)],
            [0, 0, 1],
        ]
    )
    P = np.asarray(P, dtype=np.float64)
    if P.ndim == 2:
        return S @ pj.normalize_projection(P)
    return S @ pj.normalize_projections(P.reshape(-1, 3, 4)).reshape(P.shape)


def downsample_image(image: ArrayLike, factor: int) -> NDArray[np.float64]:
    """Block-average an image by an integer factor (trailing rows/columns that do not fill a block
    are dropped), matching :func:`downsample_projection`."""
    img = np.asarray(image, dtype=np.float64)
    if factor == 1:
        return img
    h, w = (img.shape[0] // factor) * factor, (img.shape[1] // factor) * factor
    return img[:h, :w].reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))


def splat_renderer(ct_hu: Volume, labels: ArrayLike, factors: Sequence[int]) -> SplatRenderer:
    """Bone point models for each pyramid level (sample spacing ``SAMPLE_MM_PER_FACTOR`` x
    factor). Build once per CT and pass to every frame's registration."""
    spacings = [SAMPLE_MM_PER_FACTOR * f for f in factors]
    return SplatRenderer(bone_point_models(ct_hu, labels, spacings))


@dataclass(frozen=True, eq=False)
class Level:
    """One pyramid level of a view set.

    Attributes
    ----------
    index : int
        Position in the pyramid (0 = coarsest); the renderer's level.
    factor : int
        Detector binning.
    projections : (K, 3, 4) float64
        Binned projection matrices.
    similarities : K callables
        ``drrs (B, rows, cols) -> (B,)`` against each view's blurred radiograph.
    shape : (rows, cols)
    images : K (rows, cols) float64
        The blurred, binned radiographs the similarities were built from.
    """

    index: int
    factor: int
    projections: NDArray[np.float64]
    similarities: tuple
    shape: tuple[int, int]
    images: tuple = ()

    def score(self, drrs: NDArray) -> NDArray[np.float64]:
        """Similarity summed over the views: ``drrs`` (B, K, rows, cols) -> (B,)."""
        return sum(s(drrs[:, k]) for k, s in enumerate(self.similarities))

    def scored_by(self, metric: str) -> Level:
        """This level scoring its radiographs (``images``) in ``metric`` ("go" or "gncc")
        instead: a second opinion or a search in the other similarity."""
        return replace(self, similarities=tuple(_METRICS[metric](i) for i in self.images))

    def with_geometry(self, projections: Sequence[ArrayLike]) -> Level:
        """This level with the full-resolution ``projections`` (binned here) instead."""
        Ps = np.stack([downsample_projection(P, self.factor) for P in projections])
        return Level(self.index, self.factor, Ps, self.similarities, self.shape, self.images)


def blurred(image: NDArray, resolution_mm: float, points: NDArray, P, blur: float = 0.4) -> NDArray:
    """A binned radiograph (projection ``P`` of its level) blurred by a Gaussian of ``blur`` DRR
    sample spacings (``resolution_mm`` at the median depth of ``points``, world mm; at least a
    pixel, a pixel for an exact renderer, ``resolution_mm`` 0). 0.4 is the DRR's own blur (a
    tent of half-width r has sd r / sqrt(6)); ``blur`` 0: the image itself."""
    if blur <= 0:
        return image
    px = 1.0
    if resolution_mm > 0:
        K = pj.decompose_projection(P).intrinsics
        depth_mm = float(np.median(pj.depth(P, points)))
        px = resolution_mm * K[0, 0] / depth_mm  # sample spacing in pixels at the bones' depth
    return gaussian_filter(image, blur * max(px, 1.0), mode="nearest")


def noise_to_edge(image: ArrayLike) -> float:
    """How noisy a radiograph is against its own edges (scale-free): the sd of its white noise
    (the median absolute second difference along rows, / (0.6745 sqrt 6)) over the 95th
    percentile of its gradient magnitude after a Gaussian of 2 pixels (the edges, noise mostly
    smoothed away); 0 for an image without edges. Simulated quantum noise, both views of one
    patient binned 2x: 0.24-0.29 at 50 uGy per frame, 0.57-0.64 at 10, 0.89-0.95 at 5,
    1.75-1.88 at 2, 2.9-3.4 at 1."""
    img = np.asarray(image, dtype=np.float64)
    if img.shape[1] < 3:
        return 0.0
    d2 = img[:, :-2] - 2.0 * img[:, 1:-1] + img[:, 2:]
    noise = float(np.median(np.abs(d2))) / (0.6745 * np.sqrt(6.0))
    edge = float(np.percentile(gaussian_gradient_magnitude(img, 2.0), 95))
    return noise / edge if edge > 0 else 0.0


def level_blur(image: NDArray, blur: float, pyramid: PyramidSettings) -> float:
    """``blur``, raised towards ``pyramid.noise_blur`` as the binned radiograph's
    :func:`noise_to_edge` rises through ``pyramid.noise_ratio`` (linear between its ends)."""
    lo, hi = pyramid.noise_ratio
    if pyramid.noise_blur <= blur:
        return blur
    ramp = float(np.clip((noise_to_edge(image) - lo) / (hi - lo), 0.0, 1.0))
    return max(blur, pyramid.noise_blur * ramp)


def build_levels(views: ViewSet, renderer: Renderer, pyramid: PyramidSettings) -> list[Level]:
    """Every level of the pyramid for ``views`` (coarse to fine)."""
    if renderer.n_levels != pyramid.n_levels:
        raise ValueError(
            f"the renderer has {renderer.n_levels} levels, the pyramid {pyramid.n_levels}"
        )
    levels = []
    for lv, (f, metric, k) in enumerate(
        zip(pyramid.factors, pyramid.metrics, pyramid.blur, strict=True)
    ):
        Ps = np.stack([downsample_projection(P, f) for P in views.projections])
        pts = renderer.points(renderer.bones[0], lv)[::50]
        res = renderer.resolution_mm(lv)
        k = k if res > 0 else 0.0  # an exact renderer's DRR is not blurred
        imgs = []
        for img, P in zip(views.images, Ps, strict=True):
            binned = downsample_image(img, f)
            imgs.append(blurred(binned, res, pts, P, level_blur(binned, k, pyramid)))
        sims = tuple(_METRICS[metric](i) for i in imgs)
        levels.append(Level(lv, f, Ps, sims, imgs[0].shape, tuple(imgs)))
    return levels
