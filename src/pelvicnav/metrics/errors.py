"""Distances between two poses of one bone: at its centroid, or where it projects."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf

__all__ = ["pose_disagreement", "pose_distance"]


def pose_disagreement(
    T_a: NDArray,
    T_b: NDArray,
    points: ArrayLike,
    centroid: ArrayLike,
    projections: Sequence[NDArray],
    pixel_spacing: Sequence[tuple[float, float]],
) -> tuple[float, float]:
    """How far apart two poses (``world_from_ct``) of one bone are: (mm at ``centroid``, degrees).

    With one view, depth is not fixed by the image, so the distance is where the bone projects
    instead: the median distance of every 7th of its ``points`` (CT frame, mm) at the detector
    (mm; rotations show in it too) and 0 degrees.
    """
    if len(projections) == 1:
        pts = np.asarray(points, dtype=np.float64)[::7]
        P = projections[0]
        duv = pj.project(P, tf.apply(T_a, pts)) - pj.project(P, tf.apply(T_b, pts))
        dr, dc = pixel_spacing[0]
        return float(np.median(np.linalg.norm(duv * [dc, dr], axis=1))), 0.0
    return pose_distance(T_a, T_b, centroid)


def pose_distance(T_a: NDArray, T_b: NDArray, centroid: ArrayLike) -> tuple[float, float]:
    """Two poses (``world_from_ct``) of one bone: (mm between them at ``centroid`` (3,) CT mm,
    degrees of the rotation between them)."""
    c = np.asarray(centroid, dtype=np.float64)[None]
    D = T_b @ tf.invert(T_a)
    return (
        float(np.linalg.norm(tf.apply(T_a, c) - tf.apply(T_b, c))),
        float(np.rad2deg(np.linalg.norm(tf.rotvec_from_matrix(D[:3, :3])))),
    )
