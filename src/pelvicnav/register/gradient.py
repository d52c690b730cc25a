"""Local refinement of every bone's 6 DoF at once by quasi-Newton steps on an exact gradient.

For a later frame (a few mm from the last one) and for the last level of a first registration, a
population search spends thousands of DRRs on a basin it is already in. Here the objective is
gradient NCC summed over the views of one DRR of all bones, and its gradient with respect to
every bone's parameters comes from one adjoint pass
(:func:`~pelvicnav.drr.splat.splat_pullback`): the similarity's derivative on the image,
carried back through the splat to a world force and torque on each bone, then through
:func:`~pelvicnav.geometry.projection.six_dof_pose`'s rotation (its left Jacobian). One
evaluation with its gradient costs about two DRRs, whatever the number of bones, so L-BFGS-B
(scipy) refines all ``6 x L`` parameters jointly in tens of evaluations instead of thousands.

Gradient NCC rather than GO: GO thresholds at medians and has a cusp at alignment, so it has no
useful derivative; gradient NCC is smooth. The registration's final similarity and flag stay GO.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
from numpy.typing import NDArray

from pelvicnav.drr.renderer import SplatRenderer
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.metrics.similarity import GradientNCC, gradient_ncc_gradients
from pelvicnav.register.cmaes import CMAESResult
from pelvicnav.register.pyramid import Level

__all__ = ["GradientProblem", "refine_gradient", "supports_gradient"]


def supports_gradient(renderer) -> bool:
    """Whether ``renderer`` has an adjoint (the splat renderer; ray casting has none)."""
    return isinstance(renderer, SplatRenderer)


def left_jacobian(r: NDArray) -> NDArray[np.float64]:
    """SO(3) left Jacobian of a rotation vector ``r`` (rad): ``d exp(r) = [J dr]x exp(r)``."""
    theta = float(np.linalg.norm(r))
    K = tf.skew(r)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * K
    return (np.eye(3) + (1 - np.cos(theta)) / theta**2 * K
            + (theta - np.sin(theta)) / theta**3 * (K @ K))  # fmt: skip


@dataclass(frozen=True, eq=False)
class GradientProblem:
    """Every bone's ``[t (mm), r (deg)]`` about its centre on top of its base pose, at one level;
    the ``free`` bones move, the others stay at their parameters in ``y``.

    Attributes
    ----------
    renderer : SplatRenderer
    level : Level
        Its ``images`` give the fixed radiographs; its own metric is not used (gradient NCC is).
    base : (L, 4, 4) ``world_from_ct`` at zero parameters, renderer order
    centres : (L, 3) world mm
    y : (6 L,) every bone's parameters (the free bones' are the start)
    free : indices of the bones that move
    """

    renderer: SplatRenderer
    level: Level
    base: NDArray[np.float64]
    centres: NDArray[np.float64]
    y: NDArray[np.float64]
    free: tuple[int, ...]

    def __post_init__(self) -> None:
        if not self.level.images:
            raise ValueError("the level carries no radiographs (build it with build_levels)")
        sims = tuple(GradientNCC(img) for img in self.level.images)
        object.__setattr__(self, "_sims", sims)
        object.__setattr__(self, "y", np.asarray(self.y, dtype=np.float64).copy())

    def full(self, x: NDArray) -> NDArray[np.float64]:
        """The free bones' parameters ``x`` (6 F,) inside every bone's ``y`` (6 L,)."""
        y = self.y.copy()
        for n, i in enumerate(self.free):
            y[6 * i : 6 * i + 6] = x[6 * n : 6 * n + 6]
        return y

    def start(self) -> NDArray[np.float64]:
        return np.concatenate([self.y[6 * i : 6 * i + 6] for i in self.free])

    def poses(self, y: NDArray) -> NDArray[np.float64]:
        """(6 L,) parameters -> (L, 4, 4) poses."""
        X = np.asarray(y, dtype=np.float64).reshape(-1, 6)
        return np.stack([pj.six_dof_pose(X[i], center=self.centres[i]) @ self.base[i]
                         for i in range(len(X))])  # fmt: skip

    def value_and_gradient(self, x: NDArray) -> tuple[float, NDArray[np.float64]]:
        """Minus gradient NCC summed over the views, and its gradient in ``x`` (6 F,)."""
        lv, r = self.level, self.renderer
        y = self.full(np.asarray(x, dtype=np.float64))
        T = self.poses(y)
        drrs = r.render(lv.index, r.bones, T[None], lv.projections, lv.shape)[0]
        values, grads = gradient_ncc_gradients(self._sims, drrs)
        bones = [r.bones[i] for i in self.free]
        wrench = r.pullback(lv.index, bones, T[list(self.free)], lv.projections, grads)
        return -float(values.sum()), -self._chain(y.reshape(-1, 6), wrench)

    def _chain(self, Y: NDArray, wrench: NDArray) -> NDArray[np.float64]:
        """World force/torque per free bone -> gradient in its (t mm, r deg) parameters."""
        out = np.empty((len(self.free), 6))
        for n, (i, (F, tau)) in enumerate(zip(self.free, wrench.reshape(-1, 2, 3), strict=True)):
            a = self.centres[i] + Y[i, :3]  # the rotation's fixed point after the translation
            out[n, :3] = F
            J = left_jacobian(np.deg2rad(Y[i, 3:]))
            out[n, 3:] = np.deg2rad(1.0) * J.T @ (tau - np.cross(a, F))
        return out.ravel()


def _recorded(x: NDArray, *, problem: GradientProblem, history: list) -> tuple[float, NDArray]:
    """The problem's value and gradient at ``x``, the value appended to ``history``."""
    f, g = problem.value_and_gradient(x)
    history.append(f)
    return f, g


def refine_gradient(
    problem: GradientProblem,
    *,
    bounds: tuple[NDArray, NDArray],
    iterations: int = 40,
    tol: float = 1e-7,
) -> CMAESResult:
    """L-BFGS-B of the free bones from their start within ``bounds`` (6 F,) each.

    The result reads like a CMA-ES run of the free bones' parameters (``generations`` =
    iterations, ``converged`` = stopped on its tolerance rather than the iteration cap; ``f`` is
    minus gradient NCC)."""
    from scipy.optimize import minimize

    history: list[float] = []
    fun = partial(_recorded, problem=problem, history=history)
    res = minimize(fun, problem.start(), jac=True, method="L-BFGS-B",
                   bounds=list(zip(*bounds, strict=True)),
                   options={"maxiter": int(iterations), "ftol": tol, "gtol": 1e-6,
                            "maxls": 10})  # fmt: skip
    converged = bool(res.success)
    return CMAESResult(x=np.asarray(res.x), f=float(res.fun), evaluations=int(res.nfev),
                       generations=int(res.nit), converged=converged,
                       stop={"lbfgs": str(res.message)}, history=np.asarray(history),
                       final_std=0.0 if converged else np.inf)  # fmt: skip
