"""Writing a CT volume as a DICOM series (CT Image Storage), one file per slice.

The inverse of :func:`pelvicnav.io.volume.read_volume` on a folder: slice ``k`` of ``data[i, j, k]``
becomes one image whose columns run along ``i`` and rows along ``j``; Image Orientation (Patient)
holds the unit ``i`` and ``j`` axes, Image Position (Patient) the centre of voxel ``(0, 0, k)``.
DICOM slices carry no order of their own, so a reader sorts them along the normal ``i x j``: a
volume whose ``k`` axis points against that normal reads back with ``k`` reversed (the same
voxels at the same world positions).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from pelvicnav.io.dicom_base import (
    CT_IMAGE_STORAGE,
    DicomIdentity,
    ds_number,
    new_dataset,
    save_dataset,
)

__all__ = ["write_ct_series"]


def write_ct_series(
    folder: str | os.PathLike,
    hu: ArrayLike,
    world_from_ijk: ArrayLike,
    *,
    identity: DicomIdentity | None = None,
    description: str = "pelvicnav CT",
) -> list[Path]:
    """Write a CT (HU) as a DICOM series into ``folder`` (created); returns the files.

    Voxels are stored as int16 with Rescale Slope 1 and Intercept 0 when they are integers in
    range, else scaled to int16 with a slope.

    Raises
    ------
    ValueError
        Data not 3D, non-finite values, or an affine whose axes are not orthogonal (DICOM slices
        are rectangular and stacked along their normal).
    """
    from pydicom.uid import generate_uid

    data = np.asarray(hu)
    A = np.asarray(world_from_ijk, dtype=np.float64)
    if data.ndim != 3 or min(data.shape) < 1:
        raise ValueError(f"expected a 3D volume, got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise ValueError("the CT contains NaN or infinity")
    spacing = np.linalg.norm(A[:3, :3], axis=0)
    axes = A[:3, :3] / spacing
    if not np.allclose(axes.T @ axes, np.eye(3), atol=1e-6):
        raise ValueError("a DICOM series needs orthogonal voxel axes; this affine is sheared")
    stored, slope, intercept = _to_int16(data)
    identity = (identity or DicomIdentity()).filled()
    series_uid = generate_uid()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for k in range(data.shape[2]):
        ds = new_dataset(CT_IMAGE_STORAGE, "CT", identity, series_uid)
        ds.SeriesDescription = description
        ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
        ds.PatientPosition = "HFS"
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [ds_number(x) for x in A[:3, 3] + k * A[:3, 2]]
        ds.ImageOrientationPatient = [ds_number(x) for x in (*axes[:, 0], *axes[:, 1])]
        ds.PixelSpacing = [ds_number(spacing[1]), ds_number(spacing[0])]
        ds.SliceThickness = ds_number(spacing[2])
        ds.Rows, ds.Columns = data.shape[1], data.shape[0]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleSlope, ds.RescaleIntercept = ds_number(slope), ds_number(intercept)
        ds.RescaleType = "HU"
        ds.PixelData = np.ascontiguousarray(stored[:, :, k].T).tobytes()
        files.append(save_dataset(ds, folder / f"ct_{k + 1:04d}.dcm"))
    return files


def _to_int16(data: np.ndarray) -> tuple[np.ndarray, float, float]:
    lo, hi = float(data.min()), float(data.max())
    if np.all(data == np.round(data)) and lo >= -32768 and hi <= 32767:
        return data.astype(np.int16), 1.0, 0.0
    intercept = (hi + lo) / 2
    slope = max((hi - lo) / 65534.0, 1e-6)
    return np.round((data - intercept) / slope).astype(np.int16), slope, intercept
