"""A last local search of the dislocated bone in gradient NCC (session 35).

Stage 2 leaves the dislocated bone at a local optimum of the joint L-BFGS refinement in gradient
NCC, or at the re-search's GO optimum refined from there. The finest level's landscape is rugged:
on the first ten cases of study seeds 569 and 577 (20 registrations) a CMA-ES of gradient NCC
from the answer, the other bones at their final poses, found a better-scoring pose 0.1-1.4 mm away
in 17, nearer the truth in most (the bone's centroid error, median 0.38 -> 0.20 mm), and took seed
569 case 33's hip, 4.29 mm off and not flagged, to 1.4 mm (``docs/registration.md``, session 35).
With the shipped budget (``RegistrationSettings.polish``: sigma 2, population 12, 25
generations, +-4 mm / 4 deg), on study seeds 557-577 and real-CT seed 17 (206 dislocated bones):
median 0.35 -> 0.28 mm, 569/33 4.29 -> 1.92 mm, no verdict changed. The box bounds what it can
do wrong: where a hip is half outside the views, gradient NCC's optimum can be the wrong one
(study seed 31 case 33), which is why the re-search reads GO.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
from numpy.typing import NDArray

from pelvicnav.drr.renderer import Renderer
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.register.cmaes import minimize_cmaes
from pelvicnav.register.pyramid import Level

__all__ = ["Polished", "polish"]


@dataclass(frozen=True)
class Polished:
    """The bone's pose after the search and what it gained.

    Attributes
    ----------
    pose : (4, 4) float64
        ``world_from_ct``: the better-scoring pose, or the answer when none scored better.
    lead : float
        Gradient NCC (summed over the views) at ``pose`` minus at the answer (>= 0).
    evaluations : int
    """

    pose: NDArray[np.float64]
    lead: float
    evaluations: int


def polish(
    level: Level,
    renderer: Renderer,
    poses: dict[str, NDArray],
    bone: str,
    settings: tuple[float, int, int, float],
    seed: int,
) -> Polished:
    """``bone`` searched by CMA-ES of gradient NCC at ``level`` from its pose in ``poses`` (the
    others fixed there); ``settings`` = (sigma mm and deg, population, generations, half-width
    of the box in mm and deg about the answer)."""
    sigma, population, generations, half = settings
    others = [b for b in renderer.bones if b != bone]
    background = 0.0
    if others:
        stack = np.stack([poses[b] for b in others])[None]
        background = renderer.render(level.index, others, stack, level.projections, level.shape)
    start = np.asarray(poses[bone], dtype=np.float64)
    centre = tf.apply(start, renderer.centroid(bone, level.index)[None])[0]
    objective = partial(_objective, level=level.scored_by("gncc"), renderer=renderer,
                        bone=bone, start=start, centre=centre, background=background)  # fmt: skip
    f0 = float(objective(np.zeros((1, 6)))[0])
    box = np.full(6, float(half))
    res = minimize_cmaes(objective, np.zeros(6), sigma=float(sigma), seed=seed,
                         population=int(population), max_generations=int(generations),
                         bounds=(-box, box))  # fmt: skip
    if not res.f < f0:
        return Polished(start, 0.0, res.evaluations)
    pose = pj.six_dof_pose(res.x, center=centre) @ start
    return Polished(pose, f0 - float(res.f), res.evaluations)


def _objective(X: NDArray, *, level: Level, renderer: Renderer, bone: str, start: NDArray,
               centre: NDArray, background) -> NDArray[np.float64]:  # fmt: skip
    """Minus ``level``'s score (gradient NCC summed over the views) of ``bone`` at parameters
    ``X`` (N, 6) about ``centre`` from ``start``, over the others' fixed DRRs."""
    T = pj.six_dof_pose(X, center=centre) @ start
    drrs = renderer.render(level.index, [bone], T[:, None], level.projections, level.shape)
    return -level.score(drrs + background)
