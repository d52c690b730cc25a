"""How far the registration study's dislocations open the joints (the joint-gap prior's slack).

For each case of ``pelvicnav study registration --seed S`` (atlas cases), the dislocated hip's
joint samples (mesh vertices 2-15 mm from the sacrum or the other hip) and the 90th percentile of
their distances to those bones, at the CT pose and at the true (dislocated) pose: the opening is
the difference, the quantity ``Stage2Settings.joint_gap`` allows up to its slack
(:mod:`pelvicnav.register.prior` measures it on the CT's bone samples; this uses the meshes, so
no CT is synthesised). Prints the median, 90th percentile and maximum per seed and over all.

Usage: python scripts/measure_joint_opening.py --atlas PATH --seeds 127 131 137
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial import cKDTree

from pelvicnav.geometry import transforms as tf
from pelvicnav.io.atlas import load_atlas
from pelvicnav.phantom.dislocate import draw_dislocation
from pelvicnav.register.prior import GAP_QUANTILE
from pelvicnav.studies.registration import RegistrationStudySettings, registration_study


def opening(vertices: np.ndarray, faces, seed: int) -> float:
    """The case's opening (mm), redrawing its dislocation as the study's simulation does."""
    rng = np.random.default_rng(seed)
    V = np.asarray(vertices, dtype=np.float64)
    bone = ("left_hip", "right_hip")[int(rng.integers(2))]
    disl = draw_dislocation(V, faces, bone=bone, pattern="open-book", rng=rng)
    b = 1 if bone == "left_hip" else 2
    trees = [cKDTree(V[k]) for k in range(3) if k != b]

    def gap(points):
        return np.min([t.query(points)[0] for t in trees], axis=0)

    d = gap(V[b])
    joint = V[b][(d > 2.0) & (d < 15.0)]
    at_ct = np.percentile(gap(joint), GAP_QUANTILE)
    return float(np.percentile(gap(tf.apply(disl.transform, joint)), GAP_QUANTILE) - at_ct)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--atlas", default=None)
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--cases", type=int, default=40)
    args = ap.parse_args()
    atlas = load_atlas(args.atlas)
    every = []
    for seed in args.seeds:
        study = registration_study(atlas, RegistrationStudySettings(n_cases=args.cases, seed=seed))
        mm = [opening(c["vertices"], c["faces"], c["seed"]) for c in study.cases]
        every += mm
        p = np.percentile(mm, [50, 90, 100])
        print(f"seed {seed}: opening median {p[0]:.1f}, p90 {p[1]:.1f}, max {p[2]:.1f} mm")
    p = np.percentile(every, [50, 90, 100])
    print(f"all {len(every)} cases: median {p[0]:.1f}, p90 {p[1]:.1f}, max {p[2]:.1f} mm")


if __name__ == "__main__":
    main()
