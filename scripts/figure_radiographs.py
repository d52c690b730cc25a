"""Figure of the radiographs of a simulated case: ``python scripts/figure_radiographs.py CASE PNG``.

CASE is a folder written by ``pelvicnav simulate``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from pelvicnav.io.atomic import save_figure
from pelvicnav.io.views import read_views


def main(case: Path, png: Path) -> None:
    views, _ = read_views(case / "views.json")
    truth = json.loads((case / "truth.json").read_text())
    fig, axes = plt.subplots(1, len(views), figsize=(5 * len(views), 5.4), squeeze=False)
    for ax, view in zip(axes[0], views, strict=True):
        ax.imshow(view.image, cmap="gray")
        ax.set_title(view.name)
        ax.axis("off")
    d = truth["dislocation"]
    fig.suptitle(
        f"subject {truth['subject_id']}: {d['pattern']} dislocation of {d['bone']} "
        f"({d['translation_mm']:.1f} mm, {d['rotation_deg']:.1f} deg)"
    )
    fig.tight_layout()
    save_figure(fig, png)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
