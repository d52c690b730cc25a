"""Target reduction pose of dislocated bones from the observed ones (SPM and SPM_CC).

Han et al. (2020), equations 8a-8b and the collision refinement of section 2.1.2.

Given the segmented meshes of the observed (undislocated) bones and of the dislocated bone(s) in
the preoperative CT:

1. the subject is normalised with the observed bones (:meth:`PoseModel.normalised_from_subject`),
2. the observed bones' tangent vectors ``b_O`` give the mode weights by incomplete PCA with a
   Gaussian prior on the weights (equation 8a plus a Tikhonov term ``alpha * sum v_k^2 / lambda_k``,
   solved with scipy's trust-region Newton-CG = Steihaug's method),
3. ``b_X = mean_X + P_X v`` (8b) places the dislocated bone's mean shape (exponential map),
4. the subject's own dislocated mesh is fitted rigidly onto that placement: the result is the rigid
   ``target_from_current`` that reduces the bone,
5. SPM_CC: where the reduced bone overlaps an opposing joint surface, it is translated along the
   joint normal by the smallest amount that restores the minimum joint space seen in training.

With only the observed bones entering steps 1-3, the estimate cannot depend on where the dislocated
bone currently is (a test checks this).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.pose.collision import (
    JOINTS,
    JointSurface,
    as_gap_array,
    find_joint_surfaces,
    joint_gaps,
    ray_triangle_distances,
    refine_translation,
    vertex_normals,
)
from pelvicnav.pose.joint_space import JointSpaceModel, subject_plane_gaps
from pelvicnav.pose.spm import BONES, PoseModel, check_bones

__all__ = ["TargetEstimate", "TargetPlanner", "solve_weights"]


@dataclass(frozen=True)
class TargetEstimate:
    """Estimated target (reduced) pose of one dislocated bone.

    Attributes
    ----------
    bone : str
    target_from_current : (4, 4) float64
        Rigid transform moving the bone from where it is (its segmentation) to the target.
    vertices : (n_vertices, 3) float64
        The bone's vertices at the target, CT frame (mm).
    predicted_mean : (n_vertices, 3) float64
        The population mean shape placed at the SPM's predicted pose.
    refinement : (3,) float64
        Translation (mm) added by the collision refinement (zero for plain SPM).
    """

    bone: str
    target_from_current: NDArray[np.float64]
    vertices: NDArray[np.float64]
    predicted_mean: NDArray[np.float64]
    refinement: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))


def solve_weights(
    residual: ArrayLike,
    modes: ArrayLike,
    variances: ArrayLike,
    *,
    prior: float,
    method: str = "trust-ncg",
) -> NDArray[np.float64]:
    """Equation 8a with a prior: ``argmin_v |r - P v|^2 + prior * sum_k v_k^2 / lambda_k``.

    Parameters
    ----------
    residual : (m,) float
        ``b_O - mean_O``.
    modes : (m, k) float
        ``[P_SPM]_O``.
    variances : (k,) float
    prior : float
        Tikhonov weight (``0`` gives plain least squares, which over-fits with many modes).
    method : {"trust-ncg", "direct"}
        Steihaug's trust-region Newton-CG (as the paper) or a direct solve of the normal equations.
    """
    r = np.asarray(residual, dtype=np.float64)
    P = np.asarray(modes, dtype=np.float64)
    lam = np.asarray(variances, dtype=np.float64)
    H = P.T @ P + prior * np.diag(1.0 / lam)
    g0 = P.T @ r
    if method == "direct":
        return np.linalg.lstsq(H, g0, rcond=None)[0]
    if method != "trust-ncg":
        raise ValueError(f"method must be 'trust-ncg' or 'direct', got {method!r}")
    from scipy.optimize import minimize

    scale = np.sqrt(lam)  # optimise u = v / sqrt(lambda): well conditioned for any variance range
    Hu = H * scale[:, None] * scale[None, :]
    gu = g0 * scale
    res = minimize(
        lambda u: 0.5 * u @ Hu @ u - gu @ u,
        np.zeros(len(lam)),
        jac=lambda u: Hu @ u - gu,
        hess=lambda u: Hu,
        method="trust-ncg",
        options={"gtol": 1e-10 * max(1.0, np.linalg.norm(gu)), "maxiter": 200},
    )
    return res.x * scale


@dataclass(frozen=True)
class TargetPlanner:
    """A pose model for one set of observed bones, with what SPM_CC needs.

    Build it with :meth:`fit`; call :meth:`estimate`.

    Attributes
    ----------
    model : PoseModel
        Fitted with ``frame_bones`` = the observed bones.
    faces : tuple of three (m_l, 3) int arrays
    joints : dict
        Joint surfaces found on the mean shapes at their mean poses.
    min_gap : dict
        Minimum joint space (mm) per ``(joint, moving bone)``, from the training subjects.
    joint_space : JointSpaceModel
        Learned contact offsets and joint spaces for the joint-space refinement.
    prior : float
        Tikhonov weight of equation 8a.
    """

    model: PoseModel
    faces: tuple[NDArray[np.int64], ...]
    joints: dict[tuple[str, str], JointSurface]
    min_gap: dict[tuple[tuple[str, str], str], float]
    joint_space: JointSpaceModel
    prior: float = 1.0
    gap_quantile: float = 0.05

    @property
    def observed(self) -> tuple[str, ...]:
        return self.model.frame_bones

    @property
    def dislocated(self) -> tuple[str, ...]:
        return tuple(b for b in BONES if b not in self.model.frame_bones)

    @classmethod
    def fit(
        cls,
        vertices: ArrayLike,
        faces: Sequence[ArrayLike],
        *,
        observed: Sequence[str],
        prior: float = 1.0,
        n_modes: int | None = None,
        metric: str = "radius",
        joint_distance: float = 8.0,
        gap_quantile: float = 0.05,
        gap_percentile: float = 10.0,
        training_gaps: ArrayLike | None = None,
        training_plane_gaps: ArrayLike | None = None,
        spm_weight: float = 0.3,
        joint_prior: float = 0.01,
        frame_scale: bool | None = None,
    ) -> TargetPlanner:
        """Fit the SPM for ``observed`` bones and calibrate the collision refinement.

        Parameters
        ----------
        vertices : (n_subjects, 3, n_vertices, 3) float, mm
            Training population (never the test subject).
        faces : three (m_l, 3) int arrays
        observed : sequence of str
            Bones that will be seen undislocated at test time (at least one).
        prior : float
            Tikhonov weight of the weights' Gaussian prior (scaled tangent units, mm^2).
        joint_distance : float, mm
            Joint-surface detection distance on the mean shapes.
        gap_quantile, gap_percentile : float
            The minimum joint space is the ``gap_percentile``-th percentile over training subjects
            of each subject's ``gap_quantile``-th lowest joint gap.
        training_gaps : (n_subjects, 3, 2, n_vertices) float, optional
            :func:`subject_joint_gaps` of each training subject, if already computed (they depend
            on each subject alone, so a cross-validation can compute them once).
        training_plane_gaps : (n_subjects, 3, 2, n_vertices) float, optional
            :func:`~pelvicnav.pose.joint_space.subject_plane_gaps` of each training subject.
        spm_weight, joint_prior : float
            Joint-space refinement weights (see :class:`JointSpaceModel`).
        frame_scale : bool, optional
            Similarity (True) or rigid (False) global frame; default: similarity when two bones
            are observed, rigid when only one is (its size alone predicts the pelvis's poorly).

        Raises
        ------
        ValueError
            No observed bone, all bones observed, unknown names, or a bad population.
        """
        observed = check_bones(observed, what="observed bone")
        if not observed:
            raise ValueError("all bones are marked dislocated: at least one bone must be observed")
        if len(observed) == len(BONES):
            raise ValueError("no bone is marked dislocated: nothing to estimate")
        if prior < 0:
            raise ValueError(f"prior must be >= 0, got {prior}")
        V = np.asarray(vertices, dtype=np.float64)
        if frame_scale is None:
            frame_scale = len(observed) > 1
        model = PoseModel.fit(
            V, frame_bones=observed, n_modes=n_modes, metric=metric, frame_scale=frame_scale
        )
        fcs = tuple(np.asarray(f, dtype=np.int64) for f in faces)
        if len(fcs) != 3:
            raise ValueError(f"faces for 3 bones are needed, got {len(fcs)}")
        placed = tf.apply(model.mean_poses, model.mean_shapes)
        joints = find_joint_surfaces(placed, fcs, max_distance=joint_distance)
        gaps = (
            _joint_set_gaps(V, fcs, joints)
            if training_gaps is None
            else as_gap_array(training_gaps, V.shape[0], V.shape[2], "training_gaps")
        )
        min_gap = _min_gaps(gaps, joints, gap_quantile, gap_percentile)
        plane = (
            _training_plane_gaps(V, fcs, joints)
            if training_plane_gaps is None
            else as_gap_array(training_plane_gaps, V.shape[0], V.shape[2], "training_plane_gaps")
        )
        dislocated = tuple(b for b in BONES if b not in observed)
        joint_space = JointSpaceModel.fit(
            V,
            placed,
            joints,
            plane,
            movers=dislocated,
            spm_weight=spm_weight,
            prior_weight=joint_prior,
        )
        return cls(
            model=model,
            faces=fcs,
            joints=joints,
            min_gap=min_gap,
            joint_space=joint_space,
            prior=prior,
            gap_quantile=gap_quantile,
        )

    def estimate(
        self,
        observed: Mapping[str, ArrayLike],
        current: Mapping[str, ArrayLike],
        *,
        refine: str = "joint",
        method: str = "trust-ncg",
    ) -> dict[str, TargetEstimate]:
        """Target poses of the dislocated bones.

        Parameters
        ----------
        observed : mapping bone -> (n_vertices, 3) float, mm
            Segmented meshes of the observed bones (CT frame); exactly :attr:`observed`.
        current : mapping bone -> (n_vertices, 3) float, mm
            Segmented meshes of the dislocated bones where they are now; exactly
            :attr:`dislocated`.
        refine : {"joint", "collision", "none"}
            ``"none"``: plain SPM. ``"collision"``: the paper's SPM_CC refinement (smallest
            translation along the joint normal that removes overlap). ``"joint"`` (default): the
            joint-space refinement (:mod:`pelvicnav.pose.joint_space`) followed by the collision
            check.
        method : str
            Solver of equation 8a (see :func:`solve_weights`).

        Returns
        -------
        dict bone -> TargetEstimate
        """
        nv = self.model.mean_shapes.shape[1]
        obs = _check_meshes(observed, self.observed, nv, "observed")
        cur = _check_meshes(current, self.dislocated, nv, "dislocated")
        m = self.model
        G, v = self._weights(obs, method)
        subject_from_normalised = tf.invert(G)
        poses = m.poses_from_vector(m.mean + m.modes @ v)
        if refine not in ("joint", "collision", "none"):
            raise ValueError(f"refine must be 'joint', 'collision' or 'none', got {refine!r}")
        predicted = {
            bone: tf.apply(
                subject_from_normalised @ poses[BONES.index(bone)], m.mean_shapes[BONES.index(bone)]
            )
            for bone in self.dislocated
        }
        T = {bone: fit_transform(cur[bone], predicted[bone], scale=False) for bone in cur}
        if refine == "joint":
            faces = {b: self.faces[BONES.index(b)] for b in BONES}
            # Bilateral cases seat each hip against the sacrum and the other hip's current
            # estimate, twice round; unilateral cases need one pass.
            for _ in range(2 if len(cur) > 1 else 1):
                for bone in cur:
                    partners = dict(obs)
                    partners.update({b: tf.apply(T[b], cur[b]) for b in cur if b != bone})
                    T[bone] = self.joint_space.refine(
                        bone, cur[bone], predicted[bone], partners, faces
                    )
        out = {
            bone: TargetEstimate(
                bone=bone,
                target_from_current=T[bone],
                vertices=tf.apply(T[bone], cur[bone]),
                predicted_mean=predicted[bone],
            )
            for bone in self.dislocated
        }
        if refine in ("joint", "collision"):
            out = self._refine(out, obs)
        return out

    def _weights(self, obs: Mapping[str, NDArray], method: str) -> tuple[NDArray, NDArray]:
        """The normalising frame of the observed bones and the SPM weights explaining them."""
        m = self.model
        G = m.normalised_from_subject(np.stack([obs[b] for b in self.observed]))
        rows = np.concatenate([np.arange(7 * BONES.index(b), 7 * BONES.index(b) + 7) for b in obs])
        b_obs = np.concatenate([m.tangent(b, tf.apply(G, obs[b])) for b in self.observed])
        v = solve_weights(
            b_obs - m.mean[rows], m.modes[rows], m.variances, prior=self.prior, method=method
        )
        return G, v

    def plausibility(
        self, observed: Mapping[str, ArrayLike], *, method: str = "trust-ncg"
    ) -> float:
        """How unusual the observed bones' relative poses are: ``sum_k v_k^2 / lambda_k`` of the
        SPM weights that explain them (equation 8a; 0 for the mean pelvis). A dislocated bone
        among the observed ones needs large weights."""
        nv = self.model.mean_shapes.shape[1]
        obs = _check_meshes(observed, self.observed, nv, "observed")
        _, v = self._weights(obs, method)
        return float(np.sum(v**2 / self.model.variances))

    # ---- SPM_CC ---------------------------------------------------------------------------------
    def _refine(
        self, est: dict[str, TargetEstimate], obs: dict[str, NDArray]
    ) -> dict[str, TargetEstimate]:
        shifts = {b: np.zeros(3) for b in est}
        # Joints between a dislocated bone and an observed one: move the dislocated bone.
        # Joints between two dislocated bones (bilateral): move both, half each.
        for _ in range(2):
            changed = False
            for pair, joint in self.joints.items():
                movers = [b for b in pair if b in est]
                if not movers:
                    continue
                mover = movers[0] if len(movers) == 1 else pair[1]
                other = pair[0] if mover == pair[1] else pair[1]
                positions = {b: est[b].vertices + shifts[b] for b in est}
                fixed_v = positions.get(other, obs.get(other))
                moving_v = positions[mover]
                side = joint.side(mover)
                normals = vertex_normals(moving_v, self.faces[BONES.index(mover)])
                direction = -normals[joint.vertices[side]].mean(axis=0)
                direction /= np.linalg.norm(direction)
                split = 0.5 if len(movers) == 2 else 1.0

                def gaps_after(
                    shift,
                    joint=joint,
                    mover=mover,
                    other=other,
                    split=split,
                    moving_v=moving_v,
                    fixed_v=fixed_v,
                ):
                    moved = moving_v + split * shift
                    fixed = fixed_v - (1 - split) * shift
                    return _gaps_between(joint, mover, other, moved, fixed, self.faces)

                delta = refine_translation(
                    gaps_after,
                    direction,
                    min_gap=self.min_gap[(pair, mover)],
                    quantile=self.gap_quantile,
                )
                if delta > 0:
                    changed = True
                    shifts[mover] = shifts[mover] + split * delta * direction
                    if len(movers) == 2:
                        shifts[other] = shifts[other] - (1 - split) * delta * direction
            if not changed:
                break
        out = {}
        for b, e in est.items():
            D = np.eye(4)
            D[:3, 3] = shifts[b]
            out[b] = TargetEstimate(
                bone=b,
                target_from_current=D @ e.target_from_current,
                vertices=e.vertices + shifts[b],
                predicted_mean=e.predicted_mean,
                refinement=shifts[b],
            )
        return out


def _gaps_between(joint, mover, other, moving_v, fixed_v, faces) -> NDArray[np.float64]:
    return joint_gaps(
        moving_v,
        faces[BONES.index(mover)],
        joint.vertices[joint.side(mover)],
        fixed_v,
        faces[BONES.index(other)],
        joint.faces[joint.side(other)],
    )


def _min_gaps(gaps: NDArray, joints: dict, gap_quantile: float,
              gap_percentile: float) -> dict[tuple, float]:  # fmt: skip
    """The collision refinement's minimum joint space per (joint, moving bone), mm: the
    ``gap_percentile``-th percentile over subjects of each subject's ``gap_quantile``-th lowest
    gap on that side's joint vertices (``gaps``: (n_subjects, 3, 2, n_vertices), NaN where
    unmeasured; 0 when no subject has one)."""
    min_gap = {}
    for k, pair in enumerate(JOINTS):
        joint = joints[pair]
        for side, mover in enumerate(pair):
            g = gaps[:, k, side][:, joint.vertices[side]]
            per_subject = [np.quantile(row[np.isfinite(row)], gap_quantile)
                           for row in g if np.isfinite(row).any()]  # fmt: skip
            min_gap[(pair, mover)] = (
                float(np.percentile(per_subject, gap_percentile)) if per_subject else 0.0
            )
    return min_gap


def _training_plane_gaps(V: NDArray, faces: tuple, joints: dict) -> NDArray:
    """:func:`~pelvicnav.pose.joint_space.subject_plane_gaps` of every training subject on the
    joint vertices, (n_subjects, 3, 2, n_vertices)."""
    sets = {(k, side): joints[pair].vertices[side] for k, pair in enumerate(JOINTS)
            for side in range(2)}  # fmt: skip
    return np.stack([subject_plane_gaps(V[n], faces, vertex_sets=sets) for n in range(V.shape[0])])


def _joint_set_gaps(V: NDArray, faces: tuple, joints: dict) -> NDArray[np.float64]:
    """Ray-cast joint gaps of training subjects, on the joint vertex sets only (fast path)."""
    out = np.full((V.shape[0], len(JOINTS), 2, V.shape[2]), np.nan)
    for n in range(V.shape[0]):
        normals = [vertex_normals(V[n, l], faces[l]) for l in range(3)]
        for k, pair in enumerate(JOINTS):
            joint = joints[pair]
            for side, mover in enumerate(pair):
                this, other = BONES.index(mover), BONES.index(pair[1 - side])
                idx = joint.vertices[side]
                tris = V[n, other][faces[other][joint.faces[1 - side]]]
                out[n, k, side, idx] = ray_triangle_distances(
                    V[n, this][idx], normals[this][idx], tris
                )
    return out


def _check_meshes(
    meshes: Mapping[str, ArrayLike], expected: tuple[str, ...], n_vertices: int, what: str
) -> dict[str, NDArray[np.float64]]:
    names = check_bones(list(meshes), what=f"{what} bone")
    if set(names) != set(expected):
        raise ValueError(
            f"{what} bones must be exactly {list(expected)} for this model, got {list(names)}"
        )
    out = {}
    for b in expected:
        x = np.asarray(meshes[b], dtype=np.float64)
        if x.shape != (n_vertices, 3):
            raise ValueError(f"{what} mesh {b} must have shape ({n_vertices}, 3), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{what} mesh {b} contains NaN or infinity")
        out[b] = x
    return out
