"""The view-set file ``views.json``: radiographs with their projection geometry.

Format (see docs/conventions.md)::

    {"views": [{"name": "ap", "image": "ap.npy", "projection_matrix": [[...], [...], [...]],
                "pixel_spacing_mm": [dr, dc], "source_mm": [x, y, z],
                "rows": 512, "cols": 512, "dose_ugy": 5.0}],
     "degrees_of_freedom": 6}

Images are ``(rows, cols)`` float32 arrays of line integrals stored as ``.npy`` beside the JSON.
Writing is atomic (temporary names, then rename); reading validates everything and names the file.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pelvicnav.io.jsonfile import read_json

__all__ = ["View", "read_views", "write_views"]


@dataclass(frozen=True, eq=False)
class View:
    """One radiograph and its geometry.

    Attributes
    ----------
    name : str
    image : (rows, cols) float32
        Line integrals (log-transformed intensities).
    projection_matrix : (3, 4) float64
        World (LPS mm) to pixels, see :mod:`pelvicnav.geometry.projection`.
    pixel_spacing : (2,) float, mm
    meta : dict
        Extra JSON-serialisable fields (dose, angles...).
    """

    name: str
    image: NDArray[np.float32]
    projection_matrix: NDArray[np.float64]
    pixel_spacing: tuple[float, float]
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        img = np.asarray(self.image, dtype=np.float32)
        if img.ndim != 2:
            raise ValueError(f"view {self.name!r}: image must be 2D, got shape {img.shape}")
        if not np.all(np.isfinite(img)):
            raise ValueError(f"view {self.name!r}: image contains NaN or infinity")
        P = np.asarray(self.projection_matrix, dtype=np.float64)
        if P.shape != (3, 4) or not np.all(np.isfinite(P)):
            raise ValueError(f"view {self.name!r}: projection matrix must be a finite 3 x 4 array")
        sv = np.linalg.svd(P[:, :3], compute_uv=False)
        if sv[-1] <= 1e-12 * max(sv[0], 1e-300):
            raise ValueError(f"view {self.name!r}: projection matrix is singular (no source)")
        ps = tuple(float(x) for x in np.asarray(self.pixel_spacing).reshape(-1))
        if len(ps) != 2 or min(ps) <= 0:
            raise ValueError(f"view {self.name!r}: pixel spacing must be 2 positive numbers")
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "projection_matrix", P)
        object.__setattr__(self, "pixel_spacing", ps)

    @property
    def source(self) -> NDArray[np.float64]:
        """X-ray source position (mm): the projection centre ``-M^-1 p4``."""
        P = self.projection_matrix
        return -np.linalg.solve(P[:, :3], P[:, 3])


def write_views(
    directory: str | os.PathLike,
    views: list[View],
    *,
    degrees_of_freedom: int = 6,
    filename: str = "views.json",
) -> Path:
    """Write ``filename`` (``views.json``) and one ``<name>.npy`` per view into ``directory``;
    returns the JSON's path."""
    if degrees_of_freedom not in (6, 9):
        raise ValueError(f"degrees_of_freedom must be 6 or 9, got {degrees_of_freedom}")
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        raise ValueError(f"view names must be unique, got {names}")
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    entries = []
    for v in views:
        fname = f"{v.name}.npy"
        tmp = d / (fname + ".part")
        with open(tmp, "wb") as fh:
            np.save(fh, v.image)
        os.replace(tmp, d / fname)
        entries.append(
            {
                "name": v.name,
                "image": fname,
                "projection_matrix": v.projection_matrix.tolist(),
                "pixel_spacing_mm": list(v.pixel_spacing),
                "source_mm": v.source.tolist(),
                "rows": int(v.image.shape[0]),
                "cols": int(v.image.shape[1]),
                **v.meta,
            }
        )
    path = d / filename
    tmp = d / (filename + ".part")
    tmp.write_text(
        json.dumps({"views": entries, "degrees_of_freedom": degrees_of_freedom}, indent=2) + "\n"
    )
    os.replace(tmp, path)
    return path


def read_views(path: str | os.PathLike) -> tuple[list[View], int]:
    """Read a view set; returns ``(views, degrees_of_freedom)``.

    Raises
    ------
    ValueError
        Unparsable JSON, missing fields, missing or malformed images, an image whose shape differs
        from the stated geometry, NaNs, or a singular projection matrix; the message names the
        file and the view.
    """
    path = Path(path)
    doc = read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("views"), list) or not doc["views"]:
        raise ValueError(f"{path}: expected an object with a non-empty 'views' list")
    dof = doc.get("degrees_of_freedom", 6)
    if dof not in (6, 9):
        raise ValueError(f"{path}: degrees_of_freedom must be 6 or 9, got {dof!r}")
    views = []
    for n, entry in enumerate(doc["views"]):
        where = f"{path}, view {n}"
        if not isinstance(entry, dict):
            raise ValueError(f"{where}: expected an object")
        for key in ("image", "projection_matrix", "pixel_spacing_mm"):
            if key not in entry:
                raise ValueError(f"{where}: missing '{key}'")
        img_path = path.parent / str(entry["image"])
        try:
            image = np.load(img_path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise ValueError(f"{where}: cannot read image {img_path} ({err})") from None
        rows, cols = entry.get("rows"), entry.get("cols")
        if rows is not None and cols is not None and image.shape != (rows, cols):
            raise ValueError(
                f"{where}: image {img_path.name} has shape {image.shape}, but the geometry says "
                f"{rows} x {cols}"
            )
        try:
            P = np.asarray(entry["projection_matrix"], dtype=np.float64)
            meta = {
                k: v
                for k, v in entry.items()
                if k not in ("name", "image", "projection_matrix", "pixel_spacing_mm", "source_mm")
            }
            views.append(
                View(
                    name=str(entry.get("name", f"view{n}")),
                    image=image,
                    projection_matrix=P,
                    pixel_spacing=entry["pixel_spacing_mm"],
                    meta=meta,
                )
            )
        except (TypeError, ValueError) as err:
            raise ValueError(f"{where}: {err}") from None
    return views, int(dof)
