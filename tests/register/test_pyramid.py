import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, gaussian_gradient_magnitude

from pelvicnav.geometry import projection as pj
from pelvicnav.register.pyramid import blurred, level_blur, noise_to_edge
from pelvicnav.register.settings import PyramidSettings


def _noise(seed=0):
    return np.random.default_rng(seed).normal(size=(64, 64))


def _edges(n=128):
    """A blurred disc and bar: bone-like edges, no noise."""
    r, c = np.mgrid[:n, :n]
    img = ((r - n / 2) ** 2 + (c - n / 2) ** 2 < (n / 4) ** 2).astype(float)
    img[10:20, :] += 0.5
    return gaussian_filter(img, 1.5)


def test_blurred_by_sample_spacing():
    P = pj.CArm(rows=64, cols=64, pixel_spacing=(1.0, 1.0)).projection_matrix
    points = np.zeros((10, 3))  # at the isocentre
    img = _noise()
    binned = img.reshape(32, 2, 32, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(blurred(binned, 3.0, points, P, blur=0.0), binned)
    np.testing.assert_allclose(blurred(binned, 0.0, points, P, blur=0.4),  # exact: a pixel
                               gaussian_filter(binned, 0.4, mode="nearest"))  # fmt: skip
    weak = blurred(binned, 3.0, points, P, blur=0.2)
    strong = blurred(binned, 3.0, points, P, blur=0.8)
    assert binned.std() > weak.std() > strong.std()  # white noise: more blur, less variance
    np.testing.assert_allclose(strong.mean(), binned.mean(), atol=1e-2)


def test_noise_to_edge_reads_the_noise_against_the_edges():
    clean = _edges()
    rng = np.random.default_rng(1)
    assert noise_to_edge(clean) < 0.05
    edge = np.percentile(gaussian_gradient_magnitude(clean, 2.0), 95)
    ratios = []
    for sd in (0.005, 0.02, 0.08):
        r = noise_to_edge(clean + rng.normal(0, sd, clean.shape))
        ratios.append(r)
        assert r * edge == pytest.approx(sd, rel=0.25)  # the noise's sd, edges left out
    assert ratios[0] < ratios[1] < ratios[2]
    assert noise_to_edge(10 * clean + rng.normal(0, 0.2, clean.shape)) == pytest.approx(
        noise_to_edge(clean + rng.normal(0, 0.02, clean.shape)), rel=0.15
    )  # scale-free
    assert noise_to_edge(np.ones((16, 16))) == 0.0


def test_level_blur_rises_with_the_noise():
    pyr = PyramidSettings()  # blur (0.4, 0), noise_blur 0.4 over ratios 0.75-1.5
    clean = _edges()
    assert level_blur(clean, 0.0, pyr) == 0.0
    assert level_blur(clean, 0.4, pyr) == 0.4
    rng = np.random.default_rng(3)
    seen = []
    for sd in (0.01, 0.05, 0.1, 0.2, 0.5):
        noisy = clean + rng.normal(0, sd, clean.shape)
        r = noise_to_edge(noisy)
        expected = 0.4 * np.clip((r - 0.75) / 0.75, 0, 1)
        assert level_blur(noisy, 0.0, pyr) == pytest.approx(expected)
        assert level_blur(noisy, 0.3, pyr) == pytest.approx(max(0.3, expected))
        seen.append(expected)
    assert seen[0] == 0.0 and seen[-1] == pytest.approx(0.4)
    assert any(0 < e < 0.4 for e in seen)  # the ramp between


def test_blur_settings():
    assert len(PyramidSettings().blur) == len(PyramidSettings().factors)
    assert PyramidSettings().blur[-1] == 0.0  # the fine level is not blurred (see the docstring)
    with pytest.raises(ValueError, match="blur must be >= 0"):
        PyramidSettings(blur=(0.4, -1.0))
    with pytest.raises(ValueError, match="blur must be >= 0"):
        PyramidSettings(noise_blur=-0.1)
    with pytest.raises(ValueError, match="noise_ratio"):
        PyramidSettings(noise_ratio=(1.5, 0.75))
    with pytest.raises(ValueError, match="one value per level"):
        PyramidSettings(blur=(0.4,))
