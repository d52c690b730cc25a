"""C-arm projection matrices: construction, decomposition, 6/9-DoF forms, project/back-project."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf


@st.composite
def carms(draw):
    return pj.CArm(
        source_to_detector=draw(st.floats(900, 1300)),
        source_to_isocenter=draw(st.floats(450, 850)),
        rows=draw(st.integers(64, 1024)),
        cols=draw(st.integers(64, 1024)),
        pixel_spacing=(draw(st.floats(0.1, 1.0)), draw(st.floats(0.1, 1.0))),
        principal_point=(draw(st.floats(-50, 600)), draw(st.floats(-50, 600))),
        orbit_deg=draw(st.floats(-170, 170)),
        tilt_deg=draw(st.floats(-80, 80)),
        roll_deg=draw(st.floats(-170, 170)),
        isocenter=tuple(draw(st.lists(st.floats(-300, 300), min_size=3, max_size=3))),
    )


def _same_carm(a: pj.CArm, b: pj.CArm) -> None:
    np.testing.assert_allclose(b.source_to_detector, a.source_to_detector, rtol=1e-9)
    np.testing.assert_allclose(b.principal_point_px, a.principal_point_px, atol=1e-6)
    for name in ("orbit_deg", "tilt_deg", "roll_deg"):
        np.testing.assert_allclose(getattr(b, name), getattr(a, name), atol=1e-7, err_msg=name)
    np.testing.assert_allclose(b.isocenter, a.isocenter, atol=1e-6)
    np.testing.assert_allclose(b.projection_matrix, a.projection_matrix, atol=1e-8, rtol=1e-9)


@given(carms())
def test_parameters_to_matrix_to_parameters(carm):
    back = pj.CArm.from_projection_matrix(
        carm.projection_matrix,
        rows=carm.rows,
        cols=carm.cols,
        pixel_spacing=carm.pixel_spacing,
        source_to_isocenter=carm.source_to_isocenter,
    )
    _same_carm(carm, back)


@given(carms())
def test_isocentre_projects_to_principal_point(carm):
    uv = pj.project(carm.projection_matrix, np.asarray(carm.isocenter))
    np.testing.assert_allclose(uv, carm.principal_point_px, atol=1e-7)


@given(carms(), st.floats(-400, 400))
def test_magnification_is_sdd_over_source_distance(carm, shift):
    # Points on the central ray: magnification = SDD / |point - source|.
    axis = carm.rotation[:, 2]
    p = np.asarray(carm.isocenter) + shift * axis
    dist = np.linalg.norm(p - carm.source)
    assert carm.magnification(p) == pytest.approx(carm.source_to_detector / dist, rel=1e-9)
    # The same magnification is what a small displacement parallel to the detector shows.
    P = carm.projection_matrix
    du = pj.project(P, p + 0.01 * carm.rotation[:, 0]) - pj.project(P, p)
    mm_on_detector = du[0] * carm.pixel_spacing[1]
    assert mm_on_detector / 0.01 == pytest.approx(carm.source_to_detector / dist, rel=1e-6)


def test_known_points_in_ap_and_lateral_views():
    ap = pj.CArm()
    mag = 1100.0 / 600.0
    px = 300.0 / 512
    c = 255.5
    np.testing.assert_allclose(ap.source, [0, -600, 0])  # source anterior in the AP view
    P = ap.projection_matrix
    # 10 mm to the patient's left: to the right in the radiological display.
    np.testing.assert_allclose(pj.project(P, [10, 0, 0]), [c + 10 * mag / px, c], atol=1e-9)
    # 10 mm superior: up (smaller row).
    np.testing.assert_allclose(pj.project(P, [0, 0, 10]), [c, c - 10 * mag / px], atol=1e-9)
    # Depth: a point 100 mm posterior is further from the source, so less magnified.
    np.testing.assert_allclose(
        pj.project(P, [10, 100, 0]), [c + 10 * (1100 / 700) / px, c], atol=1e-9
    )

    lat = pj.CArm(orbit_deg=90.0)
    np.testing.assert_allclose(lat.source, [600, 0, 0], atol=1e-9)  # source on the patient's left
    P = lat.projection_matrix
    np.testing.assert_allclose(pj.project(P, [0, 10, 0]), [c + 10 * mag / px, c], atol=1e-9)
    np.testing.assert_allclose(pj.project(P, [0, 0, 10]), [c, c - 10 * mag / px], atol=1e-9)
    np.testing.assert_allclose(pj.project(P, [100, 0, 0]), [c, c], atol=1e-9)  # on the axis


def test_tilt_moves_source_cranially():
    inlet = pj.CArm(tilt_deg=40.0)
    direction = (inlet.source - np.asarray(inlet.isocenter)) / 600.0
    np.testing.assert_allclose(direction, [0, -np.cos(np.radians(40)), np.sin(np.radians(40))])


@given(carms())
def test_decomposition(carm):
    P = carm.projection_matrix
    dec = pj.decompose_projection(3.7 * P)  # any scale of P
    K, R = dec.intrinsics, dec.carm_from_world
    assert np.allclose(np.tril(K, -1), 0)
    assert np.all(np.diag(K) > 0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(dec.source, carm.source, atol=1e-6)
    np.testing.assert_allclose(K, carm.intrinsics, rtol=1e-9, atol=1e-7)
    rebuilt = K @ np.hstack([R, -R @ dec.source[:, None]])
    np.testing.assert_allclose(pj.normalize_projection(rebuilt), P, atol=1e-8)
    # Normalised: w is the depth in mm.
    np.testing.assert_allclose(pj.depth(P, np.asarray(carm.isocenter)), carm.source_to_isocenter)


@given(st.lists(carms(), min_size=1, max_size=4), st.floats(-5.0, 5.0))
def test_batched_normalisation_and_intrinsics_equal_the_decomposition(carms_, scale):
    Ps = np.stack([c.projection_matrix for c in carms_]) * (scale if abs(scale) > 0.01 else 1.0)
    normal = pj.normalize_projections(Ps)
    K = pj.intrinsics_of(Ps)
    for P, N, k in zip(Ps, normal, K, strict=True):
        np.testing.assert_allclose(N, pj.normalize_projection(P), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(k, pj.decompose_projection(P).intrinsics, rtol=1e-9, atol=1e-7)


def test_batched_normalisation_reports_the_one_matrix_error():
    Ps = np.stack([pj.CArm().projection_matrix] * 3)
    Ps[1, 2, :3] = Ps[1, 0, :3]
    with pytest.raises(ValueError, match="singular"):
        pj.normalize_projections(Ps)
    Ps[1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        pj.intrinsics_of(Ps)
    with pytest.raises(ValueError, match=r"\(N, 3, 4\)"):
        pj.normalize_projections(Ps[0])


def test_batched_intrinsics_keep_leading_axes_and_reject_other_shapes():
    P = pj.CArm().projection_matrix
    assert pj.intrinsics_of(np.stack([[P, P]] * 3)).shape == (3, 2, 3, 3)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 4\)"):
        pj.intrinsics_of(np.eye(4))


@given(carms(), st.lists(st.floats(-40, 40), min_size=6, max_size=6))
def test_projections_from_sources_equal_one_geometry_each(carm, offsets):
    g = carm.nine_dof()
    kw = {"rows": carm.rows, "cols": carm.cols, "pixel_spacing": carm.pixel_spacing}
    sources = np.asarray(g.source_in_detector) + np.reshape(offsets, (2, 3))
    batch = pj.projections_from_sources(sources, g.world_from_detector, **kw)
    for s, P in zip(sources, batch, strict=True):  # each: its own source, the shared detector
        back = pj.nine_dof_from_projection(P, **kw)
        np.testing.assert_allclose(back.source_in_detector, s, atol=1e-6)
        np.testing.assert_allclose(back.world_from_detector, g.world_from_detector, atol=1e-7)
    with pytest.raises(ValueError, match="s_z > 0"):
        pj.projections_from_sources(-sources, g.world_from_detector, **kw)


@given(carms(), st.lists(st.floats(0, 1000), min_size=2, max_size=2), st.floats(100, 1000))
def test_backprojected_rays_project_back(carm, pixel, t):
    P = carm.projection_matrix
    source, d = pj.backproject(P, np.array(pixel))
    np.testing.assert_allclose(source, carm.source, atol=1e-6)
    assert np.linalg.norm(d) == pytest.approx(1.0)
    np.testing.assert_allclose(pj.project(P, source + t * d), pixel, atol=1e-6)
    assert pj.depth(P, source + t * d) > 0  # the ray heads to the detector


def test_points_behind_the_source_are_nan():
    carm = pj.CArm()
    uv = pj.project(carm.projection_matrix, [[0, -700, 0], [0, 0, 0]])
    assert np.all(np.isnan(uv[0])) and np.all(np.isfinite(uv[1]))


@given(carms())
def test_nine_dof_round_trips(carm):
    g = carm.nine_dof()
    kw = {"rows": carm.rows, "cols": carm.cols, "pixel_spacing": carm.pixel_spacing}
    P9 = pj.projection_from_nine_dof(g, **kw)
    np.testing.assert_allclose(P9, carm.projection_matrix, atol=1e-8, rtol=1e-9)
    back = pj.nine_dof_from_projection(P9, **kw)
    np.testing.assert_allclose(back.vector(), g.vector(), atol=1e-7)
    again = pj.NineDof.from_vector(g.vector())
    np.testing.assert_allclose(again.world_from_detector, g.world_from_detector, atol=1e-12)
    assert g.source_in_detector[2] == pytest.approx(carm.source_to_detector)


def test_nine_dof_source_offset_moves_principal_point():
    # Equation 9: the source's (s_x, s_y) is where the central ray meets the detector, so a point
    # on the detector plane projects onto itself whatever the source position.
    g = pj.NineDof(source_in_detector=(12.0, -7.5, 1000.0), world_from_detector=np.eye(4))
    P = pj.projection_from_nine_dof(g, rows=101, cols=201, pixel_spacing=(0.5, 0.25))
    np.testing.assert_allclose(pj.project(P, [12.0, -7.5, 0.0]), [100 + 48, 50 - 15], atol=1e-9)
    np.testing.assert_allclose(pj.project(P, [3.0, 4.0, 0.0]), [100 + 12, 50 + 8], atol=1e-9)
    np.testing.assert_allclose(pj.decompose_projection(P).source, [12.0, -7.5, -1000.0])


def test_detector_centre_is_sdd_along_the_beam():
    carm = pj.CArm(orbit_deg=25, tilt_deg=10)
    np.testing.assert_allclose(
        np.linalg.norm(carm.detector_center - carm.source), carm.source_to_detector
    )
    uv = pj.project(carm.projection_matrix, carm.detector_center)
    np.testing.assert_allclose(uv, [255.5, 255.5], atol=1e-9)


@given(
    st.lists(st.floats(-50, 50), min_size=3, max_size=3),
    st.lists(st.floats(-30, 30), min_size=3, max_size=3),
)
def test_six_dof_round_trip_and_rotation_centre(t, r):
    centre = np.array([40.0, -20.0, -400.0])
    params = np.array(t + r)
    T = pj.six_dof_pose(params, center=centre)
    np.testing.assert_allclose(pj.six_dof_params(T, center=centre), params, atol=1e-9)
    # The centre moves by exactly the translation.
    np.testing.assert_allclose(tf.apply(T, centre[None])[0], centre + params[:3], atol=1e-9)
    # 6-DoF: P stays, the object moves; projecting moved points = projecting with P @ T.
    P = pj.CArm(isocenter=tuple(centre)).projection_matrix
    pts = centre + np.array([[10.0, 0, 0], [0, 20, 5]])
    np.testing.assert_allclose(pj.project(P @ T, pts), pj.project(P, tf.apply(T, pts)), atol=1e-8)


# ---- bad input ---------------------------------------------------------------------------------


def test_singular_projection_matrix():
    P = pj.CArm().projection_matrix
    P[2, :3] = P[0, :3]  # rank-deficient left block
    with pytest.raises(ValueError, match="singular"):
        pj.decompose_projection(P)
    with pytest.raises(ValueError, match="singular"):
        pj.project(np.zeros((3, 4)), [0, 0, 0])


def test_bad_projection_shapes_and_values():
    with pytest.raises(ValueError, match=r"shape \(3, 4\)"):
        pj.project(np.eye(4), [0, 0, 0])
    P = pj.CArm().projection_matrix
    P[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        pj.backproject(P, [0, 0])
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        pj.project(pj.CArm().projection_matrix, [0, 0])


def test_bad_carm_parameters():
    with pytest.raises(ValueError, match="source_to_isocenter < source_to_detector"):
        pj.CArm(source_to_detector=500.0, source_to_isocenter=600.0)
    with pytest.raises(ValueError, match="pixel spacing"):
        pj.CArm(pixel_spacing=(0.0, 0.5))
    with pytest.raises(ValueError, match="positive integers"):
        pj.CArm(rows=0)
    with pytest.raises(ValueError, match="isocenter"):
        pj.CArm(isocenter=(0.0, np.nan, 0.0))
    with pytest.raises(ValueError, match="wrong pixel spacing"):
        pj.CArm.from_projection_matrix(
            pj.CArm().projection_matrix,
            rows=512,
            cols=512,
            pixel_spacing=(0.5, 0.6),
            source_to_isocenter=600,
        )
    with pytest.raises(ValueError, match="s_z > 0"):
        pj.NineDof(source_in_detector=(0, 0, -5), world_from_detector=np.eye(4))
    with pytest.raises(ValueError, match="not rigid"):
        pj.NineDof(source_in_detector=(0, 0, 5), world_from_detector=np.diag([2.0, 2, 2, 1]))
