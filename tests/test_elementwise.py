"""Elementwise NumPy maps with a ladder of derivatives, against the same function written in CasADi's SX."""

import casadi as ca
import numpy as np
import pytest

from wss_nlp.core import elementwise
from wss_nlp.models import near_wall as nw


@pytest.mark.parametrize("family", nw.FAMILIES)
def test_profile_derivatives_equal_casadi_ad_of_the_profile(family):
    """The closed-form ``f^(k)`` of both families equal CasADi's repeated derivatives of ``f`` (k <= 4) from the
    wall to deep in the core: 1e-13 of each order's largest value (the terms cancel where ``f^(k)`` crosses
    zero, so not relative to each value)."""
    y = np.linspace(0.05, 500, 2001)
    t = ca.SX.sym("t")
    exprs = [nw.profile(family, t)]
    for _ in range(4):
        exprs.append(ca.gradient(exprs[-1], t))
    ref = ca.Function("ref", [t], exprs).map(y.size)(y[None, :])
    for k, r in enumerate(ref):
        r = np.asarray(r).ravel()
        mine = nw.profile_derivatives(family, y, k)
        np.testing.assert_allclose(mine, r, rtol=0, atol=1e-13 * np.max(np.abs(r)), err_msg=f"order {k}")


def _cells(formula: str, n: int, seed: int):
    """Depths and half-widths (layer units) for a cell-mean formula: far inside (2-300, half-widths on both
    sides of the 0.02 threshold), or across the wall (-1 to 8) for a branch's cells (point: narrower than
    0.02; box: one side below 1e-3 of the other; trapezoid: both 0.03-2)."""
    rng = np.random.default_rng(seed)
    if formula == "far":
        return rng.uniform(2.0, 300.0, n), rng.uniform(0.0, 0.5, n), rng.uniform(0.0, 0.04, n)
    y, a = rng.uniform(-1.0, 8.0, n), rng.uniform(0.03, 2.0, n)
    if formula == "point":
        return y, 0.019 * a / 2.0, rng.uniform(0.0, 0.019, n)
    return y, a, rng.uniform(0.0, 1e-3, n) * a if formula == "box" else rng.uniform(0.03, 2.0, n)


def _sx_and_numpy(family: str, formula: str, a, b):
    """The SX function of a formula (``(y, a, b) -> (mean, d mean / dy)``) and its NumPy derivatives."""
    if formula == "far":
        return nw.far_cell_mean_function(family), lambda y, d: nw.far_cell_mean_derivative(family, y, a, b, d)
    sx = nw.cell_mean_function(family, continuous=True, branch=formula)
    return sx, lambda y, d: nw.cell_mean_derivative(family, y, a, b, d, formula)


@pytest.mark.parametrize("formula", ("far", *nw.BRANCHES))
@pytest.mark.parametrize("family", nw.FAMILIES)
def test_ladder_values_and_derivatives_equal_the_sx_cell_means(family, formula):
    """D_0, D_1 of a cell mean (the far-inside one, and each branch of the coupled layer's continuous one)
    equal the SX function's value and y-derivative; through the callbacks, CasADi's gradient (reverse), a
    forward directional derivative and the Hessian of a weighted sum (forward over reverse, D_2 and D_3) equal
    those of the SX graph. Tolerance 1e-12 relative to each output's largest value: the trapezoid's second
    differences of F_2 cancel to about 1e-13 of it, in both codes alike."""
    n = 50
    y0, a, b = _cells(formula, n, 3)
    sx_function, derivative = _sx_and_numpy(family, formula, a, b)
    ladder = elementwise.Ladder(n, derivative)
    sx = sx_function.map(n)
    y = ca.MX.sym("y", 1, n)
    w = np.random.default_rng(4).normal(size=n)
    mine_v, mine_d = ladder.map(0)(y), ladder.map(1)(y)
    ref_v, ref_d = sx(y, ca.DM(a).T, ca.DM(b).T)
    seed = np.random.default_rng(5).normal(size=n)
    outputs = []
    for v, d in ((mine_v, mine_d), (ref_v, ref_d)):
        obj = ca.dot(ca.DM(w), v.T)
        grad = ca.gradient(obj, y)
        outputs.append(
            ca.Function("f", [y], [v, d, grad, ca.jtimes(v, y, ca.DM(seed).T), ca.hessian(obj, y)[0]])(y0[None, :])
        )
    for mine, ref, name in zip(*outputs, ["value", "derivative", "gradient", "forward", "hessian"]):
        mine, ref = np.asarray(mine), np.asarray(ref)
        np.testing.assert_allclose(mine, ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)), err_msg=name)


@pytest.mark.parametrize("branch", nw.BRANCHES)
def test_scaled_ladder_equals_the_sx_inside_fraction_in_depth_and_width(branch):
    """The two-variable ladder of a cell's inside fraction (erf indicator, width g): D_00, D_10 equal the SX
    function's value and y-derivative, and through the callbacks CasADi's gradient in (y, g), a forward
    derivative along (y, g) and the Hessian in (y, g) of a weighted sum (mixed orders up to three) equal the
    SX graph's. Depths -3 to 3 widths either side of the wall, where the indicator changes; tolerance as for
    the profile's cell means (the trapezoid's second differences cancel to about 1e-13)."""
    n, g0 = 40, 0.7
    rng = np.random.default_rng(8)
    y0 = rng.uniform(-3 * g0, 3 * g0, n)
    a = rng.uniform(0.03, 2.0, n)
    b = {"point": a * 1e-3, "box": a * 1e-4, "trapezoid": rng.uniform(0.03, 2.0, n)}[branch]
    if branch == "point":
        a = a * 1e-6
    ladder = elementwise.ScaledLadder(n, lambda y, g, i, j: nw.smoothed_inside_derivative(y, a, b, g, i, j, branch))
    sx = nw.smoothed_inside_function("erf", branch).map(n)
    y, g = ca.MX.sym("y", 1, n), ca.MX.sym("g")
    z = ca.vertcat(y.T, g)
    w = rng.normal(size=n)
    seed = rng.normal(size=n + 1)
    outputs = []
    for v, d in ((ladder.map(0, 0)(y, g), ladder.map(1, 0)(y, g)), sx(y, ca.DM(a).T, ca.DM(b).T, g)):
        obj = ca.dot(ca.DM(w), v.T) + ca.dot(ca.DM(w), d.T) ** 2
        fun = ca.Function(
            "f", [y, g], [v, d, ca.gradient(obj, z), ca.jtimes(v.T, z, ca.DM(seed)), ca.hessian(obj, z)[0]]
        )
        outputs.append(fun(y0[None, :], g0))
    for mine, ref, name in zip(*outputs, ["value", "derivative", "gradient", "forward", "hessian"]):
        mine, ref = np.asarray(mine), np.asarray(ref)
        np.testing.assert_allclose(mine, ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)), err_msg=name)


def test_ladder_caches_values_per_point_set():
    """One evaluation at the same points computes each order once; new points recompute."""
    calls = []

    def derivative(y, d):
        calls.append(d)
        return np.cos(y + d * np.pi / 2)  # the d-th derivative of cos

    ladder = elementwise.Ladder(4, derivative)
    y = np.array([0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(np.asarray(ladder.map(1)(y[None, :])).ravel(), -np.sin(y), rtol=1e-15)
    ladder.map(1)(y[None, :])
    assert calls == [1]
    ladder.map(1)(y[None, :] + 1)
    assert calls == [1, 1]
