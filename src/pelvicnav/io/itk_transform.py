"""Poses as ITK transform files (``.tfm``) that SimpleITK, ITK and 3D Slicer read.

Convention (stated once, tested in ``tests/io/test_itk_transform.py``). ITK stores a transform in
the *resampling* direction: it maps points of the fixed space to the moving space. pelvicnav's
fixed space is the intraoperative world (LPS mm) and the moving space the preoperative CT, so the
file of a bone whose pose is ``world_from_ct`` holds ``ct_from_world = inv(world_from_ct)``::

    sitk.ReadTransform("sacrum.tfm").TransformPoint(x_world)  == ct_from_world @ x_world
    sitk.ReadTransform("sacrum.tfm").GetInverse().TransformPoint(x_ct) == world_from_ct @ x_ct

With it, SimpleITK resamples the CT into the registered pose as is (``sitk.Resample(ct, ...,
transform)``), and 3D Slicer, which reads ITK files as "from parent" transforms, moves a CT-frame
mesh or volume placed under the transform to where the registration found the bone. Files are
written by SimpleITK as ``AffineTransform_double_3_3`` (LPS; centre zero), atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["read_pose_tfm", "write_pose_tfm", "write_pose_transforms"]


def write_pose_tfm(path: str | os.PathLike, world_from_ct: ArrayLike) -> Path:
    """Write a pose (4x4 ``world_from_ct``, rigid or similarity) as an ITK ``.tfm`` file.

    Raises
    ------
    ValueError
        Not a finite, invertible 4x4 affine.
    """
    import SimpleITK as sitk

    T = np.asarray(world_from_ct, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or np.any(T[3] != [0, 0, 0, 1]):
        raise ValueError(f"a pose must be a finite 4 x 4 affine, got {T.shape}")
    if abs(np.linalg.det(T[:3, :3])) < 1e-12:
        raise ValueError("the pose is singular")
    inv = np.linalg.inv(T)
    tx = sitk.AffineTransform(3)
    tx.SetMatrix(tuple(inv[:3, :3].reshape(-1)))
    tx.SetTranslation(tuple(inv[:3, 3]))
    path = Path(path)
    tmp = path.with_name(path.stem + ".part" + path.suffix)
    sitk.WriteTransform(tx, str(tmp))
    os.replace(tmp, path)
    return path


def read_pose_tfm(path: str | os.PathLike) -> NDArray[np.float64]:
    """Read a ``.tfm`` written in this module's convention back as ``world_from_ct`` (4x4).

    Raises
    ------
    ValueError
        Unreadable file, or not a 3D affine (matrix and offset) transform; names the file.
    """
    import SimpleITK as sitk

    try:
        tx = sitk.ReadTransform(str(path))
    except RuntimeError as err:
        raise ValueError(f"{path}: not a readable ITK transform file ({err})") from None
    if tx.GetDimension() != 3:
        raise ValueError(f"{path}: expected a 3D transform")
    try:
        affine = sitk.AffineTransform(tx.Downcast() if hasattr(tx, "Downcast") else tx)
    except (RuntimeError, TypeError):
        raise ValueError(f"{path}: not an affine (matrix and offset) transform") from None
    M = np.eye(4)
    M[:3, :3] = np.asarray(affine.GetMatrix()).reshape(3, 3)
    centre = np.asarray(affine.GetCenter())
    M[:3, 3] = np.asarray(affine.GetTranslation()) + centre - M[:3, :3] @ centre
    return np.linalg.inv(M)


def write_pose_transforms(
    folder: str | os.PathLike,
    poses: dict[str, ArrayLike],
    *,
    residual: ArrayLike | None = None,
) -> list[Path]:
    """Write ``folder/{bone}.tfm`` for every pose and ``folder/residual.tfm`` when given.

    ``residual`` is the world-frame ``T_res`` of :mod:`pelvicnav.guide.residual` (it moves the
    dislocated bone from where it is to its target): its file, read by Slicer, moves the
    registered bone onto the target.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = [write_pose_tfm(folder / f"{bone}.tfm", T) for bone, T in poses.items()]
    if residual is not None:
        written.append(write_pose_tfm(folder / "residual.tfm", residual))
    return written
