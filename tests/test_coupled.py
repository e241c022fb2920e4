"""The coupled geometry + velocity NLP: its forward model, its derivatives and its accuracy."""

from dataclasses import replace

import casadi as ca
import h5py
import json
import numpy as np
import pytest

from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.core import checks
from wss_nlp.models import coupled as cpl
from wss_nlp.models import geometry as geo
from wss_nlp.models import measurement as meas
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.models import near_wall as nw
from wss_nlp.models import velocity as vel
from wss_nlp.app.cli import main
from wss_nlp.errors import InputError
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
from wss_nlp.core.velocity_basis import make_basis

from conftest import assert_coupled_jacobian_is_exact


@pytest.fixture(scope="module")
def laminar_coarse():
    acq, truth = phantoms.make_phantom("laminar", h_mm=1.5, snr=25, seed=3)
    return acq, truth, reconstruct(acq)[0]


def _problem(res):
    lum = res.lumen
    return geo.GeometryProblem(res.grid, res.magnitude, lum.center, lum.r0, lum.r1, lum.r_area)


@pytest.mark.parametrize("kind", ["zernike", "eigen"])
def test_polar_basis_reproduces_the_basis(kind):
    basis = make_basis(kind, 12, 150.0, 4)
    rng = np.random.default_rng(0)
    rho, t = rng.uniform(0, cpl.RHO_MAX, 200), rng.uniform(-np.pi, np.pi, 200)
    pb = cpl.polar_basis(basis, t)
    tk = np.polynomial.chebyshev.chebvander(2 * rho / cpl.RHO_MAX - 1, pb.cheb.shape[1] - 1).T
    raw = (pb.select_angular @ pb.angular) * (pb.select_radial @ (pb.cheb @ tk))
    expected = basis.radial_raw(rho) * basis.angular_raw(t)
    # Zernike: a polynomial identity; eigen: Chebyshev interpolant accepted at 1e-12 relative (polar_basis)
    assert np.max(np.abs(raw - expected)) <= 1e-10 * np.max(np.abs(expected))
    inside = rho < 1
    direct = basis.evaluate(rho[inside] * np.cos(t[inside]), rho[inside] * np.sin(t[inside]))
    assert np.allclose(raw[:, inside].T @ basis.transform, direct, rtol=0, atol=1e-10 * np.max(np.abs(direct)))


def test_coupled_quadrature_defaults_to_the_decoupled_rule_capped_at_three():
    """``--coupled-quad-order`` unset: the decoupled fit's q (about R/60 apart, at least 2), at most 3; set: as
    given; the solve records the q it used."""
    grid = meas.VoxelGrid((64, 64), (0.3, 0.3))
    problem = geo.GeometryProblem(grid, np.zeros((64, 64)), (9.6, 9.6), 8.0, 12.0, 10.0)
    gopt = geo.GeometryOptions()
    assert meas.auto_quad_order(None, grid, 10.0) == 2 and cpl.misfit_quad_order(problem, gopt, None) == 2
    coarse = replace(problem, grid=meas.VoxelGrid((16, 16), (1.5, 1.5)))
    assert meas.auto_quad_order(None, coarse.grid, 10.0) == 6 and cpl.misfit_quad_order(coarse, gopt, None) == 3
    assert cpl.misfit_quad_order(problem, replace(gopt, quad_order=1), None) == 1
    assert cpl.misfit_quad_order(coarse, gopt, 5) == 5


def test_sharp_coupled_operator_is_the_decoupled_one(laminar_coarse):
    """With a (nearly) sharp indicator and R fixed, T_i(R) c is the decoupled voxel mean T~_h c exactly."""
    _, _, res = laminar_coarse
    g, v = res.geometry, res.velocity
    q = meas.auto_quad_order(None, res.grid, g.coefficients[0])
    vp = vel.assemble(
        res.grid,
        res.velocity_image,
        g.coefficients,
        g.center,
        replace(vel.VelocityOptions(), inner_radius=v.disk_map.r_in),
        basis=v.basis,
    )
    model = cpl.velocity_misfit_model(
        res.grid, res.velocity_image, res.magnitude, g.center, res.lumen.r1, geo.GeometryOptions().n_fourier, q
    )
    c = np.random.default_rng(1).normal(size=v.basis.size)
    c_r, c_v = ca.MX.sym("c_r", g.coefficients.size), ca.MX.sym("c_v", c.size)
    expr = cpl.velocity_residual(model, c_r, c_v, v.basis, v.disk_map.r_in, 1e-9, "erf", floor=1e-12)
    r = ca.Function("r", [c_r, c_v], [expr])(g.coefficients, c)
    scale = np.sqrt(model.weights / model.weights.sum())
    t_coupled = np.asarray(r).ravel() / np.where(scale > 0, scale, np.inf) + model.data
    pos = np.searchsorted(model.index, vp.voxels.index)
    assert np.array_equal(model.index[pos], vp.voxels.index)
    ok = scale[pos] > 1e-6  # voxels whose weight is ~0 do not determine T_i numerically through r_i
    assert ok.mean() > 0.9
    expected = vp.operator @ c
    # same sub-voxel points and the same closed-form inverse map: rounding-level agreement
    assert np.allclose(t_coupled[pos][ok], expected[ok], rtol=0, atol=1e-9 * np.max(np.abs(expected)))
    outside = np.setdiff1d(np.arange(model.index.size), pos)
    far = outside[scale[outside] > 1e-6]
    assert np.max(np.abs(t_coupled[far])) < 1e-9 * np.max(np.abs(expected))  # T = 0 outside the lumen


def _coupled_nlp(res, start: bool = False):
    """The coupled NLP of a decoupled result, velocity weight 1e4 (mm^2/(m/s)^2), its alpha and beta; with
    ``start`` its point classes from the result's wall (as a solve builds it; a near-wall layer needs it)."""
    g, v = res.geometry, res.velocity
    held = {"start": g.coefficients, "stretch": cpl.layer_stretch(v)} if start else {}
    return cpl.build(
        _problem(res), geo.GeometryOptions(), res.velocity_image, vel.VelocityOptions(), v.basis,
        v.disk_map.r_in, 1e4, g.alpha, v.beta, **held,
    )  # fmt: skip


def _solver_derivatives(res, hessian: str, seed: int):
    """The coupled NLP of ``res``, a start perturbed by 1e-3 relative (``seed``), gamma, and the solver's shared
    ``(f, grad, hess)`` there (``hessian``: "gauss-newton" or "exact")."""
    g, v = res.geometry, res.velocity
    nlp = _coupled_nlp(res)
    solver, _keep = cpl._ipopt(nlp, hessian, cpl.CoupledOptions())
    _, shared = solver.shared
    x = np.concatenate([g.coefficients, v.coefficients])
    x = x + np.random.default_rng(seed).normal(size=x.size) * 1e-3 * (np.abs(x) + 1e-2)
    return nlp, x, g.gamma, [np.asarray(a) for a in shared.function(x, g.gamma)]


def test_chain_rule_jacobian_equals_casadi_ad(laminar_coarse):
    _, _, res = laminar_coarse
    assert_coupled_jacobian_is_exact(_coupled_nlp(res), res.geometry, res.velocity)


def test_gauss_newton_solver_gradient_and_hessian_from_the_jacobian_blocks(laminar_coarse):
    """The coupled IPOPT's gradient ``2 J^T r + grad(penalty)`` and Hessian ``2 J^T J + 2 P`` (from the Jacobian's
    blocks, one shared evaluation) equal CasADi's reverse-mode gradient of the functional and the product of the
    assembled Jacobian, at a perturbed start."""
    _, _, res = laminar_coarse
    nlp, x, gamma, (f, grad, hess) = _solver_derivatives(res, "gauss-newton", 5)
    ref = ca.Function("ref", [nlp.x, nlp.gamma], [nlp.f, ca.gradient(nlp.f, nlp.x), nlp.jacobian])
    f_ref, grad_ref, jac = (np.asarray(a) for a in ref(x, gamma))
    hess_ref = 2 * jac.T @ jac + 2 * nlp.penalty_hessian()
    # the same derivatives summed in another order: rounding-level agreement
    assert abs(f.item() - f_ref.item()) <= 1e-12 * abs(f_ref.item())
    np.testing.assert_allclose(grad.ravel(), grad_ref.ravel(), rtol=0, atol=1e-9 * np.max(np.abs(grad_ref)))
    np.testing.assert_allclose(hess, hess_ref, rtol=0, atol=1e-11 * np.max(np.abs(hess_ref)))


def test_jacobian_stacked_from_its_block_values_equals_the_assembled_one(laminar_coarse):
    """The sensitivities stack ``J`` in NumPy from its blocks' values (:meth:`CoupledNLP.stack_jacobian`): the
    same numbers as the graph's :attr:`CoupledNLP.jacobian` (the same products in another order: 1e-13), rows
    of voxels without points (zero derivatives) included."""
    _, _, res = laminar_coarse
    g, v = res.geometry, res.velocity
    nlp = _coupled_nlp(res, start=True)
    assert nlp.velocity_model.rows is not None and nlp.velocity_model.rows.size < nlp.velocity_model.index.size
    x = np.concatenate([g.coefficients, v.coefficients])
    x = x + np.random.default_rng(6).normal(size=x.size) * 1e-3 * (np.abs(x) + 1e-2)
    values = ca.Function("blocks", [nlp.x, nlp.gamma], [*nlp.jacobian_blocks(), nlp.jacobian])(x, g.gamma)
    want = np.asarray(values[-1])
    np.testing.assert_allclose(nlp.stack_jacobian(values[:-1]), want, rtol=0, atol=1e-13 * np.max(np.abs(want)))


def test_objective_gradient_taylor(laminar_coarse):
    """Taylor test of CasADi's gradient of the coupled functional: remainder O(t^2)."""
    _, _, res = laminar_coarse
    g, v = res.geometry, res.velocity
    nlp = _coupled_nlp(res)
    fg = ca.Function("fg", [nlp.x], ca.substitute([nlp.f, ca.gradient(nlp.f, nlp.x)], [nlp.gamma], [ca.MX(g.gamma)]))
    x = np.concatenate([g.coefficients, v.coefficients])
    d = np.random.default_rng(3).normal(size=x.size) * np.concatenate(
        [np.full(g.coefficients.size, 0.05), np.abs(v.coefficients) + 1e-3]
    )
    # halving t divides the remainder by 4 (4 +- 0.5: the O(t^3) term)
    checks.assert_taylor(lambda z: fg(z)[0], lambda z, dd: np.asarray(fg(z)[1]).ravel() @ dd, x, d, steps=(1e-2, 5e-3))


def test_coupled_agrees_with_decoupled_on_well_posed_data():
    """SNR 25: both meet the issue's accuracy, differ by less than the decoupled error and lie within the error bars."""
    acq, truth = phantoms.make_phantom("laminar", h_mm=1.0, snr=25, seed=21)
    dec = reconstruct(acq)[0]
    cou = reconstruct(acq, ReconstructionOptions(method="coupled"))[0]
    assert cou.converged and cou.method == "coupled" and cou.coupled_info["velocity_weight"] > 0
    ed, ec = metrics.compare_slice(dec, truth), metrics.compare_slice(cou, truth)
    assert ec.radius_rel_l2 <= 0.005 and ec.wss_rel_l2 <= 0.05
    diff = np.linalg.norm(cou.wss.tau - dec.wss.tau) / np.linalg.norm(dec.wss.tau)
    assert diff <= ed.wss_rel_l2
    # within the error bars: the linearized 2-sigma bands (both from the same data, so this is generous) overlap
    bar = 2 * np.hypot(dec.wss.tau_std, cou.wss.tau_std)
    assert np.all(np.abs(cou.wss.tau - dec.wss.tau) <= bar)
    assert abs(cou.wss.mean - dec.wss.mean) <= 2 * np.hypot(dec.wss.mean_std, cou.wss.mean_std)


def test_coupled_geometry_better_when_magnitude_is_poor():
    """SNR 6: the velocity image constrains the wall; measured mean radius error 0.90 % -> 0.82 % (seeds 0-2)."""
    errs = {"decoupled": [], "coupled": []}
    for seed in range(3):
        acq, truth = phantoms.make_phantom("laminar", h_mm=1.0, snr=6, seed=seed)
        for method in errs:
            res = reconstruct(acq, ReconstructionOptions(method=method))[0]
            errs[method].append(metrics.compare_slice(res, truth).radius_rel_l2)
    assert np.mean(errs["coupled"]) < 0.97 * np.mean(errs["decoupled"])


def test_coupled_needs_eta_2(laminar_coarse):
    _, _, res = laminar_coarse
    v = res.velocity
    with pytest.raises(InputError, match="eta = 2"):
        cpl.build(
            _problem(res),
            geo.GeometryOptions(),
            res.velocity_image,
            vel.VelocityOptions(eta=3.0),
            v.basis,
            v.disk_map.r_in,
            1e4,
            1e-3,
            1e-8,
        )


def test_cli_coupled(tmp_path):
    inp = tmp_path / "in.h5"
    assert main(["phantom", "--case", "laminar", "--h", "1.5", "--seed", "5", "-o", str(inp)]) == 0
    out = tmp_path / "out.h5"
    assert main(["reconstruct", str(inp), "-o", str(out), "--method", "coupled", "--velocity-weight", "2e4"]) == 0
    with h5py.File(out) as f:
        s = f["slice_000"]
        assert s.attrs["method"] == "coupled"
        info = json.loads(s.attrs["coupled_json"])
        assert info["velocity_weight"] == 2e4 and info["weight_method"].startswith("given")
    assert main(["reconstruct", str(inp), "-o", str(tmp_path / "bad.h5"), "--method", "coupled", "--eta", "3"]) == 2
    assert not (tmp_path / "bad.h5").exists()


@pytest.fixture(scope="module")
def turbulent_layered():
    """A decoupled turbulent slice (DNS at Re_tau 549, h = 1.5 mm) that chose the law-of-the-wall layer (``low_re``)."""
    acq, truth = phantoms.make_phantom("turbulent550", h_mm=1.5, snr=25, seed=5)
    res = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    assert res.near_wall.model == "low_re"
    return acq, truth, res


def test_sharp_coupled_operator_with_a_layer_is_the_decoupled_one(turbulent_layered):
    """With a sharp indicator and R fixed, the coupled voxel values of an enriched basis (polynomials by the
    points' midpoint rule, the layer by its exact cell means over the exact inside area) equal the decoupled
    operator's, layer columns included: same points and cells; near the wall the coupled cell means take the
    trapezoid formula throughout and the angular factor rho^m uncapped (both smooth as R moves), where the fit
    uses the curvature-corrected midpoint deeper than 3 (a + b) (within 1e-4 of the trapezoid) and caps rho
    at 1, hence 1e-5 relative (1e-9 for the polynomial columns alone, test above)."""
    _, _, res = turbulent_layered
    g, v = res.geometry, res.velocity
    vopt = replace(vel.VelocityOptions(), inner_radius=v.disk_map.r_in)
    vp = vel.assemble(res.grid, res.velocity_image, g.coefficients, g.center, vopt, basis=v.basis.base)
    vp = vp.with_layer(v.basis, nw.LayerQuadrature(vp).columns(v.basis), vopt.laplacian_power)  # as the fit's
    q = meas.auto_quad_order(None, res.grid, g.coefficients[0])
    model = cpl.velocity_misfit_model(
        res.grid, res.velocity_image, res.magnitude, g.center, res.lumen.r1, geo.GeometryOptions().n_fourier, q,
        start=g.coefficients, reach_mm=meas.heaviside_reach(1e-9),
    )  # fmt: skip
    # the start's wall classifies the points: full cell means near it, the far-inside branch and zero beyond
    model.margin_mm = cpl.START_MARGIN_VOXELS * res.grid.h  # as build() sets it
    l_mm = v.basis.scale * cpl.layer_stretch(v)
    classes = cpl.layer_point_classes(model, l_mm, cpl.layer_stretch(v), v.disk_map.r_in, model.margin_mm)
    n_pts = model.dist.size
    outside = n_pts - classes["band"].size - classes["far"].size
    # (the voxels wholly beyond the indicator's reach of the start's wall hold no points: few outside points left)
    assert min(classes["band"].size, classes["far"].size) > 0.02 * n_pts and outside > 0.005 * n_pts
    c = np.random.default_rng(2).normal(size=v.basis.size)
    c_r, c_v = ca.MX.sym("c_r", g.coefficients.size), ca.MX.sym("c_v", c.size)
    expr = cpl.velocity_residual(
        model, c_r, c_v, v.basis, v.disk_map.r_in, 1e-9, "erf", floor=1e-12, stretch=cpl.layer_stretch(v)
    )
    r = np.asarray(ca.Function("r", [c_r, c_v], [expr])(vp.disk_map.coefficients, c)).ravel()
    scale = np.sqrt(model.weights / model.weights.sum())
    t_coupled = r / np.where(scale > 0, scale, np.inf) + model.data
    pos = np.searchsorted(model.index, vp.voxels.index)
    assert np.array_equal(model.index[pos], vp.voxels.index)
    ok = scale[pos] > 1e-6
    expected = vp.operator @ c
    assert np.allclose(t_coupled[pos][ok], expected[ok], rtol=0, atol=1e-5 * np.max(np.abs(expected)))


def test_chain_rule_jacobian_with_a_layer_equals_casadi_ad(turbulent_layered):
    _, _, res = turbulent_layered
    g, v = res.geometry, res.velocity
    nlp = _coupled_nlp(res, start=True)
    assert_coupled_jacobian_is_exact(nlp, g, v)


def test_coupled_method_takes_the_near_wall_layer(turbulent_layered):
    """Default options with ``--method coupled`` on a turbulent slice (DNS at Re_tau 549, h = 1.5 mm, SNR 25):
    the coupled solve keeps the decoupled start's law-of-the-wall layer and scale and its mean WSS is within 5 %
    (measured -1.3 %; the decoupled start -0.6 %), where the coupled method on the paper's basis alone misses by
    more than 10 % (measured -19 %)."""
    acq, truth, dec = turbulent_layered
    cou = reconstruct(acq, ReconstructionOptions(method="coupled", uncertainty=False))[0]
    assert cou.method == "coupled" and cou.converged
    assert cou.near_wall.model == "low_re" and cou.near_wall.scale_mm == dec.near_wall.scale_mm
    assert cou.velocity.basis.family == dec.velocity.basis.family  # the member at the decoupled Re_tau = R/l
    assert isinstance(cou.velocity.basis, nw.EnrichedBasis)
    assert abs(metrics.compare_slice(cou, truth).mean_wss_rel) < 0.05
    off = ReconstructionOptions(method="coupled", uncertainty=False)
    off = replace(off, velocity=replace(off.velocity, near_wall="off"))
    assert abs(metrics.compare_slice(reconstruct(acq, off)[0], truth).mean_wss_rel) > 0.10


def test_a_failed_gauss_newton_solve_falls_back_to_the_exact_hessian(laminar_coarse, monkeypatch):
    """If IPOPT with the Gauss-Newton Hessian fails (as it did on one turbulent slice with a layer, h = 0.75 mm,
    seed 0 of the resolution study), the coupled solve is redone with the exact Hessian and says so; both
    Hessians reach the same minimizer where both converge (1e-6 relative in the WSS-carrying coefficients)."""
    from wss_nlp.errors import SolverError

    _, _, res = laminar_coarse
    g, v = res.geometry, res.velocity
    calls = []
    real = cpl.run_nlpsol

    def flaky(solver, what, **kw):
        calls.append(solver.name())
        if len(calls) == 1:
            raise SolverError(f"{what}: IPOPT failed with status Error_In_Step_Computation")
        return real(solver, what, **kw)

    monkeypatch.setattr(cpl, "run_nlpsol", flaky)
    out = cpl.solve(_problem(res), geo.GeometryOptions(), res.velocity_image, vel.VelocityOptions(), g, v, 1e4)
    assert len(calls) == 2 and out.stats.converged and out.stats.extra["quad_order"] == 3
    assert out.stats.extra["hessian"] == "exact" and "Error_In_Step" in out.stats.extra["gauss_newton_failed"]
    monkeypatch.setattr(cpl, "run_nlpsol", real)
    ref = cpl.solve(_problem(res), geo.GeometryOptions(), res.velocity_image, vel.VelocityOptions(), g, v, 1e4)
    assert ref.stats.extra["hessian"] == "gauss-newton"
    np.testing.assert_allclose(out.velocity.coefficients, ref.velocity.coefficients, rtol=0,
                               atol=1e-6 * np.max(np.abs(ref.velocity.coefficients)))  # fmt: skip


def test_coupled_converges_where_a_sharp_inside_fraction_stalled():
    """The turbulent slice (h = 1 mm, SNR 25, seed 4, beta fixed) on which the coupled solve stalled with both
    Hessians while the layer's inside fraction was sharp (piecewise linear in the wall's position; a cell's edge
    sat 2e-5 mm from the wall at the stall) converges with the smoothed one, by Gauss-Newton alone and within a
    wall move of the start's margin; its WSS error is its neighbours' (7.1 %; below 10 %)."""
    acq, truth = phantoms.make_phantom("turbulent", h_mm=1.0, snr=25, seed=4)
    res = reconstruct(
        acq, ReconstructionOptions(method="coupled", uncertainty=False, choice=ChoiceOptions(beta_rule="fixed"))
    )[0]
    extra = res.velocity.stats.extra
    assert res.converged and res.near_wall.model == "low_re"
    assert extra["hessian"] == "gauss-newton" and extra["margin_passes"] == 1
    assert metrics.compare_slice(res, truth).wss_rel_l2 < 0.10


def test_coupled_with_the_layer_matches_the_decoupled_accuracy_on_the_re_tau_180_pipe():
    """The resolution study's claim (coupled within 0.3 points of the decoupled WSS error on the Re_tau 180
    pipe, 6-8 %, where the plain-basis coupled method was 15-20 % off) on a seed the study does not use
    (h = 1 mm, SNR 25, seed 21; measured 7.8 % decoupled, 8.0 % coupled): within 1 point, and below 10 %."""
    acq, truth = phantoms.make_phantom("turbulent", h_mm=1.0, snr=25, seed=21)
    dec = metrics.compare_slice(reconstruct(acq, ReconstructionOptions(uncertainty=False))[0], truth)
    res = reconstruct(acq, ReconstructionOptions(method="coupled", uncertainty=False))[0]
    cou = metrics.compare_slice(res, truth)
    assert res.near_wall.model == "low_re" and res.converged
    assert abs(cou.wss_rel_l2 - dec.wss_rel_l2) <= 0.01 and cou.wss_rel_l2 < 0.10


def test_a_wall_move_beyond_the_layer_margin_is_re_solved_with_wider_point_classes(turbulent_layered, monkeypatch):
    """The layer's point classes hold for walls within a margin of the start (the far-inside formula needs the
    cell wholly in the fluid). A margin smaller than the solve's actual move (measured 0.04 mm here, h = 1.5 mm)
    sends the solve round again with classes for twice that move, and the result equals the default one's to
    IPOPT's tolerance: the far-inside cell means differ from the trapezoid by less than 1e-4 relative, and the
    two solves stop at IPOPT's tolerance (1e-4) from different starts (measured: radius coefficients 1.2e-5 mm,
    velocity coefficients 1e-5 of the largest)."""
    _, _, res = turbulent_layered
    g, v = res.geometry, res.velocity
    args = (_problem(res), geo.GeometryOptions(), res.velocity_image, vel.VelocityOptions(), g, v, 1e4)
    ref = cpl.solve(*args)
    assert ref.stats.extra["margin_passes"] == 1
    assert ref.stats.extra["wall_move_mm"] <= ref.stats.extra["start_margin_mm"]
    monkeypatch.setattr(cpl, "START_MARGIN_VOXELS", 1e-3)  # 0.0015 mm: below the move
    out = cpl.solve(*args)
    assert out.stats.extra["margin_passes"] == 2 and out.stats.converged
    assert out.stats.extra["start_margin_mm"] == pytest.approx(2 * ref.stats.extra["wall_move_mm"], rel=0.05)
    np.testing.assert_allclose(out.geometry.coefficients, ref.geometry.coefficients, rtol=0, atol=1e-4)
    np.testing.assert_allclose(out.velocity.coefficients, ref.velocity.coefficients, rtol=0,
                               atol=1e-4 * np.max(np.abs(ref.velocity.coefficients)))  # fmt: skip


def test_voxels_beyond_the_indicators_reach_hold_no_points_and_change_nothing(laminar_coarse):
    """Voxels farther outside the start's wall than the erf indicator's reach (6 gamma) plus the margin keep
    their rows (model value 0) but lose their points: the residual and its Jacobian equal the model with every
    point's, at the start and at a wall moved by 0.8 of the margin (exact zeros there in double precision;
    the Jacobian's dropped entries were below 1e-15 of its largest)."""
    _, _, res = laminar_coarse
    g, v = res.geometry, res.velocity
    q, gamma = meas.auto_quad_order(None, res.grid, g.coefficients[0]), g.gamma
    margin = cpl.START_MARGIN_VOXELS * res.grid.h
    args = (res.grid, res.velocity_image, res.magnitude, g.center, res.lumen.r1, geo.GeometryOptions().n_fourier, q)
    full = cpl.velocity_misfit_model(*args, start=g.coefficients, margin_mm=margin)
    kept = cpl.velocity_misfit_model(
        *args, start=g.coefficients, margin_mm=margin, reach_mm=meas.heaviside_reach(gamma, "erf")
    )
    assert full.dropped == 0 and full.rows is None
    assert kept.dropped > 0.1 * kept.index.size and kept.rows.size + kept.dropped == kept.index.size
    np.testing.assert_array_equal(kept.index, full.index)
    c_r, c_v = ca.MX.sym("c_r", g.coefficients.size), ca.MX.sym("c_v", v.basis.size)
    values = []
    for model in (full, kept):
        r, j_r, j_v, _ = cpl.velocity_residual(model, c_r, c_v, v.basis, v.disk_map.r_in, gamma, "erf", jacobian=True)
        values.append(ca.Function("f", [c_r, c_v], [r, j_r, j_v]))
    moved = g.coefficients.copy()
    moved[0] += 0.8 * margin
    for c in (g.coefficients, moved):
        ref, out = (f(c, v.coefficients) for f in values)
        np.testing.assert_array_equal(np.asarray(out[0]), np.asarray(ref[0]))
        for a, b in zip(out[1:], ref[1:]):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-15 * np.max(np.abs(np.asarray(b))))


@pytest.mark.slow  # CI budget: 50 s; the coupled gradient's Taylor test and the chain-rule Jacobian tests stay in CI
def test_the_exact_hessian_fallback_equals_casadis_hessian_of_the_functional(laminar_coarse):
    """The fallback's exact Hessian, Gauss-Newton plus 2 sum_i r_i hess r_i along the c_R directions
    (coupled.residual_curvature; nlpsol's own exhausted 24 GB on a turbulent slice at h = 1 mm), equals
    CasADi's Hessian of the functional on a small slice, at a perturbed start (the same derivatives summed
    in another order: 1e-9 of the largest entry)."""
    _, _, res = laminar_coarse
    nlp, x, gamma, (_, _, hess) = _solver_derivatives(res, "exact", 6)
    ref = np.asarray(ca.Function("h", [nlp.x, nlp.gamma], [ca.hessian(nlp.f, nlp.x)[0]])(x, gamma))
    np.testing.assert_allclose(hess, ref, rtol=0, atol=1e-9 * np.max(np.abs(ref)))


def test_curvature_columns_equal_differences_of_the_chain_rule_jacobian(turbulent_layered):
    """``residual_curvature`` (forward-over-reverse sweeps of ``w^T r`` through the NumPy callbacks) along the
    c_R directions and gamma, on a slice with a near-wall layer (its cell means, smoothed inside fractions and
    far-inside ladders), equals central differences of ``J^T w`` with the chain-rule Jacobian, an independent
    route (its first derivatives are assembled by hand). Steps 1e-5 mm: 1.5e-9 of the largest entry measured
    (1.5e-6 at 1e-4 mm, truncation; 7.5e-9 at 1e-6 mm, rounding); 1e-7 allowed."""
    _, _, res = turbulent_layered
    g, v = res.geometry, res.velocity
    nlp = _coupled_nlp(res, start=True)
    rng = np.random.default_rng(12)
    x = np.concatenate([g.coefficients, v.coefficients])
    w = rng.normal(size=nlp.residual.numel())
    n_x, n_r = x.size, nlp.n_r
    directions = np.eye(n_x + 1)[:, list(range(n_r)) + [n_x]]
    got = np.asarray(cpl.residual_curvature(nlp, with_gamma=True)(x, g.gamma, w, directions))
    blocks = ca.Function("blocks", [nlp.x, nlp.gamma], [ca.densify(b) for b in nlp.jacobian_blocks()])

    def jtw(z):
        return nlp.stack_jacobian([np.asarray(b) for b in blocks(z[:n_x], z[n_x])]).T @ w

    z0, step = np.append(x, g.gamma), 1e-5
    want = np.column_stack([(jtw(z0 + step * d) - jtw(z0 - step * d)) / (2 * step) for d in directions.T])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-7 * np.max(np.abs(want)))


def test_inverse_map_ladder_equals_casadi_ad_of_the_closed_form():
    """The Taylor-series derivatives of the inverse map's radius rho(R) = 2 r / (r_in + sqrt(r_in^2 + 4 (R - r_in)
    r)) in R (orders 0-4, NumPy) equal CasADi's repeated derivatives of the formula at points from the centre
    (r = 0) to beyond the wall, to 1e-13 of each order's largest value."""
    rng = np.random.default_rng(21)
    r_in, n = 2.0, 400
    dist, big_r = np.append(rng.uniform(0.0, 14.0, n - 1), 0.0), rng.uniform(2.5, 13.0, n)
    r_sym, d_sym = ca.SX.sym("R"), ca.SX.sym("r")
    exprs = [2 * d_sym / (r_in + ca.sqrt(r_in**2 + 4 * (r_sym - r_in) * d_sym))]
    for _ in range(4):
        exprs.append(ca.jacobian(exprs[-1], r_sym))
    ref = ca.Function("ref", [r_sym, d_sym], exprs).map(n)(big_r[None, :], dist[None, :])
    derivative = cpl._inverse_map_at(dist, r_in)
    for order, r in enumerate(ref):
        r = np.asarray(r).ravel()
        np.testing.assert_allclose(derivative(big_r, order), r, rtol=0, atol=1e-13 * np.max(np.abs(r)))
