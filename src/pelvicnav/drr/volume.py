"""A voxel volume with its placement in the world: the one source of truth is ``world_from_ijk``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import transforms as tf

__all__ = ["Volume"]


@dataclass(frozen=True, eq=False)
class Volume:
    """Voxel data indexed ``data[i, j, k]`` with voxel centres at integer ``(i, j, k)``.

    Attributes
    ----------
    data : (ni, nj, nk) float32, or an integer type kept as it is
        Values per voxel, in any memory order (e.g. linear attenuation in 1/mm for DRRs, HU for
        CT). A CT stored as integers (int16 HU, as scanners write it) is not copied: a
        512 x 512 x 400 float32 copy took 0.9 s of ``pelvicnav register``.
    world_from_ijk : (4, 4) float64
        Affine from voxel indices to world (LPS mm). Spacing and orientation derive from it.
    """

    data: NDArray
    world_from_ijk: NDArray[np.float64]

    def __post_init__(self) -> None:
        d = np.asarray(self.data)  # any memory order (NIfTI reads as Fortran)
        if d.dtype.kind not in "iu":
            d = np.asarray(d, dtype=np.float32)
        if d.ndim != 3 or min(d.shape) < 1:
            raise ValueError(f"volume data must be a non-empty 3D array, got shape {d.shape}")
        if d.dtype.kind == "f" and not np.all(np.isfinite(d)):
            raise ValueError("volume data contains NaN or infinity")
        A = np.asarray(self.world_from_ijk, dtype=np.float64)
        if A.shape != (4, 4) or not np.all(np.isfinite(A)):
            raise ValueError(f"world_from_ijk must be a finite (4, 4) matrix, got {A.shape}")
        if abs(np.linalg.det(A[:3, :3])) < 1e-12 or np.any(A[3] != [0, 0, 0, 1]):
            raise ValueError("world_from_ijk must be an invertible affine (last row 0 0 0 1)")
        object.__setattr__(self, "data", d)
        object.__setattr__(self, "world_from_ijk", A)

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.data.shape  # type: ignore[return-value]

    @property
    def spacing(self) -> NDArray[np.float64]:
        """Voxel size along i, j, k (mm)."""
        return np.linalg.norm(self.world_from_ijk[:3, :3], axis=0)

    @property
    def ijk_from_world(self) -> NDArray[np.float64]:
        return np.linalg.inv(self.world_from_ijk)

    def world_points(self, ijk: ArrayLike) -> NDArray[np.float64]:
        """World positions (mm) of voxel coordinates ``(..., 3)``."""
        return tf.apply(self.world_from_ijk, np.asarray(ijk, dtype=np.float64))

    @classmethod
    def from_spacing(
        cls, data: ArrayLike, spacing: ArrayLike, origin: ArrayLike = (0.0, 0.0, 0.0)
    ) -> Volume:
        """Axis-aligned volume: voxel ``(0, 0, 0)`` centred at ``origin``, given spacing (mm)."""
        A = np.eye(4)
        A[:3, :3] = np.diag(np.asarray(spacing, dtype=np.float64))
        A[:3, 3] = origin
        return cls(np.asarray(data), A)
