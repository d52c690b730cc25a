"""Outputs for 3D Slicer and ITK: .tfm poses (read by SimpleITK), Markups JSON, VTK/STL/PLY."""

from __future__ import annotations

import json

import meshio
import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from pelvicnav.io.itk_transform import read_pose_tfm, write_pose_tfm, write_pose_transforms
from pelvicnav.io.markups import read_markups, write_markups
from pelvicnav.io.mesh_files import write_mesh, write_meshes
from pelvicnav.io.vtk_legacy import read_polydata


def _pose(rng, scale=1.0):
    T = np.eye(4)
    T[:3, :3] = scale * Rotation.from_rotvec(rng.normal(0, 0.4, 3)).as_matrix()
    T[:3, 3] = rng.normal(0, 50, 3)
    return T


@pytest.mark.parametrize("scale", [1.0, 1.07])
def test_tfm_read_by_simpleitk_maps_points_as_the_pose(tmp_path, scale):
    rng = np.random.default_rng(0)
    world_from_ct = _pose(rng, scale)
    path = write_pose_tfm(tmp_path / "left_hip.tfm", world_from_ct)
    tx = sitk.ReadTransform(str(path))
    points = rng.uniform(-200, 200, (100, 3))
    expected_world = points @ world_from_ct[:3, :3].T + world_from_ct[:3, 3]
    # ITK's resampling convention: fixed (world) -> moving (CT); its inverse is the pose.
    moved = np.array([tx.GetInverse().TransformPoint(tuple(p)) for p in points])
    np.testing.assert_allclose(moved, expected_world, atol=1e-6)
    back = np.array([tx.TransformPoint(tuple(p)) for p in expected_world])
    np.testing.assert_allclose(back, points, atol=1e-6)
    np.testing.assert_allclose(read_pose_tfm(path), world_from_ct, atol=1e-9)
    assert not list(tmp_path.glob("*.part*"))


def test_tfm_folder_and_errors(tmp_path):
    rng = np.random.default_rng(1)
    poses = {b: _pose(rng) for b in ("sacrum", "left_hip", "right_hip")}
    files = write_pose_transforms(tmp_path / "transforms", poses, residual=_pose(rng))
    assert sorted(f.name for f in files) == [
        "left_hip.tfm", "residual.tfm", "right_hip.tfm", "sacrum.tfm"
    ]  # fmt: skip
    with pytest.raises(ValueError, match="singular"):
        write_pose_tfm(tmp_path / "x.tfm", np.diag([0.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="4 x 4"):
        write_pose_tfm(tmp_path / "x.tfm", np.eye(3))
    (tmp_path / "junk.tfm").write_text("nonsense")
    with pytest.raises(ValueError, match=r"junk\.tfm: not a readable ITK transform"):
        read_pose_tfm(tmp_path / "junk.tfm")


def test_markups_round_trip(tmp_path):
    points = {"femoral_head_left": [80.5, -10.0, 20.25], "bead_1_sacrum": [0.0, 30.0, 60.0]}
    path = write_markups(tmp_path / "landmarks.mrk.json", points, name="landmarks")
    doc = json.loads(path.read_text())
    assert doc["markups"][0]["coordinateSystem"] == "LPS"
    assert doc["@schema"].endswith("markups-schema-v1.0.3.json#")
    back = read_markups(path)
    assert list(back) == list(points)
    for k, v in points.items():
        np.testing.assert_allclose(back[k], v)
    doc["markups"][0]["coordinateSystem"] = "RAS"
    (tmp_path / "ras.mrk.json").write_text(json.dumps(doc))
    np.testing.assert_allclose(read_markups(tmp_path / "ras.mrk.json")["bead_1_sacrum"],
                               [0.0, -30.0, 60.0])  # fmt: skip
    with pytest.raises(ValueError, match="3 finite numbers"):
        write_markups(tmp_path / "bad.mrk.json", {"x": [1, 2]})
    (tmp_path / "other.json").write_text("{}")
    with pytest.raises(ValueError, match=r"other\.json: not a Slicer Markups"):
        read_markups(tmp_path / "other.json")


def test_meshes_in_three_formats(tmp_path):
    V = np.array([[0, 0, 0], [10.5, 0, 0], [0, 20.25, 0], [0, 0, -30.125]], dtype=np.float64)
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    files = write_meshes(tmp_path, "sacrum", V, F)
    assert sorted(f.name for f in files) == ["sacrum.ply", "sacrum.stl", "sacrum.vtk"]
    pts, faces = read_polydata(tmp_path / "sacrum.vtk")
    np.testing.assert_allclose(pts, V)
    np.testing.assert_array_equal(faces, F)
    ply = meshio.read(tmp_path / "sacrum.ply")
    np.testing.assert_allclose(ply.points, V)
    np.testing.assert_array_equal(ply.cells_dict["triangle"], F)
    stl = meshio.read(tmp_path / "sacrum.stl")  # STL repeats vertices per face
    np.testing.assert_allclose(np.sort(np.unique(stl.points, axis=0), axis=0),
                               np.sort(V, axis=0), atol=1e-5)  # fmt: skip
    with pytest.raises(ValueError, match="unknown mesh format"):
        write_mesh(tmp_path / "x.obj", V, F)
    assert not list(tmp_path.glob("*.part*"))
