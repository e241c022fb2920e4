import numpy as np
import pytest

from wss_nlp.models import preprocess as pp
from wss_nlp.errors import LumenTouchesBorderError, NoVesselError
from wss_nlp.models.measurement import VoxelGrid


def _disk_image(n=64, r=10.0, c=(0.0, 0.0), h=0.5, lo=0.2, hi=3.0, sigma=0.05, seed=0):
    grid = VoxelGrid((n, n), (h, h), (-(n - 1) * h / 2, -(n - 1) * h / 2))
    xc, yc = grid.centers()
    img = np.where(np.hypot(xc - c[0], yc - c[1]) < r, hi, lo)
    return grid, img + np.random.default_rng(seed).normal(0, sigma, img.shape)


def test_histogram_peaks_find_background_and_lumen():
    grid, img = _disk_image()
    norm = pp.histogram_peaks(img)
    # peaks are bin centres of a histogram ~ (3.2 / 64) wide: within one bin of the truth
    assert norm.m0 == pytest.approx(0.2, abs=0.06)
    assert norm.m1 == pytest.approx(3.0, abs=0.06)
    m = pp.normalize_magnitude(img, norm)
    assert m.min() >= 0 and m.max() <= 1


def test_find_lumen_centre_and_radius():
    grid, img = _disk_image(c=(1.3, -0.7))
    m = pp.normalize_magnitude(img, pp.histogram_peaks(img))
    lum = pp.find_lumen(m, grid)
    assert lum.center == pytest.approx((1.3, -0.7), abs=0.05)
    assert lum.r_area == pytest.approx(10.0, abs=0.1)
    assert lum.r0 < 10.0 < lum.r1


def test_no_vessel_in_pure_noise():
    rng = np.random.default_rng(1)
    grid = VoxelGrid((48, 48), (1.0, 1.0))
    img = np.abs(rng.normal(size=(48, 48)) + 1j * rng.normal(size=(48, 48)))
    with pytest.raises(NoVesselError, match="no vessel in view"):
        pp.find_lumen(pp.normalize_magnitude(img, pp.histogram_peaks(img)), grid)


def test_constant_image_has_no_vessel():
    with pytest.raises(NoVesselError, match="no contrast"):
        pp.histogram_peaks(np.ones((20, 20)))


def test_lumen_touching_border():
    grid, img = _disk_image(c=(12.0, 0.0))
    m = pp.normalize_magnitude(img, pp.histogram_peaks(img))
    with pytest.raises(LumenTouchesBorderError):
        pp.find_lumen(m, grid)
