import numpy as np
import pytest

from pelvicnav.geometry import projection as pj
from pelvicnav.register.pyramid import blurred
from pelvicnav.register.settings import PyramidSettings


def _image(seed=0):
    return np.random.default_rng(seed).normal(size=(64, 64))


def test_blurred_bins_then_blurs_by_sample_spacing():
    carm = pj.CArm(rows=64, cols=64, pixel_spacing=(1.0, 1.0))
    P = carm.projection_matrix
    points = np.zeros((10, 3))  # at the isocentre
    img = _image()
    binned = img.reshape(32, 2, 32, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(blurred(img, 2, 0.0, points, P), binned)  # exact renderer
    np.testing.assert_allclose(blurred(img, 2, 3.0, points, P, blur=0.0), binned)
    weak = blurred(img, 2, 3.0, points, P, blur=0.2)
    strong = blurred(img, 2, 3.0, points, P, blur=0.8)
    assert binned.std() > weak.std() > strong.std()  # white noise: more blur, less variance
    np.testing.assert_allclose(strong.mean(), binned.mean(), atol=1e-2)


def test_blur_settings():
    assert len(PyramidSettings().blur) == len(PyramidSettings().factors)
    assert PyramidSettings().blur[-1] == 0.0  # the fine level is not blurred (see the docstring)
    with pytest.raises(ValueError, match="blur must be >= 0"):
        PyramidSettings(blur=(0.4, -1.0))
    with pytest.raises(ValueError, match="one value per level"):
        PyramidSettings(blur=(0.4,))
