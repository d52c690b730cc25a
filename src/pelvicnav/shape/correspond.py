"""Correspondence on a given surface: the shape model's most probable vertex placement.

A mesh fitted to an image (the ASM's free-form stage) can have the right surface with its
vertices slid along it: vertex ``i`` is no longer the anatomical point the model's vertex ``i``
is. Whatever uses vertex correspondence (the pose model, the joint-space refinement) then sees a
bone that is moved or turned by the slide. Measured on the atlas leave-one-out, the ASM's left
hips were 1.4 mm / 1.6 degrees (median) from their own corresponded pose with the surface within
0.7 mm.

:func:`refine_correspondence` fits the shape model to the surface with **point-to-plane**
residuals only: ``sum_i (n_i . (T(mean_i + P_i w) - c_i))^2 / sigma^2 + sum_k w_k^2 / lambda_k``
(``c_i`` the closest surface point, ``n_i`` its normal). A slide along the surface costs nothing in
the data term, so the tangential placement is the prior's (the MAP estimate given the surface),
not the fit's accident. The result is then projected back onto the surface, which therefore does
not change. On the same leave-one-out it halves the left hips' pose error (0.7 mm / 0.7 degrees).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.shape.mesh import face_normals
from pelvicnav.shape.ssm import ShapeModel

__all__ = ["refine_correspondence"]


def _closest(points: NDArray, vertices: NDArray, faces: NDArray, normals: NDArray):
    """Closest surface points and the normals of their triangles."""
    import igl

    _, tri, c = igl.point_mesh_squared_distance(points, vertices, faces)
    return np.asarray(c), normals[np.asarray(tri)]


def _similarity_step(x: NDArray, c: NDArray, n: NDArray) -> NDArray[np.float64]:
    """One linearised point-to-plane update of a similarity (translation, rotation, scale)
    about the points' centroid, as a 4x4 applied on the left."""
    g = x.mean(axis=0)
    r = np.einsum("ij,ij->i", n, x - c)
    J = np.hstack([n, np.cross(x - g, n), np.einsum("ij,ij->i", n, x - g)[:, None]])
    d = np.linalg.lstsq(J, -r, rcond=None)[0]
    D = np.eye(4)
    D[:3, :3] = (1.0 + d[6]) * tf.matrix_from_rotvec(d[3:6])
    D[:3, 3] = g + d[:3] - D[:3, :3] @ g
    return D


def refine_correspondence(
    ssm: ShapeModel,
    vertices: ArrayLike,
    faces: ArrayLike,
    *,
    noise_mm2: float = 0.5,
    iterations: int = 20,
    max_sigma: float = 3.0,
) -> NDArray[np.float64]:
    """Re-place a mesh's vertices on its own surface where the shape model expects them.

    Parameters
    ----------
    ssm : ShapeModel
        The bone's model (its topology is the mesh's).
    vertices : (n_vertices, 3) float, mm
        A mesh in the model's topology (e.g. the ASM's result); its surface is kept.
    faces : (m, 3) int
        Closed triangulation of the model.
    noise_mm2 : float
        ``sigma^2`` of the point-to-plane residuals (larger trusts the mean shape more).
    iterations : int
        Alternations of similarity and weights.
    max_sigma : float
        Weights are clamped to +- this many standard deviations.

    Returns
    -------
    (n_vertices, 3) float64
        The fitted instance's vertices projected onto the given surface.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if V.shape != ssm.mean.shape:
        raise ValueError(f"mesh {V.shape} does not match the model's {ssm.mean.shape}")
    if noise_mm2 <= 0 or iterations < 1:
        raise ValueError("noise_mm2 must be positive and iterations at least 1")
    normals = face_normals(V, F)
    P = ssm.modes.reshape(-1, 3, ssm.n_modes)
    limit = max_sigma * np.sqrt(ssm.variances)
    T = fit_transform(ssm.mean, V, scale=True)
    w = np.zeros(ssm.n_modes)
    for _ in range(iterations):
        shape = ssm.mean + (ssm.modes @ w).reshape(-1, 3)
        x = tf.apply(T, shape)
        T = _similarity_step(x, *_closest(x, V, F, normals)) @ T
        c, n = _closest(tf.apply(T, shape), V, F, normals)
        A = np.einsum("ij,jk,ikm->im", n, T[:3, :3], P)  # d(n . x) / dw
        r0 = np.einsum("ij,ij->i", n, tf.apply(T, ssm.mean) - c)
        H = A.T @ A / noise_mm2 + np.diag(1.0 / ssm.variances)
        w = np.clip(np.linalg.solve(H, -A.T @ r0 / noise_mm2), -limit, limit)
    x = tf.apply(T, ssm.mean + (ssm.modes @ w).reshape(-1, 3))
    return _closest(x, V, F, normals)[0]
