"""The pelvis model: per-bone shape models, a generative pose model and the target planners.

Fitted once from the Han 2019 atlas (:func:`build_model`) and shipped inside the package
(:mod:`pelvicnav.model.file`), so planning, simulation and the demo run without the atlas.

What it holds:

* ``shapes``: per-bone SSMs (similarity-aligned Procrustes mean, the modes that explain
  ``variance_kept`` of the variance, their variances), fitted after two repairs of the atlas's
  correspondence (stretched "spike" vertices re-placed from the mean's local shape; surfaces
  that cross themselves untangled), on the closed triangulation ``faces``;
* ``population``: an SPM over all three bones in a rigid (mm-preserving) frame, the generative
  model of bone poses and sizes that :mod:`pelvicnav.phantom.sampled` draws from;
* ``combined``: a PCA of the standardised shape weights of the three bones and pose weights of
  ``population`` over the training subjects (Cootes' combined model), so a sampled patient keeps
  the correlations between size, shape and placement of its bones;
* ``envelope``: the smallest and largest of a few sizes over the training subjects (each bone's
  extent along x, y and z and the pelvic width, in their CT frames and in the population's
  frame), within which sampled patients are kept;
* ``planners``: a :class:`~pelvicnav.pose.target.TargetPlanner` for every set of observed bones a
  plan can have (sacrum and one innominate, or the sacrum alone), fitted on the atlas's vertices as
  published (the leave-one-out study's recipe), with their joint surfaces and joint-space models;
* ``provenance``: atlas, DOI, licence, subject ids, package version, date, build settings.

Reference: R. Han et al., Phys. Med. Biol. 64 (2019) 095022, doi:10.1088/1361-6560/ab1456
(atlas, CC BY 4.0, not for clinical use); Han et al. (2020), sections 2.1.1-2.1.2.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pelvicnav import BONES
from pelvicnav.pose.spm import PoseModel, check_bones
from pelvicnav.pose.target import TargetPlanner
from pelvicnav.shape.ssm import ShapeModel

__all__ = [
    "ATLAS_CITATION",
    "OBSERVED_SETS",
    "SIZE_MEASURES",
    "CombinedModel",
    "PelvisModel",
    "build_model",
    "size_measures",
]

# Every set of observed (undislocated) bones a plan can have.
OBSERVED_SETS: tuple[tuple[str, ...], ...] = (
    ("sacrum", "right_hip"),
    ("sacrum", "left_hip"),
    ("sacrum",),
)
ATLAS_CITATION = {
    "atlas": "Han pelvis atlas (40 subjects x sacrum, left and right innominate)",
    "reference": "R. Han et al., Atlas-based automatic planning and 3D-2D fluoroscopic guidance in "
    "pelvic trauma surgery, Phys. Med. Biol. 64 (2019) 095022",
    "doi": "10.1088/1361-6560/ab1456",
    "repository": "rhan93/Altas-of-Pelvis-Segmentation-and-Trajectory-Planning",
    "licence": "CC BY 4.0",
    "note": "not for clinical use",
}


@dataclass(frozen=True)
class CombinedModel:
    """Joint Gaussian of all shape and pose weights, ``z = modes @ c`` in standardised units.

    Attributes
    ----------
    modes : (n_weights, n_modes) float64, orthonormal columns
        Rows: the shape weights of sacrum, left and right innominate, then the pose weights, each
        divided by its own standard deviation.
    variances : (n_modes,) float64
    """

    modes: NDArray[np.float64]
    variances: NDArray[np.float64]

    @property
    def n_modes(self) -> int:
        return self.modes.shape[1]


SIZE_MEASURES: tuple[str, ...] = (
    *(f"{bone}_{axis}" for bone in BONES for axis in "xyz"),
    "pelvic_width",
)


def size_measures(vertices: NDArray[np.float64]) -> NDArray[np.float64]:
    """The :data:`SIZE_MEASURES` (mm) of pelvises ``(..., 3, n_vertices, 3)``: ``(..., 10)``."""
    V = np.asarray(vertices, dtype=np.float64)
    extents = (V.max(axis=-2) - V.min(axis=-2)).reshape(*V.shape[:-3], 9)
    width = V[..., 1, :, 0].max(axis=-1) - V[..., 2, :, 0].min(axis=-1)
    return np.concatenate([extents, width[..., None]], axis=-1)


@dataclass(frozen=True, eq=False)
class PelvisModel:
    """Shape, pose and planning models of the pelvis (see the module docstring).

    Attributes
    ----------
    faces : tuple of three (m_l, 3) int64
        Closed, outward triangulations (bone order :data:`pelvicnav.BONES`).
    shapes : dict bone -> ShapeModel
    population : PoseModel
        All bones as frame bones, rigid frame.
    combined : CombinedModel
        Joint distribution of the shape and pose weights.
    envelope : (10, 2) float64, mm
        Minimum and maximum of each of :data:`SIZE_MEASURES` over the training subjects.
    planners : dict observed-bone tuple -> TargetPlanner
    provenance : dict
    """

    faces: tuple[NDArray[np.int64], ...]
    shapes: Mapping[str, ShapeModel]
    population: PoseModel
    combined: CombinedModel
    envelope: NDArray[np.float64]
    planners: Mapping[tuple[str, ...], TargetPlanner]
    provenance: Mapping[str, object] = field(default_factory=dict)

    @property
    def n_vertices(self) -> int:
        return self.population.mean_shapes.shape[1]

    @property
    def subject_ids(self) -> tuple[int, ...]:
        """Atlas ids the model was fitted from (never score it on these)."""
        return tuple(int(s) for s in self.provenance.get("subject_ids", ()))

    def planner(self, observed: Sequence[str]) -> TargetPlanner:
        """The target planner for a set of observed bones (any order).

        Raises
        ------
        ValueError
            Unknown bones, or a set no planner was built for.
        """
        key = check_bones(observed, what="observed bone")
        if key not in self.planners:
            raise ValueError(
                f"no planner for observed bones {list(key)}; the model has "
                f"{[list(k) for k in self.planners]}"
            )
        return self.planners[key]


def _repaired_shapes(
    shapes: NDArray[np.float64], faces: NDArray[np.int64]
) -> tuple[NDArray[np.float64], dict[str, int]]:
    """Subjects of one bone with stretched-correspondence vertices re-placed and crossing
    surfaces untangled; with counts of spike vertices and of crossings before and after."""
    from pelvicnav.geometry import transforms as tf
    from pelvicnav.geometry.procrustes import fit_transform
    from pelvicnav.shape.mesh import (
        inpaint_vertices,
        self_intersections,
        spike_vertices,
        untangle,
    )

    spikes = spike_vertices(shapes, faces)
    clean = shapes.copy()
    mean = ShapeModel.fit(shapes).mean
    for s in np.flatnonzero(spikes.any(axis=1)):
        ref = tf.apply(fit_transform(mean, shapes[s]), mean)
        clean[s] = inpaint_vertices(shapes[s], faces, spikes[s], ref)
    before = after = 0
    for s in range(len(clean)):
        before += len(self_intersections(clean[s], faces))
        clean[s], left = untangle(clean[s], faces)
        after += left
    counts = {"spike_vertices": int(spikes.sum()), "crossings": before, "crossings_left": after}
    return clean, counts


def _shape_model(
    shapes: NDArray[np.float64], faces: NDArray[np.int64], variance_kept: float
) -> ShapeModel:
    """SSM keeping the modes that explain ``variance_kept`` of the variance; mean untangled."""
    from pelvicnav.shape.mesh import untangle

    full = ShapeModel.fit(shapes)
    cumulative = np.cumsum(full.variances) / np.sum(full.variances)
    keep = min(int(np.searchsorted(cumulative, variance_kept)) + 1, full.n_modes)
    return ShapeModel(
        mean=untangle(full.mean, faces)[0],
        modes=full.modes[:, :keep].copy(),
        variances=full.variances[:keep].copy(),
    )


def _combined_model(
    clean: NDArray[np.float64], shapes: Mapping[str, ShapeModel], population: PoseModel
) -> CombinedModel:
    """PCA of each training subject's standardised shape and pose weights."""
    from pelvicnav.geometry import transforms as tf
    from pelvicnav.geometry.procrustes import fit_transform

    columns = []
    for b, bone in enumerate(BONES):
        ssm = shapes[bone]
        aligned = [tf.apply(fit_transform(x, ssm.mean, scale=True), x) for x in clean[:, b]]
        columns.append(np.stack([ssm.project(x) for x in aligned]) / np.sqrt(ssm.variances))
    pose = (population.training - population.mean) @ population.modes
    columns.append(pose / np.sqrt(population.variances))
    Z = np.hstack(columns)
    _, sv, vt = np.linalg.svd(Z - Z.mean(axis=0), full_matrices=False)
    variances = sv**2 / (len(Z) - 1)
    keep = int(np.sum(variances > 1e-10 * variances[0]))
    return CombinedModel(modes=vt[:keep].T.copy(), variances=variances[:keep].copy())


def _envelope(clean: NDArray[np.float64]) -> NDArray[np.float64]:
    """Range of the size measures over the subjects, in their CT frames and in the population's
    rigid frame alike (the narrower of the two ranges)."""
    from pelvicnav.geometry import transforms as tf
    from pelvicnav.shape.ssm import generalized_procrustes

    n = len(clean)
    gpa = generalized_procrustes(clean.reshape(n, -1, 3), scale=False)
    framed = size_measures(tf.apply(gpa.transforms[:, None], clean))
    as_scanned = size_measures(clean)
    low = np.maximum(framed.min(axis=0), as_scanned.min(axis=0))
    high = np.minimum(framed.max(axis=0), as_scanned.max(axis=0))
    return np.stack([low, high], axis=1)


def build_model(
    atlas,
    *,
    variance_kept: float = 0.99,
    prior: float = 0.1,
    progress: Callable[[str], None] | None = None,
) -> PelvisModel:
    """Fit the pelvis model from an atlas.

    Parameters
    ----------
    atlas : pelvicnav.io.atlas.Atlas
        At least 10 subjects, bones in :data:`pelvicnav.BONES` order.
    variance_kept : float
        Fraction of each SSM's variance its kept modes explain (0 < f <= 1).
    prior : float
        Tikhonov weight of the planners' SPM (the target-pose study's default).
    progress : callable(str), optional
        Told what is being fitted.

    Returns
    -------
    PelvisModel

    Raises
    ------
    ValueError
        Too few subjects, bones in another order, or a bad ``variance_kept``.
    """
    import datetime

    from pelvicnav import __version__
    from pelvicnav.shape.mesh import close_mesh

    if not 0 < variance_kept <= 1:
        raise ValueError(f"variance_kept must be in (0, 1], got {variance_kept}")
    if tuple(atlas.bones) != BONES:
        raise ValueError(f"atlas bones must be {BONES}, got {atlas.bones}")
    if atlas.n_subjects < 10:
        raise ValueError(f"a pelvis model needs at least 10 subjects, got {atlas.n_subjects}")
    say = progress or (lambda _: None)
    V = atlas.vertices
    faces = tuple(close_mesh(V[:, b].mean(axis=0), atlas.faces[b]) for b in range(3))
    shapes, clean, repaired = {}, V.copy(), {}
    for b, bone in enumerate(BONES):
        say(f"shape model: {bone}")
        clean[:, b], repaired[bone] = _repaired_shapes(V[:, b], faces[b])
        shapes[bone] = _shape_model(clean[:, b], faces[b], variance_kept)
    say("population pose model")
    population = PoseModel.fit(clean, frame_bones=BONES, frame_scale=False)
    combined = _combined_model(clean, shapes, population)
    envelope = _envelope(clean)
    planners = {}
    for observed in OBSERVED_SETS:
        say(f"target planner: observed {' + '.join(observed)}")
        planners[observed] = TargetPlanner.fit(V, faces, observed=observed, prior=prior)
    provenance = {
        **ATLAS_CITATION,
        "subject_ids": [int(s) for s in atlas.subject_ids],
        "pelvicnav_version": __version__,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "variance_kept": variance_kept,
        "planner_prior": prior,
        "repairs": repaired,
        "shape_modes": {bone: shapes[bone].n_modes for bone in BONES},
    }
    return PelvisModel(
        faces=faces,
        shapes=shapes,
        population=population,
        combined=combined,
        envelope=envelope,
        planners=planners,
        provenance=provenance,
    )
