"""Seeds of the registration's CMA-ES runs, derived from one seed through ``SeedSequence``.

Each run is named by a path (its stage, then level, sweep, bone...), and its seed is the first word
of ``SeedSequence([seed, stage, *path])``'s state: runs get independent streams whatever the
numbers, where arithmetic such as ``seed + 100 + 10 * level + bone`` collides (seed 10's level 0
is seed 0's level 1).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "ANCHOR",
    "FINE",
    "JOINT",
    "POLISH",
    "PROBE",
    "RAY",
    "REPASS",
    "RESCUE",
    "RESEARCH",
    "STAGE1",
    "SWEEP",
    "TURN",
    "run_seed",
]

STAGE1, SWEEP, JOINT, RESEARCH, REPASS, RESCUE, RAY, TURN, PROBE, FINE, ANCHOR = range(1, 12)
POLISH = 12


def run_seed(seed: int, stage: int, *path: int) -> int:
    """The seed (0 <= s < 2**32) of the CMA-ES run at ``path`` of ``stage`` under ``seed``."""
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    return int(
        np.random.SeedSequence([int(seed), int(stage), *map(int, path)]).generate_state(1)[0]
    )
