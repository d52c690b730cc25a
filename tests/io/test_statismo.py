"""statismo HDF5 reader."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from pelvicnav.io.statismo import read_statismo


def _write(path, nv=4, k=2, drop=None):
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        data = {
            "model/mean": rng.normal(size=3 * nv).astype(np.float32),
            "model/pcaBasis": np.linalg.qr(rng.normal(size=(3 * nv, k)))[0].astype(np.float32),
            "model/pcaVariance": np.array([2.0, 1.0][:k], dtype=np.float32),
            "representer/points": rng.normal(size=(3, nv)).astype(np.float32),
            "representer/cells": np.array([[0, 1], [1, 2], [2, 3]], dtype=np.uint32),
        }
        for key, value in data.items():
            if key != drop:
                f[key] = value
    return data


def test_reads_model(tmp_path):
    data = _write(tmp_path / "m.h5")
    m = read_statismo(tmp_path / "m.h5")
    np.testing.assert_allclose(m.mean.reshape(-1), data["model/mean"])
    assert m.basis.shape == (12, 2)
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [1, 2, 3]])
    assert m.reference.shape == (4, 3)


def test_bad_files(tmp_path):
    _write(tmp_path / "m.h5", drop="model/pcaBasis")
    with pytest.raises(ValueError, match=r"m\.h5: not a statismo model"):
        read_statismo(tmp_path / "m.h5")
    (tmp_path / "x.h5").write_text("not hdf5")
    with pytest.raises(ValueError, match=r"x\.h5: cannot read HDF5"):
        read_statismo(tmp_path / "x.h5")
