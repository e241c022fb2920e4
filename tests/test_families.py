"""The near-wall family registry: every registered family satisfies the contract the layer machinery relies on.

A new family module (:mod:`wss_nlp.models.families`) is checked here without a test of its own: f(0) = 0 and
f'(0) = 1 (the columns vanish on the wall and a column's WSS is mu S / l whatever the family), the closed-form
derivatives equal CasADi's derivatives of f, the antiderivatives differentiate back to f, and NumPy and CasADi
evaluations agree.
"""

import casadi as ca
import numpy as np
import pytest

from wss_nlp.errors import InputError
from wss_nlp.models import families, near_wall as nw

Y = np.array([0.0, 1e-3, 0.3, 1.0, 4.0, 17.0, 60.0, 250.0])


@pytest.mark.parametrize("name", families.NAMES)
def test_family_contract(name):
    fam = families.get(name)
    assert fam.name == name and fam.description and fam.scale_rule in ("consistent", "criterion")
    y = ca.SX.sym("y")
    f = fam.f(y, ca)
    fun = ca.Function("f", [y], [f])
    assert float(fun(0.0)) == pytest.approx(0.0, abs=1e-14)
    assert float(ca.Function("d", [y], [ca.jacobian(f, y)])(0.0)) == pytest.approx(1.0, rel=1e-12)
    # NumPy and CasADi evaluations of the same formula: rounding only
    np.testing.assert_allclose(fam.f(Y, np), np.array(fun(Y)).ravel(), rtol=1e-13, atol=1e-15)
    d = f
    for order in range(1, 5):  # closed-form derivatives against CasADi's exact ones
        d = ca.jacobian(d, y)
        exact = np.array(ca.Function("dk", [y], [d])(Y)).ravel()
        np.testing.assert_allclose(fam.derivative(Y, order), exact, rtol=1e-10, atol=1e-14)
    # F_1' = f and F_2' = F_1 (CasADi's derivative of the closed forms)
    f1, f2 = fam.integrals(y, ca)
    np.testing.assert_allclose(np.array(ca.Function("g", [y], [ca.jacobian(f1, y)])(Y)).ravel(), fam.f(Y, np),
                               rtol=1e-9, atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(np.array(ca.Function("g", [y], [ca.jacobian(f2, y)])(Y)).ravel(),
                               np.array(ca.Function("g", [y], [f1])(Y)).ravel(), rtol=1e-9, atol=1e-12)  # fmt: skip
    assert float(ca.Function("g", [y], [f1])(0.0)) == pytest.approx(0.0, abs=1e-12)
    assert float(ca.Function("g", [y], [f2])(0.0)) == pytest.approx(0.0, abs=1e-12)


def test_the_layer_machinery_reads_the_registry():
    assert nw.FAMILIES == families.NAMES and set(nw.MODES) == {"off", "auto", *families.NAMES}
    for name in families.NAMES:
        np.testing.assert_array_equal(nw.profile(name, Y), families.get(name).f(Y, np))
    # every family belongs to one regime, and the automatic choice tries each regime's families
    turbulent = {n for n in families.NAMES if families.get(n).turbulent}
    assert set(nw.regime_families(1e4)) == turbulent and set(nw.regime_families(500)) == set(families.NAMES) - turbulent
    with pytest.raises(InputError, match="near-wall family must be one of"):
        families.get("blasius")


def test_a_family_needs_its_own_name():
    class Plain(families.WallFamily):
        name = "plain"

    with pytest.raises(ValueError, match="its own name"):
        families.register(Plain())
