"""The shipped registration defaults on simulated pelvises: several seeds, a stated pass rate.

Patients are sampled from the packaged pelvis model (no atlas needed); each case is the
registration study's simulation (an open-book dislocation of a random hip, 20 mm / 5 deg set-up
error, AP + oblique radiographs at 50 uGy) registered with ``RegistrationSettings()`` and the
plan's dislocated bone. A case passes when every bone's centroid is within 1 mm of the truth.
Measured when written: 3 of 3 cases pass (worst bones 0.22, 0.69, 0.38 mm; ~95 s); the test asks
for 2 of 3, and that every bone over 4 mm off is flagged.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.phantom.population import load_population
from pelvicnav.register.multibody import register_multibody
from pelvicnav.register.pyramid import splat_renderer
from pelvicnav.register.settings import RegistrationSettings
from pelvicnav.studies.registration import RegistrationStudySettings, simulate_registration_case

SEEDS = (11, 12, 13)


@pytest.mark.slow
def test_shipped_defaults_register_simulated_pelvises():
    population = load_population("model", n_subjects=len(SEEDS), seed=5)
    worst, flagged_ok = [], True
    for k, seed in enumerate(SEEDS):
        sim = simulate_registration_case(population.vertices[k], population.faces, seed=seed,
                                         settings=RegistrationStudySettings())  # fmt: skip
        renderer = splat_renderer(sim["ct"], sim["labels"], RegistrationSettings().factors)
        res = register_multibody(sim["ct"], sim["labels"], sim["views"], seed=seed,
                                 renderer=renderer, dislocated=sim["bone"])  # fmt: skip
        errors = []
        for b in BONES:
            c = renderer.centroid(b)[None]
            errors.append(float(np.linalg.norm(tf.apply(res.poses[b], c)
                                               - tf.apply(sim["truth"][b], c))))  # fmt: skip
        worst.append(max(errors))
        flagged_ok &= max(errors) <= 4.0 or not res.converged
        print(seed, np.round(errors, 2), res.converged, res.warnings)
    assert sum(w < 1.0 for w in worst) >= 2, worst
    assert flagged_ok, worst


@pytest.mark.slow
def test_a_start_turned_30_deg_out_of_plane_is_recovered():
    """The capture-range case at +30 deg about the first view's detector x axis (a patient
    sampled from the packaged model, no set-up error): the first guess moves such a start
    further off, so stage 1 also runs from the unguessed start and from it turned out of plane,
    and re-centres its +-10 deg box. Before both, this start ended 46 mm off, unflagged.
    Measured when written: every bone within 0.25-0.49 mm, converged (49 s with the simulation on 2
    cores; +30 deg about y: within 0.82 mm, left out of the suite for time)."""
    from pelvicnav.geometry import projection as pj
    from pelvicnav.register.initial import about

    population = load_population("model", n_subjects=1, seed=5)
    settings = RegistrationStudySettings(setup_mm=0.0, setup_deg=0.0)
    sim = simulate_registration_case(population.vertices[0], population.faces, seed=3,
                                     settings=settings)  # fmt: skip
    iso = np.mean(list(sim["centroids"].values()), axis=0)  # the study's isocentre
    R = pj.decompose_projection(sim["views"].projections[0]).carm_from_world
    renderer = splat_renderer(sim["ct"], sim["labels"], RegistrationSettings().factors)
    start = dict.fromkeys(BONES, about(iso, R[0], 30.0) @ sim["truth"]["sacrum"])
    res = register_multibody(sim["ct"], sim["labels"], sim["views"], init_poses=start, seed=0,
                             renderer=renderer, dislocated=sim["bone"])  # fmt: skip
    errors = [float(np.linalg.norm(tf.apply(res.poses[b], sim["centroids"][b][None])
                                   - tf.apply(sim["truth"][b], sim["centroids"][b][None])))
              for b in BONES]  # fmt: skip
    assert max(errors) < 1.5, (errors, res.warnings)
    assert res.converged, res.warnings


@pytest.mark.slow
def test_a_pelvis_misplaced_in_depth_is_found_again_from_the_dislocated_bone(real_atlas_path):
    """Registration study seed 269 case 28 (atlas subject 43, right hip dislocated 1.6 mm /
    4.8 deg): every stage-1 run put the sacrum and the left hip 25 and 35 mm off in depth,
    where the final GO was 0.41 per view and nothing flagged it; the dislocated right hip was
    0.3 mm off. Stage 1 run again from where the right hip puts the pelvis
    (``RegistrationSettings.anchored_probe``) finds the truth. Measured when written: every bone
    within 0.11-0.53 mm, converged (the first attempt's similarity 0.818, the new one 0.911)."""
    from pelvicnav.io.atlas import load_atlas

    atlas = load_atlas(real_atlas_path)
    seed, case = 269, 28
    sim = simulate_registration_case(atlas.vertices[case % atlas.n_subjects], atlas.faces,
                                     seed=seed * 1000 + case,
                                     settings=RegistrationStudySettings())  # fmt: skip
    res = register_multibody(sim["ct"], sim["labels"], sim["views"], seed=seed + case,
                             dislocated=sim["bone"])  # fmt: skip
    errors = [float(np.linalg.norm(tf.apply(res.poses[b], sim["centroids"][b][None])
                                   - tf.apply(sim["truth"][b], sim["centroids"][b][None])))
              for b in BONES]  # fmt: skip
    assert max(errors) < 1.0, (errors, res.warnings)
    assert res.converged, res.warnings
    assert res.warnings[0].startswith("stage 1 from where the right_hip puts the pelvis")
