"""The re-search: independent searches of the dislocated bone after the stage-2 sweeps.

Each re-search starts the bone again from its stage-1 pose with other seeds (odd-numbered ones
with the coarse-level rotation prior, see
:class:`~pelvicnav.register.settings.ResearchSettings`). The better fine-level score wins; when
the winner comes from another basin, every bone gets one more fine-level pass over the corrected
DRRs, and the new answer must be found again by one more re-search (:class:`_Tally`). Two
answers far apart with nearly equal similarity mean the images do not pin the bone down: a
warning, and the registration is flagged. The joints judge the answers too
(:func:`_implausible`, ``ResearchSettings.joint_limits``): a kept answer whose joints no
dislocation gives is flagged, and an ambiguity whose other answer has such joints is a doubt
(``ResearchOutcome.doubts``) that a second attempt can settle.

With two or more views, the bone is then probed along each view's ray (from the source through
its centroid): a move along it keeps the bone's outline in that view, so a bone that the other
views show little of can sit in two places on it that score alike, and random re-searches from
the stage-1 pose find the other one by chance only (:func:`_ray_starts`; see
:class:`~pelvicnav.register.settings.ResearchSettings` ``ray_mm``). And it is turned by 20 degrees
either way about each axis through its centroid: a hip can also keep to a basin turned that far
from the truth (:func:`_turn_starts`, ``turn_deg``).

A bone still in question after all that (a warning or a doubt) is searched once more at the
finest level alone, from its stage-1 pose (:func:`fine_search`): the coarse level can keep every
search in a basin where the truth scores better at every level. A clear winner replaces the
answer; the questions stand. A bone not in question is probed along each view's ray once more,
at the finest level, and searched briefly from the optima found (:func:`fine_ray_check`): the
coarse levels can also agree on a wrong depth that the finest level does not prefer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.views import ViewSet
from pelvicnav.metrics.errors import pose_disagreement
from pelvicnav.register.cmaes import CMAESResult, minimize_cmaes
from pelvicnav.register.seeds import FINE, RAY, REPASS, RESEARCH, TURN, run_seed
from pelvicnav.register.stage2 import Stage2Problem, with_block

__all__ = ["ResearchOutcome", "fine_ray_check", "fine_search", "research"]

RAY_STEP_MM = 2.0  # the ray probe's step (the coarse level's samples are 3 mm apart)


@dataclass
class ResearchOutcome:
    """The parameters after the re-searches, their runs, disagreements and warnings."""

    y: NDArray[np.float64]
    runs: list[CMAESResult] = field(default_factory=list)
    disagreement: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    doubts: list[str] = field(default_factory=list)  # ambiguities whose other answer is implausible
    implausible: list[str] = field(default_factory=list)  # the kept answer's joints: no dislocation
    # bone -> every answer the searches gave it and every answer they replaced ((4, 4) each):
    # what a second opinion compares the kept one with (multibody._second_opinion)
    found: dict[str, list[NDArray[np.float64]]] = field(default_factory=dict)

    def note(self, problem: Stage2Problem, i: int, *xs: NDArray) -> None:
        """Record bone ``i``'s answers at the parameters ``xs`` (6 each) in ``found``."""
        poses = problem.blocks.bone_poses(i, np.stack(xs))
        self.found.setdefault(problem.blocks.bones[i], []).extend(poses)


def _search_from_stage1(
    problem: Stage2Problem, i: int, y: NDArray, r: int, seed: int
) -> tuple[NDArray, list[CMAESResult]]:
    """Bone ``i`` from zero parameters over every searched level (re-search ``r``)."""
    weight = problem.settings.research.coarse_rotation_prior * len(problem.levels[0].projections)
    weights = [weight if r % 2 == 0 and lv != problem.fine else 0.0 for lv in problem.searched]
    seeds = [run_seed(seed, RESEARCH, r, lv, i) for lv in problem.searched]
    return _search_from(problem, i, y, np.zeros(6), seeds, weights, sweep=0)


def _search_from(
    problem: Stage2Problem, i: int, y: NDArray, x: NDArray, seeds: list[int],
    weights: list[float], sweep: int,
) -> tuple[NDArray, list[CMAESResult]]:  # fmt: skip
    """Bone ``i`` from parameters ``x`` over every searched level, the others fixed at ``y``."""
    runs = []
    by_search = problem.settings.research.fine == "cmaes"
    for lv, run, w in zip(problem.searched, seeds, weights, strict=True):
        res = problem.search(i, with_block(y, i, x), lv, x, sweep=sweep, seed=run, weight=w,
                             cmaes=by_search and lv == problem.fine)  # fmt: skip
        runs.append(res)
        x = res.x
    return x, runs


def _ray_starts(problem: Stage2Problem, i: int, y: NDArray, views: ViewSet) -> list[NDArray]:
    """Bone ``i``'s parameters moved along each view's ray through its centroid to the best local
    optimum of the coarsest level's objective at least ``ray_min_mm`` away that scores within
    ``ray_margin`` of where the bone is (at most one per view), inside the bone's search box."""
    rs = problem.settings.research
    return _ray_optima(problem, i, y, views, problem.objective(i, y, problem.searched[0]),
                       (rs.ray_mm, RAY_STEP_MM, rs.ray_min_mm), rs.ray_margin)  # fmt: skip


def _ray_optima(problem: Stage2Problem, i: int, y: NDArray, views: ViewSet, objective,
                reach: tuple[float, float, float], margin: float) -> list[NDArray]:  # fmt: skip
    """Bone ``i``'s parameters moved along each view's ray (source to its centroid) to the best
    local optimum of ``objective`` (bone ``i``'s at one level, the others at ``y``), scanned up
    to ``reach[0]`` mm either way in steps of ``reach[1]`` mm, at least ``reach[2]`` mm away and
    within ``margin`` of where the bone is (at most one per view), inside its search box."""
    x = y[6 * i : 6 * i + 6]
    centre = problem.blocks.centres[i] + x[:3]  # the bone's centroid at x (world mm)
    steps = np.arange(-reach[0], reach[0] + 1e-9, reach[1])
    f0 = float(objective(x[None])[0])
    box = problem.box(i)
    starts = []
    for P in views.projections:
        ray = centre - pj.decompose_projection(P).source
        X = np.tile(x, (len(steps), 1))
        X[:, :3] += steps[:, None] * (ray / np.linalg.norm(ray))
        inside = np.all(np.abs(X) <= box, axis=1)
        f = np.full(len(steps), np.inf)
        f[inside] = objective(X[inside])
        best = [k for k in range(1, len(steps) - 1)
                if f[k] < f[k - 1] and f[k] < f[k + 1] and abs(steps[k]) >= reach[2]
                and f[k] <= f0 + margin]  # fmt: skip
        if best:
            starts.append(X[min(best, key=lambda k: f[k])])
    return starts


def _turn_starts(problem: Stage2Problem, i: int, y: NDArray) -> list[NDArray]:
    """Bone ``i``'s parameters turned by ``turn_deg`` either way about each world axis through its
    centroid, each turn shifted by the best of a 3 x 3 x 3 grid ``turn_shift_mm`` apart: the
    best of them inside the search box if it scores within ``ray_margin`` of where the bone is
    (coarsest level), else none."""
    rs = problem.settings.research
    objective = problem.objective(i, y, problem.searched[0])
    x = y[6 * i : 6 * i + 6]
    f0 = float(objective(x[None])[0])
    R = tf.matrix_from_rotvec(np.deg2rad(x[3:]))
    g = rs.turn_shift_mm * np.array([-1.0, 0.0, 1.0])
    shifts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    X = []
    for turn in np.concatenate([np.eye(3), -np.eye(3)]) * np.deg2rad(rs.turn_deg):
        # about the centroid (centre + t): the translation stays, the rotations compose
        r = np.rad2deg(tf.rotvec_from_matrix(tf.matrix_from_rotvec(turn) @ R))
        X.extend(np.concatenate([x[:3] + s, r]) for s in shifts)
    X = np.array(X)
    X = X[np.all(np.abs(X) <= problem.box(i), axis=1)]
    if not len(X):
        return []
    f = objective(X)
    k = int(np.argmin(f))
    return [X[k]] if f[k] <= f0 + rs.ray_margin else []


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


def _images(problem: Stage2Problem, i: int, y: NDArray, x_alt: NDArray, f_now: float,
            f_alt: float) -> tuple[float, float]:  # fmt: skip
    """The fine-level objective of bone ``i`` at ``y`` and at ``x_alt`` on the images alone
    (without the joint-aware prior): what the flag judges. Without a prior, the objective's own
    ``f_now`` and ``f_alt``."""
    if problem.prior is None or not problem.prior.active:
        return f_now, f_alt
    sl = slice(6 * i, 6 * i + 6)
    f = problem.objective(i, y, problem.fine, prior=False)(np.stack([y[sl], x_alt]))
    return float(f[0]), float(f[1])


def _joints(problem: Stage2Problem, i: int, y: NDArray, X: NDArray):
    """(inside fraction (N,), gap opening past the CT's (N,) mm) of bone ``i`` at each of the
    parameters ``X`` (N, 6), the others at ``y`` (:meth:`~pelvicnav.register.prior.JointPrior.
    measure`); None without the check (``joint_limits`` None, or no joint samples)."""
    prior = problem.prior
    if problem.settings.research.joint_limits is None or prior is None or not prior.fields:
        return None
    if prior.bone != problem.blocks.bones[i]:
        return None
    current = problem.blocks.poses(y[None])[0]
    others = {b: current[j] for j, b in enumerate(problem.blocks.bones) if j != i}
    return prior.measure(problem.blocks.bone_poses(i, X), others)


def _implausible(problem: Stage2Problem, i: int, y: NDArray, X: NDArray) -> NDArray[np.bool_]:
    """(N,) whether bone ``i`` at each of the parameters ``X`` (N, 6), the others at ``y``, has
    joints no dislocation gives: more than ``joint_limits[0]`` of its joint samples inside
    another bone, or the gap opened more than ``joint_limits[1]`` mm past the CT's (see
    :class:`~pelvicnav.register.settings.ResearchSettings`). All False without the check."""
    measured = _joints(problem, i, y, X)
    if measured is None:
        return np.zeros(len(X), dtype=bool)
    lim = problem.settings.research.joint_limits
    return (measured[0] > lim[0]) | (measured[1] > lim[1])


def _joint_warning(problem: Stage2Problem, i: int, y: NDArray) -> str | None:
    """A warning when bone ``i``'s answer at ``y`` has implausible joints (:func:`_implausible`)."""
    x = y[6 * i : 6 * i + 6][None]
    if not _implausible(problem, i, y, x)[0]:
        return None
    inside, opening = _joints(problem, i, y, x)
    lim = problem.settings.research.joint_limits
    return (f"{problem.blocks.bones[i]} ends with {inside[0]:.0%} of its joint samples inside "
            f"another bone and its joint gap {opening[0]:.1f} mm wider than the CT's (limits "
            f"{lim[0]:.0%}, {lim[1]:g} mm): no dislocation puts it there")  # fmt: skip


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
        asked = len(out.warnings) + len(out.doubts)
        tally = _Tally()
        r = 0
        while tally.more(r, count):
            x_alt, runs = _search_from_stage1(problem, i, out.y, r, seed)
            verdict = _judge(problem, i, x_alt, runs, r, seed, views, out)
            if len(views) > 1:  # one view: judged by distance alone, in _judge
                tally.add(*verdict)
            r += 1
        once = tally.found_once(bones[i], problem.settings.research)
        if once and tally.contested == tally.far:  # every other answer plausible
            out.warnings.append(once)
        elif once:
            out.doubts.append(f"{once} (an implausible other answer among them)")
        if count and len(views) > 1:
            _probe_searches(problem, i, r, seed, views, out)
            if len(out.warnings) + len(out.doubts) > asked:  # in question
                fine_search(problem, i, r, seed, views, out)
            else:
                fine_ray_check(problem, i, r, seed, views, out)
        joints = _joint_warning(problem, i, out.y)
        if joints:
            out.warnings.append(joints)
            out.implausible.append(joints)
    return out


@dataclass
class _Tally:
    """The re-searches of one bone from its stage-1 pose, as they bear on its answer (several
    views): ``far`` searches ended more than ``retry_mm`` from it and lost (or won by less
    than ``confirm_margin``), ``contested`` of them with a plausible other answer. An answer
    that a re-search replaced by winning clearly from another basin is ``pending`` until a
    search ends near it: it too was found once, and the answer before it was a wrong basin
    (seed 3 case 15: the sweeps' hip 22.6 mm off, a re-search's 21.4 mm off and 18.8 mm from
    it, winning by 0.038; the truth 0.013 better than both, and the registration unflagged)."""

    far: int = 0
    contested: int = 0
    pending: bool = False
    switched: bool = False

    def add(self, far: bool, plausible: bool, switched: bool) -> None:
        if switched:  # a new answer, found once: what was said of the old one is moot
            self.far, self.contested, self.pending, self.switched = 1, 1, True, True
        elif far:
            self.far += 1
            self.contested += plausible
        else:
            self.pending = False  # found again

    def more(self, r: int, count: int) -> bool:
        """Whether to run re-search ``r`` of ``count``: one more for an answer in question, two
        at most."""
        if r < count + min(self.far, 1):
            return True
        return self.pending and self.far < 2 and r < count + 2

    def found_once(self, bone: str, rs) -> str | None:
        """The warning when the answer's basin was found by one search only, else None."""
        if self.far > 1 and not self.switched:
            return (f"two searches of {bone} ended more than {rs.retry_mm:g} mm from the answer "
                    f"and scored worse, or better by less than {rs.confirm_margin:g}: the "
                    "answer was found once only")  # fmt: skip
        if self.far > 1 or self.pending:
            return (f"a re-search of {bone} replaced the sweeps' answer from more than "
                    f"{rs.retry_mm:g} mm away, and no other search found the new answer again: "
                    "the answer was found once only")  # fmt: skip
        return None


def fine_search(problem: Stage2Problem, i: int, r: int, seed: int, views: ViewSet,
                out: ResearchOutcome) -> None:  # fmt: skip
    """Bone ``i``, whose re-searches left a question, searched at the finest level alone from its
    stage-1 pose (``ResearchSettings`` ``fine_population``, ``fine_generations``,
    ``fine_sigma``). An answer that beats the kept one by ``confirm_margin`` replaces it (every
    bone then gets one more fine-level pass), with a warning; the questions stand either way.

    The coarse levels can hold every search in a basin where the truth scores better at every
    level (seed 251 case 19: a hip 17.7 mm off, the truth 0.02 better; the fine-level search
    finds it). The questions stand because a fine-level winner can be wrong too: on seed
    239 case 33 two such searches (from the stage-1 pose and from the kept answer) agreed on a
    hip 7.2 mm / 13.8 deg off, 0.02 better than the kept one (32 mm off); withdrawing the
    questions on that agreement left it unflagged."""
    rs = problem.settings.research
    if rs.fine_population == 0:
        return
    box, objective = problem.box(i), problem.objective(i, out.y, problem.fine)
    f_now = float(objective(out.y[None, 6 * i : 6 * i + 6])[0])
    res = minimize_cmaes(objective, np.zeros(6), sigma=rs.fine_sigma,
                         population=rs.fine_population, seed=run_seed(seed, FINE, i),
                         max_generations=rs.fine_generations, bounds=(-box, box))  # fmt: skip
    out.runs.append(res)
    _fine_verdict(problem, i, r, seed, views, out, f_now, res, check=False)


def fine_ray_check(problem: Stage2Problem, i: int, r: int, seed: int, views: ViewSet,
                   out: ResearchOutcome) -> None:  # fmt: skip
    """Bone ``i``, which the re-searches did not question, probed along each view's ray at the
    finest level (``ResearchSettings`` ``fine_ray_mm``, ``fine_ray_step_mm``,
    ``fine_ray_min_mm``, ``fine_ray_margin``; :func:`_ray_optima`), and a short fine-level
    search (``fine_ray_search``) from each optimum found. A search that beats the kept answer by
    ``confirm_margin`` replaces it, with a warning; one that ends more than ``retry_mm`` away
    and scores better by less flags the registration without replacing the answer: the finest
    level and the coarser ones disagree.

    Seed 271 case 10: a hip 7.5 mm off, 7.4 mm along the AP view's ray, its sweeps and
    re-search agreeing at the detector; the truth 0.003 worse at the coarse level and 0.007
    better at the fine one. The probe's optimum 7 mm along that ray lay 0.8 mm from the truth
    (0.0008 worse than the answer, unrefined) and its search ended 0.3 mm from the truth,
    0.006 better. On 39 good registrations (seeds 271 and 277, cases 0-19) the optima found
    scored 0.014-0.08 worse, but one (0.008 worse; its search ended 1.0 mm away and worse).
    It replaces a 20 x 40 fine-level search from the stage-1 pose that found the same case:
    about 0.2-0.8 s against 2.7 s."""
    rs = problem.settings.research
    if rs.fine_ray_mm <= 0:
        return
    reach = (rs.fine_ray_mm, rs.fine_ray_step_mm, rs.fine_ray_min_mm)
    objective = problem.objective(i, out.y, problem.fine)  # the others' DRR rendered once
    starts = _ray_optima(problem, i, out.y, views, objective, reach, rs.fine_ray_margin)
    if not starts:
        return
    box = problem.box(i)
    f_now = float(objective(out.y[None, 6 * i : 6 * i + 6])[0])
    population, generations, sigma = rs.fine_ray_search
    runs = [minimize_cmaes(objective, x0, sigma=sigma, population=population,
                           seed=run_seed(seed, FINE, i, 1, k), max_generations=generations,
                           bounds=(-box, box))
            for k, x0 in enumerate(starts)]  # fmt: skip
    out.runs.extend(runs)
    _fine_verdict(problem, i, r, seed, views, out, f_now, min(runs, key=lambda res: res.f),
                  check=True)  # fmt: skip


def _fine_verdict(problem: Stage2Problem, i: int, r: int, seed: int, views: ViewSet,
                  out: ResearchOutcome, f_now: float, res: CMAESResult, *,
                  check: bool) -> None:  # fmt: skip
    """A fine-level search's answer ``res`` for bone ``i`` against the kept one (scoring
    ``f_now``): better by ``confirm_margin`` replaces it, with a warning; a ``check`` (of a bone
    not in question) that ends more than ``retry_mm`` away and is better by less, a warning."""
    out.note(problem, i, res.x)
    if res.f >= f_now:
        return
    rs = problem.settings.research
    _, d_mm, d_deg = _compare(problem, i, out.y, res.x, views)
    bone = problem.blocks.bones[i]
    if res.f > f_now - rs.confirm_margin:
        if check and d_mm > rs.retry_mm:
            out.disagreement[bone] = max(out.disagreement.get(bone, 0.0), d_mm)
            out.warnings.append(
                f"a fine-level search of {bone} ended {d_mm:.1f} mm / {d_deg:.1f} deg from the "
                f"answer, {f_now - res.f:.3f} better: the finest level and the coarser ones "
                "disagree on its pose"
            )
        return
    out.y = _repass(problem, with_block(out.y, i, res.x), r, seed, out)
    out.disagreement[bone] = max(out.disagreement.get(bone, 0.0), d_mm)
    out.warnings.append(f"a fine-level search of {bone} ended {d_mm:.1f} mm / {d_deg:.1f} deg "
                        f"from the re-searches' answer, {f_now - res.f:.3f} better: it replaced "
                        "it, and its pose stays in question")  # fmt: skip


def _probe_searches(problem: Stage2Problem, i: int, r: int, seed: int, views: ViewSet,
                    out: ResearchOutcome) -> None:  # fmt: skip
    """A search of bone ``i`` from each of its ray starts (:func:`_ray_starts`), then from its
    turn start (:func:`_turn_starts`), each judged as a re-search (numbered from ``r`` for its
    extra pass)."""
    rs = problem.settings.research
    rays = _ray_starts(problem, i, out.y, views) if rs.ray_mm > 0 else []
    for k, x0 in enumerate(rays):
        _probe_search(problem, i, x0, [RAY, k], r + k, seed, views, out)
    if rs.turn_deg > 0:
        for x0 in _turn_starts(problem, i, out.y):
            _probe_search(problem, i, x0, [TURN], r + len(rays), seed, views, out)


def _probe_search(problem: Stage2Problem, i: int, x0: NDArray, path: list[int], r: int,
                  seed: int, views: ViewSet, out: ResearchOutcome) -> None:  # fmt: skip
    """A search of bone ``i`` from ``x0`` (seeds under ``path``), judged as re-search ``r``."""
    seeds = [run_seed(seed, *path, lv, i) for lv in problem.searched]
    x_alt, runs = _search_from(problem, i, out.y, x0, seeds, [0.0] * len(seeds), sweep=1)
    _judge(problem, i, x_alt, runs, r, seed, views, out)


def _judge(problem: Stage2Problem, i: int, x_alt: NDArray, runs: list[CMAESResult], r: int,
           seed: int, views: ViewSet, out: ResearchOutcome) -> tuple[bool, bool]:  # fmt: skip
    """An alternative answer ``x_alt`` of bone ``i`` (found by ``runs``) against ``out``'s: the
    better into ``out`` (by the objective, the joint-aware prior included), with its warnings;
    returns (whether it ended more than ``retry_mm`` away and lost, or won by less than
    ``confirm_margin``: an answer that then needs confirming; whether the answer not kept is
    plausible, :func:`_implausible`; whether it ended that far away and won by the margin or
    more: a new answer from another basin, see :class:`_Tally`). An ambiguity whose other
    answer is implausible is a doubt (``out.doubts``), not a warning. The warnings and that
    test read the images alone: the prior chooses between answers the images leave open, it does not
    close the question (seed 127 case 22: two answers 19 mm apart within 0.006 on the images,
    0.023 apart with the prior; both wrong, the truth 0.017 better than either and never found)."""
    rs = problem.settings.research
    bone = problem.blocks.bones[i]
    out.runs.extend(runs)
    out.note(problem, i, out.y[6 * i : 6 * i + 6], x_alt)
    f_now, d_mm, d_deg = _compare(problem, i, out.y, x_alt, views)
    out.disagreement[bone] = max(out.disagreement.get(bone, 0.0), d_mm)
    apart = d_mm > rs.ambiguity[0] or d_deg > rs.ambiguity[1]
    f_alt = runs[-1].f
    g_now, g_alt = _images(problem, i, out.y, x_alt, f_now, f_alt)
    bad_now, bad_alt = _implausible(problem, i, out.y, np.stack([out.y[6 * i : 6 * i + 6], x_alt]))
    plausible = not (bad_now if f_alt < f_now else bad_alt)  # the answer not kept
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
    elif apart and abs(g_alt - g_now) < rs.ambiguity_score:  # both answers fit the images
        message = (
            f"two searches for {bone} from the same start ended {d_mm:.1f} mm / "
            f"{d_deg:.1f} deg apart with similarities {-g_now:.3f} and {-g_alt:.3f} "
            f"(within {rs.ambiguity_score}): the images do not pin its pose down"
        )
        if plausible:
            out.warnings.append(message)
        else:
            out.doubts.append(f"{message}; the other answer's joints are implausible")
    narrow = g_now - g_alt < rs.confirm_margin  # lost, or won by less than the margin
    far = d_mm > rs.retry_mm
    return narrow and far, plausible, far and not narrow
