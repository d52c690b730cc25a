"""Read statismo shape models (HDF5), as shipped in the Han atlas's ``SSM/`` folder.

Layout read: ``model/mean`` (3 n_vertices,), ``model/pcaBasis`` (3 n_vertices, n_modes),
``model/pcaVariance`` (n_modes,), ``representer/points`` (3, n_vertices), ``representer/cells``
(3, n_faces). Reference: M. Luthi et al., "Statismo - a framework for PCA based statistical
models", Insight Journal (2012).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["StatismoModel", "read_statismo"]


@dataclass(frozen=True)
class StatismoModel:
    """Arrays of a statismo model.

    Attributes
    ----------
    mean : (n_vertices, 3) float64
    basis : (3 n_vertices, n_modes) float64
        Orthonormal principal directions (vertices flattened x0 y0 z0 x1 ...).
    variances : (n_modes,) float64
    faces : (n_faces, 3) int64
    reference : (n_vertices, 3) float64
        The representer's reference mesh.
    """

    mean: NDArray[np.float64]
    basis: NDArray[np.float64]
    variances: NDArray[np.float64]
    faces: NDArray[np.int64]
    reference: NDArray[np.float64]


def read_statismo(path: str | os.PathLike) -> StatismoModel:
    """Read a statismo ``.h5`` model.

    Raises
    ------
    ValueError
        Missing datasets or inconsistent sizes, naming the file.
    """
    import h5py

    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            try:
                mean = np.asarray(f["model/mean"], dtype=np.float64)
                basis = np.asarray(f["model/pcaBasis"], dtype=np.float64)
                variances = np.asarray(f["model/pcaVariance"], dtype=np.float64)
                points = np.asarray(f["representer/points"], dtype=np.float64)
                cells = np.asarray(f["representer/cells"], dtype=np.int64)
            except KeyError as err:
                raise ValueError(f"{path}: not a statismo model ({err})") from None
    except OSError as err:
        raise ValueError(f"{path}: cannot read HDF5 ({err})") from None
    nv = mean.size // 3
    if mean.size % 3 or basis.shape[0] != mean.size or basis.shape[1] != variances.size:
        raise ValueError(
            f"{path}: inconsistent model sizes: mean {mean.shape}, basis {basis.shape}, "
            f"variances {variances.shape}"
        )
    if points.shape != (3, nv) or cells.ndim != 2 or cells.shape[0] != 3:
        raise ValueError(f"{path}: representer points {points.shape} / cells {cells.shape} invalid")
    return StatismoModel(
        mean=mean.reshape(nv, 3),
        basis=basis,
        variances=variances,
        faces=cells.T.copy(),
        reference=points.T.copy(),
    )
