"""Legacy VTK POLYDATA reader/writer."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.io.vtk_legacy import read_polydata, write_polydata

POINTS = np.array([[0.0, 0, 0], [1.5, 0, 0], [0, 2.25, 0], [0, 0, -3.125]])
TRIS = np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3]])


@pytest.mark.parametrize("binary", [False, True])
def test_round_trip(tmp_path, binary):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3)) * 100
    tris = rng.integers(0, 50, size=(80, 3))
    f = tmp_path / "m.vtk"
    write_polydata(f, pts, tris, binary=binary)
    p, t = read_polydata(f)
    np.testing.assert_array_equal(p, pts)  # %.17g / float64 keep every bit
    np.testing.assert_array_equal(t, tris)
    assert p.dtype == np.float64 and t.dtype == np.int64
    assert not list(tmp_path.glob("*.part"))


def test_reads_atlas_style_ascii_with_wrapped_lines_and_attributes(tmp_path):
    # The atlas writes 9 floats per line (three points) and float precision; attributes may follow.
    text = (
        "# vtk DataFile Version 4.0\nvtk output\nASCII\nDATASET POLYDATA\nPOINTS 4 float\n"
        "0 0 0 1.5 0 0 0 2.25 0\n0 0 -3.125\n\n"
        "POLYGONS 3 12\n3 0 1 2\n3 0 1 3\n3 1 2 3\n"
        "POINT_DATA 4\nSCALARS s float\nLOOKUP_TABLE default\n1 2 3 4\n"
    )
    f = tmp_path / "a.vtk"
    f.write_text(text)
    p, t = read_polydata(f)
    np.testing.assert_array_equal(p, POINTS)
    np.testing.assert_array_equal(t, TRIS)


def _write(tmp_path, body: str, name="bad.vtk"):
    f = tmp_path / name
    f.write_text("# vtk DataFile Version 4.0\nt\nASCII\nDATASET POLYDATA\n" + body)
    return f


def test_truncated_points(tmp_path):
    f = _write(tmp_path, "POINTS 4 float\n0 0 0 1 0 0\n")
    with pytest.raises(
        ValueError, match=r"bad\.vtk: truncated POINTS: expected 12 values, found 6"
    ):
        read_polydata(f)


def test_truncated_points_before_polygons(tmp_path):
    f = _write(tmp_path, "POINTS 4 float\n0 0 0 1 0 0\nPOLYGONS 1 4\n3 0 1 2\n")
    with pytest.raises(ValueError, match="truncated POINTS"):
        read_polydata(f)


def test_truncated_binary(tmp_path):
    f = tmp_path / "b.vtk"
    write_polydata(f, POINTS, TRIS, binary=True)
    data = f.read_bytes()
    f.write_bytes(data[: len(data) - 20])
    with pytest.raises(ValueError, match=r"b\.vtk: truncated POLYGONS"):
        read_polydata(f)


def test_truncated_file_cut_mid_polygons(tmp_path):
    f = tmp_path / "c.vtk"
    write_polydata(f, POINTS, TRIS)
    f.write_text(f.read_text()[:-8])
    with pytest.raises(ValueError, match=r"c\.vtk: truncated POLYGONS"):
        read_polydata(f)


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("POINTS 3 float\n0 0 0 1 0 0 0 1 0\nPOLYGONS 1 5\n4 0 1 2 2\n", "non-triangular"),
        ("POINTS 3 float\n0 0 0 1 0 0 0 1 0\nPOLYGONS 1 4\n3 0 1 7\n", "out of range"),
        ("POINTS 3 float\n0 0 0 1 nan 0 0 1 0\nPOLYGONS 1 4\n3 0 1 2\n", "non-finite coordinate"),
        ("POINTS 3 float\n0 0 0 1 x 0 0 1 0\nPOLYGONS 1 4\n3 0 1 2\n", "non-numeric"),
        ("POINTS 3 float\n0 0 0 1 0 0 0 1 0\n", "no POLYGONS"),
        ("POLYGONS 1 4\n3 0 1 2\n", "no POINTS"),
        ("POINTS three float\n", "malformed POINTS"),
    ],
)
def test_malformed(tmp_path, body, message):
    f = _write(tmp_path, body)
    with pytest.raises(ValueError, match=message):
        read_polydata(f)


def test_not_vtk(tmp_path):
    f = tmp_path / "x.vtk"
    f.write_text("solid stl\n")
    with pytest.raises(ValueError, match=r"x\.vtk: not a legacy VTK file"):
        read_polydata(f)
    f.write_text("# vtk DataFile Version 4.0\nt\nASCII\nDATASET UNSTRUCTURED_GRID\n")
    with pytest.raises(ValueError, match="DATASET POLYDATA"):
        read_polydata(f)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_polydata(tmp_path / "nope.vtk")


def test_meshes_sharing_triangles_read_their_own_points_and_independent_triangles(tmp_path):
    """Corresponded meshes (the atlas) reuse the parsed triangles of an identical POLYGONS tail;
    each read still has its own points and its own triangle array, and a mesh whose triangles
    differ, or index points it lacks, is read (or refused) on its own."""
    rng = np.random.default_rng(1)
    tris = rng.integers(0, 40, size=(60, 3))
    meshes = [rng.normal(size=(40, 3)) for _ in range(3)]
    for k, pts in enumerate(meshes):
        write_polydata(tmp_path / f"m{k}.vtk", pts, tris)
    read = [read_polydata(tmp_path / f"m{k}.vtk") for k in range(3)]
    for (p, t), pts in zip(read, meshes, strict=True):
        np.testing.assert_array_equal(p, pts)
        np.testing.assert_array_equal(t, tris)
    read[0][1][0] = (9, 9, 9)  # a caller's change stays its own
    np.testing.assert_array_equal(read_polydata(tmp_path / "m1.vtk")[1], tris)
    other = tris[::-1].copy()
    write_polydata(tmp_path / "other.vtk", meshes[0], other)
    np.testing.assert_array_equal(read_polydata(tmp_path / "other.vtk")[1], other)
    write_polydata(tmp_path / "few.vtk", meshes[0][:10], tris)  # same triangles, 10 points
    with pytest.raises(ValueError, match="out of range"):
        read_polydata(tmp_path / "few.vtk")
