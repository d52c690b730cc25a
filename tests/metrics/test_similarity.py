"""Similarity metrics: identity, scaling invariance, misalignment, content mismatch, batches."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, shift

from pelvicnav.metrics.similarity import gradient_ncc, gradient_orientation, ncc, sobel_gradients


@pytest.fixture(scope="module")
def image():
    """A smooth image with bone-like edges: a few blurred discs and bars on a gentle ramp."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:96, 0:96].astype(float)
    img = 0.01 * xx
    for _ in range(6):
        cy, cx, r = rng.uniform(15, 80), rng.uniform(15, 80), rng.uniform(6, 14)
        img += ((yy - cy) ** 2 + (xx - cx) ** 2 < r**2) * rng.uniform(0.5, 1.5)
    img[40:46, 10:85] += 0.8
    # A little texture: no two pixels share a gradient magnitude (no ties at the median).
    return gaussian_filter(img, 1.2) + rng.normal(0, 1e-3, img.shape)


def test_identical_images_score_best(image):
    go = gradient_orientation(image, image)
    assert go == pytest.approx(1.0, abs=0.02)
    assert ncc(image, image) == pytest.approx(1.0)
    assert gradient_ncc(image, image) == pytest.approx(1.0)


def test_invariant_to_positive_intensity_scaling(image):
    moved = shift(image, (1.5, -2.0), order=1, mode="nearest")
    for metric in (gradient_orientation, ncc, gradient_ncc):
        np.testing.assert_allclose(
            metric(image, 3.7 * moved + 12.0), metric(image, moved), rtol=1e-9
        )


def test_decreases_with_misalignment(image):
    shifts = [0.0, 1.0, 2.0, 4.0, 8.0]
    batch = np.stack([shift(image, (0.0, s), order=1, mode="nearest") for s in shifts])
    for metric in (gradient_orientation, ncc, gradient_ncc):
        scores = metric(image, batch)
        assert scores.shape == (5,)
        assert np.all(np.diff(scores) < 0), (metric.__name__, scores)


def test_go_is_robust_to_a_tool_in_the_radiograph_only(image):
    radiograph = image.copy()
    radiograph[10:80, 60:66] += 4.0  # a bright instrument absent from the DRRs
    radiograph = gaussian_filter(radiograph, 0.8)
    candidates = np.stack([shift(image, (dy, dx), order=1, mode="nearest") for dy, dx in
                           [(0, 0), (0, 2), (2, 0), (-2, 1), (3, -3)]])  # fmt: skip
    go = gradient_orientation(radiograph, candidates)
    assert np.argmax(go) == 0  # the true pose still wins
    assert go[0] > 0.6


def test_batch_matches_single_calls(image):
    rng = np.random.default_rng(1)
    batch = image + rng.normal(0, 0.05, (2, 3, *image.shape))
    out = gradient_orientation(image, batch)
    assert out.shape == (2, 3)
    assert out[1, 2] == pytest.approx(gradient_orientation(image, batch[1, 2]))


def test_sobel_of_a_ramp():
    yy, xx = np.mgrid[0:8, 0:9].astype(float)
    gx, gy = sobel_gradients(2.0 * xx - 3.0 * yy)
    np.testing.assert_allclose(gx[1:-1, 1:-1], 2.0)
    np.testing.assert_allclose(gy[1:-1, 1:-1], -3.0)


def test_bad_input(image):
    with pytest.raises(ValueError, match=r"moving images must have shape \(\.\.\., 96, 96\)"):
        gradient_orientation(image, image[:50])
    bad = image.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ncc(image, bad)
    with pytest.raises(ValueError, match="2D"):
        gradient_ncc(image[None], image)


def test_fast_go_equals_equation_10():
    from pelvicnav.metrics.similarity import GradientOrientation

    rng = np.random.default_rng(3)
    fixed = rng.random((40, 50))
    moving = rng.random((2, 3, 40, 50)).astype(np.float32)
    moving[0, 0] = fixed  # identical image: GO about 1
    go = GradientOrientation(fixed)
    np.testing.assert_allclose(go(moving), gradient_orientation(fixed, moving), rtol=1e-4)
    with pytest.raises(ValueError, match="shape"):
        go(np.zeros((3, 40, 49)))
    with pytest.raises(ValueError, match="NaN"):
        go(np.full((40, 50), np.nan))


def test_fast_go_reads_one_view_of_a_drr_stack_in_place_and_refuses_any_nan_or_inf():
    from pelvicnav.metrics.similarity import GradientOrientation

    rng = np.random.default_rng(5)
    fixed = rng.random((40, 50))
    stack = rng.random((4, 2, 40, 50)).astype(np.float32)  # (B, K, H, W): view 1 is strided
    go = GradientOrientation(fixed)
    np.testing.assert_array_equal(go(stack[:, 1]), go(np.ascontiguousarray(stack[:, 1])))
    np.testing.assert_allclose(go(stack[:, 1]), gradient_orientation(fixed, stack[:, 1]), rtol=1e-4)
    for bad in (np.nan, np.inf, -np.inf):
        for pixel in ((0, 0), (39, 49), (0, 49), (17, 23)):  # corners and the inside
            images = stack.copy()
            images[2, 1][pixel] = bad
            with pytest.raises(ValueError, match="NaN or infinity"):
                go(images[:, 1])


def test_gradient_ncc_class_equals_function():
    from pelvicnav.metrics.similarity import GradientNCC

    rng = np.random.default_rng(4)
    fixed = gaussian_filter(rng.random((30, 40)), 2)
    moving = gaussian_filter(rng.random((3, 30, 40)), (0, 2, 2))
    moving[0] = 3 * fixed + 1
    g = GradientNCC(fixed)
    np.testing.assert_allclose(g(moving), gradient_ncc(fixed, moving), atol=1e-6)  # float32 DRRs
    assert g(moving)[0] == pytest.approx(1.0, abs=1e-6)
    assert g(np.ones((2, 30, 40)))[0] == 0.0  # flat image: no gradient, no correlation
