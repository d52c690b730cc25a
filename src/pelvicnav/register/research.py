"""The re-search: independent searches of the dislocated bone after the stage-2 sweeps.

Each re-search starts the bone again from its stage-1 pose with other seeds (odd-numbered ones
with the coarse-level rotation prior, see
:class:`~pelvicnav.register.settings.ResearchSettings`). The better fine-level score wins; when
the winner comes from another basin, every bone gets one more fine-level pass over the corrected
DRRs. Two answers far apart with nearly equal similarity mean the images do not pin the bone
down: a warning, and the registration is flagged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pelvicnav.io.views import ViewSet
from pelvicnav.metrics.errors import pose_disagreement
from pelvicnav.register.cmaes import CMAESResult
from pelvicnav.register.seeds import REPASS, RESEARCH, run_seed
from pelvicnav.register.stage2 import Stage2Problem, with_block

__all__ = ["ResearchOutcome", "research"]


@dataclass
class ResearchOutcome:
    """The parameters after the re-searches, their runs, disagreements and warnings."""

    y: NDArray[np.float64]
    runs: list[CMAESResult] = field(default_factory=list)
    disagreement: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def _search_from_stage1(
    problem: Stage2Problem, i: int, y: NDArray, r: int, seed: int
) -> tuple[NDArray, list[CMAESResult]]:
    """Bone ``i`` from zero parameters over every searched level (re-search ``r``)."""
    weight = problem.settings.research.coarse_rotation_prior * len(problem.levels[0].projections)
    x, runs = np.zeros(6), []
    by_search = problem.settings.research.fine == "cmaes"
    for lv in problem.searched:
        w = weight if r % 2 == 0 and lv != problem.fine else 0.0
        res = problem.search(i, with_block(y, i, x), lv, x, sweep=0,
                             seed=run_seed(seed, RESEARCH, r, lv, i), weight=w,
                             cmaes=by_search and lv == problem.fine)  # fmt: skip
        runs.append(res)
        x = res.x
    return x, runs


def _repass(problem: Stage2Problem, y: NDArray, r: int, seed: int, out: ResearchOutcome):
    """One more fine-level pass of every bone (sweep order) over the corrected DRRs."""
    if problem.is_gradient(problem.fine):
        y, res = problem.refine(problem.order, y, problem.fine)
        out.runs.append(res)
        return y
    for j in problem.order:
        res = problem.search(j, y, problem.fine, y[6 * j : 6 * j + 6], sweep=1,
                             seed=run_seed(seed, REPASS, r, j))  # fmt: skip
        out.runs.append(res)
        y = with_block(y, j, res.x)
    return y


def _compare(problem: Stage2Problem, i: int, y: NDArray, x_alt: NDArray, views: ViewSet):
    """(fine-level objective at ``y``, mm and degrees between bone ``i`` at ``y`` and ``x_alt``)."""
    sl = slice(6 * i, 6 * i + 6)
    f_now = float(problem.objective(i, y, problem.fine)(y[None, sl])[0])
    b = problem.blocks.bones[i]
    T_now, T_alt = (problem.blocks.bone_poses(i, v[None])[0] for v in (y[sl], x_alt))
    r = problem.renderer
    d_mm, d_deg = pose_disagreement(T_now, T_alt, r.points(b, problem.fine),
                                    r.centroid(b, problem.fine), views.projections,
                                    views.pixel_spacing)  # fmt: skip
    return f_now, d_mm, d_deg


def research(
    problem: Stage2Problem, y: NDArray, views: ViewSet, seed: int, count: int
) -> ResearchOutcome:
    """``count`` re-searches of the dislocated bone (of every bone without a plan) from ``y``.

    ``views`` carries the final geometry (a 9-DoF stage 1's refined ``P``) for the disagreement.
    With two or more views, a re-search that ends more than ``retry_mm`` away and loses earns one
    more (see :class:`~pelvicnav.register.settings.ResearchSettings`).
    """
    out = ResearchOutcome(y)
    bones = problem.blocks.bones
    check = [bones.index(problem.dislocated)] if problem.dislocated else range(len(bones))
    for i in check:
        far, r = 0, 0
        while r < count + min(far, 1):
            if _one_research(problem, i, r, seed, views, out) and len(views) > 1:
                far += 1
            r += 1
        if far > 1:  # the answer's basin found by one search only, missed by two others
            out.warnings.append(
                f"two re-searches of {bones[i]} ended more than "
                f"{problem.settings.research.retry_mm:g} mm away and scored worse: the answer "
                "was found once only"
            )
    return out


def _one_research(problem: Stage2Problem, i: int, r: int, seed: int, views: ViewSet,
                  out: ResearchOutcome) -> bool:  # fmt: skip
    """Re-search ``r`` of bone ``i``: the better answer into ``out``; True when it lost from
    more than ``retry_mm`` away."""
    rs = problem.settings.research
    bone = problem.blocks.bones[i]
    x_alt, runs = _search_from_stage1(problem, i, out.y, r, seed)
    out.runs.extend(runs)
    f_now, d_mm, d_deg = _compare(problem, i, out.y, x_alt, views)
    out.disagreement[bone] = max(out.disagreement.get(bone, 0.0), d_mm)
    apart = d_mm > rs.ambiguity[0] or d_deg > rs.ambiguity[1]
    f_alt = runs[-1].f
    if f_alt < f_now:
        out.y = with_block(out.y, i, x_alt)
        if apart:  # another basin: the other bones were fitted over a wrong DRR
            out.y = _repass(problem, out.y, r, seed, out)
    if len(views) == 1:  # judged where the bone projects, whatever the scores
        if d_mm > rs.single_view_flag_mm:
            out.warnings.append(
                f"the re-search of {bone} ended {d_mm:.1f} mm away at the detector: "
                "with one view its pose is not determined"
            )
    elif apart and abs(f_alt - f_now) < rs.ambiguity_score:  # both answers fit
        out.warnings.append(
            f"two searches for {bone} from the same start ended {d_mm:.1f} mm / "
            f"{d_deg:.1f} deg apart with similarities {-f_now:.3f} and {-f_alt:.3f} "
            f"(within {rs.ambiguity_score}): the images do not pin its pose down"
        )
    return f_alt >= f_now and d_mm > rs.retry_mm
