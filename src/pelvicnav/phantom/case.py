"""One simulated patient: CT, dislocation, radiographs and ground truth, written to a folder.

``simulate_case`` is what ``pelvicnav simulate`` runs. Outputs (all written to a temporary folder
and moved into place only when everything succeeded):

* ``ct.nii.gz`` - the dislocated CT (HU), ``labels.nii.gz`` - its label map (1, 2, 3);
* ``views.json`` + ``<view>.npy`` - radiographs (line integrals) and projection matrices;
* ``meshes/{sacrum,left_hip,right_hip}.{vtk,stl,ply}`` - the ground-truth bone surfaces as they
  lie in ``ct.nii.gz`` (the dislocated bone moved), LPS mm, in the population's vertex order;
* ``landmarks.mrk.json`` - femoral head centres and fiducial beads (3D Slicer Markups, LPS);
* with ``dicom=True``, ``dicom/ct/`` (the CT as a DICOM series) and ``dicom/xray/<view>.dcm``
  (each radiograph as a DICOM XA image whose tags carry its C-arm geometry; the isocentre, which
  DICOM cannot hold, is in ``truth.json``);
* ``truth.json`` - per-bone ``world_from_ct`` poses (the dislocated bone's is the dislocation),
  the dislocation, the femoral heads and the C-arm parameters of every view.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["simulate_case"]

from pelvicnav import BONES


def simulate_case(
    vertices: ArrayLike,
    faces: tuple[ArrayLike, ...],
    out: str | os.PathLike,
    *,
    subject_id: int,
    pattern: str = "open-book",
    bone: str = "left_hip",
    dose_ugy: float = 50.0,
    views: tuple[str, ...] = ("ap", "oblique30"),
    seed: int = 0,
    max_mm: float = 20.0,
    max_deg: float = 10.0,
    ct_options=None,
    dicom: bool = False,
) -> dict:
    """Simulate a dislocated patient and its radiographs; returns the truth record.

    Raises
    ------
    ValueError
        Bad dose, pattern, bone or view name, or a view that misses the pelvis; nothing is
        written then.
    """
    from pelvicnav.io.atomic import atomic_directory
    from pelvicnav.phantom.ctsynth import synthesize_ct
    from pelvicnav.phantom.dislocate import apply_dislocation, draw_dislocation
    from pelvicnav.phantom.xray import DetectorModel, quanta_per_pixel, standard_view

    # Validate the cheap things before the expensive ones.
    if not views:
        raise ValueError("at least one view is needed")
    V = np.asarray(vertices, dtype=np.float64)
    isocenter = tuple(float(c) for c in V.reshape(-1, 3).mean(axis=0))
    carms = {name: standard_view(name, isocenter=isocenter) for name in views}
    for carm in carms.values():
        quanta_per_pixel(dose_ugy, carm, DetectorModel())  # raises on a bad dose
    rng = np.random.default_rng([seed, subject_id])
    disl = draw_dislocation(
        V, faces, bone=bone, pattern=pattern, rng=rng, max_mm=max_mm, max_deg=max_deg
    )
    ct = synthesize_ct(V, faces, rng=rng, options=ct_options)
    moved_ct, moved = apply_dislocation(ct, V, faces, disl, rng=rng)
    radiographs = _radiographs(moved_ct, carms, dose_ugy, rng)
    truth = _truth(ct, moved_ct, disl, carms, subject_id=subject_id, seed=seed, dose_ugy=dose_ugy)
    hu_int16 = np.clip(np.round(moved_ct.hu.data), -32768, 32767).astype(np.int16)
    with atomic_directory(out) as tmp:
        _write_case(tmp, hu_int16, ct, moved_ct, moved, faces, radiographs, truth, subject_id)
        if dicom:
            _write_dicom(tmp / "dicom", hu_int16, moved_ct.hu.world_from_ijk, radiographs, carms,
                         subject_id, dose_ugy)  # fmt: skip
    truth["moved_vertices"] = moved
    return truth


def _radiographs(moved_ct, carms: dict, dose_ugy: float, rng: np.random.Generator) -> list:
    """One simulated radiograph (line integrals, quantum noise) of the dislocated patient per
    C-arm, as views."""
    from pelvicnav.io.views import View
    from pelvicnav.phantom.xray import simulate_radiograph

    out = []
    for name, carm in carms.items():
        rad = simulate_radiograph(moved_ct.hu, carm, dose_ugy=dose_ugy, rng=rng)
        out.append(View(name=name, image=rad.line_integrals,
                        projection_matrix=carm.projection_matrix, pixel_spacing=carm.pixel_spacing,
                        meta={"dose_ugy": dose_ugy, "orbit_deg": carm.orbit_deg,
                              "tilt_deg": carm.tilt_deg}))  # fmt: skip
    return out


def _truth(ct, moved_ct, disl, carms: dict, *, subject_id: int, seed: int,
           dose_ugy: float) -> dict:  # fmt: skip
    """``truth.json``'s record: each bone's pose, the dislocation, beads, femoral heads, views."""
    from pelvicnav.geometry import transforms as tf

    poses = {b: np.eye(4) for b in BONES}
    poses[disl.bone] = disl.transform
    return {
        "subject_id": int(subject_id),
        "seed": int(seed),
        "poses_world_from_ct": {b: T.tolist() for b, T in poses.items()},
        "dislocation": {
            "bone": disl.bone,
            "pattern": disl.pattern,
            "translation_mm": disl.translation_mm,
            "rotation_deg": disl.rotation_deg,
            "pivot_mm": disl.pivot.tolist(),
            "attempts": disl.attempts,
            "geodesic_6dof": tf.se3_log(disl.transform).tolist(),
        },
        "beads_mm": {
            "preoperative": ct.beads.tolist(),
            "dislocated": moved_ct.beads.tolist(),
            "bone_labels": ct.bead_bones.tolist(),
            "radius_mm": ct.bead_radius,
        },
        "femoral_heads_mm": {
            "left": ct.femoral_heads[0].tolist(),
            "right": ct.femoral_heads[1].tolist(),
        },
        "views": {
            name: {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(carm).items()}
            for name, carm in carms.items()
        },
        "dose_ugy": dose_ugy,
        "note": "CT and label map are the dislocated patient; world_from_ct maps each bone of the "
        "preoperative (undislocated) CT frame to this patient's frame.",
    }


def _write_case(tmp: Path, hu_int16: NDArray, ct, moved_ct, moved, faces, radiographs: list,
                truth: dict, subject_id: int) -> None:  # fmt: skip
    """The case's files (the CT ``hu_int16``, labels, views, meshes, landmarks, truth) into
    ``tmp``."""
    from pelvicnav.io.markups import write_markups
    from pelvicnav.io.mesh_files import write_meshes
    from pelvicnav.io.nifti import write_nifti
    from pelvicnav.io.views import write_views

    write_nifti(tmp / "ct.nii.gz", hu_int16, moved_ct.hu.world_from_ijk)
    write_nifti(tmp / "labels.nii.gz", moved_ct.labels, moved_ct.hu.world_from_ijk)
    write_views(tmp, radiographs, degrees_of_freedom=6)
    (tmp / "meshes").mkdir()
    for b, bone in enumerate(BONES):
        title = f"pelvicnav simulate subject {subject_id} {bone} (CT frame)"
        write_meshes(tmp / "meshes", bone, moved[b], faces[b], title=title)
    write_markups(tmp / "landmarks.mrk.json", _landmarks(ct, moved_ct), name="landmarks")
    (tmp / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")


def _landmarks(ct, moved_ct) -> dict:
    heads = np.asarray(ct.femoral_heads)[:, :3]
    points = {"femoral_head_left": heads[0], "femoral_head_right": heads[1]}
    for n, p in enumerate(np.asarray(moved_ct.beads).reshape(-1, 3), start=1):
        points[f"bead_{n}_{BONES[int(ct.bead_bones[n - 1]) - 1]}"] = p
    return points


def _write_dicom(folder, hu, world_from_ijk, radiographs, carms, subject_id, dose_ugy) -> None:
    from pelvicnav.io.dicom_base import DicomIdentity
    from pelvicnav.io.dicom_ct import write_ct_series
    from pelvicnav.io.xray_dicom import write_xray_dicom

    identity = DicomIdentity(patient_id=f"PELVICNAV-{subject_id}").filled()
    write_ct_series(folder / "ct", hu, world_from_ijk, identity=identity)
    (folder / "xray").mkdir()
    for view in radiographs:
        write_xray_dicom(folder / "xray" / f"{view.name}.dcm", view.image, carms[view.name],
                         identity=identity, description=view.name, dose_ugy=dose_ugy)  # fmt: skip
