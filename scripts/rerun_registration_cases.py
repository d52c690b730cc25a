"""Run chosen cases of the registration study again, with the shipped settings or one switch off.

Each ``SEED:CASE`` is case ``CASE`` of ``pelvicnav study registration --seed SEED`` (atlas cases,
the study's other defaults): the same simulation and registration seeds, so a case run here
matches the study's row unless the code or the settings differ. ``--without anchored_probe``
(or ``lone_run_settles``, ...) sets that ``RegistrationSettings`` switch False, to compare a
change with the code before it on the same cases. Writes one row per bone (the study's columns)
and prints one line per case.

Usage: python scripts/rerun_registration_cases.py --atlas PATH --out rows.csv 269:28 373:33
       [--without anchored_probe] [--workers 2]
"""

from __future__ import annotations

import argparse
import csv
from concurrent.futures import ProcessPoolExecutor
from dataclasses import fields

from pelvicnav.io.atlas import load_atlas
from pelvicnav.register.settings import RegistrationSettings
from pelvicnav.studies.registration import (
    RegistrationStudySettings,
    registration_study,
    run_registration_case,
)


def case_of(atlas, seed: int, index: int, settings: RegistrationSettings) -> dict:
    """Case ``index`` of the study with ``seed`` (as many cases as it needs), registered with
    ``settings``."""
    study = registration_study(atlas, RegistrationStudySettings(n_cases=index + 1, seed=seed),
                               registration=settings)  # fmt: skip
    return study.cases[index]


def run(case: dict) -> list[dict]:
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        return run_registration_case(case)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+", help="SEED:CASE")
    ap.add_argument("--atlas", default=None)
    ap.add_argument("--out", required=True)
    ap.add_argument("--without", nargs="*", default=[], help="RegistrationSettings switches")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    try:
        pairs = [tuple(int(v) for v in c.split(":")) for c in args.cases]
        if any(len(p) != 2 or min(p) < 0 for p in pairs):
            raise ValueError
    except ValueError:
        ap.error(f"cases must be SEED:CASE with non-negative integers, got {args.cases}")
    switches = [f.name for f in fields(RegistrationSettings) if f.type in (bool, "bool")]
    if unknown := sorted(set(args.without) - set(switches)):
        ap.error(f"--without takes {', '.join(switches)}; got {', '.join(unknown)}")
    settings = RegistrationSettings(**dict.fromkeys(args.without, False))
    atlas = load_atlas(args.atlas)
    cases = [case_of(atlas, s, i, settings) for s, i in pairs]
    rows = []
    with ProcessPoolExecutor(args.workers) as pool:
        for (seed, _), bones in zip(pairs, pool.map(run, cases), strict=True):
            rows += [{"seed": seed, **r} for r in bones]
            r0 = bones[0]
            errors = " ".join(f"{r['bone']} {r['error_mm']:.2f}" for r in bones)
            print(f"{seed}/{r0['case']}: converged {r0['converged']}, similarity "
                  f"{r0['similarity']:.3f}, mm: {errors}")  # fmt: skip
    with open(args.out, "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
