"""Stage 1 (Han et al. 2020, section 2.2.1): one rigid body against every view.

The body is the whole pelvis (or, with a plan, every bone but the dislocated one) or a single
bone; its bones keep their initial poses relative to each other. Two parameterisations:

* :class:`SixDof` — ``[t (mm), r (deg)]`` about the body's centre, every ``P`` known (equation 11b);
* :class:`NineDof` — the same plus the source position in detector coordinates (equation 11a:
  one view; the intrinsics are refined, the detector pose absorbs into the body pose).

CMA-ES runs on every pyramid level with a non-zero generation budget, coarse to fine.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from numpy.typing import NDArray

from pelvicnav.drr.renderer import Renderer
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.views import ViewSet
from pelvicnav.register.cmaes import CMAESResult, minimize_cmaes
from pelvicnav.register.pyramid import Level, downsample_projection
from pelvicnav.register.result import StageResult
from pelvicnav.register.seeds import STAGE1, run_seed
from pelvicnav.register.settings import RegistrationSettings

__all__ = [
    "Body",
    "NineDof",
    "SixDof",
    "Stage1Outcome",
    "parameterisation",
    "run_stage1",
    "stage1_body",
]


@dataclass(frozen=True, eq=False)
class Body:
    """The rigid body of stage 1: its bones, their poses relative to the first, its centre.

    Attributes
    ----------
    name : str
        ``"pelvis"`` or a bone name.
    bones : tuple of str
    start : (4, 4)
        Initial ``world_from_ct`` of the first bone.
    relative : (L, 4, 4)
        Each bone's initial pose relative to ``start`` (they move together).
    centre : (3,) mm, CT frame
        Mass-weighted centroid of the body's bones (the rotation centre).
    """

    name: str
    bones: tuple[str, ...]
    start: NDArray[np.float64]
    relative: NDArray[np.float64]
    centre: NDArray[np.float64]


def pelvis_bones(bones: Sequence[str], dislocated: str | None) -> tuple[str, ...]:
    """The bones of the stage-1 ``"pelvis"`` body: all but the plan's dislocated one."""
    return tuple(b for b in bones if b != dislocated)


def stage1_body(
    renderer: Renderer, name: str, init: dict[str, NDArray], dislocated: str | None
) -> Body:
    """The stage-1 body ``name`` (``"pelvis"`` or a bone) from the initial poses ``init``."""
    if name == "pelvis":
        bones = pelvis_bones(renderer.bones, dislocated)
        masses = [renderer.mass(b) for b in bones]
        centre = sum(m * renderer.centroid(b) for m, b in zip(masses, bones, strict=True))
        centre = centre / sum(masses)
    else:
        bones, centre = (name,), renderer.centroid(name)
    start = init[bones[0]]
    if name == "pelvis":
        relative = np.stack([tf.invert(start) @ init[b] for b in bones])
    else:
        relative = np.eye(4)[None]
    return Body(name, bones, start, relative, np.asarray(centre, dtype=np.float64))


def _rigid(X: NDArray, centre_world: NDArray, start: NDArray) -> NDArray[np.float64]:
    """``(N, 6+) -> (N, 4, 4)``: ``[t (mm), r (deg)]`` about ``centre_world``, then ``start``."""
    return pj.six_dof_pose(X[:, :6], center=centre_world) @ start


@dataclass(frozen=True, eq=False)
class SixDof:
    """``[t (mm), r (deg)]`` about ``centre_world`` on top of ``start``; the views' ``P`` fixed."""

    start: NDArray[np.float64]
    centre_world: NDArray[np.float64]
    box: NDArray[np.float64]

    dim = 6
    scales = None

    def poses(self, X: NDArray) -> NDArray[np.float64]:
        """``(N, 6) -> (N, 4, 4)`` ``world_from_ct`` of the body's first bone."""
        return _rigid(X, self.centre_world, self.start)

    def projections(self, X: NDArray, level: Level) -> NDArray[np.float64]:
        return level.projections

    def final_projections(self, x: NDArray, views: ViewSet) -> None:
        """The refined full-resolution geometry: none, the views' own stands."""
        return None

    def recentred(self, x: NDArray) -> SixDof:
        """The same parameterisation with its zero (and box) moved to ``x``."""
        return replace(self, **_moved_pose(self.start, self.centre_world, x))


@dataclass(frozen=True, eq=False)
class NineDof:
    """:class:`SixDof` plus the source position offset (mm, detector axes) of the one view."""

    start: NDArray[np.float64]
    centre_world: NDArray[np.float64]
    box: NDArray[np.float64]
    geometry: pj.NineDof
    rows: int
    cols: int
    pixel_spacing: tuple[float, float]

    dim = 9
    scales = (1.0,) * 6 + (5.0,) * 3  # the source moves the image less than the pose

    def poses(self, X: NDArray) -> NDArray[np.float64]:
        """``(N, 9) -> (N, 4, 4)`` ``world_from_ct`` of the body's first bone."""
        return _rigid(X, self.centre_world, self.start)

    def _full(self, X: NDArray) -> NDArray[np.float64]:
        """``(N, 9) -> (N, 3, 4)``: the view's full-resolution ``P`` at each candidate source."""
        return pj.projections_from_sources(
            np.asarray(self.geometry.source_in_detector) + X[:, 6:],
            self.geometry.world_from_detector,
            rows=self.rows, cols=self.cols, pixel_spacing=self.pixel_spacing,
        )  # fmt: skip

    def projections(self, X: NDArray, level: Level) -> NDArray[np.float64]:
        """One binned ``P`` per candidate: (N, 1, 3, 4)."""
        return downsample_projection(self._full(X), level.factor)[:, None]

    def final_projections(self, x: NDArray, views: ViewSet) -> tuple[NDArray, ...]:
        """The refined full-resolution geometry of the one view."""
        return (self._full(np.asarray(x)[None])[0],)

    def recentred(self, x: NDArray) -> NineDof:
        """The same parameterisation with its zero (and box) moved to ``x``."""
        s = np.asarray(self.geometry.source_in_detector) + x[6:]
        geometry = pj.NineDof(tuple(s), self.geometry.world_from_detector)
        return replace(self, **_moved_pose(self.start, self.centre_world, x), geometry=geometry)


def _moved_pose(start: NDArray, centre_world: NDArray, x: NDArray) -> dict:
    """``start`` and ``centre_world`` moved by the pose parameters ``x[:6]`` (about the centre)."""
    moved = pj.six_dof_pose(x[None, :6], center=centre_world)[0]
    return {"start": moved @ start, "centre_world": tf.apply(moved, centre_world[None])[0]}


def parameterisation(
    body: Body, views: ViewSet, settings: RegistrationSettings
) -> SixDof | NineDof:
    """The stage-1 parameters for ``settings.stage1.dof`` (9 needs exactly one view)."""
    s1 = settings.stage1
    c = tf.apply(body.start, body.centre[None])[0]
    t, r = s1.search_range
    if s1.dof == 6:
        return SixDof(body.start, c, np.array([t] * 3 + [r] * 3))
    rows, cols = views.shape
    ps = views.pixel_spacing[0]
    geometry = pj.nine_dof_from_projection(
        views.projections[0], rows=rows, cols=cols, pixel_spacing=ps
    )
    box = np.array([t] * 3 + [r] * 3 + [s1.source_range_mm] * 3)
    return NineDof(body.start, c, box, geometry, rows, cols, ps)


def _body_objective(
    X: NDArray, *, params: SixDof | NineDof, body: Body, renderer: Renderer, level: Level
) -> NDArray[np.float64]:
    """Minus the similarity of the body at each candidate ``X`` (N, dim)."""
    stack = params.poses(X)[:, None] @ body.relative[None]
    drrs = renderer.render(
        level.index, body.bones, stack, params.projections(X, level), level.shape
    )
    return -level.score(drrs)


def _search(params, x, body, renderer, lv: Level, settings, seed: int, attempt: int):
    """One CMA-ES run of the body on level ``lv`` from ``x`` within ``params.box``."""
    s1 = settings.stage1
    objective = partial(_body_objective, params=params, body=body, renderer=renderer, level=lv)
    return minimize_cmaes(
        objective,
        x,
        sigma=(s1.sigmas or settings.pyramid.sigmas)[lv.index],
        population=s1.populations[lv.index],
        seed=run_seed(seed, STAGE1, lv.index, *([attempt] if attempt else [])),
        max_generations=s1.max_generations[lv.index],
        scales=params.scales,
        bounds=(-params.box, params.box),
    )


def _at_edge(x: NDArray, box: NDArray, fraction: float = 0.9) -> bool:
    """Whether a pose parameter of ``x`` ended within ``1 - fraction`` of its box's edge."""
    return bool(np.any(np.abs(x[:6]) >= fraction * box[:6]))


@dataclass(frozen=True)
class Stage1Outcome:
    """Stage 1's answer: how the body moved, the refined geometry (9 DoF) and the runs."""

    delta: NDArray[np.float64]  # world_from_world: applied to every bone's initial pose
    projections: tuple[NDArray[np.float64], ...] | None
    result: StageResult


def run_stage1(
    views: ViewSet,
    levels: Sequence[Level],
    renderer: Renderer,
    body: Body,
    settings: RegistrationSettings,
    seed: int,
    progress: Callable[[str, int, int], None] | None = None,
) -> Stage1Outcome:
    """Register ``body`` on every level with a stage-1 generation budget."""
    t0 = time.perf_counter()
    s1 = settings.stage1
    params = parameterisation(body, views, settings)
    x = np.zeros(params.dim)
    runs: list[CMAESResult] = []
    for lv in levels:
        if s1.max_generations[lv.index] == 0:
            continue
        for attempt in range(1 + s1.recentre):
            res = _search(params, x, body, renderer, lv, settings, seed, attempt)
            runs.append(res)
            x = res.x
            if not _at_edge(res.x, params.box):
                break
            params, x = params.recentred(res.x), np.zeros(params.dim)  # the answer lies beyond
        if progress:
            progress("stage 1", lv.index + 1, len(levels))
    delta = params.poses(x[None])[0] @ tf.invert(body.start)
    result = StageResult("stage 1", runs, time.perf_counter() - t0)
    return Stage1Outcome(delta, params.final_projections(x, views), result)
