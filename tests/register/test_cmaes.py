"""CMA-ES driver: finds known minima, is reproducible, reports non-convergence."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.register.cmaes import minimize_cmaes


def _quadratic(X):
    target = np.array([3.0, -2.0, 1.0, 0.5, -4.0, 2.0])
    return np.sum(((X - target) * [1, 1, 1, 2, 2, 2]) ** 2, axis=1)


def test_finds_a_known_minimum():
    res = minimize_cmaes(_quadratic, np.zeros(6), sigma=4.0, population=20, seed=1)
    np.testing.assert_allclose(res.x, [3.0, -2.0, 1.0, 0.5, -4.0, 2.0], atol=0.05)
    assert res.converged
    assert res.evaluations == 20 * res.generations
    assert res.history[-1] <= res.history[0]


def test_reproducible_from_the_seed():
    a = minimize_cmaes(
        _quadratic, np.zeros(6), sigma=4.0, population=12, seed=7, max_generations=15
    )
    b = minimize_cmaes(
        _quadratic, np.zeros(6), sigma=4.0, population=12, seed=7, max_generations=15
    )
    np.testing.assert_array_equal(a.x, b.x)


def test_budget_exhaustion_is_not_convergence():
    res = minimize_cmaes(
        _quadratic, np.zeros(6), sigma=4.0, population=8, seed=0, max_generations=3
    )
    assert not res.converged
    assert "maxiter" in res.stop


def test_bad_objective():
    with pytest.raises(ValueError, match="finite values"):
        minimize_cmaes(
            lambda X: np.full(len(X), np.nan), np.zeros(2), sigma=1, population=4, seed=0
        )
    with pytest.raises(ValueError, match="sigma > 0"):
        minimize_cmaes(_quadratic, np.zeros(6), sigma=0, population=4, seed=0)


def test_pycma_loads_without_its_interactive_extras():
    """A fresh process: the registration's CMA-ES runs without pycma pulling in matplotlib or
    scipy.stats (1-2 s of import), and both still import normally afterwards."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from pelvicnav.register.cmaes import minimize_cmaes\n"
        "import numpy as np\n"
        "r = minimize_cmaes(lambda X: (X ** 2).sum(axis=1), np.ones(3), sigma=1.0,"
        " population=8, seed=1)\n"
        "print(r.f < 1e-3, 'matplotlib' in sys.modules, 'scipy.stats' in sys.modules)\n"
        "import scipy.stats, matplotlib.pyplot\n"
        "print('later', 'scipy.stats' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()  # fmt: skip
    assert out == ["True", "False", "False", "later", "True"]
