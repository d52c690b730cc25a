"""Joint-space refinement: seat a reduced bone against its neighbours as in the population.

The SPM predicts a pose from the global configuration of the other bones; it knows nothing about
the subject's own joint surfaces. This refinement uses them. For every joint between the reduced
bone ``X`` and a partner ``Y`` (sacroiliac, pubic symphysis) it learns from the training subjects:

* **contact offsets**: where each joint vertex ``i`` of ``X`` sits relative to its corresponding
  partner vertex ``j(i)``, expressed in a rigid frame fitted to the partner's joint region, and
* **joint space**: the signed point-to-plane distance from ``X``'s vertex ``i`` to the partner's
  nearest vertex along that vertex's normal (mean and spread per vertex).

At test time (1) the contact offsets, applied to the subject's partner, give target positions for
``X``'s joint vertices; a weighted rigid fit of those targets plus the SPM prediction starts the
refinement; (2) Gauss-Newton point-to-plane iterations then make the subject's own joint space
match the population's mean joint space (weights 1/variance per vertex), with a weak prior that
keeps the bone near the start. Everything uses the partner's mesh and ``X``'s own shape, never
``X``'s current position, so the estimate stays independent of the dislocation.

This goes beyond the paper's collision-only refinement (Han et al. 2020, section 2.1.2), which only
removes overlap; the study reports both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.pose.collision import JOINTS, JointSurface, as_gap_array
from pelvicnav.shape.mesh import vertex_normals

__all__ = ["JointSide", "JointSpaceModel", "subject_plane_gaps"]


def subject_plane_gaps(
    vertices: ArrayLike,
    faces: tuple[ArrayLike, ArrayLike, ArrayLike],
    *,
    near_distance: float = 25.0,
    vertex_sets: dict[tuple[int, int], ArrayLike] | None = None,
) -> NDArray[np.float64]:
    """Point-to-plane distance from every vertex to the partner bone of each joint, one subject.

    For joint ``k`` and side ``s`` (bone ``JOINTS[k][s]``), entry ``[k, s, i]`` is
    ``n_j . (x_i - y_j)``: ``y_j`` the partner's vertex nearest to ``x_i`` and ``n_j`` its outward
    normal. Depends on this subject only (computed once per subject in a cross-validation).

    Returns
    -------
    (3, 2, n_vertices) float64, mm
        NaN for vertices further than ``near_distance`` from the partner, and for vertices outside
        ``vertex_sets[(joint, side)]`` when those are given (only they are computed).
    """
    from scipy.spatial import cKDTree

    V = np.asarray(vertices, dtype=np.float64)
    normals = [vertex_normals(V[l], faces[l]) for l in range(3)]
    trees = [cKDTree(V[l]) for l in range(3)]
    out = np.full((len(JOINTS), 2, V.shape[1]), np.nan)
    for k, pair in enumerate(JOINTS):
        for side in range(2):
            this, other = BONES.index(pair[side]), BONES.index(pair[1 - side])
            # Only vertices near the joint matter; the distance bound keeps the queries cheap.
            sel = (
                np.arange(V.shape[1])
                if vertex_sets is None
                else np.asarray(vertex_sets[(k, side)], dtype=np.int64)
            )
            d, j = trees[other].query(V[this][sel], distance_upper_bound=near_distance)
            near = np.isfinite(d)
            jn = j[near]
            out[k, side, sel[near]] = np.einsum(
                "ij,ij->i", normals[other][jn], V[this][sel[near]] - V[other][jn]
            )
    return out


@dataclass(frozen=True)
class JointSide:
    """What is learned for one bone moving against one partner at one joint."""

    mover: str
    partner: str
    vertices: NDArray[np.int64]  # mover joint vertices
    partner_vertices: NDArray[np.int64]  # j(i)
    region: NDArray[np.int64]  # partner vertices framing the joint
    region_mean: NDArray[np.float64]  # partner region in the mean configuration
    offsets: NDArray[np.float64]  # (k, 3) mean offset in the partner-region frame
    offset_weights: NDArray[np.float64]  # (k,) 1/variance, normalised
    plane_gap: NDArray[np.float64]  # (k,) mean point-to-plane joint space
    plane_weights: NDArray[np.float64]  # (k,) 1/variance, normalised


@dataclass(frozen=True)
class JointSpaceModel:
    """Learned joint geometry for the refinement; build with :meth:`fit`.

    Attributes
    ----------
    sides : dict
        ``(joint pair, moving bone) -> learned side``.
    spm_weight : float
        Weight of the SPM prediction against the contact targets in the starting fit.
    prior_weight : float
        Weight of the pull towards the start during the point-to-plane iterations.
    max_motion : (float, float)
        Trust region of the point-to-plane stage: it may move the bone at most this far from the
        contact start (mm at the centroid, degrees); an update that would leave it stops there.
    max_pair_distance : float, mm
        Point-to-plane pairs further apart than this are ignored in an iteration.
    """

    sides: dict[tuple[tuple[str, str], str], JointSide]
    spm_weight: float = 0.3
    prior_weight: float = 0.01
    region_radius: float = 30.0
    max_motion: tuple[float, float] = (6.0, 6.0)
    max_pair_distance: float = 10.0

    @classmethod
    def fit(
        cls,
        vertices: ArrayLike,
        placed_means: ArrayLike,
        joints: dict[tuple[str, str], JointSurface],
        plane_gaps: ArrayLike,
        *,
        movers: tuple[str, ...],
        spm_weight: float = 0.3,
        prior_weight: float = 0.01,
        region_radius: float = 30.0,
        max_motion: tuple[float, float] = (6.0, 6.0),
        max_pair_distance: float = 10.0,
    ) -> JointSpaceModel:
        """Learn contact offsets and joint spaces from a training population.

        Parameters
        ----------
        vertices : (n_subjects, 3, n_vertices, 3) float, mm
        placed_means : (3, n_vertices, 3) float
            Mean shapes at their mean poses (one frame), to pair vertices across each joint.
        joints : dict
            Joint surfaces (:func:`pelvicnav.pose.collision.find_joint_surfaces`).
        plane_gaps : (n_subjects, 3, 2, n_vertices) float
            :func:`subject_plane_gaps` of each training subject.
        movers : tuple of str
            Bones that may be refined (the dislocated ones).
        """
        from scipy.spatial import cKDTree

        V = np.asarray(vertices, dtype=np.float64)
        M = np.asarray(placed_means, dtype=np.float64)
        G = as_gap_array(plane_gaps, V.shape[0], V.shape[2], "plane_gaps")
        sides = {}
        for k, pair in enumerate(JOINTS):
            joint = joints[pair]
            for side, mover in enumerate(pair):
                if mover not in movers:
                    continue
                partner = pair[1 - side]
                xi, yi = BONES.index(mover), BONES.index(partner)
                idx = joint.vertices[side]
                _, j = cKDTree(M[yi]).query(M[xi][idx])
                d_region, _ = cKDTree(M[xi][idx]).query(M[yi])
                region = np.flatnonzero(d_region < region_radius)
                offsets = []
                for n in range(V.shape[0]):
                    F = fit_transform(M[yi][region], V[n, yi][region])
                    Finv = tf.invert(F)
                    offsets.append(tf.apply(Finv, V[n, xi][idx]) - tf.apply(Finv, V[n, yi][j]))
                offsets = np.asarray(offsets)
                o_var = offsets.var(axis=0).sum(axis=-1) + 1e-3
                # Point-to-plane joint space; a vertex far from the partner in some training
                # subject (NaN there) is averaged over the others, or dropped if mostly far.
                g = G[:, k, side][:, idx]
                seen = np.isfinite(g).mean(axis=0) >= 0.5
                with np.errstate(invalid="ignore"):
                    g_mean = np.nanmean(np.where(seen, g, 0.0), axis=0)
                    g_var = np.nanvar(np.where(seen, g, 0.0), axis=0) + 1e-3
                plane_w = np.where(seen, 1 / g_var, 0.0)
                sides[(pair, mover)] = JointSide(
                    mover=mover,
                    partner=partner,
                    vertices=idx,
                    partner_vertices=j.astype(np.int64),
                    region=region.astype(np.int64),
                    region_mean=M[yi][region],
                    offsets=offsets.mean(axis=0),
                    offset_weights=(1 / o_var) / np.sum(1 / o_var),
                    plane_gap=g_mean,
                    plane_weights=plane_w / np.sum(plane_w),
                )
        return cls(
            sides=sides,
            spm_weight=spm_weight,
            prior_weight=prior_weight,
            region_radius=region_radius,
            max_motion=max_motion,
            max_pair_distance=max_pair_distance,
        )

    def refine(
        self,
        mover: str,
        mover_vertices: ArrayLike,
        spm_prediction: ArrayLike,
        partners: dict[str, ArrayLike],
        partner_faces: dict[str, ArrayLike],
        *,
        max_iter: int = 30,
        tol: float = 1e-7,
    ) -> NDArray[np.float64]:
        """Rigid ``target_from_current`` for ``mover`` seated against its partners.

        Parameters
        ----------
        mover : str
        mover_vertices : (n_vertices, 3) float
            The bone's mesh where it currently is (only its shape matters).
        spm_prediction : (n_vertices, 3) float
            The SPM's prediction of the bone's vertices (the mean shape at the predicted pose).
        partners : dict bone -> (n_vertices, 3)
            Neighbouring bones (observed, or estimated in a bilateral case).
        partner_faces : dict bone -> (m, 3) int
        """
        from scipy.spatial import cKDTree

        X = np.asarray(mover_vertices, dtype=np.float64)
        pred = np.asarray(spm_prediction, dtype=np.float64)
        sides = [s for (_, m), s in self.sides.items() if m == mover and s.partner in partners]
        n_v = len(X)
        # 1. contact targets + SPM prediction -> starting rigid fit
        src, dst, w = [X], [pred], [np.full(n_v, self.spm_weight / n_v)]
        for s in sides:
            Y = np.asarray(partners[s.partner], dtype=np.float64)
            F = fit_transform(s.region_mean, Y[s.region])
            targets = Y[s.partner_vertices] + s.offsets @ F[:3, :3].T
            src.append(X[s.vertices])
            dst.append(targets)
            w.append(s.offset_weights)
        T0 = fit_transform(np.concatenate(src), np.concatenate(dst), weights=np.concatenate(w))
        if not sides:
            return T0
        # 2. point-to-plane Gauss-Newton on the joint space, weak pull to the start
        start = tf.apply(T0, X)
        geo = []
        for s in sides:
            Y = np.asarray(partners[s.partner], dtype=np.float64)
            normals = vertex_normals(Y, partner_faces[s.partner])
            geo.append((s, Y, normals, cKDTree(Y)))
        T = T0
        centroid = start.mean(axis=0)
        sw_prior = np.sqrt(self.prior_weight / n_v)
        for _ in range(max_iter):
            rows, rhs = [], []
            for s, Y, normals, tree in geo:
                p = tf.apply(T, X[s.vertices])
                dist, j = tree.query(p)
                nrm = normals[j]
                r = np.einsum("ij,ij->i", nrm, p - Y[j]) - s.plane_gap
                # Pairs further apart than a joint space can be are not across the joint (ICP
                # outlier rejection); they would drag the bone along the surface.
                sw = np.sqrt(np.where(dist < self.max_pair_distance, s.plane_weights, 0.0))
                rows.append(np.hstack([nrm, np.cross(p, nrm)]) * sw[:, None])
                rhs.append(-r * sw)
            p = tf.apply(T, X)
            J = np.zeros((n_v, 3, 6))
            J[:, :, :3] = np.eye(3)
            J[:, :, 3:] = -tf.skew(p)
            rows.append(J.reshape(-1, 6) * sw_prior)
            rhs.append(-(p - start).reshape(-1) * sw_prior)
            delta = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
            T_new = tf.from_params(delta[:3], delta[3:]) @ T
            moved = T_new @ tf.invert(T0)
            shift = np.linalg.norm(tf.apply(moved, centroid[None])[0] - centroid)
            angle = np.degrees(np.linalg.norm(tf.rotvec_from_matrix(moved[:3, :3])))
            if shift > self.max_motion[0] or angle > self.max_motion[1]:
                break
            T = T_new
            if np.linalg.norm(delta) < tol:
                break
        return T
