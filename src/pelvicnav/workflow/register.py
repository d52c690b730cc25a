"""``pelvicnav register``: the low-level registration of a CT's bones to a view set, from files.

Reads and checks the CT, the label map (any scheme; its bones must be bone and on their sides),
the view set and an optional plan (``dislocated_bone``, ``target_from_current``, optionally
``reference_bone``: a hand-written JSON or ``pelvicnav plan``'s ``plan.json``), registers
(:func:`pelvicnav.register.multibody.register`) and writes ``result.json``,
``transforms/*.tfm`` beside it and, if asked, the overlays. Nothing is written when an input is
refused. The CT's bone models come from the cache when the same CT and label files were read
before (:func:`bones_of_files`, :mod:`pelvicnav.workflow.bone_cache`; ``models_cached`` in
``result.json``).

Tracking: with ``init`` (a previous ``result.json`` of the same CT, bones and number of views)
the registration starts from that frame's poses and geometry, skips stage 1 and refines locally
(:meth:`~pelvicnav.register.settings.RegistrationSettings.tracking`); if that does not converge
it falls back to a full registration. ``result.json`` says which (``mode``: ``first``,
``tracking`` or ``re-registered``) and carries the CT's fingerprint, which ``init`` is checked
against.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np

from pelvicnav import BONES

__all__ = [
    "bones_of_files",
    "ct_fingerprint",
    "read_init",
    "read_register_plan",
    "register_files",
    "track_or_register",
]


def track_or_register(views, models, *, dof, seed, dislocated, previous=None, progress=None):
    """Track from a previous frame, or register afresh; returns ``(result, mode)``.

    ``models``: the CT's bone models (:func:`~pelvicnav.register.pyramid.splat_renderer`).
    ``previous``: ``{"poses": bone -> (4, 4), "projections": optional}`` (a 9-DoF frame's
    estimated geometry stands for the views'). Tracking uses
    :meth:`~pelvicnav.register.settings.RegistrationSettings.tracking`; when it does not
    converge, or with no previous frame, a full registration follows. ``mode`` is ``first``,
    ``tracking`` or ``re-registered``.
    """
    from pelvicnav.register.multibody import register
    from pelvicnav.register.settings import RegistrationSettings

    if previous is not None:
        Ps = previous.get("projections") if dof == 9 else None
        tracked = views if Ps is None else views.with_projections(Ps)
        tracking = RegistrationSettings.tracking()
        result = register(tracked, models, init_poses=previous["poses"], seed=seed,
                          settings=tracking, dislocated=dislocated)  # fmt: skip
        if result.converged:
            return result, "tracking"
    result = register(views, models, seed=seed, settings=RegistrationSettings.for_dof(dof),
                      progress=progress, dislocated=dislocated)  # fmt: skip
    return result, ("first" if previous is None else "re-registered")


def ct_fingerprint(data, world_from_ijk) -> dict:
    """What identifies a CT in ``result.json``: shape, affine and a digest of every 4th voxel."""
    arr = np.ascontiguousarray(np.asarray(data)[::4, ::4, ::4], dtype=np.float32)
    return {"shape": [int(n) for n in np.shape(data)],
            "world_from_ijk": np.round(np.asarray(world_from_ijk, float), 6).tolist(),
            "digest": hashlib.sha256(arr.tobytes()).hexdigest()[:16]}  # fmt: skip


def read_init(path: str | os.PathLike, *, n_views: int, ct: dict) -> dict:
    """A previous frame's ``result.json`` to track from: ``{"poses", "projections"}``.

    Raises
    ------
    ValueError
        Naming ``path``: not a result, a result for other bones, for another CT (its fingerprint,
        :func:`ct_fingerprint`, differs) or for another number of views.
    """
    from pelvicnav.io.jsonfile import read_json

    doc = read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("poses"), dict):
        raise ValueError(f"{path}: not a pelvicnav result (no 'poses')")
    if set(doc["poses"]) != set(BONES):
        raise ValueError(f"{path}: a result for the bones {sorted(doc['poses'])}; this "
                         f"registration has {list(BONES)}")  # fmt: skip
    theirs = doc.get("ct")
    if not isinstance(theirs, dict):
        raise ValueError(
            f"{path}: the result does not say which CT it registered (no 'ct' record; results "
            "of this version do); register without --init"
        )
    same = theirs.get("shape") == ct["shape"] and theirs.get("digest") == ct["digest"]
    A = np.asarray(theirs.get("world_from_ijk", np.zeros((4, 4))), dtype=float)
    if not same or A.shape != (4, 4) or np.abs(A - np.asarray(ct["world_from_ijk"])).max() > 1e-3:
        raise ValueError(f"{path}: the result is for another CT (shape {theirs.get('shape')}, "
                         f"digest {theirs.get('digest')}; this CT: {ct['shape']}, "
                         f"{ct['digest']})")  # fmt: skip
    Ps = doc.get("projection_matrices", [])
    if len(Ps) != n_views:
        raise ValueError(f"{path}: the result has {len(Ps)} view(s), this view set {n_views}")
    poses = {}
    for b in BONES:
        T = np.asarray(doc["poses"][b], dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"{path}: the pose of {b} is not a finite 4 x 4 matrix")
        poses[b] = T
    projections = tuple(np.asarray(P, dtype=float) for P in Ps)
    if any(P.shape != (3, 4) or not np.all(np.isfinite(P)) for P in projections):
        raise ValueError(f"{path}: projection_matrices must be finite 3 x 4 matrices")
    return {"poses": poses, "projections": projections}


def read_register_plan(path: str | os.PathLike) -> dict:
    """A plan as the register command reads it: ``dislocated_bone``, ``target_from_current``
    (4 x 4, CT frame) and ``reference_bone`` (default sacrum). Raises ValueError naming the file."""
    from pelvicnav.io.jsonfile import read_json

    plan = read_json(path)
    if not isinstance(plan, dict):
        raise ValueError(f"{path}: expected a JSON object")
    for key in ("dislocated_bone", "target_from_current"):
        if key not in plan:
            raise ValueError(f"{path}: missing '{key}'")
    if plan["dislocated_bone"] is None:
        raise ValueError(f"{path}: the plan has no dislocated bone; register without --plan")
    plan.setdefault("reference_bone", "sacrum")
    for key in ("dislocated_bone", "reference_bone"):
        if plan[key] not in BONES:
            raise ValueError(f"{path}: {key} {plan[key]!r} is not one of {BONES}")
    T = np.asarray(plan["target_from_current"], dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{path}: target_from_current must be a finite 4 x 4 matrix")
    plan["target_from_current"] = T
    return plan


def register_files(
    ct: str | os.PathLike,
    labels: str | os.PathLike,
    views: str | os.PathLike,
    out: str | os.PathLike,
    *,
    plan: str | os.PathLike | None = None,
    dof: int = 6,
    seed: int = 0,
    overlay: str | os.PathLike | None = None,
    overlay_dicom: bool = False,
    label_scheme: str = "ours",
    series: str | None = None,
    progress=None,
    init: str | os.PathLike | None = None,
):
    """Register and write the outputs; returns ``(record, result)``.

    ``init``: a previous frame's ``result.json`` to track from (see the module's notes). With
    ``dof=9`` its estimated geometry stands for the views' and the poses are refined in 6 DoF.

    Raises
    ------
    ValueError
        Any input refused (the message names the file); nothing is written then.
    """
    from pelvicnav.io.atomic import write_text
    from pelvicnav.io.itk_transform import write_pose_transforms
    from pelvicnav.io.views import ViewSet, read_views
    from pelvicnav.register.settings import RegistrationSettings

    if dof not in (6, 9):
        raise ValueError(f"--dof must be 6 or 9, got {dof}")
    the_plan = read_register_plan(plan) if plan is not None else None
    vs, _ = read_views(views)
    factors = RegistrationSettings.for_dof(dof).factors
    bones, t_models, cached = bones_of_files(ct, labels, label_scheme, series, factors)
    previous = None if init is None else read_init(init, n_views=len(vs), ct=bones.fingerprint)
    result, mode = track_or_register(
        ViewSet(tuple(vs)), bones.models, dof=dof, seed=seed, previous=previous,
        dislocated=None if the_plan is None else the_plan["dislocated_bone"], progress=progress,
    )  # fmt: skip
    record = {"views": [v.name for v in vs], "degrees_of_freedom": dof, "seed": seed,
              "mode": mode, "ct": bones.fingerprint, "models_seconds": t_models,
              "models_cached": cached}  # fmt: skip
    if init is not None:
        record["init"] = str(init)
    record |= result.to_json()
    if the_plan is not None:
        record["residual"] = _residual(result, the_plan, bones.centroids)
    if overlay is not None:
        from pelvicnav.guide.overlay import write_view_overlays

        write_view_overlays(overlay, bones.models.models[-1], vs, result, the_plan,
                            dicom=overlay_dicom)  # fmt: skip
    out = Path(out)
    residual = record.get("residual", {}).get("world_transform")
    write_pose_transforms(out.parent / "transforms", result.poses, residual=residual)
    write_text(out, json.dumps(record, indent=2) + "\n")
    return record, result


def bones_of_files(ct, labels, label_scheme: str, series: str | None, factors, *,
                   voxel_digest: bool = False):  # fmt: skip
    """``(CachedBones, models_seconds, cached)`` of a CT and its label map: from the cache
    (:mod:`pelvicnav.workflow.bone_cache`) when these files were read before, else read, checked
    (:func:`~pelvicnav.workflow.inputs.read_ct_and_bones`), sampled into bone models for the
    pyramid ``factors`` and stored. ``voxel_digest``: with the CT's digest as a plan records it
    (:func:`pelvicnav.io.plan.fingerprint`). ValueError naming the file on bad input."""
    from concurrent.futures import ThreadPoolExecutor

    from pelvicnav.workflow import bone_cache
    from pelvicnav.workflow.inputs import read_ct_and_bones

    with ThreadPoolExecutor(max_workers=2) as pool:
        keyed = pool.submit(_key_then_read, pool, ct, labels, label_scheme, series, factors)
        _import_engine()  # meanwhile, in this thread: a registration needs it either way
        key, reads = keyed.result()
        hit = None if key is None else bone_cache.load(key)
        if hit is not None and (hit.voxel_digest is not None or not voxel_digest):
            return hit, 0.0, True  # nothing built (hashing and loading count as reading)
        from pelvicnav.drr.volume import Volume
        from pelvicnav.register.pyramid import splat_renderer

        data, affine, lab, centroids = read_ct_and_bones(
            ct, labels, label_scheme, series, meanwhile=_import_writers,
            reads=reads,  # None (a stored entry refused): read_ct_and_bones starts them
        )  # fmt: skip
    t_models = time.perf_counter()
    try:  # one set of bone models for registration and overlays
        models = splat_renderer(Volume(data, affine), lab, factors)  # integer HU, no float copy
    except ValueError as err:
        raise ValueError(f"{labels}: {err}") from None
    t_models = time.perf_counter() - t_models
    digest = None
    if voxel_digest:
        from pelvicnav.io.plan import fingerprint

        digest = fingerprint(data, affine)
    entry = bone_cache.CachedBones(models, ct_fingerprint(data, affine), centroids, digest)
    if key is not None:
        bone_cache.store(key, entry)
    return entry, t_models, False


def _key_then_read(pool, ct, labels, label_scheme, series, factors) -> tuple:
    """``(key, reads)``: the bone cache's key of these files (None: no cache, or a file it
    cannot take), hashed in this pool thread (0.1 s for a 52 MB CT: hashing releases the GIL)
    while the caller imports the engine; and, when no entry is stored under it, the CT and label
    map already being read (:func:`~pelvicnav.workflow.inputs.start_reads`), else None. Reading
    as soon as the key says it is needed, not after the imports, saves a CT's first command the
    imports' time."""
    from pelvicnav.workflow import bone_cache

    key = None
    if bone_cache.cache_dir() is not None and all(map(bone_cache.cacheable, (ct, labels))):
        try:
            digest = bone_cache.files_digest(ct, labels)
        except OSError:
            digest = None  # unreadable: the reader says why, naming the file
        if digest is not None:
            from pelvicnav.register.settings import SAMPLE_MM_PER_FACTOR  # light: no scipy

            options = {"scheme": label_scheme, "series": series, "factors": list(factors),
                       "sample_mm": SAMPLE_MM_PER_FACTOR}  # fmt: skip
            key = bone_cache.cache_key(digest, **options)
    if key is not None and bone_cache.stored(key):
        return key, None
    from pelvicnav.workflow.inputs import start_reads

    return key, start_reads(pool, ct, labels, series)


def _import_engine() -> None:
    """The registration's modules (scipy.ndimage among them), imported while the CT's files are
    hashed (pycma and scipy.optimize too measured no better: the imports hold the GIL)."""
    import pelvicnav.register.multibody  # noqa: F401


def _import_writers() -> None:
    """What writes the outputs (SimpleITK for the transforms), imported while a CT decompresses."""
    import SimpleITK  # noqa: F401

    import pelvicnav.io.itk_transform  # noqa: F401


def _residual(result, plan: dict, centroids: dict) -> dict:
    from pelvicnav.guide.residual import residual_reduction

    bone, ref = plan["dislocated_bone"], plan["reference_bone"]
    res = residual_reduction(
        result.poses[ref], result.poses[bone], plan["target_from_current"], centroids[bone]
    )
    return {"bone": bone, "reference_bone": ref, **res.to_json()}
