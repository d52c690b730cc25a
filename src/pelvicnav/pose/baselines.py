"""Baseline target-pose estimators of Han et al. (2020), section 2.3.1.

* **SSM_single** - one shape model of the whole pelvis (three bones concatenated), so shape and pose
  share one PCA. It is fitted to the observed bones (equation 13a, with a similarity alignment and a
  Gaussian prior on the weights), predicts the dislocated bone's vertices (13b), and the bone's own
  mesh is fitted rigidly onto the prediction.
* **CM, contralateral mirroring** - the mid-sagittal plane is estimated from the sacrum's point
  cloud (symmetry plane by iteratively reweighted matching of the cloud with its reflection, in the
  manner of Combes et al. 2008), the contralateral innominate is mirrored across it, and the
  dislocated bone is registered rigidly to the mirror image. Left and right innominates have no
  vertex correspondence, so a left-right vertex map is built once on the training mean shapes
  (mirror + ICP + nearest neighbours) to initialise the fit, which ICP then refines.

B. Combes, R. Hennessy, J. Waddington, N. Roberts, S. Prima, "Automatic symmetry plane estimation of
bilateral objects in point clouds", CVPR 2008, doi:10.1109/CVPR.2008.4587571.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.pose.spm import BONES, check_bones
from pelvicnav.shape.ssm import ShapeModel, generalized_procrustes

__all__ = [
    "MirrorEstimator",
    "SinglePelvisEstimator",
    "icp",
    "reflection",
    "symmetry_plane",
]


# ---- SSM_single ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class SinglePelvisEstimator:
    """SSM_single: the three bones as one shape (equation 13)."""

    model: ShapeModel
    n_vertices: int
    noise_variance: float = 4.0

    @classmethod
    def fit(
        cls, vertices: ArrayLike, *, noise_variance: float = 4.0, n_modes: int | None = None
    ) -> SinglePelvisEstimator:
        """Build the single-pelvis SSM from ``(n_subjects, 3, n_vertices, 3)`` training vertices."""
        V = np.asarray(vertices, dtype=np.float64)
        if V.ndim != 4 or V.shape[1] != 3 or V.shape[3] != 3:
            raise ValueError(
                f"vertices must have shape (n_subjects, 3, n_vertices, 3), got {V.shape}"
            )
        model = ShapeModel.fit(V.reshape(len(V), -1, 3), align="similarity", n_modes=n_modes)
        return cls(model=model, n_vertices=V.shape[2], noise_variance=noise_variance)

    def estimate(
        self, observed: Mapping[str, ArrayLike], current: Mapping[str, ArrayLike]
    ) -> dict[str, NDArray[np.float64]]:
        """``target_from_current`` (rigid 4x4) for each bone in ``current``."""
        obs_names = check_bones(list(observed), what="observed bone")
        cur_names = check_bones(list(current), what="dislocated bone")
        if not obs_names:
            raise ValueError("all bones are marked dislocated: at least one bone must be observed")
        nv = self.n_vertices
        idx = np.concatenate([np.arange(nv) + BONES.index(b) * nv for b in obs_names])
        pts = np.concatenate([np.asarray(observed[b], dtype=np.float64) for b in obs_names])
        fit = self.model.fit_partial(pts, idx, noise_variance=self.noise_variance)
        out = {}
        for b in cur_names:
            pred = fit.vertices[BONES.index(b) * nv : (BONES.index(b) + 1) * nv]
            out[b] = fit_transform(np.asarray(current[b], dtype=np.float64), pred, scale=False)
        return out


# ---- contralateral mirroring --------------------------------------------------------------------


def reflection(normal: ArrayLike, offset: float) -> NDArray[np.float64]:
    """4x4 reflection across the plane ``n . x = offset`` (``n`` normalised here)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    M = np.eye(4)
    M[:3, :3] -= 2.0 * np.outer(n, n)
    M[:3, 3] = 2.0 * offset * n
    return M


def symmetry_plane(
    points: ArrayLike,
    *,
    initial_normal: ArrayLike = (1.0, 0.0, 0.0),
    max_iter: int = 100,
    tol: float = 1e-7,
) -> tuple[NDArray[np.float64], float]:
    """Plane of bilateral symmetry of a point cloud, ``n . x = d``.

    Alternates (1) matching every point's reflection to its nearest cloud point and (2) the plane
    that best bisects the matched pairs: ``n`` = principal direction of the pair differences and
    ``d`` = mean of ``n . midpoints``, with Cauchy weights on the residuals (robust to asymmetric
    parts, as Combes et al. 2008).

    Parameters
    ----------
    points : (n, 3) float, mm
    initial_normal : (3,) float
        Starting normal (the patient's left-right axis; LPS x for a CT).

    Returns
    -------
    normal : (3,) float64, unit, same hemisphere as ``initial_normal``
    offset : float, mm
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 10:
        raise ValueError(f"points must have shape (n >= 10, 3), got {p.shape}")
    n0 = np.asarray(initial_normal, dtype=np.float64)
    n = n0 / np.linalg.norm(n0)
    d = float(n @ p.mean(axis=0))
    tree = cKDTree(p)
    scale = None
    for _ in range(max_iter):
        reflected = tf.apply(reflection(n, d), p)
        dist, j = tree.query(reflected)
        if scale is None:
            scale = max(float(np.median(dist)), 1e-3)
        w = 1.0 / (1.0 + (dist / scale) ** 2)
        q = p[j]
        u = p - q
        cov = (w[:, None] * u).T @ u
        evals, evecs = np.linalg.eigh(cov)
        n_new = evecs[:, -1]
        if n_new @ n0 < 0:
            n_new = -n_new
        d_new = float(np.sum(w * ((p + q) / 2.0 @ n_new)) / np.sum(w))
        change = np.linalg.norm(n_new - n) + abs(d_new - d) / 100.0
        n, d = n_new, d_new
        scale = max(0.5 * scale + 0.5 * float(np.median(dist)), 1e-3)
        if change < tol:
            break
    return n, d


def icp(
    source: ArrayLike,
    target: ArrayLike,
    *,
    init: ArrayLike | None = None,
    max_iter: int = 50,
    tol: float = 1e-6,
    trim: float = 0.9,
) -> NDArray[np.float64]:
    """Rigid trimmed point-to-point ICP: ``target_from_source`` (4x4).

    Each iteration matches the transformed source points to their nearest target points, keeps the
    ``trim`` fraction with the smallest distances, and refits the rigid transform.
    """
    from scipy.spatial import cKDTree

    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    T = np.eye(4) if init is None else np.asarray(init, dtype=np.float64)
    tree = cKDTree(dst)
    prev = np.inf
    for _ in range(max_iter):
        moved = tf.apply(T, src)
        dist, j = tree.query(moved)
        keep = dist <= np.quantile(dist, trim)
        T = fit_transform(src[keep], dst[j[keep]], scale=False)
        err = float(np.sqrt(np.mean(dist[keep] ** 2)))
        if abs(prev - err) < tol:
            break
        prev = err
    return T


@dataclass(frozen=True)
class MirrorEstimator:
    """CM: mirror the contralateral innominate across the sacrum's mid-sagittal plane.

    Attributes
    ----------
    left_from_right : (n_vertices,) int
        For each left-innominate vertex, the matching vertex of the mirrored right innominate.
    right_from_left : (n_vertices,) int
    """

    left_from_right: NDArray[np.int64]
    right_from_left: NDArray[np.int64]

    @classmethod
    def fit(cls, vertices: ArrayLike) -> MirrorEstimator:
        """Build the left-right vertex map on the training population's mean shapes."""
        from scipy.spatial import cKDTree

        V = np.asarray(vertices, dtype=np.float64)
        if V.ndim != 4 or V.shape[1] != 3 or V.shape[3] != 3:
            raise ValueError(
                f"vertices must have shape (n_subjects, 3, n_vertices, 3), got {V.shape}"
            )
        n = len(V)
        mean = generalized_procrustes(V.reshape(n, -1, 3), scale=True).mean.reshape(3, -1, 3)
        normal, offset = symmetry_plane(mean[0])
        mirrored_right = tf.apply(reflection(normal, offset), mean[2])
        T = icp(mirrored_right, mean[1])
        mirrored_right = tf.apply(T, mirrored_right)
        _, lr = cKDTree(mirrored_right).query(mean[1])
        _, rl = cKDTree(mean[1]).query(mirrored_right)
        return cls(left_from_right=lr.astype(np.int64), right_from_left=rl.astype(np.int64))

    def estimate(
        self, observed: Mapping[str, ArrayLike], current: Mapping[str, ArrayLike]
    ) -> dict[str, NDArray[np.float64]]:
        """``target_from_current`` for the one dislocated innominate.

        Raises
        ------
        ValueError
            Unless the sacrum and exactly one innominate are observed (CM cannot handle bilateral
            dislocation).
        """
        obs = check_bones(list(observed), what="observed bone")
        cur = check_bones(list(current), what="dislocated bone")
        if "sacrum" not in obs or len(cur) != 1 or cur[0] == "sacrum" or cur[0] in obs:
            raise ValueError(
                "contralateral mirroring needs the sacrum and one innominate observed and the "
                f"other innominate dislocated; got observed {list(obs)}, dislocated {list(cur)}"
            )
        bone = cur[0]
        contra = "right_hip" if bone == "left_hip" else "left_hip"
        sacrum = np.asarray(observed["sacrum"], dtype=np.float64)
        other = np.asarray(observed[contra], dtype=np.float64)
        moving = np.asarray(current[bone], dtype=np.float64)
        # Start from the CT's left-right axis (LPS x); the iteration finds the actual plane.
        normal, offset = symmetry_plane(sacrum)
        mirrored = tf.apply(reflection(normal, offset), other)
        corr = self.left_from_right if bone == "left_hip" else self.right_from_left
        init = fit_transform(moving, mirrored[corr], scale=False)
        return {bone: icp(moving, mirrored, init=init)}
