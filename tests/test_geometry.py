import numpy as np
import pytest

import casadi as ca

from wss_nlp.models import geometry as geo
from wss_nlp.models import measurement as meas
from wss_nlp.core import radius as rad
from wss_nlp.errors import InputError, SolverError
from wss_nlp.core import checks
from wss_nlp.synthetic import phantoms
from wss_nlp.core.solver import ipopt_options, run_nlpsol

from conftest import geometry_problem


@pytest.mark.parametrize("kind", ["erf", "arctan"])
def test_forward_model_taylor(fourier_noise_free, kind):
    """||F(c + e d) - F(c) - e J d|| must fall like e^2 (CasADi's exact Jacobian)."""
    acq, _ = fourier_noise_free
    prob = geometry_problem(acq)
    model = meas.annulus_model(prob.grid, prob.center, prob.r0, prob.r1, 4)
    c = ca.MX.sym("c", rad.n_coefficients(6))
    f_expr = meas.magnitude_model(model, c, 0.2, kind)
    fun = ca.Function("F", [c], [f_expr, ca.jacobian(f_expr, c)])
    rng = np.random.default_rng(0)
    c0 = np.zeros(rad.n_coefficients(6))
    c0[0] = prob.r_ref
    c0[1:] = 0.2 * rng.normal(size=c0.size - 1) / np.arange(1, c0.size) ** 0
    d = rng.normal(size=c0.size)
    f0, jac = (np.asarray(v) for v in fun(c0))
    # numeric evaluation path must agree with the symbolic one
    assert np.allclose(meas.magnitude_model(model, c0, 0.2, kind), f0.ravel(), atol=1e-13)
    # second order: halving e divides the remainder by 4 (3.5..4.5 allows the O(e^3) term)
    checks.assert_taylor(
        lambda c: fun(c)[0], lambda c, dd: np.asarray(fun(c)[1]) @ dd, c0, d, steps=(1e-2, 5e-3, 2.5e-3, 1.25e-3)
    )


def test_noise_free_recovery_of_radius_in_VN(fourier_noise_free):
    """The lumen's radius lies in V_4; noise-free data must give it back (rel. error < 1e-3)."""
    acq, truth = fourier_noise_free
    prob = geometry_problem(acq)
    res = geo.solve_ipopt(prob, geo.GeometryOptions(n_fourier=4, alpha=1e-6))
    phi = rad.uniform_angles(360)
    rt = truth.radius_about(res.center, phi)
    err = np.linalg.norm(res.radius(phi) - rt) / np.linalg.norm(rt)
    assert res.stats.converged
    assert err < 1e-3, err
    # and about the true centre the coefficients themselves come back
    assert np.allclose(res.coefficients[0], truth.lumen.coefficients[0], rtol=1e-3)


@pytest.mark.parametrize("hessian", ["newton", "gauss-newton", "exact"])
def test_projected_gauss_newton_agrees_with_ipopt(laminar_snr25, hessian):
    acq, _ = laminar_snr25
    prob = geometry_problem(acq)
    opt = geo.GeometryOptions(hessian=hessian, tol=1e-12)
    a = geo.solve_ipopt(prob, opt)
    b = geo.solve_projected_gauss_newton(prob, opt)
    assert a.stats.converged and b.stats.converged
    # same strictly convex-near-solution functional: minimizers agree to solver tolerance
    assert np.allclose(a.coefficients, b.coefficients, rtol=0, atol=1e-6 * a.coefficients[0])
    assert a.stats.objective == pytest.approx(b.stats.objective, rel=1e-9)


@pytest.mark.parametrize("kind", ["erf", "arctan"])
def test_heaviside_curvature_is_the_slope_derivative(kind):
    """H'' of the smoothed Heaviside equals CasADi's derivative of H' (two exact derivatives: to rounding)."""
    x = ca.SX.sym("x")
    ad = ca.Function("d2", [x], [ca.jacobian(meas.heaviside_slope(x, 0.3, kind), x)])
    grid = np.linspace(-2, 2, 41)
    assert np.allclose(meas.heaviside_curvature(grid, 0.3, kind), np.asarray(ad(grid)).ravel(), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", ["erf", "arctan"])
def test_heaviside_antiderivatives_differentiate_to_the_heaviside(kind):
    """G_1' = H_gamma and G_2' = G_1 by CasADi's exact derivative (to rounding of G ~ x^2: 1e-12), and the erf pair
    tends to the sharp (x_+, x_+^2/2) as gamma -> 0: at gamma = 1e-5 the Gaussian tails are below 1e-12 for
    |x| >= 0.1, and G_2 keeps gamma^2/4 = 2.5e-11 inside (a constant the means' differences cancel)."""
    x = ca.SX.sym("x")
    g1, g2 = meas.heaviside_antiderivatives(x, 0.3, kind)
    ad = ca.Function("d", [x], [ca.jacobian(g1, x), ca.jacobian(g2, x), g1])
    grid = np.linspace(-3, 3, 61)
    d1, d2, v1 = (np.asarray(v).ravel() for v in ad(grid))
    np.testing.assert_allclose(d1, meas.smoothed_heaviside(grid, 0.3, kind), rtol=0, atol=1e-12)
    np.testing.assert_allclose(d2, v1, rtol=0, atol=1e-12)
    if kind == "erf":
        far = np.abs(grid) >= 0.1
        sharp1, sharp2 = meas.heaviside_antiderivatives(grid[far], 1e-5, kind)
        np.testing.assert_allclose(sharp1, np.maximum(grid[far], 0), rtol=0, atol=1e-12)
        np.testing.assert_allclose(sharp2, np.maximum(grid[far], 0) ** 2 / 2, rtol=0, atol=3e-11)


@pytest.mark.parametrize("k", [0, 1, 2])
def test_erf_indicator_derivatives_equal_casadi_ad_in_x_and_gamma(k):
    """The closed-form mixed derivatives d^i/dx^i d^j/dgamma^j (i + j <= 3) of H_gamma (k = 0) and of its
    antiderivatives G_1, G_2 (k = 1, 2) equal CasADi's repeated derivatives of the erf formulas, from deep in
    the tails to 4 widths inside: 1e-13 of each order's largest value (terms cancel where an order crosses 0)."""
    x, g = ca.SX.sym("x"), ca.SX.sym("g")
    base = meas.smoothed_heaviside(x, g, "erf") if k == 0 else meas.heaviside_antiderivatives(x, g, "erf")[k - 1]
    orders = [(i, j) for i in range(4) for j in range(4 - i)]
    exprs = []
    for i, j in orders:
        e = base
        for _ in range(i):
            e = ca.jacobian(e, x)
        for _ in range(j):
            e = ca.jacobian(e, g)
        exprs.append(e)
    grid = np.linspace(-6, 4, 201) * 0.3
    ref = ca.Function("ref", [x, g], exprs).map(grid.size)(grid[None, :], 0.3)
    for (i, j), r in zip(orders, ref):
        r = np.asarray(r).ravel()
        mine = meas.erf_indicator_derivative(grid, 0.3, k, i, j)
        np.testing.assert_allclose(mine, r, rtol=0, atol=1e-13 * np.max(np.abs(r)), err_msg=f"order ({i}, {j})")


@pytest.mark.parametrize("kind", ["erf", "arctan"])
def test_newton_hessian_equals_casadi_exact_hessian(laminar_snr25, kind):
    """The chain-rule Hessian 2 (J^T J + sum r_i Hess r_i + alpha W) the "newton" solver passes to IPOPT equals
    CasADi's algorithmic Hessian of the functional at a point away from the minimizer (residuals not small),
    to rounding relative to its largest entry."""
    problem = geometry_problem(laminar_snr25[0])
    opts = geo.GeometryOptions(heaviside=kind)
    solver = geo.IpoptGeometrySolver(problem, opts)
    assert solver.hessian == "newton"
    nlp = solver.nlp
    assert nlp.jacobian is not None and nlp.curvature is not None
    gram = ca.mtimes(nlp.jacobian.T, nlp.jacobian)
    chain = 2 * (gram + nlp.curvature + nlp.alpha * ca.diag(ca.DM(nlp.weights)))
    exact = ca.hessian(nlp.f, nlp.c)[0]
    both = ca.Function("h", [nlp.c, nlp.alpha, nlp.data], [chain, exact])
    rng = np.random.default_rng(4)
    c = geo.initial_guess(problem, opts.n_fourier) + 0.05 * rng.normal(size=nlp.c.numel())
    data = problem.magnitude.ravel()[nlp.model.annulus]
    ours, casadi_h = (np.asarray(v) for v in both(c, 1e-3, data))
    assert np.max(np.abs(ours - casadi_h)) < 1e-10 * np.max(np.abs(casadi_h))
    # and the second-order term matters here: Gauss-Newton alone is off by far more than rounding
    assert np.max(np.abs(ours - np.asarray(ca.Function("g", [nlp.c, nlp.data], [2 * gram])(c, data)))) > 1e-3


def test_newton_converges_in_fewer_iterations_to_the_same_minimizer(laminar_snr25):
    """Same minimizer with the Newton and the Gauss-Newton Hessian (both at tol 1e-9: 1e-8 mm); the Gauss-Newton
    iteration converges linearly on this non-zero-residual problem, Newton quadratically (fewer iterations)."""
    problem = geometry_problem(laminar_snr25[0])
    newton = geo.IpoptGeometrySolver(problem, geo.GeometryOptions()).solve()
    gauss = geo.IpoptGeometrySolver(problem, geo.GeometryOptions(hessian="gauss-newton")).solve()
    assert newton.stats.converged and gauss.stats.converged
    assert newton.stats.extra["hessian"] == "newton" and gauss.stats.extra["hessian"] == "gauss-newton"
    assert np.max(np.abs(newton.coefficients - gauss.coefficients)) < 1e-8
    assert newton.stats.iterations < gauss.stats.iterations


def test_initial_guess_is_the_half_maximum_contour(laminar_snr25):
    """The start lies near the minimizer (the ellipse: within 0.1 mm, where the equal-area circle is ~1 mm off),
    inside a box the contour leaves, and is the circle where no ray finds the contour or a value is not finite."""
    problem = geometry_problem(laminar_snr25[0])
    opts = geo.GeometryOptions()
    solution = geo.solve_ipopt(problem, opts).coefficients
    start = geo.initial_guess(problem, opts.n_fourier)
    circle = np.zeros_like(start)
    circle[0] = problem.r_ref
    phi = rad.uniform_angles(360)
    assert np.max(np.abs(rad.evaluate(start - solution, phi))) < 0.1
    assert np.max(np.abs(rad.evaluate(circle - solution, phi))) > 0.5
    tight = geo.GeometryProblem(problem.grid, problem.magnitude, problem.center, problem.r0, 12.5, problem.r_ref)
    inside = rad.evaluate(geo.initial_guess(tight, opts.n_fourier), phi)  # the ellipse reaches 13 mm
    assert inside.min() > tight.r0 and inside.max() < tight.r1
    flat = geo.GeometryProblem(
        problem.grid, np.ones_like(problem.magnitude), problem.center, problem.r0, problem.r1, problem.r_ref
    )
    assert np.allclose(geo.initial_guess(flat, opts.n_fourier), circle, rtol=0, atol=1e-12)
    holes = problem.magnitude.copy()
    holes[::7, ::5] = np.nan  # a non-finite value on some ray: the circle, never a non-finite start
    gappy = geo.GeometryProblem(problem.grid, holes, problem.center, problem.r0, problem.r1, problem.r_ref)
    assert np.array_equal(geo.initial_guess(gappy, opts.n_fourier), circle)


def test_box_constraint_active_both_solvers(laminar_snr25):
    """With r1 below the true maximum radius the box binds; both solvers respect it and agree."""
    acq, _ = laminar_snr25
    prob = geometry_problem(acq)
    prob.r1 = 12.0  # the ellipse reaches 13 mm
    opt = geo.GeometryOptions(tol=1e-12)
    a = geo.solve_ipopt(prob, opt)
    b = geo.solve_projected_gauss_newton(prob, opt)
    rb = rad.evaluate(a.coefficients, opt.box_angles())
    assert a.box_active and rb.max() <= 12.0 + 1e-6
    assert rad.evaluate(b.coefficients, opt.box_angles()).max() <= 12.0 + 1e-8
    assert np.allclose(a.coefficients, b.coefficients, atol=1e-4)


def test_inverted_box_is_an_input_error(laminar_snr25):
    acq, _ = laminar_snr25
    prob = geometry_problem(acq)
    with pytest.raises(InputError, match="0 < r0 < r1"):
        geo.GeometryProblem(prob.grid, prob.magnitude, prob.center, 14.0, 9.0, prob.r_ref)


def test_ipopt_hard_failure_is_a_solver_error():
    """A NaN in the objective is a hard failure: an error, never a returned iterate."""
    x = ca.MX.sym("x")
    solver = ca.nlpsol("s", "ipopt", {"x": x, "f": ca.sqrt(x - 2)}, ipopt_options(1e-8, 50))
    with pytest.raises(SolverError, match="IPOPT"):
        run_nlpsol(solver, "toy", x0=0.0)


def test_iteration_limit_is_flagged_not_hidden(laminar_snr25):
    acq, _ = laminar_snr25
    res = geo.solve_ipopt(geometry_problem(acq), geo.GeometryOptions(max_iter=2))
    assert not res.stats.converged
    assert res.stats.status == "Maximum_Iterations_Exceeded"


def test_prior_zero_shrinks_radius(laminar_snr25):
    """eq. (tik1) literally (prior 'zero') biases the mean radius low; 'area' does not."""
    acq, _ = laminar_snr25
    prob = geometry_problem(acq)
    area = geo.solve(prob, geo.GeometryOptions(alpha=0.05, prior="area")).coefficients[0]
    zero = geo.solve(prob, geo.GeometryOptions(alpha=0.05, prior="zero")).coefficients[0]
    assert zero < area - 0.01


def test_cached_solver_serves_other_magnitudes_exactly(laminar_snr25):
    """The magnitude values are solver parameters: one built solver (geo.solver_for) solves a second image on
    the same grid, centre and box to the same coefficients as a solver built for that image (same IPOPT
    iterates: equal to rounding), and a different box gets its own solver."""
    problem = geometry_problem(laminar_snr25[0])
    opts = geo.GeometryOptions()
    first = geo.solver_for(problem, opts)
    rng = np.random.default_rng(11)
    other = geo.GeometryProblem(
        problem.grid,
        np.clip(problem.magnitude + 0.05 * rng.normal(size=problem.magnitude.shape), 0, 1),
        problem.center,
        problem.r0,
        problem.r1,
        problem.r_ref,
    )
    assert geo.solver_for(other, geo.with_options(opts, alpha=2 * opts.alpha)) is first
    reused = first.solve(opts.alpha, None, other)
    fresh = geo.IpoptGeometrySolver(other, opts).solve(opts.alpha)
    assert reused.stats.iterations == fresh.stats.iterations
    assert np.max(np.abs(reused.coefficients - fresh.coefficients)) < 1e-12
    assert reused.residual_norm == pytest.approx(fresh.residual_norm, rel=1e-12)
    own = geo.solve_ipopt(problem, opts)
    assert np.max(np.abs(own.coefficients - reused.coefficients)) > 1e-4  # the other image's answer differs
    wider = geo.GeometryProblem(
        problem.grid, problem.magnitude, problem.center, problem.r0, problem.r1 + 0.5, problem.r_ref
    )
    assert geo.solver_for(wider, opts) is not first


@pytest.mark.parametrize("acquisition", ["box", "kspace"])
def test_response_predicts_the_resolve_to_second_order(acquisition):
    """IpoptGeometrySolver.response (implicit function theorem on the stationarity, the exact Hessian) against
    re-solves after a change eps * d of the magnitude: the prediction's error falls like eps^2 (ratio 4 when eps
    halves; the re-solves' tolerance, ~1e-10 mm, lies far below the smallest error, ~2e-5 mm) and is below 5 %
    of the move at the larger eps (measured 2 %, a 4-7 um move); and it equals sensitivity.geometry_kkt's
    derivative in the magnitude (measured 1e-15 relative). Box and k-space model (Hamming PSF), seed 13
    (not used elsewhere)."""
    from wss_nlp.models import kspace

    psf = kspace.PSF("hamming", (1.0, 1.0)) if acquisition == "kspace" else None
    acq, _ = phantoms.make_phantom("laminar", h_mm=1.0, snr=25, seed=13, psf=psf)
    base = geometry_problem(acq)
    problem = geo.GeometryProblem(base.grid, base.magnitude, base.center, base.r0, base.r1, base.r_ref, psf=psf)
    opts = geo.GeometryOptions()
    solver = geo.IpoptGeometrySolver(problem, opts)
    g = solver.solve()
    assert g.stats.converged and not g.box_active
    rng = np.random.default_rng(13)
    d = 0.05 * rng.normal(size=problem.magnitude.shape)
    errors, moves = [], []
    for eps in (0.4, 0.2):
        changed = geo.GeometryProblem(
            problem.grid, problem.magnitude + eps * d, problem.center, problem.r0, problem.r1, problem.r_ref, psf=psf
        )
        again = solver.solve(opts.alpha, g.coefficients, changed)
        predicted = solver.response(g, problem, changed.magnitude)
        moves.append(np.max(np.abs(again.coefficients - g.coefficients)))
        errors.append(np.max(np.abs(again.coefficients - g.coefficients - predicted)))
    assert errors[0] < 0.05 * moves[0]
    assert errors[0] / errors[1] == pytest.approx(4.0, rel=0.25)
    # the same derivative from the band's implicit-function theorem (its own graph): equal to rounding
    from wss_nlp.uncertainty import sensitivity as sens

    dc_dp, annulus = sens.geometry_kkt(problem, opts, g.coefficients, g.alpha, g.gamma, g.box_multipliers)
    predicted = solver.response(g, problem, problem.magnitude + d)
    assert np.max(np.abs(predicted - dc_dp[:, : annulus.size] @ d.ravel()[annulus])) <= 1e-10 * np.max(
        np.abs(predicted)
    )
    assert geo.IpoptGeometrySolver(problem, geo.GeometryOptions(hessian="gauss-newton")).response(g, problem, d) is None
