"""Atlas reader, location, archive install and download (offline: file:// URLs)."""

from __future__ import annotations

import io
import shutil
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pelvicnav.io import atlas as atlas_mod
from pelvicnav.io.atlas import (
    Atlas,
    AtlasNotFoundError,
    download_atlas,
    install_atlas_archive,
    load_atlas,
    resolve_atlas_path,
)
from pelvicnav.io.vtk_legacy import read_polydata, write_polydata


def test_loads_tiny_atlas(tiny_atlas):
    a = load_atlas(tiny_atlas)
    assert a.subject_ids == (1, 2, 3)
    assert a.tcia_ids == ("CASE_001", "CASE_002", "CASE_003")
    assert a.vertices.shape == (3, 3, 6, 3)
    assert a.vertices.dtype == np.float64
    assert [f.shape for f in a.faces] == [(8, 3)] * 3
    # Bone order is sacrum, left_hip, right_hip, whatever the folder order on disk.
    pts, _ = read_polydata(tiny_atlas / "surface" / "left" / "LeftHip2_cpd.vtk")
    np.testing.assert_array_equal(a.vertices[1, 1], pts)
    v, _f = a.mesh(3, "right_hip")
    np.testing.assert_array_equal(v, a.vertices[2, 2])
    assert a.subset([2, 0]).subject_ids == (3, 1)
    with pytest.raises(ValueError, match="unknown bone 'femur'"):
        a.mesh(1, "femur")
    with pytest.raises(ValueError, match="unknown subject id 99"):
        a.mesh(99, "sacrum")


def test_expected_subject_count(tiny_atlas):
    with pytest.raises(ValueError, match="lists 3 subjects, expected 40"):
        load_atlas(tiny_atlas, expected_subjects=40)


def test_missing_subject_file_is_named(tiny_atlas):
    (tiny_atlas / "surface" / "left" / "LeftHip2_cpd.vtk").unlink()
    with pytest.raises(ValueError, match=r"surface/left: missing subject file\(s\) LeftHip2_cpd"):
        load_atlas(tiny_atlas)


def test_extra_subject_file_is_named(tiny_atlas):
    src = tiny_atlas / "surface" / "sacrum" / "Sacrum1_cpd.vtk"
    shutil.copy(src, src.with_name("Sacrum9_cpd.vtk"))
    with pytest.raises(ValueError, match="Sacrum9_cpd.vtk not listed in table.csv"):
        load_atlas(tiny_atlas)


def test_truncated_vtk_is_named(tiny_atlas):
    f = tiny_atlas / "surface" / "right" / "RightHip3_cpd.vtk"
    f.write_text(f.read_text()[:200])
    with pytest.raises(ValueError, match=r"RightHip3_cpd\.vtk: truncated"):
        load_atlas(tiny_atlas)


def test_inconsistent_meshes(tiny_atlas):
    f = tiny_atlas / "surface" / "sacrum" / "Sacrum2_cpd.vtk"
    pts, tris = read_polydata(f)
    write_polydata(f, pts, tris[:, ::-1])
    with pytest.raises(ValueError, match=r"Sacrum2_cpd\.vtk: triangles differ from those of Sac"):
        load_atlas(tiny_atlas)
    write_polydata(f, np.vstack([pts, [0, 0, 0]]), tris)
    with pytest.raises(ValueError, match="has 7 vertices, but Sacrum1_cpd.vtk has 6"):
        load_atlas(tiny_atlas)


def test_bad_table(tiny_atlas):
    (tiny_atlas / "table.csv").write_text("id,name\n1,2\n")
    with pytest.raises(ValueError, match="expected header"):
        load_atlas(tiny_atlas)
    (tiny_atlas / "table.csv").unlink()
    with pytest.raises(ValueError, match=r"table\.csv: missing"):
        load_atlas(tiny_atlas)


def test_atlas_rejects_non_finite():
    v = np.zeros((1, 3, 6, 3))
    v[0, 2, 4, 1] = np.inf
    faces = (np.array([[0, 1, 2]]),) * 3
    with pytest.raises(
        ValueError, match="subject 7, bone right_hip: non-finite coordinate at vert"
    ):
        Atlas(subject_ids=(7,), vertices=v, faces=faces)


def test_location_order(tiny_atlas, tmp_path, monkeypatch):
    monkeypatch.setenv("PELVICNAV_ATLAS", str(tiny_atlas))
    assert resolve_atlas_path() == tiny_atlas
    other = tmp_path / "other"
    other.mkdir()
    assert resolve_atlas_path(other) == other  # an explicit path wins
    monkeypatch.delenv("PELVICNAV_ATLAS")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert resolve_atlas_path.__module__  # the cache default depends on the platform
    with pytest.raises(AtlasNotFoundError, match="pelvicnav atlas download"):
        resolve_atlas_path()
    cache_atlas = atlas_mod.default_atlas_dir()
    assert str(cache_atlas).startswith(str(tmp_path / "cache"))
    shutil.copytree(tiny_atlas, cache_atlas)
    assert load_atlas().n_subjects == 3
    monkeypatch.setenv("PELVICNAV_ATLAS", str(tmp_path / "missing"))
    with pytest.raises(AtlasNotFoundError, match=r"missing \(\$PELVICNAV_ATLAS\)"):
        load_atlas()


# ---- archives ------------------------------------------------------------------------------------


def _zip_atlas(src: Path, archive: Path, prefix: str = "Altas-master/") -> Path:
    with zipfile.ZipFile(archive, "w") as zf:
        for f in sorted(src.rglob("*")):
            if f.is_file():
                zf.write(f, prefix + f.relative_to(src).as_posix())
        zf.writestr(prefix + "segmentation/sacrum/Sacrum_1.stl", "solid x\nendsolid x\n")
        zf.writestr(prefix + "README.md", "atlas\n")
    return archive


def test_install_from_zip_keeps_only_what_is_read(tiny_atlas, tmp_path):
    archive = _zip_atlas(tiny_atlas, tmp_path / "atlas.zip")
    dest = tmp_path / "cache" / "pelvis-atlas"
    a = install_atlas_archive(archive, dest, expected_subjects=3)
    assert a.n_subjects == 3 and a.source == str(dest)
    assert (dest / "table.csv").is_file() and (dest / "README.md").is_file()
    assert not (dest / "segmentation").exists()
    np.testing.assert_array_equal(load_atlas(dest).vertices, load_atlas(tiny_atlas).vertices)
    assert [p.name for p in dest.parent.iterdir()] == ["pelvis-atlas"]  # no temporary left
    with pytest.raises(FileExistsError):
        install_atlas_archive(archive, dest, expected_subjects=3)
    install_atlas_archive(archive, dest, expected_subjects=3, force=True)


def test_install_from_tar(tiny_atlas, tmp_path):
    archive = tmp_path / "atlas.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        tar.add(tiny_atlas, arcname="repo")
    a = install_atlas_archive(archive, tmp_path / "dest", expected_subjects=3)
    assert a.vertices.shape == (3, 3, 6, 3)


def test_invalid_archive_leaves_nothing(tiny_atlas, tmp_path):
    (tiny_atlas / "surface" / "right" / "RightHip1_cpd.vtk").unlink()
    archive = _zip_atlas(tiny_atlas, tmp_path / "atlas.zip")
    dest = tmp_path / "cache" / "pelvis-atlas"
    with pytest.raises(ValueError, match="not a valid atlas: .*missing subject file"):
        install_atlas_archive(archive, dest, expected_subjects=3)
    assert not dest.exists()
    assert list((tmp_path / "cache").iterdir()) == []
    junk = tmp_path / "junk.zip"
    junk.write_bytes(b"not an archive")
    with pytest.raises(ValueError, match="neither a zip nor a tar"):
        install_atlas_archive(junk, dest)


def test_archive_without_atlas_or_with_unsafe_paths(tmp_path, tiny_atlas):
    empty = tmp_path / "empty.zip"
    with zipfile.ZipFile(empty, "w") as zf:
        zf.writestr("repo/README.md", "nothing here")
    with pytest.raises(ValueError, match="exactly one atlas"):
        install_atlas_archive(empty, tmp_path / "d1")
    evil = _zip_atlas(tiny_atlas, tmp_path / "evil.zip", prefix="")
    with zipfile.ZipFile(evil, "a") as zf:
        zf.writestr("surface/../../escape.txt", "x")
    with pytest.raises(ValueError, match="escapes the extraction folder"):
        install_atlas_archive(evil, tmp_path / "d2", expected_subjects=3)
    assert not (tmp_path / "escape.txt").exists()


def test_download_from_file_url_with_progress(tiny_atlas, tmp_path):
    archive = _zip_atlas(tiny_atlas, tmp_path / "atlas.zip")
    seen = []
    dest = tmp_path / "cache" / "pelvis-atlas"
    a = download_atlas(
        dest,
        urls=((tmp_path / "absent.zip").as_uri(), archive.as_uri()),
        expected_subjects=3,
        progress=lambda done, total: seen.append((done, total)),
    )
    assert a.n_subjects == 3
    assert seen and seen[-1][0] == archive.stat().st_size
    assert sorted(p.name for p in dest.parent.iterdir()) == ["pelvis-atlas"]
    with pytest.raises(FileExistsError):
        download_atlas(dest, urls=(archive.as_uri(),), expected_subjects=3)


def test_download_failure_is_reported(tmp_path):
    with pytest.raises(ValueError, match="could not download the atlas"):
        download_atlas(tmp_path / "a", urls=((tmp_path / "none.zip").as_uri(),))
    assert not (tmp_path / "a").exists()
    assert not list(tmp_path.glob("*.part"))


def test_zip_member_listing_handles_flat_archives(tiny_atlas, tmp_path):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("table.csv", "x")
        zf.writestr("surface/left/LeftHip1_cpd.vtk", "x")
        zf.writestr("trajectory/a.stl", "x")
    root, members = atlas_mod._atlas_members(zipfile.ZipFile(buf).namelist())
    assert root == "."
    assert sorted(members.values()) == ["surface/left/LeftHip1_cpd.vtk", "table.csv"]


# ---- the real atlas ----------------------------------------------------------------------------


@pytest.mark.atlas
def test_real_atlas(real_atlas_path):
    a = load_atlas(real_atlas_path, expected_subjects=40)
    assert a.vertices.shape == (40, 3, 5000, 3)
    assert len(a.faces) == 3 and all(f.shape[1] == 3 for f in a.faces)
    assert a.subject_ids[:3] == (2, 3, 4) and a.tcia_ids[0] == "ABD_LYMPH_002"
    # LPS: the left innominate lies at larger x than the sacrum, the right at smaller x, always.
    c = a.vertices.mean(axis=2)
    assert np.all(c[:, 1, 0] > c[:, 0, 0]) and np.all(c[:, 0, 0] > c[:, 2, 0])
    # ... and the sacrum is posterior (larger y) to both innominates.
    assert np.all(c[:, 0, 1] > c[:, 1, 1]) and np.all(c[:, 0, 1] > c[:, 2, 1])
    # Pelvic width (left-right extent) in an adult range.
    width = a.vertices[:, 1:, :, 0].max(axis=(1, 2)) - a.vertices[:, 1:, :, 0].min(axis=(1, 2))
    assert 200 < width.min() and width.max() < 380
