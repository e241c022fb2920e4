import numpy as np
import pytest

from wss_nlp.core import radius as rad


def test_design_matrix_matches_series(rng):
    c = rng.normal(size=rad.n_coefficients(5))
    phi = rng.uniform(0, 2 * np.pi, 50)
    k = np.arange(1, 6)
    direct = c[0] + np.cos(np.outer(phi, k)) @ c[1:6] + np.sin(np.outer(phi, k)) @ c[6:]
    assert np.allclose(rad.evaluate(c, phi), direct, atol=1e-13)


@pytest.mark.parametrize("n", [0, 1, 4, 8])
def test_weighted_gram_from_three_products(rng, n):
    """B^T diag(d) B assembled from B^T [d, d cos N phi, d sin N phi] equals the direct product for scattered
    angles and signed weights (the same sums in another order: equal to rounding)."""
    phi = rng.uniform(-np.pi, np.pi, 300)
    d = rng.normal(size=300)
    b = rad.design_matrix(phi, n)
    direct = b.T @ (d[:, None] * b)
    stacked = np.concatenate([b.T @ d, b.T @ (d * np.cos(n * phi)), b.T @ (d * np.sin(n * phi))])
    assembled = (rad.weighted_gram_map(n) @ stacked).reshape(b.shape[1], b.shape[1])
    assert np.max(np.abs(assembled - direct)) < 1e-11 * np.sum(np.abs(d))
    assert np.max(np.abs(rad.weighted_gram(b, d) - direct)) < 1e-11 * np.sum(np.abs(d))


@pytest.mark.parametrize("s", [0, 1, 2, 3])
def test_sobolev_norm_against_quadrature(rng, s):
    # The trapezoidal rule with more than 2N+1 points integrates products of
    # trigonometric polynomials of degree N exactly, so the only error is rounding.
    c = rng.normal(size=rad.n_coefficients(7))
    phi = rad.uniform_angles(64)
    quad = sum(np.sum(rad.evaluate(c, phi, j) ** 2) * 2 * np.pi / phi.size for j in range(s + 1))
    assert rad.sobolev_norm(c, s) ** 2 == pytest.approx(quad, rel=1e-12)


def test_derivative_matrix_against_finite_difference(rng):
    c = rng.normal(size=rad.n_coefficients(4))
    phi = np.linspace(0, 6, 7)
    h = 1e-5
    fd = (rad.evaluate(c, phi + h) - rad.evaluate(c, phi - h)) / (2 * h)
    # central difference error ~ h^2 |R'''| / 6 with |R'''| <= sum k^3 |c_k| ~ 1e2
    assert np.allclose(rad.evaluate(c, phi, 1), fd, atol=1e-7)


def test_symbolic_equals_numeric(rng):
    import casadi as ca

    c = rng.normal(size=rad.n_coefficients(3))
    p = ca.SX.sym("p")
    f = ca.Function("f", [p], [rad.symbolic(ca.DM(c), p, 0), rad.symbolic(ca.DM(c), p, 2)])
    r0, r2 = f(0.7)
    assert float(r0) == pytest.approx(rad.evaluate(c, [0.7])[0], abs=1e-13)
    assert float(r2) == pytest.approx(rad.evaluate(c, [0.7], 2)[0], abs=1e-12)


def test_fit_recovers_trig_polynomial(rng):
    c = rng.normal(size=rad.n_coefficients(6))
    phi = rad.uniform_angles(40)
    assert np.allclose(rad.fit(phi, rad.evaluate(c, phi), 6), c, atol=1e-12)


def test_odd_length_required():
    with pytest.raises(ValueError):
        rad.n_fourier_from_size(4)
