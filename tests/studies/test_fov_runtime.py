"""Field-of-view crops keep their geometry; the runtime summary reads the paper's table."""

from __future__ import annotations

import numpy as np

from pelvicnav.geometry import projection as pj
from pelvicnav.studies.fov import CLINICAL_CARM, _crop_window, _shifted, _visible
from pelvicnav.studies.runtime import STEPS, summarise_runtime


def test_a_cropped_view_projects_every_point_to_the_same_pixel_of_the_crop():
    carm = pj.CArm(isocenter=(0.0, 0.0, 0.0), **dict(CLINICAL_CARM))
    P = carm.projection_matrix
    rng = np.random.default_rng(0)
    points = rng.uniform(-80, 80, (50, 3))
    r0, c0 = 101, 37
    moved = pj.project(_shifted(P, r0, c0), points)
    assert np.allclose(moved, pj.project(P, points) - [c0, r0])
    assert abs(carm.source_to_detector / carm.source_to_isocenter - 1.1) < 1e-12  # magnification


def test_crop_windows_keep_two_bones_in_view():
    carm = pj.CArm(isocenter=(0.0, 0.0, 0.0), **dict(CLINICAL_CARM))
    P = carm.projection_matrix
    centres = {"sacrum": (0, 40, 20), "left_hip": (80, 0, 0), "right_hip": (-80, 0, 0)}
    rng = np.random.default_rng(1)
    sim = {
        "views": type("V", (), {"images": (np.zeros((512, 512)),),
                                "pixel_spacing": ((340 / 512, 340 / 512),)})(),
        "true_projections": (P,), "truth": {b: np.eye(4) for b in centres},
        "landmarks": {b: np.asarray(c) + rng.normal(0, 25, (40, 3)) for b, c in centres.items()},
    }  # fmt: skip
    for size in (340.0, 200.0, 150.0):
        r0, c0, side, vis = _crop_window(sim, size, 0.2, np.random.default_rng(2))
        assert side == round(size / (340 / 512))
        assert sum(v >= 0.2 for v in vis.values()) >= 2
        for b, v in vis.items():
            window = (c0, r0, c0 + side, r0 + side)
            assert v == _visible(P, sim["landmarks"][b], window)


def test_runtime_summary_has_every_step_with_the_paper_alongside():
    rows = [{s: float(k + i) for i, s in enumerate(STEPS)} for k in range(4)]
    summary = summarise_runtime(rows)
    assert [s["step"] for s in summary] == [s.removesuffix("_s") for s in STEPS]
    assert summary[0]["median_s"] == 1.5 and summary[0]["iqr_s"] == 1.5
    assert summary[0]["paper_s"] == "122.0 ± 5.7"


def test_the_simulated_patient_fills_the_clinical_field_of_view():
    """Every ray of the 340 mm detector crosses the simulated CT at the patient's centre plane
    (with room for the set-up error): no CT end shows up in the radiograph as a hard edge."""
    from pelvicnav.phantom.ctsynth import CTOptions, synthesize_ct
    from pelvicnav.phantom.population import load_population
    from pelvicnav.studies.fov import CLINICAL_MARGIN_MM

    pop = load_population("model", n_subjects=1)
    V = pop.vertices[0]
    options = CTOptions(spacing=(4.0, 4.0, 4.0), margin_mm=CLINICAL_MARGIN_MM, femurs=False,
                        bowel_gas=False)  # fmt: skip
    ct = synthesize_ct(V, pop.faces, rng=np.random.default_rng(0), options=options)
    corners = np.array([[0, 0, 0], np.array(ct.hu.shape) - 1], dtype=float)
    lo, hi = np.sort(ct.hu.world_points(corners), axis=0)
    carm = pj.CArm(isocenter=tuple(V.reshape(-1, 3).mean(axis=0)), **dict(CLINICAL_CARM))
    half = (
        0.5
        * carm.cols
        * carm.pixel_spacing[1]
        * carm.source_to_isocenter
        / (carm.source_to_detector)
    )  # the field at the isocentre, mm
    iso = np.asarray(carm.isocenter)
    setup = 20.0
    for axis in (0, 2):  # AP view: left-right and head-foot span the detector
        assert lo[axis] <= iso[axis] - half - setup and hi[axis] >= iso[axis] + half + setup
