"""Statistical shape models: generalised Procrustes alignment and PCA over corresponding vertices.

``S = mean + P v`` (Han et al. 2020, section 2.1.1) with ``P`` orthonormal modes and ``v`` weights
whose prior variances are the PCA eigenvalues. A model can be fitted to a partial observation (some
vertices, e.g. the bones that are not dislocated) with a similarity alignment and a Gaussian prior
on the weights.

References
----------
J. C. Gower, "Generalized Procrustes analysis", Psychometrika 40 (1975) 33-51.
T. F. Cootes et al., "Active shape models - their training and application", CVIU 61 (1995) 38-59.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform

__all__ = ["GPAResult", "PartialFit", "ShapeModel", "generalized_procrustes"]


@dataclass(frozen=True)
class GPAResult:
    """Result of :func:`generalized_procrustes`.

    Attributes
    ----------
    mean : (n_vertices, 3) float64
        Consensus shape, centred at the origin; with scaling its centroid size equals the mean
        centroid size of the inputs, so it stays in mm.
    aligned : (n_shapes, n_vertices, 3) float64
        Every input mapped onto the mean.
    transforms : (n_shapes, 4, 4) float64
        ``mean_from_subject`` for each input (similarity or rigid).
    iterations : int
    """

    mean: NDArray[np.float64]
    aligned: NDArray[np.float64]
    transforms: NDArray[np.float64]
    iterations: int


def _check_shapes(shapes: ArrayLike, name: str = "shapes") -> NDArray[np.float64]:
    x = np.asarray(shapes, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"{name} must have shape (n_shapes, n_vertices, 3), got {x.shape}")
    if x.shape[0] < 2:
        raise ValueError(f"{name}: need at least 2 shapes, got {x.shape[0]}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contain NaN or infinity")
    return x


def generalized_procrustes(
    shapes: ArrayLike,
    *,
    scale: bool = True,
    max_iter: int = 100,
    tol: float = 1e-10,
) -> GPAResult:
    """Align shapes to their common mean (iterated Procrustes).

    Parameters
    ----------
    shapes : (n_shapes, n_vertices, 3) float, mm
    scale : bool
        Similarity (True) or rigid (False) alignment.
    max_iter : int
    tol : float
        Stop when the mean moves less than this (RMS, mm).

    Returns
    -------
    GPAResult

    Notes
    -----
    The gauge (the mean's orientation) is fixed to the first shape's: each iteration's mean is
    re-aligned rigidly onto the previous one, so results do not drift.
    """
    x = _check_shapes(shapes)
    sizes = np.sqrt(np.sum((x - x.mean(axis=1, keepdims=True)) ** 2, axis=(1, 2)))
    mean = x[0] - x[0].mean(axis=0)
    T = np.tile(np.eye(4), (len(x), 1, 1))
    aligned = x
    it = 0
    for it in range(1, max_iter + 1):
        T = fit_transform(x, np.broadcast_to(mean, x.shape), scale=scale)
        aligned = tf.apply(T, x)
        new = aligned.mean(axis=0)
        new = new - new.mean(axis=0)
        if scale:
            new *= sizes.mean() / np.sqrt(np.sum(new**2))
        new = tf.apply(fit_transform(new, mean, scale=False), new)
        moved = np.sqrt(np.mean(np.sum((new - mean) ** 2, axis=1)))
        mean = new
        if moved < tol:
            break
    T = fit_transform(x, np.broadcast_to(mean, x.shape), scale=scale)
    return GPAResult(mean=mean, aligned=tf.apply(T, x), transforms=T, iterations=it)


@dataclass(frozen=True)
class PartialFit:
    """A shape model fitted to some of its vertices.

    Attributes
    ----------
    weights : (n_modes,) float64
    subject_from_model : (4, 4) float64
        Similarity placing the model instance on the observation.
    vertices : (n_vertices, 3) float64
        The whole model instance in the observation's frame (observed and predicted vertices).
    rms : float
        RMS residual (mm) at the observed vertices.
    iterations : int
    """

    weights: NDArray[np.float64]
    subject_from_model: NDArray[np.float64]
    vertices: NDArray[np.float64]
    rms: float
    iterations: int


@dataclass(frozen=True)
class ShapeModel:
    """Point distribution model ``S = mean + modes @ v`` (vertices flattened as x0 y0 z0 x1 ...).

    Attributes
    ----------
    mean : (n_vertices, 3) float64, mm
    modes : (3 n_vertices, n_modes) float64, orthonormal columns
    variances : (n_modes,) float64, mm^2, decreasing
    """

    mean: NDArray[np.float64]
    modes: NDArray[np.float64]
    variances: NDArray[np.float64]

    @property
    def n_modes(self) -> int:
        return self.modes.shape[1]

    @property
    def n_vertices(self) -> int:
        return self.mean.shape[0]

    @classmethod
    def fit(
        cls,
        shapes: ArrayLike,
        *,
        align: str = "similarity",
        n_modes: int | None = None,
    ) -> ShapeModel:
        """Build a model from corresponding shapes.

        Parameters
        ----------
        shapes : (n_shapes, n_vertices, 3) float, mm
        align : {"similarity", "rigid", "none"}
            Generalised Procrustes alignment before PCA.
        n_modes : int, optional
            Modes to keep (at most ``n_shapes - 1``); default all with non-zero variance.

        Raises
        ------
        ValueError
            Bad shapes, unknown ``align``, or more modes requested than the data support.
        """
        x = _check_shapes(shapes)
        if align == "none":
            aligned = x
        elif align in ("similarity", "rigid"):
            aligned = generalized_procrustes(x, scale=align == "similarity").aligned
        else:
            raise ValueError(f"align must be 'similarity', 'rigid' or 'none', got {align!r}")
        n = len(x)
        if n_modes is not None and not 1 <= n_modes <= n - 1:
            raise ValueError(
                f"n_modes={n_modes} is not available from {n} shapes (at most {n - 1} modes)"
            )
        mean = aligned.mean(axis=0)
        centred = (aligned - mean).reshape(n, -1)
        _, s, vt = np.linalg.svd(centred, full_matrices=False)
        variances = s**2 / (n - 1)
        keep = n_modes if n_modes is not None else int(np.sum(variances > 1e-12 * variances[0]))
        keep = min(keep, n - 1)
        return cls(mean=mean, modes=vt[:keep].T.copy(), variances=variances[:keep].copy())

    def instance(self, weights: ArrayLike) -> NDArray[np.float64]:
        """Shape for mode weights ``v`` (mm): ``(n_modes,) -> (n_vertices, 3)``."""
        v = np.asarray(weights, dtype=np.float64)
        if v.shape != (self.n_modes,):
            raise ValueError(f"weights must have shape ({self.n_modes},), got {v.shape}")
        return self.mean + (self.modes @ v).reshape(-1, 3)

    def project(self, shape: ArrayLike) -> NDArray[np.float64]:
        """Mode weights of a shape already in the model frame (least squares)."""
        x = np.asarray(shape, dtype=np.float64)
        if x.shape != self.mean.shape:
            raise ValueError(f"shape must have shape {self.mean.shape}, got {x.shape}")
        return self.modes.T @ (x - self.mean).reshape(-1)

    def fit_partial(
        self,
        points: ArrayLike,
        indices: ArrayLike,
        *,
        noise_variance: float = 1.0,
        scale: bool = True,
        max_iter: int = 50,
        tol: float = 1e-6,
    ) -> PartialFit:
        """Fit the model to observed vertices, alternating alignment and weights.

        Minimises ``|obs - T(mean_O + P_O v)|^2 / sigma^2 + sum_k v_k^2 / lambda_k`` over the
        similarity (or rigid) ``T`` and the weights ``v`` (a Gaussian prior: MAP estimate).

        Parameters
        ----------
        points : (m, 3) float, mm
            Observed positions of vertices ``indices`` (any frame).
        indices : (m,) int
            Which model vertices were observed.
        noise_variance : float, mm^2
            ``sigma^2``; larger trusts the prior (mean shape) more.
        scale : bool
            Similarity (True) or rigid alignment.

        Returns
        -------
        PartialFit
        """
        obs = np.asarray(points, dtype=np.float64)
        idx = np.asarray(indices)
        if idx.ndim != 1 or obs.shape != (len(idx), 3):
            raise ValueError(f"points {obs.shape} and indices {idx.shape} do not correspond")
        if len(idx) and (idx.min() < 0 or idx.max() >= self.n_vertices):
            raise ValueError(f"indices out of range [0, {self.n_vertices})")
        if noise_variance <= 0:
            raise ValueError(f"noise_variance must be positive, got {noise_variance}")
        rows = (3 * idx[:, None] + np.arange(3)).reshape(-1)
        P_o = self.modes[rows]
        mean_o = self.mean[idx]
        A = P_o.T @ P_o / noise_variance + np.diag(1.0 / self.variances)
        v = np.zeros(self.n_modes)
        T = np.eye(4)
        it = 0
        for it in range(1, max_iter + 1):
            model_o = mean_o + (P_o @ v).reshape(-1, 3)
            T = fit_transform(model_o, obs, scale=scale)
            obs_model = tf.apply(tf.invert(T), obs)
            v_new = np.linalg.solve(A, P_o.T @ (obs_model - mean_o).reshape(-1) / noise_variance)
            step = np.max(np.abs(v_new - v) / np.sqrt(self.variances)) if self.n_modes else 0.0
            v = v_new
            if step < tol:
                break
        model_o = mean_o + (P_o @ v).reshape(-1, 3)
        T = fit_transform(model_o, obs, scale=scale)
        verts = tf.apply(T, self.instance(v))
        rms = float(np.sqrt(np.mean(np.sum((verts[idx] - obs) ** 2, axis=1))))
        return PartialFit(weights=v, subject_from_model=T, vertices=verts, rms=rms, iterations=it)
