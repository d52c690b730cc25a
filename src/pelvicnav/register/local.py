"""Local refinement of one bone's 6 DoF: finite-difference Newton steps with a batched line search.

For tracking (a later frame starts within a few mm of the answer) a population search wastes most
of its candidates. Each iteration here evaluates one batch: the current point, ``+-h`` along each
of the 6 parameters (central differences: gradient and diagonal curvature) — 13 candidates — then
a second batch along the diagonal-Newton direction at a few step lengths. The best point seen is
kept; the difference step halves whenever an iteration does not improve, and the run stops when it
falls below ``min_step`` (converged) or after ``iterations``.

The result is a :class:`~pelvicnav.register.cmaes.CMAESResult` (``generations`` = iterations,
``final_std`` = the final difference step) so stages report it like a CMA-ES run.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.register.cmaes import CMAESResult

__all__ = ["refine_local"]

STEPS = (0.25, 0.5, 1.0, 2.0)  # line-search multiples of the Newton step


def _newton_direction(f0: float, fp: NDArray, fm: NDArray, h: float, max_step: float) -> NDArray:
    """Diagonal Newton step from central differences (gradient descent where not convex)."""
    g = (fp - fm) / (2 * h)
    c = (fp - 2 * f0 + fm) / h**2
    floor = np.abs(g) / max_step  # a non-convex or flat direction moves at most max_step
    return -g / np.maximum(c, np.maximum(floor, 1e-12))


def refine_local(
    objective: Callable[[NDArray], NDArray],
    x0: ArrayLike,
    *,
    step: float = 1.0,
    min_step: float = 0.05,
    iterations: int = 8,
    max_step: float = 3.0,
    tol_fun: float = 1e-4,
    bounds: tuple[ArrayLike, ArrayLike] | None = None,
) -> CMAESResult:
    """Minimise a batched objective ``(N, d) -> (N,)`` locally from ``x0``.

    Parameters
    ----------
    step : float
        Initial central-difference step (mm and degrees).
    min_step : float
        Stop (converged) when the step halves below this.
    iterations : int
    max_step : float
        Largest move per coordinate and iteration.
    tol_fun : float
        An iteration improving the objective by less than this halves the step.
    bounds : (lower, upper), optional
        Candidates are clipped to the box.
    """
    x = np.asarray(x0, dtype=np.float64).copy()
    d = len(x)
    lo, hi = (
        (np.full(d, -np.inf), np.full(d, np.inf)) if bounds is None else map(np.asarray, bounds)
    )
    h, evaluations, history = float(step), 0, []
    f = None
    for _ in range(iterations):
        E = np.eye(d) * h
        X = np.clip(np.concatenate([x[None], x + E, x - E]), lo, hi)
        F = np.asarray(objective(X), dtype=np.float64)
        evaluations += len(X)
        f0 = F[0] if f is None else min(F[0], f)
        s = _newton_direction(F[0], F[1 : d + 1], F[d + 1 :], h, max_step)
        Y = np.clip(x + np.outer(STEPS, s), lo, hi)
        G = np.asarray(objective(Y), dtype=np.float64)
        evaluations += len(Y)
        cand = np.concatenate([X, Y])
        vals = np.concatenate([F, G])
        k = int(np.argmin(vals))
        improved = vals[k] < f0 - tol_fun
        if vals[k] <= f0:
            x, f = cand[k].copy(), float(vals[k])
        else:
            f = float(f0)
        history.append(f)
        if not improved or k == 0:
            h /= 2
            if h < min_step:
                break
    converged = h < min_step
    return CMAESResult(x=x, f=float(f), evaluations=evaluations, generations=len(history),
                       converged=converged, stop={"local": "step" if converged else "iterations"},
                       history=np.asarray(history), final_std=h)  # fmt: skip
