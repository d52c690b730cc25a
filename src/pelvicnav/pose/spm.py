"""Statistical pose model (SPM): principal geodesic analysis of per-bone similarity transforms.

Han et al. (2020), section 2.1.2, equations 6-7. For every training subject ``n`` and bone ``l``:

1. *Global frame.* The subject is normalised by a similarity Procrustes fit of its **frame bones**
   (by default the bones that will be observed at test time) onto their population mean. Using the
   same bones for training and test keeps the frame consistent, and a frame that never touches the
   dislocated bone cannot leak its true pose into the estimate.
2. *Local pose* (equation 6). ``T_nl = argmin_T |S_nl - T(mean_l)|^2`` over similarity transforms,
   with ``mean_l`` the bone's mean shape centred on its centroid, so rotations turn the bone about
   its own centre.
3. *Tangent space.* The Frechet mean ``mu_l`` of ``T_nl`` over subjects, then
   ``b_nl = log(mu_l^-1 T_nl)`` (exact Sim(3) logarithm, equation 3) and the 7L-vector per subject.
4. *PGA* (equation 7): PCA of the 7L-vectors after a metric scaling: rotation and log-scale
   components are multiplied by ``rho_l`` (the bone's RMS radius, mm), so one unit is the
   displacement it causes at the bone's surface and mm and radians become commensurable.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.shape.ssm import generalized_procrustes

__all__ = ["BONES", "PoseModel", "check_bones", "frechet_mean"]

BONES: tuple[str, ...] = ("sacrum", "left_hip", "right_hip")


def check_bones(names: Sequence[str], *, what: str = "bone") -> tuple[str, ...]:
    """Validate bone names (``ValueError`` naming an unknown one); keep the canonical order."""
    names = tuple(names)
    for b in names:
        if b not in BONES:
            raise ValueError(f"unknown {what} {b!r}; expected one of {BONES}")
    if len(set(names)) != len(names):
        raise ValueError(f"repeated {what} in {names}")
    return tuple(b for b in BONES if b in names)


def frechet_mean(T: ArrayLike, *, max_iter: int = 50, tol: float = 1e-12) -> NDArray[np.float64]:
    """Intrinsic (Frechet/Karcher) mean of similarity transforms, ``(n, 4, 4) -> (4, 4)``.

    Iterates ``mu <- mu exp(mean_n log(mu^-1 T_n))`` (Pennec 2006) from the first transform.
    """
    T = np.asarray(T, dtype=np.float64)
    mu = T[0]
    for _ in range(max_iter):
        step = tf.sim3_log(tf.invert(mu) @ T).mean(axis=0)
        mu = mu @ tf.sim3_exp(step)
        if np.linalg.norm(step) < tol:
            break
    return mu


@dataclass(frozen=True)
class PoseModel:
    """A fitted statistical pose model.

    Attributes
    ----------
    frame_bones : tuple of str
        Bones whose vertices define each subject's global frame.
    frame_reference : (n_frame_vertices, 3) float64
        Population mean of the frame bones' vertices (the frame's target).
    mean_shapes : (3, n_vertices, 3) float64
        Each bone's mean shape, centred on its centroid (bone-local frame).
    mean_poses : (3, 4, 4) float64
        Frechet mean of each bone's pose (bone-local -> normalised frame).
    metric : (21,) float64
        Scaling of the tangent components before PCA (1 for mm, ``rho_l`` for rad and log-scale).
    mean : (21,) float64
        Mean of the scaled tangent vectors.
    modes : (21, n_modes) float64
        Orthonormal principal directions (scaled tangent space).
    variances : (n_modes,) float64
    training : (n_subjects, 21) float64
        Scaled tangent vectors of the training subjects.
    frame_scale : bool
        Whether the global frame removes scale (similarity) or only a rigid motion.
    """

    frame_bones: tuple[str, ...]
    frame_reference: NDArray[np.float64]
    mean_shapes: NDArray[np.float64]
    mean_poses: NDArray[np.float64]
    metric: NDArray[np.float64]
    mean: NDArray[np.float64]
    modes: NDArray[np.float64]
    variances: NDArray[np.float64]
    training: NDArray[np.float64]
    frame_scale: bool = True

    @property
    def n_modes(self) -> int:
        return self.modes.shape[1]

    @classmethod
    def fit(
        cls,
        vertices: ArrayLike,
        *,
        frame_bones: Sequence[str] = BONES,
        n_modes: int | None = None,
        metric: str = "radius",
        frame_scale: bool = True,
    ) -> PoseModel:
        """Fit the SPM to a population.

        Parameters
        ----------
        vertices : (n_subjects, 3, n_vertices, 3) float, mm
            Corresponding vertices of sacrum, left and right innominate per subject.
        frame_bones : sequence of str
            Bones that define the global frame (use the bones observed at test time).
        n_modes : int, optional
            Principal modes to keep; default all (``n_subjects - 1``) with non-zero variance.
        metric : {"radius", "plain"}
            ``"radius"`` scales rotation and log-scale by the bone's RMS radius (mm); ``"plain"``
            uses the raw 7-vector as in equation 5.
        frame_scale : bool
            Normalise subjects by a similarity (True, the paper's Procrustes) or a rigid transform
            of the frame bones. With the sacrum alone as frame, its size is a poor proxy of the
            pelvis's, and keeping mm (rigid) lets the model learn the relation instead.

        Raises
        ------
        ValueError
            Wrong array shape, non-finite vertices, unknown bone, or more modes than
            ``n_subjects - 1``.
        """
        V = np.asarray(vertices, dtype=np.float64)
        if V.ndim != 4 or V.shape[1] != 3 or V.shape[3] != 3:
            raise ValueError(
                f"vertices must have shape (n_subjects, 3, n_vertices, 3), got {V.shape}"
            )
        if not np.all(np.isfinite(V)):
            raise ValueError("vertices contain NaN or infinity")
        n = V.shape[0]
        if n < 3:
            raise ValueError(f"a pose model needs at least 3 subjects, got {n}")
        if n_modes is not None and not 1 <= n_modes <= n - 1:
            raise ValueError(
                f"n_modes={n_modes} is not available from {n} subjects (at most {n - 1} modes)"
            )
        if metric not in ("radius", "plain"):
            raise ValueError(f"metric must be 'radius' or 'plain', got {metric!r}")
        frame_bones = check_bones(frame_bones, what="frame bone")
        if not frame_bones:
            raise ValueError("at least one frame bone is needed")
        fidx = [BONES.index(b) for b in frame_bones]

        # 1. global frame from the frame bones
        frame_pts = V[:, fidx].reshape(n, -1, 3)
        gpa = generalized_procrustes(frame_pts, scale=frame_scale)
        normalised = tf.apply(gpa.transforms[:, None], V)  # (n, 3, nv, 3)

        # 2. local poses against each bone's mean shape (centred)
        mean_shapes = normalised.mean(axis=0)
        mean_shapes = mean_shapes - mean_shapes.mean(axis=1, keepdims=True)
        poses = np.stack(
            [fit_transform(mean_shapes[None, l], normalised[:, l], scale=True) for l in range(3)],
            axis=1,
        )  # (n, 3, 4, 4) normalised_from_bone
        # 3. tangent vectors at the Frechet mean of each bone
        mean_poses = np.stack([frechet_mean(poses[:, l]) for l in range(3)])
        b = tf.sim3_log(tf.invert(mean_poses)[None] @ poses)  # (n, 3, 7)
        radius = np.sqrt(np.mean(np.sum(mean_shapes**2, axis=-1), axis=-1))  # (3,)
        rho = radius if metric == "radius" else np.ones(3)
        w = np.concatenate([np.r_[1.0, 1.0, 1.0, r, r, r, r] for r in rho])
        X = b.reshape(n, -1) * w
        # 4. PCA
        mean = X.mean(axis=0)
        _, s, vt = np.linalg.svd(X - mean, full_matrices=False)
        variances = s**2 / (n - 1)
        # Modes with no variance (degenerate populations) carry nothing and would break the prior.
        nonzero = int(np.sum(variances > 1e-12 * variances[0]))
        keep = min(n_modes if n_modes is not None else n - 1, nonzero, len(variances))
        return cls(
            frame_bones=frame_bones,
            frame_reference=gpa.mean,
            mean_shapes=mean_shapes,
            mean_poses=mean_poses,
            metric=w,
            mean=mean,
            modes=vt[:keep].T.copy(),
            variances=variances[:keep].copy(),
            training=X,
            frame_scale=frame_scale,
        )

    # ---- frames and tangent vectors ---------------------------------------------------------
    def normalised_from_subject(self, frame_vertices: ArrayLike) -> NDArray[np.float64]:
        """Similarity ``(4, 4)`` taking a subject to the model's normalised frame.

        Parameters
        ----------
        frame_vertices : (n_frame_bones, n_vertices, 3) float, mm
            The subject's vertices of :attr:`frame_bones`, in that order.
        """
        x = np.asarray(frame_vertices, dtype=np.float64)
        expected = (len(self.frame_bones), self.mean_shapes.shape[1], 3)
        if x.shape != expected:
            raise ValueError(
                f"frame vertices for {self.frame_bones} must have shape {expected}, got {x.shape}"
            )
        return fit_transform(x.reshape(-1, 3), self.frame_reference, scale=self.frame_scale)

    def tangent(self, bone: str, normalised_vertices: ArrayLike) -> NDArray[np.float64]:
        """Scaled tangent 7-vector of one bone given its vertices in the normalised frame."""
        l = BONES.index(check_bones([bone])[0])
        T = fit_transform(self.mean_shapes[l], np.asarray(normalised_vertices), scale=True)
        return tf.sim3_log(tf.invert(self.mean_poses[l]) @ T) * self.metric[7 * l : 7 * l + 7]

    def poses_from_vector(self, x: ArrayLike) -> NDArray[np.float64]:
        """Per-bone poses ``(3, 4, 4)`` (bone-local -> normalised) from a scaled 21-vector."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (21,):
            raise ValueError(f"a pose vector has shape (21,), got {x.shape}")
        b = (x / self.metric).reshape(3, 7)
        return self.mean_poses @ tf.sim3_exp(b)

    def instance(self, weights: ArrayLike) -> NDArray[np.float64]:
        """Mean shapes placed by mode weights ``v`` (equation 7): ``(3, n_vertices, 3)``."""
        v = np.asarray(weights, dtype=np.float64)
        if v.shape != (self.n_modes,):
            raise ValueError(f"weights must have shape ({self.n_modes},), got {v.shape}")
        T = self.poses_from_vector(self.mean + self.modes @ v)
        return tf.apply(T, self.mean_shapes)
