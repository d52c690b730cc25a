"""Registration settings: one frozen block per stage and a shared pyramid block.

Defaults are the paper's (section 2.2: binning [4, 2], sigma [4, 1] mm and degrees, population
100) with the changes measured on simulated cases and documented per field: generation caps, a
stage-1 body of the whole pelvis, gradient NCC at the coarse level, block-coordinate stage 2 and an
independent re-search of the dislocated bone.

``RegistrationSettings()`` is a first registration; :meth:`RegistrationSettings.tracking` a later
frame started from the previous one. Blocks are replaced with :func:`dataclasses.replace`::

    s = RegistrationSettings()
    s = replace(s, stage2=replace(s.stage2, sweeps=3))
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = [
    "SAMPLE_MM_PER_FACTOR",
    "PyramidSettings",
    "RegistrationSettings",
    "ResearchSettings",
    "Stage1Settings",
    "Stage2Settings",
]

METRICS = ("go", "gncc")
MIN_SIMILARITY = {"go": 0.4, "gncc": 0.05}  # per view, see RegistrationSettings


# Bone model sample spacing per unit of pyramid binning (mm): 3 mm at 4x, 1.5 mm at 2x. The
# splatting cost grows as 1 / spacing; finer samples did not improve accuracy measurably. Here,
# not in `pyramid` (which re-exports it), so that the bone cache's key needs no scipy import.
SAMPLE_MM_PER_FACTOR = 0.75


@dataclass(frozen=True)
class PyramidSettings:
    """The levels both stages share, coarse to fine.

    Attributes
    ----------
    factors : per level, int
        Detector binning (bone models are sampled at 0.75 x factor mm).
    sigmas : per level, float
        Initial CMA-ES step (mm and degrees).
    metrics : per level, "go" or "gncc"
        Similarity. Default gradient NCC at the coarse level, GO (equation 10) at the fine
        level. GO everywhere is the paper's choice; on simulated cases its coarse-level peak stood
        only ~10% above its background (every strong-gradient pixel scores >= 0.29 whatever its
        orientation) and stage 1 locked onto magnified poses 30-50 mm off in depth in 3 of 20
        cases; gradient NCC has a sharp capture peak.
    blur : per level, float
        Standard deviation of the Gaussian each level's radiograph is blurred with, in DRR
        sample spacings at the bones' depth (0: none; :func:`pelvicnav.register.pyramid.blurred`).
        0.4 matches the splat's own blur. At the coarse level it smooths the objective; at the
        fine level it biased the optimum in depth (tracking from the truth, the benchmark case:
        0.32 / 0.43 / 0.30 mm with 0.4, 0.24 / 0.37 / 0.23 mm with 0, 0.39 / 0.51 / 0.34 mm
        with 0.6), so the fine level is not blurred: on 40 atlas cases (seed 107) medians in /
        out of plane 0.17 / 0.21 -> 0.15 / 0.15 mm (3D 0.27 -> 0.21), the same gross cases; on
        the 18 real-CT cases (seeds 101, 109, 113) the right hip out of plane 0.27 -> 0.17 mm.
    noise_blur, noise_ratio : float, (float, float)
        A noisy radiograph is blurred at every level by up to ``noise_blur`` sample spacings:
        that much where its noise-to-edge ratio
        (:func:`pelvicnav.register.pyramid.noise_to_edge`) reaches ``noise_ratio[1]``, none
        below ``noise_ratio[0]``, linear between (the level's ``blur`` if larger). Quantum
        noise at 50 uGy per frame (the studies' dose) scores 0.24-0.29, at 5 uGy about 0.9, at
        2 uGy about 1.8. Unblurred at 2 and 1 uGy, the worst fiducial of two simulated patients
        ended 3.5-6.1 and 0.8-9.8 mm off (three of four flagged); blurred 0.4, 1.2-1.4 and
        2.9-3.2 mm. At 5 and 10 uGy the unblurred fine level was as good or better (median
        TRE 0.15-0.36 against 0.18-0.58 mm).
    """

    factors: tuple[int, ...] = (4, 2)
    sigmas: tuple[float, ...] = (4.0, 1.0)
    metrics: tuple[str, ...] = ("gncc", "go")
    blur: tuple[float, ...] = (0.4, 0.0)
    noise_blur: float = 0.4
    noise_ratio: tuple[float, float] = (0.75, 1.5)

    def __post_init__(self) -> None:
        if not self.factors or any(int(f) != f or f < 1 for f in self.factors):
            raise ValueError(f"pyramid factors must be positive integers, got {self.factors}")
        if any(m not in METRICS for m in self.metrics):
            raise ValueError(f"metrics must be 'go' or 'gncc', got {self.metrics}")
        if any(s <= 0 for s in self.sigmas):
            raise ValueError(f"sigmas must be positive, got {self.sigmas}")
        if any(not b >= 0 for b in self.blur) or not self.noise_blur >= 0:
            raise ValueError(f"blur must be >= 0, got {self.blur} and {self.noise_blur}")
        if not 0 <= self.noise_ratio[0] < self.noise_ratio[1]:
            raise ValueError(f"noise_ratio must be increasing and >= 0, got {self.noise_ratio}")
        if not len(self.sigmas) == len(self.metrics) == len(self.factors) == len(self.blur):
            raise ValueError("pyramid settings need one value per level in every field")

    @property
    def n_levels(self) -> int:
        return len(self.factors)


@dataclass(frozen=True)
class Stage1Settings:
    """Stage 1: one rigid body against the views (section 2.2.1).

    Attributes
    ----------
    dof : 6 or 9
        6: the body's pose with every ``P`` known; 9 (exactly one view): pose and source position
        in detector coordinates (equation 11a).
    body : str
        ``"pelvis"`` (default: all bones moving as one rigid body; with a plan, all but the
        dislocated bone) or one bone name (the paper's choice). A single bone's DRR covers a small
        part of the image, and GO then rewards poses that enlarge its edge footprint; on
        simulated cases single-bone stage 1 locked onto bones turned by 80-90 degrees. The whole
        pelvis fills the image and has no such bias; stage 2 resolves the inter-bone motion.
    populations, max_generations : per level
        0 generations skips the level (by default stage 1 runs on the coarse level only: stage 2
        refines every bone at the fine level anyway).
    sigmas : per level, optional
        Initial CMA-ES step of stage 1 (None: the pyramid's). ``RegistrationSettings()`` uses 8
        at the coarse level (6 DoF; the pyramid's 4 is the paper's): with 4, a 19.6 mm set-up
        error ended in a local optimum (gradient NCC 0.69 against 1.09 at the truth) in 2 of 2
        seeds and two bones 6 and 17 mm off, unflagged; with 8 both seeds found it.
    search_range : (mm, deg)
        Search box around the start (set-up error up to 20 mm / 5 deg).
    recentre : int
        When a run ends at the edge of its box (a pose parameter within 10% of it: the answer
        lies beyond), the box is re-centred on that answer and the level searched again, up to
        this many times. With the box alone a start turned 20 deg out of plane ended with the
        body turned the box's 10 deg and bones 3-6 mm off (capture range +-10 deg).
    rescue_turn_deg : float
        Out-of-plane turn of the extra stage-1 starts: the registration's start turned by this
        much either way about the first view's detector axes. When the first guess is taken
        they are tried at once with the guess and the unguessed start; otherwise only when the
        registration ends flagged (see :mod:`pelvicnav.register.multibody`), and the better
        result is kept. 0: neither.
    rescue_margin : float
        Fine-level similarity (summed over the views) by which a rescued answer that keeps the
        pelvis where the first attempt had it must beat the first attempt to clear its flag
        (:func:`pelvicnav.register.multibody._rescue`). Such a rescue has only searched the
        dislocated bone again. Seeds 127 and 131: five hips 13-47 mm off, flagged in the first
        attempt, came back from the rescue 0.001-0.011 better and unflagged; seed 137 case 33,
        a hip 0.06 mm off, came back 0.037 better (its first attempt flagged for two answers
        3.9 mm apart at equal scores).
    probe_mm, probe_sigma, probe_population, probe_generations : float, float, int, int
        A lone stage-1 run (no first guess taken) is probed: two short runs (this initial step,
        population and generation budget on the levels stage 1 searches) from its answer shifted
        +-``probe_mm``
        along the views' mean beam direction, the depth that views a few tens of degrees apart
        see least (AP and oblique 30: a 20 mm error in depth is 10 mm in the oblique view).
        When a probe ends elsewhere and scores better, a full stage-1 run from its answer goes
        on as another run, and the best answer is kept. Seed 193 case 0: the lone run stopped
        with the pelvis 20.9 mm off in depth (stage-1 objective -0.662) and passed unflagged;
        the +20 mm probe ended 2.4 mm from the truth at -0.733 (the truth: -0.781). About 0.4 s
        per probe (population 30, 12 generations missed it). Two or more views, 6 DoF only
        (one view's depth is its magnification, which the 9-DoF source position also moves).
        ``probe_mm`` 0 switches it off.
    source_range_mm : float
        9 DoF: search box of the source position in detector coordinates.
    initial_search_mm : float
        Before stage 1, the body's translation from a 2D correlation of its DRR with every
        view over shifts up to this many mm (:mod:`pelvicnav.register.initial`); 0 skips it.
        On one simulated patient (capture-range cases) starts 100-150 mm off along each
        C-arm axis all ended within 0.9 mm (without it: +-25 mm was the capture range).
    initial_turn_deg : (in plane, out of plane), degrees
        With ``initial_search_mm``: the body also turned, in 10 deg steps up to these, about
        the first view's beam and then about its detector axes, the turn whose best shifts
        correlate best kept (0: no turn searched). Default: +-60 deg in plane; the
        out-of-plane search was tried (+-30 deg) and failed on 5 of 8 starts turned 30-50 deg.
    initial_min_mm, initial_min_deg : float
        The first guess is taken only when it moves the body's centre at least this far or
        turns it at least this much; otherwise stage 1 starts where it would have (its box
        reaches +-40 mm / +-10 deg). On the development study (seed 31, set-up errors up to
        20 mm) the guess brought 5 of 8 starts from 12-21 mm to within 1-4 mm of the truth, but
        moved the two whose stage-1 objective prefers a wrong pose 36-64 mm off; used
        everywhere it left 5 registrations of 40 gross (2 unflagged) against 3. When it is
        taken, stage 1 also runs from the unguessed start and from that start turned out of
        plane (``rescue_turn_deg``), and the best stage-1 answer goes on (starts turned 30 deg
        out of plane were guessed 50-170 mm off).
    """

    dof: int = 6
    body: str = "pelvis"
    populations: tuple[int, ...] = (100, 100)
    max_generations: tuple[int, ...] = (25, 0)
    sigmas: tuple[float, ...] | None = None
    search_range: tuple[float, float] = (40.0, 10.0)
    recentre: int = 3
    rescue_turn_deg: float = 20.0
    rescue_margin: float = 0.02
    probe_mm: float = 20.0
    probe_sigma: float = 4.0
    probe_population: int = 50
    probe_generations: int = 15
    source_range_mm: float = 80.0
    initial_search_mm: float = 200.0
    initial_turn_deg: tuple[float, float] = (60.0, 0.0)
    initial_min_mm: float = 25.0
    initial_min_deg: float = 15.0

    def __post_init__(self) -> None:
        if self.dof not in (6, 9):
            raise ValueError(f"dof must be 6 or 9, got {self.dof}")
        if self.recentre < 0:
            raise ValueError(f"recentre must be >= 0, got {self.recentre}")
        if not self.rescue_margin >= 0:
            raise ValueError(f"rescue_margin must be >= 0, got {self.rescue_margin}")
        if not (self.probe_mm >= 0 and self.probe_sigma > 0 and self.probe_population >= 2
                and self.probe_generations >= 1):  # fmt: skip
            raise ValueError(
                "probe_mm must be >= 0, probe_sigma > 0, probe_population >= 2 and "
                f"probe_generations >= 1, got {self.probe_mm}, {self.probe_sigma}, "
                f"{self.probe_population} and {self.probe_generations}"
            )


@dataclass(frozen=True)
class Stage2Settings:
    """Stage 2: the 6-DoF pose of every bone from the stage-1 pose (equation 12).

    Attributes
    ----------
    enabled : bool
        Run stage 2 (else every bone takes the stage-1 pose).
    mode : "sweep", "joint", "local" or "gradient"
        ``"joint"``: one CMA-ES over all 6 x L parameters (the paper). ``"sweep"`` (default):
        block coordinates, each bone's 6 DoF in turn over the fixed DRR of the others, ``sweeps``
        sweeps per level (sigma halved on the second). DRRs add, so a candidate renders one bone
        instead of all: on simulated cases 3-4x faster at the same accuracy. ``"local"``: the
        sweeps with a finite-difference local refinement (:mod:`pelvicnav.register.local`) at
        every level. ``"gradient"``: every level refined by L-BFGS on gradient NCC with its exact
        gradient, all bones at once (:mod:`pelvicnav.register.gradient`; a later frame, see
        :meth:`RegistrationSettings.tracking`). ``max_generations`` caps a local refinement's
        iterations; ``gradient_iterations`` a gradient refinement's.
    fine : "cmaes", "local" or "gradient"
        The search of the finest searched level in the sweeps and the re-search. Default
        ``"gradient"``: all bones refined at once by L-BFGS on gradient NCC (one run of ~50
        evaluations instead of 2 sweeps x 3 bones x 400 CMA-ES candidates of GO; on an atlas
        case the first registration took 3.4-3.7 s instead of 6.9-7.3 s, every bone within
        0.1-0.34 mm against 0.1-0.43). A renderer without an adjoint (ray casting) falls back
        to CMA-ES.
    sweeps : int
    populations : per level
        Population of each problem (default 30 and 20: the paper's 100 is for its 18-DoF joint
        problem; the 6-DoF block problems converge with fewer candidates per generation).
    max_generations : per level (0 skips the level)
    attached : "gradient" or "cmaes"
        With a plan, how the bones it says are not dislocated are fitted at the searched
        (non-gradient) levels: ``"gradient"`` (default) — each sweep searches the dislocated
        bone by CMA-ES, then refines every bone at once by gradient; ``"cmaes"`` — each bone
        searched in turn. The attached bones moved with the pelvis in stage 1.
    gradient_iterations : int
        L-BFGS iterations of a gradient refinement (its tolerance stops it first: 15-30 on
        simulated cases). 100 (was 50): seed 107 case 20, good (bones within 0.61 mm), was
        flagged for its fine-level refinement at 50 iterations still improving; it stops on its
        tolerance at 55.
    gradient_tol : float
        Relative change of the objective that stops a gradient refinement at the finest level
        (10x this at coarser levels, which only bring the bones into the fine level's basin).
        On the benchmark's tracking frames 1e-6 gave the errors of 1e-7 (0.17-0.44 mm) with
        about 15% fewer evaluations.
    search_range : (mm, deg)
        Box around the stage-1 pose (dislocation up to 20 mm / 10 deg on top of stage 1).
    range_attached : (mm, deg)
        Box of the bones the plan says are not dislocated (they moved with the pelvis in stage 1,
        up to the few mm the dislocated bone biased it).
    recentre : int
        Sweep mode with a plan: when a bone of the pelvis ends at the edge of its
        ``range_attached`` box (the answer lies beyond it: stage 1 misplaced the pelvis), stage 2
        runs again from its answer, its boxes centred there, up to this many times; a bone
        still at the edge flags the result (``multibody._edges``). Seed 373 case 16: a lone
        stage-1 run left the pelvis 11 mm off and stage 2 stopped the sacrum and right hip at
        the box's 4 deg, 2.6-5.3 mm / 7 deg off, unflagged; once more, 1.0-2.4 mm and still at
        the edge; with 3 (the default, as stage 1's), 0.3-0.5 mm and converged.
    joint_prior : float
        Weight (per view) of the joint-aware prior's interpenetration term on the plan's
        dislocated bone: the fraction of its joint samples inside another bone is taken off the
        similarity (:mod:`pelvicnav.register.prior`). Off by default, as is ``joint_gap``: with
        both on (0.1 and (0.001, 20)) the out-of-plane capture test's hip ended 1.69 mm off
        against its 1.5 mm limit, and the prior changes which basin a half-visible hip's search
        falls into (seed 127: gross hips 4 -> 1, but in one variant a hip 10 mm off unflagged);
        measured on seed 127 only in its final form (session 18, docs/registration.md). Seed
        157 (session 19): 1 gross registration with both on (a hip 12.2 mm off, flagged), 0
        without; what the joints say is read by the judgement instead
        (``ResearchSettings.joint_limits``).
    joint_gap : (per mm, mm)
        The prior's gap term: weight (per view, per mm) and slack. The 90th percentile of the
        joint samples' distances to the other bones may exceed the CT's by the slack; each mm
        beyond costs the weight. Default (0, 20): off. The slack is the largest opening a
        dislocation of up to 20 mm gives (the studies' open-book dislocations opened it by 8.4 mm
        median, 17.3 mm at most over 280 cases), so the truth is never penalised; on the
        half-visible hips of the simulated studies (13-35 % of the hip in a view) wrong answers
        8-47 mm off scored as well as the truth, or better by up to 0.006, and opened it 15-48
        mm. A 12 mm slack penalised true poses that opened further and left two wrong hips
        unflagged (seeds 127 and 131). ``(0, 0)`` turns the term off.
    rejoin : (mm, deg) or None
        With a plan and a gradient-refined finest level (searching, not tracking): a bone the
        plan does not name that ended further than this from another such bone's pose (mm at
        its centroid, degrees; in the CT's frame they move as one) is tried at that pose and
        every bone refined from there; the images keep the better
        (:func:`~pelvicnav.register.stage2.rejoined`). None: not tried.
    """

    enabled: bool = True
    mode: str = "sweep"
    sweeps: int = 2
    populations: tuple[int, ...] = (30, 20)
    max_generations: tuple[int, ...] = (30, 20)
    search_range: tuple[float, float] = (25.0, 12.0)
    range_attached: tuple[float, float] = (8.0, 4.0)
    recentre: int = 3
    joint_prior: float = 0.0
    joint_gap: tuple[float, float] = (0.0, 20.0)
    fine: str = "gradient"
    attached: str = "gradient"
    gradient_iterations: int = 100
    gradient_tol: float = 1e-6
    rejoin: tuple[float, float] | None = (1.0, 1.0)

    def __post_init__(self) -> None:
        if self.rejoin is not None and (len(self.rejoin) != 2 or not min(self.rejoin) > 0):
            raise ValueError(f"rejoin must be (mm, deg) > 0 or None, got {self.rejoin}")
        if not self.joint_prior >= 0:
            raise ValueError(f"joint_prior must be >= 0, got {self.joint_prior}")
        if len(self.joint_gap) != 2 or not min(self.joint_gap) >= 0:
            raise ValueError(f"joint_gap must be (weight, slack_mm) >= 0, got {self.joint_gap}")
        if self.fine not in ("cmaes", "local", "gradient"):
            raise ValueError(
                f"stage-2 fine must be 'cmaes', 'local' or 'gradient', got {self.fine!r}"
            )
        if self.mode not in ("joint", "sweep", "local", "gradient"):
            raise ValueError(
                f"stage-2 mode must be 'joint', 'sweep', 'local' or 'gradient', got {self.mode!r}"
            )
        if self.attached not in ("cmaes", "gradient"):
            raise ValueError(
                f"stage-2 attached must be 'cmaes' or 'gradient', got {self.attached!r}"
            )
        if self.sweeps < 1:
            raise ValueError(f"stage-2 sweeps must be >= 1, got {self.sweeps}")


@dataclass(frozen=True)
class ResearchSettings:
    """The independent re-search of the dislocated bone after the stage-2 sweeps.

    Attributes
    ----------
    restarts : int, optional
        Re-searches from the bone's stage-1 pose with other seeds (every bone without a plan);
        the first (and every odd one) with the ``coarse_rotation_prior``, the second without.
        Default (None): 1 with two or more views, 2 with one view (one view leaves a dislocated
        bone several optima: on 10 single-view 9-DoF cases the largest PDE fell from 3.4 to
        1.9 mm). The better fine-level score wins; two answers further apart than ``ambiguity``
        (mm at the centroid, degrees) whose similarities differ by less than ``ambiguity_score``
        flag the registration (the images leave the pose ambiguous). A re-search that ends
        clearly worse is a failed restart, not an ambiguity. Sweep mode only.
    fine : "cmaes" or "stage2"
        The re-search's finest level: ``"cmaes"`` (default) searches the bone by CMA-ES on
        GO whatever stage 2 does there; ``"stage2"`` as stage 2 does (the gradient refinement
        by default). Gradient NCC and GO can have their fine-level optima in different places
        when a hip is half out of the views (study seed 31, case 33: the gradient answer 7.6 mm
        off, GO's near the truth), so the re-search looks with the other metric.
    single_view_flag_mm : float
        With one view, a re-search that ends more than this far from the answer (median distance
        of the bone's samples at the detector) flags the result whatever the scores (this
        replaces the ``ambiguity`` rule, which flagged a good real-CT case 2.8 mm apart): on 12
        single-view 9-DoF atlas cases (seed 7) the re-searches of the 9 good registrations
        ended <= 1.4 mm away, of the 3 gross ones 2 ended 7.9 and 39.9 mm away (6 real-CT cases:
        <= 2.8 mm, all good).
    ambiguity : (mm, deg)
        Answers closer than this are one answer. 3 mm / 3 deg (was 2 / 2 until session 15: seed
        89 case 13, a good registration with every bone within 0.4 mm, was flagged for two
        answers 2.2 mm / 2.3 deg apart). The ambiguous gross registrations seen had answers
        10.8-26.7 mm apart; closer than 3 mm, either answer is within what the flag's 4 mm
        gross error is about.
    ambiguity_score : float
        Fine-level GO (summed over the views) within which two answers are equally good.
        Tried 0.03 with the gradient refinement (study seed 31): it flagged all 3 gross
        registrations of 40 but 4 of its 7 flags were good registrations (two answers 4-10 mm
        apart within 0.006-0.020: the images do not decide); 0.01 flags 2 of the 3 and the
        third falls under ``min_similarity``. 0.005 was tried in session 21: on the eight
        seeds of session 20 it kept every gross registration flagged and cleared three good
        ones (their answers 0.006-0.010 apart), but on a fresh seed (193, case 13) it left a
        hip 18.3 mm off unflagged whose two answers were 0.006 apart.
    retry_mm : float
        With two or more views, a re-search that ends more than this far from the answer (mm
        at the detector) and scores worse earns one more re-search (another seed, the other
        prior setting); if that one too ends this far away and loses, the registration is
        flagged: the answer's basin was found by one search and missed by two. On the study
        with seed 61 (20 atlas cases) the re-searches of good registrations ended 0.07-0.69 mm
        away (one, ambiguous and flagged, 5.9 mm); the one gross registration (the hip 27 mm
        off in depth, unflagged) had its re-search end 13.5 mm away, scoring worse, while the
        truth scored better than the answer (GO 0.946 against 0.936).
    confirm_margin : float
        A re-search that ends more than ``retry_mm`` away and wins by less than this (fine-level
        GO summed over the views) replaces the answer but counts like one that lost: it earns
        one more re-search, and if that one ends far from it too, the new answer was found once
        and the registration is flagged. Seed 137 case 16: the hip's sweeps and its re-search
        ended 14.4 mm apart, the re-search winning by 0.011; its answer was 17.5 mm off,
        unflagged (the truth scored 0.016 better than it, at both levels). One that wins by
        this or more replaces the answer as well, and since session 26 it too is confirmed:
        the sweeps' answer was a wrong basin, so the new one must be found twice (one more
        re-search; one more again if that one replaces it too; then flagged "found once").
        Seed 3 case 15: the sweeps' hip 22.6 mm off, a re-search's 21.4 mm off winning by
        0.038, unflagged; the confirming search ended 29.6 mm away, and the fine-level
        search the question then earns found the truth (0.2 mm, flagged).
    ray_mm, ray_min_mm, ray_margin : float
        With two or more views and at least one re-search: the bone is moved along each view's
        ray (source to its centroid) up to ``ray_mm`` either way in 2 mm steps and scored at the
        coarsest level, the others fixed; the best local optimum at least ``ray_min_mm`` away
        that scores within ``ray_margin`` of the answer starts one more search (half the step),
        judged like a re-search (better wins; far and equally good flags). A move along a ray
        keeps the bone's outline in that view, and a hip that the other view shows little of
        had two places on it: on study seed 83, case 22, the left hip (27 % and 45 % inside the
        two views) ended 28.4 mm off along the AP ray, unflagged (GO 1.020 against 1.050 at the
        truth); the re-searches from the stage-1 pose found the truth in 1 of 4 seeds, while
        the ray showed its optimum 28 mm away at a better coarse score. 0 switches it off.
    turn_deg, turn_shift_mm : float
        With two or more views and at least one re-search: the bone is also turned by
        ``turn_deg`` either way about each world axis through its centroid, each turn with the
        best of a 3 x 3 x 3 grid of shifts ``turn_shift_mm`` apart, scored at the coarsest level;
        the best turn inside the search box that scores within ``ray_margin`` of the answer
        starts one more search, judged like a re-search. On study seed 107, case 26, the left
        hip ended 20 deg turned about the body's long axis (5.0 mm at its centroid), unflagged:
        the sweeps, the re-search (1.3 mm away) and the rays all kept to that basin although
        the truth scored better (coarse 1.31 against 1.22, fine GO 1.146 against 1.072); the
        20 deg turn about z with the best shift scored 1.229. 0 switches it off.
    coarse_rotation_prior : float
        At every level but the finest, ``coarse_rotation_prior x K x |r|^2`` is taken off the
        similarity of the bone rotated by ``|r|`` degrees from its stage-1 pose (K views). A bone
        about half out of the field of view leaves the coarse levels a valley of nearly equal
        similarity along which it can turn 10-15 degrees; the prior takes the least-turned end of
        it. The finest level is not regularised and picks between the answers; when the
        re-search wins from another basin, every bone gets one more fine-level pass over the
        corrected DRRs. 0 switches it off.
    joint_limits : (fraction, mm) or None
        What a dislocation can do to the dislocated bone's joints (its joint samples, see
        :mod:`pelvicnav.register.prior`): at most ``fraction`` of them inside another bone
        (nearer than 1 mm to its samples), and their gap (90th percentile of their distances to
        the other bones) at most ``mm`` wider than in the CT. Only the judgement reads it (the
        search does not: ``Stage2Settings.joint_prior`` and ``joint_gap`` put such a prior into
        the objective; off):

        * a kept answer beyond either limit flags the registration. Study seeds 131, 139 and
          151: the 5 gross hips (7.8-47 mm off) opened the gap 24-40 mm; the good answers of
          seeds 127, 137, 139 and 149 at most 16 mm, with up to 4 % of their samples inside
          (an open-book dislocation closes the joint at its hinge);
        * an ambiguity (or an answer found once) whose other answer is beyond the limits is a
          *doubt*: it flags the first attempt and so calls the rescue, whose second attempt
          from other stage-1 starts settles it when it ends at the same answer with nothing in
          doubt (``register.multibody._confirmed``; seeds 137 case 25 and 139 case 4, good,
          confirmed so; 139 case 4 was flagged before). A doubt the rescue does not settle
          stays a flag.

        Default (0.2, 20): the studies' dislocations open the gap by 17.3 mm at most (280
        cases, ``scripts/measure_joint_opening.py``). The percentile is read over up to
        ``prior.MEASURED_POINTS`` joint samples: over a random 200 of them it moved by up to
        8 mm (seed 151 case 6: 23.5 against 15.1 mm over 2000), where a tenth of the samples
        (the symphysis) lie apart from the rest. None switches it off.
    fine_population, fine_generations, fine_sigma : int, int, float
        With two or more views, a dislocated bone whose re-searches left a question (a warning
        or a doubt) is searched again at the finest level alone: CMA-ES from its stage-1 pose
        with this population, generation limit and step (mm, deg), the coarse levels skipped
        (:func:`~pelvicnav.register.research.fine_search`). An answer better than the kept
        one by ``confirm_margin`` replaces it; the registration stays flagged. Seeds 251 case 19
        and 229 case 24 (session 25): the truth scored 0.02-0.03 better than the answer at
        every level, yet no search from the coarse level found it (hips 17.7 and 26.5 mm off);
        fine-level searches from the stage-1 pose found it 3 of 3 and 1 of 3 times (about
        4.5 s each on 2 cores); on seed 239 case 33 they found a hip 7.2 mm off, better than the
        kept one (32 mm off) but not the truth, so the flag is not lifted.
        ``fine_population = 0`` switches it off.
    fine_ray_mm, fine_ray_step_mm, fine_ray_min_mm, fine_ray_margin : float
        With two or more views, a dislocated bone the re-searches did not question is probed
        along each view's ray at the finest level: scanned up to ``fine_ray_mm`` either way in
        ``fine_ray_step_mm`` steps, the best local optimum at least ``fine_ray_min_mm`` away
        that scores within ``fine_ray_margin`` of the answer (at most one per view) starts a
        short fine-level search (``fine_ray_search``: population, generation limit, step mm and
        degrees). Its answer replaces the kept one if better by ``confirm_margin``; one that
        ends more than ``retry_mm`` away and scores better by less flags the registration
        (:func:`~pelvicnav.register.research.fine_ray_check`). Seed 271 case 10: a hip 7.5 mm
        off in depth, unflagged, its sweeps and re-search agreeing; the truth 0.007 better at
        the finest level only. The probe's optimum 7 mm along the AP view's ray lay 0.8 mm from
        the truth and its search ended at the truth, 0.006 better: flagged. On 39 good
        registrations (seeds 271 and 277, cases 0-19) the optima scored 0.014-0.08 worse but
        one (0.008; its search ended 1.0 mm away and worse): no false alarm. About 0.2 s per
        registration, 0.8 s with a search (session 26's 20 x 40 search from the stage-1 pose
        found the same case for 2.7 s). ``fine_ray_mm`` 0 switches it off.
    """

    restarts: int | None = None
    fine: str = "cmaes"
    single_view_flag_mm: float = 4.0
    retry_mm: float = 4.0
    confirm_margin: float = 0.02
    ray_mm: float = 40.0
    ray_min_mm: float = 6.0
    ray_margin: float = 0.01
    turn_deg: float = 20.0
    turn_shift_mm: float = 4.0
    ambiguity: tuple[float, float] = (3.0, 3.0)
    ambiguity_score: float = 0.01
    coarse_rotation_prior: float = 5e-5
    joint_limits: tuple[float, float] | None = (0.2, 20.0)
    fine_population: int = 30
    fine_generations: int = 60
    fine_sigma: float = 6.0
    fine_ray_mm: float = 20.0
    fine_ray_step_mm: float = 1.0
    fine_ray_min_mm: float = 3.0
    fine_ray_margin: float = 0.01
    fine_ray_search: tuple[int, int, float] = (10, 25, 2.0)

    def __post_init__(self) -> None:
        if not (
            self.fine_ray_mm >= 0
            and self.fine_ray_step_mm > 0
            and self.fine_ray_min_mm >= 0
            and self.fine_ray_margin >= 0
        ):
            raise ValueError("fine_ray_mm, fine_ray_min_mm and fine_ray_margin must be >= 0 and "
                             f"fine_ray_step_mm > 0, got fine_ray_mm={self.fine_ray_mm}, "
                             f"fine_ray_step_mm={self.fine_ray_step_mm}, "
                             f"fine_ray_min_mm={self.fine_ray_min_mm}, "
                             f"fine_ray_margin={self.fine_ray_margin}")  # fmt: skip
        population, generations, sigma = self.fine_ray_search
        if population < 2 or generations < 1 or not sigma > 0:
            raise ValueError("fine_ray_search must be (population >= 2, generations >= 1, "
                             f"sigma > 0), got {self.fine_ray_search}")  # fmt: skip
        if not (self.fine_population >= 0 and self.fine_generations >= 1 and self.fine_sigma > 0):
            raise ValueError("fine_population must be >= 0, fine_generations >= 1 and fine_sigma "
                             f"> 0, got {self.fine_population}, {self.fine_generations}, "
                             f"{self.fine_sigma}")  # fmt: skip
        if self.fine not in ("cmaes", "stage2"):
            raise ValueError(f"research fine must be 'cmaes' or 'stage2', got {self.fine!r}")
        if not self.confirm_margin >= 0:
            raise ValueError(f"confirm_margin must be >= 0, got {self.confirm_margin}")
        if self.restarts is not None and self.restarts < 0:
            raise ValueError(f"restarts must be >= 0, got {self.restarts}")
        if not self.coarse_rotation_prior >= 0:
            raise ValueError(
                f"coarse_rotation_prior must be >= 0, got {self.coarse_rotation_prior}"
            )
        if not (self.turn_deg >= 0 and self.turn_shift_mm >= 0):
            raise ValueError(f"turn_deg and turn_shift_mm must be >= 0, got {self.turn_deg} and "
                             f"{self.turn_shift_mm}")  # fmt: skip
        if self.joint_limits is not None and (
            len(self.joint_limits) != 2 or not min(self.joint_limits) >= 0
        ):
            raise ValueError(
                f"joint_limits must be (fraction, mm) >= 0 or None, got {self.joint_limits}"
            )

    def count(self, n_views: int) -> int:
        """Re-searches to run with ``n_views`` views."""
        if self.restarts is not None:
            return self.restarts
        return 2 if n_views == 1 else 1


@dataclass(frozen=True)
class RegistrationSettings:
    """Everything :func:`~pelvicnav.register.multibody.register` needs to know.

    Attributes
    ----------
    pyramid, stage1, stage2, research : the blocks
    min_similarity : float, optional
        Final similarity (fine-level metric summed over views) below ``min_similarity`` per view
        is flagged as not converged. Default (None): the fine metric's own, 0.4 for GO and 0.05
        for gradient NCC. GO 0.4 per view: good two-view registrations scored 0.44-0.63 per view
        (52 atlas cases, study seeds 7 and 31; 6 real-CT cases 0.47-0.61), a stage-1 failure
        with every bone 14-36 mm off 0.39 (seed 31, case 38; its re-search agreed with it).
        For GO the floor is per view of what the answer's DRRs score against themselves (1 where
        the bones' edges cover half the view or more, as in every C-arm view above; ~0.8 in the
        340 mm radiographs of the field-of-view study), so a view the bones fill less of is not
        held to a score it cannot reach.
    unsettled_similarity : float
        With two or more views, a registration whose stage 1 did not settle (below) and whose
        final GO is below this per view (of what the answer's DRRs can score) is flagged: the
        answer fits no better than the weakest good registrations, and nothing confirms where
        stage 1 put the pelvis. Good registrations scored 0.46 per view and more (210 atlas cases,
        seeds 61-107); the whole pelvis misplaced scored 0.35-0.44 (seed 83 case 12, seed 89
        case 33, seed 107 case 37, 23-56 mm off). 0 switches it off.
    unsettled_confirm_mm, unsettled_confirmations : float, int
        Stage 1 has *settled* when at least ``unsettled_confirmations`` of the other stage-1
        runs (the starts tried with a first guess, or the rescue's restarts) end within
        ``unsettled_confirm_mm`` (at the body's centre, and as many degrees) of its answer; or
        when its answer stopped on a tolerance and was the only run, or one other run ended
        there too. Measured: seven good registrations with several starts had 1-4 others
        within 1.2 mm; the three gross ones above had 0, 0 and 1 (their others 10.6-117 mm
        away); seed 103 case 32, good but stopped on the generation limit, had 3 of the
        rescue's 4 restarts within 0.1 mm (it was flagged before). 0 confirmations: a stage 1
        that stopped on a tolerance has settled, and agreement is not counted.
    unsettled_lead : float
        Stage 1 has also settled when its answer scores better than every other run that ended
        elsewhere by at least this fraction of its own objective: a clear winner, found once,
        whether it stopped on a tolerance or was still improving at its generation limit.
        Measured (sessions 22-23, stage-1 objectives of every run): good registrations flagged
        only as unsettled led by 5.7-20 % (seeds 197 cases 26 and 29, 137 case 22, 181 case
        23, 211 case 36; at the generation limit 6.7-11.6 %: 181 case 17, 179 case 36, 229
        case 12, the others 100-380 mm away); of 28 gross registrations, the wrong
        stage-1 answers that stopped on a tolerance led by 2.5-9.3 % (seeds 107 case 37, 127
        case 14, 151 case 12, 193 case 24, 179 case 1), and every one above 2.8 % also scored
        below ``min_similarity``, which flags it whatever stage 1 did. Default 0.05 (session
        23; 0.10 before): between the wrong leads that only this rule can flag (2.5-2.8 %)
        and the smallest good one. 0 switches it off.
    lone_run_settles : bool
        Whether a lone stage-1 run (no first guess taken, so one start) that stopped on a
        tolerance has settled (default True). False treats it as unsettled, so a weak final
        GO (below ``unsettled_similarity``) flags it and calls the rescue, whose restarts settle
        it when they end where it did and none scores better elsewhere, or find the better
        answer. Seed 193 case 0: a lone run stopped with the pelvis 17.8 mm off in depth and
        passes unflagged by default; with False the rescue's restarts find the truth
        (stage-1 objective -0.780 against -0.662) and it ends at 0.5 mm, unflagged. Measured
        with False on the 360 registrations of nine seeds (session 23): that case fixed, no
        other verdict changed, but every registration whose final GO is below 0.5 per view
        (half or more) runs four more stage-1 runs: about 10 s instead of 2.5 s alone on 2
        cores, and the benchmark's first registration of the 0.8 mm CT 12 s on a quiet machine
        (18 s on a busy one) instead of 3.05 s (target 5 s). Restarts with half the
        population are cheaper but miss 193 case 0. So the default stays True: for a slower,
        safer first registration, set False. Since session 24 the depth probes
        (``Stage1Settings.probe_mm``) catch 193 case 0 for 0.8 s. A tracked frame (no stage-1
        search) has settled where the last frame did, either way.
    anchored_probe : bool
        With a plan and two or more views (6 DoF), a registration whose final GO is below
        ``unsettled_similarity`` per view (of what the answer's DRRs can score) gets one more
        short stage-1 run (``Stage1Settings``' probe budget) from where its dislocated bone puts
        the pelvis: every other bone at the dislocated bone's ``world_from_ct``, their poses in
        the CT. Stage 1 searches the pelvis from the set-up error alone, and where its runs all
        end in a wrong basin nothing else looks elsewhere; stage 2 still finds the dislocated
        bone by its own edges, so its answer places the pelvis within the dislocation. When that
        run ends elsewhere and scores better than stage 1's answer, stage 2 runs from it and the
        result with the higher final similarity is kept (:func:`~pelvicnav.register.multibody.
        _anchored`). Seed 269 case 28: every stage-1 run put the sacrum and the left hip 25 and
        35 mm off in depth (GO 0.41 per view, unflagged; the right hip, dislocated, 0.3 mm);
        the run from the right hip ends 0.7 / 1.0 mm from the truth, its stage-1 objective
        -0.590 against -0.527. Measured (session 33) on the registrations below 0.5 per view:
        it changed none of 48 on the fresh seeds 479 and 487 nor 40 good ones of seeds 373-467
        (bit-identical), and 4 of the 28 flagged or gross ones of seeds 373-467: 373/33 and
        439/4 from 20-46 mm off to within 0.4 mm (still flagged: stage 1 unsettled, the
        floor), 443/4 gross either way (implausible), 431/7 fine either way. Cost: the probe,
        0.3-0.4 s, in the weak half of registrations (the benchmark's first registration 3.74
        -> 4.15 s, median of 3, quiet machine). False switches it off.
    intact_limits : (mm, deg) or None
        With a plan, the bones stage 1 moves as the pelvis keep their CT relative poses (the
        intact joints): a registration where stage 2 moved one of them further than this from
        where the pelvis's first bone puts it (mm at its centroid and degrees; one view: the
        median distance of its points at the detector) is flagged. Stage 2 gives the attached
        bones a small box to absorb the models' error, not a joint that opens: a bone that used
        it to move apart from the others was pulling the pelvis towards a place stage 1 missed
        (seed 167 case 30: every stage-1 run put the pelvis 17-18 mm too far forward, where the
        coarse gradient NCC scored better than the truth; stage 2 moved the right hip 11.9 mm
        from the sacrum, towards the truth; its stage 1 settled by agreement and the final GO
        0.43 per view passed). Default (5, 5): on eight seeds (320 atlas cases), 4 of the 13 gross
        registrations moved a kept bone 5.9-12.6 mm / 2.3-8.0 deg (167/30 caught by this alone),
        the good ones at most 2.5 mm / 3.4 deg (seed 149 case 35, its kept hip 1.7 mm / 2.3 deg
        off: flagged under (3, 3)). None switches it off.
    second_opinion : (float, float) or None
        With a plan and two or more views, a registration flagged only because its dislocated
        bone's answer is in question (``MultiBodyResult.questions``: two answers the images
        score alike, an answer found once, a fine-level search that disagrees, a rescue that
        kept the pelvis) is settled when, at the finest level, its answer scores higher than
        every other answer the searches gave the bone beyond ``research.ambiguity`` (3 mm or
        3 deg; ``retry_mm``, 4 mm, until session 33) by more than these margins, in gradient
        NCC and in GO (each summed over the views; :mod:`~pelvicnav.register.opinion`); the
        flag stands, with the other answer named, when one comes within its margin or scores
        better, or when there is none to compare. The poses are never changed. Default
        (0.01, 0.0): session 30 shipped (0, 0), which settled real-CT seed 17 case 2 (a hip
        6.73 mm off whose truth no search found; it led the answers found by 0.005 in gradient
        NCC and 0.003 in GO). Rescored on the 52
        registrations whose answers were recorded (sessions 30-31), 0.01 keeps it flagged and
        unsettles two fine ones (419/15 and 367/36, leads 0.0035 and 0.0045); every other
        fine one led by 0.0106 or more. None switches it off.
    polish : (float, int, int, float) or None
        With a plan and two or more views (6 DoF), after the verdict: the dislocated bone
        searched once more at the finest level by CMA-ES of gradient NCC from its answer, the
        other bones fixed (:mod:`~pelvicnav.register.polish`): (sigma in mm and deg, population,
        generations, half-width of the box about the answer in mm and deg). The pose is taken
        when it scores better; the verdict and the warnings stay those of the answer,
        ``similarity`` is the polished pose's. Default ``(2.0, 12, 25, 4.0)`` (300 evaluations,
        0.2-0.4 s; session 35): on five atlas seeds and a real-CT seed (206 dislocated bones)
        the dislocated bone's centroid error fell from a median of 0.35 to 0.28 mm (111
        nearer, 41 further, 7 of them by more than 0.3 mm), and seed 569 case 33's hip, 4.29 mm
        off and not flagged, to 1.92 mm; no verdict changed. None switches it off.
    """

    pyramid: PyramidSettings = field(default_factory=PyramidSettings)
    stage1: Stage1Settings = field(default_factory=lambda: Stage1Settings(sigmas=(8.0, 1.0)))
    stage2: Stage2Settings = field(default_factory=Stage2Settings)
    research: ResearchSettings = field(default_factory=ResearchSettings)
    min_similarity: float | None = None
    unsettled_similarity: float = 0.5
    unsettled_confirm_mm: float = 2.0
    unsettled_confirmations: int = 2
    unsettled_lead: float = 0.05
    lone_run_settles: bool = True
    anchored_probe: bool = True
    intact_limits: tuple[float, float] | None = (5.0, 5.0)
    second_opinion: tuple[float, float] | None = (0.01, 0.0)
    polish: tuple[float, int, int, float] | None = (2.0, 12, 25, 4.0)

    def __post_init__(self) -> None:
        for name in ("lone_run_settles", "anchored_probe"):
            if not isinstance(getattr(self, name), bool):  # "false" would switch it on
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if not (
            self.unsettled_confirm_mm >= 0
            and self.unsettled_confirmations >= 0
            and self.unsettled_lead >= 0
        ):
            raise ValueError(
                "unsettled_confirm_mm, unsettled_confirmations and unsettled_lead must be >= 0"
            )
        if self.intact_limits is not None and (
            len(self.intact_limits) != 2 or not min(self.intact_limits) > 0
        ):
            raise ValueError(
                f"intact_limits must be (mm, deg) > 0 or None, got {self.intact_limits}"
            )
        if self.polish is not None and not _valid_polish(self.polish):
            raise ValueError(
                "polish must be (sigma > 0, population >= 2, generations >= 1, box > 0) or "
                f"None, got {self.polish!r}"
            )
        if self.second_opinion is not None and (
            not isinstance(self.second_opinion, tuple | list)
            or len(self.second_opinion) != 2
            or not min(self.second_opinion) >= 0
        ):
            raise ValueError(
                "second_opinion must be (gradient NCC margin, GO margin) >= 0 or None, got "
                f"{self.second_opinion}"
            )
        n = self.pyramid.n_levels
        per_level = {
            "stage1.populations": self.stage1.populations,
            "stage1.max_generations": self.stage1.max_generations,
            "stage1.sigmas": self.stage1.sigmas or self.pyramid.sigmas,
            "stage2.populations": self.stage2.populations,
            "stage2.max_generations": self.stage2.max_generations,
        }
        for name, values in per_level.items():
            if len(values) != n:
                raise ValueError(
                    f"{name} needs one value per pyramid level ({n}), got {len(values)}"
                )

    def min_similarity_for(self, metric: str) -> float:
        """The per-view floor of the final similarity for the fine ``metric``."""
        if self.min_similarity is not None:
            return self.min_similarity
        return MIN_SIMILARITY[metric]

    @property
    def dof(self) -> int:
        return self.stage1.dof

    @property
    def factors(self) -> tuple[int, ...]:
        return self.pyramid.factors

    @classmethod
    def for_dof(cls, dof: int) -> RegistrationSettings:
        """The defaults with stage 1 in ``dof`` degrees of freedom."""
        if dof == 6:
            return cls()
        return cls(stage1=Stage1Settings(dof=dof))  # 9 DoF: the pyramid's sigmas (measured)

    @classmethod
    def tracking(cls) -> RegistrationSettings:
        """A later frame from the previous frame's poses: stage 2 only, every bone refined at
        once by gradient at both pyramid levels (at most 100 iterations each), no
        re-search. On an atlas case after a 3 mm / 2 deg move of every bone: 0.38-0.47 s and
        0.15-0.34 mm (CMA-ES sweeps: 2.0-2.8 s, 0.12-0.44 mm); after 7 mm / 4 deg the same,
        where the fine level alone ended with a hip 12-13 mm off.

        The refinements stop at a relative change of 2e-5 (``gradient_tol``; a first
        registration's 1e-6). Session 27 measured 1e-5 on the benchmark's frames (3 mm / 2 deg,
        six of them): 0.46-0.52 s against 0.71-0.80 s with 1e-6, 20 fine-level evaluations
        instead of 30, the same errors (median 0.257 against 0.262 mm, worst 0.38 mm); 1e-4 was
        faster (0.33 s) but worse (median 0.33 mm). Session 28, 24 frames of the benchmark case:
        1e-5 / 2e-5 / 4e-5 took 20.2 / 17.9 / 15.5 fine-level evaluations, median 0.46-0.50 /
        0.41-0.45 / 0.40 s, median error 0.261 / 0.268 / 0.275 mm (worst 0.40 / 0.39 / 0.39 mm);
        after 7 mm / 4 deg, 1e-5 / 2e-5: 0.60 / 0.48 s, 0.259 / 0.261 mm, and the same one hip
        lost (9.0-9.1 mm) with either."""
        return cls(stage1=Stage1Settings(max_generations=(0, 0)),
                   stage2=Stage2Settings(mode="gradient", gradient_tol=2e-5),
                   research=ResearchSettings(restarts=0))  # fmt: skip


def _valid_polish(polish) -> bool:
    """Whether ``polish`` is (sigma > 0, population >= 2, generations >= 1, box > 0)."""
    try:
        sigma, population, generations, half = polish
        ints = all(float(v) == int(v) for v in (population, generations))
        return bool(sigma > 0 and half > 0 and ints and population >= 2 and generations >= 1)
    except (TypeError, ValueError):
        return False
