"""``pelvicnav segment``: the bones of a CT as corresponded meshes and a label map.

With a label map (ours, TotalSegmentator's or a mapping), the pelvis model is fitted to it
(:func:`pelvicnav.shape.fit.fit_labels`); without one, the multi-resolution active shape model
segments the CT (:func:`pelvicnav.shape.asm.segment_ct`).

Outputs in ``out`` (written to a temporary sibling folder and moved into place only when all of
them succeeded): ``labels.nii.gz`` (ours, on the CT's grid), ``{bone}.vtk``, ``.stl`` and ``.ply``
(LPS mm, the model's vertex order), ``segmentation.json`` (fit quality, timings, model
provenance) and ``contours.png`` (axial, coronal and sagittal slices through each bone).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from pelvicnav import BONES

__all__ = ["segment"]


def segment(
    ct: str | os.PathLike,
    out: str | os.PathLike,
    *,
    labels: str | os.PathLike | None = None,
    label_scheme: str = "ours",
    model=None,
    prior=None,
    series: str | None = None,
    progress=None,
) -> dict:
    """Segment (or fit) the three bones of a CT and write them to ``out``; returns the record.

    ``ct`` and ``labels`` are any volume :func:`pelvicnav.io.volume.read_volume` reads (a DICOM
    series folder, ``series`` choosing among several, NIfTI, NRRD, MetaImage). Without
    ``labels`` the active shape model segments the CT (``prior``: a
    :class:`~pelvicnav.shape.asm.ShapePrior`, default the model's).

    Raises
    ------
    ValueError
        Unreadable files, labels on another grid, a bad scheme, a map whose bones are not bone
        (see :func:`pelvicnav.shape.labels.check_bone_labels`), a CT without bone; nothing is
        written then.
    """
    from pelvicnav.model import load_model
    from pelvicnav.shape.voxelize import inside_mask
    from pelvicnav.workflow.inputs import bones_of_ct

    model = model or (load_model() if prior is None else None)
    bones = bones_of_ct(ct, labels, label_scheme=label_scheme, series=series, model=model,
                        prior=prior, progress=progress)  # fmt: skip
    faces = prior.faces if prior is not None else model.faces
    fitted = np.zeros(bones.hu.shape, dtype=np.uint8)
    for b, bone in enumerate(BONES):
        inside = inside_mask(bones.meshes[bone], faces[b], bones.world_from_ijk, bones.hu.shape)
        fitted[inside & (fitted == 0)] = b + 1
    record = {
        "ct": str(ct),
        "labels": None if labels is None else str(labels),
        "label_scheme": label_scheme if labels is not None else None,
        "method": bones.method,
        "bones": {
            bone: {
                **bones.quality.get(bone, {}),
                "dice_surface_vs_labels": _dice(fitted == b + 1, bones.labels == b + 1),
                "voxels": int((bones.labels == b + 1).sum()),
            }
            for b, bone in enumerate(BONES)
        },
        "seconds": bones.seconds,
        "model": _provenance(model, prior),
    }
    _write(Path(out), bones, fitted, faces, record)
    return record


def _provenance(model, prior) -> dict:
    if model is not None:
        return {k: model.provenance.get(k) for k in ("doi", "licence", "note", "created")}
    return {"source": getattr(prior, "source", "shape prior fitted from an atlas"),
            "doi": "10.1088/1361-6560/ab1456"}  # fmt: skip


def _dice(a, b) -> float:
    return float(2 * np.sum(a & b) / max(np.sum(a) + np.sum(b), 1))


def _write(out: Path, bones, fitted, faces, record) -> None:
    from pelvicnav.io.atomic import atomic_directory
    from pelvicnav.io.mesh_files import write_meshes
    from pelvicnav.io.nifti import write_nifti

    with atomic_directory(out) as tmp:
        write_nifti(tmp / "labels.nii.gz", bones.labels, bones.world_from_ijk)
        for b, bone in enumerate(BONES):
            write_meshes(tmp, bone, bones.meshes[bone], faces[b], title=f"pelvicnav {bone}")
        write_contours(bones.hu, bones.labels, fitted, bones.world_from_ijk, tmp / "contours.png")
        (tmp / "segmentation.json").write_text(json.dumps(record, indent=2) + "\n")


def write_contours(hu, labels, fitted, world_from_ijk, path: Path) -> None:
    """Axial, coronal and sagittal slices through each bone's centre: the label map's contours
    (solid) and the fitted meshes' interiors (dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pelvicnav.io.atomic import save_figure

    colours = ("tab:blue", "tab:orange", "tab:green")
    spacing = np.linalg.norm(np.asarray(world_from_ijk)[:3, :3], axis=0)
    fig, axes = plt.subplots(3, 3, figsize=(12, 12))
    for b, bone in enumerate(BONES):
        centre = np.round(np.argwhere(labels == b + 1).mean(axis=0)).astype(int)
        for col, (axis, name) in enumerate(((2, "axial"), (1, "coronal"), (0, "sagittal"))):
            index = [slice(None)] * 3
            index[axis] = centre[axis]
            image, lab, fit = (x[tuple(index)].T for x in (hu, labels, fitted))
            rest = [d for d in range(3) if d != axis]
            aspect = spacing[rest[1]] / spacing[rest[0]]
            ax = axes[b, col]
            ax.imshow(image, cmap="gray", vmin=-200, vmax=1200, origin="lower", aspect=aspect)
            for k, colour in enumerate(colours):
                for mask, style in ((lab == k + 1, "solid"), (fit == k + 1, "dashed")):
                    if mask.any():
                        ax.contour(mask, levels=[0.5], colors=colour, linewidths=0.8,
                                   linestyles=style)  # fmt: skip
            ax.set_title(f"{bone}: {name} slice {centre[axis]}", fontsize=9)
            ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path, dpi=70)
