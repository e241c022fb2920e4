"""The k-space (point-spread function) measurement model: kernels, forward models, phantoms, pipeline, CLI."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

import casadi as ca

from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.core import checks
from wss_nlp.app import cli
from wss_nlp.models import kspace
from wss_nlp.analysis import metrics
from wss_nlp.models import coupled as cpl
from wss_nlp.io import files as wio
from wss_nlp.models import geometry as geo
from wss_nlp.models import measurement as meas
from wss_nlp.synthetic import phantoms as ph
from wss_nlp.models import preprocess as pp
from wss_nlp.core import radius as rad
from wss_nlp.pipeline import ReconstructionOptions
from wss_nlp.pipeline import driver as rc
from wss_nlp.models import velocity as vel
from wss_nlp.parameters import noise as nl
from wss_nlp.uncertainty import sensitivity as sens
from wss_nlp.models import wss as wss_mod
from wss_nlp.parameters.alpha import choose_alpha
from wss_nlp.errors import InputError

from conftest import assert_coupled_jacobian_is_exact

GRID = meas.VoxelGrid((40, 36), (1.0, 1.2), (-19.5, -20.8))


def _blob(x, y):
    """A smooth complex object, band-limited to far below the acquired frequencies."""
    return np.exp(-((x - 0.3) ** 2 + (y + 0.7) ** 2) / (2 * 3.0**2)) * np.exp(0.3j * x)


def _kernel_image(psf, order, f):
    ny, nx = GRID.shape
    ky, kx = psf.kernel(ny, GRID.dy, order, 0), psf.kernel(nx, GRID.dx, order, 1)
    fy = GRID.origin_mm[1] + (np.arange(ny * order) + 0.5) * GRID.dy / order - 0.5 * GRID.dy
    fx = GRID.origin_mm[0] + (np.arange(nx * order) + 0.5) * GRID.dx / order - 0.5 * GRID.dx
    yy, xx = np.meshgrid(fy, fx, indexing="ij")
    return ky @ f(xx, yy) @ kx.T


@pytest.mark.parametrize("kind", kspace.FILTERS)
def test_kernel_agrees_with_the_fft_acquisition(kind):
    """Two independent implementations (kernel matrices; numpy FFT, crop, filter, inverse FFT) of one PSF.

    Without zero-filling both keep the same frequencies and agree to rounding (1e-9 of a unit signal).
    With F = 2 the scanner's extra Nyquist line (-N/2 without +N/2) differs from the model's symmetric
    split; for this smooth object its share is below 1e-3.
    """
    for fill, tol in ((1.0, 1e-9), (2.0, 1e-3)):
        psf = kspace.PSF(kind, (fill, fill))
        acquired = kspace.acquire(_blob, GRID, psf, None, np.random.default_rng(0))
        model = _kernel_image(psf, 8, _blob)
        assert np.max(np.abs(acquired - model)) < tol, (kind, fill)


def test_kernel_rows_sum_to_the_dc_filter_weight():
    """A constant object is reproduced exactly: ``sum_m K[j, m] = w(0) = 1`` for every filter and fill."""
    for kind in kspace.FILTERS:
        for fill in (1.0, 1.5, 2.0):
            k = kspace.PSF(kind, (fill, fill)).kernel(31, 0.7, 3, 0)
            np.testing.assert_allclose(k.sum(axis=1), 1.0, atol=1e-12)


def test_acquired_noise_level_matches_the_snr_definition():
    """SNR is defined at the acquired resolution without filter: image noise std rho/snr per channel there,
    lower with a filter (Hamming: sqrt(mean w^2) = 0.63 per axis, 0.40 in 2D). 40 x 36 voxels, 20 draws:
    the sample std is within 3 % of its expectation."""
    zero = lambda x, y: np.zeros_like(x, dtype=complex)  # noqa: E731
    for kind, factor in (("none", 1.0), ("hamming", None)):
        psf = kspace.PSF(kind, (1.0, 1.0))
        noise = np.array([kspace.acquire(zero, GRID, psf, 10.0, np.random.default_rng(s)) for s in range(20)])
        if factor is None:
            w = [kspace.filter_weights(np.arange(-(n // 2), n - n // 2), n, kind) for n in GRID.shape]
            factor = float(np.sqrt(np.mean(w[0] ** 2) * np.mean(w[1] ** 2)))
        assert np.std(noise.real) == pytest.approx(0.1 * factor, rel=0.03)


def test_averager_equals_the_dense_kernel_sum():
    """The separable two-product evaluation of :class:`kspace.Averager` against the explicit double sum."""
    psf = kspace.PSF("tukey", (2.0, 2.0))
    order = 3
    index = np.array([5 * 36 + 7, 5 * 36 + 8, 6 * 36 + 8, 20 * 36 + 30])
    rng = np.random.default_rng(4)
    values = rng.standard_normal((index.size, order * order, 2))
    out_index = np.array([0, 6 * 36 + 9, 21 * 36 + 30])
    got = kspace.Averager(GRID, index, order, psf, out_index)(values)
    ky = psf.kernel(40, GRID.dy, order, 0)
    kx = psf.kernel(36, GRID.dx, order, 1)
    want = np.zeros((out_index.size, 2))
    for j, o in enumerate(out_index):
        oy, ox = divmod(o, 36)
        for i, v in enumerate(index):
            vy, vx = divmod(v, 36)
            for p in range(order * order):
                a, b = divmod(p, order)
                want[j] += ky[oy, vy * order + a] * kx[ox, vx * order + b] * values[i, p]
    np.testing.assert_allclose(got, want, atol=1e-13)


def test_magnitude_model_casadi_equals_numpy_and_its_jacobian_passes_a_taylor_test():
    """The CasADi graph of the k-space magnitude model equals its NumPy twin; CasADi's exact Jacobian in the
    coefficients and in the centre shift gives second-order Taylor remainders (halving the step quarters them)."""
    psf = kspace.PSF("hamming", (2.0, 2.0))
    c0 = np.zeros(rad.n_coefficients(4))
    c0[0], c0[1], c0[6] = 9.0, 0.6, -0.4
    model = kspace.magnitude_setup(GRID, (0.2, -0.3), 6.0, 12.0, 3, 1.0 / 3, psf)
    c, shift = ca.MX.sym("c", c0.size), ca.MX.sym("shift", 2)
    expr = kspace.magnitude_model(model, c, 1.0 / 3, shift=shift)
    x = ca.vertcat(c, shift)
    fun = ca.Function("f", [x], [expr])
    jac = ca.Function("j", [x], [ca.jacobian(expr, x)])
    x0 = np.concatenate([c0, [0.0, 0.0]])
    np.testing.assert_allclose(np.asarray(fun(x0)).ravel(), kspace.magnitude_model(model, c0, 1.0 / 3), atol=1e-13)
    d = np.random.default_rng(1).standard_normal(x0.size)
    checks.assert_taylor(lambda z: np.asarray(fun(z)), lambda z, dz: np.asarray(jac(z)) @ dz, x0, d)


def test_separable_psf_callback_equals_casadi_products_with_exact_derivatives():
    """The BLAS-evaluated PSF operation (kspace.SeparablePSF) inside a nonlinear CasADi graph against the same
    graph with CasADi's own products: values, Jacobian (forward mode, batched seeds), gradient (reverse mode,
    the adjoint) and Hessian (forward over reverse) agree to rounding; the map and its adjoint pass a dot test."""
    rng = np.random.default_rng(4)
    ky, kx = rng.normal(size=(5, 7)), rng.normal(size=(4, 6))
    op = kspace.SeparablePSF(ky, kx)
    x, c = ca.MX.sym("x", 7, 6), ca.MX.sym("c", 3)
    inner = ca.sin(x * c[0]) + c[1] * x**2 + c[2]
    x0, c0 = rng.normal(size=(7, 6)), rng.normal(size=3)
    outs = []
    for image in (op(inner), ca.mtimes(ca.mtimes(ca.DM(ky), inner), ca.DM(kx.T))):
        f = ca.sumsqr(image)
        fun = ca.Function("f", [x, c], [image, ca.jacobian(image, c), ca.gradient(f, x), ca.hessian(f, c)[0]])
        outs.append([np.asarray(v) for v in fun(x0, c0)])
    for mine, plain in zip(*outs):
        assert np.max(np.abs(mine - plain)) <= 1e-12 * max(1.0, np.max(np.abs(plain)))
    adjoint = kspace.SeparablePSF(ky, kx, adjoint=True)
    checks.dottest(
        lambda v: op.apply(v.reshape(6, 7).T).T.ravel(),
        lambda w: adjoint.apply(w.reshape(4, 5).T).T.ravel(),
        42,
        20,
        rng,
    )


def test_separable_jacobian_equals_casadi_ad_and_the_solvers_agree():
    """The geometry solver's k-space Jacobian, assembled by the chain rule with the BLAS PSF
    (magnitude_model(jacobian=True)), equals CasADi's AD of the plain graph to rounding; IPOPT on it and the
    projected Gauss-Newton method on the plain graph (two independent solvers) reach the same minimizer."""
    psf = kspace.PSF("hamming", (2.0, 2.0))
    c0 = np.zeros(rad.n_coefficients(4))
    c0[0], c0[1], c0[6] = 9.0, 0.6, -0.4
    model = kspace.magnitude_setup(GRID, (0.2, -0.3), 6.0, 12.0, 3, 1.0 / 3, psf)
    c = ca.MX.sym("c", c0.size)
    value, jac = kspace.magnitude_model(model, c, 1.0 / 3, jacobian=True)
    plain = kspace.magnitude_model(model, c, 1.0 / 3)
    fun = ca.Function("f", [c], [value, jac, plain, ca.jacobian(plain, c)])
    v1, j1, v2, j2 = (np.asarray(a) for a in fun(c0))
    assert np.max(np.abs(v1 - v2)) < 1e-13 and np.max(np.abs(j1 - j2)) < 1e-12 * np.max(np.abs(j2))
    acq, _ = ph.make_phantom("laminar", h_mm=1.5, snr=25, seed=23, psf=psf)
    _, m, lumen = pp.preprocess(acq.magnitude[0], acq.grid, clip_upper=False)
    problem = geo.GeometryProblem(acq.grid, m, lumen.center, lumen.r0, lumen.r1, lumen.r_area, psf=psf)
    opts = geo.GeometryOptions(tol=1e-12)
    a = geo.IpoptGeometrySolver(problem, opts).solve()
    b = geo.solve_projected_gauss_newton(problem, opts)
    assert a.stats.converged and b.stats.converged
    assert np.max(np.abs(a.coefficients - b.coefficients)) < 1e-6 * a.coefficients[0]


def test_kspace_newton_hessian_equals_casadi_exact_hessian():
    """The chain-rule second-order term of the k-space model (eps^2 / F^3 outer products of dI plus the
    adjoint PSF on the points' H''), inside 2 (J^T J + sum r_i Hess r_i + alpha W), equals CasADi's
    algorithmic Hessian of the functional away from its minimizer (to rounding relative to the largest entry);
    IPOPT with it and with the Gauss-Newton Hessian reach the same minimizer, Newton in fewer iterations."""
    psf = kspace.PSF("hamming", (2.0, 2.0))
    acq, _ = ph.make_phantom("laminar", h_mm=1.5, snr=25, seed=29, psf=psf)
    _, m, lumen = pp.preprocess(acq.magnitude[0], acq.grid, clip_upper=False)
    problem = geo.GeometryProblem(acq.grid, m, lumen.center, lumen.r0, lumen.r1, lumen.r_area, psf=psf)
    newton = geo.IpoptGeometrySolver(problem, geo.GeometryOptions())
    nlp = newton.nlp
    assert nlp.jacobian is not None and nlp.curvature is not None
    chain = 2 * (ca.mtimes(nlp.jacobian.T, nlp.jacobian) + nlp.curvature + nlp.alpha * ca.diag(ca.DM(nlp.weights)))
    both = ca.Function("h", [nlp.c, nlp.alpha, nlp.data], [chain, ca.hessian(nlp.f, nlp.c)[0]])
    c = geo.initial_guess(problem, 8) + 0.05 * np.random.default_rng(5).normal(size=nlp.c.numel())
    ours, exact = (np.asarray(v) for v in both(c, 1e-3, problem.magnitude.ravel()[nlp.model.annulus]))
    assert np.max(np.abs(ours - exact)) < 1e-10 * np.max(np.abs(exact))
    a = newton.solve()
    b = geo.IpoptGeometrySolver(problem, geo.GeometryOptions(hessian="gauss-newton")).solve()
    assert a.stats.converged and b.stats.converged and a.stats.extra["hessian"] == "newton"
    assert np.max(np.abs(a.coefficients - b.coefficients)) < 1e-8
    assert a.stats.iterations < b.stats.iterations


def test_alpha_rules_of_the_two_geometry_solvers_agree_on_kspace_data():
    """The discrepancy rule for alpha run with IPOPT and with the projected Gauss-Newton method on k-space
    data: both estimate the noise on the voxels the k-space model fits (its window, not the box annulus) and
    choose the same alpha (two independent solvers, seed 24)."""
    psf = kspace.PSF("hamming", (2.0, 2.0))
    acq, _ = ph.make_phantom("laminar", h_mm=1.5, snr=25, seed=24, psf=psf)
    norm, m, lumen = pp.preprocess(acq.magnitude[0], acq.grid, clip_upper=False)
    problem = geo.GeometryProblem(acq.grid, m, lumen.center, lumen.r0, lumen.r1, lumen.r_area, psf=psf)
    choices = []
    for solver in ("ipopt", "gauss-newton"):
        options = ReconstructionOptions(
            geometry=geo.GeometryOptions(solver=solver), choice=ChoiceOptions(alpha_rule="discrepancy")
        )
        _, choice = choose_alpha(problem, acq.magnitude[0], norm, lumen, options.geometry, options.choice, "test")
        choices.append(choice)
    assert choices[0].noise == pytest.approx(choices[1].noise, rel=1e-12)
    assert choices[0].chosen == choices[1].chosen


def test_averaging_operator_dot_test():
    """The hand-written k-space averaging operator and its adjoint (two dense products each) pass a dot test."""
    psf = kspace.PSF("fermi", (2.0, 2.0))
    coef = np.zeros(rad.n_coefficients(2))
    coef[0] = 8.0
    vox = meas.lumen_voxels(GRID, (0.4, -0.2), coef, 3)
    averager = kspace.Averager(GRID, vox.index, 3, psf)
    signal = averager(vox.inside.astype(float))
    op = kspace.AveragingOperator(averager, vox.inside, signal, signal > 0.02)
    rng = np.random.default_rng(3)
    checks.dottest(lambda v: op @ v, lambda y: op.T @ y, op.shape[1], op.shape[0], rng)
    # and it is the velocity operator's averaging: constant point values give 1 on every kept voxel
    np.testing.assert_allclose((op @ np.ones(op.shape[1]))[signal > 0.02], 1.0, atol=1e-12)


@pytest.mark.parametrize("kind,fill", [("none", 1.0), ("hamming", 1.0), ("tukey", 2.0), ("fermi", 2.0)])
def test_noise_free_kspace_geometry_recovers_the_radius(kind, fill):
    """Noise-free k-space data of a static lumen (venc far above the flow), the exact signal scale: the
    k-space model recovers R within 0.05 % (the issue's bound), the box model misses by several times that.

    The ellipse's radius function is not in V_N; N = 12 represents it to < 1e-4 R. Seed 7 (not used to tune).
    """
    psf = kspace.PSF(kind, (fill, fill))
    acq, truth = ph.make_phantom("laminar", h_mm=1.0, snr=None, seed=7, psf=psf, venc=1e3)
    raw = acq.magnitude[0]
    _, m, lumen = pp.preprocess(raw, acq.grid, clip_upper=False)
    errors = []
    for model, data in ((psf, raw), (None, m)):
        problem = geo.GeometryProblem(acq.grid, data, lumen.center, lumen.r0, lumen.r1, lumen.r_area, psf=model)
        g = geo.solve(problem, geo.GeometryOptions(alpha=1e-6, n_fourier=12))
        phi = rad.uniform_angles(720)
        r_true = truth.radius_about(g.center, phi)
        errors.append(np.max(np.abs(g.radius(phi) - r_true)) / np.mean(r_true))
    assert errors[0] < 5e-4
    assert errors[1] > 3 * errors[0]


def test_kspace_velocity_operator_is_the_first_order_phase():
    """``T c = (K chi v)/(K chi)`` is the phase of ``K (chi exp(i pi v / venc))`` to first order: the
    difference shrinks like venc^-2 (the next term of arg is cubic in the phase spread over its mean)."""
    psf = kspace.PSF("hamming", (1.0, 1.0))
    coef = np.zeros(rad.n_coefficients(2))
    coef[0] = 9.0
    opts = vel.VelocityOptions(near_wall="off", degree=6, angular_order=2)
    vp = vel.assemble(GRID, np.zeros(GRID.shape), coef, (0.0, 0.0), opts, psf=psf)
    c = np.random.default_rng(2).standard_normal(vp.basis.size) * 0.1
    lin = vp.operator @ c
    vox = vp.voxels
    u = np.zeros(vox.px.shape)
    res = vel.result(vp, opts, c, 1.0, None)
    u[vox.inside] = res.evaluate_physical(vox.px[vox.inside], vox.py[vox.inside])
    keep = vp.weights > 0
    gaps = []
    for venc in (2.0, 4.0):
        z = vp.averager(vox.inside * np.exp(1j * np.pi * u / venc))
        gaps.append(np.max(np.abs(venc / np.pi * np.angle(z) - lin)[keep]))
    assert gaps[1] / gaps[0] == pytest.approx(0.25, abs=0.05)


@pytest.mark.parametrize("kind,fill", [("none", 1.0), ("hamming", 1.0), ("tukey", 2.0), ("hamming", 2.0)])
def test_noise_free_kspace_reconstruction_gets_laminar_wss_within_one_percent(kind, fill):
    """The whole pipeline (normalization, geometry, velocity, dephasing passes) on noise-free k-space data of
    Poiseuille flow in an ellipse: mean WSS within 1 % with the k-space model (measured 0.07-0.4 %), the box
    model at least 3x further off on the same data (measured 1.7-230 %). Noise-free data leave the beta rules
    nothing to weigh (their noise estimate is 0, so they fall back to the fixed beta): beta is fixed at a
    small 1e-9, as for any noise-free recovery. Seed 5 (not used to tune)."""
    psf = kspace.PSF(kind, (fill, fill))
    acq, truth = ph.make_phantom("laminar", h_mm=1.0, snr=None, seed=5, psf=psf)
    errors = {}
    for model in ("kspace", "box"):
        options = ReconstructionOptions(
            uncertainty=False,
            velocity=vel.VelocityOptions(beta=1e-9),
            acquisition=kspace.AcquisitionOptions(model, kind),
            choice=ChoiceOptions(beta_rule="fixed"),
        )
        r = rc.reconstruct(acq, options)[0]
        errors[model] = abs(r.wss.mean - truth.mean_wss) / truth.mean_wss
    assert errors["kspace"] < 0.01
    assert errors["box"] > 3 * errors["kspace"]


def test_zero_fill_comes_from_the_file_and_is_recorded(tmp_path):
    """``acquired_voxel_size_mm`` round-trips through the input file, sets F for the model, and the slice
    records the resolved PSF; the command line's --zero-fill overrides it."""
    inp = tmp_path / "in.h5"
    code = cli.main(
        ["phantom", "--case", "circle", "--h", "1.5", "--acquisition", "kspace", "--kspace-filter", "hamming",
         "--zero-fill", "2", "--snr", "30", "-o", str(inp)]
    )  # fmt: skip
    assert code == 0
    acq = wio.read_acquisition(str(inp))
    assert acq.acquired_voxel_size_mm == (3.0, 3.0)
    for k, (extra, fill) in enumerate((([], [2.0, 2.0]), (["--zero-fill", "1"], [1.0, 1.0]))):
        out = tmp_path / f"out{k}.h5"
        argv = ["reconstruct", str(inp), "-o", str(out), "--acquisition", "kspace", "--kspace-filter", "hamming"]
        assert cli.main([*argv, *extra, "--no-uncertainty"]) == 0
        with h5py.File(out) as f:
            recorded = json.loads(f["slice_000/geometry"].attrs["options_json"])["acquisition"]
        assert recorded == {"model": "kspace", "kspace_filter": "hamming", "zero_fill": fill}


def test_kspace_input_errors(tmp_path, capsys):
    """An acquired voxel smaller than the reported one, and a zero-filling factor below 1: one line, exit code
    2, nothing written."""
    inp, out = tmp_path / "in.h5", tmp_path / "out.h5"
    acq, _ = ph.make_phantom("circle", h_mm=1.5, snr=30, seed=1)
    acq.acquired_voxel_size_mm = (1.0, 1.5)
    with pytest.raises(InputError, match="acquired_voxel_size_mm"):
        acq.validate()
    acq.acquired_voxel_size_mm = None
    wio.write_acquisition(str(inp), acq)
    for argv in (["--acquisition", "kspace", "--zero-fill", "0.5"],):
        assert cli.main(["reconstruct", str(inp), "-o", str(out), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("wss-nlp: error:")
        assert not out.exists()


KSPACE = kspace.PSF("hamming", (2.0, 2.0))


class KSpacePipeline:
    """Geometry -> velocity -> mean WSS with the k-space model, re-run with one input changed (re-solves)."""

    gopt = geo.GeometryOptions(tol=1e-13)
    vopt = vel.VelocityOptions(near_wall="off")

    def __init__(self):
        acq, _ = ph.make_phantom("laminar", h_mm=1.5, snr=25, seed=13, psf=KSPACE)
        options = ReconstructionOptions(
            uncertainty=False, dephasing_correction=False, acquisition=kspace.AcquisitionOptions("kspace", "hamming")
        )
        self.res, self.mu = rc.reconstruct(acq, options)[0], acq.viscosity_pa_s
        self.problem = self._problem()
        self.g = geo.solve(self.problem, self.gopt)
        self.vp = self._velocity(self.g, self.res.velocity_image)
        self.v = vel.solve(self.vp, self.vopt, beta=1e-6)

    def _problem(self, m=None, center=None):
        lum = self.res.lumen
        m = self.res.magnitude if m is None else m
        center = lum.center if center is None else center
        return geo.GeometryProblem(self.res.grid, m, center, lum.r0, lum.r1, lum.r_area, psf=KSPACE)

    def _velocity(self, g, u):
        return vel.assemble(self.res.grid, u, g.coefficients, g.center, self.vopt, psf=KSPACE)

    def mean(self, m=None, alpha=None, gamma=None, center=None, u=None):
        g = self.g
        opts = geo.with_options(self.gopt, alpha=g.alpha if alpha is None else alpha, gamma=gamma or g.gamma)
        gg = geo.solve(self._problem(m, center), opts, x0=g.coefficients)
        vv = self._velocity(gg, self.res.velocity_image if u is None else u)
        return wss_mod.from_reconstruction(vel.solve(vv, self.vopt, beta=self.v.beta), 360, self.mu).mean

    def sensitivity(self):
        return sens.decoupled(self.problem, self.gopt, self.g, self.vp, self.vopt, self.v, self.mu)


def _image_sigma(grid, psf, snr: float) -> float:
    """Per-channel noise of a k-space phantom's image: ``1/snr`` times the filter's rms weight per axis."""
    out = 1.0 / snr
    for n, fill in zip(grid.shape, psf.zero_fill):
        n_acq = kspace.acquired_points(n, fill)
        out *= float(
            np.sqrt(
                np.mean(kspace.filter_weights(np.arange(-(n_acq // 2), n_acq - n_acq // 2), n_acq, psf.filter) ** 2)
            )
        )
    return out


def _central(f, h):
    return (f(h) - f(-h)) / (2 * h)


def test_kspace_sensitivities_match_resolves():
    """Exact derivatives of the k-space pipeline (CasADi Hessian and mixed derivatives of the PSF model,
    the averaging operator's adjoint) against central differences of re-solves (IPOPT at 1e-13): alpha,
    gamma, the centre, and random directions in the magnitude and velocity data, to 1e-4 relative as
    for the box model (tests/test_sensitivity.py). Hamming, twofold zero-filling, seed 13."""
    p = KSpacePipeline()
    s = p.sensitivity()
    g = p.g
    resolves = {
        "alpha": _central(lambda t: p.mean(alpha=g.alpha * (1 + t)), 1e-3) / g.alpha,
        "gamma": _central(lambda t: p.mean(gamma=g.gamma * (1 + t)), 1e-3) / g.gamma,
    }
    c0 = np.asarray(p.res.lumen.center, float)
    for j, name in enumerate(("center_x", "center_y")):
        resolves[name] = _central(lambda t: p.mean(center=tuple(c0 + t * np.eye(2)[j])), 1e-4)
    for name, fd in resolves.items():
        assert s.d_mean[sens.SCALARS.index(name)] == pytest.approx(fd, rel=1e-4), name
    rng = np.random.default_rng(17)
    m0, u0 = p.res.magnitude, p.res.velocity_image
    dm, du = np.zeros(m0.size), np.zeros(u0.size)
    dm[s.m_index] = rng.normal(size=s.m_index.size)
    du[s.u_index] = 0.01 * rng.normal(size=s.u_index.size)
    fd_m = _central(lambda t: p.mean(m=m0 + t * dm.reshape(m0.shape)), 1e-4)
    fd_u = _central(lambda t: p.mean(u=u0 + t * du.reshape(u0.shape)), 1e-4)
    assert s.d_mean_d_m @ dm[s.m_index] == pytest.approx(fd_m, rel=1e-4)
    assert s.d_mean_d_u @ du[s.u_index] == pytest.approx(fd_u, rel=1e-4)


@pytest.mark.slow
def test_kspace_band_agrees_with_monte_carlo():
    """The k-space band (correlated noise: Hamming, twofold zero-filling) against 80 noise draws added in
    k-space to one noise-free acquisition, beta fixed, no near-wall layer (the band is linearized at one
    model), the true noise level given (so the test checks the derivatives and the correlation model, not
    the noise estimate): the mean WSS's std within 25 % (the sample std of 80 draws is itself uncertain by
    8 %). Seed 21; about 2 minutes, hence slow (the derivatives are checked in CI by re-solves, the
    correlation model by sampling)."""
    acq0, _ = ph.make_phantom("laminar", h_mm=1.5, snr=None, seed=21, psf=KSPACE)
    signal0 = acq0.magnitude[0] * np.exp(1j * acq0.phase[0])
    rng = np.random.default_rng(2026)
    zero = lambda x, y: np.zeros_like(x, dtype=complex)  # noqa: E731
    snr = 25.0
    sigma = _image_sigma(acq0.grid, KSPACE, snr)

    def draw():
        d = signal0 + kspace.acquire(zero, acq0.grid, KSPACE, snr, rng)
        return wio.Acquisition(**{**vars(acq0), "magnitude": np.abs(d)[None], "phase": np.angle(d)[None]})

    how = kspace.AcquisitionOptions("kspace", "hamming")
    vopt = vel.VelocityOptions(near_wall="off")
    base = dict(choice=ChoiceOptions(beta_rule="fixed"), acquisition=how, noise_sigma=sigma, velocity=vopt)
    banded = rc.reconstruct(draw(), ReconstructionOptions(**base))[0]
    means = [rc.reconstruct(draw(), ReconstructionOptions(uncertainty=False, **base))[0].wss.mean for _ in range(80)]
    assert banded.wss.mean_std == pytest.approx(np.std(means, ddof=1), rel=0.25)


@pytest.mark.slow  # CI budget: 46 s; the SNR-definition and PSF-tail noise tests stay in CI
def test_noise_correlation_matches_sampled_kspace_noise():
    """The separable noise correlation of filtered, zero-filled k-space noise (what the band uses) against
    400 sampled noise images: neighbours 0-3 voxels apart within 0.02 (the sampling error is about 0.005)."""
    grid = meas.VoxelGrid((26, 26), (1.5, 1.5), (0.0, 0.0))
    zero = lambda x, y: np.zeros_like(x, dtype=complex)  # noqa: E731
    for kind, fill in (("hamming", 2.0), ("none", 2.0), ("tukey", 1.0)):
        psf = kspace.PSF(kind, (fill, fill))
        rng = np.random.default_rng(5)
        re = np.array([kspace.acquire(zero, grid, psf, 25.0, rng) for _ in range(400)]).real
        sampled = [np.mean(re[:, :, : 26 - d] * re[:, :, d:]) / np.mean(re**2) for d in range(4)]
        model = kspace.noise_correlation(26, fill, kind)[5, 5:9]
        np.testing.assert_allclose(sampled, model, atol=0.02)


def test_noise_estimate_subtracts_the_psf_tails():
    """With a wide PSF the vessel's signal reaches past the background margin: the plain Rayleigh estimate
    is biased high, the one with the predicted tails subtracted is within 10 % of the true level
    (mean over 6 draws; Hamming, twofold zero-filling; seeds 30-35)."""
    plain, corrected = [], []
    for seed in range(30, 36):
        acq, _ = ph.make_phantom("laminar", h_mm=1.5, snr=25, seed=seed, psf=KSPACE)
        how = kspace.AcquisitionOptions("kspace", "hamming")
        r = rc.reconstruct(acq, ReconstructionOptions(uncertainty=False, acquisition=how))[0]
        raw = acq.magnitude[0]
        plain.append(nl.complex_noise_sigma(raw, r.lumen.noise_mask))
        corrected.append(nl.complex_noise_sigma(raw, r.lumen.noise_mask, r.lumen.signal))
    sigma = _image_sigma(acq.grid, KSPACE, 25.0)
    assert np.mean(corrected) == pytest.approx(sigma, rel=0.1)
    assert np.mean(plain) > 1.1 * sigma


def test_kspace_stack_reconstructs_every_slice():
    """A z-regularized stack acquired in k-space: the k-space model reaches each slice's exact WSS within
    5 % at SNR 30 (h = 1 mm, Hamming), the box model does not (measured k-space 1-3 %, box > 30 %)."""
    psf = kspace.PSF("hamming", (1.0, 1.0))
    acq, truth = ph.make_stack("tapered", nz=3, h_mm=1.0, spacing_mm=2.0, snr=30.0, seed=11, psf=psf)
    for model, ok in (("kspace", True), ("box", False)):
        options = ReconstructionOptions(uncertainty=False, acquisition=kspace.AcquisitionOptions(model, "hamming"))
        results = rc.reconstruct(acq, options)
        errors = [abs(r.wss.mean - t.mean_wss) / t.mean_wss for r, t in zip(results, truth.slices)]
        assert (max(errors) < 0.05) == ok, (model, errors)


@pytest.mark.parametrize("vendor", ["siemens", "enhanced"])
def test_import_reads_the_acquired_resolution_from_dicom(tmp_path, vendor):
    """A k-space phantom written as DICOM (Acquisition Matrix, or the enhanced MR FOV/Geometry Sequence) imports
    with ``acquired_voxel_size_mm``, so ``--acquisition kspace`` finds the zero-filling without being told."""
    pytest.importorskip("pydicom")
    inp, folder, imported = tmp_path / "in.h5", tmp_path / "dcm", tmp_path / "imported.h5"
    argv = ["phantom", "--case", "circle", "--h", "1.5", "--snr", "30", "--acquisition", "kspace", "--zero-fill", "2"]
    assert cli.main([*argv, "-o", str(inp), "--dicom", str(folder), "--vendor", vendor]) == 0
    assert cli.main(["import", str(folder), "-o", str(imported)]) == 0
    acq = wio.read_acquisition(str(imported))
    assert acq.acquired_voxel_size_mm == pytest.approx((3.0, 3.0))
    with h5py.File(imported) as f:
        assert json.loads(f.attrs["import_json"])["acquired_matrix"] == [10, 10]


@pytest.mark.parametrize("kind", ["hamming", "tukey"])
def test_filter_auto_finds_the_scanner_filter_and_records_the_choice(kind):
    """``--kspace-filter auto`` picks the filter the phantom was acquired with from the magnitude misfit alone
    (seeds 40-41, not used to tune; Hamming and Tukey differ from the rest by wide margins, "none" and
    "fermi" from each other by little, which the record reports as ambiguous), records misfits and margin,
    and the result is then the one the right filter gives when named."""
    psf = kspace.PSF(kind, (2.0, 2.0))
    for seed in (40, 41):
        acq, _ = ph.make_phantom("laminar", h_mm=1.0, snr=25, seed=seed, psf=psf)
        how = kspace.AcquisitionOptions("kspace", "auto")
        r = rc.reconstruct(acq, ReconstructionOptions(uncertainty=False, acquisition=how))[0]
        record = r.geometry.options["acquisition"]
        assert record["kspace_filter"] == kind
        choice = record["filter_choice"]
        assert choice["chosen"] == kind and set(choice["misfits_mm"]) == set(kspace.FILTERS)
        assert choice["margin"] > 0.05 and not choice["ambiguous"]
        named = kspace.AcquisitionOptions("kspace", kind)
        same = rc.reconstruct(acq, ReconstructionOptions(uncertainty=False, acquisition=named))[0]
        assert r.wss.mean == pytest.approx(same.wss.mean, rel=1e-9)


def test_acquisition_auto_follows_the_file_and_the_box_model_on_zero_filled_data_is_suspect():
    """``--acquisition auto`` (the default) uses the k-space model when the file states its acquired
    resolution and the box model otherwise; the box model forced onto a zero-filled file flags the slice."""
    psf = kspace.PSF("hamming", (2.0, 2.0))
    acq, _ = ph.make_phantom("circle", h_mm=1.5, snr=30, seed=42, psf=psf)
    r = rc.reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    assert r.geometry.options["acquisition"]["model"] == "kspace"
    assert r.geometry.options["acquisition"]["zero_fill"] == [2.0, 2.0]
    boxed = rc.reconstruct(acq, ReconstructionOptions(uncertainty=False, acquisition=kspace.AcquisitionOptions("box")))[
        0
    ]
    assert boxed.screen["suspect"] and any("zero-filled" in n for n in boxed.notes)
    plain, _ = ph.make_phantom("circle", h_mm=1.5, snr=30, seed=42)
    r = rc.reconstruct(plain, ReconstructionOptions(uncertainty=False))[0]
    assert r.geometry.options["acquisition"] == {"model": "box"}


def test_noise_correlation_operator_and_effective_samples():
    """``NoiseCorrelation.apply`` is the Kronecker product ``R_y (x) R_x`` restricted to the voxels (dense check),
    and its effective sample fraction is 1 for white noise and about ``1 / F^2`` for zero-filling without a
    filter (``(sum w^2)^2 / (n sum w^4)`` per axis, by Parseval: 20^2 / (40 x 19.5) for N = 20 of n = 40 with
    the Nyquist line split), smaller with a Hamming filter."""
    index = np.array([3 * 36 + 4, 3 * 36 + 5, 4 * 36 + 4, 10 * 36 + 20, 11 * 36 + 22])
    rng = np.random.default_rng(8)
    x = rng.standard_normal((index.size, 3))
    psf = kspace.PSF("hamming", (2.0, 2.0))
    corr = kspace.NoiseCorrelation(GRID.shape, psf, index)
    ry, rx = (kspace.noise_correlation(n, 2.0, "hamming") for n in GRID.shape)
    iy, ix = np.divmod(index, 36)
    dense = ry[np.ix_(iy, iy)] * rx[np.ix_(ix, ix)]
    np.testing.assert_allclose(corr.apply(x), dense @ x, atol=1e-13)
    assert kspace.NoiseCorrelation(GRID.shape, kspace.PSF("none", (1.0, 1.0)), index).effective_fraction == (
        pytest.approx(1.0, abs=1e-12)
    )
    assert kspace.NoiseCorrelation((40, 40), kspace.PSF("none", (2.0, 2.0)), index).effective_fraction == (
        pytest.approx((20**2 / (40 * 19.5)) ** 2, rel=1e-12)
    )
    assert corr.effective_fraction < 0.2


def test_balancing_grams_with_correlated_noise_equal_per_beta_solves():
    """The noise Gram matrix of the balancing principle with correlated noise ``Sigma = D C D`` from the one
    generalized eigendecomposition, against per-beta Cholesky solves with the dense covariance (two
    independent computations; relative 1e-10 of the largest entry, both double-precision solves)."""
    from wss_nlp.core.tikhonov import LinearTikhonov

    psf = kspace.PSF("hamming", (2.0, 2.0))
    acq, _ = ph.make_phantom("circle", h_mm=1.5, snr=25, seed=43, psf=psf)
    coef = np.zeros(rad.n_coefficients(4))
    coef[0] = 10.0
    vp = vel.assemble(
        acq.grid, acq.velocity_images()[0], coef, (0.0, 0.0), vel.VelocityOptions(near_wall="off"), psf=psf
    )
    smat, _ = wss_mod.wss_matrix(vp.basis, vp.disk_map, 3.5e-3, 360)
    sigma = np.random.default_rng(9).uniform(0.005, 0.05, vp.data.size)
    betas = np.array([1e-4, 1e-7, 1e-10])
    _, noise, _ = LinearTikhonov(vp.operator, vp.weights, vp.data, vp.gram).balance_grams(
        betas, smat, sigma, vp.noise_correlation.apply
    )
    w = vp.weights / np.sum(vp.weights)
    tw = vp.operator * w[:, None]
    cov = sigma[:, None] * vp.noise_correlation.apply(np.diag(sigma))
    parts = [smat @ np.linalg.solve(tw.T @ vp.operator + b / np.pi * vp.gram, tw.T) for b in betas]
    want = np.array([[np.trace(a @ cov @ b.T) for b in parts] for a in parts])
    assert np.max(np.abs(noise - want)) <= 1e-10 * np.max(np.abs(want))


# ------------------------------------------------------------------ the coupled method with the k-space model
@pytest.fixture(scope="module")
def kspace_coupled():
    """A decoupled k-space reconstruction (Hamming, twofold zero-filling, h = 1.5, SNR 25, seed 13) and the
    coupled NLP built on it (velocity weight 1e4 mm^2/(m/s)^2, its alpha and beta)."""
    acq, _ = ph.make_phantom("laminar", h_mm=1.5, snr=25, seed=13, psf=KSPACE)
    options = ReconstructionOptions(uncertainty=False, acquisition=kspace.AcquisitionOptions("kspace", "hamming"))
    res = rc.reconstruct(acq, options)[0]
    lum, g, v = res.lumen, res.geometry, res.velocity
    problem = geo.GeometryProblem(res.grid, res.magnitude, lum.center, lum.r0, lum.r1, lum.r_area, psf=KSPACE)
    nlp = cpl.build(
        problem, geo.GeometryOptions(), res.velocity_image, vel.VelocityOptions(), v.basis, v.disk_map.r_in, 1e4,
        g.alpha, v.beta, start=g.coefficients,
    )  # fmt: skip
    return res, problem, nlp


def test_coupled_kspace_jacobian_equals_casadi_ad(kspace_coupled):
    """The hand-assembled chain rule through the separable PSF image (Averager.casadi) against CasADi's AD of
    the same residual at a perturbed point: two exact derivatives, equal to rounding."""
    res, _, nlp = kspace_coupled
    assert nlp.velocity_model.averager is not None
    assert_coupled_jacobian_is_exact(nlp, res.geometry, res.velocity)


def test_sharp_coupled_kspace_operator_is_the_decoupled_one(kspace_coupled):
    """With a (nearly) sharp indicator, no floor and R fixed, the coupled k-space voxel value t_i s_i / s_i^2 is
    the decoupled first-order phase operator (K chi v)/(K chi) on every voxel both keep (same sub-voxel points,
    same kernels): rounding-level agreement. The coupled set also keeps voxels just outside the lumen that
    the PSF gives signal (>= KSPACE_VOXEL_SIGNAL), which the decoupled fit leaves out, and leaves out voxels
    below that signal, which the decoupled fit keeps down to MIN_KSPACE_SIGNAL."""
    res, _, nlp = kspace_coupled
    g, v = res.geometry, res.velocity
    model = nlp.velocity_model
    vp = vel.assemble(
        res.grid, res.velocity_image, g.coefficients, g.center,
        vel.VelocityOptions(inner_radius=v.disk_map.r_in, quad_order=model.order), basis=v.basis, psf=KSPACE,
    )  # fmt: skip
    c = np.random.default_rng(1).normal(size=v.basis.size)
    c_r, c_v = ca.MX.sym("c_r", g.coefficients.size), ca.MX.sym("c_v", c.size)
    expr = cpl.velocity_residual(model, c_r, c_v, v.basis, v.disk_map.r_in, 1e-9, "erf", floor=1e-12)
    r = np.asarray(ca.Function("r", [c_r, c_v], [expr])(g.coefficients, c)).ravel()
    scale = np.sqrt(model.weights / model.weights.sum())
    kept = vp.weights > 0
    common, pos, pos_vp = np.intersect1d(model.index, vp.voxels.index[kept], return_indices=True)
    ok = scale[pos] > 1e-6  # voxels whose weight is ~0 do not determine T_i through r_i
    strong = vp.voxels.index[vp.weights >= cpl.KSPACE_VOXEL_SIGNAL * res.grid.voxel_area * (1 + 1e-9)]
    assert np.all(np.isin(strong, common)) and ok.mean() > 0.9
    t_coupled = r[pos][ok] / scale[pos][ok] + model.data[pos][ok]
    expected = (vp.operator[kept] @ c)[pos_vp][ok]
    assert np.allclose(t_coupled, expected, rtol=0, atol=1e-9 * np.max(np.abs(expected)))
    assert model.index.size > common.size  # the outside voxels the PSF reaches


def test_noise_free_coupled_kspace_gets_laminar_wss_within_one_percent():
    """Noise-free k-space data (Hamming, twofold zero-filling, seed 5 as the decoupled test): the coupled
    method with the k-space model reaches the exact mean WSS within 1 % (measured 0.28 %) and the radius
    as well as the decoupled k-space fit does (both 0.20 % L2: the fixed alpha's bias); the coupled box
    model on the same data misses by more than 3x (measured 26 %). Noise-free data give no likelihood
    weight (no noise): the weight is given, and beta fixed small as for every noise-free recovery."""
    acq, truth = ph.make_phantom("laminar", h_mm=1.0, snr=None, seed=5, psf=KSPACE)
    errors = {}
    for method, model in (("coupled", "kspace"), ("decoupled", "kspace"), ("coupled", "box")):
        options = ReconstructionOptions(
            method=method,
            uncertainty=False,
            velocity=vel.VelocityOptions(beta=1e-9),
            coupled=cpl.CoupledOptions(velocity_weight=1e4),
            acquisition=kspace.AcquisitionOptions(model, "hamming"),
            choice=ChoiceOptions(beta_rule="fixed"),
        )
        r = rc.reconstruct(acq, options)[0]
        assert r.converged and r.method == method
        errors[method, model] = metrics.compare_slice(r, truth)
    mine = errors["coupled", "kspace"]
    assert abs(mine.mean_wss_rel) < 0.01
    assert mine.radius_rel_l2 <= 1.05 * errors["decoupled", "kspace"].radius_rel_l2
    assert abs(errors["coupled", "box"].mean_wss_rel) > 3 * abs(mine.mean_wss_rel)


def test_coupled_kspace_converges_on_unfiltered_low_snr_slices():
    """Unfiltered k-space data (the sinc PSF rings most), SNR 10, h = 1 mm: the coupled solve converges and
    stays within 5 % of the exact mean WSS (measured 0.1-3.0 % on seeds 105-112). With the voxel set down to
    2 % or 5 % modeled signal IPOPT failed or stalled on 2 of 10 such slices (seeds 100-104, which chose
    KSPACE_VOXEL_SIGNAL = 0.1); seeds 105-108 here were not used for that."""
    for seed in range(105, 109):
        acq, truth = ph.make_phantom("laminar", h_mm=1.0, snr=10, seed=seed, psf=kspace.PSF("none", (1.0, 1.0)))
        options = ReconstructionOptions(
            method="coupled", uncertainty=False, acquisition=kspace.AcquisitionOptions("kspace", "none")
        )
        r = rc.reconstruct(acq, options)[0]
        assert r.converged, seed
        assert abs(r.wss.mean - truth.mean_wss) / truth.mean_wss < 0.05, seed


def test_coupled_kspace_sensitivities_match_resolves(kspace_coupled):
    """The coupled KKT sensitivities with the k-space model (its exact second derivatives through the PSF,
    the k-space centre derivative) against central differences of coupled re-solves: alpha, beta, the
    centre and a random velocity direction, to 1e-4 relative as for the box model (tests/test_sensitivity.py)."""
    res, problem, _ = kspace_coupled
    options = ReconstructionOptions(uncertainty=False, acquisition=kspace.AcquisitionOptions("kspace", "hamming"))
    start_g, start_v = res.geometry, res.velocity
    mu = 4e-3

    def solve(u=None, center=None, **scalars):
        lum = res.lumen
        pr = (
            problem
            if center is None
            else geo.GeometryProblem(res.grid, res.magnitude, center, lum.r0, lum.r1, lum.r_area, psf=KSPACE)
        )
        c = cpl.solve(
            pr, options.geometry, res.velocity_image if u is None else u, options.velocity, start_g, start_v, 1e4,
            **scalars,
        )  # fmt: skip
        return sens.coupled(c, pr, options.geometry, options.velocity, mu)

    s = solve()
    assert s.correlation is not None  # the band sees the k-space noise correlation
    assert s.noise["kkt_residual_after_polish"] < 1e-8
    mean = lambda **kw: solve(**kw).noise["mean_reference"]  # noqa: E731
    for name, x0 in (("alpha", start_g.alpha), ("beta", start_v.beta)):
        fd = (mean(**{name: x0 * (1 + 1e-3)}) - mean(**{name: x0 * (1 - 1e-3)})) / (2e-3 * x0)
        assert s.d_mean[sens.SCALARS.index(name)] == pytest.approx(fd, rel=1e-4), name
    c0 = np.asarray(res.lumen.center, float)
    for j, name in enumerate(("center_x", "center_y")):
        fd = _central(lambda t: mean(center=tuple(c0 + t * np.eye(2)[j])), 1e-4)
        assert s.d_mean[sens.SCALARS.index(name)] == pytest.approx(fd, rel=1e-4), name
    u0 = res.velocity_image
    du = np.zeros(u0.size)
    du[s.u_index] = 0.01 * np.random.default_rng(5).normal(size=s.u_index.size)
    fd_u = _central(lambda t: mean(u=u0 + t * du.reshape(u0.shape)), 1e-4)
    assert s.d_mean_d_u @ du[s.u_index] == pytest.approx(fd_u, rel=1e-4)


def test_cli_coupled_with_the_kspace_model(tmp_path):
    """`reconstruct --method coupled` on a file that states its acquired resolution: the k-space model is
    taken (auto), the result records it, and the band is there."""
    inp, out = tmp_path / "in.h5", tmp_path / "out.h5"
    argv = ["phantom", "--case", "laminar", "--h", "1.5", "--acquisition", "kspace", "--kspace-filter", "hamming",
            "--zero-fill", "2", "--snr", "25", "--seed", "19", "-o", str(inp)]  # fmt: skip
    assert cli.main(argv) == 0
    assert cli.main(["reconstruct", str(inp), "-o", str(out), "--method", "coupled", "--kspace-filter", "hamming"]) == 0
    with h5py.File(out) as f:
        recorded = json.loads(f["slice_000/geometry"].attrs["options_json"])["acquisition"]
        assert recorded["model"] == "kspace" and recorded["zero_fill"] == [2.0, 2.0]
        assert np.all(np.isfinite(f["slice_000/wss/tau_std_pa"][()]))


def test_dephasing_passes_stop_when_the_next_one_would_not_move_the_wall(monkeypatch):
    """A k-space slice ends its dephasing passes when the next pass is predicted (geometry.predicted_change) to
    move the wall less than KSPACE_PASS_TOL voxels; it records that prediction. Running that pass anyway
    (KSPACE_PASS_PREDICTION off: the iteration then stops after a pass that moved the wall less than the
    tolerance) moves the wall by less than the tolerance and the mean WSS by less than 0.1 % (the whole WSS
    curve moved by at most 0.18 % of its peak on 144 development slices, scripts/kspace_passes.py).
    Laminar flow, Hamming PSF, h = 0.6 mm, seed 17 (not used to tune)."""
    psf = kspace.PSF("hamming", (1.0, 1.0))
    acq, _ = ph.make_phantom("laminar", h_mm=0.6, snr=25, seed=17, psf=psf)
    options = ReconstructionOptions(uncertainty=False, acquisition=kspace.AcquisitionOptions("kspace", "hamming"))
    short = rc.reconstruct(acq, options)[0]
    assert short.dephasing.passes >= 1
    assert short.dephasing.next_move < rc.KSPACE_PASS_TOL
    monkeypatch.setattr(rc, "KSPACE_PASS_PREDICTION", False)
    full = rc.reconstruct(acq, options)[0]
    assert full.dephasing.passes == short.dephasing.passes + 1
    phi = rad.uniform_angles(72)
    moved = np.max(np.abs(full.geometry.radius(phi) - short.geometry.radius(phi)))
    assert moved < rc.KSPACE_PASS_TOL * acq.grid.h
    # the prediction itself: within 5 % of the move it predicted (measured 1e-4)
    assert moved / acq.grid.h == pytest.approx(short.dephasing.next_move, rel=0.05)
    assert abs(full.wss.mean - short.wss.mean) < 1e-3 * abs(full.wss.mean)


def test_analyze_reports_the_dephasing_passes(tmp_path, capsys):
    """``wss-nlp analyze`` states each slice's dephasing passes, the smallest predicted magnitude factor and,
    for a k-space slice that ran a pass, the predicted move of a further pass against the tolerance; the
    numbers are the slice's own (read back from the result file)."""
    inp, out = tmp_path / "in.h5", tmp_path / "out.h5"
    kspace_args = ["--acquisition", "kspace", "--kspace-filter", "hamming"]
    assert cli.main(["phantom", "--case", "laminar", "--h", "1.0", "--snr", "25", "-o", str(inp), *kspace_args]) == 0
    assert cli.main(["reconstruct", str(inp), "-o", str(out), "--no-uncertainty", *kspace_args]) == 0
    rec = wio.read_dephasing(str(out))["slice_000"]
    assert rec["passes"] >= 1 and rec["min_factor"] < 0.99 and rec["next_move"] is not None
    capsys.readouterr()
    assert cli.main(["analyze", str(out)]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "dephasing:" in ln)
    assert f"{rec['passes']} pass(es)" in line and f"{rec['min_factor']:.4g}" in line
    assert f"{rec['next_move']:.2g} voxel" in line and f"below {rc.KSPACE_PASS_TOL:g}" in line
    # the record is its own attribute, not part of the timings; a file written before it existed (the record
    # inside seconds_json under the old keys) reads back the same
    with h5py.File(out, "r+") as f:
        attrs = f["slice_000"].attrs
        record, seconds = json.loads(attrs["dephasing_json"]), json.loads(attrs["seconds_json"])
        assert "min_factor" in record
        assert not {"dephasing_passes", "min_dephasing_factor", "dephasing_next_move", "dephasing_beta"} & set(seconds)
        old = {"dephasing_passes": "passes", "min_dephasing_factor": "min_factor", "dephasing_next_move": "next_move"}
        seconds.update({key: record[new] for key, new in old.items()})
        attrs["seconds_json"] = json.dumps(seconds)
        del attrs["dephasing_json"]
    assert wio.read_dephasing(str(out))["slice_000"] == rec
