"""What a command derives from a CT and its label map, kept for the next command on the same files.

``pelvicnav register`` (and every frame of a guidance run, and ``--init`` tracking) reads the same
CT and labels again and again: decompressing, checking and sampling a 512 x 512 x 400 CT takes
2-3 s, several times a registered frame. The first command stores the bone models of every pyramid
level, the CT's fingerprint and each bone's centroid; a later one whose CT and label files are
byte for byte the same (a BLAKE2 digest of their bytes, 0.1 s for a 52 MB CT), read with the same
label scheme, series and levels by the same pelvicnav, loads them instead (0.05 s). Everything
that was checked when they were stored (HU, bones that are bone, on their sides) holds for the same
bytes.

Where: ``$PELVICNAV_CACHE`` (``0`` or ``off``: no cache), else ``$XDG_CACHE_HOME/pelvicnav`` or
``~/.cache/pelvicnav``. A cache that cannot be written or read is skipped (the command then reads
the files as without one); entries are written atomically and never trusted on a format or
version mismatch.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

import pelvicnav
from pelvicnav.drr.renderer import SplatRenderer
from pelvicnav.drr.splat import PointModel
from pelvicnav.io.atomic import write_bytes

__all__ = ["CachedBones", "cache_dir", "cache_key", "cacheable", "files_digest", "load", "store"]

FORMAT = 1
_CHUNK = 1 << 24


@dataclass(frozen=True, eq=False)
class CachedBones:
    """A CT's bone models and what the commands need besides them.

    Attributes
    ----------
    models : SplatRenderer
        The bone point models of every pyramid level.
    fingerprint : dict
        :func:`~pelvicnav.workflow.register.ct_fingerprint` of the CT.
    centroids : dict bone -> (3,) float64
        Each bone's label centroid (world mm).
    voxel_digest : str, optional
        :func:`pelvicnav.io.plan.fingerprint` of the CT (what a plan records of its CT), where a
        command asked for it.
    """

    models: SplatRenderer
    fingerprint: dict
    centroids: dict[str, NDArray[np.float64]]
    voxel_digest: str | None = None


def cache_dir() -> Path | None:
    """The cache folder, or None when switched off (``PELVICNAV_CACHE=0``)."""
    env = os.environ.get("PELVICNAV_CACHE")
    if env is not None:
        return None if env.strip().lower() in ("", "0", "off", "no") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "pelvicnav"


# Files that hold a whole volume (a .mhd or .nhdr header's voxels are in another file); a DICOM
# series is taken as its whole folder.
_SELF_CONTAINED = (".nii", ".nii.gz", ".nrrd", ".mha")


def cacheable(path: str | os.PathLike) -> bool:
    """Whether the bytes of ``path`` are the whole volume: a DICOM folder or a self-contained
    volume file (a single DICOM file reads its whole series, a header its data file: no)."""
    p = Path(path)
    return p.is_dir() or (p.is_file() and p.name.lower().endswith(_SELF_CONTAINED))


def _digest_into(h, path: Path) -> None:
    """The bytes of ``path`` (a file, or every file of a folder in name order) into ``h``."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        h.update(str(f.relative_to(path) if path.is_dir() else f.name).encode())
        with open(f, "rb") as fh:
            while chunk := fh.read(_CHUNK):
                h.update(chunk)


def files_digest(ct: str | os.PathLike, labels: str | os.PathLike) -> str:
    """A digest of the CT and label files' bytes (the slow part of a key: run it in a thread,
    hashing releases the GIL)."""
    h = hashlib.blake2b(digest_size=20)
    for path in (ct, labels):
        _digest_into(h, Path(path))
    return h.hexdigest()


def cache_key(digest: str, **options) -> str:
    """The key of files with :func:`files_digest` ``digest`` read with ``options`` (scheme,
    series, levels...) by this pelvicnav."""
    h = hashlib.blake2b(digest_size=20)
    meta = {"format": FORMAT, "version": pelvicnav.__version__, **options}
    h.update(json.dumps(meta, sort_keys=True, default=str).encode())
    h.update(digest.encode())
    return h.hexdigest()


def _entry(key: str) -> Path | None:
    """The file of the entry under ``key``, or None without a cache."""
    folder = cache_dir()
    return None if folder is None else folder / f"bones-{key}.npz"


def _stored(key: str) -> Path | None:
    """The file of the entry under ``key`` when it is there, else None."""
    path = _entry(key)
    return path if path is not None and path.is_file() else None


def stored(key: str) -> bool:
    """Whether an entry is stored under ``key`` (:func:`load` may still refuse it): a cheap look
    before reading."""
    return _stored(key) is not None


def load(key: str) -> CachedBones | None:
    """The entry stored under ``key``, or None (no cache, no entry, or an unreadable one)."""
    path = _stored(key)
    if path is None:
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta.get("format") != FORMAT or meta.get("key") != key:
                return None
            levels = tuple(
                {b: PointModel(z[f"points_{lv}_{b}"], z[f"mass_{lv}_{b}"], s)
                 for b, s in spacing.items()}
                for lv, spacing in enumerate(meta["spacing"])
            )  # fmt: skip
            centroids = {b: np.asarray(c, dtype=np.float64) for b, c in meta["centroids"].items()}
            return CachedBones(SplatRenderer(levels), meta["fingerprint"], centroids,
                               meta.get("voxel_digest"))  # fmt: skip
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile):
        return None  # a damaged entry is rebuilt, never trusted


def store(key: str, entry: CachedBones) -> None:
    """Write ``entry`` under ``key`` (atomically); a cache that cannot be written is skipped."""
    path = _entry(key)
    if path is None:
        return
    arrays, spacing = {}, []
    for lv, models in enumerate(entry.models.models):
        spacing.append({b: m.spacing for b, m in models.items()})
        for b, m in models.items():
            arrays[f"points_{lv}_{b}"] = m.points
            arrays[f"mass_{lv}_{b}"] = m.mass
    centroids = {b: np.asarray(c).tolist() for b, c in entry.centroids.items()}
    meta = {"format": FORMAT, "key": key, "spacing": spacing, "fingerprint": entry.fingerprint,
            "centroids": centroids, "voxel_digest": entry.voxel_digest}  # fmt: skip
    buffer = io.BytesIO()
    np.savez(buffer, meta=np.array(json.dumps(meta)), **arrays)
    try:  # two workers may store the same CT at once: write_bytes names its temporary uniquely
        path.parent.mkdir(parents=True, exist_ok=True)
        write_bytes(path, buffer.getvalue())
    except OSError:
        pass  # a cache that cannot be written is skipped
