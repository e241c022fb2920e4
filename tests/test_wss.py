"""The WSS formula, eq. (wss) with grad_x u = J^{-T} grad_xi v, against analytic fields."""

import numpy as np
import pytest

import casadi as ca

from wss_nlp.core import radius as rad
from wss_nlp.models import wss
from wss_nlp.core.mapping import symbolic_forward

COEF = np.array([10.0, 0.8, 0.5, -0.4, 0.3, 0.6, -0.2])  # a lumen in V_3
CENTER = (1.5, -0.5)
MU = 3.5e-3


class PulledBack:
    """v = u o phi_R for an analytic physical field u(x, y), as a CasADi expression in xi."""

    n_params = 1

    def __init__(self, u, r_in, eta):
        self.u, self.r_in, self.eta = u, r_in, eta

    def __call__(self, xi, p):
        x = symbolic_forward(xi, COEF, CENTER, self.r_in, self.eta)
        return p[0] * self.u(x[0] - CENTER[0], x[1] - CENTER[1])


def _star_poiseuille(x, y):
    """u = 1 - r^2 / R(phi)^2, zero on the wall; -du/dn = 2 sqrt(R^2 + R'^2) / R^2."""
    phi = ca.atan2(y, x)
    return 1 - (x**2 + y**2) / rad.symbolic(ca.DM(COEF), phi) ** 2


def _modulated(x, y):
    """u = (1 - r^2/R^2)(1 + x/20): exact wall gradient (1 + x/20) * 2 sqrt(R^2 + R'^2) / R^2."""
    return _star_poiseuille(x, y) * (1 + x / 20)


@pytest.mark.parametrize("r_in,eta", [(7.0, 2.0), (4.0, 3.0), (8.9, 2.0)])
@pytest.mark.parametrize("field", ["poiseuille", "modulated"])
def test_wss_of_mapped_analytic_fields(r_in, eta, field):
    u = {"poiseuille": _star_poiseuille, "modulated": _modulated}[field]
    phi = rad.uniform_angles(360)
    res = wss.evaluate(phi, COEF, CENTER, PulledBack(u, r_in, eta), [0.4], r_in, eta, MU)
    big_r, dr = rad.evaluate(COEF, phi), rad.evaluate(COEF, phi, 1)
    grad = 2 * 0.4 * np.sqrt(big_r**2 + dr**2) / big_r**2
    if field == "modulated":
        grad = grad * (1 + big_r * np.cos(phi) / 20)
    exact = MU * 1000 * grad
    # exact arithmetic up to rounding: J^{-T}, the normal and grad v are all symbolic
    assert np.abs(res.tau - exact).max() <= 1e-8 * np.abs(exact).max()
    assert np.allclose(res.wall_x, CENTER[0] + big_r * np.cos(phi), atol=1e-12)
    mean = rad.arc_length_mean(exact, big_r, dr)
    assert res.mean == pytest.approx(mean, rel=1e-12)


def test_transpose_matters():
    """Using J^{-1} (as eq. (wss) is printed) instead of J^{-T} gives a different, wrong value."""
    r_in, eta = 5.0, 2.0
    xi = ca.SX.sym("xi", 2)
    x = symbolic_forward(xi, COEF, CENTER, r_in, eta)
    jac = ca.Function("J", [xi], [ca.jacobian(x, xi)])(np.array([np.cos(0.3), np.sin(0.3)]))
    jac = np.asarray(jac)
    assert np.abs(jac - jac.T).max() > 0.1  # J is not symmetric, so the two formulas differ


def test_mean_of_constant_is_constant():
    phi = rad.uniform_angles(400)
    assert rad.arc_length_mean(np.full(400, 2.5), rad.evaluate(COEF, phi), rad.evaluate(COEF, phi, 1)) == pytest.approx(
        2.5
    )


def test_wss_matrix_equals_direct_evaluation(laminar_snr25):
    """tau is linear in the velocity coefficients: A c must equal the direct evaluation."""
    from wss_nlp.models import geometry as geo
    from wss_nlp.models import velocity as vel

    from conftest import geometry_problem

    acq, _ = laminar_snr25
    g = geo.solve(geometry_problem(acq), geo.GeometryOptions())
    vo = vel.VelocityOptions(degree=8, angular_order=4)
    vp = vel.assemble(acq.grid, acq.velocity_images()[0], g.coefficients, g.center, vo)
    res = vel.solve(vp, vo)
    direct = wss.from_reconstruction(res, 360, 3.5e-3)
    a, xw = wss.wss_matrix(vp.basis, vp.disk_map, 3.5e-3)
    assert np.allclose(a @ res.coefficients, direct.tau, rtol=1e-10, atol=1e-12)
    assert np.allclose(xw[0], direct.wall_x, atol=1e-12)


def test_from_reconstruction_takes_the_kept_matrix_on_the_same_wall_only(laminar_snr25):
    """After wss_matrix on a plain basis and wall (the beta choice's), from_reconstruction on that wall returns
    A c: the same tau and mean as the expression's evaluation to 1e-13 relative (one matrix product against
    CasADi's evaluation, both double precision), the same wall points bit for bit; another viscosity or another
    wall is not served from the kept matrix (its tau scales with mu: checked at 2 mu)."""
    from wss_nlp.models import geometry as geo
    from wss_nlp.models import velocity as vel

    from conftest import geometry_problem

    acq, _ = laminar_snr25
    g = geo.solve(geometry_problem(acq), geo.GeometryOptions())
    vo = vel.VelocityOptions(degree=8, angular_order=4)
    vp = vel.assemble(acq.grid, acq.velocity_images()[0], g.coefficients, g.center, vo)
    res = vel.solve(vp, vo)
    wss._MATRICES.clear()
    direct = wss.from_reconstruction(res, 360, MU)
    wss.wss_matrix(vp.basis, vp.disk_map, MU)
    assert wss._matrix_key(res.basis, res.disk_map, MU, 360) in wss._MATRICES
    kept = wss.from_reconstruction(res, 360, MU)
    assert np.max(np.abs(kept.tau - direct.tau)) <= 1e-13 * np.max(np.abs(direct.tau))
    assert kept.mean == pytest.approx(direct.mean, rel=1e-13)
    assert np.array_equal(kept.wall_x, direct.wall_x) and np.array_equal(kept.wall_y, direct.wall_y)
    assert wss._matrix_key(res.basis, res.disk_map, 2 * MU, 360) not in wss._MATRICES
    assert np.allclose(wss.from_reconstruction(res, 360, 2 * MU).tau, 2 * direct.tau, rtol=1e-12, atol=0)
