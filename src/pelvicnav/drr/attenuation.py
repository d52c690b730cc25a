"""CT numbers to linear attenuation, and per-bone attenuation models from a CT and its labels."""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav import LABELS
from pelvicnav.drr.splat import PointModel, model_from_block_sums, point_model
from pelvicnav.drr.volume import Volume

__all__ = ["MU_WATER_PER_MM", "bone_models", "bone_point_models", "bone_volumes", "mu_from_hu",
           "sample_factors", "sample_volumes"]  # fmt: skip

MU_WATER_PER_MM = 0.02059  # water at 60 keV: 0.2059 cm^-1 (NIST XCOM, with coherent)


def mu_from_hu(hu: ArrayLike, *, mu_water: float = MU_WATER_PER_MM) -> NDArray[np.float32]:
    """Linear attenuation (1/mm) from Hounsfield units; air and below map to 0."""
    return (mu_water * np.maximum(0.0, 1.0 + np.asarray(hu, dtype=np.float64) / 1000.0)).astype(
        np.float32
    )


def sample_factors(spacing: ArrayLike, target_mm: float) -> tuple[int, int, int]:
    """Integer block sizes that bring voxel ``spacing`` (mm) closest to ``target_mm``."""
    s = np.asarray(spacing, dtype=np.float64)
    return tuple(int(max(1, round(target_mm / x))) for x in s)  # type: ignore[return-value]


def bone_volumes(
    ct_hu: Volume, labels: ArrayLike, *, label_values: Mapping[str, int] = LABELS
) -> dict[str, Volume]:
    """Each bone's attenuation (1/mm) on its bounding box of the CT grid, zero outside its label.

    One pass over the label map finds every bone's box (:func:`pelvicnav.io.volume.label_boxes`);
    the HU -> mu conversion then touches the boxes only (the bones fill a few % of a clinical CT).

    Raises
    ------
    ValueError
        A label map whose shape differs from the CT, or a bone with no voxel.
    """
    lab = np.asarray(labels)
    out = {}
    for bone, value, box, world_from_box in _bone_boxes(ct_hu, lab, label_values):
        mu = np.where(lab[box] == value, mu_from_hu(ct_hu.data[box]), np.float32(0.0))
        out[bone] = Volume(mu, world_from_box)
    return out


def _bone_boxes(ct_hu: Volume, lab: NDArray, label_values: Mapping[str, int]):
    """Per bone ``(bone, value, box, world_from_box)``: its label's bounding box on the CT grid
    (one pass over the label map, :func:`pelvicnav.io.volume.label_boxes`) and the box's grid.

    Raises
    ------
    ValueError
        A label map whose shape differs from the CT, or a bone with no voxel.
    """
    from pelvicnav.io.volume import label_boxes

    if lab.shape != ct_hu.shape:
        raise ValueError(f"label map shape {lab.shape} differs from the CT's {ct_hu.shape}")
    boxes = label_boxes(lab, [v for v in label_values.values() if v != 0])
    found = []
    for bone, value in label_values.items():
        box = boxes.get(value)
        if box is None:
            raise ValueError(f"the label map has no voxel of {bone} (label {value})")
        world_from_box = ct_hu.world_from_ijk.copy()
        world_from_box[:3, 3] += ct_hu.world_from_ijk[:3, :3] @ [s.start for s in box]
        found.append((bone, value, box, world_from_box))
    return found


def bone_models(
    ct_hu: Volume,
    labels: ArrayLike,
    *,
    label_values: Mapping[str, int] = LABELS,
    sample_mm: float = 1.0,
) -> dict[str, PointModel]:
    """One attenuation model per bone: the CT's mu inside the bone's label, block-summed.

    Parameters
    ----------
    ct_hu : Volume
        CT in HU (the preoperative CT; its frame is each bone's ``ct`` frame).
    labels : (ni, nj, nk) int
        Label map on the CT grid.
    label_values : bone name -> label value (default 1 sacrum, 2 left, 3 right innominate)
    sample_mm : float
        Target sample spacing (e.g. half the pyramid level's binning factor, in mm).

    Raises
    ------
    ValueError
        A label map whose shape differs from the CT, or a bone with no voxel.
    """
    return sample_volumes(bone_volumes(ct_hu, labels, label_values=label_values), sample_mm)


def sample_volumes(volumes: Mapping[str, Volume], sample_mm: float) -> dict[str, PointModel]:
    """Point models of attenuation volumes (:func:`bone_volumes`) at about ``sample_mm``."""
    return {b: point_model(v, sample_factors(v.spacing, sample_mm)) for b, v in volumes.items()}


def bone_point_models(
    ct_hu: Volume,
    labels: ArrayLike,
    sample_mm: Sequence[float],
    *,
    label_values: Mapping[str, int] = LABELS,
) -> tuple[dict[str, PointModel], ...]:
    """Each bone's point model at every spacing of ``sample_mm``, straight from HU and labels.

    The models of ``sample_volumes(bone_volumes(ct_hu, labels), mm)`` for each ``mm``
    (bitwise), in one compiled pass over each bone's box that converts HU to attenuation on the
    fly and fills every spacing's block sums at once: no attenuation volume is made. On a
    512 x 512 x 400 CT at 0.8 mm, two spacings: 0.33 s against 0.65-0.89 s.

    Raises
    ------
    ValueError
        A label map whose shape differs from the CT, or a bone with no voxel.
    """
    lab = np.asarray(labels)
    factors = np.array([sample_factors(ct_hu.spacing, mm) for mm in sample_mm], dtype=np.int64)
    out: tuple[dict[str, PointModel], ...] = tuple({} for _ in sample_mm)
    for bone, value, box, world_from_box in _bone_boxes(ct_hu, lab, label_values):
        extent = np.array([s.stop - s.start for s in box])
        dims = -(-extent[None] // factors)  # blocks per axis at each spacing (ceil)
        sizes = 4 * dims.prod(axis=1)
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        sums = np.zeros(int(sizes.sum()))
        _compile_bone_blocks()(ct_hu.data[box], lab[box], value, MU_WATER_PER_MM, factors, dims,
                               offsets, sums)  # fmt: skip
        for level, models in enumerate(out):
            block = sums[offsets[level] : offsets[level] + sizes[level]].reshape(4, *dims[level])
            models[bone] = model_from_block_sums(block, world_from_box, factors[level])
    return out


@functools.cache  # compile once per process, on first use
def _compile_bone_blocks():  # pragma: no cover - compiled code
    import numba as nb

    @nb.njit(cache=True)
    def kernel(hu, lab, value, mu_water, factors, dims, offsets, sums):
        """Per spacing l, per block: the attenuation of the ``value`` voxels (float32 as
        :func:`mu_from_hu` makes it) and its voxel-index first moments, at ``sums[offsets[l]:]``
        laid out (4, bi, bj, bk); voxels in (i, j, k) order as :func:`point_model` sums them."""
        ni, nj, nk = lab.shape
        for i in range(ni):
            for j in range(nj):
                for k in range(nk):
                    if lab[i, j, k] != value:
                        continue
                    mu = mu_water * max(0.0, 1.0 + np.float64(hu[i, j, k]) / 1000.0)
                    v = np.float64(np.float32(mu))
                    if v == 0.0:
                        continue
                    for level in range(factors.shape[0]):
                        d1, d2 = dims[level, 1], dims[level, 2]
                        n = dims[level, 0] * d1 * d2
                        bi = i // factors[level, 0]
                        bj = j // factors[level, 1]
                        q = offsets[level] + (bi * d1 + bj) * d2 + k // factors[level, 2]
                        sums[q] += v
                        sums[q + n] += v * i
                        sums[q + 2 * n] += v * j
                        sums[q + 3 * n] += v * k

    return kernel
