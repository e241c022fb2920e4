"""Shared fixtures: phantoms are seeded factories, so tests are reproducible."""

import numpy as np
import pytest

from wss_nlp import geometry as geo
from wss_nlp import phantoms
from wss_nlp import preprocess as pp


def geometry_problem(acq):
    """Preprocess slice 0 of an acquisition into a geometry problem."""
    mag = acq.magnitude[0]
    m = pp.normalize_magnitude(mag, pp.histogram_peaks(mag))
    lum = pp.find_lumen(m, acq.grid)
    return geo.GeometryProblem(acq.grid, m, lum.center, lum.r0, lum.r1, lum.r_area)


@pytest.fixture(scope="session")
def fourier_noise_free():
    """Lumen whose radius lies in V_4, no noise, no dephasing (venc far above the velocities)."""
    return phantoms.make_phantom("fourier", h_mm=0.5, snr=None, seed=3, venc=100.0)


@pytest.fixture(scope="session")
def laminar_snr25():
    return phantoms.make_phantom("laminar", h_mm=1.0, snr=25, seed=7)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
