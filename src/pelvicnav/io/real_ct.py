"""The real pelvic CTs with manual bone labels (FracSegNet test cases; ``shared/data/real-ct``).

Each case folder ``NNN`` holds the CT three times, each copy masked to one bone
(``NNN_{SA,LI,RI}.nii.gz``: sacrum, left and right innominate; 0 outside that bone), and each
bone's manual label (``NNN_*_mask.nii.gz``, fragments numbered 1, 2, ...). :func:`read_real_ct`
merges them into one CT (HU inside the bones, 0 elsewhere) and one label map in our scheme.
Liu Y. et al., MICCAI 2023, doi:10.1007/978-3-031-43996-4_30 (MIT licence).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pelvicnav import BONES

__all__ = ["REAL_CT_CASES", "RealCT", "default_real_ct_dir", "read_real_ct"]

REAL_CT_CASES = ("002", "004", "005")
_CODES = {"sacrum": "SA", "left_hip": "LI", "right_hip": "RI"}


@dataclass(frozen=True, eq=False)
class RealCT:
    """One real case: ``hu`` (float32, 0 outside the bones), ``labels`` (1 sacrum, 2 left hip,
    3 right hip), ``world_from_ijk`` (LPS mm) and its name."""

    name: str
    hu: NDArray[np.float32]
    labels: NDArray[np.uint8]
    world_from_ijk: NDArray[np.float64]


def default_real_ct_dir() -> Path | None:
    """``$PELVICNAV_REAL_CT``, else ``shared/data/real-ct/fracsegnet`` next to the checkout or
    its parent, if present."""
    env = os.environ.get("PELVICNAV_REAL_CT")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    for up in here.parents:
        candidate = up / "shared" / "data" / "real-ct" / "fracsegnet"
        if candidate.is_dir():
            return candidate
    return None


def read_real_ct(folder: str | os.PathLike) -> RealCT:
    """Merge a case folder's three masked CTs and labels into one CT and one label map.

    Raises
    ------
    ValueError
        A missing file, or files on different grids; the message names the file.
    """
    from pelvicnav.io.volume import read_volume

    folder = Path(folder)
    name = folder.name
    hu = labels = A = None
    for b, bone in enumerate(BONES):
        ct_path = folder / f"{name}_{_CODES[bone]}.nii.gz"
        mask_path = folder / f"{name}_{_CODES[bone]}_mask.nii.gz"
        for p in (ct_path, mask_path):
            if not p.exists():
                raise ValueError(f"{p}: file not found (a real-CT case needs {name}_SA/LI/RI)")
        data, A_ct = read_volume(ct_path)
        mask, A_mask = read_volume(mask_path)
        if hu is None:
            hu = np.zeros(data.shape, dtype=np.float32)
            labels = np.zeros(data.shape, dtype=np.uint8)
            A = A_ct
        for p, shape, affine in ((ct_path, data.shape, A_ct), (mask_path, mask.shape, A_mask)):
            if shape != hu.shape or not np.allclose(affine, A, atol=1e-3):
                raise ValueError(f"{p}: not on the grid of {name}_SA.nii.gz")
        inside = np.asarray(mask) > 0
        hu[inside] = np.asarray(data, dtype=np.float32)[inside]
        labels[inside & (labels == 0)] = b + 1
    return RealCT(name=name, hu=hu, labels=labels, world_from_ijk=np.asarray(A, dtype=np.float64))
