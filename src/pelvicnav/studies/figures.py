"""Figures of the planning models (matplotlib, written atomically)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pelvicnav.io.atomic import save_figure
from pelvicnav.pose.spm import PoseModel


def plot_spm_modes(model: PoseModel, path: str | os.PathLike, *, n_modes: int = 4) -> Path:
    """The first SPM modes at -3 and +3 standard deviations, like Han et al. (2020) figure 2.

    Each column is a mode; rows are the coronal (AP: x-z) and axial (x-y) projections of the mean
    shapes placed at the mean pose (grey), at -3 sd (yellow) and at +3 sd (green).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    k = min(n_modes, model.n_modes)
    fig, axes = plt.subplots(2, k, figsize=(3.6 * k, 7.2), squeeze=False)
    sub = slice(None, None, 5)  # a vertex subset keeps the scatter light
    for m in range(k):
        sd = np.sqrt(model.variances[m])
        for row, (a, b, label) in enumerate(((0, 2, "z (mm)"), (0, 1, "y (mm)"))):
            ax = axes[row, m]
            for weight, colour, alpha in (
                (0.0, "0.6", 0.25),
                (-3.0, "gold", 0.35),
                (3.0, "green", 0.35),
            ):
                w = np.zeros(model.n_modes)
                w[m] = weight * sd
                shapes = model.instance(w)
                pts = shapes[:, sub].reshape(-1, 3)
                ax.scatter(pts[:, a], pts[:, b], s=0.8, c=colour, alpha=alpha, linewidths=0)
            ax.set_aspect("equal")
            ax.set_xlabel("x (mm, patient left)")
            ax.set_ylabel(label)
            if row == 1:
                ax.invert_yaxis()  # anterior (negative y) up in the axial view
            if row == 0:
                share = model.variances[m] / model.variances.sum()
                ax.set_title(f"mode {m + 1} ({100 * share:.0f}% of variance)")
    fig.suptitle("Statistical pose model: mean (grey), -3 sd (yellow), +3 sd (green)")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    return path


def spm_modes_figure(population, path: str | os.PathLike, *, n_modes: int = 4) -> Path:
    """``pelvicnav study spm-modes``: fit the SPM on a population and plot its first modes."""
    return plot_spm_modes(PoseModel.fit(population.vertices), path, n_modes=n_modes)
