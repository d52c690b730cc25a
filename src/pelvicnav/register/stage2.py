"""Stage 2 (Han et al. 2020, equation 12): the 6-DoF pose of every bone from the stage-1 pose.

Parameters are ``6 x L``: each bone's ``[t (mm), r (deg)]`` about its own centroid on top of its
stage-1 pose. Two ways to search them, coarse to fine over the pyramid:

* :func:`sweeps` (default) — block coordinates: each bone's 6 DoF in turn over the fixed DRR of
  the others (DRRs add, so a candidate renders one bone), the dislocated bone first;
* :func:`joint` — one CMA-ES over all ``6 x L`` parameters (the paper).

Each block search is CMA-ES or, where :meth:`Stage2Problem.is_local`, the local refinement of
:mod:`~pelvicnav.register.local` (``max_generations`` then caps its iterations).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from numpy.typing import NDArray

from pelvicnav.drr.renderer import Renderer
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.metrics.errors import pose_distance
from pelvicnav.register.cmaes import CMAESResult, minimize_cmaes
from pelvicnav.register.gradient import GradientProblem, refine_gradient, supports_gradient
from pelvicnav.register.local import refine_local
from pelvicnav.register.prior import JointPrior
from pelvicnav.register.pyramid import Level
from pelvicnav.register.seeds import JOINT, SWEEP, run_seed
from pelvicnav.register.settings import RegistrationSettings

__all__ = ["Blocks", "Stage2Problem", "joint", "rejoined", "sweeps"]


@dataclass(frozen=True, eq=False)
class Blocks:
    """Every bone's 6 parameters about its centre (world mm) on top of its base pose.

    Attributes
    ----------
    bones : tuple of str
    base : (L, 4, 4) ``world_from_ct`` at zero parameters (the stage-1 poses)
    centres : (L, 3) world mm (each bone's centroid at its base pose)
    """

    bones: tuple[str, ...]
    base: NDArray[np.float64]
    centres: NDArray[np.float64]

    @classmethod
    def at(cls, poses: dict[str, NDArray], renderer: Renderer) -> Blocks:
        """Blocks about the bones' ``poses`` (renderer order)."""
        bones = renderer.bones
        base = np.stack([poses[b] for b in bones])
        centres = np.stack([tf.apply(base[i], renderer.centroid(b)[None])[0]
                            for i, b in enumerate(bones)])  # fmt: skip
        return cls(bones, base, centres)

    def bone_poses(self, i: int, X: NDArray) -> NDArray[np.float64]:
        """Bone ``i`` at its parameters ``X`` (N, 6) -> (N, 4, 4)."""
        return pj.six_dof_pose(X, center=self.centres[i]) @ self.base[i]

    def poses(self, Y: NDArray) -> NDArray[np.float64]:
        """Every bone at ``Y`` (N, 6 L) -> (N, L, 4, 4)."""
        return np.stack([self.bone_poses(i, Y[:, 6 * i : 6 * i + 6])
                         for i in range(len(self.bones))], axis=1)  # fmt: skip

    def as_dict(self, y: NDArray) -> dict[str, NDArray[np.float64]]:
        final = self.poses(y[None])[0]
        return {b: final[i] for i, b in enumerate(self.bones)}


def with_block(y: NDArray, i: int, x: NDArray) -> NDArray[np.float64]:
    """``y`` with bone ``i``'s 6 parameters replaced by ``x`` (a copy)."""
    out = y.copy()
    out[6 * i : 6 * i + 6] = x
    return out


def _block_objective(
    X: NDArray, *, problem: Stage2Problem, i: int, level: Level, background, weight: float,
    others: dict | None,
) -> NDArray[np.float64]:  # fmt: skip
    T = problem.blocks.bone_poses(i, X)
    bone = problem.blocks.bones[i]
    drrs = problem.renderer.render(level.index, [bone], T[:, None], level.projections, level.shape)
    f = weight * np.sum(X[:, 3:] ** 2, axis=1) - level.score(drrs + background)
    if others is not None:  # the joint-aware prior: no interpenetration
        f = f + problem.prior.penalty(T, others, len(level.projections))
    return f


def _joint_objective(X: NDArray, *, problem: Stage2Problem, level: Level) -> NDArray[np.float64]:
    drrs = problem.renderer.render(level.index, problem.blocks.bones, problem.blocks.poses(X),
                                   level.projections, level.shape)  # fmt: skip
    return -level.score(drrs)


@dataclass(frozen=True, eq=False)
class Stage2Problem:
    """What every stage-2 search shares: the blocks, renderer, levels, settings and the plan.

    Attributes
    ----------
    blocks : Blocks
    renderer : Renderer
    levels : list of Level
    settings : RegistrationSettings
    dislocated : str or None
        The plan's dislocated bone: the full search box and first in every sweep; the others get
        ``stage2.range_attached``.
    prior : JointPrior or None
        Added to the objective of its bone (:mod:`pelvicnav.register.prior`).
    """

    blocks: Blocks
    renderer: Renderer
    levels: list[Level]
    settings: RegistrationSettings
    dislocated: str | None = None
    prior: JointPrior | None = None

    @property
    def searched(self) -> list[int]:
        """Levels with a stage-2 generation budget."""
        return [lv.index for lv in self.levels if self.settings.stage2.max_generations[lv.index]]

    @property
    def fine(self) -> int:
        s = self.searched
        return s[-1] if s else 0

    def is_gradient(self, level: int) -> bool:
        """Whether ``level`` is refined by gradient (``mode="gradient"``: every level;
        ``fine="gradient"``: the finest searched level; with a renderer that has an adjoint)
        instead of searched."""
        s2 = self.settings.stage2
        chosen = s2.mode == "gradient" or (s2.fine == "gradient" and level == self.fine)
        return chosen and supports_gradient(self.renderer)

    def refine(self, free: list[int], y: NDArray, level: int) -> tuple[NDArray, CMAESResult]:
        """The ``free`` bones refined jointly by gradient at ``level`` from ``y``; the run's
        ``f`` is the level's own objective (its metric, as a search's would be)."""
        s2 = self.settings.stage2
        gp = GradientProblem(self.renderer, self.levels[level], self.blocks.base,
                             self.blocks.centres, y, tuple(free))  # fmt: skip
        box = np.concatenate([self.box(i) for i in free])
        tol = s2.gradient_tol * (1.0 if level == self.fine else 10.0)
        res = refine_gradient(gp, bounds=(-box, box), iterations=s2.gradient_iterations, tol=tol)
        y = gp.full(res.x)
        i = free[0]
        f = float(self.objective(i, y, level)(y[None, 6 * i : 6 * i + 6])[0])
        return y, replace(res, f=f)

    @property
    def attached_by_gradient(self) -> bool:
        """Sweeps search the plan's dislocated bone only, then refine all by gradient."""
        return (self.settings.stage2.attached == "gradient" and self.dislocated is not None
                and supports_gradient(self.renderer))  # fmt: skip

    @property
    def final_runs(self) -> int:
        """How many of the last runs produced the estimate (one per bone of the last sweep)."""
        if self.settings.stage2.mode == "joint" or self.is_gradient(self.fine):
            return 1
        return 2 if self.attached_by_gradient else len(self.blocks.bones)

    def is_local(self, level: int) -> bool:
        """Whether ``level`` searches by local refinement (``mode="local"``: every level;
        ``fine="local"``: the finest searched level) instead of CMA-ES."""
        s2 = self.settings.stage2
        return s2.mode == "local" or (s2.fine == "local" and level == self.fine)

    @property
    def order(self) -> list[int]:
        """Sweep order: the dislocated bone first."""
        return sorted(range(len(self.blocks.bones)),
                      key=lambda j: self.blocks.bones[j] != self.dislocated)  # fmt: skip

    def objective(self, i: int, y: NDArray, level: int, weight: float = 0.0,
                  prior: bool = True):  # fmt: skip
        """Bone ``i``'s 6-DoF objective at ``level`` over the others' fixed DRR at ``y``, with
        ``weight x |r|^2`` added (a rotation prior) and, unless not ``prior``, the joint-aware
        prior where it is this bone's."""
        lv = self.levels[level]
        others = [j for j in range(len(self.blocks.bones)) if j != i]
        background = 0.0
        current = self.blocks.poses(y[None])
        if others:
            names = [self.blocks.bones[j] for j in others]
            background = self.renderer.render(lv.index, names, current[:, others],
                                              lv.projections, lv.shape)  # fmt: skip
        poses = None
        mine = self.prior is not None and self.prior.bone == self.blocks.bones[i]
        if prior and mine and self.prior.active:
            poses = {self.blocks.bones[j]: current[0, j] for j in others}
        return partial(_block_objective, problem=self, i=i, level=lv, background=background,
                       weight=weight, others=poses)  # fmt: skip

    def box(self, i: int) -> NDArray[np.float64]:
        s2 = self.settings.stage2
        held = self.dislocated is not None and self.blocks.bones[i] != self.dislocated
        t, r = s2.range_attached if held else s2.search_range
        return np.array([t] * 3 + [r] * 3)

    def search(
        self, i: int, y: NDArray, level: int, x0: NDArray, *, sweep: int, seed: int,
        weight: float = 0.0, cmaes: bool = False,
    ) -> CMAESResult:  # fmt: skip
        """One bone's 6 DoF at ``level`` over the fixed DRR of the others (at ``y``): CMA-ES, or
        the gradient or local refinement where :meth:`is_gradient` or :meth:`is_local` (unless
        ``cmaes``); sigma (the first difference step) is divided by ``1 + sweep``."""
        box = self.box(i)
        if self.is_gradient(level) and not cmaes:
            y, res = self.refine([i], with_block(y, i, x0), level)
            return replace(res, x=y[6 * i : 6 * i + 6])
        if self.is_local(level) and not cmaes:
            return refine_local(self.objective(i, y, level, weight), x0,
                                step=self.settings.pyramid.sigmas[level] / (1 + sweep),
                                iterations=self.settings.stage2.max_generations[level],
                                bounds=(-box, box))  # fmt: skip
        return minimize_cmaes(
            self.objective(i, y, level, weight),
            x0,
            sigma=self.settings.pyramid.sigmas[level] / (1 + sweep),
            population=self.settings.stage2.populations[level],
            seed=seed,
            max_generations=self.settings.stage2.max_generations[level],
            bounds=(-box, box),
        )


ProgressFn = Callable[[str, int, int], None] | None


def sweeps(
    problem: Stage2Problem, y: NDArray, seed: int, progress: ProgressFn = None
) -> tuple[NDArray, list[CMAESResult]]:
    """Block coordinates over every searched level; returns the parameters and every run.

    At a gradient level every bone is refined at once (one run). Elsewhere each sweep searches
    the bones in turn; with ``attached="gradient"`` and a plan, only the dislocated bone is
    searched and then every bone is refined at once by gradient (the attached bones moved with
    the pelvis in stage 1 and are within a few mm).
    """
    runs = []
    for lv in problem.searched:
        if problem.is_gradient(lv):  # every bone at once, one run
            y, res = problem.refine(problem.order, y, lv)
            runs.append(res)
        else:
            for sweep in range(problem.settings.stage2.sweeps):
                y = _sweep(problem, y, lv, sweep, seed, runs)
        if progress:
            progress("stage 2", lv + 1, len(problem.levels))
    return y, runs


def _sweep(problem: Stage2Problem, y: NDArray, lv: int, sweep: int, seed: int, runs: list):
    """One sweep at level ``lv``; appends its runs."""
    searched = problem.order
    if problem.attached_by_gradient:
        searched = [problem.blocks.bones.index(problem.dislocated)]
    for i in searched:
        res = problem.search(i, y, lv, y[6 * i : 6 * i + 6], sweep=sweep,
                             seed=run_seed(seed, SWEEP, lv, sweep, i))  # fmt: skip
        runs.append(res)
        y = with_block(y, i, res.x)
    if problem.attached_by_gradient:
        y, res = problem.refine(problem.order, y, lv)
        runs.append(res)
    return y


def rejoined(problem: Stage2Problem, y: NDArray) -> tuple[NDArray, CMAESResult | None]:
    """The intact joints tried at the finest level: with a plan, where a bone it does not name
    ended further than ``stage2.rejoin`` (mm at its centroid, degrees) from another's pose (in
    the CT's frame the bones it does not name move as one: their joints are intact), every such
    bone is put at each of the others' poses in turn, all bones are refined from there by
    gradient, and the best of these and ``y`` by the level's similarity goes on.

    The images decide: a rejoined start that scores worse is dropped. On seed 229 cases 14 and
    20 the coarse level had pulled the intact hip 3 mm / 4.6 deg off, a basin the fine level's
    refinement could not leave, and the hip at the sacrum's pose scored better there (0.921
    against 0.916, 0.964 against 0.961). Returns the parameters and the refinement that gave
    them (None: ``y`` stands).
    """
    lim, fine = problem.settings.stage2.rejoin, problem.fine
    held = [i for i, b in enumerate(problem.blocks.bones) if b != problem.dislocated]
    if lim is None or problem.dislocated is None or len(held) < 2 or not problem.is_gradient(fine):
        return y, None
    T = problem.blocks.poses(y[None])[0]
    level = problem.levels[fine]
    score = partial(_joint_objective, problem=problem, level=level)
    best, f_best, chosen = y, float(score(y[None])[0]), None
    for k in held:
        moved = [i for i in held if i != k and np.any(_apart(problem, i, T[i], T[k]) > lim)]
        if not moved:
            continue
        c = y.copy()
        for i in moved:
            box = problem.box(i)
            x = pj.six_dof_params(T[k] @ tf.invert(problem.blocks.base[i]),
                                  center=problem.blocks.centres[i])  # fmt: skip
            c[6 * i : 6 * i + 6] = np.clip(x, -box, box)
        c, res = problem.refine(problem.order, c, fine)
        f = float(score(c[None])[0])
        if f < f_best:
            best, f_best, chosen = c, f, res
    return best, chosen


def _apart(problem: Stage2Problem, i: int, T_a: NDArray, T_b: NDArray) -> NDArray[np.float64]:
    """Bone ``i`` at ``T_a`` and ``T_b``: (mm at its CT centroid, degrees) apart."""
    return np.array(pose_distance(T_a, T_b, problem.renderer.centroid(problem.blocks.bones[i])))


def joint(
    problem: Stage2Problem, y: NDArray, seed: int, progress: ProgressFn = None
) -> tuple[NDArray, list[CMAESResult]]:
    """One CMA-ES over all ``6 x L`` parameters per searched level (the paper's stage 2)."""
    s2 = problem.settings.stage2
    t, r = s2.search_range
    box = np.tile([t] * 3 + [r] * 3, len(problem.blocks.bones))
    runs = []
    for lv in problem.searched:
        res = minimize_cmaes(
            partial(_joint_objective, problem=problem, level=problem.levels[lv]),
            y,
            sigma=problem.settings.pyramid.sigmas[lv],
            population=s2.populations[lv],
            seed=run_seed(seed, JOINT, lv),
            max_generations=s2.max_generations[lv],
            bounds=(-box, box),
        )
        runs.append(res)
        y = res.x
        if progress:
            progress("stage 2", lv + 1, len(problem.levels))
    return y, runs
