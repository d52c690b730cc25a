"""The view-set file ``views.json``: radiographs with their projection geometry.

Format (see docs/conventions.md)::

    {"views": [{"name": "ap", "image": "ap.npy", "projection_matrix": [[...], [...], [...]],
                "pixel_spacing_mm": [dr, dc], "source_mm": [x, y, z],
                "rows": 512, "cols": 512, "dose_ugy": 5.0}],
     "degrees_of_freedom": 6}

Images are ``(rows, cols)`` float32 arrays of line integrals stored as ``.npy`` beside the JSON.
Writing is atomic (temporary names, then rename); reading validates everything and names the file.

:class:`View` is one radiograph; :class:`ViewSet` the views one registration uses together (the
type :mod:`pelvicnav.register` takes).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry.projection import normalize_projection
from pelvicnav.io.jsonfile import read_json

__all__ = ["View", "ViewSet", "read_views", "write_views"]

MIN_SIZE = 16  # pixels: the coarsest pyramid level (4x binning) still has a 4 x 4 image


@dataclass(frozen=True, eq=False)
class View:
    """One radiograph and its geometry.

    Attributes
    ----------
    name : str
    image : (rows, cols) float32 or float64
        Line integrals (log-transformed intensities); integer images become float32.
    projection_matrix : (3, 4) float64
        World (LPS mm) to pixels, see :mod:`pelvicnav.geometry.projection`; stored normalised
        (``det > 0``, third row of unit length: ``w`` is depth in mm).
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
        img = np.asarray(self.image)
        if not np.issubdtype(img.dtype, np.floating):
            img = img.astype(np.float32)
        if img.ndim != 2:
            raise ValueError(f"view {self.name!r}: image must be 2D, got shape {img.shape}")
        if not np.all(np.isfinite(img)):
            raise ValueError(f"view {self.name!r}: image contains NaN or infinity")
        P = np.asarray(self.projection_matrix, dtype=np.float64)
        if P.shape != (3, 4) or not np.all(np.isfinite(P)):
            raise ValueError(f"view {self.name!r}: projection matrix must be a finite 3 x 4 array")
        try:
            P = normalize_projection(P)
        except ValueError as err:
            raise ValueError(f"view {self.name!r}: {err}") from None
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


@dataclass(frozen=True, eq=False)
class ViewSet:
    """The radiographs one registration uses together: at least one view, all the same shape,
    each at least 16 x 16 pixels.

    Attributes
    ----------
    views : tuple of View
    """

    views: tuple[View, ...]

    def __post_init__(self) -> None:
        views = tuple(self.views)
        if not views:
            raise ValueError("a view set needs at least one view")
        shapes = [v.image.shape for v in views]
        if len(set(shapes)) != 1:
            raise ValueError(f"all views must have the same shape, got {shapes}")
        if min(shapes[0]) < MIN_SIZE:
            raise ValueError(
                f"view {views[0].name!r}: image must be at least {MIN_SIZE} x {MIN_SIZE} pixels, "
                f"got {shapes[0]}"
            )
        object.__setattr__(self, "views", views)

    @classmethod
    def from_arrays(
        cls,
        images: list[ArrayLike] | tuple,
        projections: list[ArrayLike] | tuple,
        pixel_spacing: list | tuple,
    ) -> ViewSet:
        """Views named ``view0, view1...`` from images, matrices and pixel spacings."""
        n = (len(images), len(projections), len(pixel_spacing))
        if len(set(n)) != 1:
            raise ValueError(
                f"need one projection matrix and pixel spacing per image, got {n[0]} images, "
                f"{n[1]} matrices and {n[2]} spacings"
            )
        items = zip(images, projections, pixel_spacing, strict=True)
        return cls(tuple(View(f"view{k}", np.asarray(img), P, ps)
                         for k, (img, P, ps) in enumerate(items)))  # fmt: skip

    def with_projections(self, projections: list[ArrayLike] | tuple) -> ViewSet:
        """The same images with other projection matrices (e.g. a 9-DoF frame's estimate)."""
        if len(projections) != len(self.views):
            raise ValueError(f"need {len(self.views)} projection matrices, got {len(projections)}")
        return ViewSet(tuple(View(v.name, v.image, P, v.pixel_spacing, v.meta)
                             for v, P in zip(self.views, projections, strict=True)))  # fmt: skip

    def __len__(self) -> int:
        return len(self.views)

    @property
    def images(self) -> tuple[NDArray, ...]:
        return tuple(v.image for v in self.views)

    @property
    def projections(self) -> tuple[NDArray[np.float64], ...]:
        return tuple(v.projection_matrix for v in self.views)

    @property
    def pixel_spacing(self) -> tuple[tuple[float, float], ...]:
        return tuple(v.pixel_spacing for v in self.views)

    @property
    def shape(self) -> tuple[int, int]:
        return self.views[0].image.shape  # type: ignore[return-value]


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
            np.save(fh, v.image.astype(np.float32, copy=False))
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
