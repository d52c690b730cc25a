"""A small CT with three bone blocks and three soft-tissue organs, labelled two ways."""

from __future__ import annotations

import numpy as np


def label_phantom():
    """``(hu, ours, totalsegmentator, world_from_ijk)``; 2 mm voxels, LPS (+i: patient's left)."""
    hu = np.full((60, 40, 40), 40.0)
    ours = np.zeros(hu.shape, dtype=np.int16)
    total = np.zeros(hu.shape, dtype=np.int16)
    for value, ts, sl in (
        (1, 25, np.s_[25:35, 20:35, 10:30]),  # sacrum, centre
        (2, 77, np.s_[40:55, 5:30, 5:35]),  # left hip, patient's left (+x)
        (3, 78, np.s_[5:20, 5:30, 5:35]),  # right hip
    ):
        hu[sl] = 350.0
        ours[sl], total[sl] = value, ts
    # TotalSegmentator's 1-3: spleen (left), right kidney, left kidney, all soft tissue
    for ts, sl in ((1, np.s_[45:55, 30:38, 30:38]), (2, np.s_[8:16, 30:38, 25:35]),
                   (3, np.s_[44:52, 30:38, 25:29])):  # fmt: skip
        total[sl] = ts
    return hu, ours, total, np.diag([2.0, 2.0, 2.0, 1.0])
