"""The joint-aware prior of stage 2: a dislocated bone does not pass through its neighbours.

The sacroiliac joints and the symphysis do not interpenetrate, whatever the dislocation. The prior
takes the dislocated bone's samples near the other bones in the preoperative CT (the *joint
samples*: within ``reach`` of another bone but clear of it) and, for a candidate pose, counts the
fraction that end up inside another bone (nearer than ``clearance`` to one of its samples, after
both bones' poses). That fraction, times ``weight`` per view, is taken off the similarity.

A pose the CT shows (each bone at its CT place relative to the others) scores zero, and so does
any pose that keeps the joints open: the prior does not pull, it only forbids. It matters where
the images leave the bone a valley of nearly equal similarity (a hip half out of the field of
view), along which the search could otherwise slide the hip into the sacrum or the other hip.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from pelvicnav.drr.renderer import Renderer
from pelvicnav.geometry import transforms as tf

__all__ = ["JointPrior", "joint_prior"]


@dataclass(frozen=True, eq=False)
class JointPrior:
    """Interpenetration of one bone with the others.

    Attributes
    ----------
    bone : str
    points : (n, 3) mm, the bone's CT frame
        Its joint samples.
    others : dict bone -> cKDTree of that bone's samples (its CT frame)
    clearance : float, mm
    weight : float
        Penalty for every joint sample inside another bone (per view, as a fraction).
    """

    bone: str
    points: NDArray[np.float64]
    others: dict
    clearance: float
    weight: float

    def penalty(self, poses: NDArray, others: dict[str, NDArray], n_views: int) -> NDArray:
        """``weight x K x`` the fraction of joint samples inside another bone, for each of the
        bone's candidate ``poses`` (N, 4, 4) with the other bones at ``others`` (bone -> (4, 4))."""
        inside = np.zeros((len(poses), len(self.points)), dtype=bool)
        for b, tree in self.others.items():
            M = tf.invert(others[b])[None] @ poses  # other's ct_from_this bone's ct
            q = np.einsum("nij,pj->npi", M[:, :3, :3], self.points) + M[:, None, :3, 3]
            d, _ = tree.query(q.reshape(-1, 3), distance_upper_bound=self.clearance)
            inside |= np.isfinite(d).reshape(inside.shape)
        return self.weight * n_views * inside.mean(axis=1)


def joint_prior(
    renderer: Renderer,
    bone: str,
    *,
    level: int = -1,
    reach: float = 15.0,
    clearance: float = 1.0,
    weight: float = 0.1,
    max_points: int = 400,
    seed: int = 0,
) -> JointPrior | None:
    """The prior of ``bone`` against the renderer's other bones, from their CT-frame samples at
    ``level``; None if the bone has no sample within ``reach`` mm of another bone."""
    pts = renderer.points(bone, level)
    trees = {b: cKDTree(renderer.points(b, level)) for b in renderer.bones if b != bone}
    near = np.zeros(len(pts), dtype=bool)
    clear = np.ones(len(pts), dtype=bool)
    for tree in trees.values():
        d, _ = tree.query(pts, distance_upper_bound=reach)
        near |= np.isfinite(d)
        clear &= ~(d < 2 * clearance)  # inside or touching in the CT: not a joint sample
    idx = np.flatnonzero(near & clear)
    if len(idx) == 0:
        return None
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    return JointPrior(bone, pts[idx], trees, clearance, weight)
