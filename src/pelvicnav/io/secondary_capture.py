"""Images for PACS: an RGB picture (an overlay) as a DICOM Secondary Capture.

The capture carries the patient and study of the radiograph it was made from (so PACS files it
with that study), references the radiograph's SOP instance when known, and says what it is in
Series Description and Derivation Description. RGB, 8 bits, uncompressed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from pelvicnav.io.dicom_base import (
    SECONDARY_CAPTURE_STORAGE,
    DicomIdentity,
    new_dataset,
    save_dataset,
)

__all__ = ["write_secondary_capture"]


def write_secondary_capture(
    path: str | os.PathLike,
    rgb: ArrayLike,
    *,
    identity: DicomIdentity | None = None,
    description: str = "pelvicnav overlay",
    source: tuple[str, str] | None = None,
) -> Path:
    """Write ``(rows, cols, 3)`` RGB (floats in [0, 1] or uint8) as a Secondary Capture image.

    Parameters
    ----------
    identity : DicomIdentity, optional
        The radiograph's patient and study (new identifiers when not given).
    source : (SOP Class UID, SOP Instance UID), optional
        The radiograph the picture derives from.

    Raises
    ------
    ValueError
        Not an RGB image.
    """
    from pydicom.dataset import Dataset
    from pydicom.uid import generate_uid

    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an RGB image (rows, cols, 3), got {img.shape}")
    if img.dtype != np.uint8:
        img = np.round(np.clip(img, 0.0, 1.0) * 255).astype(np.uint8)
    ds = new_dataset(SECONDARY_CAPTURE_STORAGE, "OT", (identity or DicomIdentity()).filled(),
                     generate_uid())  # fmt: skip
    ds.ConversionType = "WSD"
    ds.ImageType = ["DERIVED", "SECONDARY"]
    ds.SeriesDescription = description
    ds.DerivationDescription = description
    ds.InstanceNumber = 1
    ds.Rows, ds.Columns = img.shape[:2]
    ds.SamplesPerPixel, ds.PhotometricInterpretation, ds.PlanarConfiguration = 3, "RGB", 0
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 8, 8, 7, 0
    if source is not None and all(source):
        ref = Dataset()
        ref.ReferencedSOPClassUID, ref.ReferencedSOPInstanceUID = source
        ds.SourceImageSequence = [ref]
    ds.PixelData = np.ascontiguousarray(img).tobytes()
    return save_dataset(ds, path)
