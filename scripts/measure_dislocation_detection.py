"""Leave-one-out measure of ``pelvicnav plan --dislocated auto`` on the atlas.

For every atlas subject, the planners are fitted on the other 39; the subject is tested intact
and with each innominate dislocated by the simulator (open-book, SI and PS patterns, up to
20 mm / 10 deg). Reported: how often the dislocated side is found for dislocations >= 5 mm, and how
often "none" is found for intact pelvises. Writes a CSV and prints the summary.

Usage: python scripts/measure_dislocation_detection.py --atlas PATH --out detection.csv
       [--seed 8] [--first 0 --last 40]
"""

from __future__ import annotations

import argparse
import csv

import numpy as np
from threadpoolctl import threadpool_limits

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.atlas import load_atlas
from pelvicnav.phantom.dislocate import draw_dislocation
from pelvicnav.pose.target import TargetPlanner
from pelvicnav.workflow.plan import decide_dislocated

SETS = (("sacrum", "right_hip"), ("sacrum", "left_hip"))


class _Planners:
    """Leave-one-out planners with the model's ``planner(observed)`` interface."""

    def __init__(self, train, faces, prior):
        self._p = {s: TargetPlanner.fit(train, faces, observed=s, prior=prior) for s in SETS}

    def planner(self, observed):
        return self._p[tuple(sorted(observed, key=BONES.index))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--atlas", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--seed", type=int, default=8)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--last", type=int, default=40)
    args = parser.parse_args()
    atlas = load_atlas(args.atlas)
    V, F = atlas.vertices, atlas.faces
    rows = []
    with threadpool_limits(1):
        for s in range(args.first, min(args.last, len(V))):
            planners = _Planners(np.delete(V, s, axis=0), F, prior=0.1)
            rng = np.random.default_rng([args.seed, s])
            cases = [("none", "", V[s], 0.0, 0.0)]
            for bone in ("left_hip", "right_hip"):
                for pattern in ("open-book", "si", "ps"):
                    d = draw_dislocation(V[s], F, bone=bone, pattern=pattern, rng=rng)
                    W = V[s].copy()
                    W[BONES.index(bone)] = tf.apply(d.transform, W[BONES.index(bone)])
                    cases.append((bone, pattern, W, d.translation_mm, d.rotation_deg))
            for truth, pattern, W, mm, deg in cases:
                meshes = dict(zip(BONES, W, strict=True))
                decision, _ = decide_dislocated(meshes, planners)
                found = decision.dislocated[0] if decision.dislocated else "none"
                rows.append(
                    {
                        "subject": atlas.subject_ids[s],
                        "truth": truth,
                        "pattern": pattern,
                        "translation_mm": mm,
                        "rotation_deg": deg,
                        "found": found,
                        "margin": decision.margin,
                        "side_margin": decision.side_margin,
                    }
                )
            print(s, flush=True)
    with open(args.out, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    big = [r for r in rows if r["truth"] != "none" and r["translation_mm"] >= 5]
    intact = [r for r in rows if r["truth"] == "none"]
    side = sum(r["found"] == r["truth"] for r in big)
    none = sum(r["found"] == "none" for r in intact)
    print(f"dislocated >= 5 mm: correct side {side}/{len(big)} = {side / max(len(big), 1):.3f}")
    print(f"intact: none {none}/{len(intact)} = {none / max(len(intact), 1):.3f}")


if __name__ == "__main__":
    main()
