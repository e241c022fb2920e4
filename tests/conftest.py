"""Shared fixtures: phantoms are seeded factories, so tests are reproducible."""

import casadi as ca
import numpy as np
import pytest

from wss_nlp.models import geometry as geo
from wss_nlp.synthetic import phantoms
from wss_nlp.models import preprocess as pp


def geometry_problem(acq):
    """Preprocess slice 0 of an acquisition into a geometry problem."""
    mag = acq.magnitude[0]
    m = pp.normalize_magnitude(mag, pp.histogram_peaks(mag))
    lum = pp.find_lumen(m, acq.grid)
    return geo.GeometryProblem(acq.grid, m, lum.center, lum.r0, lum.r1, lum.r_area)


def assert_coupled_jacobian_is_exact(nlp, geometry, velocity, seed: int = 2, directions: int = 4) -> None:
    """The coupled NLP's hand-assembled chain-rule Jacobian equals CasADi's AD of its residual at a perturbed
    point (two exact derivatives of one expression: equal to rounding), compared through ``directions`` random
    forward products ``J v`` and as many reverse products ``J^T w`` (CasADi's forward and adjoint modes): a
    Jacobian that differs anywhere differs along a random direction with probability one, and the products
    avoid the dense AD Jacobian's graph (1.5 GB of memory on the k-space problem)."""
    rng = np.random.default_rng(seed)
    c_r, c_v = geometry.coefficients, velocity.coefficients
    x = np.concatenate([c_r + 0.05 * rng.normal(size=c_r.size), c_v * (1 + 0.1 * rng.normal(size=c_v.size))])
    n, m = nlp.x.numel(), nlp.residual.numel()
    v = ca.MX.sym("v", n, directions)
    w = ca.MX.sym("w", m, directions)
    f = ca.Function("j", [nlp.x, nlp.gamma, v, w], [nlp.jacobian, ca.jtimes(nlp.residual, nlp.x, v),
                                                     ca.jtimes(nlp.residual, nlp.x, w, True)])  # fmt: skip
    vv, ww = rng.normal(size=(n, directions)), rng.normal(size=(m, directions))
    mine, forward, reverse = (np.asarray(a) for a in f(x, geometry.gamma, vv, ww))
    assert np.max(np.abs(mine @ vv - forward)) <= 1e-9 * np.max(np.abs(forward))
    assert np.max(np.abs(mine.T @ ww - reverse)) <= 1e-9 * np.max(np.abs(reverse))


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
