"""Patients sampled from the embedded pelvis model: the offline default population.

Each subject draws, from one seeded generator per subject:

1. the weights of the model's combined shape-and-pose modes from their Gaussian, clipped at
   ``clip`` standard deviations, which give correlated weights of
2. the population SPM (all bones, rigid frame, so sizes stay in mm): each bone's similarity pose,
   and of each bone's SSM: the bone's shape, aligned onto the SPM's mean shape of that bone and
   placed by its pose (drawing the two independently loses how a sacrum's shape goes with its
   size: its width then spread a third wider than in the atlas);
3. a small rigid placement of the whole pelvis in its "CT" frame.

A draw whose meshes still cross themselves after untangling (rare: a fold at the sacral base,
next to the atlas's own defect there) is drawn again, and so is one whose sizes (bone extents,
pelvic width) leave the model's envelope of the training subjects: clipping each mode at 2.5 sd
does not bound a size, and a population spread like the atlas would otherwise put a few
patients a few mm beyond the largest or smallest pelvis the model was fitted from.

Any crossing of a bone's surface through itself (the linear model can push the two sheets of a
thin iliac wing through each other) is removed by :func:`pelvicnav.shape.mesh.untangle`, which
moves only the crossing vertices. Vertex ``i`` is the same anatomical point in every subject and
in the model (exact correspondence); the triangles are the model's closed faces.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.io.atlas import Atlas

__all__ = [
    "MODEL_SOURCE",
    "SamplingOptions",
    "sample_subject",
    "sampled_population",
    "weights_from_combined",
]

MODEL_SOURCE = "model"


@dataclass(frozen=True)
class SamplingOptions:
    """Spread of a sampled population.

    Attributes
    ----------
    clip : float
        Every combined mode's weight is clipped at this many standard deviations.
    max_draws : int
        Draws per subject before giving up on one inside the size envelope (and, separately,
        on one whose meshes untangle).
    placement_rotation_deg : (3,) float
        Standard deviation of the pelvis's rotation in its CT frame about x, y and z.
    placement_translation_mm : float
        Standard deviation of its translation (per axis).
    """

    clip: float = 2.5
    max_draws: int = 200
    placement_rotation_deg: tuple[float, float, float] = (3.0, 1.0, 1.0)
    placement_translation_mm: float = 15.0


def sample_subject(
    model,
    pose_weights: NDArray[np.float64],
    shape_weights: dict[str, NDArray[np.float64]],
    ct_from_model: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], int]:
    """Vertices of one pelvis for given weights, and the crossings untangling could not remove.

    Parameters
    ----------
    model : pelvicnav.model.PelvisModel
    pose_weights : (n_pose_modes,) float
        Weights of ``model.population`` (in units of the modes, not standard deviations).
    shape_weights : dict bone -> (n_shape_modes,) float
    ct_from_model : (4, 4) float, optional
        Rigid placement in the CT frame (default identity).

    Returns
    -------
    vertices : (3, n_vertices, 3) float64, mm
    crossings : int
        Triangle pairs still crossing after :func:`~pelvicnav.shape.mesh.untangle` (0 normally).
    """
    from pelvicnav.shape.mesh import untangle

    placement = np.eye(4) if ct_from_model is None else np.asarray(ct_from_model, float)
    out = _placed_shapes(model, pose_weights, shape_weights)
    crossings = 0
    for b in range(3):
        out[b], left = untangle(tf.apply(placement, out[b]), model.faces[b])
        crossings += left
    return out, crossings


def _placed_shapes(model, pose_weights, shape_weights) -> NDArray[np.float64]:
    """Each bone's shape placed by its pose, in the model's frame (not yet untangled)."""
    pop = model.population
    poses = pop.poses_from_vector(pop.mean + pop.modes @ np.asarray(pose_weights, float))
    out = np.empty((3, model.n_vertices, 3))
    for b, bone in enumerate(BONES):
        ssm = model.shapes[bone]
        local_from_ssm = fit_transform(ssm.mean, pop.mean_shapes[b], scale=True)
        out[b] = tf.apply(poses[b] @ local_from_ssm, ssm.instance(shape_weights[bone]))
    return out


def _draw_inside_envelope(model, rng: np.random.Generator, opt: SamplingOptions):
    """Draws until the placed pelvis's sizes lie in the model's envelope.

    Returns pose weights, shape weights and the placement ``ct_from_model``.
    """
    from pelvicnav.model.pelvis import size_measures

    low, high = model.envelope[:, 0], model.envelope[:, 1]
    for _ in range(opt.max_draws):
        xi = np.clip(rng.standard_normal(model.combined.n_modes), -opt.clip, opt.clip)
        pose, shape = weights_from_combined(model, xi)
        angles = np.deg2rad(opt.placement_rotation_deg) * rng.standard_normal(3)
        placement = tf.from_params(opt.placement_translation_mm * rng.standard_normal(3), angles)
        sizes = size_measures(tf.apply(placement, _placed_shapes(model, pose, shape)))
        if np.all((sizes >= low) & (sizes <= high)):
            return pose, shape, placement
    raise ValueError(
        f"no draw inside the model's size envelope in {opt.max_draws} tries; "
        "is the model file consistent?"
    )


def weights_from_combined(
    model, combined_sd: NDArray[np.float64]
) -> tuple[NDArray[np.float64], dict[str, NDArray[np.float64]]]:
    """Pose weights and per-bone shape weights for combined-mode weights given in sd units.

    Parameters
    ----------
    model : PelvisModel
    combined_sd : (n_combined_modes,) float
        Weight of each combined mode in standard deviations.

    Returns
    -------
    pose_weights : (n_pose_modes,) float64
    shape_weights : dict bone -> (n_shape_modes,) float64
    """
    c = model.combined
    z = c.modes @ (np.asarray(combined_sd, float) * np.sqrt(c.variances))
    shapes, start = {}, 0
    for bone in BONES:
        ssm = model.shapes[bone]
        shapes[bone] = z[start : start + ssm.n_modes] * np.sqrt(ssm.variances)
        start += ssm.n_modes
    return z[start:] * np.sqrt(model.population.variances), shapes


def sampled_population(
    n_subjects: int = 40,
    *,
    seed: int = 0,
    model=None,
    options: SamplingOptions | None = None,
    subject_ids: Sequence[int] | None = None,
) -> Atlas:
    """A population of pelvises sampled from the pelvis model.

    Parameters
    ----------
    n_subjects : int
        Subjects, with ids ``1..n_subjects``; subject ``k`` is the same for any ``n_subjects``.
    seed : int
    model : PelvisModel, optional
        Default: :func:`pelvicnav.model.load_model` (``$PELVICNAV_MODEL`` or the packaged file).
    options : SamplingOptions, optional
    subject_ids : sequence of int, optional
        Draw only these subjects (each as it is in the full population), e.g. the one a
        simulation needs; default ``1..n_subjects``.

    Returns
    -------
    Atlas
        ``source="model"``, the model's faces.
    """
    from pelvicnav.model import load_model

    if n_subjects < 1:
        raise ValueError(f"n_subjects must be >= 1, got {n_subjects}")
    opt = options or SamplingOptions()
    if opt.clip <= 0 or opt.max_draws < 1:
        raise ValueError(f"clip must be positive and max_draws >= 1, got {opt}")
    ids = tuple(range(1, n_subjects + 1)) if subject_ids is None else tuple(subject_ids)
    if not ids or min(ids) < 1 or len(set(ids)) != len(ids):
        raise ValueError(f"subject ids must be distinct and >= 1, got {list(ids)}")
    model = model or load_model()
    out = np.empty((len(ids), 3, model.n_vertices, 3))
    for s, subject in enumerate(ids):
        # Subject k's stream is the k-th child of the seed, whatever else is drawn.
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(subject - 1,)))
        for _ in range(opt.max_draws):
            pose, shape, placement = _draw_inside_envelope(model, rng, opt)
            out[s], crossings = sample_subject(model, pose, shape, placement)
            if crossings == 0:  # rare: a sacral-base fold the untangling cannot undo
                break
        else:
            raise ValueError(f"subject {subject}: no draw without self-crossing meshes")
    return Atlas(
        subject_ids=ids,
        vertices=out,
        faces=model.faces,
        source=MODEL_SOURCE,
        bones=BONES,
    )
