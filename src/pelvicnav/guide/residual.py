"""The residual reduction: how far the dislocated bone still is from its planned target.

Han et al. (2020), section 2.2.2: ``T_res = T_3D2D,O @ T_target @ inv(T_3D2D,X)``, where
``T_3D2D,O`` and ``T_3D2D,X`` are the registered ``world_from_ct`` poses of an observed
(undislocated) bone and of the dislocated bone, and ``T_target`` the planned correction of the
dislocated bone in the preoperative CT frame (``target_from_current``). ``T_res`` moves the bone
from where it is now to where the plan wants it, in the intraoperative world.

Reported in anatomical terms: the displacement of the bone's centroid and the rotation about it,
along the patient's axes (the preoperative CT's LPS axes carried by the observed bone), so "2 mm
left, 3 mm superior" stays true however the patient lies under the C-arm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import transforms as tf

__all__ = ["Residual", "residual_reduction"]

_AXES = (("right", "left"), ("anterior", "posterior"), ("inferior", "superior"))


@dataclass(frozen=True)
class Residual:
    """Residual reduction of one bone.

    Attributes
    ----------
    transform : (4, 4) float64
        ``T_res`` in the world frame.
    translation_mm : (3,) float64
        Centroid displacement still needed, patient axes (x left, y posterior, z superior).
    rotation_deg : (3,) float64
        Rotation still needed about the centroid, as a rotation vector in degrees, patient axes.
    """

    transform: NDArray[np.float64]
    translation_mm: NDArray[np.float64]
    rotation_deg: NDArray[np.float64]

    @property
    def distance_mm(self) -> float:
        return float(np.linalg.norm(self.translation_mm))

    @property
    def angle_deg(self) -> float:
        return float(np.linalg.norm(self.rotation_deg))

    def to_json(self) -> dict:
        """The residual as ``result.json`` and ``plan.json`` record it."""
        return {
            "translation_mm": self.translation_mm.tolist(),
            "rotation_deg": self.rotation_deg.tolist(),
            "distance_mm": self.distance_mm,
            "angle_deg": self.angle_deg,
            "description": self.describe(),
            "world_transform": np.asarray(self.transform).tolist(),
        }

    def describe(self) -> str:
        """A sentence for the surgeon, e.g. ``move 4.0 mm left, 1.5 mm superior; rotate ...``."""
        moves = [
            f"{abs(v):.1f} mm {names[int(v > 0)]}"
            for v, names in zip(self.translation_mm, _AXES, strict=True)
            if abs(v) >= 0.05
        ]
        turns = [
            f"{abs(v):.1f} deg about the {axis} axis ({'+' if v > 0 else '-'})"
            for v, axis in zip(
                self.rotation_deg, ("left-right", "anterior-posterior", "superior-inferior"),
                strict=True,
            )
            if abs(v) >= 0.05
        ]  # fmt: skip
        if not moves and not turns:
            return "reduced: no residual motion"
        parts = []
        if moves:
            parts.append("move " + ", ".join(moves))
        if turns:
            parts.append("rotate " + ", ".join(turns))
        return "; ".join(parts)


def residual_reduction(
    observed_pose: ArrayLike,
    dislocated_pose: ArrayLike,
    target_from_current: ArrayLike,
    centroid_ct: ArrayLike,
) -> Residual:
    """``T_res = T_O @ T_target @ inv(T_X)`` and its anatomical reading.

    Parameters
    ----------
    observed_pose : (4, 4) float
        Registered ``world_from_ct`` of an undislocated bone (e.g. the sacrum).
    dislocated_pose : (4, 4) float
        Registered ``world_from_ct`` of the dislocated bone.
    target_from_current : (4, 4) float
        The plan: the rigid correction of the dislocated bone in the preoperative CT frame.
    centroid_ct : (3,) float, mm
        The dislocated bone's centroid in the preoperative CT.

    Raises
    ------
    ValueError
        If any pose is not a finite rigid transform.
    """
    T_O = np.asarray(observed_pose, dtype=np.float64)
    T_X = np.asarray(dislocated_pose, dtype=np.float64)
    T_t = np.asarray(target_from_current, dtype=np.float64)
    for name, T in (("observed pose", T_O), ("dislocated pose", T_X), ("target", T_t)):
        try:
            tf.se3_log(T)
        except ValueError as err:
            raise ValueError(f"{name}: {err}") from None
    T_res = T_O @ T_t @ tf.invert(T_X)
    c = np.asarray(centroid_ct, dtype=np.float64)
    c_now = tf.apply(T_X, c[None])[0]
    c_target = tf.apply(T_res, c_now[None])[0]
    patient_from_world = T_O[:3, :3].T  # the patient's (CT) axes as carried by the observed bone
    rotvec_world = tf.rotvec_from_matrix(T_res[:3, :3])
    return Residual(
        transform=T_res,
        translation_mm=patient_from_world @ (c_target - c_now),
        rotation_deg=np.degrees(patient_from_world @ rotvec_world),
    )
