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

__all__ = ["bone_edges", "overlay_rgb", "write_overlay", "write_view_overlays"]

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


def overlay_rgb(
    image: ArrayLike,
    edges: Mapping[str, NDArray[np.bool_]],
    *,
    target: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """The overlay at the detector's resolution: ``(rows, cols, 3)`` RGB in [0, 1].

    The radiograph windowed to its 1st-99th percentiles (bone bright), registered edges yellow,
    the target green on top.
    """
    img = np.asarray(image, dtype=np.float64)
    lo, hi = np.percentile(img, [1, 99])
    grey = np.clip((img - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = np.repeat(grey[..., None], 3, axis=-1)
    for e in edges.values():
        rgb[e] = YELLOW
    if target is not None:
        rgb[target] = GREEN
    return rgb


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

    rgb = overlay_rgb(image, edges, target=target)
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.imshow(rgb)
    ax.set_title(title or "registered bones (yellow), target (green)")
    ax.axis("off")
    fig.tight_layout()
    return save_figure(fig, path)


def write_view_overlays(
    folder: str | os.PathLike,
    models: Mapping,
    views,
    result,
    plan: Mapping | None = None,
    *,
    dicom: bool = False,
) -> list[Path]:
    """One overlay PNG per view, ``overlay_<view>.png``; with ``dicom`` also a Secondary Capture.

    Parameters
    ----------
    models : mapping bone -> bone model
        The finest registration level's models (what the registration saw).
    views : list of :class:`pelvicnav.io.views.View`
    result : the registration result (``poses``, ``projections``)
    plan : mapping, optional
        ``dislocated_bone``, ``reference_bone`` and ``target_from_current``: the target is drawn.
    dicom : bool
        Also ``overlay_<view>.dcm``, carrying the radiograph's patient and study identifiers when
        the view came from a DICOM file.
    """
    from pelvicnav.io.dicom_base import DicomIdentity
    from pelvicnav.io.secondary_capture import write_secondary_capture

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for k, view in enumerate(views):
        P = result.projections[k] if len(result.projections) > k else view.projection_matrix
        shape = view.image.shape
        edges = {b: bone_edges(models[b], result.poses[b], P, shape) for b in models}
        target = None
        if plan is not None:
            T = result.poses[plan["reference_bone"]] @ plan["target_from_current"]
            target = bone_edges(models[plan["dislocated_bone"]], T, P, shape)
        written.append(write_overlay(
            folder / f"overlay_{view.name}.png", view.image, edges, target=target,
            title=f"{view.name}: registered (yellow), target (green)",
        ))  # fmt: skip
        if dicom:
            tags = view.meta.get("dicom", {})
            written.append(write_secondary_capture(
                folder / f"overlay_{view.name}.dcm", overlay_rgb(view.image, edges, target=target),
                identity=DicomIdentity.from_tags(tags),
                description=f"pelvicnav overlay {view.name}: registered yellow, target green",
                source=(tags.get("sop_class_uid", ""), tags.get("sop_instance_uid", "")),
            ))  # fmt: skip
    return written
