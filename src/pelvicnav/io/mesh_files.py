"""A bone's surface in the formats 3D Slicer, ITK-SNAP, MeshLab and CAD tools open: VTK, STL, PLY.

All in LPS millimetres, the coordinates pelvicnav works in. 3D Slicer assumes LPS for STL and PLY
files unless their header says otherwise (Slicer 4.11 and later), and reads the legacy VTK files
written here as LPS as well (their title line says ``SPACE=LPS``). Writes are atomic.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["MESH_FORMATS", "write_mesh", "write_meshes"]

MESH_FORMATS = ("vtk", "stl", "ply")


def write_mesh(
    path: str | os.PathLike, vertices: ArrayLike, faces: ArrayLike, *, title: str = "pelvicnav"
) -> Path:
    """Write a triangle mesh; the format follows the suffix (``.vtk``, ``.stl``, ``.ply``).

    Raises
    ------
    ValueError
        An unknown suffix, or vertices / faces of the wrong shape.
    """
    import meshio

    from pelvicnav.io.vtk_legacy import write_polydata

    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in MESH_FORMATS:
        raise ValueError(f"{path}: unknown mesh format; use one of {MESH_FORMATS}")
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"{path}: vertices must be (n, 3) and faces (m, 3)")
    if fmt == "vtk":
        write_polydata(path, V, F, binary=True, title=f"{title} SPACE=LPS mm")
        return path
    tmp = path.with_name(path.stem + ".part" + path.suffix)
    mesh = meshio.Mesh(V, [("triangle", F.astype(np.int32))])
    meshio.write(tmp, mesh, file_format=fmt, binary=True)
    os.replace(tmp, path)
    return path


def write_meshes(
    folder: str | os.PathLike,
    name: str,
    vertices: ArrayLike,
    faces: ArrayLike,
    *,
    formats: tuple[str, ...] = MESH_FORMATS,
    title: str = "pelvicnav",
) -> list[Path]:
    """Write ``folder/{name}.{fmt}`` for every format."""
    return [
        write_mesh(Path(folder) / f"{name}.{fmt}", vertices, faces, title=title) for fmt in formats
    ]
