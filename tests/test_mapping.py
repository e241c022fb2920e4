import numpy as np
import pytest

import casadi as ca

from wss_nlp.core import radius as rad
from wss_nlp.errors import InputError
from wss_nlp.core.mapping import DiskMap, symbolic_forward

COEF = np.array([10.0, 0.5, 0.8, -0.3, 0.0, 0.4, 0.2])  # N = 3


@pytest.mark.parametrize("eta", [2.0, 3.0, 4.5])
def test_inverse_undoes_forward(rng, eta):
    dm = DiskMap(COEF, (1.0, -2.0), r_in=6.0, eta=eta)
    rho = rng.uniform(0, 1, 200)
    t = rng.uniform(-np.pi, np.pi, 200)
    x, y = dm.forward(rho, t)
    rho2, t2 = dm.inverse(x, y)
    assert np.allclose(rho2, rho, atol=1e-12)
    assert np.allclose(np.angle(np.exp(1j * (t2 - t))), 0, atol=1e-12)


def test_wall_maps_to_wall():
    dm = DiskMap(COEF, (0.0, 0.0), r_in=5.0)
    t = rad.uniform_angles(50)
    x, y = dm.forward(np.ones_like(t), t)
    assert np.allclose(np.hypot(x, y), rad.evaluate(COEF, t), atol=1e-12)


def test_symbolic_jacobian_matches_paper_formula():
    """J_R of eq. (Jacobian_rep) in polar form, from CasADi's derivative of the Cartesian map."""
    r_in, eta = 6.0, 2.5
    xi = ca.SX.sym("xi", 2)
    x = symbolic_forward(xi, COEF, (0.0, 0.0), r_in, eta)
    f = ca.Function("J", [xi], [ca.jacobian(x, xi)])
    rho, t = 0.7, 1.1
    jac = np.asarray(f([rho * np.cos(t), rho * np.sin(t)]))
    big_r, dr = rad.evaluate(COEF, [t])[0], rad.evaluate(COEF, [t], 1)[0]
    e_r, e_t = np.array([np.cos(t), np.sin(t)]), np.array([-np.sin(t), np.cos(t)])
    s = r_in * rho + (big_r - r_in) * rho**eta
    ds_drho = r_in + eta * (big_r - r_in) * rho ** (eta - 1)
    # d x / d rho = s_rho e_r ; (1/rho) d x / d t = (R' rho^(eta-1)) e_r + (s / rho) e_t
    assert np.allclose(jac @ e_r, ds_drho * e_r, atol=1e-12)
    assert np.allclose(jac @ e_t, dr * rho ** (eta - 1) * e_r + s / rho * e_t, atol=1e-12)


def test_inner_radius_must_not_exceed_min_radius():
    with pytest.raises(InputError, match="inner radius"):
        DiskMap(COEF, (0, 0), r_in=20.0)
    with pytest.raises(InputError, match="eta"):
        DiskMap(COEF, (0, 0), r_in=5.0, eta=1.5)
