"""Renderers behind one protocol: what the registration driver asks of a DRR generator.

A renderer holds the bodies (bones) of one CT and renders any subset of them at any pyramid level
for a batch of candidate poses. Two implementations:

* :class:`SplatRenderer` — attenuation point models splatted onto the detector
  (:func:`~pelvicnav.drr.splat.splat`), one model set per pyramid level; the fast path.
* :class:`RayCastRenderer` — trilinear ray casting through attenuation volumes
  (:func:`~pelvicnav.drr.projector.render`); the exact, slow reference.

The driver (:func:`pelvicnav.register.multibody.register`) sees only the protocol, so the
ray-cast reference is a choice of renderer, not a second driver.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.drr.projector import render
from pelvicnav.drr.splat import PointModel, splat, splat_pullback
from pelvicnav.drr.volume import Volume

__all__ = ["RayCastRenderer", "Renderer", "SplatRenderer"]


@runtime_checkable
class Renderer(Protocol):
    """DRRs of named rigid bodies at the levels of a pyramid.

    ``bones`` names the bodies; ``centroid``, ``mass`` and ``points`` describe each one in its CT
    frame (mm) at a level; ``resolution_mm`` is the blur of its DRRs at a level (the radiograph is
    blurred to match; 0 = exact); ``render`` draws a subset of bodies.
    """

    @property
    def bones(self) -> tuple[str, ...]: ...

    @property
    def n_levels(self) -> int: ...

    def centroid(self, bone: str, level: int = -1) -> NDArray[np.float64]: ...

    def mass(self, bone: str, level: int = -1) -> float: ...

    def points(self, bone: str, level: int = -1) -> NDArray[np.float64]: ...

    def resolution_mm(self, level: int) -> float: ...

    def render(
        self,
        level: int,
        bones: Sequence[str],
        poses: ArrayLike,
        projections: ArrayLike,
        shape: tuple[int, int],
    ) -> NDArray[np.float32]:
        """``poses`` (B, len(bones), 4, 4) ``world_from_ct``; ``projections`` (K, 3, 4) or
        (B, K, 3, 4) for a ``shape`` image; returns (B, K, rows, cols) line integrals."""
        ...


@dataclass(frozen=True, eq=False)
class SplatRenderer:
    """Point models per pyramid level (coarse to fine), each a dict bone -> PointModel."""

    models: tuple[Mapping[str, PointModel], ...]

    def __post_init__(self) -> None:
        models = tuple(self.models)
        if not models or any(set(m) != set(models[0]) for m in models):
            raise ValueError("a splat renderer needs the same bones at every level")
        object.__setattr__(self, "models", models)

    @property
    def bones(self) -> tuple[str, ...]:
        return tuple(self.models[0])

    @property
    def n_levels(self) -> int:
        return len(self.models)

    def centroid(self, bone: str, level: int = -1) -> NDArray[np.float64]:
        return self.models[level][bone].centroid

    def mass(self, bone: str, level: int = -1) -> float:
        return float(self.models[level][bone].mass.sum())

    def points(self, bone: str, level: int = -1) -> NDArray[np.float64]:
        return self.models[level][bone].points

    def resolution_mm(self, level: int) -> float:
        return max(m.spacing for m in self.models[level].values())

    def render(self, level, bones, poses, projections, shape):
        return splat([self.models[level][b] for b in bones], poses, projections, shape)

    def pullback(self, level, bones, poses, projections, image_gradients):
        """World force and torque on each of ``bones`` of a scalar of their DRR, from its image
        gradients (:func:`~pelvicnav.drr.splat.splat_pullback`); ``poses`` (L, 4, 4)."""
        return splat_pullback([self.models[level][b] for b in bones], poses, projections,
                              image_gradients)  # fmt: skip


@dataclass(frozen=True, eq=False)
class RayCastRenderer:
    """Attenuation volumes (1/mm) per body, ray cast at every level at ``step_mm`` (default half
    the smallest voxel spacing). The same volumes serve every level."""

    volumes: Mapping[str, Volume]
    levels: int = 1
    step_mm: float | None = None

    def __post_init__(self) -> None:
        if not self.volumes:
            raise ValueError("a ray-cast renderer needs at least one volume")
        if self.levels < 1:
            raise ValueError(f"levels must be >= 1, got {self.levels}")
        object.__setattr__(self, "volumes", dict(self.volumes))

    @property
    def bones(self) -> tuple[str, ...]:
        return tuple(self.volumes)

    @property
    def n_levels(self) -> int:
        return self.levels

    @cached_property
    def _samples(self) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """Each body's voxels with attenuation: (positions (n, 3) mm, attenuation (n,))."""
        out = {}
        for bone, v in self.volumes.items():
            ijk = np.argwhere(v.data > 0)
            if len(ijk) == 0:
                raise ValueError(f"the volume of {bone} has no attenuation")
            out[bone] = (v.world_points(ijk), np.asarray(v.data[tuple(ijk.T)], dtype=np.float64))
        return out

    def _voxels(self, bone: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self._samples[bone]

    def centroid(self, bone: str, level: int = -1) -> NDArray[np.float64]:
        pts, w = self._voxels(bone)
        return (w @ pts) / w.sum()

    def mass(self, bone: str, level: int = -1) -> float:
        v = self.volumes[bone]
        return float(
            np.sum(v.data, dtype=np.float64) * abs(np.linalg.det(v.world_from_ijk[:3, :3]))
        )

    def points(self, bone: str, level: int = -1) -> NDArray[np.float64]:
        return self._voxels(bone)[0]

    def resolution_mm(self, level: int) -> float:
        return 0.0

    def render(self, level, bones, poses, projections, shape):
        vols = [self.volumes[b] for b in bones]
        Ps = np.asarray(projections, dtype=np.float64)
        if Ps.ndim == 3:
            return render(vols, poses, Ps, shape, step_mm=self.step_mm)
        T = np.asarray(poses, dtype=np.float64)  # one geometry per candidate
        return np.concatenate([render(vols, T[b : b + 1], Ps[b], shape, step_mm=self.step_mm)
                               for b in range(len(T))])  # fmt: skip
