"""The cycle models of a cine volume (issue 38, item 7): the periodic temporal prior split by the temporal DFT,
its weight and its choice against the frames' own fits by the data, the forced settings."""

import dataclasses

import numpy as np
import pytest
import scipy.ndimage as ndi

from wss_nlp.errors import InputError
from wss_nlp.io.volume import VolumeAcquisition
from wss_nlp.models.temporal import second_difference
from wss_nlp.synthetic import vessels as vs
from wss_nlp.vessel import cycle3d as c3
from wss_nlp.vessel import geometry3d as g3
from wss_nlp.vessel import reconstruct as vrec
from wss_nlp.vessel import tube
from wss_nlp.vessel import velocity3d as v3

FRAMES = 12
BETA = 1e-6


def _smooth_cine(seed: int, snr=20.0):
    """A short straight tube (radius 7 mm, h = 2.5 mm: 2.8 voxels) with a temporally smooth pulsatile flow (one
    harmonic, reverse flow in part of the cycle, skew and swirl), 12 frames: the truth's content sits in the
    temporal DFT's modes 0 and 1, the noise in all 7."""
    cl = vs.build_centreline((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), [vs.LineSegment(60.0)])
    flow = vs.VesselFlow(u_peak_m_s=0.8, skew=0.2, swirl_m_s=0.1, waveform=vs.Waveform(0.3, (0.6,), (0.3,)))
    vessel = vs.Vessel(cl, vs.Section(7.0), flow)
    return vs.make_vessel_phantom("straight", h_mm=2.5, snr=snr, seed=seed, frames=FRAMES, vessel=vessel,
                                  visible_mm=(20.0, 38.0))  # fmt: skip


@pytest.fixture(scope="module", autouse=True)
def _one_blas_thread():
    """Small dense products, as in the reconstruction (``VesselOptions.blas_threads``): threads only cost here."""
    with vrec.blas_threads(1):
        yield


@pytest.fixture(scope="module")
def cine():
    """The smooth cine's velocity problem on a fitted wall, the frames' own fits (one GCV beta) and the levels."""
    vol, truth = _smooth_cine(seed=3)
    inputs = vrec.vessel_inputs(vol)
    cl = inputs.centerline
    co = tube.voxel_coordinates(vol, np.argwhere(ndi.binary_dilation(inputs.mask, iterations=5)), cl)
    # the middle of the visible part only (the wall fit's cost grows with the length): 16 mm
    mid = float(cl.project(truth.centreline(np.array([29.0])).point).s[0])
    problem = g3.problem_from_mask(vol, cl, inputs.mask, co, (mid - 8.0, mid + 8.0), np.linspace(0, cl.length_mm, 60))
    frame, lev = problem.frame, problem.levels
    geo = g3.fit_wall(problem, g3.Geometry3DOptions(n_fourier=3, outside_updates=0))
    # one small fixed beta for the cycle, a weak spatial prior as GCV chooses on the pulsatile arch (1e-8 there):
    # the frames' own fits keep their noise, which a temporal prior can take out
    vopt = v3.Velocity3DOptions(degree=6, angular_order=2, beta=BETA)
    vp = v3.assemble(vol, geo, frame, co, vopt)
    vel = v3.fit_velocity(vol, vp, vopt, levels=lev)
    return {"vol": vol, "truth": truth, "problem": vp, "velocity": vel, "levels": lev, "centerline": cl, "geo": geo}


def _joint_matrix(problem, beta, gamma, n):
    """The prior's normal matrix assembled whole (frames' blocks and the coupling by Kronecker products): the
    direct computation the DFT split is checked against."""
    d2 = second_difference(n)
    return np.kron(np.eye(n), problem.hessian(beta)) + gamma / (np.pi * problem.length_mm) * np.kron(
        d2.T @ d2, c3.mass_gram(problem)
    )


@pytest.mark.parametrize("n", [5, 6])  # odd and even: the Nyquist mode counts once
def test_the_dft_split_solve_and_trace_equal_the_joint_ones(cine, n):
    vp, beta = cine["problem"], cine["velocity"].beta
    rng = np.random.default_rng(11)
    rhs = rng.normal(size=(n, vp.size, 3))
    gamma = 0.7
    joint = _joint_matrix(vp, beta, gamma, n)
    direct = np.linalg.solve(joint, rhs.reshape(n * vp.size, 3)).reshape(n, vp.size, 3)
    split = c3.solve_prior(vp, beta, gamma, rhs)
    # one functional, two exact solves (banded Cholesky per mode against dense LU of the whole): they differ by
    # rounding amplified by the condition number (about 1e6 here)
    assert np.max(np.abs(split - direct)) <= 1e-9 * np.max(np.abs(direct))
    spec = c3._Spectrum(vp, beta, rhs, c3.mass_gram(vp))
    assert np.max(np.abs(spec.coefficients(gamma) - direct)) <= 1e-8 * np.max(np.abs(direct))
    # the smoother's trace tr(J^-1 (I x K)), exactly, from the generalized eigenvectors
    trace = np.trace(np.linalg.solve(joint, np.kron(np.eye(n), vp.normal())))
    assert spec.trace(gamma) == pytest.approx(trace, rel=1e-9)


def test_gamma_zero_gives_the_frames_own_fits_back(cine):
    vol, vp, vel = cine["vol"], cine["problem"], cine["velocity"]
    u = v3.voxel_velocities(vol, vp)
    rhs = np.stack([vp.rhs(u[t]) for t in range(vol.nt)])
    own = vel.coefficients
    assert np.max(np.abs(c3.solve_prior(vp, vel.beta, 0.0, rhs) - own)) <= 1e-10 * np.max(np.abs(own))
    spec = c3._Spectrum(vp, vel.beta, rhs, c3.mass_gram(vp))
    # the eigenvector route (the criterion's) loses more to rounding: cond(H) ~ 1e8 at this small beta
    assert np.max(np.abs(spec.coefficients(0.0) - own)) <= 1e-6 * np.max(np.abs(own))
    # and the forced "frames" leaves them as they are
    same, choice = c3.fit_cycle(vol, vp, vel, "frames", vol.trigger_times_ms, vol.cardiac_period_ms, cine["levels"])
    assert same is vel and choice.model == "frames" and "forced" in choice.how


def _velocity_error(cine, velocity) -> float:
    """RMS of the fitted minus the phantom's exact velocity at the lumen points a voxel inside the true wall over
    the visible part, all frames, over the peak speed (the truth from the phantom's closed form)."""
    vol, truth, cl = cine["vol"], cine["truth"], cine["centerline"]
    rng = np.random.default_rng(5)
    s = rng.uniform(24.0, 34.0, 400)  # well inside the fitted 16 mm about s = 29 mm (the phantom's arclength)
    phi = rng.uniform(-np.pi, np.pi, 400)
    r = np.sqrt(rng.uniform(0, 1, 400)) * (truth.radius(s, phi) - 2.5)
    f = truth.centreline(s)
    x = f.point + r[:, None] * (np.cos(phi)[:, None] * f.n1 + np.sin(phi)[:, None] * f.n2)
    proj = cl.project(x)
    num = den = 0.0
    for k, t in enumerate(vol.trigger_times_ms):
        exact = truth.vessel.velocity(x, float(t))
        fit = velocity.basis.evaluate(velocity.coefficients[k], proj.s, proj.r, proj.phi)
        num += float(np.sum((fit - exact) ** 2))
        den += exact.size
    return float(np.sqrt(num / den)) / truth.vessel.flow.u_peak_m_s


def test_the_prior_is_chosen_and_recovers_a_smooth_truth_better(cine):
    vol, vp, vel, lev = cine["vol"], cine["problem"], cine["velocity"], cine["levels"]
    tied, choice = c3.fit_cycle(vol, vp, vel, "auto", vol.trigger_times_ms, vol.cardiac_period_ms, lev)
    assert choice.model == "temporal" and choice.criterion == "bic" and choice.selection == "upre"
    assert choice.values["frames"] - choice.values["temporal"] == pytest.approx(choice.margin + c3.EVIDENCE)
    assert choice.margin > 0 and choice.gamma > 0 and choice.dof["temporal"] < choice.dof["frames"]
    # the chosen gamma is the predictive risk's minimum over gamma > 0
    assert choice.curve[choice.gamma] == min(v for g, v in choice.curve.items() if g > 0)
    own, prior = _velocity_error(cine, vel), _velocity_error(cine, tied)
    # measured on this seed: the frames' own fits 0.70 % of the peak speed, the prior (gamma 0.18) 0.54 %; the
    # noise's share of the frames' error is what a smooth truth lets the prior remove (the rest, the spatial
    # model's error, stays). 0.9 leaves room for rounding across platforms, not for a prior that does not help
    assert prior < 0.9 * own, (own, prior)


def test_forced_settings_and_refusals(cine):
    vol, vp, vel, lev = cine["vol"], cine["problem"], cine["velocity"], cine["levels"]
    times, period = vol.trigger_times_ms, vol.cardiac_period_ms
    fixed, choice = c3.fit_cycle(vol, vp, vel, 0.5, times, period, lev)
    assert choice.model == "temporal" and choice.gamma == 0.5 and "fixed" in choice.how
    u = v3.voxel_velocities(vol, vp)
    rhs = np.stack([vp.rhs(u[t]) for t in range(vol.nt)])
    assert np.allclose(fixed.coefficients, c3.solve_prior(vp, vel.beta, 0.5, rhs), rtol=0, atol=1e-12)
    _, forced = c3.fit_cycle(vol, vp, vel, "temporal", times, period, lev)
    assert forced.model == "temporal" and "forced" in forced.how and forced.gamma in forced.curve
    # irregular trigger times: the prior is refused with the reason, the frames keep their own fits
    uneven = np.asarray(times, float).copy()
    uneven[3] += 0.3 * (uneven[1] - uneven[0])
    same, refused = c3.fit_cycle(vol, vp, vel, "temporal", uneven, period, lev)
    assert same is vel and refused.model == "frames" and "not equally spaced" in refused.reason
    assert "not equally spaced" in refused.note()
    # without the venc the criterion is GCV
    blind = VolumeAcquisition(vol.magnitude, vol.velocity, vol.affine_mm, None, vol.viscosity_pa_s,
                              trigger_times_ms=times, cardiac_period_ms=period)  # fmt: skip
    _, gcv = c3.fit_cycle(blind, vp, vel, "auto", times, period, lev)
    assert gcv.criterion == "gcv" and set(gcv.values) == {"frames", "temporal"}
    for bad in ("momentum", -1.0, float("nan"), True):
        with pytest.raises(InputError):
            c3.check_setting(bad)
    with pytest.raises(InputError, match="cycle model"):
        vrec.VesselOptions(cycle="womersley")
    assert dataclasses.replace(vrec.VesselOptions(), cycle=2.0).cycle == 2.0


def test_the_command_line_sets_the_cycle_model_and_refuses_momentum():
    from wss_nlp.app.cli.parser import build_parser
    from wss_nlp.app.cli.vessel import vessel_options

    parser = build_parser()

    def options(*extra):
        args = parser.parse_args(["reconstruct", "exam.h5", "-o", "r.h5", *extra])
        return vessel_options(args)

    assert options().cycle == "auto"
    assert options("--cine-model", "independent").cycle == "frames"
    assert options("--cine-model", "temporal").cycle == "temporal"
    with pytest.raises(InputError, match="momentum balance") as info:
        options("--cine-model", "momentum")
    assert "\n" not in str(info.value)


def test_the_summary_names_the_cycle_model():
    rec = c3.CycleChoice("temporal", 0.05, "chosen by the BIC", "bic", {"frames": 100.0, "temporal": 50.0}, 40.0)
    line = c3.summary(rec.as_dict(), 20)
    assert "periodic temporal prior, gamma 0.05" in line and "margin 40" in line
    assert "each frame's own fit" in c3.summary(c3.CycleChoice("frames", how="forced").as_dict(), 20)
    assert "not recorded" in c3.summary(None, 20) and "one frame" in c3.summary(None, 1)


def test_a_reconstructed_cine_records_its_cycle_model_and_analyze_names_it(cine, tmp_path, capsys):
    """The whole route with the default options: the cycle model in the result's parameters and notes, read back
    from the file by ``analyze``."""
    from wss_nlp.app.cli.main import main

    res = vrec.reconstruct_vessel(cine["vol"], vrec.VesselOptions(n_phi=16))
    record = res.parameters["cycle"]
    assert record["model"] in ("temporal", "frames") and record["criterion"] == "bic"
    assert set(record["values"]) == {"frames", "temporal"} and record["curve"]
    assert any(note.startswith("velocity over the cycle:") for note in res.notes)
    path = tmp_path / "result.h5"
    vrec.write_result(path, res, mode="w")
    capsys.readouterr()
    assert main(["analyze", str(path)]) == 0
    out = capsys.readouterr().out
    name = "periodic temporal prior" if record["model"] == "temporal" else "each frame's own fit"
    assert f"velocity over the cycle: {name}" in out and "BIC" in out
