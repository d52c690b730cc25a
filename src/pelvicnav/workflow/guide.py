"""``pelvicnav guide``: one intraoperative frame after another, against a plan.

A session folder belongs to one plan (``session.json`` holds the plan's id). Each call:

1. reads the plan and its CT (refused if the CT's voxels are not the plan's), the bones' labels
   and the frame's views; the CT's bone models come from the cache after the first frame
   (:mod:`pelvicnav.workflow.bone_cache`: the same CT and label files' bytes);
2. registers: the first frame (or a frame with another number of views, or 9 DoF) with both
   stages and the plan's dislocated bone; a later frame starts from the previous frame's poses
   and refines locally (stage 2 only, one sweep over both pyramid levels) — if that does not
   converge, the frame is registered again from scratch;
3. writes ``frame-NNN/`` atomically: ``result.json`` (poses, flags, timings, the residual in the
   surgeon's terms), ``transforms/*.tfm`` and ``overlay_<view>.png`` (registered edges yellow,
   target green);
4. updates ``session.json`` and rewrites ``report.html``.

A frame whose registration is not converged is recorded as *unreliable*: the report shows it as
such and never as guidance.
"""

from __future__ import annotations

import datetime
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pelvicnav import BONES

__all__ = ["FrameResult", "guide_frame", "read_session"]

SESSION_FORMAT = "pelvicnav-session"


@dataclass(frozen=True)
class FrameResult:
    """One guided frame.

    Attributes
    ----------
    index : int
    folder : Path
    mode : str
        ``"first"`` (both stages), ``"tracking"`` (from the previous frame) or ``"re-registered"``
        (tracking did not converge, so both stages).
    converged : bool
    residual : dict bone -> dict
        Residual reduction per dislocated bone (``description``, ``distance_mm``, ...).
    seconds : float
    record : dict
        What ``result.json`` holds.
    """

    index: int
    folder: Path
    mode: str
    converged: bool
    residual: dict
    seconds: float
    record: dict


def read_session(session: str | os.PathLike) -> dict | None:
    """The session record of a folder, or None for a new (absent or empty) folder."""
    from pelvicnav.io.jsonfile import read_json

    path = Path(session) / "session.json"
    if not path.exists():
        if Path(session).exists() and any(Path(session).iterdir()):
            raise ValueError(f"{session}: not a pelvicnav session folder (no session.json)")
        return None
    doc = read_json(path)
    if not isinstance(doc, dict) or doc.get("format") != SESSION_FORMAT:
        raise ValueError(f"{path}: not a pelvicnav session")
    return doc


def _write_json(path: Path, doc: dict) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, path)


def guide_frame(
    plan_dir: str | os.PathLike,
    views: str | os.PathLike,
    session: str | os.PathLike,
    *,
    seed: int = 0,
    dof: int = 6,
    progress=None,
) -> FrameResult:
    """Register one frame against a plan and add it to a session folder.

    Raises
    ------
    ValueError
        A plan that does not validate, its CT changed or missing, a views file that does not
        read (a missing image, a singular matrix), a session folder of another plan; nothing is
        written then.
    """
    from pelvicnav.io.plan import read_plan
    from pelvicnav.io.views import read_views

    plan_dir = Path(plan_dir)
    plan = read_plan(plan_dir)
    session = Path(session)
    record = read_session(session)
    if record is not None and record.get("plan_id") != plan.identity:
        raise ValueError(
            f"{session}: this session belongs to another plan ({record.get('plan')}, id "
            f"{record.get('plan_id')}); use a new session folder for {plan_dir}"
        )
    vs, file_dof = read_views(views)
    dof = dof if dof != 6 else file_dof
    bones = _plan_bones(plan, plan_dir, dof)
    frames = (record or {}).get("frames", [])
    previous = _previous(session, frames, len(vs), dof)
    started = time.perf_counter()
    result, mode, models = _register(bones.models, vs, plan, previous, seed, dof, progress)
    residual = _residuals(result, plan, bones.centroids)
    index = len(frames) + 1
    out = {"frame": index, "mode": mode, "views": str(Path(views).resolve()), "seed": seed,
           "degrees_of_freedom": dof, "plan": str(plan_dir.resolve()), "plan_id": plan.identity,
           "reliable": bool(result.converged), **result.to_json(), "residual": residual,
           "time": datetime.datetime.now().isoformat(timespec="seconds")}  # fmt: skip
    folder = _write_frame(session, index, out, models, vs, result, plan)
    seconds = time.perf_counter() - started
    summary = {b: r["description"] for b, r in residual.items()}
    frames = [*frames, {"frame": index, "folder": folder.name, "mode": mode,
                        "reliable": bool(result.converged), "seconds": seconds,
                        "residual": summary}]  # fmt: skip
    _write_json(session / "session.json", {
        "format": SESSION_FORMAT, "plan": str(plan_dir.resolve()), "plan_id": plan.identity,
        "frames": frames,
    })  # fmt: skip
    from pelvicnav.guide.report import write_report

    write_report(session)
    return FrameResult(index, folder, mode, bool(result.converged), residual, seconds, out)


def _previous(session: Path, frames: list, n_views: int, dof: int) -> dict | None:
    """The last frame's poses, when the new frame can track from them."""
    from pelvicnav.io.jsonfile import read_json

    if not frames or dof != 6:
        return None
    last = read_json(session / frames[-1]["folder"] / "result.json")
    if len(last.get("projection_matrices", [])) != n_views or not last.get("reliable", False):
        return None
    return {b: np.asarray(last["poses"][b], dtype=np.float64) for b in BONES}


def _plan_bones(plan, plan_dir: Path, dof: int):
    """The plan's CT and labels as bone models (:func:`~pelvicnav.workflow.register.
    bones_of_files`: from the cache after the first frame), refused unless the CT's voxels are
    the plan's."""
    from pelvicnav.register.settings import RegistrationSettings
    from pelvicnav.workflow.register import bones_of_files

    factors = RegistrationSettings.for_dof(dof).factors
    try:
        bones, _, _ = bones_of_files(plan.ct.path, plan_dir / plan.labels, "ours", None, factors,
                                     voxel_digest=True)  # fmt: skip
    except ValueError as err:
        raise ValueError(f"{plan_dir / 'plan.json'}: cannot read the plan's CT or labels "
                         f"({err})") from None  # fmt: skip
    plan.ct.check_fingerprint(bones.voxel_digest, bones.fingerprint["shape"],
                              source=str(plan.ct.path))  # fmt: skip
    return bones


def _register(models, vs, plan, previous, seed, dof, progress):
    from pelvicnav.io.views import ViewSet
    from pelvicnav.workflow.register import track_or_register

    result, mode = track_or_register(
        ViewSet(tuple(vs)), models, dof=dof, seed=seed,
        dislocated=plan.dislocated[0] if len(plan.dislocated) == 1 else None,
        previous=None if previous is None else {"poses": previous}, progress=progress,
    )  # fmt: skip
    return result, mode, models.models[-1]


def _residuals(result, plan, centroids: dict) -> dict:
    from pelvicnav.guide.residual import residual_reduction

    out = {}
    for bone, T in plan.targets.items():
        r = residual_reduction(result.poses[plan.reference_bone], result.poses[bone], T,
                               centroids[bone])  # fmt: skip
        out[bone] = r.to_json()
    return out


def _write_frame(session: Path, index: int, record: dict, models, vs, result, plan) -> Path:
    from pelvicnav.guide.overlay import write_view_overlays
    from pelvicnav.io.atomic import atomic_directory
    from pelvicnav.io.itk_transform import write_pose_transforms

    session.mkdir(parents=True, exist_ok=True)
    folder = session / f"frame-{index:03d}"
    first = plan.dislocated[0] if plan.dislocated else None
    plan_dict = None
    if first is not None:
        plan_dict = {"dislocated_bone": first, "reference_bone": plan.reference_bone,
                     "target_from_current": plan.targets[first]}  # fmt: skip
    with atomic_directory(folder) as tmp:
        write_view_overlays(tmp, models, vs, result, plan_dict)
        residual = record["residual"].get(first, {}).get("world_transform") if first else None
        write_pose_transforms(tmp / "transforms", result.poses, residual=residual)
        _write_json(tmp / "result.json", record)
    return folder
