"""The pelvis model file: one compressed ``.npz`` with a format version, and its loader.

Location, in order: an explicit path (``--model PATH``), ``$PELVICNAV_MODEL``, then the file
packaged in :mod:`pelvicnav.data`. Every array is checked against the others when the file is
read, so a damaged or foreign file is refused with a message naming it, never half-used.

Layout (``/``-separated keys, float arrays stored as float32 where their size matters):
``format_version``, ``provenance`` (JSON text), ``faces/{bone}``,
``ssm/{bone}/{mean,modes,variances}``, ``population/...``, ``combined/{modes,variances}``,
``envelope`` and ``planner/{observed}/...`` (a :class:`PoseModel`, the joint surfaces, minimum
joint spaces and the joint-space model of each planner).
"""

from __future__ import annotations

import functools
import json
import os
import zipfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pelvicnav import BONES
from pelvicnav.model.pelvis import SIZE_MEASURES, CombinedModel, PelvisModel
from pelvicnav.pose.collision import JOINTS, JointSurface
from pelvicnav.pose.joint_space import JointSide, JointSpaceModel
from pelvicnav.pose.spm import PoseModel
from pelvicnav.pose.target import TargetPlanner
from pelvicnav.shape.ssm import ShapeModel

__all__ = [
    "FORMAT_VERSION",
    "MODEL_ENV",
    "PACKAGED_MODEL",
    "ModelFileError",
    "build_model_file",
    "load_model",
    "resolve_model_path",
    "save_model",
]

FORMAT_VERSION = 1
MODEL_ENV = "PELVICNAV_MODEL"
PACKAGED_MODEL = "pelvis_model_v1.npz"
# Arrays at least this large are stored as float32 (model sizes, not precision, limit the file).
_FLOAT32_FROM = 3000
_POSE_FIELDS = ("frame_reference", "mean_shapes", "mean_poses", "metric", "mean", "modes")
_SIDE_ARRAYS = (
    "vertices", "partner_vertices", "region", "region_mean", "offsets", "offset_weights",
    "plane_gap", "plane_weights",
)  # fmt: skip


class ModelFileError(ValueError):
    """A model file that cannot be used (unreadable, unknown version, inconsistent arrays)."""


def _key(bones) -> str:
    return "+".join(bones)


def _store(a) -> NDArray:
    a = np.asarray(a)
    return a.astype(np.float32) if a.dtype == np.float64 and a.size >= _FLOAT32_FROM else a


# ---- writing -----------------------------------------------------------------------------------
def _pose_arrays(prefix: str, m: PoseModel) -> dict[str, NDArray]:
    out = {f"{prefix}/{name}": getattr(m, name) for name in _POSE_FIELDS}
    out[f"{prefix}/variances"] = m.variances
    out[f"{prefix}/frame_bones"] = np.array(m.frame_bones)
    out[f"{prefix}/frame_scale"] = np.array(m.frame_scale)
    return out


def _planner_arrays(prefix: str, p: TargetPlanner) -> dict[str, NDArray]:
    out = _pose_arrays(f"{prefix}/pose", p.model)
    out[f"{prefix}/settings"] = np.array([p.prior, p.gap_quantile])
    js = p.joint_space
    out[f"{prefix}/joint_space/settings"] = np.array(
        [js.spm_weight, js.prior_weight, js.region_radius, *js.max_motion, js.max_pair_distance]
    )
    for pair in JOINTS:
        joint = p.joints[pair]
        for side, bone in enumerate(pair):
            where = f"{prefix}/joints/{_key(pair)}/{bone}"
            out[f"{where}/vertices"] = joint.vertices[side]
            out[f"{where}/faces"] = joint.faces[side]
            out[f"{where}/min_gap"] = np.array(p.min_gap[(pair, bone)])
            s = js.sides.get((pair, bone))
            if s is not None:
                for name in _SIDE_ARRAYS:
                    out[f"{where}/side/{name}"] = getattr(s, name)
    return out


def save_model(model: PelvisModel, path: str | os.PathLike) -> Path:
    """Write the model as one compressed ``.npz`` (atomically: a failed write leaves nothing)."""
    path = Path(path)
    arrays: dict[str, NDArray] = {
        "format_version": np.array(FORMAT_VERSION),
        "provenance": np.array(json.dumps(dict(model.provenance), sort_keys=True)),
    }
    for b, bone in enumerate(BONES):
        arrays[f"faces/{bone}"] = model.faces[b].astype(np.int32)
        ssm = model.shapes[bone]
        arrays |= {f"ssm/{bone}/mean": ssm.mean, f"ssm/{bone}/modes": ssm.modes}
        arrays[f"ssm/{bone}/variances"] = ssm.variances
    arrays |= _pose_arrays("population", model.population)
    arrays["combined/modes"] = model.combined.modes
    arrays["combined/variances"] = model.combined.variances
    arrays["envelope"] = model.envelope
    for observed, planner in model.planners.items():
        arrays |= _planner_arrays(f"planner/{_key(observed)}", planner)
    tmp = path.with_name(path.name + ".part.npz")
    try:
        np.savez_compressed(tmp, **{k: _store(v) for k, v in arrays.items()})
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


# ---- reading -----------------------------------------------------------------------------------
class _Reader:
    """Typed access to the arrays of one file; every failure names the file and the key."""

    def __init__(self, path: Path, data: dict[str, NDArray]):
        self.path, self.data = path, data

    def fail(self, what: str) -> ModelFileError:
        return ModelFileError(f"{self.path}: {what}")

    def get(self, key: str, shape: tuple | None = None, dtype=np.float64) -> NDArray:
        if key not in self.data:
            raise self.fail(f"missing array {key!r} (not a complete pelvis model)")
        a = np.asarray(self.data[key])
        if shape is not None and (
            a.ndim != len(shape)
            or any(s is not None and s != d for s, d in zip(shape, a.shape, strict=True))
        ):
            expected = "x".join("?" if s is None else str(s) for s in shape) or "scalar"
            raise self.fail(f"array {key!r} has shape {a.shape}, expected {expected}")
        if dtype is not None:
            a = a.astype(dtype)
            if np.issubdtype(dtype, np.floating) and not np.all(np.isfinite(a)):
                raise self.fail(f"array {key!r} contains NaN or infinity")
        return a

    def pose_model(self, prefix: str, n_vertices: int) -> PoseModel:
        bones = tuple(str(b) for b in self.get(f"{prefix}/frame_bones", (None,), dtype=None))
        if not bones or any(b not in BONES for b in bones):
            raise self.fail(f"array {prefix}/frame_bones names unknown bones {bones}")
        modes = self.get(f"{prefix}/modes", (21, None))
        k = modes.shape[1]
        variances = self.get(f"{prefix}/variances", (k,))
        if np.any(variances <= 0):
            raise self.fail(f"array {prefix}/variances has non-positive entries")
        return PoseModel(
            frame_bones=bones,
            frame_reference=self.get(f"{prefix}/frame_reference", (len(bones) * n_vertices, 3)),
            mean_shapes=self.get(f"{prefix}/mean_shapes", (3, n_vertices, 3)),
            mean_poses=self.get(f"{prefix}/mean_poses", (3, 4, 4)),
            metric=self.get(f"{prefix}/metric", (21,)),
            mean=self.get(f"{prefix}/mean", (21,)),
            modes=modes,
            variances=variances,
            training=np.zeros((0, 21)),
            frame_scale=bool(self.get(f"{prefix}/frame_scale", (), dtype=bool)),
        )

    def planner(self, prefix: str, faces: tuple, n_vertices: int) -> TargetPlanner:
        pose = self.pose_model(f"{prefix}/pose", n_vertices)
        prior, gap_quantile = self.get(f"{prefix}/settings", (2,))
        s = self.get(f"{prefix}/joint_space/settings", (6,))
        joints, min_gap, sides = {}, {}, {}
        for pair in JOINTS:
            verts, tris = [], []
            for bone in pair:
                where = f"{prefix}/joints/{_key(pair)}/{bone}"
                verts.append(self.index(f"{where}/vertices", n_vertices))
                tris.append(self.index(f"{where}/faces", len(faces[BONES.index(bone)])))
                min_gap[(pair, bone)] = float(self.get(f"{where}/min_gap", ()))
                if f"{where}/side/vertices" in self.data:
                    sides[(pair, bone)] = self.side(f"{where}/side", bone, pair, n_vertices)
            joints[pair] = JointSurface(bones=pair, vertices=tuple(verts), faces=tuple(tris))
        joint_space = JointSpaceModel(
            sides=sides, spm_weight=float(s[0]), prior_weight=float(s[1]),
            region_radius=float(s[2]), max_motion=(float(s[3]), float(s[4])),
            max_pair_distance=float(s[5]),
        )  # fmt: skip
        return TargetPlanner(
            model=pose, faces=faces, joints=joints, min_gap=min_gap,
            joint_space=joint_space, prior=float(prior), gap_quantile=float(gap_quantile),
        )  # fmt: skip

    def side(self, where: str, bone: str, pair: tuple, n_vertices: int) -> JointSide:
        idx = self.index(f"{where}/vertices", n_vertices)
        k, r = len(idx), len(self.index(f"{where}/region", n_vertices))
        return JointSide(
            mover=bone,
            partner=pair[1 - pair.index(bone)],
            vertices=idx,
            partner_vertices=self.index(f"{where}/partner_vertices", n_vertices, (k,)),
            region=self.index(f"{where}/region", n_vertices),
            region_mean=self.get(f"{where}/region_mean", (r, 3)),
            offsets=self.get(f"{where}/offsets", (k, 3)),
            offset_weights=self.get(f"{where}/offset_weights", (k,)),
            plane_gap=self.get(f"{where}/plane_gap", (k,)),
            plane_weights=self.get(f"{where}/plane_weights", (k,)),
        )

    def index(self, key: str, bound: int, shape: tuple = (None,)) -> NDArray[np.int64]:
        a = self.get(key, shape, dtype=None)
        if not np.issubdtype(a.dtype, np.integer) or (a.size and (a.min() < 0 or a.max() >= bound)):
            raise self.fail(f"array {key!r} is not a set of indices below {bound}")
        return a.astype(np.int64)


def _read(path: Path) -> PelvisModel:
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
        for a in data.values():
            a.setflags(write=False)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, KeyError) as err:
        raise ModelFileError(f"{path}: not a readable pelvis model file ({err})") from None
    r = _Reader(path, data)
    version = r.get("format_version", (), dtype=None)
    if not np.issubdtype(version.dtype, np.integer) or int(version) != FORMAT_VERSION:
        raise r.fail(
            f"model format version {version!r} is not supported (this pelvicnav reads version "
            f"{FORMAT_VERSION}); rebuild it with `pelvicnav model build`"
        )
    try:
        provenance = json.loads(str(r.get("provenance", (), dtype=None)))
    except json.JSONDecodeError as err:
        raise r.fail(f"provenance is not JSON ({err})") from None
    n_vertices = r.get("ssm/sacrum/mean", (None, 3)).shape[0]
    faces = tuple(r.index(f"faces/{bone}", n_vertices, (None, 3)) for bone in BONES)
    shapes = {}
    for bone in BONES:
        modes = r.get(f"ssm/{bone}/modes", (3 * n_vertices, None))
        variances = r.get(f"ssm/{bone}/variances", (modes.shape[1],))
        if np.any(variances <= 0):
            raise r.fail(f"array 'ssm/{bone}/variances' has non-positive entries")
        mean = r.get(f"ssm/{bone}/mean", (n_vertices, 3))
        shapes[bone] = ShapeModel(mean=mean, modes=modes, variances=variances)
    planners = {}
    for key in sorted({k.split("/")[1] for k in data if k.startswith("planner/")}):
        observed = tuple(key.split("+"))
        if any(b not in BONES for b in observed):
            raise r.fail(f"planner {key!r} names unknown bones")
        planners[observed] = r.planner(f"planner/{key}", faces, n_vertices)
    if not planners:
        raise r.fail("holds no target planner")
    population = r.pose_model("population", n_vertices)
    n_weights = sum(m.n_modes for m in shapes.values()) + population.n_modes
    combined_modes = r.get("combined/modes", (n_weights, None))
    combined = CombinedModel(
        modes=combined_modes,
        variances=r.get("combined/variances", (combined_modes.shape[1],)),
    )
    return PelvisModel(
        faces=faces,
        shapes=shapes,
        population=population,
        combined=combined,
        envelope=r.get("envelope", (len(SIZE_MEASURES), 2)),
        planners=planners,
        provenance=provenance,
    )


def resolve_model_path(path: str | os.PathLike | None = None) -> Path:
    """``path``, else ``$PELVICNAV_MODEL``, else the packaged model file.

    Raises
    ------
    FileNotFoundError
        The chosen file does not exist (naming where it was looked for and why).
    """
    if path is not None:
        where, how = Path(path), "given path"
    elif os.environ.get(MODEL_ENV):
        where, how = Path(os.environ[MODEL_ENV]), f"${MODEL_ENV}"
    else:
        from importlib.resources import files

        where, how = Path(str(files("pelvicnav.data").joinpath(PACKAGED_MODEL))), "packaged"
    if not where.is_file():
        raise FileNotFoundError(f"no pelvis model file at {where} ({how})")
    return where


def load_model(path: str | os.PathLike | None = None) -> PelvisModel:
    """Read a pelvis model (see :func:`resolve_model_path` for where from); cached per file.

    Raises
    ------
    FileNotFoundError
        No such file.
    ModelFileError
        Unreadable or truncated file, unknown format version, missing or inconsistent arrays.
    """
    where = resolve_model_path(path).resolve()
    stat = where.stat()
    return _cached(str(where), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=4)
def _cached(path: str, mtime_ns: int, size: int) -> PelvisModel:
    return _read(Path(path))


def build_model_file(
    atlas, out: str | os.PathLike, *, variance_kept: float = 0.99, progress=None
) -> PelvisModel:
    """``pelvicnav model build``: fit the model from an atlas (a path, or None for the
    configured one) and save it to ``out``."""
    from pelvicnav.io.atlas import load_atlas
    from pelvicnav.model.pelvis import build_model

    model = build_model(load_atlas(atlas), variance_kept=variance_kept, progress=progress)
    save_model(model, out)
    return model
