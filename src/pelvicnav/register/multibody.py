"""Two-stage multi-body 3D-2D registration (Han et al. 2020, section 2.2, equations 9-12).

The orchestrator: check the inputs, build the pyramid (:mod:`~pelvicnav.register.pyramid`), run
stage 1 (:mod:`~pelvicnav.register.stage1`: the pelvis as one rigid body, 6 or 9 DoF; a lone run
probed in depth, :func:`_probed`), stage 2
(:mod:`~pelvicnav.register.stage2`: every bone's 6 DoF, sweeps or joint; then the intact joints
tried, :func:`~pelvicnav.register.stage2.rejoined`), the re-search of the dislocated bone
(:mod:`~pelvicnav.register.research`; a bone it leaves in question searched again at the finest
level alone), and judge the result. A weak answer's pelvis is searched again from where the
dislocated bone puts it (:func:`_anchored`).

DRRs come from a :class:`~pelvicnav.drr.renderer.Renderer`: splatted point models
(:func:`register_multibody` builds them from a CT and label map) or the ray-cast reference
(:func:`register` with a :class:`~pelvicnav.drr.renderer.RayCastRenderer`).

A stage whose final runs stopped on a tolerance, collapsed or plateaued is *converged*. The flag
judges the answer: a registration whose final stage hit a generation limit while improving, whose
final similarity is below ``min_similarity`` per view, whose re-search found an equally good other
answer, or (one view) whose re-search ended more than ``single_view_flag_mm`` away is flagged not
converged, never reported as a success; so is a rescued answer that kept the first attempt's
pelvis and scores barely better than it (:func:`_rescue`), and one whose dislocated bone has
joints no dislocation gives (closed through, or opened far past the CT's). An ambiguity whose
other answer has such joints is a doubt: it calls the rescue, and a second attempt that ends at
the same answer settles it (:func:`_confirmed`). Stage 1's own limit is a warning
only (stage 2 refines from its answer): with one view, 9 DoF, it was reached in every case and
flagged 8 good registrations of 12 (atlas, seed 7). A result flagged only because the
dislocated bone's answer is in question gets a second opinion at the end, which the poses do not
depend on (:func:`_second_opinion`, :mod:`~pelvicnav.register.opinion`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.drr.renderer import Renderer
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.views import ViewSet
from pelvicnav.metrics.errors import pose_disagreement
from pelvicnav.register.initial import about, initial_pose, initial_translation
from pelvicnav.register.opinion import second_opinion
from pelvicnav.register.polish import polish
from pelvicnav.register.prior import MEASURED_POINTS, joint_prior
from pelvicnav.register.pyramid import Level, build_levels, splat_renderer
from pelvicnav.register.research import research
from pelvicnav.register.result import MultiBodyResult, StageResult
from pelvicnav.register.seeds import ANCHOR, POLISH, PROBE, RESCUE, run_seed
from pelvicnav.register.settings import RegistrationSettings
from pelvicnav.register.stage1 import pelvis_bones, run_stage1, stage1_body
from pelvicnav.register.stage2 import Blocks, Stage2Problem, joint, rejoined, sweeps

__all__ = ["register", "register_multibody"]

ProgressFn = Callable[[str, int, int], None] | None

EDGE = 0.99  # a stage-2 parameter this close to its box's bound (fraction) is at the edge


def register_multibody(
    ct_hu: Volume,
    labels: ArrayLike,
    views: ViewSet,
    *,
    renderer: Renderer | None = None,
    **kwargs,
) -> MultiBodyResult:
    """Register the sacrum and both innominate bones of a CT to one or more radiographs.

    Parameters
    ----------
    ct_hu : Volume
        Preoperative CT (HU); each bone's ``ct`` frame is this volume's world frame.
    labels : (ni, nj, nk) int
        Label map (1 sacrum, 2 left, 3 right innominate) on the CT grid.
    views : ViewSet
    renderer : Renderer, optional
        Bone models of this CT (default: splatted point models per pyramid level,
        :func:`~pelvicnav.register.pyramid.splat_renderer`); build once, pass for every frame.
    **kwargs
        Of :func:`register`: ``init_poses``, ``seed``, ``settings``, ``progress``, ``dislocated``.

    Raises
    ------
    ValueError
        Label map and CT mismatch, a missing bone, and every error of :func:`register`.
    """
    if renderer is None:
        settings = kwargs.get("settings") or RegistrationSettings()
        renderer = splat_renderer(ct_hu, labels, settings.factors)
    return register(views, renderer, **kwargs)


def register(
    views: ViewSet,
    renderer: Renderer,
    *,
    init_poses: dict[str, ArrayLike] | None = None,
    seed: int = 0,
    settings: RegistrationSettings | None = None,
    progress: ProgressFn = None,
    dislocated: str | None = None,
) -> MultiBodyResult:
    """Register the renderer's bodies to the views: stage 1, stage 2, re-search, judgement.

    Parameters
    ----------
    views : ViewSet
    renderer : Renderer
        One model set per pyramid level of ``settings``.
    init_poses : dict bone -> (4, 4), optional
        Starting ``world_from_ct`` (default identity: the CT placed at its nominal pose).
    seed : int
        Every CMA-ES run's seed derives from it (:mod:`pelvicnav.register.seeds`).
    settings : RegistrationSettings, optional
    progress : callable(stage, level, levels), optional
    dislocated : str, optional
        The dislocated bone (from the plan): stage 1 then registers the other bones as one rigid
        body (a rigid fit of the whole pelvis can lock onto the dislocated bone instead: 1 of 20
        simulated cases), the dislocated bone gets the full stage-2 search box, goes first in
        each sweep and is the one re-searched.

    Raises
    ------
    ValueError
        ``dof=9`` with several views, an unknown bone, a non-rigid initial pose.
    """
    t_start = time.perf_counter()
    cfg = settings or RegistrationSettings()
    init = _check_inputs(views, renderer, cfg, init_poses, dislocated)
    levels = build_levels(views, renderer, cfg.pyramid)
    run = _Run(views, levels, renderer, cfg, seed, progress, dislocated)
    starts = [init]
    searching = any(cfg.stage1.max_generations)  # not tracking
    if cfg.stage1.initial_search_mm > 0 and searching:
        guess = _initial(levels[0], renderer, run.body(init), init, cfg.stage1)
        starts = [guess, init] if guess is not init else starts
    guessed = len(starts) > 1
    rescue = cfg.stage1.rescue_turn_deg > 0 and searching
    if guessed and rescue:  # a start far off: every start the rescue would try, tried now
        starts += _turned(run, init)
    seeds = [seed] + [run_seed(seed, RESCUE, k) for k in range(len(starts) - 1)]
    tried = _stage1_runs(run, starts, seeds)
    if searching and not guessed:
        tried += _probed(run, tried[0])
    start, s1 = _best(tried)
    attempt = _attempt(run, start, s1)
    # a tracked frame's stage 1 searches nothing: it starts where the last frame settled
    settled = not searching or _settled(run, (start, s1), tried)
    result = _judged(run, attempt, settled)
    if searching and (anchored := _anchored(run, (start, s1), attempt, result)) is not None:
        (start, s1), attempt, result, settled = anchored
    if not (result.converged or guessed or not rescue):
        result = _rescue(run, init, (start, s1), attempt, result, settled)
    result = _second_opinion(run, result)
    if searching:  # not a tracked frame
        result = _polished(run, result)
    # timed here, for the whole call: a probe or rescue may run after an answer is judged
    return replace(result, seconds=time.perf_counter() - t_start)


def _anchored(run: _Run, answer: tuple, first: _Attempt, result: MultiBodyResult) -> tuple | None:
    """``((start, stage-1 outcome), attempt, result, settled)`` from stage 1 run again where
    the dislocated bone puts the pelvis (``RegistrationSettings.anchored_probe``), when that
    run ends elsewhere than stage 1's ``answer`` (start, outcome), scores better, and the
    attempt from it ends with a higher final similarity than ``result``; else None. The run
    starts every bone at the dislocated bone's ``world_from_ct`` in the ``first`` attempt
    (their poses in the CT) with the depth probes' budget; it has settled when it leads
    ``answer`` by ``unsettled_lead`` (:func:`_leads`). The attempt's re-search answers join
    ``run.found`` whether it is kept or not, as the rescue's do."""
    cfg, bone = run.cfg, run.dislocated
    if not cfg.anchored_probe or bone is None or len(run.views) < 2 or cfg.stage1.dof != 6:
        return None
    if not _weak(run, first, result.similarity):
        return None
    start = dict.fromkeys(run.renderer.bones, first.poses[bone])
    probe = run_stage1(run.views, run.levels, run.renderer, run.body(start),
                       _probe_settings(cfg), run_seed(run.seed, ANCHOR))  # fmt: skip
    tried = (start, probe)
    if _f(probe) >= _f(answer[1]) or _agree(run, answer, tried):
        return None
    settled = _leads(run, tried, [answer])
    second = _attempt(run, start, probe)
    again = _judged(run, second, settled)
    if again.similarity <= result.similarity:
        return None
    mm, deg = _between(run, answer, tried)
    note = (f"stage 1 from where the {bone} puts the pelvis (their poses in the CT) found a "
            f"better answer {mm:.1f} mm / {deg:.1f} deg from the first one's pelvis (final "
            f"similarity {result.similarity:.3f} -> {again.similarity:.3f})")  # fmt: skip
    return tried, second, replace(again, warnings=(note, *again.warnings)), settled


def _weak(run: _Run, a: _Attempt, similarity: float) -> bool:
    """Whether attempt ``a``'s final GO ``similarity`` is below ``unsettled_similarity`` per view
    of what its DRRs can score, as :func:`_unsettled` asks of an unsettled stage 1."""
    bones = run.renderer.bones
    stack = np.stack([a.poses[b] for b in bones])[None]
    drrs = run.renderer.render(a.fine.index, bones, stack, a.fine.projections, a.fine.shape)
    metric, n = run.cfg.pyramid.metrics[a.fine.index], len(run.views)
    return _unsettled(False, metric, similarity, _attainable(metric, drrs[0], n), n, run.cfg)


@dataclass(frozen=True, eq=False)
class _Run:
    """What every attempt of one registration shares."""

    views: ViewSet
    levels: list[Level]
    renderer: Renderer
    cfg: RegistrationSettings
    seed: int
    progress: ProgressFn
    dislocated: str | None
    # bone -> every answer the re-searches of every attempt gave it or replaced ((4, 4) each)
    found: dict[str, list[NDArray[np.float64]]] = field(default_factory=dict)

    def body(self, init: dict):
        return stage1_body(self.renderer, self.cfg.stage1.body, init, self.dislocated)


@dataclass(frozen=True, eq=False)
class _Attempt:
    """Stages 1 and 2 from one start, before the judgement."""

    views: ViewSet  # with a 9-DoF stage 1's refined geometry
    fine: Level
    poses: dict[str, NDArray[np.float64]]
    stages: list[StageResult]
    warnings: list[str]  # stage 2's (the re-search's ambiguities)
    disagreement: dict[str, float]
    body: str
    doubts: list[str] = field(default_factory=list)  # ambiguities with an implausible other answer
    implausible: list[str] = field(default_factory=list)  # warnings: joints no answer can have
    faults: list[str] = field(default_factory=list)  # stage 2's: a pelvis stage 1 misplaced


def _attempt(run: _Run, init: dict, s1) -> _Attempt:
    """Stage 2 from a stage-1 answer started at ``init``."""
    views, levels, cfg = run.views, run.levels, run.cfg
    if s1.projections is not None:  # 9 DoF: later levels and the result use the refined geometry
        views = views.with_projections(s1.projections)
        levels = [lv.with_geometry(views.projections) for lv in levels]
    poses = {b: s1.delta @ init[b] for b in run.renderer.bones}  # they share the set-up error
    stages, warnings, disagreement, doubts, implausible, faults = [s1.result], [], {}, [], [], []
    if cfg.stage2.enabled:
        s2 = _stage2_recentred(run, views, levels, poses)
        poses, disagreement, warnings, doubts = s2.poses, s2.disagreement, s2.warnings, s2.doubts
        faults = s2.faults
        stages.append(s2.result)
        intact = _intact_warnings(run, poses, views, levels[-1])
        warnings, implausible = [*warnings, *intact], [*s2.implausible, *intact]
    return _Attempt(views, levels[-1], poses, stages, warnings, disagreement, run.body(init).name,
                    doubts, implausible, faults)  # fmt: skip


def _stage2_recentred(run: _Run, views: ViewSet, levels: list[Level], poses: dict):
    """Stage 2 from ``poses``, run again from its answer while a bone of the pelvis ends at the
    edge of its box (:func:`_edges`), up to ``Stage2Settings.recentre`` times; the last run's
    outcome (its stage result times that run only). Every run's other answers for the re-searched
    bone go to ``run.found``."""
    for _ in range(run.cfg.stage2.recentre + 1):
        s2 = _stage2(views, levels, run.renderer, poses, run.cfg, run.seed, run.progress,
                     run.dislocated)  # fmt: skip
        for b, found in s2.found.items():
            run.found.setdefault(b, []).extend(found)
        if not s2.faults:
            break
        poses = s2.poses
    return s2


def _intact_warnings(run: _Run, poses: dict, views: ViewSet, fine: Level) -> list[str]:
    """With a plan: each bone stage 1 moves with the pelvis that ended further than
    ``intact_limits`` from the pose of the pelvis's first bone. Their joints are intact, so in
    the CT's frame they move as one: the same ``world_from_ct`` (not the start's relative poses:
    a tracked frame starts from the previous frame's; see
    :class:`~pelvicnav.register.settings.RegistrationSettings`)."""
    limits, kept = run.cfg.intact_limits, _kept(run)
    if limits is None or run.dislocated is None or len(kept) < 2:
        return []
    first, out = kept[0], []
    for b in kept[1:]:
        mm, deg = _apart(run, views, fine, b, poses[first], poses[b])
        if mm > limits[0] or deg > limits[1]:
            out.append(f"{b} ended {mm:.1f} mm / {deg:.1f} deg from where the {first} puts it "
                       f"(its pose in the CT; limits {limits[0]:g} mm / {limits[1]:g} deg): the "
                       "intact joints moved, so the pelvis may be misplaced")  # fmt: skip
    return out


def _judged(run: _Run, a: _Attempt, settled: bool) -> MultiBodyResult:
    """The attempt judged (``settled``: see :func:`_settled`); its doubts flag it too, and its
    joints that no dislocation gives mark it ``implausible``."""
    result = _judge(a.views, a.fine, run.renderer, a.poses, a.stages, [*a.warnings, *a.doubts],
                    a.disagreement, run.cfg, a.body, settled, a.faults)  # fmt: skip
    return replace(result, implausible=tuple(a.implausible))


def _f(s1) -> float:
    """The stage-1 objective at its answer (lower is better)."""
    return s1.result.levels[-1].f


def _turned(run: _Run, init: dict) -> list[dict]:
    """``init`` turned by +-``rescue_turn_deg`` about the first view's detector axes (out of
    plane) through the stage-1 body's centre: where neither the first guess (in-plane turns
    only) nor one stage-1 box (+-10 deg) reaches."""
    body = run.body(init)
    centre = tf.apply(body.start, body.centre[None])[0]
    R = pj.decompose_projection(run.levels[0].projections[0]).carm_from_world
    a = run.cfg.stage1.rescue_turn_deg
    turns = [about(centre, axis, sign * a) for axis in R[:2] for sign in (1, -1)]
    return [{b: T @ P for b, P in init.items()} for T in turns]


def _stage1_runs(run: _Run, starts: list[dict], seeds: list[int]) -> list[tuple]:
    """``(start, stage-1 outcome)`` from each start (with its seed). When the first guess was
    taken, the starts are the guess, the start before it and that start turned out of plane: a
    guess can move a body turned out of plane further off (starts turned 30 deg were guessed
    50-170 mm off, and stage 1 settled in wrong optima that no flag caught: 46 and 29 mm off,
    unflagged); the best-scoring answer goes on."""
    return [(start, run_stage1(run.views, run.levels, run.renderer, run.body(start), run.cfg,
                               seed, run.progress if k == 0 else None))
            for k, (start, seed) in enumerate(zip(starts, seeds, strict=True))]  # fmt: skip


def _probed(run: _Run, lone: tuple) -> list[tuple]:
    """The lone stage-1 run ``lone`` (start, outcome) probed in depth (``Stage1Settings``
    ``probe_mm``): two short runs from its answer shifted either way along the views' mean beam
    direction. A probe that did not come back (its answer more than ``probe_mm`` / 2 from the
    lone run's) found another basin: a full stage-1 run from its answer is returned as another
    run ``(start, outcome)`` (from the better-scoring one when both stayed away); else none,
    and the lone run stands as it was. A short run ends 0.3-3.7 mm short of the answer it
    returns to (seed 193, 30 good registrations); seed 193 case 0's +20 mm probe stayed 21.6 mm
    away, 3 % worse than the lone run and not yet converged, and the full run from there ends
    at the truth, 18 % better."""
    s1 = run.cfg.stage1
    if s1.probe_mm <= 0 or s1.dof != 6 or len(run.views) < 2:
        return []
    start, first = lone
    short = _probe_settings(run.cfg)
    beam = _mean_beam(run.levels[0].projections)
    away = []
    for k, sign in enumerate((1.0, -1.0)):
        shift = np.eye(4)
        shift[:3, 3] = sign * s1.probe_mm * beam
        probe_start = {b: shift @ first.delta @ P for b, P in start.items()}
        body = run.body(probe_start)
        outcome = run_stage1(run.views, run.levels, run.renderer, body, short,
                             run_seed(run.seed, PROBE, k))  # fmt: skip
        probe = (probe_start, outcome)
        if _between(run, lone, probe)[0] > s1.probe_mm / 2:
            away.append(probe)
    if not away:
        return []
    probe_start, probe = min(away, key=lambda pair: _f(pair[1]))
    again = {b: probe.delta @ P for b, P in probe_start.items()}
    return [(again, run_stage1(run.views, run.levels, run.renderer, run.body(again), run.cfg,
                               run_seed(run.seed, PROBE, 2)))]  # fmt: skip


def _probe_settings(cfg: RegistrationSettings) -> RegistrationSettings:
    """``cfg`` with stage 1's step, populations and generations those of a probe."""
    s1 = cfg.stage1
    n = len(s1.max_generations)
    gens = tuple(min(g, s1.probe_generations) for g in s1.max_generations)
    probe = replace(s1, populations=(s1.probe_population,) * n, sigmas=(s1.probe_sigma,) * n,
                    max_generations=gens)  # fmt: skip
    return replace(cfg, stage1=probe)


def _mean_beam(projections: NDArray) -> NDArray[np.float64]:
    """(3,) unit vector: the mean of the views' beam directions (world)."""
    beams = [pj.decompose_projection(P).carm_from_world[2] for P in projections]
    beams = [b if b @ beams[0] >= 0 else -b for b in beams]
    mean = np.mean(beams, axis=0)
    return mean / np.linalg.norm(mean)


def _best(tried: list[tuple]) -> tuple:
    """The ``(start, outcome)`` whose stage-1 answer scores best (the only one when tracking,
    whose stage 1 runs no level)."""
    return tried[0] if len(tried) == 1 else min(tried, key=lambda pair: _f(pair[1]))


def _body_pose(run: _Run, start: dict, s1) -> NDArray[np.float64]:
    """Where stage 1 put the body: its first bone's ``world_from_ct``."""
    return s1.delta @ run.body(start).start


def _settled(run: _Run, answer: tuple, tried: list[tuple]) -> bool:
    """Whether stage 1's ``answer`` (start, outcome), the best of the runs ``tried``, stands:
    at least ``unsettled_confirmations`` of the other runs ended where it did (within
    ``unsettled_confirm_mm`` at the body's centre and as many degrees); or it stopped on a
    tolerance and was the only run (with ``lone_run_settles``) or another one ended there
    too; or it leads every run that ended elsewhere by ``unsettled_lead`` (:func:`_leads`),
    stopped or still improving at its generation limit (seeds 229 case 12, 181 case 17 and
    179 case 36: good, the winner at its limit 6.7-11.6 % ahead of runs that ended 100-380 mm
    away). With 0 confirmations, a run that stopped on a tolerance is settled (agreement is
    not counted)."""
    need = run.cfg.unsettled_confirmations
    if need == 0:
        return answer[1].result.converged
    others = [o for o in tried if o[1] is not answer[1]]
    elsewhere = [o for o in others if not _agree(run, answer, o)]
    agree = len(others) - len(elsewhere)
    lone = len(tried) == 1 and run.cfg.lone_run_settles
    stopped = answer[1].result.converged
    return agree >= need or (stopped and (lone or agree >= 1)) or _leads(run, answer, elsewhere)


def _agree(run: _Run, answer: tuple, other: tuple) -> bool:
    """Whether stage-1 run ``other`` (start, outcome) ended where ``answer`` did: within
    ``unsettled_confirm_mm`` at the body's centre and as many degrees."""
    mm, deg = _between(run, answer, other)
    lim = run.cfg.unsettled_confirm_mm
    return bool(mm <= lim and deg <= lim)


def _between(run: _Run, answer: tuple, other: tuple) -> tuple[float, float]:
    """How far apart two stage-1 runs (start, outcome) ended: mm at the body's centre, deg."""
    T, U = _body_pose(run, *answer), _body_pose(run, *other)
    centre = run.body(answer[0]).centre[None]
    mm = np.linalg.norm(tf.apply(U, centre) - tf.apply(T, centre))
    deg = np.rad2deg(np.linalg.norm(tf.rotvec_from_matrix(U[:3, :3] @ T[:3, :3].T)))
    return float(mm), float(deg)


def _leads(run: _Run, answer: tuple, elsewhere: list[tuple]) -> bool:
    """Whether ``answer`` scores better than every run in ``elsewhere`` (those that ended
    elsewhere) by at least ``unsettled_lead`` of its own objective (a clear winner found
    once); False when there is none."""
    lead, f = run.cfg.unsettled_lead, _f(answer[1])
    return lead > 0 and bool(elsewhere) and min(_f(o[1]) for o in elsewhere) - f >= lead * abs(f)


def _rescue(run: _Run, init: dict, answer: tuple, first: _Attempt, result: MultiBodyResult,
            settled: bool) -> MultiBodyResult:  # fmt: skip
    """A flagged registration (whose first guess was not taken) tried again from its start
    turned out of plane (:func:`_turned`). When enough of these restarts end where ``answer``
    (the first attempt's stage 1: start, outcome) did and none scores better elsewhere
    (:func:`_found_again`), that answer is confirmed and the first attempt judged again as
    settled, and returned if nothing else flags it. Otherwise the best stage-1 answer, if
    better than ``answer``, goes on to stage 2, and the better-scoring result is returned;
    still flagged, with the first attempt's warnings, when it kept the pelvis where the first
    attempt had it (:func:`_moved_pelvis`) and scores less than ``rescue_margin`` better
    (``Stage1Settings``), unless the first attempt was flagged only by doubts or an unsettled
    stage 1 and the rescued answer by nothing (:func:`_answered`). A first attempt flagged
    only by doubts (ambiguities whose other answer has implausible joints,
    :class:`~pelvicnav.register.settings.ResearchSettings` ``joint_limits``) or an unsettled
    stage 1 is confirmed when the rescue's stage 2 ends where it did with no warning of its
    own (:func:`_confirmed`)."""
    s1 = answer[1]
    turned = _turned(run, init)
    seeds = [run_seed(run.seed, RESCUE, k) for k in range(len(turned))]
    tried = _stage1_runs(run, turned, seeds)
    if _found_again(run, answer, tried):  # the restarts found stage 1's answer
        settled, result = True, _judged(run, first, True)
        if result.converged:
            return result
    start, best = _best(tried)
    if _f(best) >= _f(s1):
        return result
    second = _attempt(run, start, best)
    settled_again = _settled(run, (start, best), [answer, *tried])
    again = _judged(run, second, settled_again)
    confirmed = _confirmed(run, (first, settled), (second, settled_again))
    if confirmed is not None:
        return confirmed
    if again.similarity <= result.similarity:
        return result
    clearly = again.similarity - result.similarity >= run.cfg.stage1.rescue_margin
    if clearly or _moved_pelvis(run, first, again) or _answered(run, first, again):
        return replace(again, warnings=(_rescued_note(result), *again.warnings))
    return _doubts_stand(run, result, again)


def _second_opinion(run: _Run, result: MultiBodyResult) -> MultiBodyResult:
    """``result``, settled when it was flagged only by questions about the dislocated bone's
    answer and, at the finest level, that answer scores above every other one the searches found
    far from it, by more than ``RegistrationSettings.second_opinion``'s margins, in gradient NCC
    and in the level's own similarity (GO) alike (:mod:`~pelvicnav.register.opinion`); still
    flagged, the other answer named, when one of them comes within its margin or scores better
    in either. The poses are never changed. With one view (whose flag reads the detector
    distance) or no plan, ``result`` as it is."""
    margin, bone = run.cfg.second_opinion, run.dislocated  # (gradient NCC, GO)
    if (margin is None or bone is None or len(run.views) < 2 or result.converged
            or result.implausible or not result.questions):  # fmt: skip
        return result
    far = run.cfg.research.ambiguity
    op = second_opinion(run.levels[-1], run.renderer, run.views, result.poses, bone,
                        run.found.get(bone, []), far)  # fmt: skip
    if op.compared == 0:
        return result
    leads = (("gradient correlation", op.lead, margin[0]),
             ("the searches' own similarity", op.lead_level, margin[1]))  # fmt: skip
    if all(lead > m for _, lead, m in leads):
        note = (f"settled by a second opinion: at the finest level, this {bone} scores above each "
                f"of the {op.compared} other answers the searches found more than {far[0]:g} mm "
                f"or {far[1]:g} deg away, by {op.lead:.3f} at least in gradient correlation and "
                f"{op.lead_level:.3f} in the searches' own similarity")  # fmt: skip
        return replace(result, converged=True, warnings=(note, *result.warnings))
    which = " and ".join(f"{name} (to within {m:g})" if m else name
                         for name, lead, m in leads if lead <= m)  # fmt: skip
    note = (f"second opinion: another answer the searches found for {bone}, "
            f"{op.rival_mm:.1f} mm / {op.rival_deg:.1f} deg away, scores as well or better at the "
            f"finest level in {which}")  # fmt: skip
    return replace(result, warnings=(*result.warnings, note))


def _polished(run: _Run, result: MultiBodyResult) -> MultiBodyResult:
    """``result`` with its dislocated bone searched once more in gradient NCC at the finest level
    (``RegistrationSettings.polish``, :mod:`~pelvicnav.register.polish`), the pose taken when it
    scores better and the similarity read there; the verdict and warnings unchanged.
    ``result`` as it is with ``polish=None``, one view or 9 DoF, or no plan."""
    cfg, bone = run.cfg, run.dislocated
    if cfg.polish is None or bone is None or len(run.views) < 2 or cfg.stage1.dof != 6:
        return result
    fine = run.levels[-1]
    found = polish(fine, run.renderer, result.poses, bone, cfg.polish, run_seed(run.seed, POLISH))
    if found.lead <= 0:
        return result
    poses = {**result.poses, bone: found.pose}
    bones = run.renderer.bones
    stack = np.stack([poses[b] for b in bones])[None]
    drrs = run.renderer.render(fine.index, bones, stack, fine.projections, fine.shape)
    return replace(result, poses=poses, similarity=float(fine.score(drrs)[0]))


def _rescued_note(first: MultiBodyResult) -> str:
    """The warning that opens a rescued result."""
    return (f"rescued: the first attempt was flagged (similarity {first.similarity:.3f}); "
            "stage 1 from another start scored better and gave this answer")  # fmt: skip


def _doubts_stand(run: _Run, first: MultiBodyResult, again: MultiBodyResult) -> MultiBodyResult:
    """The rescue's answer ``again``, flagged: it kept the pelvis where the ``first`` attempt
    had it and scores less than ``rescue_margin`` better, so the first attempt's doubts stand.
    The first attempt's warnings follow, each marked as the first attempt's: they speak of its
    answer, not of the one returned (seed 347 case 27: the first attempt's hip had joints no
    dislocation gives, the rescue's did not, and the verdict "in question" read against an
    unmarked "no dislocation puts it there")."""
    same = (f"{_rescued_note(first)}, but with the same pelvis ({', '.join(_kept(run))} within "
            f"{run.cfg.research.ambiguity[0]:g} mm / {run.cfg.research.ambiguity[1]:g} deg of the "
            f"first attempt) and a similarity less than {run.cfg.stage1.rescue_margin:g} better: "
            "the first attempt's doubts stand")  # fmt: skip
    said = tuple(f"first attempt: {w}" for w in first.warnings)
    # questions, for a second opinion, when neither attempt had a fault (its joints aside: the
    # first attempt's implausible answer is among those the second opinion compares)
    questions = (same, *said, *again.questions) if first.questions and (
        again.converged or again.questions) else ()  # fmt: skip
    return replace(again, converged=False, warnings=(same, *said, *again.warnings),
                   questions=questions)  # fmt: skip


def _found_again(run: _Run, first: tuple, tried: list[tuple]) -> bool:
    """Whether the rescue's restarts ``tried`` settle the first attempt's unsettled stage-1
    answer ``first`` (start, outcome): with them it has settled (:func:`_settled`), and none
    that ended elsewhere scores better. A restart that found a better answer elsewhere is a
    reason to go on, whatever the others agree on: seed 193 case 0 (stage 1 run once, the
    pelvis 17.8 mm off in depth): two restarts ended at its answer and one 18 % better at the
    truth."""
    alone = [first]
    if _settled(run, first, alone) or not _settled(run, first, [*alone, *tried]):
        return False
    f = _f(first[1])
    return not any(_f(o[1]) < f and not _agree(run, first, o) for o in tried)


def _confirmed(run: _Run, first: tuple, second: tuple) -> MultiBodyResult | None:
    """The better-scoring of two attempts ``(attempt, settled)`` judged as settled and without
    their doubts, when the first was flagged only by doubts or an unsettled stage 1, neither
    has a warning of its own, and every bone ended within the re-search's ``ambiguity`` of the
    first attempt's pose; else None. Both questions are answered by a second attempt from other
    stage-1 starts that ends at the same answer with nothing else in doubt: an ambiguity whose
    other answer no dislocation gives (the joints closed through or opened past
    ``joint_limits``) is a doubt, not a verdict (seeds 137 case 25 and 139 case 4, good to
    0.3 mm, each found once against implausible other answers: confirmed); and the same pelvis
    found from two sets of starts has settled (seed 181 case 39: 0.8 mm, stage 1 stopped on its
    generation limit; the rescue ended at the same answer 0.001 below it and the first attempt
    stayed flagged before). When the second attempt ends elsewhere, it is judged as before
    (seed 151 case 1: the first attempt's hip was 8.7 mm off; the rescue found the truth,
    0.022 better)."""
    (a, settled), (b, _) = first, second
    if not a.doubts and settled:
        return None
    clean = [_judged(run, replace(x, doubts=[]), True) for x in (a, b)]
    if not all(c.converged for c in clean) or not _same_answer(run, a, b):
        return None
    best = max(clean, key=lambda c: c.similarity)
    questions = [*a.doubts, *([] if settled else ["stage 1 did not settle"])]
    note = (f"confirmed: the first attempt's doubts ({'; '.join(questions)}) were settled by a "
            "second attempt from other stage-1 starts that ended at the same answer")  # fmt: skip
    return replace(best, warnings=(note, *best.warnings))


def _answered(run: _Run, first: _Attempt, again: MultiBodyResult) -> bool:
    """Whether the first attempt was flagged only for questions a second attempt answers, and
    the rescue's answer (which scores better) is flagged by nothing, its own doubts included.
    The questions: doubts (ambiguities or single finds whose other answer has implausible
    joints) and a stage 1 that did not settle; the first attempt judged as settled and without
    its doubts must pass. A better answer from other stage-1 starts that passes every check
    replies to both, even when it kept the pelvis (then the pelvis was found twice). Seed 137
    case 16: the first attempt's hip 17.5 mm off, found once against an implausible other
    answer; the rescue's 0.2 mm, 0.015 better, clean. Seed 173 case 29: stage 1 unsettled at
    0.48 per view; the rescue kept the pelvis, 0.4 mm, clean. The gross rescues that kept the
    pelvis (seeds 127, 131, 173) were each flagged on their own, by joints or ambiguities."""
    if first.warnings or not again.converged:
        return False
    return _judged(run, replace(first, doubts=[]), True).converged


def _same_answer(run: _Run, a: _Attempt, b: _Attempt) -> bool:
    """Whether every bone of attempt ``b`` ended within the re-search's ``ambiguity`` (mm at
    its centroid, degrees) of attempt ``a``'s pose."""
    lim = run.cfg.research.ambiguity
    for bone in run.renderer.bones:
        mm, deg = _apart(run, a.views, a.fine, bone, a.poses[bone], b.poses[bone])
        if mm > lim[0] or deg > lim[1]:
            return False
    return True


def _apart(run: _Run, views: ViewSet, fine: Level, bone: str, T_a: NDArray,
           T_b: NDArray) -> tuple[float, float]:  # fmt: skip
    """How far apart two poses of ``bone`` are (:func:`~pelvicnav.metrics.errors.
    pose_disagreement` with its fine-level model): mm at its centroid and degrees, or with one
    view the median distance of its points at the detector."""
    r = run.renderer
    return pose_disagreement(T_a, T_b, r.points(bone, fine.index), r.centroid(bone, fine.index),
                             views.projections, views.pixel_spacing)  # fmt: skip


def _kept(run: _Run) -> list[str]:
    """The bones stage 1 places: all but the dislocated one (all without a plan)."""
    return list(pelvis_bones(run.renderer.bones, run.dislocated) or run.renderer.bones)


def _moved_pelvis(run: _Run, first: _Attempt, again: MultiBodyResult) -> bool:
    """Whether the rescue moved a bone stage 1 places (:func:`_kept`) further than the
    re-search's ``ambiguity`` (mm at its centroid, degrees) from the first attempt. A rescue
    exists for a misplaced pelvis; one that keeps it has only searched the dislocated bone
    again, and a second answer for it does not clear the first attempt's doubts (seed 127,
    cases 16, 22 and 34: a hip 13-45 mm off flagged as ambiguous or found once, then
    13-33 mm off from the rescue, unflagged)."""
    lim = run.cfg.research.ambiguity
    for b in _kept(run):
        mm, deg = _apart(run, first.views, first.fine, b, first.poses[b], again.poses[b])
        if mm > lim[0] or deg > lim[1]:
            return True
    return False


def _initial(level: Level, renderer, body, init: dict, s1) -> dict[str, NDArray]:
    """Every bone's initial pose moved by the translation (and turn, where
    ``s1.initial_turn_deg``) that lays the body's DRR on the views
    (:mod:`pelvicnav.register.initial`)."""
    poses = np.stack([init[b] for b in body.bones])
    centre = tf.apply(body.start, body.centre[None])[0]
    mm = s1.initial_search_mm
    if max(s1.initial_turn_deg) > 0:
        angles = tuple(
            np.arange(-a, a + 1e-9, 10.0)
            for a in (s1.initial_turn_deg[0], *[s1.initial_turn_deg[1]] * 2)
        )
        delta = initial_pose(level, renderer, body.bones, poses, centre, mm, angles)
    else:
        delta = initial_translation(level, renderer, body.bones, poses, centre, mm)
    moved_mm = np.linalg.norm(tf.apply(delta, centre[None])[0] - centre)
    turned_deg = np.rad2deg(np.linalg.norm(tf.rotvec_from_matrix(delta[:3, :3])))
    if moved_mm < s1.initial_min_mm and turned_deg < s1.initial_min_deg:
        return init  # within stage 1's own reach: its search decides (see Stage1Settings)
    return {b: delta @ T for b, T in init.items()}


def _check_inputs(views, renderer, cfg, init_poses, dislocated) -> dict[str, NDArray]:
    """The initial pose of every bone (identity where not given); raises on bad input."""
    if not isinstance(views, ViewSet):
        raise TypeError(f"views must be a ViewSet, got {type(views).__name__}")
    if cfg.dof == 9 and len(views) != 1:
        raise ValueError(f"9-DoF registration takes exactly one view, got {len(views)}")
    bones = renderer.bones
    if dislocated is not None and dislocated not in bones:
        raise ValueError(f"unknown dislocated bone {dislocated!r}; expected one of {list(bones)}")
    first = cfg.stage1.body
    if first != "pelvis" and first not in bones:
        raise ValueError(f"unknown stage-1 body {first!r}; expected 'pelvis' or one of {bones}")
    init = {b: np.eye(4) for b in bones}
    for b, T in (init_poses or {}).items():
        if b not in init:
            raise ValueError(f"unknown bone {b!r} in the initial poses")
        init[b] = np.asarray(T, dtype=np.float64)
        tf.se3_log(init[b])  # a rigid pose, or a clear error
    return init


@dataclass(frozen=True)
class _Stage2Outcome:
    poses: dict[str, NDArray[np.float64]]
    disagreement: dict[str, float]
    warnings: list[str]
    result: StageResult
    doubts: list[str]
    implausible: list[str]  # of the warnings: the dislocated bone's joints no dislocation gives
    found: dict[str, list[NDArray[np.float64]]]  # the re-search's (ResearchOutcome.found)
    faults: list[str]  # the pelvis's bones at the edge of their box (_edges)


def _stage2(views, levels, renderer, poses, cfg, seed, progress, dislocated) -> _Stage2Outcome:
    """Stage 2 from the stage-1 poses, then the re-search (sweep mode)."""
    t0 = time.perf_counter()
    prior = None
    s2 = cfg.stage2
    searching = s2.mode != "gradient"  # gradient refinement (tracking) does not read the prior
    limits = cfg.research.joint_limits
    active = s2.joint_prior > 0 or s2.joint_gap[0] > 0  # in the objective, else only measured
    if dislocated is not None and searching and (active or limits is not None):
        prior = joint_prior(renderer, dislocated, weight=s2.joint_prior, gap_weight=s2.joint_gap[0],
                            gap_slack=s2.joint_gap[1], fields=limits[1] if limits else 0.0,
                            max_points=200 if active else MEASURED_POINTS, seed=seed)  # fmt: skip
    problem = Stage2Problem(Blocks.at(poses, renderer), renderer, levels, cfg, dislocated, prior)
    y = np.zeros(6 * len(renderer.bones))
    search = joint if cfg.stage2.mode == "joint" else sweeps
    y, runs = search(problem, y, seed, progress)
    if cfg.stage2.mode == "sweep":  # searching, not tracking
        y, chosen = rejoined(problem, y)
        runs = runs if chosen is None else [*runs, chosen]
    count = cfg.research.count(len(views)) if cfg.stage2.mode != "joint" else 0
    again = research(problem, y, views, seed, count if problem.searched else 0)
    result = StageResult("stage 2", runs, time.perf_counter() - t0, problem.final_runs, again.runs)
    faults = _edges(problem, again.y) if cfg.stage2.mode == "sweep" else []
    return _Stage2Outcome(problem.blocks.as_dict(again.y), again.disagreement, again.warnings,
                          result, again.doubts, again.implausible, again.found,
                          faults)  # fmt: skip


def _edges(problem: Stage2Problem, y: NDArray) -> list[str]:
    """With a plan, a warning for each bone stage 1 placed (the pelvis) whose stage-2 parameters
    ``y`` reached the edge of its box (``Stage2Settings.range_attached``): the answer lies beyond
    it, so stage 1 misplaced the pelvis and stage 2 could not bring it back. Seed 373 case 16: a
    lone stage-1 run left the pelvis 11 mm off; stage 2 turned the sacrum and the right hip by
    the box's 4 deg about two axes and stopped there, both bones 2.6-5.3 mm / 7 deg off, no
    other rule raised; at the finest level the true pelvis scored 0.058 better in GO."""
    if problem.dislocated is None:
        return []
    out = []
    for i, bone in enumerate(problem.blocks.bones):
        if bone == problem.dislocated:
            continue
        box = problem.box(i)
        if np.any(np.abs(y[6 * i : 6 * i + 6]) >= EDGE * box):
            out.append(f"stage 2 moved {bone} to the edge of its box ({box[0]:g} mm / "
                       f"{box[3]:g} deg from where it started): stage 1 misplaced the "
                       "pelvis")  # fmt: skip
    return out


def _attainable(metric: str, drrs: NDArray, n_views: int) -> float:
    """What the answer's DRRs (K, rows, cols) could score at best, summed over the views: the
    floor of the final similarity is a fraction of it. For GO, each view's DRR against itself:
    1 when the bones' edges cover at least half the view (``N_LB``, equation 10), less when they
    cover less (340 mm radiographs of a mobile system at magnification 1.1: about 0.8, and
    good registrations scored 0.36-0.37 against a floor of 0.4 per view). Gradient NCC: 1."""
    if metric != "go":
        return float(n_views)
    from pelvicnav.metrics.similarity import gradient_orientation

    return float(sum(gradient_orientation(d, d[None])[0] for d in drrs))


def _unsettled(settled: bool, metric: str, similarity: float, attainable: float, n_views: int,
               cfg) -> bool:  # fmt: skip
    """Whether stage 1 did not settle (several views) and the answer's GO is weak (see
    ``RegistrationSettings.unsettled_similarity``)."""
    return (n_views > 1 and metric == "go" and not settled
            and similarity < cfg.unsettled_similarity * attainable)  # fmt: skip


def _judge(views, fine: Level, renderer, poses, stages, ambiguous, disagreement, cfg, body,
           settled: bool, faults=()) -> MultiBodyResult:  # fmt: skip
    """The result with its similarity (all bones, finest level) and convergence flag
    (``settled``: whether stage 1's answer stands, :func:`_settled`; ``faults``: stage 2's
    warnings that flag it whatever else is said, :func:`_edges`)."""
    bones = renderer.bones
    stack = np.stack([poses[b] for b in bones])[None]
    drrs = renderer.render(fine.index, bones, stack, fine.projections, fine.shape)
    similarity = float(fine.score(drrs)[0])
    warnings = []
    converged = stages[-1].converged  # the final stage's runs; an earlier one is only a start
    for s in stages:
        if not s.converged:
            later = "" if s is stages[-1] else f" ({stages[-1].name} refined from there)"
            warnings.append(f"{s.name}: a search hit its generation limit while still improving"
                            + later)  # fmt: skip
    faulted = not converged or bool(faults)  # flagged by more than questions
    if faults:
        converged = False
        warnings.extend(faults)
    if ambiguous:
        converged = False
        warnings.extend(ambiguous)
    metric = cfg.pyramid.metrics[fine.index]
    per_view = cfg.min_similarity_for(metric)
    attainable = _attainable(metric, drrs[0], len(views))
    floor = per_view * attainable
    if similarity < floor:
        converged, faulted = False, True
        warnings.append(f"final similarity {similarity:.3f} is below {floor:.3f} "
                        f"({per_view} per view)")  # fmt: skip
    elif _unsettled(settled, metric, similarity, attainable, len(views), cfg):
        converged, faulted = False, True
        warnings.append(f"stage 1 did not settle and the final similarity {similarity:.3f} is "
                        f"below {cfg.unsettled_similarity * attainable:.3f} "
                        f"({cfg.unsettled_similarity} per view): the bones may be misplaced "
                        "together")  # fmt: skip
    return MultiBodyResult(
        poses=poses,
        projections=views.projections,
        similarity=similarity,
        converged=converged,
        stages=stages,
        stage1_bone=body,
        warnings=tuple(warnings),
        restart_disagreement=disagreement,
        questions=() if faulted else tuple(ambiguous),
    )
