"""Whole-pelvis radiographs of a sampled patient above those of an atlas subject.

``python scripts/figure_sampled_vs_atlas.py SAMPLED_CASE ATLAS_CASE PNG``: both folders written by
``pelvicnav simulate``. Each CT is radiographed in AP, inlet and oblique views with a
radiography-room geometry (source 1000 mm from the isocentre, detector 100 mm behind it, 410 mm
detector: the whole pelvis in view, where the mobile C-arm of ``simulate`` sees the centre only).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from pelvicnav.drr.volume import Volume
from pelvicnav.io.atomic import save_figure
from pelvicnav.io.nifti import read_nifti
from pelvicnav.phantom.xray import simulate_radiograph, standard_view

VIEWS = ("ap", "inlet", "oblique30")
WIDE = {
    "source_to_isocenter": 1000.0,
    "source_to_detector": 1100.0,
    "rows": 512,
    "cols": 512,
    "pixel_spacing": (0.8, 0.8),
}


def _radiographs(case: Path) -> list[np.ndarray]:
    hu, world_from_ijk = read_nifti(case / "ct.nii.gz")
    labels, _ = read_nifti(case / "labels.nii.gz")
    ct = Volume(hu.astype(np.float32), world_from_ijk)
    ijk = np.argwhere(labels > 0).mean(axis=0)
    centre = tuple((world_from_ijk @ np.r_[ijk, 1.0])[:3])
    rng = np.random.default_rng(0)
    return [
        simulate_radiograph(
            ct, standard_view(v, isocenter=centre, **WIDE), dose_ugy=50.0, rng=rng
        ).line_integrals
        for v in VIEWS
    ]


def main(sampled: Path, atlas: Path, png: Path) -> None:
    rows = [(sampled, "sampled patient"), (atlas, "atlas subject")]
    fig, axes = plt.subplots(2, len(VIEWS), figsize=(4.6 * len(VIEWS), 9.6), squeeze=False)
    for r, (case, label) in enumerate(rows):
        subject = json.loads((case / "truth.json").read_text())["subject_id"]
        for ax, view, image in zip(axes[r], VIEWS, _radiographs(case), strict=True):
            body = image[image > 0.5 * np.median(image)]  # window on the patient, not the air
            lo, hi = np.percentile(body, [20, 99.8])
            ax.imshow(image, cmap="gray", vmin=lo, vmax=hi)
            ax.set_title(f"{label} {subject}: {view}", fontsize=11)
            ax.axis("off")
    fig.suptitle(
        "A patient sampled from the packaged pelvis model (top) and an atlas subject (bottom); "
        "open-book dislocation of the left hip"
    )
    fig.tight_layout()
    save_figure(fig, png, dpi=110)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))
