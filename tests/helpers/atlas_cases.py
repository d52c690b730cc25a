"""A registration study case on the real Han atlas, simulated as the study does (or skip)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from pelvicnav.io.atlas import load_atlas
from pelvicnav.studies.registration import (
    RegistrationStudySettings,
    registration_study,
    simulate_registration_case,
)


def atlas_study_case(seed: int, index: int) -> tuple[dict, dict]:
    """Case ``index`` of ``pelvicnav study registration --seed seed``: (the case, its
    simulation); skips the test where ``PELVICNAV_ATLAS`` is not a folder."""
    path = os.environ.get("PELVICNAV_ATLAS")
    if not path or not Path(path).is_dir():
        pytest.skip("PELVICNAV_ATLAS is not set to a folder: the real Han atlas is not available")
    settings = RegistrationStudySettings(n_cases=index + 1, seed=seed)
    case = registration_study(load_atlas(path), settings).cases[index]
    sim = simulate_registration_case(case["vertices"], case["faces"], seed=case["seed"],
                                     settings=case["settings"])  # fmt: skip
    return case, sim
