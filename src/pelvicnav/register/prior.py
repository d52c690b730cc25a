"""The joint-aware prior of stage 2: a dislocated bone stays at its joints.

The prior takes the dislocated bone's samples near the other bones in the preoperative CT (the
*joint samples*: within ``reach`` of another bone but clear of it) and, for a candidate pose,
measures each one's distance to the nearest sample of another bone (after both bones' poses). Two
terms, each per view, are taken off the similarity:

* interpenetration: the sacroiliac joints and the symphysis do not pass through each other,
  whatever the dislocation; ``weight`` times the fraction of joint samples nearer than
  ``clearance`` to another bone;
* the joint gap: a dislocation opens the joints by a bounded amount; ``gap_weight`` per mm by
  which the ``GAP_QUANTILE`` percentile of the joint samples' distances exceeds the CT's by more
  than ``gap_slack``.

A pose the CT shows (each bone at its CT place relative to the others) scores zero, and so does any
pose whose joints are neither closed through nor opened past the slack: inside that range the
prior does not pull. It matters where the images leave the bone a valley of nearly equal
similarity (a hip half out of the field of view): along it the search could otherwise slide the
hip into the sacrum, or away from it to a pose that scores as well as the truth (on the simulated
cases, wrong answers 8-47 mm off had 90th-percentile gaps 4-36 mm wider than the truth's).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import cKDTree

from pelvicnav.drr.renderer import Renderer
from pelvicnav.geometry import transforms as tf

__all__ = ["GAP_QUANTILE", "MEASURED_POINTS", "DistanceField", "JointPrior", "joint_prior"]

GAP_QUANTILE = 90.0  # the percentile of the joint samples' distances that measures the gap
GAP_REACH_MM = 20.0  # the gap is read up to gap_ct + gap_slack + this (the penalty saturates)
FIELD_SPACING_MM = 3.0  # the distance fields' voxels
MEASURED_POINTS = 2000  # joint samples when the prior only measures (a few poses per registration)


@dataclass(frozen=True, eq=False)
class DistanceField:
    """Distance (mm) to the nearest sample of a bone, on a grid in its CT frame.

    Attributes
    ----------
    origin : (3,) mm, the centre of voxel (0, 0, 0)
    spacing : float, mm
    data : (ni, nj, nk) float32, mm
    cap : float, mm
        Every distance is read as at most this, and anywhere off the grid as this.
    """

    origin: NDArray[np.float64]
    spacing: float
    data: NDArray[np.float32]
    cap: float

    @classmethod
    def of(cls, points: NDArray, cap: float, spacing: float = FIELD_SPACING_MM) -> DistanceField:
        """The field of ``points`` (n, 3) mm over their bounding box grown by ``cap``."""
        origin = points.min(axis=0) - cap
        shape = np.ceil((points.max(axis=0) + cap - origin) / spacing).astype(int) + 1
        occupied = np.zeros(shape, dtype=bool)
        ijk = np.rint((points - origin) / spacing).astype(int)
        occupied[tuple(ijk.T)] = True
        d = ndimage.distance_transform_edt(~occupied, sampling=spacing)
        return cls(origin, float(spacing), np.minimum(d, cap).astype(np.float32), float(cap))

    def __call__(self, points: NDArray) -> NDArray[np.float64]:
        """Trilinear distance at ``points`` (..., 3) mm -> (...)."""
        q = ((points.reshape(-1, 3) - self.origin) / self.spacing).T
        d = ndimage.map_coordinates(self.data, q, order=1, mode="constant", cval=self.cap)
        return d.reshape(points.shape[:-1]).astype(np.float64)


@dataclass(frozen=True, eq=False)
class JointPrior:
    """Interpenetration and joint gap of one bone with the others.

    Attributes
    ----------
    bone : str
    points : (n, 3) mm, the bone's CT frame
        Its joint samples.
    others : dict bone -> cKDTree of that bone's samples (its CT frame)
    clearance : float, mm
    weight : float
        Penalty for every joint sample inside another bone (per view, as a fraction).
    gap_weight : float, per mm per view
        Penalty per mm of the gap (the ``GAP_QUANTILE`` percentile of the joint samples'
        distances to the other bones) beyond ``gap_ct + gap_slack``; 0 turns the term off.
    gap_slack : float, mm
    gap_ct : float, mm
        The gap with every bone at its CT pose.
    fields : dict bone -> DistanceField
        The other bones' distance fields (the gap term; empty when it is off).
    """

    bone: str
    points: NDArray[np.float64]
    others: dict
    clearance: float
    weight: float
    gap_weight: float = 0.0
    gap_slack: float = 0.0
    gap_ct: float = 0.0
    fields: dict = field(default_factory=dict)

    def _in_others(self, poses: NDArray, others: dict[str, NDArray]):
        """(other bone, (N, n, 3) joint samples in its CT frame) for each other bone."""
        for b in self.others:
            M = tf.invert(others[b])[None] @ poses  # other's ct_from_this bone's ct
            yield b, np.einsum("nij,pj->npi", M[:, :3, :3], self.points) + M[:, None, :3, 3]

    def inside(self, poses: NDArray, others: dict[str, NDArray]) -> NDArray[np.float64]:
        """(N,) the fraction of joint samples nearer than ``clearance`` to another bone, for each
        of the bone's candidate ``poses`` (N, 4, 4) with the others at ``others``
        (bone -> (4, 4))."""
        hit = np.zeros((len(poses), len(self.points)), dtype=bool)
        for b, q in self._in_others(poses, others):
            d, _ = self.others[b].query(q.reshape(-1, 3), distance_upper_bound=self.clearance)
            hit |= np.isfinite(d).reshape(hit.shape)
        return hit.mean(axis=1)

    def distances(self, poses: NDArray, others: dict[str, NDArray]) -> NDArray[np.float64]:
        """(N, n) mm: each joint sample's distance to the nearest other bone, read from
        ``fields`` (at most their cap; the gap term only)."""
        d = np.full((len(poses), len(self.points)), np.inf)
        for b, q in self._in_others(poses, others):
            d = np.minimum(d, self.fields[b](q))
        return d

    @property
    def active(self) -> bool:
        """Whether the prior adds anything to the objective (else it only measures)."""
        return self.weight > 0 or self.gap_weight > 0

    def measure(self, poses: NDArray, others: dict[str, NDArray]) -> tuple[NDArray, NDArray]:
        """For each candidate pose (N,): the fraction of joint samples nearer than ``clearance``
        to another bone, and the gap's opening past the CT's (mm; the ``GAP_QUANTILE``
        percentile of their distances less ``gap_ct``), from ``fields``."""
        d = self.distances(poses, others)
        opening = np.percentile(d, GAP_QUANTILE, axis=1) - self.gap_ct
        return np.mean(d < self.clearance, axis=1), opening

    def penalty(self, poses: NDArray, others: dict[str, NDArray], n_views: int) -> NDArray:
        """``K x`` (``weight x`` the fraction of joint samples inside another bone ``+
        gap_weight x`` the gap's excess over ``gap_ct + gap_slack`` in mm), for each candidate
        pose (N,). With the distance fields, both read them (a sample is inside where its
        distance is under ``clearance``); else the inside fraction from the trees
        (:meth:`inside`)."""
        if not self.fields:
            return n_views * self.weight * self.inside(poses, others)
        inside, opening = self.measure(poses, others)
        excess = np.maximum(opening - self.gap_slack, 0.0)
        return n_views * (self.weight * inside + self.gap_weight * excess)


def joint_prior(
    renderer: Renderer,
    bone: str,
    *,
    level: int = -1,
    reach: float = 15.0,
    clearance: float = 1.0,
    weight: float = 0.1,
    gap_weight: float = 0.0,
    gap_slack: float = 0.0,
    fields: float = 0.0,
    max_points: int = 200,
    seed: int = 0,
) -> JointPrior | None:
    """The prior of ``bone`` against the renderer's other bones, from their CT-frame samples at
    ``level`` (see :class:`JointPrior`); None if the bone has no sample within ``reach`` mm of
    another bone. The distance fields are built when ``gap_weight`` or ``fields`` is positive,
    reaching openings up to ``max(gap_slack, fields) + GAP_REACH_MM`` past the CT's gap
    (``fields``: the largest opening :meth:`JointPrior.measure` must read)."""
    pts = renderer.points(bone, level)
    others = {b: renderer.points(b, level) for b in renderer.bones if b != bone}
    trees = {b: cKDTree(p) for b, p in others.items()}
    nearest = np.full(len(pts), np.inf)  # mm to the nearest other bone, within reach
    for tree in trees.values():
        nearest = np.minimum(nearest, tree.query(pts, distance_upper_bound=reach)[0])
    # within reach, and clear of the others (inside or touching in the CT: not a joint sample)
    idx = np.flatnonzero(np.isfinite(nearest) & (nearest >= 2 * clearance))
    if len(idx) == 0:
        return None
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    if gap_weight == 0 and fields == 0:
        return JointPrior(bone, pts[idx], trees, clearance, weight)
    gap_ct = float(np.percentile(nearest[idx], GAP_QUANTILE))
    cap = gap_ct + max(gap_slack, fields) + GAP_REACH_MM
    grids = {b: DistanceField.of(p, cap) for b, p in others.items()}
    return JointPrior(bone, pts[idx], trees, clearance, weight, gap_weight, gap_slack, gap_ct,
                      grids)  # fmt: skip
