"""The momentum model of a cine slice (wss_nlp.womersley): its pieces against closed forms, recovery of exact
Womersley flow, the BIC choice on flows it does and does not describe, forced choices and the result file.

Seeds 60-69 (the report, scripts/cine.py, uses 0-4; nothing was tuned on these)."""

import json

import h5py
import numpy as np
import pytest
import scipy.special

from wss_nlp import cine, pulsatile, womersley
from wss_nlp import radius as rad
from wss_nlp.reconstruct import ReconstructionOptions


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
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options("momentum", noise_velocity=0.01))
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
    worst, tawss, osi = _errors(s, truth)
    own = np.max(np.abs(np.array([f[0].wss.mean for f in res.frames]) - truth.tau())) / np.max(np.abs(truth.tau()))
    assert worst < 0.03 < own and tawss < 0.02 and osi < 0.01
    outside = np.abs(s.mean - truth.tau()) > 2.5 * s.mean_std
    assert np.sum(outside) <= 3 and np.all(s.mean_std > 0)


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


@pytest.mark.parametrize("case", ["laminar", "manufactured", "turbulent"])
def test_flows_that_do_not_obey_the_momentum_balance_keep_their_own_fits(case):
    """Steady profiles scaled by the waveform (pulsatile.make_quasi_steady_cine): not Womersley flow, so the BIC
    keeps each frame's own fit, and the series is exactly those fits."""
    frames, truth = pulsatile.make_quasi_steady_cine(case, h_mm=1.5, snr=25, seed=63, frames=8)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options())
    s = res.series(0)
    assert s.model.model == "independent" and s.model.margin > 100
    assert np.array_equal(s.mean, [f[0].wss.mean for f in res.frames])
    assert "did not fit" in " ".join(s.notes)


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
    for f in res.frames:
        assert f[0].pending_band is None and f[0].wss.tau_std is None and cine.MOMENTUM_BAND_NOTE in f[0].notes
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
    walls, choice = womersley.smooth_walls(t, omega, rigid, "auto", 9)
    assert choice.degree == 0 and np.allclose(walls, rigid.mean(axis=0))
    moving = truth.copy()
    moving[:, 0] += 0.5 * np.sin(omega * t)
    noisy = moving + 0.02 * rng.standard_normal(truth.shape)
    walls, choice = womersley.smooth_walls(t, omega, noisy, "auto", 9)
    assert choice.degree == 1 and np.max(np.abs(walls - moving)) < 0.03
    assert np.array_equal(womersley.smooth_walls(t, omega, noisy, "frames", 9)[0], noisy)
    assert np.allclose(womersley.smooth_walls(t, omega, noisy, "shared", 9)[0], noisy.mean(axis=0))


def test_kspace_acquired_cine_gets_the_momentum_model_through_the_psf():
    """Frames acquired with a Hamming filter and twofold zero-filling (seed 68, h = 1.5 mm, 8 frames): the
    model's columns go through the PSF as the frames' own operator does (velocity.voxel_values), so the
    momentum model is chosen, every frame lands within 3 % of the peak (measured 1.4 %; at h = 1 mm 1.1 %
    where the frames' own fits miss by about 45 %) and the TAWSS within the issue's 5 % (measured 2.3 %: 3 mm
    acquired voxels)."""
    from wss_nlp import kspace

    psf = kspace.PSF("hamming", (2.0, 2.0))
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=68, frames=8, psf=psf)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options())
    s = res.series(0)
    assert s.model.model == "momentum"
    worst, tawss, _ = _errors(s, truth)
    assert worst < 0.03 and tawss < 0.05


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


def test_temporal_prior_pencils_cholesky_and_the_coupled_block_system_agree():
    """wss_nlp.temporal: the BIC search's pencils, a Cholesky solve per frequency and the whole coupled system
    (all frames' normal equations plus gamma D2^T D2 x G0, assembled as one block matrix) give the same
    coefficients (to 1e-7 relative: three independent solvers of one linear problem)."""
    from wss_nlp import phantoms, temporal
    from wss_nlp import velocity as vel
    from wss_nlp.reconstruct import reconstruct

    acq, _ = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=69)
    r = reconstruct(acq, _options())[0]
    problem = vel.assemble(r.grid, r.velocity_image, r.geometry.coefficients, r.geometry.center,
                           ReconstructionOptions().velocity.__class__(near_wall="off"))  # fmt: skip
    rng = np.random.default_rng(69)
    n = 6
    data = problem.data[None, :] * (1 + 0.3 * np.sin(np.arange(n) * 2 * np.pi / n))[:, None]
    data = data + 0.01 * rng.standard_normal(data.shape)
    sigma = np.full(data.shape, 0.01)
    best = temporal.fit(problem, data, sigma, 1.0, float(np.log(data.size)))
    direct = temporal.solve(problem, data, best.beta, best.gamma)
    assert np.max(np.abs(best.coefficients - direct)) <= 1e-7 * np.max(np.abs(direct))
    beta, gamma = 1e-6, 10.0
    t, w = problem.operator, problem.weights / problem.area
    k = t.T @ (w[:, None] * t)
    d2 = np.roll(np.eye(n), 1, axis=1) - 2 * np.eye(n) + np.roll(np.eye(n), -1, axis=1)
    big = np.kron(np.eye(n), k + beta * problem.gram / np.pi) + gamma * np.kron(
        d2.T @ d2, problem.basis.laplacian_gram(0) / np.pi
    )
    coupled = np.linalg.solve(big, ((w[None, :] * data) @ t).ravel()).reshape(n, -1)
    got = temporal.solve(problem, data, beta, gamma)
    assert np.max(np.abs(got - coupled)) <= 1e-7 * np.max(np.abs(coupled))


def test_forced_temporal_prior_on_a_steady_profile_scaled_in_time():
    """--cine-model temporal on the quasi-steady circle (h = 1.5 mm, SNR 25, 8 frames, seed 69): one shared
    wall, the prior's WSS within 5 % of the peak at every frame (the frames' own fits: about 2 %), no band."""
    frames, truth = pulsatile.make_quasi_steady_cine("circle", h_mm=1.5, snr=25, seed=69, frames=8)
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, _options("temporal"))
    s = res.series(0)
    assert s.model.model == "temporal" and s.model.walls["degree"] == 0 and "temporal_prior" in s.model.walls
    worst, tawss, _ = _errors(s, truth)
    assert worst < 0.05 and tawss < 0.05 and np.all(np.isnan(s.tau_std))
