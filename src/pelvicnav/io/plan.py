"""The plan: one typed object between ``pelvicnav plan`` and ``pelvicnav guide``, as versioned JSON.

A plan folder holds ``plan.json`` (this module), ``labels.nii.gz`` (the bones on the CT's grid,
1 sacrum, 2 left hip, 3 right hip) and ``meshes/`` (each bone now, and each dislocated bone at its
target). The plan names the CT it was made from by path *and* by a fingerprint of its voxels and
grid, so guidance refuses another CT. Reading validates every field and names the file.

``plan.json`` also carries ``dislocated_bone`` and ``target_from_current`` of the first dislocated
bone at its top level: the keys ``pelvicnav register --plan`` reads.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav import BONES, LABELS

__all__ = ["PLAN_FORMAT", "PLAN_VERSION", "CTReference", "Plan", "read_plan", "write_plan"]

PLAN_FORMAT = "pelvicnav-plan"
PLAN_VERSION = 1


def _matrix(value, what: str, where: str, *, rigid: bool = False) -> NDArray[np.float64]:
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {what} must be a 4 x 4 matrix") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"{where}: {what} must be a finite 4 x 4 affine matrix")
    if rigid:
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
            raise ValueError(f"{where}: {what} must be rigid (a rotation and a translation)")
    return T


@dataclass(frozen=True)
class CTReference:
    """The CT a plan was made from.

    Attributes
    ----------
    path : str
        Where it was read (absolute).
    fingerprint : str
        SHA-256 of the voxel values, their type and the grid (shape and affine, to 1e-4 mm).
    shape : (3,) int
    world_from_ijk : (4, 4) float64
    """

    path: str
    fingerprint: str
    shape: tuple[int, int, int]
    world_from_ijk: NDArray[np.float64]

    @classmethod
    def of(cls, path: str | os.PathLike, data: ArrayLike, world_from_ijk: ArrayLike) -> CTReference:
        A = np.asarray(world_from_ijk, dtype=np.float64)
        return cls(str(Path(path).resolve()), fingerprint(data, A), tuple(np.shape(data)), A)

    def check(self, data: ArrayLike, world_from_ijk: ArrayLike, *, source: str) -> None:
        """Raise unless ``data`` on ``world_from_ijk`` is this CT."""
        self.check_fingerprint(fingerprint(data, world_from_ijk), np.shape(data), source=source)

    def check_fingerprint(self, found: str, shape, *, source: str) -> None:
        """Raise unless ``found`` (:func:`fingerprint` of a CT of ``shape``) is this CT's."""
        if found != self.fingerprint:
            raise ValueError(
                f"{source}: this is not the CT the plan was made from (plan: {self.path}, "
                f"{self.shape[0]} x {self.shape[1]} x {self.shape[2]}, fingerprint "
                f"{self.fingerprint[:12]}; found {tuple(shape)}, {found[:12]})"
            )


def fingerprint(data: ArrayLike, world_from_ijk: ArrayLike) -> str:
    """SHA-256 of a volume's voxels (C order), dtype, shape and affine (rounded to 1e-4 mm)."""
    d = np.ascontiguousarray(data)
    h = hashlib.sha256()
    h.update(f"{d.dtype.str}{d.shape}".encode())
    h.update(np.round(np.asarray(world_from_ijk, dtype=np.float64), 4).tobytes())
    h.update(memoryview(d.reshape(-1)).cast("B"))
    return h.hexdigest()


@dataclass(frozen=True)
class Plan:
    """A reduction plan made from one CT.

    Attributes
    ----------
    ct : CTReference
    dislocated : tuple of str
        The dislocated innominate(s), possibly none.
    targets : dict bone -> (4, 4) float64
        ``target_from_current`` of each dislocated bone, rigid, in the CT frame.
    reference_bone : str
        The bone the targets are relative to at guidance (never dislocated).
    decision : dict
        How the dislocated bone(s) were chosen: ``mode`` ("auto" or "given"), per-side scores,
        the margin and a sentence.
    residual_in_ct : dict bone -> dict
        The reduction as seen in the CT (translation mm, rotation deg, description).
    method : str
    model : dict
        Model provenance (DOI, licence, creation date).
    labels : str
        Label map file, relative to the plan folder.
    meshes : dict bone -> str
        Each bone's mesh now (relative paths); ``"{bone}_target"`` for the targets.
    created : str
    """

    ct: CTReference
    dislocated: tuple[str, ...]
    targets: dict[str, NDArray[np.float64]]
    reference_bone: str = "sacrum"
    decision: dict = field(default_factory=dict)
    residual_in_ct: dict = field(default_factory=dict)
    method: str = ""
    model: dict = field(default_factory=dict)
    labels: str = "labels.nii.gz"
    meshes: dict = field(default_factory=dict)
    created: str = ""

    def __post_init__(self) -> None:
        for b in self.dislocated:
            if b not in ("left_hip", "right_hip"):
                raise ValueError(f"dislocated bone {b!r} must be left_hip or right_hip")
        if set(self.targets) != set(self.dislocated):
            raise ValueError("a plan needs one target per dislocated bone")
        if self.reference_bone not in BONES or self.reference_bone in self.dislocated:
            raise ValueError(f"reference bone {self.reference_bone!r} must be an undislocated bone")

    @property
    def identity(self) -> str:
        """A short id of the plan: the CT's fingerprint and the targets (for session folders)."""
        h = hashlib.sha256(self.ct.fingerprint.encode())
        for b in sorted(self.targets):
            h.update(b.encode() + np.round(self.targets[b], 9).tobytes())
        return h.hexdigest()[:16]

    def to_json(self) -> dict:
        first = self.dislocated[0] if self.dislocated else None
        return {
            "format": PLAN_FORMAT,
            "version": PLAN_VERSION,
            "id": self.identity,
            "created": self.created,
            "ct": {
                "path": self.ct.path,
                "fingerprint": self.ct.fingerprint,
                "shape": list(self.ct.shape),
                "world_from_ijk": self.ct.world_from_ijk.tolist(),
            },
            "labels": self.labels,
            "bone_labels": {b: LABELS[b] for b in BONES},
            "meshes": self.meshes,
            "dislocated": list(self.dislocated),
            "reference_bone": self.reference_bone,
            "targets_from_current": {b: T.tolist() for b, T in self.targets.items()},
            "decision": self.decision,
            "residual_in_ct": self.residual_in_ct,
            "method": self.method,
            "model": self.model,
            # what `pelvicnav register --plan` reads
            "dislocated_bone": first,
            "target_from_current": self.targets[first].tolist() if first else None,
        }


def write_plan(folder: str | os.PathLike, plan: Plan) -> Path:
    """Write ``folder/plan.json`` (atomically)."""
    path = Path(folder) / "plan.json"
    tmp = path.with_name("plan.json.part")
    tmp.write_text(json.dumps(plan.to_json(), indent=2) + "\n")
    os.replace(tmp, path)
    return path


def read_plan(path: str | os.PathLike) -> Plan:
    """Read and validate a plan (``plan.json`` or the folder holding it).

    Raises
    ------
    ValueError
        Not a pelvicnav plan, another version, a missing or malformed field, a non-rigid target,
        a label map or mesh file that is not there; the message names the file.
    """
    from pelvicnav.io.jsonfile import read_json

    path = Path(path)
    if path.is_dir():
        path = path / "plan.json"
    doc = read_json(path)
    where = str(path)
    if not isinstance(doc, dict) or doc.get("format") != PLAN_FORMAT:
        raise ValueError(f'{where}: not a pelvicnav plan (no "format": "{PLAN_FORMAT}")')
    if doc.get("version") != PLAN_VERSION:
        raise ValueError(f"{where}: plan version {doc.get('version')!r}; this pelvicnav reads 1")
    try:
        ct = doc["ct"]
        ref = CTReference(
            str(ct["path"]),
            str(ct["fingerprint"]),
            tuple(int(n) for n in ct["shape"]),
            _matrix(ct["world_from_ijk"], "ct.world_from_ijk", where),
        )
        dislocated = tuple(str(b) for b in doc["dislocated"])
        targets = {
            str(b): _matrix(T, f"the target of {b}", where, rigid=True)
            for b, T in doc["targets_from_current"].items()
        }
        plan = Plan(
            ct=ref, dislocated=dislocated, targets=targets,
            reference_bone=str(doc.get("reference_bone", "sacrum")),
            decision=dict(doc.get("decision", {})),
            residual_in_ct=dict(doc.get("residual_in_ct", {})),
            method=str(doc.get("method", "")), model=dict(doc.get("model", {})),
            labels=str(doc.get("labels", "labels.nii.gz")), meshes=dict(doc.get("meshes", {})),
            created=str(doc.get("created", "")),
        )  # fmt: skip
    except KeyError as err:
        raise ValueError(f"{where}: missing {err}") from None
    except (TypeError, AttributeError) as err:
        raise ValueError(f"{where}: malformed plan ({err})") from None
    except ValueError as err:
        raise ValueError(f"{where}: {err}" if where not in str(err) else str(err)) from None
    for name in (plan.labels, *plan.meshes.values()):
        if not (path.parent / name).is_file():
            raise ValueError(f"{where}: the plan's file {name} is missing from {path.parent}")
    return plan
