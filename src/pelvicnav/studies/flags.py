"""How far a study's "not converged" flag can be trusted.

A registration that ends far off should say so (``converged`` False), and one that is fine should
not: a flag that is always raised tells the user nothing. For a study's rows (one per bone or per
case, each with an error and the registration's ``converged``), :func:`flag_counts` counts, per
registration (``case_id``):

* ``gross``: registrations with an error over the limit (4 mm: the paper's success criterion),
  and ``gross_flagged``, those of them that were flagged;
* ``flagged``: flagged registrations, and ``flagged_fine``, those of them with every error within
  the limit (false alarms);
* where the rows say which results' joints no dislocation gives (``implausible``, see
  :class:`~pelvicnav.register.result.MultiBodyResult`): ``implausible``, such registrations, and
  ``implausible_gross``, those of them with an error over the limit. Such a flag says "likely
  wrong"; the others, "in question";
* where the rows say which results a second opinion settled (``settled``, see
  :func:`~pelvicnav.register.multibody._second_opinion`): ``settled``, such registrations (not
  flagged), and ``settled_gross``, those of them with an error over the limit.

Issue 13's goals: every gross error flagged, at most 10 % of flagged registrations fine.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["LIMIT_MM", "flag_counts", "flag_line"]

LIMIT_MM = 4.0


def flag_counts(
    rows: Sequence[dict],
    error_key: str | Sequence[str],
    *,
    limit_mm: float = LIMIT_MM,
    case_key: str = "case_id",
) -> dict[str, int]:
    """Registrations that went wrong, and what the flag said of them (see the module).

    ``error_key``: the column of the error (mm), or several (e.g. one per bone).
    """
    keys = (error_key,) if isinstance(error_key, str) else tuple(error_key)
    cases: dict[str, list[dict]] = {}
    for r in rows:
        cases.setdefault(str(r[case_key]), []).append(r)
    gross, flagged, implausible, settled = set(), set(), set(), set()
    for cid, sel in cases.items():
        errors = np.array([float(r[k]) for r in sel for k in keys], dtype=float)
        if np.any(~np.isfinite(errors)) or np.any(errors > limit_mm):
            gross.add(cid)
        if not all(_true(r["converged"]) for r in sel):
            flagged.add(cid)
        if any(_true(r.get("implausible", False)) for r in sel):
            implausible.add(cid)
        if any(_true(r.get("settled", False)) for r in sel):
            settled.add(cid)
    out = {"registrations": len(cases), "gross": len(gross), "gross_flagged": len(gross & flagged),
           "flagged": len(flagged), "flagged_fine": len(flagged - gross)}  # fmt: skip
    if any("implausible" in r for r in rows):
        out |= {"implausible": len(implausible), "implausible_gross": len(implausible & gross)}
    if any("settled" in r for r in rows):
        out |= {"settled": len(settled), "settled_gross": len(settled & gross)}
    return out


def flag_line(counts: dict[str, int], limit_mm: float = LIMIT_MM) -> str:
    """One sentence for a summary."""
    c = counts
    line = (f"Flag: {c['gross']} of {c['registrations']} registrations had an error over "
            f"{limit_mm:g} mm, {c['gross_flagged']} of them flagged as not converged; "
            f"{c['flagged']} flagged, {c['flagged_fine']} of them in fact fine.")  # fmt: skip
    if "implausible" in c:
        line += (f" {c['implausible']} flagged as implausible (joints no dislocation gives: "
                 f"likely wrong), {c['implausible_gross']} of them with an error over "
                 f"{limit_mm:g} mm.")  # fmt: skip
    if "settled" in c:
        line += (f" {c['settled']} in question settled by the second opinion (not flagged), "
                 f"{c['settled_gross']} of them with an error over {limit_mm:g} mm.")  # fmt: skip
    return line


def _true(value) -> bool:
    """``converged`` as stored: a bool, or its text in a CSV."""
    if isinstance(value, str):
        return value.strip().lower() in ("true", "1")
    return bool(value)
