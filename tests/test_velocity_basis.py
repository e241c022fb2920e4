import numpy as np
import pytest

import casadi as ca
import scipy.special

from wss_nlp.core import velocity_basis as vb


def _disk_quadrature(nr, nt):
    g, w = np.polynomial.legendre.leggauss(nr)
    rho, wr = 0.5 * (g + 1), 0.25 * w * (g + 1)
    t = 2 * np.pi * np.arange(nt) / nt
    rr, tt = np.meshgrid(rho, t, indexing="ij")
    ww = (wr[:, None] * np.full(nt, 2 * np.pi / nt)).ravel()
    return (rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel(), ww


@pytest.mark.parametrize("degree,order", [(6, None), (9, 3)])
def test_zernike_gram_matrices_against_2d_casadi_derivatives(degree, order):
    """1-D radial Laplacians (used for speed) must equal 2-D CasADi Hessian traces, exactly."""
    b = vb.ZernikeWallBasis(degree, order)
    xi = ca.SX.sym("xi", 2)
    v = b.symbolic(xi)
    lap = ca.vertcat(*[ca.trace(ca.hessian(v[i], xi)[0]) for i in range(b.size)])
    lap2 = ca.vertcat(*[ca.trace(ca.hessian(lap[i], xi)[0]) for i in range(b.size)])
    f = ca.Function("f", [xi], [v, lap, lap2])
    x, y, w = _disk_quadrature(degree + 6, 4 * degree + 8)  # exact for these polynomial integrands
    vals = [np.asarray(a) for a in f.map(x.size)(np.vstack([x, y]))]
    for t, a in enumerate(vals):
        ref = (a * w) @ a.T
        got = np.eye(b.size) if t == 0 else b.laplacian_gram(t)
        # entries grow to ~1e8 for t = 2; compare relative to the largest
        assert np.abs(got - ref).max() <= 1e-9 * max(1.0, np.abs(ref).max())


def test_zernike_values_vanish_on_wall_and_numpy_matches_casadi():
    b = vb.ZernikeWallBasis(8)
    t = np.linspace(0, 2 * np.pi, 17)
    assert np.abs(b.evaluate(np.cos(t), np.sin(t))).max() < 1e-12
    xi = ca.SX.sym("xi", 2)
    f = ca.Function("f", [xi], [b.symbolic(xi)])
    assert np.allclose(np.asarray(f([0.3, -0.2])).ravel(), b.evaluate(0.3, -0.2).ravel(), atol=1e-12)


def test_first_zernike_function_is_poiseuille():
    b = vb.ZernikeWallBasis(6)
    x, y = np.array([0.0, 0.5, 0.2]), np.array([0.0, 0.1, -0.7])
    v0 = b.evaluate(x, y)[:, 0]
    assert np.allclose(v0 / v0[0], 1 - x**2 - y**2)
    # ||Delta (1 - r^2)||^2 / ||1 - r^2||^2 = 16 pi / (pi / 3) = 48
    assert b.laplacian_gram(1)[0, 0] == pytest.approx(48.0, rel=1e-12)


def test_eigen_basis_is_orthonormal_and_solves_helmholtz():
    b = vb.DirichletEigenBasis(120.0)
    x, y, w = _disk_quadrature(60, 64)
    vals = b.evaluate(x, y)
    # Bessel functions are not polynomials; 60 Gauss nodes still give ~1e-12
    assert np.abs((vals.T * w) @ vals - np.eye(b.size)).max() < 1e-10
    xi = ca.MX.sym("xi", 2)
    v = b.symbolic(xi)
    lap = ca.vertcat(*[ca.trace(ca.hessian(v[i], xi)[0]) for i in range(b.size)])
    f = ca.Function("f", [xi], [v, lap])
    pv, pl = (np.asarray(a).ravel() for a in f([0.31, 0.42]))
    lam = np.array([j for _, j, _ in b.terms]) ** 2
    assert np.allclose(pl, -lam * pv, rtol=1e-9, atol=1e-9)  # -Delta v = lambda v via the callback's derivatives
    assert np.allclose(np.diag(b.laplacian_gram(1)), lam**2)


def test_bessel_callback_derivative_matches_scipy():
    z = ca.MX.sym("z")
    f = ca.Function("f", [z], [ca.jacobian(vb.bessel_j(2)(z), z)])
    assert float(f(3.7)) == pytest.approx(scipy.special.jvp(2, 3.7), rel=1e-12)


@pytest.mark.parametrize("m,k", [(0, 1), (3, 2), (7, 4), (12, 3)])
def test_chebyshev_bessel_matches_scipy_with_derivatives(m, k):
    j = scipy.special.jn_zeros(m, k)[-1]
    coef = vb.bessel_chebyshev(m, float(j))
    x = np.linspace(0, 1, 101)
    assert np.abs(vb.clenshaw(coef, x) - scipy.special.jv(m, j * x)).max() < 1e-13
    r = ca.SX.sym("r")
    f = ca.Function("f", [r], [ca.jacobian(vb.clenshaw(coef, r), r)])
    d = np.asarray(f.map(x.size)(x)).ravel()
    # derivative of the interpolant: error grows ~ degree^2 x 1e-16
    assert np.abs(d - j * scipy.special.jvp(m, j * x)).max() < 1e-10 * max(1.0, j)


def test_eigen_symbolic_chebyshev_equals_callbacks():
    b = vb.DirichletEigenBasis(150.0)
    xi = ca.MX.sym("xi", 2)
    f = ca.Function("f", [xi], [ca.jacobian(b.symbolic(xi), xi), ca.jacobian(b.symbolic(xi, exact_callbacks=True), xi)])
    a, c = (np.asarray(v) for v in f([0.6, -0.8]))
    assert np.abs(a - c).max() < 1e-10


def test_raw_values_through_the_transform_are_the_values_and_averages_agree():
    """``evaluate_raw @ transform`` is ``evaluate`` for every basis (Zernike, eigen, with a near-wall layer), and
    the voxel average taken function by function equals averaging the full value array (same sums)."""
    import scipy.sparse

    from wss_nlp.models import near_wall as nw

    rng = np.random.default_rng(8)
    rho, t = np.sqrt(rng.uniform(0, 1, 400)), rng.uniform(0, 2 * np.pi, 400)
    x, y = rho * np.cos(t), rho * np.sin(t)
    zernike = vb.ZernikeWallBasis(12, 4)
    for basis in (zernike, vb.DirichletEigenBasis(60.0), nw.EnrichedBasis(zernike, "wall_law", 0.01)):
        values = basis.evaluate(x, y)
        assert np.allclose(basis.evaluate_raw(x, y) @ basis.transform, values, rtol=0, atol=1e-12)
    average = scipy.sparse.csr_matrix((np.full(400, 0.25), (np.repeat(np.arange(100), 4), np.arange(400))))
    assert np.allclose(zernike.evaluate(x, y, average=average), average @ zernike.evaluate(x, y), rtol=0, atol=1e-12)
