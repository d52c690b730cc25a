"""CMA-ES through ask/tell (pycma), scoring a whole generation in one vectorised call.

Parameters are scaled so that one unit is 1 mm or 1 degree (``CMA_stds``), as the paper's sigma of
[4, 1] "mm and degrees" implies. Every run is seeded; a run that stops on its generation budget
rather than on a tolerance is reported as not converged, never as a success.

Reference: N. Hansen, "The CMA evolution strategy: a tutorial" (2016), arXiv:1604.00772; pycma.
"""

from __future__ import annotations

import functools
import importlib.abc
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["CMAESResult", "minimize_cmaes"]

_CONVERGED = ("tolfun", "tolfunhist", "tolx", "tolstagnation", "tolflatfitness")


class _WithoutExtras(importlib.abc.MetaPathFinder):
    """Refuses matplotlib and scipy.stats to pycma's own modules while pycma is imported.

    pycma imports both at import time for its interactive extras (``cma.plot``, ``cma.s``) and
    its surrogate models, none of which the registration uses, and handles their absence. They
    cost 1.0-2.2 s of every process's first registration (``import cma``: 1.5 s of import time,
    of it scipy.stats 0.9 s and matplotlib.pyplot 0.4 s), against 0.05 s without. Only imports
    made from a ``cma`` module are refused, so another thread importing either is unaffected, and
    both import normally once pycma is loaded.
    """

    EXTRAS = ("matplotlib", "scipy.stats")

    def find_spec(self, name, path=None, target=None):
        if not any(name == e or name.startswith(e + ".") for e in self.EXTRAS):
            return None
        frame = sys._getframe(1)
        while frame is not None:
            module = frame.f_globals.get("__name__", "")
            if module == "cma" or module.startswith("cma."):
                raise ImportError(f"{name} is not loaded for pycma (see pelvicnav.register.cmaes)")
            frame = frame.f_back
        return None


@functools.cache
def _pycma():
    """The ``cma`` module, imported without its interactive extras (:class:`_WithoutExtras`)."""
    if "cma" in sys.modules:
        return sys.modules["cma"]
    hook = _WithoutExtras()
    sys.meta_path.insert(0, hook)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "Could not import matplotlib.pyplot ..."
            import cma
    finally:
        sys.meta_path.remove(hook)
    return cma


@dataclass(frozen=True)
class CMAESResult:
    """Outcome of one CMA-ES run.

    Attributes
    ----------
    x : (d,) float64
        Best parameters seen.
    f : float
        Objective at ``x`` (minimised).
    evaluations, generations : int
    converged : bool
        True when a tolerance stopped the run, False when the budget did.
    stop : dict
        pycma's stop conditions.
    history : (generations,) float64
        Best objective of each generation.
    """

    x: NDArray[np.float64]
    f: float
    evaluations: int
    generations: int
    converged: bool
    stop: dict = field(default_factory=dict)
    history: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    final_std: float = np.inf


def minimize_cmaes(
    objective: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    x0: ArrayLike,
    *,
    sigma: float,
    population: int,
    seed: int,
    scales: ArrayLike | None = None,
    max_generations: int = 100,
    tol_fun: float = 1e-4,
    tol_x: float = 0.01,
    bounds: tuple[ArrayLike, ArrayLike] | None = None,
) -> CMAESResult:
    """Minimise a batched objective with CMA-ES.

    Parameters
    ----------
    objective : callable
        ``(population, d) -> (population,)`` objective values (lower is better).
    x0 : (d,) float
        Start.
    sigma : float
        Initial step in scaled units (1 = one mm or one degree with the default scales).
    population : int
    seed : int
    scales : (d,) float, optional
        Per-parameter standard deviation multipliers (pycma ``CMA_stds``).
    max_generations : int
    tol_fun, tol_x : float
        Stop when the objective's range over recent generations, or the step size (in scaled
        units), falls below these.
    bounds : (lower (d,), upper (d,)), optional
        Box constraints (pycma's boundary handling): the search range, e.g. the capture range.

    Raises
    ------
    ValueError
        Non-positive sigma or population, or an objective returning the wrong shape or NaN.
    """
    cma = _pycma()
    x0 = np.asarray(x0, dtype=np.float64)
    if sigma <= 0 or population < 2:
        raise ValueError(f"need sigma > 0 and population >= 2, got {sigma}, {population}")
    opts = _options(population, seed, max_generations, tol_fun, tol_x, bounds, scales)
    es = cma.CMAEvolutionStrategy(x0.tolist(), float(sigma), opts)
    history = []
    best_x, best_f = x0.copy(), np.inf
    evaluations = 0
    while not es.stop():
        X = np.asarray(es.ask(), dtype=np.float64)
        f = np.asarray(objective(X), dtype=np.float64)
        if f.shape != (len(X),) or not np.all(np.isfinite(f)):
            raise ValueError(f"objective must return {len(X)} finite values, got {f.shape}")
        es.tell(list(X), f.tolist())
        evaluations += len(X)
        k = int(np.argmin(f))
        history.append(float(f[k]))
        if f[k] < best_f:
            best_f, best_x = float(f[k]), X[k].copy()
    stop = dict(es.stop())
    converged = any(key in stop for key in _CONVERGED)
    return CMAESResult(
        x=best_x,
        f=best_f,
        evaluations=evaluations,
        generations=len(history),
        converged=converged,
        stop=stop,
        history=np.asarray(history),
        final_std=float(np.max(es.result.stds)),
    )


def _options(population: int, seed: int, max_generations: int, tol_fun: float, tol_x: float,
             bounds, scales) -> dict:  # fmt: skip
    """pycma's options for :func:`minimize_cmaes` (silent: no output, no log files)."""
    opts = {
        "popsize": int(population),
        "seed": int(seed) % (2**32 - 1) + 1,  # pycma treats seed 0 as "random"
        "maxiter": int(max_generations),
        "tolfun": tol_fun,
        "tolx": tol_x,
        "verbose": -9,
        "verb_log": 0,
        "verb_disp": 0,
    }
    if bounds is not None:
        opts["bounds"] = [list(np.asarray(b, dtype=np.float64)) for b in bounds]
    if scales is not None:
        opts["CMA_stds"] = list(np.asarray(scales, dtype=np.float64))
    return opts
