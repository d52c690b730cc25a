"""A dislocated hip mostly outside the views, held at its joints by the joint-aware prior.

Registration study seed 131, case 30 (atlas subject 45; the real atlas, so CI only): the left hip
is 19.3 mm / 7.2 deg out of place and 24 % / 27 % of it projects inside the two views. On the
images alone (``Stage2Settings(joint_prior=0, joint_gap=(0, 0))``, the default before session 18)
it ended 14.4 mm off, flagged: the search never reached the truth's basin, which scores 0.015
better. With the interpenetration term alone 0.52 mm; with the shipped defaults (both terms)
0.62 mm (flagged: its re-searches still find other answers) when measured.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.io.atlas import load_atlas
from pelvicnav.register.multibody import register_multibody
from pelvicnav.register.settings import RegistrationSettings, Stage2Settings
from pelvicnav.studies.registration import (
    RegistrationStudySettings,
    registration_study,
    simulate_registration_case,
)

# the prior as session 18 measured it (off by default: the out-of-plane capture test's hip
# ended 1.69 mm off with it, over that test's 1.5 mm)
PRIOR = RegistrationSettings(stage2=Stage2Settings(joint_prior=0.1, joint_gap=(0.001, 20.0)))


@pytest.mark.slow
def test_a_half_visible_hip_is_held_at_its_joints(real_atlas_path):
    study = registration_study(load_atlas(real_atlas_path),
                               RegistrationStudySettings(n_cases=31, seed=131))  # fmt: skip
    case = study.cases[30]
    sim = simulate_registration_case(case["vertices"], case["faces"], seed=case["seed"],
                                     settings=case["settings"])  # fmt: skip
    assert sim["bone"] == "left_hip"
    res = register_multibody(sim["ct"], sim["labels"], sim["views"], dislocated=sim["bone"],
                             seed=case["registration_seed"], settings=PRIOR)  # fmt: skip
    errors = {}
    for b, c in sim["centroids"].items():
        at = [tf.apply(T, c[None])[0] for T in (res.poses[b], sim["truth"][b])]
        errors[b] = float(np.linalg.norm(at[0] - at[1]))
    assert max(errors.values()) < 1.0, errors
