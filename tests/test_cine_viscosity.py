"""Issue 40: the momentum model's Stokes layer from the data (wss_nlp.parameters.viscosity), its exact derivatives,
the phantoms' independent truth and waveforms, cine completeness (issue 42), and cine results through the command
line (analyze, compare, sensitivity, export).

Seeds 70-79, and the first reported seed 1000 for the targets' fast check (the report, scripts/cine.py --extra
viscosity, uses 1000-1004: test_viscosity_study_targets, slow; development 0-4)."""

import copy
import json
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from wss_nlp.app.cli import main
from wss_nlp.core import radius as rad
from wss_nlp.errors import InputError
from wss_nlp.io import files
from wss_nlp.models import velocity as vel
from wss_nlp.models import womersley
from wss_nlp.models.measurement import VoxelGrid
from wss_nlp.parameters import viscosity
from wss_nlp.pipeline import ReconstructionOptions, cine
from wss_nlp.synthetic import pulsatile

OMEGA, NU = 2 * np.pi, 3.5e-3 / 1060


@pytest.fixture(scope="module")
def problem():
    """A plain velocity problem on a circle of radius 6 mm (h = 1 mm, 6 x 6 points per voxel)."""
    grid = VoxelGrid((18, 18), (1.0, 1.0), (-8.5, -8.5))
    coefficients = np.zeros(rad.n_coefficients(4))
    coefficients[0] = 6.0
    options = ReconstructionOptions().velocity.__class__(near_wall="off", quad_order=6)
    return vel.assemble(grid, np.zeros(grid.shape), coefficients, (0.13, -0.21), options)


def test_shape_and_wall_slope_derivatives_in_ln_nu_are_exact():
    """Taylor test: dS/d(ln nu) and dS'(1)/d(ln nu) in closed form against central differences in ln nu (step
    1e-5: truncation ~1e-10 relative, rounding ~1e-11 / 1e-5), and the tabulated derivative (Hermite table) against
    the closed form within 3e-8 of its scale (the table's step, womersley.TABLE_STEP)."""
    sigma = np.random.default_rng(70).uniform(0, 1, 5000)
    for lam in womersley.lambdas(6, 10.0, OMEGA, NU):
        d = 1e-5  # theta + d: Lambda exp(-d / 2)
        fd = (womersley.shape(sigma, lam * np.exp(-d / 2)) - womersley.shape(sigma, lam * np.exp(d / 2))) / (2 * d)
        exact = womersley.shape_derivative(sigma, lam)
        assert np.max(np.abs(fd - exact)) <= 1e-7 * np.max(np.abs(exact))
        fd_slope = (womersley.wall_slope(lam * np.exp(-d / 2)) - womersley.wall_slope(lam * np.exp(d / 2))) / (2 * d)
        assert abs(fd_slope - womersley.wall_slope_derivative(lam)) <= 1e-7 * abs(fd_slope)
    lams = womersley.lambdas(6, 10.0, OMEGA, NU)
    _, table = womersley.shapes_at(sigma, lams, derivative=True)
    direct = np.column_stack([np.zeros_like(sigma)] + [womersley.shape_derivative(sigma, lam) for lam in lams])
    assert np.max(np.abs(table - direct)) <= 3e-8 * np.max(np.abs(direct))


def test_cell_integrals_along_rays_match_a_fine_quadrature(problem):
    """offset_columns integrates each point's cell along its ray: against a fine midpoint rule (24 x 24 points per
    cell of the voxels within 2 mm of the wall, inside points averaged) the voxel values of S_0 .. S_6 at Womersley
    number 14 (layers down to 0.3 mm in 1 mm voxels) agree within 5e-4 of the columns' scale in voxels inside
    the lumen (measured 2e-4: the radial cell average matches the square cell up to its fourth moment) and 3e-2
    in the wall's partial voxels (measured 1.7e-2: the wall cuts a cell along a line at an angle, approximated by
    the radial segment's inside length), in each at least 3-5 times better than the problem's own 6 x 6 midpoint
    values (the earlier columns: 5e-3 and 0.16)."""
    lams = womersley.lambdas(6, 6.0, OMEGA, NU * (6 / 10) ** 2)  # the 10 mm pipe's Womersley numbers at 6 mm
    got = womersley.offset_columns(womersley.WallPoints.of(problem), 6, OMEGA, NU * 0.36, 6.0, 0.0, False)
    vox, dm = problem.voxels, problem.disk_map
    s_mid = womersley.ray_coordinate(dm.coefficients, dm.center, vox.px[vox.inside], vox.py[vox.inside])
    mid = womersley.shapes_at(s_mid, lams)
    midpoint = vel.voxel_values(problem, mid.real) + 1j * vel.voxel_values(problem, mid.imag)
    near = np.hypot(vox.px.mean(axis=1) - dm.center[0], vox.py.mean(axis=1) - dm.center[1]) > 4.0  # the layer's
    fine = 24
    t = (np.arange(fine) + 0.5) / fine - 0.5
    ox, oy = (a.ravel() for a in np.meshgrid(t / 6, t / 6))  # within each 1/6 mm cell
    px = (vox.px[near][:, :, None] + ox[None, None, :]).reshape(np.sum(near), -1)
    py = (vox.py[near][:, :, None] + oy[None, None, :]).reshape(np.sum(near), -1)
    sigma = womersley.ray_coordinate(dm.coefficients, dm.center, px.ravel(), py.ravel()).reshape(px.shape)
    inside = sigma < 1
    shapes = womersley.shapes_at(np.where(inside, sigma, 1.0).ravel(), lams).reshape(sigma.shape + (7,))
    exact = np.sum(inside[..., None] * shapes, axis=1) / np.sum(inside, axis=1)[:, None]
    scale = np.max(np.abs(exact))
    full = inside.all(axis=1)
    got, midpoint = got[near], midpoint[near]
    assert np.max(np.abs(got[full] - exact[full])) <= 5e-4 * scale < np.max(np.abs(midpoint[full] - exact[full])) / 5
    worst_partial = np.max(np.abs(got[~full] - exact[~full]))
    assert worst_partial <= 0.03 * scale < np.max(np.abs(midpoint[~full] - exact[~full])) / 3


def test_offset_columns_derivatives_taylor(problem):
    """The columns' derivatives in ln(nu) and the wall offset against central differences (steps 1e-5 and 1e-6
    mm): within 1e-4 of the derivative's scale (the offset moves the cells' inside lengths piecewise linearly:
    central differences across a kink of a few points are the residual)."""
    points = womersley.WallPoints.of(problem)
    nu, eps = NU * 1.2, 0.03
    _, d_theta, d_eps = womersley.offset_columns(points, 4, OMEGA, nu, 6.0, eps)

    def columns(nu_, eps_):
        return womersley.offset_columns(points, 4, OMEGA, nu_, 6.0, eps_, derivative=False)

    fd_theta = (columns(nu * np.exp(1e-5), eps) - columns(nu * np.exp(-1e-5), eps)) / 2e-5
    fd_eps = (columns(nu, eps + 1e-6) - columns(nu, eps - 1e-6)) / 2e-6
    assert np.max(np.abs(fd_theta - d_theta)) <= 1e-4 * np.max(np.abs(d_theta))
    assert np.max(np.abs(fd_eps - d_eps)) <= 1e-4 * np.max(np.abs(d_eps))


def _synthetic_cycle(problem, nu_true, eps_true, noise, seed, frames=10):
    """CycleData of ``frames`` frames whose data are the model's own voxel values at (nu_true, eps_true) with a
    carotid-like set of coefficients and white noise ``noise`` (m/s)."""
    from dataclasses import replace

    rng = np.random.default_rng(seed)
    a = np.array([0.2, 0.15, -0.1, 0.08, 0.05, -0.03, 0.04])  # a_0 and three complex harmonics (m/s)
    points = womersley.WallPoints.of(problem)
    shapes = womersley.offset_columns(points, 3, OMEGA, nu_true, 6.0, eps_true, derivative=False)
    problems, sigmas, times = [], [], np.arange(frames) / frames
    for t in times:
        clean = womersley._columns(shapes, womersley.time_factors(3, OMEGA, t)) @ a
        data = clean + noise * rng.standard_normal(clean.size)
        problems.append(replace(problem, data=data))
        sigmas.append(np.full(clean.size, noise))
    return womersley.CycleData(problems, sigmas, times, OMEGA, 6.0, voxel_mm=1.0)


def test_profile_gradient_is_exact(problem):
    """The variable-projection gradient of f(ln nu, offset) = min_a chi^2 (parameters.viscosity._profile) against
    central differences of f (steps 1e-4 in ln nu, 1e-5 mm): within 1e-3 relative, away from the optimum."""
    data = _synthetic_cycle(problem, NU, 0.0, 0.01, 71)
    x, steps = np.array([0.2, 0.05]), (1e-4, 1e-5)
    _, _, grad, _, _ = viscosity._profile(data.blocks(NU * np.exp(x[0]), 3, x[1]))
    for j, step in enumerate(steps):
        up, down = x.copy(), x.copy()
        up[j] += step
        down[j] -= step
        f_up = viscosity._profile(data.blocks(NU * np.exp(up[0]), 3, up[1], derivative=False))[1]
        f_down = viscosity._profile(data.blocks(NU * np.exp(down[0]), 3, down[1], derivative=False))[1]
        assert (f_up - f_down) / (2 * step) == pytest.approx(grad[j], rel=1e-3)


@pytest.mark.parametrize("seed", [72, 73, 74])
def test_viscosity_and_offset_are_recovered_with_an_honest_interval(problem, seed):
    """Frames made by the model itself at nu = 1.3 x the stated one and the walls 0.03 mm further out, noise 0.01
    m/s (SNR about 25 on 0.25 m/s): the fit starts at the stated viscosity and no offset and lands within 3 of its
    own standard deviations of the truth in both (a wrong interval would miss; 3 sd: 0.3 % false alarms), the
    stated viscosity is flagged (outside the interval), and the fit beats the stated one's chi^2 by far."""
    data = _synthetic_cycle(problem, 1.3 * NU, 0.03, 0.01, seed)
    fit = viscosity.fit_viscosity(data, 3, NU, voxel_mm=1.0)
    assert abs(fit.theta - np.log(1.3)) < 3 * fit.std and fit.std < 0.05
    assert abs(fit.offset_mm - 0.03) < 3 * fit.offset_std_mm
    assert fit.determined and not fit.agrees and not fit.at_bound
    assert fit.fit.chi2 < fit.chi2_stated - 100  # strongly preferred: two parameters cost 2 ln N = 14 BIC units
    lo, hi = fit.interval()
    assert lo < 1.3 * NU < hi


def test_phantom_truth_is_independent_of_the_model_and_agrees_with_it():
    """pulsatile.WomersleyPipe computes its profile and WSS from Kelvin functions (scipy's ber/bei, not
    models.womersley's complex Bessel functions): both agree within 1e-9 (two implementations of J_0 along
    i^{3/2} x, each about 1e-11), and the phantom module does not import models.womersley."""
    import inspect

    flow = pulsatile.WomersleyPipe(lumen=pulsatile.Circle(r=10.0), viscosity_pa_s=3.5e-3)
    _, terms = flow._coefficients()
    x = np.linspace(0, 1, 2001)
    for n, alpha, _ in terms:
        lam = womersley.womersley_parameter(n, 10.0, OMEGA, NU)
        kelvin = 1 - pulsatile.kelvin(alpha * x) / pulsatile.kelvin(alpha)
        assert np.max(np.abs(kelvin - womersley.shape(x, lam))) < 1e-9
        slope = -alpha * pulsatile.kelvin_slope(alpha) / pulsatile.kelvin(alpha)
        assert abs(slope - womersley.wall_slope(lam)) < 1e-9 * abs(slope)
    assert all(m.__name__ != womersley.__name__ for _, m in inspect.getmembers(pulsatile, inspect.ismodule))


def test_published_shape_waveforms_have_their_features():
    """16 harmonics of each waveform (pulsatile.WAVEFORMS) reproduce its pulse train within 1 % of the peak, peak
    bulk velocity as given (sampled: 1e-5); carotid forward all cycle (diastolic flow at least 15 % of the peak),
    aortic, femoral and brachial reverse (femoral the most, at least 20 % of the peak), and the Womersley numbers
    at the typical radii span the issue's 3-20 (3.0 brachial to 16.6 aortic)."""
    phase = np.arange(2000) / 2000
    alphas = {}
    for name, w in pulsatile.WAVEFORMS.items():
        h = w.harmonics()
        v = pulsatile._bulk(h, phase)
        train = w.values(phase) * w.peak_m_s / np.max(w.values(phase))
        assert np.max(np.abs(v - train)) < 0.01 * w.peak_m_s and np.max(v) == pytest.approx(w.peak_m_s, rel=1e-5)
        alphas[name] = w.radius_mm * 1e-3 * np.sqrt(2 * np.pi / (w.period_ms / 1000) / NU)
        if name == "carotid":
            assert np.min(v) > 0.15 * w.peak_m_s
        else:
            assert np.min(v) < 0
    assert np.min(pulsatile._bulk(pulsatile.WAVEFORMS["femoral"].harmonics(), phase)) < -0.2 * 0.6
    assert 2.9 < min(alphas.values()) < 3.1 and 16 < max(alphas.values()) < 17


def test_coverage_refuses_frames_that_do_not_cover_the_cycle():
    """Issue 42: one or two frames, or frames over part of the cycle, give no TAWSS/OSI (a refusal that says why);
    one missing frame of 20 is bridged with a note; 12 jittered frames are fine."""
    good = np.ones(20, bool)
    times = np.arange(20) * 50.0
    assert cine.coverage(times, good, 1000.0) == (None, None)
    refusal, _ = cine.coverage(np.array([0.0, 62.5]), np.ones(2, bool), 1000.0)
    assert "2 frame(s)" in refusal and "not computed" in refusal
    refusal, _ = cine.coverage(times[:8], good[:8], 1000.0)  # 0-350 ms of a 1000 ms cycle
    assert "650 ms" in refusal
    missing = good.copy()
    missing[7] = False
    refusal, note = cine.coverage(times, missing, 1000.0)
    assert refusal is None and "100 ms" in note
    jittered = (np.arange(12) + np.r_[0, np.random.default_rng(75).uniform(-0.15, 0.15, 11)]) * 1000 / 12
    assert cine.coverage(jittered, np.ones(12, bool), 1000.0)[0] is None


def test_two_frames_with_the_whole_period_give_no_tawss(tmp_path, capsys):
    """Two frames 125 ms apart stated as a 1000 ms cycle: the per-frame WSS is written, TAWSS and OSI are NaN with
    the reason in the file (wss attribute tawss_note) and on the command line, never an average of 125 ms as if it
    were the cycle."""
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=76, frames=8)
    inp, out = tmp_path / "two.h5", tmp_path / "r.h5"
    files.write_frames(str(inp), frames[:2], truth.times_ms[:2], 1000.0)
    assert main(["reconstruct", str(inp), "-o", str(out), "--no-uncertainty"]) == 0
    text = capsys.readouterr()
    assert "TAWSS and OSI not computed" in text.out and "not computed" in text.err
    with h5py.File(out) as f:
        g = f["slice_000"]
        assert np.all(np.isnan(g["wss/tawss_pa"][()])) and np.all(np.isnan(g["wss/osi"][()]))
        assert "2 frame(s)" in g["wss"].attrs["tawss_note"] and np.all(np.isfinite(g["wss/mean_pa_t"][()]))


def test_group_warnings_says_each_kind_once_with_the_count():
    """Messages that differ only in numbers are one kind: one line with the frames (ranges) and the count."""
    items = [(k, f"slice 0: no band for this frame (beta {1e-9 * (k + 1):.2g})") for k in range(20)]
    items += [(4, "geometry did not converge"), (5, "geometry did not converge"), (9, "only here")]
    lines = cine.group_warnings(items, 20)
    assert lines[0].startswith("frames 0-19 (20 of 20): slice 0: no band") and len(lines) == 3
    assert "frames 4-5 (2 of 20): geometry did not converge" in lines and "frame 9: only here" in lines


def test_the_summary_names_the_cycle_model():
    """The printed line per cine slice names the model over the cycle (the temporal prior as such), the viscosity
    the frames imply, and says when TAWSS and OSI were not computed."""
    from wss_nlp.app.cli.reconstruct import _cycle_summary

    record = {"mode": "fit", "implied_interval_pa_s": [3.3e-3, 3.6e-3], "implied_pa_s": 3.45e-3, "stated_pa_s": 3.5e-3,
              "agrees": True}  # fmt: skip
    base = dict(index=0, tawss=np.ones(4), osi=np.zeros(4), time_average_mean=1.0, mean=np.array([1.0, 2.0]))
    temporal = SimpleNamespace(**base, model=SimpleNamespace(model="temporal", harmonics=0, viscosity={}))
    assert "temporal prior" in _cycle_summary(temporal, [0, 500])
    momentum = SimpleNamespace(**base, model=SimpleNamespace(model="momentum", harmonics=4, viscosity=record))
    assert "momentum model (4 harmonics; the frames imply 3.45 mPa s" in _cycle_summary(momentum, [0, 500])
    base["tawss"] = np.full(4, np.nan)
    own = SimpleNamespace(**base, model=SimpleNamespace(model="independent", harmonics=0, viscosity={}))
    line = _cycle_summary(own, [0, 500])
    assert "not computed" in line and "frames' own fits" in line


@pytest.fixture(scope="module")
def stated_high(tmp_path_factory):
    """One cine slice shared by the tests below (one reconstruction keeps CI cheap): the rigid 10 mm pipe
    (Womersley number 13.8), 8 frames (the waveform's 4 harmonics; 6 frames would alias them), h = 1.5 mm, SNR
    25, the first reported seed (1000), the files stating the viscosity 30 % high; reconstructed with the default
    options and written as ``wss-nlp reconstruct`` writes it (``cine.write_result``), with the truth file."""
    folder = tmp_path_factory.mktemp("cine_cli")
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=1000, frames=8, viscosity_error=0.3)
    options = ReconstructionOptions()
    res = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, options)
    out, truth_path = folder / "r.h5", folder / "t.h5"
    cine.write_result(str(out), res, options.as_dict())
    pulsatile.write_truth(str(truth_path), truth)
    return SimpleNamespace(folder=folder, frames=frames, truth=truth, result=res, out=out, truth_path=truth_path)


def test_stated_viscosity_30_percent_off_is_found_in_the_data(stated_high):
    """The files state the viscosity 30 % high: with the viscosity fitted (the default) every frame is within 2 %
    of the peak of the WSS the stated viscosity implies (issue 40's goal; measured 1.3 %), TAWSS within 2 %
    (1.2 %) and OSI within 0.02 (0.003) of the exact integrals over the whole cycle, the fitted kinematic
    viscosity within 5 % of the truth (1.2 %) with the truth inside its 95 % interval, and the stated value
    flagged; the same frames' fits with the stated viscosity (the momentum model forced, --cine-viscosity
    stated) miss by more than 5 % (measured 9.4 %: the layer 30 % too thick in nu). The full study (3 voxel
    sizes, 5 viscosity errors, reported seeds) is scripts/cine.py --extra viscosity and
    test_viscosity_study_targets (slow)."""
    truth, res = stated_high.truth, stated_high.result
    s = res.series(0)
    ref = truth.reference_tau()
    peak = np.max(np.abs(ref))
    tawss, osi, _ = truth.cycle_integrals()
    assert s.model.model == "momentum" and np.max(np.abs(s.mean - ref)) < 0.02 * peak
    assert abs(np.mean(s.tawss) / tawss - 1) < 0.02 and abs(np.mean(s.osi) - osi) < 0.02
    v = s.model.viscosity
    nu_true = truth.viscosity_pa_s / truth.flow.density_kg_m3
    assert abs(v["nu_m2_s"] / nu_true - 1) < 0.05 and v["nu_interval_m2_s"][0] < nu_true < v["nu_interval_m2_s"][1]
    assert not v["agrees"] and any("OUTSIDE" in n or "disagree" in n for n in s.notes)
    stated = ReconstructionOptions(cine=womersley.CineModelOptions(model="momentum", viscosity="stated"))
    other = copy.copy(res)
    other.models = cine.cycle_models(res, stated_high.frames, stated, OMEGA, None)
    assert other.series(0).model.viscosity["mode"] == "stated"
    assert np.max(np.abs(other.series(0).mean - ref)) > 0.05 * peak


def test_analyze_compare_sensitivity_export_read_a_cine_result(stated_high, capsys):
    """Through the command line, exit 0: analyze names the cycle model and why (the candidates' criteria, the
    viscosity the frames imply, the stated one flagged) and lists every frame's alpha and beta; compare gives
    the frames' errors against the WSS the stated viscosity implies (within 2 % of the peak), TAWSS, OSI and
    the fitted viscosity against the truth (within 5 %, inside its interval); sensitivity the momentum model's
    table; export the wall with TAWSS and OSI."""
    folder, out, truth = stated_high.folder, str(stated_high.out), str(stated_high.truth_path)
    capsys.readouterr()
    assert main(["analyze", out, "--figures", str(folder / "figs")]) == 0
    text = capsys.readouterr().out
    assert "velocity over the cycle: the momentum model" in text and "<- chosen" in text
    assert "the frames imply" in text and "OUTSIDE" in text and text.count("  beta ") >= 1 and "     7 " in text
    assert main(["compare", out, truth]) == 0
    text = capsys.readouterr().out
    assert "worst frame |mean WSS err| / peak" in text and "stated / true viscosity" in text

    def number(label):  # the table's row: the label, then the value right-aligned
        return float(text.split(label)[1].split("\n")[0].split()[-1].rstrip("%"))

    assert number("worst frame |mean WSS err| / peak") < 2.0 and abs(number("TAWSS rel. error")) < 2.0
    assert abs(number("OSI error")) < 0.02 and abs(number("fitted kinematic viscosity rel. error")) < 5.0
    assert text.split("truth inside its 95 % interval")[1].split("\n")[0].split()[-1] == "yes"
    assert main(["sensitivity", out]) == 0
    assert "stated viscosity +10 %" in capsys.readouterr().out
    pytest.importorskip("meshio")
    assert main(["export", out, "--vtk", str(folder / "w.vtu")]) == 0


def test_compare_refuses_a_truth_of_another_layout(stated_high, tmp_path, capsys):
    """A cine result against a single-slice truth: one line naming what is missing, exit 2."""
    out = stated_high.out
    single, single_truth = tmp_path / "s.h5", tmp_path / "st.h5"
    assert main(["phantom", "--case", "circle", "--h", "1.5", "-o", str(single), "--truth", str(single_truth)]) == 0
    capsys.readouterr()
    assert main(["compare", str(out), str(single_truth)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "time-resolved truth" in err[0]


def test_read_result_and_records_of_a_cine_result(stated_high):
    """files.read_result gives the per-frame alpha and beta as arrays (they were a TypeError) and the series;
    read_cine_models the model record with the viscosity; read_choices each frame's choices."""
    out = stated_high.out
    d = files.read_result(out)[0]
    assert d["alpha"].shape == (8,) and d["tau"].shape[0] == 8 and d["time_ms"].shape == (8,)
    rec = files.read_cine_models(out)["slice_000"]
    assert rec["model"] == "momentum" and rec["viscosity"]["mode"] == "fit" and rec["time_ms"].size == 8
    assert set(files.read_choices(out)) == {f"slice_000/frame_{k:03d}" for k in range(8)}
    assert files.result_layout(out) == "cine"
    with h5py.File(out) as f:
        assert json.loads(f["slice_000"].attrs["cine_model_json"])["sensitivity"]["tawss_pa"] > 0
    with pytest.raises(InputError):
        files.result_layout(str(out) + ".missing")


@pytest.mark.slow
@pytest.mark.parametrize("h", [1.5, 1.0, 0.6])
@pytest.mark.parametrize("error", [0.0, -0.15, 0.15, -0.3, 0.3])
def test_viscosity_study_targets(h, error):
    """Issue 40's Must show on the reported seeds 1000-1004 (scripts/results/cine_viscosity*.md): 20 frames, SNR
    25, the files stating the viscosity off by ``error``, default options: every frame within 2 % of the peak of
    the WSS the stated viscosity implies, TAWSS within 2 %, OSI within 0.02; at h <= 1 mm (Womersley number
    13.8 >= 8) the fitted viscosity within 5 % of the truth; its 95 % interval holds the truth on at least 4 of
    the 5 seeds (an honest 95 % interval misses one seed in 20 on average; 2 misses of 5 have probability 2 %)."""
    inside = 0
    for seed in range(1000, 1005):
        frames, truth = pulsatile.make_cine(h_mm=h, snr=25, seed=seed, frames=20, viscosity_error=error)
        s = cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, ReconstructionOptions()).series(0)
        ref = truth.reference_tau()
        tawss, osi, _ = truth.cycle_integrals()
        assert np.max(np.abs(s.mean - ref)) < 0.02 * np.max(np.abs(ref)), seed
        assert abs(np.mean(s.tawss) / tawss - 1) < 0.02 and abs(np.mean(s.osi) - osi) < 0.02, seed
        v = s.model.viscosity
        nu_true = truth.viscosity_pa_s / truth.flow.density_kg_m3
        if h <= 1.0:
            assert abs(v["nu_m2_s"] / nu_true - 1) < 0.05, seed
        inside += v["nu_interval_m2_s"][0] <= nu_true <= v["nu_interval_m2_s"][1]
    assert inside >= 4
