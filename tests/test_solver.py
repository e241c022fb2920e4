"""Solver plumbing: the shared evaluation of the Gauss-Newton derivatives and its deferred exact derivatives."""

import casadi as ca
import numpy as np

import pytest

from wss_nlp.core.solver import DenseCall, EagerObjective, SharedEvaluation, gauss_newton_ipopt, run_nlpsol


def _toy():
    """A nonlinear least-squares function of x (3) and a parameter p, with exact derivatives to compare."""
    x, p = ca.MX.sym("x", 3), ca.MX.sym("p")
    r = ca.vertcat(ca.sin(x[0]) * x[1] - p, x[1] ** 2 - x[2], ca.exp(0.3 * x[2]) - x[0] * p)
    return x, p, r


def test_shared_evaluation_evaluates_once_per_point_and_its_derivatives_are_the_functions_own():
    x, p, r = _toy()
    f = ca.sumsqr(r) * p
    shared = SharedEvaluation(ca.Function("toy", [x, p], [f, r], ["x", "p"], ["f", "r"]))
    x0, p0 = np.array([0.3, -1.2, 0.7]), 1.9
    direct = ca.Function("direct", [x, p], [f, r])
    for _ in range(3):
        out = shared(x0, p0)
    assert shared.evaluations == 1
    shared(x0 + 1e-12, p0)
    assert shared.evaluations == 2  # compared exactly: any change is a new point
    np.testing.assert_array_equal(np.asarray(out[1]), np.asarray(direct(x0, p0)[1]))
    # derivatives through the callback (reverse, forward over reverse, forward) equal CasADi's on the graph itself
    z = ca.vertcat(x, p)
    f_cb = shared(x, p)[0]
    for name, make in [
        ("gradient", lambda e: ca.gradient(e, z)),
        ("hessian", lambda e: ca.hessian(e, z)[0]),
        ("jtimes", lambda e: ca.jtimes(shared(x, p)[1] if e is f_cb else r, z, ca.DM([1.0, -2.0, 0.5, 3.0]))),
    ]:
        mine = ca.Function("mine", [x, p], [make(f_cb)])(x0, p0)
        ref = ca.Function("ref", [x, p], [make(f)])(x0, p0)
        # the same CasADi derivative graph evaluated behind a callback: equal to rounding
        np.testing.assert_allclose(np.asarray(mine), np.asarray(ref), rtol=1e-13, atol=1e-13, err_msg=name)


def test_gauss_newton_ipopt_with_a_supplied_gradient_reaches_the_same_minimizer_with_one_jacobian_per_point():
    """The same box-constrained least-squares problem solved with the gradient by reverse mode and with
    ``grad = 2 J^T r`` shared with the Hessian: the same minimizer (to IPOPT's tolerance), and the shared
    function is evaluated at most once per gradient request (IPOPT asks for the Hessian at the same points).
    (With the box active this residual makes Gauss-Newton crawl to "acceptable": the box is left inactive.)"""
    x, p, r = _toy()
    jac = ca.jacobian(r, x)
    f = ca.sumsqr(r) + 0.1 * ca.sumsqr(x)
    hess = 2 * ca.mtimes(jac.T, jac) + 0.2 * ca.DM.eye(3)
    grad = 2 * ca.mtimes(jac.T, r) + 0.2 * x
    g = x[0] + x[1]
    args = {"x0": [0.5, 0.5, 0.5], "p": 0.8, "lbg": -0.2, "ubg": 5.0}
    plain = gauss_newton_ipopt("plain", x, f, g, hess, p, tol=1e-8)
    shared = gauss_newton_ipopt("shared", x, f, g, hess, p, tol=1e-8, grad=grad)
    (sol_a, st_a), (sol_b, st_b) = run_nlpsol(plain, "plain", **args), run_nlpsol(shared, "shared", **args)
    assert st_a.converged and st_b.converged
    # both stop at IPOPT's tolerance 1e-8
    np.testing.assert_allclose(np.asarray(sol_b["x"]), np.asarray(sol_a["x"]), rtol=0, atol=1e-6)
    stats = shared.stats()
    _, derivatives = shared.shared
    requests = stats["n_call_nlp_grad_f"] + stats["n_call_nlp_hess_l"]
    assert derivatives.evaluations <= stats["n_call_nlp_grad_f"] < requests


def test_eager_objective_reads_f_from_the_derivatives_at_accepted_points_and_alone_after_a_rejected_trial():
    """IPOPT asks for f at a trial point and, once it accepts the step, for the derivatives there: the objective
    evaluates (f, grad, hess) together while steps are accepted (the derivatives were asked for at its last
    point) and f alone after a rejected trial; every value is f's own (the same expression: equal exactly)."""
    x, p, r = _toy()
    f = ca.sumsqr(r) + 0.1 * ca.sumsqr(x)
    jac = ca.jacobian(r, x)
    grad, hess = 2 * ca.mtimes(jac.T, r) + 0.2 * x, 2 * ca.mtimes(jac.T, jac)
    derivatives = SharedEvaluation(ca.Function("d", [x, p], [f, grad, hess], ["x", "p"], ["f", "grad", "hess"]))
    f_only = ca.Function("f", [x, p], [f], ["x", "p"], ["f"])
    objective = EagerObjective(f_only, derivatives)
    points = [np.array([0.3, -1.2, 0.7]) + k * 0.01 for k in range(4)]
    p0 = 1.9

    def value(k):
        return float(objective(points[k], p0))

    assert value(0) == float(f_only(points[0], p0)) and derivatives.evaluations == 1  # the first point: eager
    derivatives(points[0], p0)  # accepted: IPOPT asks for the derivatives at it, read from the same evaluation
    assert derivatives.evaluations == 1
    assert value(1) == float(f_only(points[1], p0)) and derivatives.evaluations == 2  # eager again
    # no derivatives asked at points[1] (a rejected trial): the next f comes from f alone
    assert value(2) == float(f_only(points[2], p0)) and derivatives.evaluations == 2 and objective.evaluations == 1
    derivatives(points[2], p0)  # accepted after all: evaluated now, and the objective is eager again
    assert derivatives.evaluations == 3
    assert value(3) == float(f_only(points[3], p0)) and derivatives.evaluations == 4
    assert objective.eager_evaluations == 3


def test_dense_call_equals_casadis_call_in_every_shape_and_reuses_its_buffer():
    """DenseCall returns the same numbers as CasADi's own call (exactly: the same evaluation), in the outputs'
    shapes (column-major memory read back correctly for a non-square matrix), at several points through one
    buffer, with numbers broadcast to an input's entries; outputs with structural zeros are refused."""
    x, p = ca.MX.sym("x", 3), ca.MX.sym("p", 2, 3)
    outputs = [ca.mtimes(p, x), ca.densify(ca.reshape(ca.vertcat(x, x) * ca.sum1(x), 2, 3)), ca.mtimes(x, x.T)]
    fun = ca.Function("f", [x, p], outputs)
    call = DenseCall(fun)
    rng = np.random.default_rng(4)
    for _ in range(3):
        xv, pv = rng.normal(size=3), rng.normal(size=(2, 3))
        for got, want in zip(call(xv, pv), fun(xv, pv)):
            assert got.shape == want.shape and np.array_equal(got, np.asarray(want))
    got, want = call(xv, 0.5)[0], np.asarray(fun(xv, np.full((2, 3), 0.5))[0])
    assert np.array_equal(got, want)
    with pytest.raises(ValueError, match="not dense"):
        DenseCall(ca.Function("g", [x], [ca.diag(x)]))
