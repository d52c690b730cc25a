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
        loaded = _read_gz_unscaled(path) if path.name.lower().endswith(".gz") else None
        if loaded is None:
            img = _load(path)
            loaded = np.asarray(img.dataobj), img.affine
        data, affine = loaded
    except FileNotFoundError:
        raise ValueError(f"{path}: file not found") from None
    except Exception as err:  # nibabel raises several types for corrupt files
        raise ValueError(f"{path}: not a readable NIfTI file ({err})") from None
    if data.ndim != 3:
        raise ValueError(f"{path}: expected a 3D volume, got shape {data.shape}")
    return data, LPS_TO_RAS @ np.asarray(affine, dtype=np.float64)


# The NIfTI-1 header fields the fast path reads: (name, numpy type, byte offset), the standard's
# layout (nifti1.h); the whole header is 348 bytes.
_NIFTI1_FIELDS = (
    ("sizeof_hdr", "i4", 0), ("dim", ("i2", 8), 40), ("datatype", "i2", 70),
    ("vox_offset", "f4", 108), ("scl_slope", "f4", 112), ("scl_inter", "f4", 116),
    ("sform_code", "i2", 254), ("srow", ("f4", 12), 280), ("magic", "S4", 344),
)  # fmt: skip
# NIfTI datatype code -> numpy type (the plain numeric ones; anything else goes to nibabel)
_NIFTI_TYPES = {2: "u1", 4: "i2", 8: "i4", 16: "f4", 64: "f8", 256: "i1", 512: "u2", 768: "u4",
                1024: "i8", 1280: "u8"}  # fmt: skip


def _read_gz_unscaled(path: Path) -> tuple[NDArray, NDArray] | None:
    """``(data, ras_affine)`` of a gzipped NIfTI-1 file, decompressed straight into its array.

    ISA-L (``isal``) inflates the file into one buffer of the size its gzip trailer states: no
    copy from a decompressed string into an array (0.34 s instead of 0.7 s for a 512 x 512 x 400
    int16 CT). Its C reader, fed 16 MiB at a time, holds the GIL only between those reads, so
    another thread imports or computes meanwhile (``IGzipFile`` reads 512 KiB at a time, and
    waiting for the GIL after each made the same read 2 s beside a busy thread).

    Only the plain case is read here, without nibabel (whose import, pydicom with it, held the
    GIL for 0.2 s of ``pelvicnav register``): one gzip member under 4 GiB, a NIfTI-1 header with
    an sform (what nibabel then takes as the affine), a plain numeric type, no scaling. ``None``
    otherwise: the caller reads the file through nibabel (``tests/io/test_nifti.py`` checks
    both against nibabel)."""
    try:
        from isal.isal_zlib import _GzipReader  # C, documented in isal.igzip; pinned version
    except ImportError:
        return None
    with open(path, "rb") as fh:
        packed = fh.seek(-4, os.SEEK_END) + 4
        size = int.from_bytes(fh.read(4), "little")  # ISIZE: length mod 2**32
        fh.seek(0)
        if not 352 <= size <= 1032 * packed:  # deflate inflates at most 1032:1
            return None
        buf = np.empty(size, dtype=np.uint8)
        reader = _GzipReader(fh, 1 << 24)
        view, got = memoryview(buf), 0
        while got < size and (n := reader.readinto(view[got:])):
            got += n
        if got != size or reader.read(1):
            return None  # shorter or longer than the trailer says
    layout = _plain_nifti1(buf)
    if layout is None:
        return None
    shape, dtype, offset, affine = layout
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if offset + nbytes > size:
        return None
    return buf[offset : offset + nbytes].view(dtype).reshape(shape, order="F"), affine


def _plain_nifti1(buf: NDArray[np.uint8]):
    """``(shape, dtype, data offset, ras_affine)`` from a NIfTI-1 header at the start of
    ``buf``, or None when it is not the plain case :func:`_read_gz_unscaled` reads."""
    for order in "<>":
        names, formats, offsets = zip(*_NIFTI1_FIELDS, strict=True)
        dt = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                       "itemsize": 348}).newbyteorder(order)  # fmt: skip
        h = buf[:348].view(dt)[0]
        if h["sizeof_hdr"] == 348:
            break
    else:
        return None  # NIfTI-2 (540) or not NIfTI
    ndim = int(h["dim"][0])
    shape = tuple(int(n) for n in h["dim"][1 : ndim + 1])
    code = int(h["datatype"])
    slope, inter = float(h["scl_slope"]), float(h["scl_inter"])
    scaled = (slope not in (0.0, 1.0) and np.isfinite(slope)) or (inter != 0 and np.isfinite(inter))
    offset = float(h["vox_offset"])
    plain = h["magic"] == b"n+1" and 1 <= ndim <= 7 and min(shape) >= 1 and h["sform_code"] > 0
    if not plain or code not in _NIFTI_TYPES or scaled or offset != int(offset) or offset < 352:
        return None
    dtype = np.dtype(_NIFTI_TYPES[code]).newbyteorder(order)
    if int(offset) % dtype.itemsize:
        return None
    affine = np.eye(4)
    affine[:3] = np.asarray(h["srow"], dtype=np.float64).reshape(3, 4)
    return shape, dtype, int(offset), affine


def _load(path: Path):
    """A NIfTI image through nibabel; a gzipped one decompressed by ISA-L (``isal``, about 3x
    faster than zlib) before nibabel is imported (the decompression releases the GIL)."""
    if not path.name.lower().endswith(".gz"):
        import nibabel as nib

        return nib.load(path)
    from isal import igzip

    raw = igzip.decompress(path.read_bytes())
    import nibabel as nib

    sizes = (int.from_bytes(raw[:4], "little"), int.from_bytes(raw[:4], "big"))
    image_class = nib.Nifti2Image if 540 in sizes else nib.Nifti1Image
    return image_class.from_bytes(raw)
