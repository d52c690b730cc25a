"""What ``segment``, ``plan`` and ``register`` all read first: a CT and the label map of its bones.

The CT is read and checked for HU (:func:`pelvicnav.io.volume.read_ct`), the label map put on its
grid (:func:`pelvicnav.io.volume.read_labels`), mapped to our labels through its scheme and checked
to hold bone on the right sides (:func:`pelvicnav.shape.labels.check_bone_labels`).
"""

from __future__ import annotations

import os

import numpy as np
from numpy.typing import NDArray

__all__ = ["fit_bones", "read_ct_and_bones"]


def read_ct_and_bones(
    ct: str | os.PathLike,
    labels: str | os.PathLike,
    label_scheme: str = "ours",
    series: str | None = None,
) -> tuple[NDArray, NDArray[np.float64], NDArray, NDArray]:
    """``(hu, world_from_ijk, raw_labels, ours)``; ValueError naming the file on bad input."""
    from pelvicnav.io.volume import read_ct, read_labels
    from pelvicnav.shape.labels import check_bone_labels, parse_scheme, to_bone_labels

    scheme = parse_scheme(label_scheme)
    hu, A = read_ct(ct, series=series)
    raw = read_labels(labels, hu.shape, A)
    ours = to_bone_labels(raw, scheme)
    check_bone_labels(hu, ours, A, source=str(labels), raw_labels=raw)
    return hu, A, raw, ours


def fit_bones(ours: NDArray, world_from_ijk: NDArray, model) -> dict:
    """The pelvis model fitted to a label map (:func:`pelvicnav.shape.fit.fit_labels`), started
    from the population's mean pelvis; bone -> LabelFit."""
    from pelvicnav.geometry import transforms as tf
    from pelvicnav.shape.fit import fit_labels

    pop = model.population
    reference = tf.apply(pop.poses_from_vector(pop.mean), pop.mean_shapes)
    return fit_labels(ours, world_from_ijk, model.shapes, model.faces, reference)
