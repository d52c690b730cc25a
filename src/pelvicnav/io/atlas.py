"""The Han pelvis atlas: 40 subjects x 3 bones with 5000 corresponding vertices per bone.

Layout read (as published in the atlas repository)::

    table.csv                         "TCIA Subject ID,Atlas ID"
    surface/sacrum/Sacrum{ID}_cpd.vtk
    surface/left/LeftHip{ID}_cpd.vtk
    surface/right/RightHip{ID}_cpd.vtk
    SSM/{Sacrum,LeftHip,RightHip}.h5  (statismo reference models; not needed to load)

Coordinates are each subject's CT coordinates in LPS millimetres.

Reference: R. Han et al., "Atlas-based automatic planning and 3D-2D fluoroscopic guidance in pelvic
trauma surgery", Phys. Med. Biol. 64 (2019) 095022, doi:10.1088/1361-6560/ab1456 (atlas: CC BY 4.0).

Location, in order: an explicit path, the ``PELVICNAV_ATLAS`` environment variable, then the user
cache directory (``pelvicnav atlas download`` puts it there).
"""

from __future__ import annotations

import csv
import os
import shutil
import tarfile
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path, PurePosixPath

import numpy as np
from numpy.typing import NDArray

from pelvicnav.io.vtk_legacy import read_polydata

__all__ = [
    "ATLAS_ENV",
    "ATLAS_URLS",
    "BONE_FILES",
    "Atlas",
    "AtlasNotFoundError",
    "default_atlas_dir",
    "download_atlas",
    "install_atlas_archive",
    "load_atlas",
    "resolve_atlas_path",
]

BONES = ("sacrum", "left_hip", "right_hip")
ATLAS_ENV = "PELVICNAV_ATLAS"
# bone name -> (folder under surface/, file name prefix)
BONE_FILES: dict[str, tuple[str, str]] = {
    "sacrum": ("sacrum", "Sacrum"),
    "left_hip": ("left", "LeftHip"),
    "right_hip": ("right", "RightHip"),
}
_REPO = "rhan93/Altas-of-Pelvis-Segmentation-and-Trajectory-Planning"
ATLAS_URLS: tuple[str, ...] = tuple(
    f"https://github.com/{_REPO}/archive/refs/heads/{branch}.zip" for branch in ("master", "main")
)
# What an installed atlas keeps from the repository archive (segmentations and trajectories are
# large and unused).
_KEEP = ("table.csv", "README.md", "LICENSE.txt", "surface/", "SSM/")


class AtlasNotFoundError(FileNotFoundError):
    """No atlas at the given or configured location."""


@dataclass(frozen=True, eq=False)
class Atlas:
    """A population of pelvises with vertex correspondence.

    Attributes
    ----------
    subject_ids : tuple of int
        Atlas ids (``table.csv``'s "Atlas ID"), one per subject.
    vertices : (n_subjects, 3, n_vertices, 3) float64, mm (LPS)
        Bone order ``sacrum, left_hip, right_hip``.
    faces : tuple of three (n_faces_l, 3) int64
        Triangles of each bone, identical for every subject.
    source : str
        Where the atlas came from (a folder, or ``"procedural"``).
    tcia_ids : tuple of str, optional
        The TCIA CT Lymph Nodes subject of each atlas member.
    """

    subject_ids: tuple[int, ...]
    vertices: NDArray[np.float64]
    faces: tuple[NDArray[np.int64], ...]
    source: str = ""
    tcia_ids: tuple[str, ...] | None = None
    bones: tuple[str, ...] = BONES

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=np.float64)
        n = len(self.subject_ids)
        if v.ndim != 4 or v.shape[0] != n or v.shape[1] != len(self.bones) or v.shape[3] != 3:
            raise ValueError(
                f"atlas vertices must have shape ({n}, {len(self.bones)}, n_vertices, 3), "
                f"got {v.shape}"
            )
        if n == 0:
            raise ValueError("atlas has no subjects")
        if len(set(self.subject_ids)) != n:
            raise ValueError(f"atlas subject ids are not unique: {self.subject_ids}")
        if not np.all(np.isfinite(v)):
            s, b, i, _ = np.argwhere(~np.isfinite(v))[0]
            raise ValueError(
                f"atlas subject {self.subject_ids[s]}, bone {self.bones[b]}: "
                f"non-finite coordinate at vertex {i}"
            )
        if len(self.faces) != len(self.bones):
            raise ValueError(f"expected faces for {len(self.bones)} bones, got {len(self.faces)}")
        faces = tuple(np.asarray(f, dtype=np.int64) for f in self.faces)
        for bone, f in zip(self.bones, faces, strict=True):
            if f.ndim != 2 or f.shape[1] != 3 or f.min() < 0 or f.max() >= v.shape[2]:
                raise ValueError(f"atlas faces of {bone} are not valid triangles into the vertices")
        if self.tcia_ids is not None and len(self.tcia_ids) != n:
            raise ValueError("tcia_ids must have one entry per subject")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "subject_ids", tuple(int(s) for s in self.subject_ids))

    @property
    def n_subjects(self) -> int:
        return len(self.subject_ids)

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[2]

    def bone_index(self, bone: str) -> int:
        """Position of ``bone`` in :attr:`bones` (``ValueError`` for an unknown name)."""
        try:
            return self.bones.index(bone)
        except ValueError:
            raise ValueError(f"unknown bone {bone!r}; expected one of {self.bones}") from None

    def bone_summary(self) -> list[dict]:
        """Per bone: vertex and triangle counts, mean extent and mean centroid (mm, LPS)."""
        rows = []
        for b, bone in enumerate(self.bones):
            v = self.vertices[:, b]
            rows.append({
                "bone": bone, "vertices": int(v.shape[1]), "triangles": len(self.faces[b]),
                "mean_extent_mm": (v.max(axis=1) - v.min(axis=1)).mean(axis=0).tolist(),
                "centroid_mm": v.mean(axis=(0, 1)).tolist(),
            })  # fmt: skip
        return rows

    def subject_index(self, subject_id: int) -> int:
        """Position of an atlas id (``ValueError`` for an unknown id)."""
        try:
            return self.subject_ids.index(int(subject_id))
        except ValueError:
            raise ValueError(
                f"unknown subject id {subject_id}; atlas ids are {list(self.subject_ids)}"
            ) from None

    def mesh(self, subject_id: int, bone: str) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """``(vertices (n_vertices, 3), faces (n_faces, 3))`` of one bone of one subject."""
        b = self.bone_index(bone)
        return self.vertices[self.subject_index(subject_id), b], self.faces[b]

    def subset(self, indices: list[int] | NDArray[np.int_]) -> Atlas:
        """The atlas restricted to subjects at ``indices`` (positions, not ids)."""
        idx = np.asarray(indices, dtype=int)
        return Atlas(
            subject_ids=tuple(self.subject_ids[i] for i in idx),
            vertices=self.vertices[idx],
            faces=self.faces,
            source=self.source,
            tcia_ids=None if self.tcia_ids is None else tuple(self.tcia_ids[i] for i in idx),
            bones=self.bones,
        )


def default_atlas_dir() -> Path:
    """``<user cache>/pelvicnav/pelvis-atlas`` (where ``pelvicnav atlas download`` installs)."""
    from platformdirs import user_cache_dir

    return Path(user_cache_dir("pelvicnav")) / "pelvis-atlas"


def resolve_atlas_path(path: str | os.PathLike | None = None) -> Path:
    """The atlas folder: ``path``, else ``$PELVICNAV_ATLAS``, else the user cache directory.

    Raises
    ------
    AtlasNotFoundError
        If the chosen location is not a folder, with a hint on how to get the atlas.
    """
    if path is not None:
        where, how = Path(path), "given path"
    elif os.environ.get(ATLAS_ENV):
        where, how = Path(os.environ[ATLAS_ENV]), f"${ATLAS_ENV}"
    else:
        where, how = default_atlas_dir(), "default cache location"
    if not where.is_dir():
        raise AtlasNotFoundError(
            f"no pelvis atlas at {where} ({how}). Pass --atlas PATH, set {ATLAS_ENV}, "
            "or run `pelvicnav atlas download`."
        )
    return where


def _read_table(path: Path) -> tuple[list[int], list[str]]:
    if not path.is_file():
        raise ValueError(f"{path}: missing (the atlas table of subjects)")
    with open(path, newline="", encoding="utf-8-sig") as fh:
        rows = list(csv.reader(fh))
    if not rows or [c.strip() for c in rows[0][:2]] != ["TCIA Subject ID", "Atlas ID"]:
        raise ValueError(f"{path}: expected header 'TCIA Subject ID,Atlas ID'")
    ids, tcia = [], []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        if len(row) < 2 or not row[1].strip().isdigit():
            raise ValueError(f"{path}, line {lineno}: expected 'TCIA id,atlas id', got {row}")
        tcia.append(row[0].strip())
        ids.append(int(row[1]))
    if not ids:
        raise ValueError(f"{path}: lists no subjects")
    if len(set(ids)) != len(ids):
        raise ValueError(f"{path}: duplicate atlas ids")
    return ids, tcia


def load_atlas(
    path: str | os.PathLike | None = None, *, expected_subjects: int | None = None
) -> Atlas:
    """Read the Han pelvis atlas.

    Parameters
    ----------
    path : path-like, optional
        Atlas folder; see :func:`resolve_atlas_path` for the default.
    expected_subjects : int, optional
        Fail unless the table lists exactly this many subjects.

    Returns
    -------
    Atlas

    Raises
    ------
    AtlasNotFoundError
        No atlas folder.
    ValueError
        A missing, extra or malformed file (named), unequal vertex counts or triangles that differ
        between subjects of a bone.
    """
    root = resolve_atlas_path(path)
    ids, tcia = _read_table(root / "table.csv")
    if expected_subjects is not None and len(ids) != expected_subjects:
        raise ValueError(
            f"{root / 'table.csv'}: lists {len(ids)} subjects, expected {expected_subjects}"
        )
    per_bone_vertices: list[NDArray[np.float64]] = []
    faces: list[NDArray[np.int64]] = []
    for bone in BONES:
        folder, prefix = BONE_FILES[bone]
        bone_dir = root / "surface" / folder
        if not bone_dir.is_dir():
            raise ValueError(f"{bone_dir}: missing bone folder for {bone}")
        present = {p.name for p in bone_dir.glob(f"{prefix}*_cpd.vtk")}
        expected = {f"{prefix}{i}_cpd.vtk" for i in ids}
        missing = sorted(expected - present)
        if missing:
            raise ValueError(
                f"{bone_dir}: missing subject file(s) {', '.join(missing)} listed in table.csv"
            )
        extra = sorted(present - expected)
        if extra:
            raise ValueError(f"{bone_dir}: file(s) {', '.join(extra)} not listed in table.csv")
        verts, ref_faces, ref_file = [], None, None
        for i in ids:
            f = bone_dir / f"{prefix}{i}_cpd.vtk"
            pts, tri = read_polydata(f)
            if ref_faces is None:
                ref_faces, ref_file = tri, f
            elif pts.shape != verts[0].shape:
                raise ValueError(
                    f"{f}: has {len(pts)} vertices, but {ref_file.name} has {len(verts[0])}: "
                    "no vertex correspondence"
                )
            elif not np.array_equal(tri, ref_faces):
                raise ValueError(
                    f"{f}: triangles differ from those of {ref_file.name}: no mesh correspondence"
                )
            verts.append(pts)
        per_bone_vertices.append(np.stack(verts))
        faces.append(ref_faces)
    counts = {b: v.shape[1] for b, v in zip(BONES, per_bone_vertices, strict=True)}
    if len(set(counts.values())) != 1:
        raise ValueError(f"{root}: bones have different vertex counts {counts}")
    vertices = np.stack(per_bone_vertices, axis=1)
    return Atlas(
        subject_ids=tuple(ids),
        vertices=vertices,
        faces=tuple(faces),
        source=str(root),
        tcia_ids=tuple(tcia),
    )


# ---------------------------------------------------------------------------------------------
# download and install


def _atlas_members(names: list[str]) -> tuple[str, dict[str, str]]:
    """Find the atlas root inside an archive; map member names to relative paths to extract."""
    tables = [n for n in names if PurePosixPath(n).name == "table.csv"]
    roots = [str(PurePosixPath(t).parent) for t in tables]
    roots = [r for r in roots if any(n.startswith(_join(r, "surface/")) for n in names)]
    if len(roots) != 1:
        raise ValueError(
            "archive does not contain exactly one atlas (a folder with table.csv and surface/); "
            f"found {len(roots)}"
        )
    root = roots[0]
    members = {}
    for n in names:
        if not n.startswith(_join(root, "")) and root not in ("", "."):
            continue
        rel = n[len(_join(root, "")) :] if root not in ("", ".") else n
        if not rel or rel.endswith("/"):
            continue
        rel_path = PurePosixPath(rel)
        if rel_path.is_absolute() or ".." in rel_path.parts:
            raise ValueError(f"archive member {n!r} escapes the extraction folder")
        if any(rel == k or (k.endswith("/") and rel.startswith(k)) for k in _KEEP):
            members[n] = rel
    return root, members


def _join(root: str, rest: str) -> str:
    return rest if root in ("", ".") else f"{root}/{rest}"


def install_atlas_archive(
    archive: str | os.PathLike,
    dest: str | os.PathLike,
    *,
    expected_subjects: int | None = 40,
    force: bool = False,
) -> Atlas:
    """Unpack an atlas archive (zip or tar) into ``dest`` and validate it before it appears there.

    Only the parts the project reads are kept (table, surfaces, SSMs, README, licence). Extraction
    goes to a temporary sibling folder that is renamed into place after the atlas loads and
    validates, so ``dest`` is never left half-written.

    Raises
    ------
    ValueError
        Unreadable archive, no atlas inside, unsafe member paths, or an atlas that fails validation.
    FileExistsError
        ``dest`` exists and ``force`` is false.
    """
    archive, dest = Path(archive), Path(dest)
    if dest.exists() and not force:
        raise FileExistsError(f"{dest} already exists; use force=True (--force) to replace it")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".pelvis-atlas-", dir=dest.parent))
    try:
        try:
            _extract(archive, tmp)
            atlas = load_atlas(tmp, expected_subjects=expected_subjects)
        except (zipfile.BadZipFile, tarfile.TarError, OSError) as err:
            raise ValueError(f"{archive}: cannot unpack atlas archive ({err})") from None
        except ValueError as err:
            raise ValueError(f"{archive}: not a valid atlas: {err}") from None
        if dest.exists():
            shutil.rmtree(dest)
        os.replace(tmp, dest)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return replace(atlas, source=str(dest))


def _extract(archive: Path, out: Path) -> None:
    if zipfile.is_zipfile(archive):
        with zipfile.ZipFile(archive) as zf:
            _, members = _atlas_members(zf.namelist())
            for name, rel in members.items():
                target = out / rel
                target.parent.mkdir(parents=True, exist_ok=True)
                with zf.open(name) as src, open(target, "wb") as dst:
                    shutil.copyfileobj(src, dst)
    elif tarfile.is_tarfile(archive):
        with tarfile.open(archive) as tar:
            infos = {m.name: m for m in tar.getmembers() if m.isfile()}
            _, members = _atlas_members(list(infos))
            for name, rel in members.items():
                target = out / rel
                target.parent.mkdir(parents=True, exist_ok=True)
                src = tar.extractfile(infos[name])
                assert src is not None  # isfile() members always have data
                with src, open(target, "wb") as dst:
                    shutil.copyfileobj(src, dst)
    else:
        raise ValueError(f"{archive}: neither a zip nor a tar archive")


def download_atlas(
    dest: str | os.PathLike | None = None,
    *,
    urls: tuple[str, ...] = ATLAS_URLS,
    force: bool = False,
    expected_subjects: int | None = 40,
    progress: Callable[[int, int | None], None] | None = None,
    timeout: float = 60.0,
) -> Atlas:
    """Download the public atlas archive and install it (see :func:`install_atlas_archive`).

    Parameters
    ----------
    dest : path-like, optional
        Install folder; default :func:`default_atlas_dir`.
    urls : tuple of str
        Tried in order until one downloads (``file://`` works, for tests and mirrors).
    force : bool
        Replace an existing atlas.
    progress : callable(bytes_done, bytes_total or None), optional
        Called as the download proceeds.

    Raises
    ------
    ValueError
        Every URL failed, or the archive is not a valid atlas.
    FileExistsError
        An atlas is already installed and ``force`` is false.
    """
    import urllib.error
    import urllib.request

    dest = Path(dest) if dest is not None else default_atlas_dir()
    if dest.exists() and not force:
        raise FileExistsError(f"{dest} already exists; use --force to replace it")
    dest.parent.mkdir(parents=True, exist_ok=True)
    errors = []
    for url in urls:
        fd, part = tempfile.mkstemp(prefix=".atlas-download-", suffix=".part", dir=dest.parent)
        os.close(fd)
        try:
            try:
                with urllib.request.urlopen(url, timeout=timeout) as resp, open(part, "wb") as out:
                    length = resp.headers.get("Content-Length")
                    total = int(length) if length and length.isdigit() else None
                    done = 0
                    while chunk := resp.read(1 << 20):
                        out.write(chunk)
                        done += len(chunk)
                        if progress is not None:
                            progress(done, total)
            except (urllib.error.URLError, OSError, ValueError) as err:
                errors.append(f"{url}: {err}")
                continue
            return install_atlas_archive(
                part, dest, expected_subjects=expected_subjects, force=force
            )
        finally:
            Path(part).unlink(missing_ok=True)
    raise ValueError("could not download the atlas:\n  " + "\n  ".join(errors))
