"""NIfTI volumes in pelvicnav's LPS world: ``world_from_ijk`` <-> the file's RAS affine.

NIfTI stores a RAS affine; pelvicnav works in LPS. The two differ by ``diag(-1, -1, 1)``:
``ras_from_ijk = diag(-1, -1, 1, 1) @ world_from_ijk``. Writes are atomic.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["LPS_TO_RAS", "read_nifti", "write_nifti"]

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def write_nifti(path: str | os.PathLike, data: ArrayLike, world_from_ijk: ArrayLike) -> Path:
    """Write a volume (``data[i, j, k]``) with its LPS ``world_from_ijk`` as NIfTI-1."""
    import nibabel as nib

    path = Path(path)
    A = np.asarray(world_from_ijk, dtype=np.float64)
    if A.shape != (4, 4):
        raise ValueError(f"world_from_ijk must be (4, 4), got {A.shape}")
    img = nib.Nifti1Image(np.asarray(data), LPS_TO_RAS @ A)
    img.set_qform(LPS_TO_RAS @ A, code=1)
    img.set_sform(LPS_TO_RAS @ A, code=1)
    suffix = ".nii.gz" if path.name.endswith(".nii.gz") else path.suffix
    tmp = path.with_name(path.name[: -len(suffix)] + ".part" + suffix)
    nib.save(img, tmp)
    os.replace(tmp, path)
    return path


def read_nifti(path: str | os.PathLike) -> tuple[NDArray, NDArray[np.float64]]:
    """Read ``(data, world_from_ijk)`` (LPS) from a NIfTI file.

    Raises
    ------
    ValueError
        Unreadable file or not a 3D volume, naming the file.
    """
    path = Path(path)
    try:
        if path.name.lower().endswith(".gz"):
            img = _load(path)
        else:
            import nibabel as nib

            img = nib.load(path)
        data = np.asarray(img.dataobj)
    except FileNotFoundError:
        raise ValueError(f"{path}: file not found") from None
    except Exception as err:  # nibabel raises several types for corrupt files
        raise ValueError(f"{path}: not a readable NIfTI file ({err})") from None
    if data.ndim != 3:
        raise ValueError(f"{path}: expected a 3D volume, got shape {data.shape}")
    return data, LPS_TO_RAS @ np.asarray(img.affine, dtype=np.float64)


def _load(path: Path):
    """A gzipped NIfTI, decompressed by ISA-L (``isal``): about 3x faster than zlib, which took
    1.3 s of ``pelvicnav register`` on a 512 x 512 x 400 int16 CT. nibabel is imported after
    the decompression, which releases the GIL: a thread reading another file imports it
    meanwhile."""
    from isal import igzip

    raw = igzip.decompress(path.read_bytes())
    import nibabel as nib

    sizes = (int.from_bytes(raw[:4], "little"), int.from_bytes(raw[:4], "big"))
    image_class = nib.Nifti2Image if 540 in sizes else nib.Nifti1Image
    return image_class.from_bytes(raw)
