"""A second opinion on an answer the re-searches left in question.

The flag's questions (two answers within ``ambiguity_score``, an answer found once, a fine-level
search that disagrees, a rescue that kept the pelvis: :mod:`~pelvicnav.register.research`,
:func:`~pelvicnav.register.multibody._rescue`) read the search's own similarity, gradient
orientation (GO) at the finest level. Where a dislocated hip is half outside the views, GO scores
its answer and a rival 5-40 mm away within 0.01, and the questions are raised whichever is right:
on the fresh seeds of sessions 27-29, 33 of 52 flagged registrations were fine.

The second opinion scores the kept answer and every other answer the searches gave the bone
beyond the ambiguity limits (3 mm or 3 deg from it) at the finest level, the others at their
final poses (the same DRRs and radiographs), in two similarities: gradient NCC
(:class:`~pelvicnav.metrics.similarity.GradientNCC`), which weighs each edge by its strength where
GO counts its direction only, and the level's own (GO). The kept answer must lead every other one
in both.

Measured on the 16 two-view registrations flagged only as in question on seeds 311 and 347-367
(scored afterwards, the answers as the searches left them): in gradient NCC, every other answer
scored below the kept one by 0.0045-0.10 (summed over both views) in the 13 fine ones, and one
scored above it by 0.016-0.052 in the 3 gross ones (hips 6.3-20.5 mm off); in GO, one scored
above the kept one in the 3 gross ones and in 2 of the fine ones (by 0.007 and 0.011). Both
together settle 11 of the 13 fine ones and none of the gross ones. Gradient NCC alone also
settled seed 389 case 4 (a fresh seed): a hip 13.6 mm / 21 deg off whose true pose no search
found (it scored 0.024 above the answer in GO and 0.041 in gradient NCC), where GO put one of
the answers found 0.015 above the kept one. The second opinion can only compare what the
searches found: an answer that leads every other one found may still be wrong.

Real-CT seed 17 case 2 (session 31; CT 005, its left hip 6.73 mm off) is such a one: the truth
scores 0.021 above the kept answer in gradient NCC and 0.006 in GO, no search found it, and the
kept answer led the eight answers found by 0.005 and 0.003. Gradient NCC must therefore lead by
more than a margin (``RegistrationSettings.second_opinion``, default 0.01 in gradient NCC, 0 in
GO): rescored on the registrations whose answers were recorded in sessions 30-31, it keeps that
case flagged and unsettles two fine ones (leads 0.0035 and 0.0045); every other fine one led by
0.0106 or more.

Which answers are compared (session 34). Until session 33, those more than 4 mm
(``ResearchSettings.retry_mm``) from the kept one at its centroid. An ambiguity between answers
nearer in millimetres but more than 3 deg apart then raised the question and left nothing to
compare, and the flag stood: three of the six false alarms on the fresh seeds of session 33
(479/18, 487/20, 499/35: the hip 0.5-1.0 mm off) and one on seeds 373-467 (439/6). Now every
answer beyond the ambiguity limits (``ResearchSettings.ambiguity``) is compared: the answers that
can raise a question.

Rerun on the 36 flagged registrations and the 29 settled by a second opinion of seeds 373-499:
- settled now: 487/20 and 499/35 (fine);
- flagged now: 419/14 (fine; an answer 1.5 mm / 3.2 deg away scored 0.0007 above it in GO);
- every other verdict, and every gross registration's, unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pelvicnav.drr.renderer import Renderer
from pelvicnav.io.views import ViewSet
from pelvicnav.metrics.errors import pose_disagreement
from pelvicnav.register.pyramid import Level

__all__ = ["SecondOpinion", "second_opinion"]


@dataclass(frozen=True)
class SecondOpinion:
    """The kept answer of ``bone`` against the other answers found far from it.

    Attributes
    ----------
    bone : str
    compared : int
        Other answers further than ``far`` from the kept one.
    lead : float
        The kept answer's gradient NCC (summed over the views) minus the best other answer's;
        NaN when none was compared.
    lead_level : float
        The same in the level's own similarity (GO at the finest level: what the searches read).
    rival_mm, rival_deg : float
        How far the other answer that comes closest to the kept one (the least of its two
        leads) is from it (mm at the bone's centroid, degrees); NaN when none was compared.
    """

    bone: str
    compared: int
    lead: float
    lead_level: float
    rival_mm: float
    rival_deg: float


def second_opinion(
    level: Level,
    renderer: Renderer,
    views: ViewSet,
    poses: dict[str, NDArray],
    bone: str,
    found: Sequence[NDArray],
    far: tuple[float, float],
) -> SecondOpinion:
    """Gradient NCC at ``level`` of ``bone`` at its kept pose and at each pose of ``found``
    further than ``far`` from it, in millimetres or in degrees
    (:func:`~pelvicnav.metrics.errors.pose_disagreement`), every other bone at ``poses``.

    Parameters
    ----------
    level : Level
        The finest level (its radiographs and projections, ``views``' geometry).
    renderer : Renderer
    views : ViewSet
        The final geometry (for the distances).
    poses : dict bone -> (4, 4)
        The answer, ``world_from_ct``.
    bone : str
    found : sequence of (4, 4)
        Other answers for ``bone`` (``world_from_ct``); repeats count once.
    far : (mm, deg)
        An answer further than either (mm at the centroid, degrees) is another answer: the
        ambiguity limits (``ResearchSettings.ambiguity``), beyond which answers raise questions.
    """
    far_mm, far_deg = _limits(far)
    kept = poses[bone]
    points, centre = renderer.points(bone, level.index), renderer.centroid(bone, level.index)
    others, apart = [], []
    # the searches record an answer again each time they are judged against it: each once
    unique = np.unique(np.asarray(found, dtype=np.float64).reshape(-1, 4, 4), axis=0)
    for T in unique:
        mm, deg = pose_disagreement(kept, T, points, centre, views.projections,
                                    views.pixel_spacing)  # fmt: skip
        if mm > far_mm or deg > far_deg:
            others.append(T)
            apart.append((mm, deg))
    if not others:
        nan = float("nan")
        return SecondOpinion(bone, 0, nan, nan, nan, nan)
    bones = renderer.bones
    stack = np.stack([[T if b == bone else poses[b] for b in bones] for T in (kept, *others)])
    drrs = renderer.render(level.index, bones, stack, level.projections, level.shape)
    ncc = level.scored_by("gncc").score(drrs)
    own = level.score(drrs)
    lead, lead_level = ncc[0] - ncc[1:], own[0] - own[1:]
    k = int(np.argmin(np.minimum(lead, lead_level)))
    return SecondOpinion(bone, len(others), float(lead.min()), float(lead_level.min()), *apart[k])


def _limits(far) -> tuple[float, float]:
    """``far`` as ``(mm, deg)``, both finite and >= 0; ValueError otherwise (a lone number, as
    this function took until session 33, included)."""
    try:
        mm, deg = (float(v) for v in far)
    except (TypeError, ValueError):
        raise ValueError(f"far must be (mm, deg), got {far!r}") from None
    if not (np.isfinite([mm, deg]).all() and min(mm, deg) >= 0):
        raise ValueError(f"far must be (mm, deg), each finite and >= 0, got {far!r}")
    return mm, deg
