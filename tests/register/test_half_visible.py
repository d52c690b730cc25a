"""A dislocated hip mostly outside the views, held at its joints by the joint-aware prior.

Registration study seed 131, case 30 (atlas subject 45; the real atlas, so CI only): the left hip
is 19.3 mm / 7.2 deg out of place and 24 % / 27 % of it projects inside the two views. On the
images alone (``Stage2Settings(joint_prior=0, joint_gap=(0, 0))``, the default before session 18)
it ended 14.4 mm off, flagged: the search never reached the truth's basin, which scores 0.015
better. With the interpenetration term alone 0.52 mm; with both terms (``PRIOR`` below)
0.62 mm (flagged: its re-searches still find other answers) when measured.
"""

from __future__ import annotations

import numpy as np
import pytest
from tests.helpers.atlas_cases import atlas_study_case

from pelvicnav.geometry import transforms as tf
from pelvicnav.register.multibody import register_multibody
from pelvicnav.register.settings import RegistrationSettings, Stage2Settings

# the prior as session 18 measured it (off by default: the out-of-plane capture test's hip
# ended 1.69 mm off with it, over that test's 1.5 mm)
PRIOR = RegistrationSettings(stage2=Stage2Settings(joint_prior=0.1, joint_gap=(0.001, 20.0)))


@pytest.fixture(scope="module")
def case30():
    """Seed 131, case 30, simulated once for this file (the real atlas, or skip)."""
    case, sim = atlas_study_case(131, 30)
    assert sim["bone"] == "left_hip"
    return case, sim


def _errors(res, sim) -> dict[str, float]:
    errors = {}
    for b, c in sim["centroids"].items():
        at = [tf.apply(T, c[None])[0] for T in (res.poses[b], sim["truth"][b])]
        errors[b] = float(np.linalg.norm(at[0] - at[1]))
    return errors


@pytest.mark.slow
def test_a_half_visible_hip_is_held_at_its_joints(case30):
    case, sim = case30
    res = register_multibody(sim["ct"], sim["labels"], sim["views"], dislocated=sim["bone"],
                             seed=case["registration_seed"], settings=PRIOR)  # fmt: skip
    errors = _errors(res, sim)
    assert max(errors.values()) < 1.0, errors


@pytest.mark.slow
def test_with_the_shipped_defaults_a_wrong_half_visible_hip_is_flagged_by_its_joints(case30):
    """Shipped defaults (the prior off, the joints judged): measured in the session-19 study, the
    hip 14.4 mm off with its joint gap 32.4 mm wider than the CT's, flagged; its re-search's
    other answer was implausible too (a doubt, which the joint check keeps from passing)."""
    case, sim = case30
    res = register_multibody(sim["ct"], sim["labels"], sim["views"], dislocated=sim["bone"],
                             seed=case["registration_seed"])  # fmt: skip
    errors = _errors(res, sim)
    if max(errors.values()) > 4.0:
        assert not res.converged, (errors, res.warnings)
        assert any("no dislocation puts it there" in w for w in res.warnings), res.warnings
        assert res.verdict == "implausible", res.implausible  # likely wrong, not only in question
        assert res.to_json()["verdict"] == "implausible"
