"""The momentum model of a cine slice (wss_nlp.models.womersley): its pieces against closed forms, recovery of exact
Womersley flow, the BIC choice on flows it does and does not describe, forced choices and the result file.

Seeds 60-69 (the report, scripts/cine.py, uses 0-4; nothing was tuned on these)."""

import json
from dataclasses import replace

import h5py
import numpy as np
import pytest
import scipy.linalg
import scipy.special

from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.pipeline import cine
from wss_nlp.synthetic import pulsatile
from wss_nlp.models import womersley
from wss_nlp.parameters import cycle
from wss_nlp.core import radius as rad
from wss_nlp.pipeline import ReconstructionOptions


def _options(model="auto", **kw):
    return ReconstructionOptions(uncertainty=False, cine=womersley.CineModelOptions(model=model), **kw)


def _errors(series, truth):
    """Worst frame error of the mean WSS / peak, TAWSS relative error, OSI error (wall means)."""
    tt = truth.tau()
    ta, osi = cine.tawss_osi(tt[:, None], cine.cycle_weights(truth.times_ms, truth.period_ms))
    worst = np.nanmax(np.abs(series.mean - tt)) / np.max(np.abs(tt))
    return worst, abs(np.mean(series.tawss) / ta[0] - 1), abs(np.mean(series.osi) - osi[0])


def test_shape_solves_the_harmonic_momentum_balance_and_vanishes_on_the_wall():
    """Delta S = Lambda^2 (1 - S) on the unit disk (the radial Bessel ODE), S(1) = 0 and S'(1) the closed form;
    derivatives by central differences of step 1e-4 (truncation d^2 |Lambda|^2 / 12, about 1e-6 relative at
    |Lambda| = 28)."""
    lam = womersley.womersley_parameter(3, 10.0, 2 * np.pi, 3.5e-3 / 1060)
    assert 20 < abs(lam) < 40
    s, d = np.array([0.2, 0.6, 0.95]), 1e-4

    def f(x):
        return womersley.shape(x, lam)

    lap = (f(s + d) - 2 * f(s) + f(s - d)) / d**2 + (f(s + d) - f(s - d)) / (2 * d) / s
    assert np.allclose(lap, lam**2 * (1 - f(s)), rtol=1e-5)
    assert abs(f(np.array([1.0]))[0]) < 1e-12
    slope = (f(np.array([1.0 + d])) - f(np.array([1.0 - d])))[0] / (2 * d)  # the formula continues past 1
    assert womersley.wall_slope(lam) == pytest.approx(slope, rel=1e-5)
    assert womersley.shape(np.array([0.5]), 0)[0] == 0.75 and womersley.wall_slope(0) == -2.0


def test_tabulated_columns_match_direct_bessel_evaluation():
    """The spline table (womersley.TABLE_POINTS) against scipy's Bessel functions at 20 000 random points, nine
    harmonics at Womersley number 15: within 1e-8 of the columns' scale."""
    omega, nu = 2 * np.pi, 3.5e-3 / 1060
    lams = womersley.lambdas(9, 10.0, omega, nu)
    phase = womersley.time_factors(9, omega, 0.37)
    sigma = np.random.default_rng(60).uniform(0, 1, 20000)
    got = womersley.columns_at(sigma, lams, phase)
    direct = [1 - sigma**2]
    for lam, e in zip(lams, phase):
        v = (1 - scipy.special.jv(0, lam * sigma) / scipy.special.jv(0, lam)) * e
        direct += [v.real, -v.imag]
    assert np.max(np.abs(got - np.array(direct).T)) <= 1e-8 * np.max(np.abs(direct))


def test_normal_gradient_of_the_ray_coordinate_is_exact():
    """n . grad sigma = sqrt(R^2 + R'^2) / R^2 at the wall (1/R on a circle), from CasADi's derivatives."""
    phi = rad.uniform_angles(13)
    coef = np.zeros(rad.n_coefficients(4))
    coef[0], coef[2], coef[4 + 3] = 10.0, 0.8, 0.5
    fun = womersley.normal_gradient_function(4).map(phi.size)
    got = np.asarray(fun(phi[None, :], coef)).ravel()
    big_r, d_r = rad.evaluate(coef, phi), rad.evaluate(coef, phi, 1)
    assert np.allclose(got, np.hypot(big_r, d_r) / big_r**2, rtol=1e-12)
    circle = np.r_[7.0, np.zeros(8)]
    assert np.allclose(np.asarray(fun(phi[None, :], circle)).ravel(), 1 / 7.0, rtol=1e-12)


def test_noise_free_womersley_flow_is_recovered():
    """Noise-free frames with a given noise level (the BIC needs one): the model's mean WSS within 0.5 % of the
    peak at every frame at h = 1.5 mm (measured 0.22 %: the frames' radii are 0.05 % off and the wall voxels'
    sub-voxel rule integrates the Stokes layer) and the four harmonics the phantom has are found."""
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=None, seed=60, frames=12)
    options = _options("momentum", choice=ChoiceOptions(noise_velocity=0.01))
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, options)
    s = res.series(0)
    assert s.model.model == "momentum" and s.model.harmonics == 4
    worst, tawss, osi = _errors(s, truth)
    assert worst < 5e-3 and tawss < 5e-3 and osi < 2e-3


@pytest.mark.parametrize("seed", [61, 62])
def test_the_bic_takes_the_momentum_model_for_womersley_flow(seed):
    """h = 1.5 mm, SNR 25, 12 frames: chosen by the BIC with a wide margin, every frame within 3 % of the peak
    (scripts/results/cine.md: about 1 %; independent frames 28-32 %), TAWSS within 2 %, OSI within 0.01;
    the band (velocity noise) covers the errors: at most 3 of 12 frames outside 2.5 standard deviations."""
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=seed, frames=12)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options())
    s = res.series(0)
    assert s.model.model == "momentum" and s.model.margin > 100
    assert s.model.walls["degree"] == 0 and np.ptp(s.coefficients[:, 0]) == 0  # rigid: one shared wall
    # 4 harmonics of the 6 that 12 frames carry: the waveform is resolved, not flagged (tests/test_cine_sampling.py)
    assert s.model.sampling["harmonics"] < s.model.sampling["carried"] and not s.model.sampling["flagged"]
    worst, tawss, osi = _errors(s, truth)
    own = np.max(np.abs(np.array([f[0].wss.mean for f in res.frames]) - truth.tau())) / np.max(np.abs(truth.tau()))
    assert worst < 0.03 < own and tawss < 0.02 and osi < 0.01
    outside = np.abs(s.mean - truth.tau()) > 2.5 * s.mean_std
    assert np.sum(outside) <= 3 and np.all(s.mean_std > 0)


@pytest.mark.parametrize("radius, h", [(3.0, 0.6), (14.0, 1.5)])
def test_small_and_large_womersley_numbers_meet_the_goals(radius, h):
    """Pipes of radius 3 and 14 mm (first harmonic's Womersley number 4.1 and 19.3: the issue's range 3-20),
    SNR 25, 8 frames, seed 65: the BIC takes the momentum model and every frame is within the issue's 8 % of
    the peak, TAWSS within 5 % (measured 1.9 % / 0.5 % and 1.0 % / 1.7 %; report: scripts/results/cine_alpha.md)."""
    frames, truth = pulsatile.make_cine(h_mm=h, snr=25, seed=65, frames=8, radius_mm=radius)
    assert 3 < truth.flow.womersley(1) < 20
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options())
    s = res.series(0)
    worst, tawss, osi = _errors(s, truth)
    assert s.model.model == "momentum" and worst < 0.08 and tawss < 0.05 and osi < 0.03


def test_a_distending_pipe_is_followed_frame_by_frame():
    """10 % distension (pulsatile.DistendingWomersley), h = 1.5 mm, SNR 25, 12 frames: every frame's radius
    within 1 % of R(t) (the shared lumen box covers the whole cycle) and the momentum model, with the cycle's
    reference radius in Lambda_n, within 3 % of the peak at every frame (measured 0.6 % on a report seed; the
    phantom's field is the rigid profile stretched to R(t), which the model describes along the rays)."""
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=65, frames=12, distension=0.1)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options())
    radius = np.array([f[0].geometry.coefficients[0] for f in res.frames])
    assert np.allclose(radius, 10.0 * truth.flow.stretch(truth.times_ms / 1000.0), rtol=0.01)
    s = res.series(0)
    worst, tawss, _ = _errors(s, truth)
    assert s.model.model == "momentum" and worst < 0.03 and tawss < 0.02
    # the walls regularized in time follow the breathing (degree >= 1) and are the series' geometry
    assert s.model.walls["degree"] >= 1
    assert np.allclose(s.coefficients[:, 0], 10.0 * truth.flow.stretch(truth.times_ms / 1000.0), rtol=0.01)


# CI budget: the manufactured flow (32 s) runs with -m slow; laminar and turbulent stay in CI
@pytest.mark.parametrize("case", ["laminar", pytest.param("manufactured", marks=pytest.mark.slow), "turbulent"])
def test_flows_that_do_not_obey_the_momentum_balance_keep_their_own_fits(case):
    """Steady profiles scaled by the waveform (pulsatile.make_quasi_steady_cine): not Womersley flow, so the BIC
    refuses the momentum model by far (> 100 units beyond the better plain candidate); with the frames' own
    fits the series is exactly those fits, with the temporal prior its notes say so."""
    frames, truth = pulsatile.make_quasi_steady_cine(case, h_mm=1.5, snr=25, seed=63, frames=8)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options())
    s = res.series(0)
    momentum = min(v for k, v in s.model.bic.items() if k.startswith("momentum"))
    plain = min(s.model.bic["independent"], s.model.bic.get("temporal", np.inf))
    assert s.model.model in ("independent", "temporal") and momentum - plain > 100
    if s.model.model == "independent":
        assert np.array_equal(s.mean, [f[0].wss.mean for f in res.frames])
        assert "did not fit" in " ".join(s.notes)
    else:
        assert "temporal prior" in " ".join(s.notes)


def test_forced_models_and_the_result_file(tmp_path):
    """--cine-model independent computes no model; momentum is used even where the BIC would refuse it and
    says so; the result file carries the band and the choice (cine_model_json)."""
    frames, truth = pulsatile.make_quasi_steady_cine("circle", h_mm=1.5, snr=25, seed=64, frames=6)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options("independent"))
    assert res.series(0).model.model == "independent" and not res.series(0).model.bic
    forced = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options("momentum"))
    s = forced.series(0)
    assert s.model.model == "momentum" and s.model.bic["independent"] < min(
        v for k, v in s.model.bic.items() if k != "independent"
    )
    path = str(tmp_path / "r.h5")
    cine.write_result(path, forced, {})
    with h5py.File(path) as f:
        g = f["slice_000"]
        record = json.loads(g.attrs["cine_model_json"])
        assert record["model"] == "momentum" and record["criterion"].endswith("forced")
        assert g["wss/tau_std_pa"].shape == g["wss/tau_pa"].shape and g["wss/mean_std_pa_t"].shape == (6,)
        assert np.allclose(g["wss/mean_pa_t"][()], s.mean)


def test_frames_bands_are_computed_only_for_the_model_the_series_keeps():
    """Default options (band on): where the momentum model wins, the frames' own bands are skipped (its band
    replaces them, and each frame says so); where the frames' own fits are kept, each frame has its band."""
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=66, frames=8)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, ReconstructionOptions())
    s = res.series(0)
    assert s.model.model == "momentum" and np.all(np.isfinite(s.tau_std))
    note = cine.MODEL_BAND_NOTE.format(model=cine.MODEL_NAMES["momentum"])
    for f in res.frames:
        assert f[0].pending_band is None and f[0].wss.tau_std is None and note in f[0].notes
    frames, truth = pulsatile.make_quasi_steady_cine("circle", h_mm=1.5, snr=25, seed=66, frames=6)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, ReconstructionOptions())
    assert res.series(0).model.model == "independent"
    for f in res.frames:
        assert f[0].pending_band is None and f[0].wss.tau_std is not None and f[0].sensitivity is not None


def test_wall_smoothing_in_time_finds_a_rigid_and_a_moving_wall():
    """Synthetic frames' walls (radius coefficients and centre, mm) with noise of 0.02 mm (seed 67): a rigid
    wall gets degree 0 (the frames' mean), a wall breathing by 0.5 mm degree 1 with the motion recovered within
    the noise's effect on a fit of 3 parameters from 20 frames (0.02 sqrt(3/20), 4x margin: 0.03 mm)."""
    rng = np.random.default_rng(67)
    omega, t = 2 * np.pi, np.arange(20) / 20
    truth = np.tile(np.r_[10.0, 0.3, -0.2, 0.1, 0.05, 0.4, -0.1], (20, 1))
    rigid = truth + 0.02 * rng.standard_normal(truth.shape)
    walls, choice = cycle.smooth_walls(t, omega, rigid, "auto", 9)
    assert choice.degree == 0 and np.allclose(walls, rigid.mean(axis=0))
    moving = truth.copy()
    moving[:, 0] += 0.5 * np.sin(omega * t)
    noisy = moving + 0.02 * rng.standard_normal(truth.shape)
    walls, choice = cycle.smooth_walls(t, omega, noisy, "auto", 9)
    assert choice.degree == 1 and np.max(np.abs(walls - moving)) < 0.03
    assert np.array_equal(cycle.smooth_walls(t, omega, noisy, "frames", 9)[0], noisy)
    assert np.allclose(cycle.smooth_walls(t, omega, noisy, "shared", 9)[0], noisy.mean(axis=0))


def test_kspace_acquired_cine_gets_the_momentum_model_through_the_psf():
    """Frames acquired with a Hamming filter and twofold zero-filling (seed 68, h = 1.5 mm, 8 frames): the
    model's columns go through the PSF as the frames' own operator does (velocity.voxel_values), so the
    momentum model is chosen, every frame lands within 3 % of the peak (measured 1.4 %; at h = 1 mm 1.1 %
    where the frames' own fits miss by about 45 %) and the TAWSS within the issue's 5 % (measured 2.3 %: 3 mm
    acquired voxels)."""
    from wss_nlp.models import kspace

    psf = kspace.PSF("hamming", (2.0, 2.0))
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=68, frames=8, psf=psf)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options())
    s = res.series(0)
    assert s.model.model == "momentum"
    worst, tawss, _ = _errors(s, truth)
    assert worst < 0.03 and tawss < 0.05


@pytest.mark.slow  # CI budget: 42 s; the elliptic momentum-balance test of test_cine stays in CI
def test_elliptic_pipe_the_circle_profile_along_rays_stays_within_the_goals():
    """An elliptic pipe (aspect 1.32) with its exact pulsatile flow (pulsatile.EllipticWomersley), h = 1.5 mm,
    SNR 25, 8 frames (seed 69): the model's circle profile along each ray is an approximation here, yet the
    BIC takes it and every frame stays within the issue's 8 % of the peak and TAWSS within 5 % (report:
    scripts/results/cine_ellipse.md, about 2 % and 3 %)."""
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=69, frames=8, shape="ellipse")
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options())
    s = res.series(0)
    worst, tawss, osi = _errors(s, truth)
    assert s.model.model == "momentum" and worst < 0.08 and tawss < 0.05 and osi < 0.03


def _prior_problems(n: int, seed: int):
    """n frames of the circle phantom's voxel data on one wall, scaled in time plus noise (sigma 0.01 m/s)."""
    from wss_nlp.synthetic import phantoms
    from wss_nlp.models import velocity as vel
    from wss_nlp.pipeline import reconstruct

    acq, _ = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=seed)
    r = reconstruct(acq, _options())[0]
    problem = vel.assemble(r.grid, r.velocity_image, r.geometry.coefficients, r.geometry.center,
                           ReconstructionOptions().velocity.__class__(near_wall="off"))  # fmt: skip
    rng = np.random.default_rng(seed)
    scale = 1 + 0.3 * np.sin(np.arange(n) * 2 * np.pi / n)
    return [replace(problem, data=problem.data * a + 0.01 * rng.standard_normal(problem.data.size)) for a in scale]


def test_temporal_prior_block_cholesky_equals_a_solve_per_temporal_frequency():
    """wss_nlp.models.temporal on one wall with one beta for every frame: the block system's Cholesky solve equals an
    independent solver, a discrete Fourier transform over the frames and one system per frequency
    (K + beta/pi G + gamma/pi lambda_j G0, lambda_j = (2 - 2 cos(2 pi j / n))^2): to 1e-9 relative, two
    factorizations of well-conditioned (cond < 1e7) systems of one linear problem."""
    from wss_nlp.models import temporal

    problems = _prior_problems(6, 69)
    beta, gamma, n = 1e-6, 10.0, len(problems)
    p = problems[0]
    t, w = p.operator, p.weights / p.area
    k = t.T @ (w[:, None] * t)
    rhs_hat = np.fft.fft(np.array([(w * q.data) @ t for q in problems]), axis=0)
    lam = (2 - 2 * np.cos(2 * np.pi * np.arange(n) / n)) ** 2
    g, g0 = p.gram / np.pi, p.basis.laplacian_gram(0) / np.pi
    v_hat = np.array([np.linalg.solve(k + beta * g + gamma * lam[j] * g0, rhs_hat[j]) for j in range(n)])
    per_frequency = np.fft.ifft(v_hat, axis=0).real
    got = temporal.solve(problems, [beta] * n, gamma)
    assert np.max(np.abs(got - per_frequency)) <= 1e-9 * np.max(np.abs(per_frequency))


def test_temporal_prior_criterion_trace_and_band_against_dense_formulas():
    """models.temporal.fit with per-frame betas: the chosen gamma is the smallest criterion it evaluated or
    bounded; at that gamma the coefficients, the smoother's trace tr(H^-1 blockdiag K_k) (from a triangular
    inverse) and each frame's covariance block (H^-1 blockdiag(T^T W S W T) H^-1) equal dense numpy formulas
    to 1e-8 relative; gamma -> 0 gives each frame's own Tikhonov solution back (1e-6: gamma 1e-9 perturbs it
    by about that)."""
    from wss_nlp.models import temporal

    problems = _prior_problems(5, 68)
    n, m = len(problems), problems[0].operator.shape[1]
    betas = 10.0 ** np.array([-8.0, -6.0, -7.0, -5.0, -6.5])
    sigmas = [np.full(q.data.size, 0.01) for q in problems]
    best = temporal.fit(problems, betas, sigmas, 1.0, float(np.log(sum(q.data.size for q in problems))))
    assert best.bic == min(best.curve.values()) and best.curve[best.gamma] == best.bic
    # a bracket and its refinement, not one point (values a lower bound decided are in bounds, all above the best)
    assert len(best.curve) + len(best.bounds) >= 4 and min(best.bounds.values(), default=np.inf) > best.bic
    tw = [q.operator * (q.weights / q.area)[:, None] for q in problems]
    kk = [a.T @ q.operator for a, q in zip(tw, problems)]
    d2 = temporal.second_difference(n)
    big = scipy.linalg.block_diag(*[k + b / np.pi * q.gram for k, b, q in zip(kk, betas, problems)])
    big = big + best.gamma * np.kron(d2.T @ d2, problems[0].basis.laplacian_gram(0) / np.pi)
    inv = np.linalg.inv(big)
    rhs = np.concatenate([a.T @ q.data for a, q in zip(tw, problems)])
    coef = (inv @ rhs).reshape(n, m)
    assert np.max(np.abs(best.coefficients - coef)) <= 1e-8 * np.max(np.abs(coef))
    dof = float(np.trace(inv @ scipy.linalg.block_diag(*kk)))
    assert best.dof == pytest.approx(dof, rel=1e-8)
    middle = scipy.linalg.block_diag(*[a.T @ (s[:, None] ** 2 * a) for a, s in zip(tw, sigmas)])
    cov = inv @ middle @ inv
    for k in range(n):
        block = cov[k * m : (k + 1) * m, k * m : (k + 1) * m]
        assert np.max(np.abs(best.covariance[k] - block)) <= 1e-8 * np.max(np.abs(block))
    loose = temporal.solve(problems, betas, 1e-9)
    for q, b, v in zip(problems, betas, loose):
        own = q.tikhonov.solve(b)
        assert np.max(np.abs(v - own)) <= 1e-6 * np.max(np.abs(own))


def test_temporal_prior_bounds_decide_without_changing_the_fit(monkeypatch):
    """models.temporal.fit skips the trace where a lower bound of the criterion decides (_TraceFloor): the same
    best gamma, criterion and coefficients, bit for bit, as the search computing every trace (the margin made
    infinite, so no bound decides); every recorded bound at most the criterion computed there; and the trace
    bounds themselves below the traces (per-frame and gamma -> infinity bounds, four gammas): proven inequalities,
    checked to a rounding slack of 1e-9 relative."""
    from wss_nlp.models import temporal

    problems = _prior_problems(6, 67)
    betas = 10.0 ** np.array([-8.0, -6.0, -7.0, -5.0, -6.5, -7.5])
    sigmas = [np.full(q.data.size, 0.01) for q in problems]
    args = (problems, betas, sigmas, 1.0, float(np.log(sum(q.data.size for q in problems))))
    fast = temporal.fit(*args)
    monkeypatch.setattr(temporal, "_FLOOR_MARGIN", np.inf)
    full = temporal.fit(*args)
    assert fast.gamma == full.gamma and fast.bic == full.bic and fast.dof == full.dof
    assert np.array_equal(fast.coefficients, full.coefficients)
    assert not full.bounds and set(fast.curve) | set(fast.bounds) == set(full.curve)
    for gamma, bound in fast.bounds.items():
        assert bound <= full.curve[gamma] * (1 + 1e-9)
    system = temporal._System(problems, betas)
    floor = temporal._TraceFloor(system)
    for gamma in (1e-4, 1e-2, 1.0, 1e2):
        z = temporal._BandedFactor(system, gamma).inverse_diagonal()
        dof = sum(float(np.sum(a * k)) for a, k in zip(z, system.normal))
        assert floor.limit <= floor(gamma) <= dof * (1 + 1e-9)


def test_forced_temporal_prior_on_a_steady_profile_scaled_in_time():
    """--cine-model temporal on the quasi-steady circle (h = 1.5 mm, SNR 25, 8 frames, seed 69): one shared
    wall, the prior's WSS within 5 % of the peak at every frame (the frames' own fits: about 2 %), and a band
    (the velocity noise's) on every frame."""
    frames, truth = pulsatile.make_quasi_steady_cine("circle", h_mm=1.5, snr=25, seed=69, frames=8)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options("temporal"))
    s = res.series(0)
    assert s.model.model == "temporal" and s.model.walls["degree"] == 0 and "temporal_prior" in s.model.walls
    worst, tawss, _ = _errors(s, truth)
    assert worst < 0.05 and tawss < 0.05
    assert np.all(np.isfinite(s.tau_std)) and np.all(s.mean_std > 0)


def test_forced_temporal_prior_follows_a_distending_wall():
    """--cine-model temporal on the distending pipe (10 %, h = 1.5 mm, SNR 25, 8 frames, seed 67): the prior
    ties the frames on their own (smoothed, moving) walls, so its worst frame is no worse than 1.2 x the
    independent frames' (a first version forced one shared wall and missed by 130-170 % of the peak)."""
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=67, frames=8, distension=0.1)
    prior = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options("temporal")).series(0)
    own = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options("independent")).series(0)
    assert prior.model.model == "temporal" and prior.model.walls["degree"] >= 1
    assert _errors(prior, truth)[0] <= 1.2 * _errors(own, truth)[0]


def test_auto_takes_the_temporal_prior_only_with_the_evidence():
    """cycle.choose on frames whose criteria are set by hand (momentum chi^2 = u^T S^-1 u = 3000 for every
    harmonic count, the frames' own fits 1000 + ln N 40): the prior is taken exactly when its criterion beats
    the frames' own fits by cycle.EVIDENCE, and a momentum model that beats both wins over it."""

    def terms(usu):
        return [womersley.FrameTerms(k, k / 4, np.array([5.0, 0, 0]), (0.0, 0.0), np.eye(3), np.zeros(3), usu, 100,
                                     np.array([250.0]), np.array([10.0]), 1.0, 5.0) for k in range(4)]  # fmt: skip

    opts, omega, nu = womersley.CineModelOptions(), 2 * np.pi, 3.3e-6
    frames = terms(750.0)
    log_n = cycle.criterion_scale(frames)[1]
    independent = 4 * (250.0 + 10.0 * log_n)
    choose = cycle.choose
    assert choose(frames, omega, nu, opts, None)[0].model == "independent"  # momentum: 3000 + ln N > independent
    assert choose(frames, omega, nu, opts, independent - 1.5 * cycle.EVIDENCE)[0].model == "temporal"
    assert choose(frames, omega, nu, opts, independent - 0.5 * cycle.EVIDENCE)[0].model == "independent"
    good = terms(1.0)  # the momentum model explains the data: chi^2 = 4
    assert choose(good, omega, nu, opts, independent - 1.5 * cycle.EVIDENCE)[0].model == "momentum"
