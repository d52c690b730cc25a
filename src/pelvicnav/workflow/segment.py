"""``pelvicnav segment``: the bones of a CT as corresponded meshes and a label map.

With a label map (ours, TotalSegmentator's or a mapping), the pelvis model is fitted to it
(:func:`pelvicnav.shape.fit.fit_labels`). The active shape model on the CT alone (issue 12) is
not there yet; asking for it is an error that says so.

Outputs in ``out`` (written to a temporary sibling folder and moved into place only when all of
them succeeded): ``labels.nii.gz`` (ours, on the CT's grid), ``{bone}.vtk``, ``.stl`` and ``.ply``
(LPS mm, the model's vertex order), ``segmentation.json`` (fit quality, timings, model
provenance) and ``contours.png`` (axial, coronal and sagittal slices through each bone).
"""

from __future__ import annotations

import json
import os
import time
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
    series: str | None = None,
) -> dict:
    """Segment (fit) the three bones of a CT and write them to ``out``; returns the record.

    ``ct`` and ``labels`` are any volume :func:`pelvicnav.io.volume.read_volume` reads (a DICOM
    series folder, ``series`` choosing among several, NIfTI, NRRD, MetaImage).

    Raises
    ------
    ValueError
        No label map (the ASM is not available yet), unreadable files, labels on another grid,
        a bad scheme, or a map whose bones are not bone (see
        :func:`pelvicnav.shape.labels.check_bone_labels`); nothing is written then.
    """
    from pelvicnav.model import load_model
    from pelvicnav.phantom.ctsynth import bone_labels
    from pelvicnav.workflow.inputs import fit_bones, read_ct_and_bones

    if labels is None:
        raise ValueError(
            "segmentation from the CT alone (active shape model) is not available yet: "
            "pass --labels with an existing label map (ours or TotalSegmentator's)"
        )
    started = time.perf_counter()
    hu, world_from_ijk, _, ours = read_ct_and_bones(ct, labels, label_scheme, series)
    model = model or load_model()
    read_s = time.perf_counter() - started
    fits = fit_bones(ours, world_from_ijk, model)
    fit_s = time.perf_counter() - started - read_s
    fitted = bone_labels(
        np.stack([fits[b].vertices for b in BONES]), model.faces, hu.shape, world_from_ijk
    )
    record = {
        "ct": str(ct),
        "labels": str(labels),
        "label_scheme": label_scheme,
        "method": "model fitted to the label map (shape.fit.fit_labels)",
        "bones": {
            bone: {
                "rms_mm": fits[bone].rms_mm,
                "dice_fitted_vs_labels": _dice(fitted == b + 1, ours == b + 1),
                "voxels": int((ours == b + 1).sum()),
            }
            for b, bone in enumerate(BONES)
        },
        "seconds": {"read": read_s, "fit": fit_s},
        "model": {k: model.provenance.get(k) for k in ("doi", "licence", "note", "created")},
    }
    _write(Path(out), hu, ours, fitted, world_from_ijk, model, fits, record)
    return record


def _dice(a, b) -> float:
    return float(2 * np.sum(a & b) / max(np.sum(a) + np.sum(b), 1))


def _write(out: Path, hu, ours, fitted, world_from_ijk, model, fits, record) -> None:
    from pelvicnav.io.atomic import atomic_directory
    from pelvicnav.io.mesh_files import write_meshes
    from pelvicnav.io.nifti import write_nifti

    with atomic_directory(out) as tmp:
        write_nifti(tmp / "labels.nii.gz", ours, world_from_ijk)
        for b, bone in enumerate(BONES):
            write_meshes(tmp, bone, fits[bone].vertices, model.faces[b], title=f"pelvicnav {bone}")
        write_contours(hu, ours, fitted, world_from_ijk, tmp / "contours.png")
        (tmp / "segmentation.json").write_text(json.dumps(record, indent=2) + "\n")


def write_contours(hu, labels, fitted, world_from_ijk, path: Path) -> None:
    """Axial, coronal and sagittal slices through each bone's centre: the label map's contours
    (solid) and the fitted meshes' (dashed)."""
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
