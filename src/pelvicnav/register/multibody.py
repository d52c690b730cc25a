"""Two-stage multi-body 3D-2D registration (Han et al. 2020, section 2.2, equations 9-12).

* **Stage 1** — one bone (by default the innominate with the most attenuation mass, the most
  salient in the images) against the views: with ``dof=6`` its rigid pose with every ``P`` known
  (GO summed over the views); with ``dof=9`` (one view) its pose *and* the source position in
  detector coordinates (equation 11a: the intrinsics are refined, the detector pose absorbs into
  the bone pose).
* **Stage 2** — the 6-DoF pose of every bone, started from the stage-1 pose, GO summed over the
  views (equation 12). All bones move at once (6 x L parameters).

Both stages run CMA-ES (pycma, ask/tell) on a pyramid (binning [4, 2], population [100, 100],
sigma [4, 1] mm and degrees: parameters are ``[t (mm), r (deg)]`` about each bone's centroid, so a
unit step moves the bone by comparable amounts). DRRs come from the splatting projector
(:mod:`pelvicnav.drr.splat`) with bone models sampled at 0.75 x the binning factor in mm. The
radiographs are blurred to the same resolution as the DRRs at every level.

A stage whose every level stopped on a tolerance is *converged*; a registration whose final GO is
below ``min_similarity`` or that hit a generation limit is flagged not converged, never reported
as a success.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.drr.attenuation import bone_models
from pelvicnav.drr.projector import downsample_image, downsample_projection
from pelvicnav.drr.splat import PointModel, splat
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.metrics.similarity import GradientNCC, GradientOrientation
from pelvicnav.register.cmaes import CMAESResult, minimize_cmaes

__all__ = [
    "MultiBodyResult",
    "RegistrationSettings",
    "RegistrationViews",
    "StageResult",
    "level_models",
    "register_multibody",
]

# Bone model sample spacing per unit of pyramid binning (mm): 3 mm at 4x, 1.5 mm at 2x. The
# splatting cost grows as 1 / spacing; finer samples did not improve accuracy measurably.
SAMPLE_MM_PER_FACTOR = 0.75


@dataclass(frozen=True)
class RegistrationSettings:
    """Settings of both stages (defaults are the paper's, with generation caps).

    Attributes
    ----------
    dof : 6 or 9
        Stage-1 degrees of freedom (9 needs exactly one view).
    stage1_bone : str
        Body of stage 1: ``"pelvis"`` (default: all bones moving as one rigid body) or one bone
        name (the paper's choice). A single bone's DRR covers a small part of the image, and GO
        (equation 10) then rewards poses that enlarge its edge footprint (every pixel above both
        median thresholds scores >= 0.29, even with orthogonal gradients); on simulated cases
        single-bone stage 1 locked onto bones turned by 80-90 degrees. The whole pelvis fills the
        image and has no such bias; stage 2 then resolves the inter-bone motion.
    factors, populations, sigmas : per pyramid level, coarse to fine
    max_generations_stage1, max_generations_stage2 : per level
        0 skips the level (by default stage 1 runs on the coarse level only: stage 2 refines
        every bone at the fine level anyway).
    stage2 : bool
        Run stage 2 (else every bone takes the stage-1 pose).
    min_similarity : float
        Final GO below this is flagged as not converged.
    stage2_mode : "sweep" or "joint"
        ``"joint"``: one CMA-ES over all 6 x L parameters (the paper). ``"sweep"`` (default):
        block coordinates, each bone's 6 DoF in turn over the fixed DRR of the others, for
        ``stage2_sweeps`` sweeps per level (sigma halved on the second sweep). DRRs add, so a
        candidate renders one bone instead of all: on simulated cases 3-4x faster at the same
        accuracy.
    metrics : per level, "go" or "gncc"
        Similarity per pyramid level. Default gradient NCC at the coarse level, GO (equation 10)
        at the fine level. GO everywhere is the paper's choice; on simulated cases its peak at
        the coarse level stood only ~10% above its background level (every strong-gradient pixel
        scores >= 0.29 whatever its orientation) and stage 1 locked onto magnified poses 30-50 mm
        off in depth in 3 of 20 cases; gradient NCC has a sharp capture peak.
    stage2_restarts : int, optional
        Sweep mode: independent re-searches of the dislocated bone (every bone without a plan)
        from its stage-1 pose with other seeds, after the sweeps; the first (and every odd one)
        with the ``coarse_rotation_prior``, the second without. Default (None): 1 with two or
        more views, 2 with one view (one view leaves a dislocated bone several optima: on 10
        single-view 9-DoF cases the largest PDE fell from 3.4 to 1.9 mm, for ~1 s more; with
        two views a second re-search would cost ~1 s). The better fine-level score
        wins; two answers further apart than ``ambiguity`` (mm at the centroid, degrees) whose
        summed similarities differ by less than ``ambiguity_score`` flag the registration as not
        converged (the images leave the bone's pose ambiguous). A re-search that ends at a
        clearly worse similarity is a failed restart, not an ambiguity.
    stage2_populations : per level, optional
        Population of each 6-DoF block problem (default 30 and 20; None: ``populations``). The
        paper's 100 is for its 18-DoF joint problem; the block problems converge with fewer
        candidates per generation.
    stage1_range, stage2_range : (mm, deg)
        Search box of each stage around its start (set-up error up to 20 mm / 5 deg; dislocation
        up to 20 mm / 10 deg on top of stage 1).
    stage2_range_attached : (mm, deg)
        Stage-2 box of the bones the plan says are not dislocated (they moved with the pelvis in
        stage 1, up to the few mm the dislocated bone biased it), when ``dislocated`` is given.
    coarse_rotation_prior : float
        The re-search (``stage2_restarts``) is regularised at every level but the finest:
        ``coarse_rotation_prior x K x |r|^2`` is taken off the similarity of the bone rotated by
        ``|r|`` degrees from its stage-1 pose (K views). A bone about half out of the field of
        view leaves the coarse levels a valley of nearly equal similarity along which it can turn
        10-15 degrees; the prior (0.001 per view at 4.5 deg, 0.01 at 14 deg) takes the
        least-turned end of it, so the re-search is a second hypothesis rather than a repeat.
        The finest level is not regularised and picks between the answers; when the re-search
        wins from another basin, every bone gets one more fine-level pass over the corrected
        DRRs. The sweeps themselves are not regularised: a prior there shifted the sacrum's
        poorly determined depth by ~0.2 mm through the DRR it overlaps. 0 switches it off.
    """

    dof: int = 6
    stage1_bone: str = "pelvis"
    factors: tuple[int, ...] = (4, 2)
    populations: tuple[int, ...] = (100, 100)
    sigmas: tuple[float, ...] = (4.0, 1.0)
    max_generations_stage1: tuple[int, ...] = (25, 0)
    max_generations_stage2: tuple[int, ...] = (30, 20)
    stage2: bool = True
    min_similarity: float = 0.05
    stage1_range: tuple[float, float] = (40.0, 10.0)
    stage2_range: tuple[float, float] = (25.0, 12.0)
    stage2_range_attached: tuple[float, float] = (8.0, 4.0)
    stage2_mode: str = "sweep"
    stage2_sweeps: int = 2
    stage2_populations: tuple[int, ...] | None = (30, 20)
    metrics: tuple[str, ...] = ("gncc", "go")
    stage2_restarts: int | None = None
    ambiguity: tuple[float, float] = (2.0, 2.0)
    ambiguity_score: float = 0.01
    coarse_rotation_prior: float = 5e-5

    @classmethod
    def tracking(cls) -> RegistrationSettings:
        """A later frame from the previous frame's poses: stage 2 only, one sweep, both pyramid
        levels (15 coarse + 20 fine generations), no re-search. The fine level alone did not
        converge after a 7 mm reduction step between frames in the demo; both levels did."""
        return cls(max_generations_stage1=(0, 0), max_generations_stage2=(15, 20),
                   stage2_sweeps=1, stage2_restarts=0)  # fmt: skip

    def __post_init__(self) -> None:
        if self.dof not in (6, 9):
            raise ValueError(f"dof must be 6 or 9, got {self.dof}")
        n = len(self.factors)
        lists = (
            self.populations,
            self.sigmas,
            self.max_generations_stage1,
            self.max_generations_stage2,
        )
        if self.stage2_populations is None:
            object.__setattr__(self, "stage2_populations", self.populations)
        if any(m not in ("go", "gncc") for m in self.metrics):
            raise ValueError(f"metrics must be 'go' or 'gncc', got {self.metrics}")
        if any(len(x) != n for x in (*lists, self.stage2_populations, self.metrics)):
            raise ValueError("registration settings need one value per pyramid level")
        if self.stage2_restarts is not None and self.stage2_restarts < 0:
            raise ValueError(f"stage2_restarts must be >= 0, got {self.stage2_restarts}")
        if not self.coarse_rotation_prior >= 0:
            raise ValueError(
                f"coarse_rotation_prior must be >= 0, got {self.coarse_rotation_prior}"
            )
        if self.stage2_mode not in ("joint", "sweep"):
            raise ValueError(f"stage2_mode must be 'joint' or 'sweep', got {self.stage2_mode!r}")


@dataclass(frozen=True)
class RegistrationViews:
    """Radiographs (line integrals) and their geometry.

    Attributes
    ----------
    images : K (H, W) float arrays
    projections : K (3, 4) float arrays
    pixel_spacing : K (row, col) mm
    """

    images: tuple[NDArray[np.float64], ...]
    projections: tuple[NDArray[np.float64], ...]
    pixel_spacing: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        if not self.images or len(self.images) != len(self.projections):
            raise ValueError(
                f"need one projection matrix per image, got {len(self.images)} images and "
                f"{len(self.projections)} matrices"
            )
        imgs, Ps = [], []
        for k, (img, P) in enumerate(zip(self.images, self.projections, strict=True)):
            a = np.asarray(img, dtype=np.float64)
            if a.ndim != 2 or min(a.shape) < 16:
                raise ValueError(f"view {k}: image must be 2D and at least 16 x 16, got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"view {k}: image contains NaN or infinity")
            try:
                P = pj.normalize_projection(P)
            except ValueError as err:
                raise ValueError(f"view {k}: {err}") from None
            imgs.append(a)
            Ps.append(P)
        if len({a.shape for a in imgs}) != 1:
            raise ValueError(f"all views must have the same shape, got {[a.shape for a in imgs]}")
        object.__setattr__(self, "images", tuple(imgs))
        object.__setattr__(self, "projections", tuple(Ps))
        if len(self.pixel_spacing) != len(imgs):
            raise ValueError("need one pixel spacing per view")

    @property
    def shape(self) -> tuple[int, int]:
        return self.images[0].shape  # type: ignore[return-value]


PLATEAU = 1e-3
COLLAPSED = 0.5  # mm or degrees


def _plateaued(history: NDArray) -> bool:
    h = np.minimum.accumulate(np.asarray(history, dtype=np.float64))
    return len(h) > 10 and h[-11] - h[-1] < PLATEAU


@dataclass(frozen=True)
class StageResult:
    """One stage: per-level CMA-ES results, time and evaluations."""

    name: str
    levels: list[CMAESResult]
    seconds: float
    n_final: int = 1
    restarts: list[CMAESResult] = field(default_factory=list)  # re-searches (not the estimate)

    @property
    def converged(self) -> bool:
        """The runs that produced the final estimate (the last level; in stage 2 the last sweep,
        one run per bone) each stopped on a tolerance, collapsed (largest search standard
        deviation below ``COLLAPSED`` mm or degrees) or plateaued (best similarity improved by
        less than ``PLATEAU`` over its last ten generations)."""
        final = self.levels[-self.n_final :] if self.levels else []
        return all(r.converged or r.final_std < COLLAPSED or _plateaued(r.history) for r in final)

    @property
    def evaluations(self) -> int:
        return sum(r.evaluations for r in (*self.levels, *self.restarts))


@dataclass(frozen=True)
class MultiBodyResult:
    """Registered poses and diagnostics.

    Attributes
    ----------
    poses : dict bone -> (4, 4) float64
        ``world_from_ct`` of each bone.
    projections : tuple of (3, 4)
        The views' projection matrices (refined by stage 1 with ``dof=9``).
    similarity : float
        GO (summed over views) at the finest level, all bones rendered.
    converged : bool
    stages : list of StageResult
    seconds : float
    stage1_bone : str
    warnings : tuple of str
    restart_disagreement : dict bone -> mm
        Distance between the stage-2 answer and the independent re-search (``stage2_restarts``):
        at the bone's centroid, or with one view the median distance of its projected samples
        at the detector.
    """

    poses: dict[str, NDArray[np.float64]]
    projections: tuple[NDArray[np.float64], ...]
    similarity: float
    converged: bool
    stages: list[StageResult] = field(default_factory=list)
    seconds: float = 0.0
    stage1_bone: str = ""
    warnings: tuple[str, ...] = ()
    restart_disagreement: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict:
        """The ``result.json`` record of ARCHITECTURE.md."""
        return {
            "poses": {b: np.asarray(T).tolist() for b, T in self.poses.items()},
            "projection_matrices": [np.asarray(P).tolist() for P in self.projections],
            "similarity": self.similarity,
            "converged": self.converged,
            "warnings": list(self.warnings),
            "stage1_bone": self.stage1_bone,
            "restart_disagreement_mm": dict(self.restart_disagreement),
            "seconds": self.seconds,
            "stages": [
                {
                    "name": s.name,
                    "seconds": s.seconds,
                    "evaluations": s.evaluations,
                    "converged": s.converged,
                    "levels": [
                        {
                            "similarity": -r.f,
                            "generations": r.generations,
                            "evaluations": r.evaluations,
                            "converged": r.converged,
                            "final_std": r.final_std,
                            "stop": {k: str(v) for k, v in r.stop.items()},
                        }
                        for r in s.levels
                    ],
                }
                for s in self.stages
            ],
        }


def level_models(ct_hu: Volume, labels: NDArray, factors: Sequence[int]) -> list[dict]:
    """Bone models for each pyramid level (sample spacing ``SAMPLE_MM_PER_FACTOR`` x factor).

    Build once per CT and pass to :func:`register_multibody` (``models=``) for every frame.
    """
    return [bone_models(ct_hu, labels, sample_mm=SAMPLE_MM_PER_FACTOR * f) for f in factors]


def _blurred(image: NDArray, factor: int, models: dict[str, PointModel], P: NDArray) -> NDArray:
    """Radiograph at a pyramid level, blurred like the DRR (tent of one sample spacing)."""
    from scipy.ndimage import gaussian_filter

    img = downsample_image(image, factor)
    spacing = max(m.spacing for m in models.values())
    K = pj.decompose_projection(P).intrinsics
    depth = float(np.median(pj.depth(P, next(iter(models.values())).points[::50])))
    px = spacing * K[0, 0] / depth  # sample spacing in pixels at the bones' depth
    sigma = 0.4 * max(px, 1.0)  # a tent of half-width r has sd r / sqrt(6)
    return gaussian_filter(img, sigma, mode="nearest")


def _pose_disagreement(
    T_a: NDArray, T_b: NDArray, model: PointModel, projections: Sequence[NDArray], spacing
) -> tuple[float, float]:
    """How far apart two poses of one bone are: (mm at its centroid, degrees).

    With one view, depth is not fixed by the image, so the distance is where the bone projects
    instead: the median distance of its samples at the detector (mm; rotations show in it too)
    and 0 degrees.
    """
    if len(projections) == 1:
        pts = model.points[::7]
        P = projections[0]
        duv = pj.project(P, tf.apply(T_a, pts)) - pj.project(P, tf.apply(T_b, pts))
        dr, dc = spacing[0]
        return float(np.median(np.linalg.norm(duv * [dc, dr], axis=1))), 0.0
    c = model.centroid[None]
    D = T_b @ tf.invert(T_a)
    return (
        float(np.linalg.norm(tf.apply(T_a, c) - tf.apply(T_b, c))),
        float(np.rad2deg(np.linalg.norm(tf.rotvec_from_matrix(D[:3, :3])))),
    )


def register_multibody(
    ct_hu: Volume,
    labels: ArrayLike,
    views: RegistrationViews,
    *,
    init_poses: dict[str, ArrayLike] | None = None,
    seed: int = 0,
    settings: RegistrationSettings | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    models: list[dict[str, PointModel]] | None = None,
    dislocated: str | None = None,
) -> MultiBodyResult:
    """Register the sacrum and both innominate bones of a CT to one or more radiographs.

    Parameters
    ----------
    ct_hu : Volume
        Preoperative CT (HU); each bone's ``ct`` frame is this volume's world frame.
    labels : (ni, nj, nk) int
        Label map (1 sacrum, 2 left, 3 right innominate) on the CT grid.
    views : RegistrationViews
    init_poses : dict bone -> (4, 4), optional
        Starting ``world_from_ct`` (default identity: the CT placed at its nominal pose).
    seed : int
    settings : RegistrationSettings, optional
    progress : callable(stage, generation, max_generations), optional
    models : per-level bone models, optional (reuse across frames)
    dislocated : str, optional
        The dislocated bone (from the plan): stage 1 then registers the other bones as one rigid
        body (a rigid fit of the whole pelvis can lock onto the dislocated bone instead: 1 of 20
        simulated cases), the dislocated bone gets the full stage-2 search box and goes first in
        each sweep, the others get ``stage2_range_attached``.

    Raises
    ------
    ValueError
        Label map and CT mismatch, a missing bone, ``dof=9`` with several views, bad images.
    """
    t_start = time.perf_counter()
    cfg = settings or RegistrationSettings()
    lab = np.asarray(labels)
    if cfg.dof == 9 and len(views.images) != 1:
        raise ValueError(f"9-DoF registration takes exactly one view, got {len(views.images)}")
    if models is None:
        models = level_models(ct_hu, lab, cfg.factors)
    bones = list(models[0])
    init = {b: np.eye(4) for b in bones}
    for b, T in (init_poses or {}).items():
        if b not in init:
            raise ValueError(f"unknown bone {b!r} in the initial poses")
        init[b] = np.asarray(T, dtype=np.float64)
        tf.se3_log(init[b])
    first = cfg.stage1_bone
    if dislocated is not None and dislocated not in bones:
        raise ValueError(f"unknown dislocated bone {dislocated!r}; expected one of {bones}")
    if first != "pelvis" and first not in bones:
        raise ValueError(f"unknown stage-1 body {first!r}; expected 'pelvis' or one of {bones}")
    body = bones if first == "pelvis" else [first]
    if first == "pelvis" and dislocated is not None:
        body = [b for b in bones if b != dislocated]  # the bones that moved together
    centroids = {b: models[-1][b].centroid for b in bones}
    masses = {b: models[-1][b].mass.sum() for b in bones}
    centroids["pelvis"] = sum(masses[b] * centroids[b] for b in body) / sum(masses[b] for b in body)
    levels = []
    for lv, f in enumerate(cfg.factors):
        Ps = np.stack([downsample_projection(P, f) for P in views.projections])
        imgs = [_blurred(img, f, models[lv], P) for img, P in zip(views.images, Ps, strict=True)]
        metric = GradientOrientation if cfg.metrics[lv] == "go" else GradientNCC
        levels.append((Ps, [metric(i) for i in imgs], imgs[0].shape))

    def score(gos, drrs):
        return sum(go(drrs[:, k]) for k, go in enumerate(gos))

    # ---- stage 1: the pelvis as one rigid body, or one bone
    t0 = time.perf_counter()
    T1 = init[body[0]]
    c1 = tf.apply(T1, centroids[first][None])[0]
    Ps_final = tuple(views.projections)
    x = np.zeros(cfg.dof)
    nine = None
    if cfg.dof == 9:
        rows, cols = views.shape
        nine = pj.nine_dof_from_projection(
            views.projections[0], rows=rows, cols=cols, pixel_spacing=views.pixel_spacing[0]
        )
    stage1_levels = []

    def stage1_geometry(X: NDArray, factor: int) -> tuple[NDArray, NDArray]:
        poses = pj.six_dof_pose(X[:, :6], center=c1) @ T1
        if nine is None:
            return poses, None
        rows, cols = views.shape
        s0 = np.asarray(nine.source_in_detector)
        Ps = np.stack(
            [
                downsample_projection(
                    pj.projection_from_nine_dof(
                        pj.NineDof(tuple(s0 + xi[6:]), nine.world_from_detector),
                        rows=rows,
                        cols=cols,
                        pixel_spacing=views.pixel_spacing[0],
                    ),
                    factor,
                )
                for xi in X
            ]
        )[:, None]
        return poses, Ps

    # the bones' initial poses relative to the pelvis body move with it
    rel = [tf.invert(T1) @ init[b] for b in body] if first == "pelvis" else [np.eye(4)]
    t_max, r_max = cfg.stage1_range
    box = np.array([t_max] * 3 + [r_max] * 3 + ([80.0] * 3 if cfg.dof == 9 else []))
    for lv, f in enumerate(cfg.factors):
        if cfg.max_generations_stage1[lv] == 0:
            continue
        Ps, gos, shape = levels[lv]
        m = [models[lv][b] for b in body]

        def objective(X, Ps=Ps, gos=gos, shape=shape, m=m, f=f):
            poses, P_cand = stage1_geometry(X, f)
            stack = np.stack([poses @ R for R in rel], axis=1)
            drrs = splat(m, stack, Ps if P_cand is None else P_cand, shape)
            return -score(gos, drrs)

        res = minimize_cmaes(
            objective,
            x,
            sigma=cfg.sigmas[lv],
            population=cfg.populations[lv],
            seed=seed + lv,
            max_generations=cfg.max_generations_stage1[lv],
            # source position (mm) moves the image less than the pose: larger steps
            scales=None if nine is None else [1.0] * 6 + [5.0] * 3,
            bounds=(-box, box),
        )
        stage1_levels.append(res)
        x = res.x
        if progress:
            progress("stage 1", lv + 1, len(cfg.factors))
    pose1, P1 = stage1_geometry(x[None], 1)
    if P1 is not None:
        Ps_final = (pj.normalize_projection(P1[0, 0]),)
        # later levels use the refined geometry
        levels = [
            (
                np.stack([downsample_projection(Ps_final[0], f)]),
                gos,
                shape,
            )
            for (_, gos, shape), f in zip(levels, cfg.factors, strict=True)
        ]
    stages = [StageResult("stage 1", stage1_levels, time.perf_counter() - t0)]
    # every bone starts where stage 1 put the body (they share the set-up error)
    delta = pose1[0] @ tf.invert(T1)
    poses = {b: delta @ init[b] for b in bones}

    # ---- stage 2: all bones
    if cfg.stage2:
        t0 = time.perf_counter()
        base = np.stack([poses[b] for b in bones])
        centres = [tf.apply(base[i], centroids[b][None])[0] for i, b in enumerate(bones)]
        y = np.zeros(6 * len(bones))

        def stage2_poses(Y: NDArray) -> NDArray:
            out = np.empty((len(Y), len(bones), 4, 4))
            for i in range(len(bones)):
                out[:, i] = pj.six_dof_pose(Y[:, 6 * i : 6 * i + 6], center=centres[i]) @ base[i]
            return out

        searched = [lv for lv in range(len(cfg.factors)) if cfg.max_generations_stage2[lv] > 0]
        fine = searched[-1] if searched else 0
        n_views = len(views.images)

        def with_block(y: NDArray, i: int, x: NDArray) -> NDArray:
            """``y`` with bone ``i``'s 6 parameters replaced by ``x`` (a copy)."""
            out = y.copy()
            out[6 * i : 6 * i + 6] = x
            return out

        def block_objective(i, y, lv, regularised=False):
            """Bone ``i``'s 6-DoF objective at level ``lv`` over the others' fixed DRR at ``y``
            (``regularised``: with the coarse-level rotation prior)."""
            weight = cfg.coarse_rotation_prior * n_views if regularised and lv != fine else 0.0
            Ps, gos, shape = levels[lv]
            m = [models[lv][b] for b in bones]
            others = [j for j in range(len(bones)) if j != i]
            current = stage2_poses(y[None])
            background = splat([m[j] for j in others], current[:, others], Ps, shape)

            def objective_i(X):
                T = pj.six_dof_pose(X, center=centres[i]) @ base[i]
                drrs = splat([m[i]], T[:, None], Ps, shape) + background
                return weight * np.sum(X[:, 3:] ** 2, axis=1) - score(gos, drrs)

            return objective_i

        def block_search(i, y, lv, x0, sweep, seed_i, regularised=False):
            """One bone's 6 DoF at level ``lv`` over the fixed DRR of the others (at ``y``)."""
            held = dislocated is not None and bones[i] != dislocated  # near the body (plan)
            t_i, r_i = cfg.stage2_range_attached if held else cfg.stage2_range
            box = np.array([t_i] * 3 + [r_i] * 3)
            return minimize_cmaes(
                block_objective(i, y, lv, regularised),
                x0,
                sigma=cfg.sigmas[lv] / (1 + sweep),
                population=cfg.stage2_populations[lv],
                seed=seed_i,
                max_generations=cfg.max_generations_stage2[lv],
                bounds=(-box, box),
            )

        order = list(range(len(bones)))  # sweep order: the dislocated bone first
        if dislocated is not None:
            order.sort(key=lambda j: bones[j] != dislocated)
        stage2_levels = []
        disagreement: dict[str, float] = {}
        restart_runs: list[CMAESResult] = []
        ambiguous: list[str] = []
        t_max, r_max = cfg.stage2_range
        for lv in range(len(cfg.factors)):
            if cfg.max_generations_stage2[lv] == 0:
                continue
            if cfg.stage2_mode == "joint":
                Ps, gos, shape = levels[lv]
                m = [models[lv][b] for b in bones]

                def objective2(Y, Ps=Ps, gos=gos, shape=shape, m=m):
                    return -score(gos, splat(m, stage2_poses(Y), Ps, shape))

                box2 = np.tile([t_max] * 3 + [r_max] * 3, len(bones))
                res = minimize_cmaes(
                    objective2,
                    y,
                    sigma=cfg.sigmas[lv],
                    population=cfg.stage2_populations[lv],
                    seed=seed + 100 + lv,
                    max_generations=cfg.max_generations_stage2[lv],
                    bounds=(-box2, box2),
                )
                stage2_levels.append(res)
                y = res.x
            else:  # block coordinates: one bone at a time over the others' fixed DRR
                for sweep in range(cfg.stage2_sweeps):
                    for i in order:
                        res = block_search(i, y, lv, y[6 * i : 6 * i + 6], sweep,
                                           seed + 100 + 10 * lv + 3 * sweep + i)  # fmt: skip
                        stage2_levels.append(res)
                        y = with_block(y, i, res.x)
            if progress:
                progress("stage 2", lv + 1, len(cfg.factors))
        # independent re-searches: a second answer that disagrees means the images do not pin
        # the bone down (a local optimum of one of the runs); keep the better fine score, flag it
        check = [bones.index(dislocated)] if dislocated is not None else range(len(bones))
        restarts = cfg.stage2_restarts
        if restarts is None:
            restarts = 2 if n_views == 1 else 1
        if cfg.stage2_mode != "sweep" or not searched:
            restarts = 0
        for r in range(restarts):
            for i in check:
                sl = slice(6 * i, 6 * i + 6)
                x_alt = np.zeros(6)  # the stage-1 pose
                for lv in searched:
                    seed_r = seed + 1000 * (r + 1) + 10 * lv + i
                    res = block_search(i, with_block(y, i, x_alt), lv, x_alt, 0, seed_r,
                                       regularised=r % 2 == 0)  # fmt: skip
                    restart_runs.append(res)
                    x_alt = res.x
                f_now = float(block_objective(i, y, fine)(y[None, sl])[0])
                T_now, T_alt = (
                    pj.six_dof_pose(v[None], center=centres[i])[0] @ base[i] for v in (y[sl], x_alt)
                )
                d_mm, d_deg = _pose_disagreement(
                    T_now, T_alt, models[fine][bones[i]], Ps_final, views.pixel_spacing
                )
                disagreement[bones[i]] = max(disagreement.get(bones[i], 0.0), d_mm)
                apart = d_mm > cfg.ambiguity[0] or d_deg > cfg.ambiguity[1]
                if res.f < f_now:
                    y = with_block(y, i, x_alt)
                    if apart:  # another basin: the other bones were fitted over a wrong DRR
                        for j in order:
                            rj = block_search(j, y, fine, y[6 * j : 6 * j + 6], 1,
                                              seed + 2000 * (r + 1) + j)  # fmt: skip
                            restart_runs.append(rj)
                            y = with_block(y, j, rj.x)
                if apart and abs(res.f - f_now) < cfg.ambiguity_score:  # both answers fit
                    ambiguous.append(
                        f"two searches for {bones[i]} from the same start ended {d_mm:.1f} mm / "
                        f"{d_deg:.1f} deg apart with similarities within {cfg.ambiguity_score}: "
                        "the images do not pin its pose down"
                    )
        final = stage2_poses(y[None])[0]
        poses = {b: final[i] for i, b in enumerate(bones)}
        n_final = 1 if cfg.stage2_mode == "joint" else len(bones)
        stages.append(
            StageResult("stage 2", stage2_levels, time.perf_counter() - t0, n_final, restart_runs)
        )
    # final similarity: all bones at the finest level
    Ps, gos, shape = levels[-1]
    stack = np.stack([poses[b] for b in bones])[None]
    similarity = float(score(gos, splat([models[-1][b] for b in bones], stack, Ps, shape))[0])
    warnings = []
    converged = all(s.converged for s in stages)
    if not converged:
        warnings.append("a CMA-ES level hit its generation limit while still improving")
    if cfg.stage2 and ambiguous:
        converged = False
        warnings.extend(ambiguous)
    if similarity < cfg.min_similarity * len(views.images):
        converged = False
        warnings.append(f"final GO {similarity:.3f} is below {cfg.min_similarity} per view")
    return MultiBodyResult(
        poses=poses,
        projections=Ps_final,
        similarity=similarity,
        converged=converged,
        stages=stages,
        seconds=time.perf_counter() - t_start,
        stage1_bone=first,
        warnings=tuple(warnings),
        restart_disagreement=disagreement if cfg.stage2 else {},
    )
