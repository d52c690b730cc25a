"""Radiograph simulation: dose scaling of noise, attenuation, views, cropping, errors."""

from __future__ import annotations

import numpy as np
import pytest

from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj
from pelvicnav.phantom.xray import (
    MU_WATER_PER_MM,
    DetectorModel,
    crop,
    mu_from_hu,
    quanta_per_pixel,
    simulate_radiograph,
    standard_view,
)

DOSES = (50.0, 15.0, 5.0, 1.5, 0.5)


@pytest.fixture(scope="module")
def water_slab():
    """A 300 x 100 x 300 mm box of water (0 HU) at 5 mm voxels, centred at the isocentre."""
    data = np.zeros((60, 20, 60), dtype=np.float32)
    return Volume.from_spacing(data, [5.0] * 3, [-147.5, -47.5, -147.5])


def _carm():
    # 128 x 2 mm = 256 mm at the detector, ~140 mm at the isocentre: inside the slab.
    return pj.CArm(rows=128, cols=128, pixel_spacing=(2.0, 2.0))


REGION = (slice(14, 114), slice(14, 114))  # 10,000 pixels: the variance is known to ~2%


def _noise_variance(ct, carm, dose, detector):
    """Variance of the noise alone: half the variance of the difference of two realisations."""
    a = simulate_radiograph(
        ct, carm, dose_ugy=dose, rng=np.random.default_rng(1), detector=detector
    )
    b = simulate_radiograph(
        ct, carm, dose_ugy=dose, rng=np.random.default_rng(2), detector=detector
    )
    d = (a.line_integrals - b.line_integrals)[REGION]
    return float(np.var(d) / 2), a


def test_unattenuated_noise_scales_as_one_over_dose(water_slab):
    air = Volume(np.full(water_slab.shape, -1000.0, np.float32), water_slab.world_from_ijk)
    v = [_noise_variance(air, _carm(), d, DetectorModel())[0] for d in DOSES]
    product = np.array(v) * np.array(DOSES)
    np.testing.assert_allclose(product / product[0], 1.0, rtol=0.10)


def test_noise_through_the_slab_scales_as_one_over_dose_and_matches_the_model(water_slab):
    det = DetectorModel()
    products = []
    sigma = det.blur_sigma_px
    x = np.arange(-2, 3)
    k = np.exp(-(x**2) / (2 * sigma**2))
    blur_factor = float(np.sum(k**2) / np.sum(k) ** 2) ** 2
    for dose in DOSES:
        var, rad = _noise_variance(water_slab, _carm(), dose, det)
        products.append(var * dose)
        # Quantum noise through p: var(-ln I) = blur_factor / (N0 e^-p) (+ small electronic part).
        n = rad.incident_quanta * np.exp(-float(np.median(rad.line_integrals[REGION])))
        expected = blur_factor / n + (det.electronic_sigma / n) ** 2
        assert var == pytest.approx(expected, rel=0.06)
    np.testing.assert_allclose(np.array(products) / products[0], 1.0, rtol=0.10)


def test_high_dose_recovers_the_line_integrals():
    small = Volume.from_spacing(np.zeros((30, 25, 30), np.float32), [4.0] * 3, [-58, -48, -58])
    carm = pj.CArm(rows=96, cols=96, pixel_spacing=(4.0, 4.0))  # corners see air
    rad = simulate_radiograph(
        small, carm, dose_ugy=1e6, rng=np.random.default_rng(0),
        detector=DetectorModel(blur_sigma_px=0.0, electronic_sigma=0.0),
    )  # fmt: skip
    # The centre ray crosses 100 mm of water (the slab's y extent).
    assert rad.line_integrals[47:49, 47:49].mean() == pytest.approx(100 * MU_WATER_PER_MM, rel=0.02)
    assert abs(rad.line_integrals[:5, :5].mean()) < 1e-3  # air


def test_hu_to_mu_and_quanta():
    np.testing.assert_allclose(
        mu_from_hu([-1000, 0, 1000, -2000]), [0, 0.02059, 0.04118, 0], rtol=1e-5
    )
    carm = pj.CArm()
    n50 = quanta_per_pixel(50, carm, DetectorModel())
    assert 5e4 < n50 < 2e5  # ~1e5 quanta per pixel unattenuated at nominal fluoroscopy dose
    assert quanta_per_pixel(0.5, carm, DetectorModel()) == pytest.approx(n50 / 100)


def test_standard_views():
    assert standard_view("AP").orbit_deg == 0
    inlet = standard_view("inlet")
    assert inlet.source[2] > 0  # source cranial: beam angled caudally
    assert standard_view("outlet").source[2] < 0
    lateral = standard_view("lateral")
    np.testing.assert_allclose(lateral.source, [600, 0, 0], atol=1e-9)
    assert standard_view("oblique30").tilt_deg == -20
    with pytest.raises(ValueError, match="unknown view 'sideways'"):
        standard_view("sideways")


def test_crop_keeps_world_points_on_the_same_physical_pixel():
    carm = pj.CArm(rows=64, cols=64)
    img = np.arange(64 * 64, dtype=float).reshape(64, 64)
    sub, P2 = crop(img, carm.projection_matrix, top=10, left=20, rows=30, cols=25)
    assert sub.shape == (30, 25)
    x = np.array([3.0, -2.0, 5.0])
    np.testing.assert_allclose(pj.project(P2, x), pj.project(carm.projection_matrix, x) - [20, 10])
    assert sub[0, 0] == img[10, 20]
    with pytest.raises(ValueError, match="exceeds the image"):
        crop(img, carm.projection_matrix, top=50, left=0, rows=30, cols=10)


def test_bad_input(water_slab):
    carm = _carm()
    rng = np.random.default_rng(0)
    for dose in (0.0, -5.0, np.nan):
        with pytest.raises(ValueError, match="dose must be a positive"):
            simulate_radiograph(water_slab, carm, dose_ugy=dose, rng=rng)
    away = pj.CArm(rows=32, cols=32, pixel_spacing=(1.0, 1.0), isocenter=(0.0, 0.0, 800.0))
    with pytest.raises(ValueError, match="misses the CT volume"):
        simulate_radiograph(water_slab, away, dose_ugy=5.0, rng=rng)
