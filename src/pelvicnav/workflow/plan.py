"""``pelvicnav plan``: from a CT (and, optionally, its bone labels) to a reduction plan.

1. The CT (and a label map, when given) are read and checked (:mod:`pelvicnav.io.volume`,
   :func:`pelvicnav.shape.labels.check_bone_labels`).
2. The bones as meshes in the model's correspondence: the model fitted to the labels, or, with
   no labels, segmented by the active shape model (:func:`pelvicnav.shape.asm.segment_ct`).
3. Which innominate is dislocated: given, or ``auto`` — each hip's target is predicted from the
   sacrum and the other hip (SPM_CC); the hip that sits further from where the others put it,
   by more than :data:`DISLOCATION_THRESHOLD` (mm at its centroid plus degrees), is the dislocated
   one; below it, none. The decision, both scores and the margin go into the plan.
4. The target of each dislocated bone: SPM_CC from the undislocated bones.
5. Written atomically to the plan folder: ``plan.json`` (:class:`pelvicnav.io.plan.Plan`),
   ``labels.nii.gz``, ``meshes/{bone}.{vtk,stl}`` and ``meshes/{bone}_target.{vtk,stl}``,
   ``reduced_ct.nii.gz`` (the dislocated bone moved to its target, the gap infilled as the
   simulator does), ``rendering.png`` (current against target, cf. figure 3c of Han et al. 2020)
   and ``contours.png``.
"""

from __future__ import annotations

import datetime
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pelvicnav import BONES

__all__ = ["DISLOCATION_THRESHOLD", "Decision", "decide_dislocated", "make_plan"]

HIPS = ("left_hip", "right_hip")
# Measured on leave-one-out atlas cases (docs/workflow.md): a hip is called dislocated when the
# SPM_CC correction its planner proposes reaches DISLOCATION_THRESHOLD (mm at its centroid plus
# half its degrees); the side is the hip whose correction and whose pairing with the sacrum
# (SPM weight energy) stand out most, each in units of its typical left-right difference.
DISLOCATION_THRESHOLD = 6.0
DEG_WEIGHT = 0.5
CORRECTION_SCALE = 4.3
ENERGY_SCALE = 5.8


@dataclass(frozen=True)
class Decision:
    """Which innominate is dislocated, and how clearly.

    Attributes
    ----------
    dislocated : tuple of str
        The chosen bone(s); empty for none.
    scores : dict bone -> dict
        Per hip: ``mm`` and ``deg`` of the correction its planner proposes, ``correction``
        (mm + DEG_WEIGHT x deg), ``pair_energy`` (how unusual the hip's pose against the sacrum
        is) and ``side`` (the combined side score).
    margin : float
        Detection margin: the larger correction minus the threshold (negative: none).
    side_margin : float
        The side score of the chosen hip minus the other's.
    mode : str
        ``"auto"`` or ``"given"``.
    """

    dislocated: tuple[str, ...]
    scores: dict
    margin: float
    side_margin: float
    mode: str

    def describe(self) -> str:
        s = ", ".join(f"{b} {v['mm']:.1f} mm / {v['deg']:.1f} deg" for b, v in self.scores.items())
        what = " and ".join(self.dislocated) if self.dislocated else "none"
        if self.mode == "given":
            return f"dislocated: {what} (given); the model's corrections: {s}"
        return (f"dislocated: {what} (auto; detection margin {self.margin:+.1f}, side margin "
                f"{self.side_margin:.2f}; corrections {s})")  # fmt: skip

    def to_json(self) -> dict:
        return {"mode": self.mode, "dislocated": list(self.dislocated), "scores": self.scores,
                "margin": self.margin, "side_margin": self.side_margin,
                "threshold": DISLOCATION_THRESHOLD, "description": self.describe()}  # fmt: skip


def _correction(planner, meshes: dict, bone: str) -> tuple[np.ndarray, float, float]:
    from pelvicnav.geometry import transforms as tf

    observed = {b: meshes[b] for b in planner.observed}
    T = planner.estimate(observed, {bone: meshes[bone]})[bone].target_from_current
    c = meshes[bone].mean(axis=0)
    mm = float(np.linalg.norm(tf.apply(T, c[None])[0] - c))
    deg = float(np.degrees(np.linalg.norm(tf.rotvec_from_matrix(T[:3, :3]))))
    return T, mm, deg


def decide_dislocated(meshes: dict, model, requested: str = "auto") -> tuple[Decision, dict]:
    """Which innominate is dislocated, and each one's SPM_CC correction.

    Parameters
    ----------
    meshes : dict bone -> (n_vertices, 3)
        The three bones in the model's correspondence (CT frame, mm).
    model
        Anything with ``planner(observed)`` (a :class:`~pelvicnav.model.PelvisModel`).
    requested : {"auto", "left_hip", "right_hip", "both", "none"}

    Returns
    -------
    Decision, dict bone -> (4, 4) target_from_current of each dislocated bone
    """
    if requested not in ("auto", "left_hip", "right_hip", "both", "none"):
        raise ValueError(
            f"--dislocated must be auto, left_hip, right_hip, both or none, got {requested!r}"
        )
    corrections, scores = {}, {}
    for hip in HIPS:
        other = HIPS[1 - HIPS.index(hip)]
        corrections[hip] = T, mm, deg = _correction(model.planner(("sacrum", other)), meshes, hip)
        pairing = model.planner(("sacrum", hip)).plausibility(
            {b: meshes[b] for b in ("sacrum", hip)}
        )
        scores[hip] = {"mm": mm, "deg": deg, "correction": mm + DEG_WEIGHT * deg,
                       "pair_energy": pairing}  # fmt: skip
    for hip in HIPS:
        scores[hip]["side"] = (scores[hip]["correction"] / CORRECTION_SCALE
                               + scores[hip]["pair_energy"] / ENERGY_SCALE)  # fmt: skip
    side = max(HIPS, key=lambda h: scores[h]["side"])
    other = HIPS[1 - HIPS.index(side)]
    strongest = max(scores[h]["correction"] for h in HIPS)
    margin = strongest - DISLOCATION_THRESHOLD
    side_margin = scores[side]["side"] - scores[other]["side"]
    if requested == "auto":
        chosen, mode = ((side,) if margin >= 0 else ()), "auto"
    else:
        chosen, mode = {"both": HIPS, "none": ()}.get(requested, (requested,)), "given"
    targets = {h: corrections[h][0] for h in chosen}
    if len(chosen) == 2:  # both out: both from the sacrum alone
        both = model.planner(("sacrum",)).estimate({"sacrum": meshes["sacrum"]},
                                                   {h: meshes[h] for h in HIPS})  # fmt: skip
        targets = {h: both[h].target_from_current for h in HIPS}
    return Decision(tuple(chosen), scores, float(margin), float(side_margin), mode), targets


def make_plan(
    ct: str | os.PathLike,
    out: str | os.PathLike,
    *,
    labels: str | os.PathLike | None,
    label_scheme: str = "ours",
    dislocated: str = "auto",
    model=None,
    series: str | None = None,
    progress=None,
):
    """Make a reduction plan from a CT; returns the :class:`~pelvicnav.io.plan.Plan`.

    Parameters
    ----------
    ct, labels : paths
        Anything :func:`pelvicnav.io.volume.read_volume` reads; ``labels`` on the CT's grid.
    out : path
        The plan folder (written atomically: nothing is left of a failed run).
    dislocated : {"auto", "left_hip", "right_hip", "both", "none"}
    progress : callable(str), optional
        Told each step's name.

    Raises
    ------
    ValueError
        Unreadable or implausible inputs, a CT on which the ASM finds no bone.
    """
    from pelvicnav.guide.residual import residual_reduction
    from pelvicnav.io.plan import CTReference, Plan
    from pelvicnav.model import load_model
    from pelvicnav.workflow.inputs import bones_of_ct

    say = progress or (lambda step: None)
    if dislocated not in ("auto", "left_hip", "right_hip", "both", "none"):
        raise ValueError(
            f"--dislocated must be auto, left_hip, right_hip, both or none, got {dislocated!r}"
        )
    started = time.perf_counter()
    model = model or load_model()
    bones = bones_of_ct(ct, labels, label_scheme=label_scheme, series=series, model=model,
                        progress=say)  # fmt: skip
    hu, A, ours, meshes = bones.hu, bones.world_from_ijk, bones.labels, bones.meshes
    say("planning the target")
    decision, targets = decide_dislocated(meshes, model, dislocated)
    residual = {}
    for bone, T in targets.items():
        r = residual_reduction(np.eye(4), np.eye(4), T, meshes[bone].mean(axis=0))
        residual[bone] = r.to_json()
    mesh_files = {b: f"meshes/{b}.vtk" for b in BONES} | {
        f"{b}_target": f"meshes/{b}_target.vtk" for b in targets
    }
    plan = Plan(
        ct=CTReference.of(ct, hu, A), dislocated=decision.dislocated, targets=targets,
        decision=decision.to_json(), residual_in_ct=residual,
        method=f"bones: {bones.method}; targets by SPM_CC from the undislocated bones "
        "(Han et al. 2020, section 2.1.2)",
        model={k: model.provenance.get(k) for k in ("doi", "licence", "note", "created")},
        meshes=mesh_files, created=datetime.datetime.now().isoformat(timespec="seconds"),
    )  # fmt: skip
    say("writing")
    _write(Path(out), plan, hu, A, ours, meshes, model, time.perf_counter() - started)
    return plan


def _write(out: Path, plan, hu, A, ours, meshes, model, seconds: float) -> None:
    from pelvicnav.geometry import transforms as tf
    from pelvicnav.io.atomic import atomic_directory
    from pelvicnav.io.mesh_files import write_meshes
    from pelvicnav.io.nifti import write_nifti
    from pelvicnav.io.plan import write_plan
    from pelvicnav.shape.voxelize import inside_mask
    from pelvicnav.workflow.segment import write_contours

    faces = dict(zip(BONES, model.faces, strict=True))
    with atomic_directory(out) as tmp:
        write_nifti(tmp / "labels.nii.gz", ours, A)
        (tmp / "meshes").mkdir()
        for b in BONES:
            write_meshes(tmp / "meshes", b, meshes[b], faces[b], formats=("vtk", "stl"),
                         title=f"pelvicnav {b} now (CT frame)")  # fmt: skip
        for b, T in plan.targets.items():
            write_meshes(tmp / "meshes", f"{b}_target", tf.apply(T, meshes[b]), faces[b],
                         formats=("vtk", "stl"), title=f"pelvicnav {b} target")  # fmt: skip
        reduced = _reduced_ct(hu, A, ours, meshes, faces, plan.targets)
        write_nifti(tmp / "reduced_ct.nii.gz", reduced, A)
        fitted = np.zeros(hu.shape, dtype=np.uint8)
        for k, b in enumerate(BONES):
            fitted[inside_mask(meshes[b], faces[b], A, hu.shape) & (fitted == 0)] = k + 1
        write_contours(hu, ours, fitted, A, tmp / "contours.png")
        _rendering(meshes, faces, plan, tmp / "rendering.png")
        write_plan(tmp, plan)
        (tmp / "timing.txt").write_text(f"planned in {seconds:.1f} s\n")


def _reduced_ct(hu, A, ours, meshes, faces, targets) -> np.ndarray:
    """The CT with each dislocated bone moved to its target (the simulator's resampling and
    infill, :func:`pelvicnav.phantom.dislocate.apply_dislocation`)."""
    from pelvicnav.drr.volume import Volume
    from pelvicnav.phantom.ctsynth import SynthCT
    from pelvicnav.phantom.dislocate import Dislocation, apply_dislocation

    current = SynthCT(Volume(np.asarray(hu, np.float32), A), np.asarray(ours, np.uint8),
                      np.zeros((2, 4)))  # fmt: skip
    V = np.stack([meshes[b] for b in BONES])
    rng = np.random.default_rng(0)  # the infill's texture noise
    for bone, T in targets.items():
        move = Dislocation(bone, "reduction", T, 0.0, 0.0, np.zeros(3), 0)
        current, V = apply_dislocation(current, V, tuple(faces[b] for b in BONES), move, rng=rng)
    return np.clip(np.round(current.hu.data), -32768, 32767).astype(np.int16)


def _rendering(meshes, faces, plan, path: Path) -> None:
    """Current (orange) against target (green) of the dislocated bone(s), other bones grey;
    anterior and superior views."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from pelvicnav.geometry import transforms as tf
    from pelvicnav.io.atomic import save_figure

    fig = plt.figure(figsize=(11, 5.2))
    everything = np.concatenate(list(meshes.values()))
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2 + 10
    for k, (title, elev, azim) in enumerate((("anterior", 0, -90), ("superior", 90, -90))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        for b in BONES:
            layers = [(meshes[b], "0.75" if b not in plan.targets else "tab:orange", 1.0)]
            if b in plan.targets:
                layers.append((tf.apply(plan.targets[b], meshes[b]), "tab:green", 0.55))
            for V, colour, alpha in layers:
                ax.add_collection3d(Poly3DCollection(V[faces[b]], facecolors=colour, alpha=alpha,
                                                     edgecolor="none", shade=True))  # fmt: skip
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.view_init(elev=elev, azim=azim)
        ax.set_title(f"{title} view", fontsize=10)
        ax.set_axis_off()
        ax.set_box_aspect((1, 1, 1), zoom=1.35)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.9, wspace=0)
    what = ", ".join(plan.dislocated) or "no dislocated bone"
    fig.suptitle(f"plan: {what} now (orange) and at its target (green)")
    save_figure(fig, path, dpi=80)
