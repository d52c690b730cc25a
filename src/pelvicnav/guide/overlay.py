"""Overlays for the surgeon: the radiograph with the registered bones' edges and the target.

Like Han et al. (2020) figures 3 and 11: Canny edges (scikit-image) of each registered bone's DRR
in yellow, and of the dislocated bone at its planned target pose in green.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.drr.splat import PointModel, splat
from pelvicnav.io.atomic import save_figure

__all__ = ["bone_edges", "write_overlay"]

YELLOW = (1.0, 0.85, 0.0)
GREEN = (0.1, 0.9, 0.2)


def bone_edges(
    model: PointModel,
    pose: ArrayLike,
    projection: ArrayLike,
    shape: tuple[int, int],
    *,
    sigma: float = 2.0,
) -> NDArray[np.bool_]:
    """Canny edges ``(rows, cols)`` of one bone's DRR at ``pose`` (``world_from_ct``)."""
    from skimage.feature import canny

    T = np.asarray(pose, dtype=np.float64)[None, None]
    drr = splat([model], T, np.asarray(projection)[None], shape)[0, 0]
    if drr.max() <= 0:
        return np.zeros(shape, dtype=bool)
    return canny(drr / drr.max(), sigma=sigma, low_threshold=0.05, high_threshold=0.15)


def write_overlay(
    path: str | os.PathLike,
    image: ArrayLike,
    edges: Mapping[str, NDArray[np.bool_]],
    *,
    target: NDArray[np.bool_] | None = None,
    title: str = "",
) -> Path:
    """Write a PNG: the radiograph (bone bright), registered edges yellow, target green."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = np.asarray(image, dtype=np.float64)
    lo, hi = np.percentile(img, [1, 99])
    grey = np.clip((img - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = np.repeat(grey[..., None], 3, axis=-1)
    for e in edges.values():
        rgb[e] = YELLOW
    if target is not None:
        rgb[target] = GREEN
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.imshow(rgb)
    ax.set_title(title or "registered bones (yellow), target (green)")
    ax.axis("off")
    fig.tight_layout()
    return save_figure(fig, path)
