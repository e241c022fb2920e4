#!/usr/bin/env python
"""How gamma of the cine volume's temporal prior is chosen (``wss_nlp.vessel.cycle3d``): the predictive risk
(the default), Schwarz's criterion (BIC) and GCV against the frames' own fits, by the velocity's error against the
phantom's exact velocity.

Phantom: a short straight tube (radius 7 mm, h = 2.5 mm) with a temporally smooth pulsatile flow (one harmonic,
reverse flow, skew and swirl), 12 frames, ``synthetic.vessels`` (the phantom of ``tests/test_vessel_cycle.py``);
the wall fitted on 16 mm about the middle, the velocity with one fixed small beta (1e-6) for the cycle. Error: the
RMS of the fitted minus the exact velocity at 400 random lumen points at least 2.5 mm inside the wall over all
frames, over the peak speed. Development seeds only.

    python scripts/vessel_cycle_choice.py [--seeds 3,4,5] [--snr 10,20] [--out scripts/results]

Writes ``vessel_cycle_choice.md``.
"""

import argparse

import numpy as np
import scipy.ndimage as ndi

from _report import RESULTS, write_report
from wss_nlp.io.volume import VolumeAcquisition
from wss_nlp.synthetic import vessels as vs
from wss_nlp.vessel import cycle3d as c3
from wss_nlp.vessel import geometry3d as g3
from wss_nlp.vessel import reconstruct as vrec
from wss_nlp.vessel import tube
from wss_nlp.vessel import velocity3d as v3

BETA = 1e-6


def setup(seed: int, snr: float) -> dict:
    cl0 = vs.build_centreline((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), [vs.LineSegment(60.0)])
    flow = vs.VesselFlow(u_peak_m_s=0.8, skew=0.2, swirl_m_s=0.1, waveform=vs.Waveform(0.3, (0.6,), (0.3,)))
    vessel = vs.Vessel(cl0, vs.Section(7.0), flow)
    vol, truth = vs.make_vessel_phantom("straight", h_mm=2.5, snr=snr, seed=seed, frames=12, vessel=vessel,
                                        visible_mm=(20.0, 38.0))  # fmt: skip
    inputs = vrec.vessel_inputs(vol)
    cl = inputs.centerline
    co = tube.voxel_coordinates(vol, np.argwhere(ndi.binary_dilation(inputs.mask, iterations=5)), cl)
    mid = float(cl.project(truth.centreline(np.array([29.0])).point).s[0])
    problem = g3.problem_from_mask(vol, cl, inputs.mask, co, (mid - 8.0, mid + 8.0), np.linspace(0, cl.length_mm, 60))
    frame, lev = problem.frame, problem.levels
    geo = g3.fit_wall(problem, g3.Geometry3DOptions(n_fourier=3, outside_updates=0))
    vopt = v3.Velocity3DOptions(degree=6, angular_order=2, beta=BETA)
    vp = v3.assemble(vol, geo, frame, co, vopt)
    vel = v3.fit_velocity(vol, vp, vopt, levels=lev)
    return {"vol": vol, "truth": truth, "problem": vp, "velocity": vel, "levels": lev, "centerline": cl}


def velocity_error(case: dict, coefficients) -> float:
    vol, truth, cl, vp = case["vol"], case["truth"], case["centerline"], case["problem"]
    rng = np.random.default_rng(5)
    s = rng.uniform(24.0, 34.0, 400)
    phi = rng.uniform(-np.pi, np.pi, 400)
    r = np.sqrt(rng.uniform(0, 1, 400)) * (truth.radius(s, phi) - 2.5)
    f = truth.centreline(s)
    x = f.point + r[:, None] * (np.cos(phi)[:, None] * f.n1 + np.sin(phi)[:, None] * f.n2)
    proj = cl.project(x)
    num = den = 0.0
    for k, t in enumerate(vol.trigger_times_ms):
        exact = truth.vessel.velocity(x, float(t))
        fit = vp.basis.evaluate(coefficients[k], proj.s, proj.r, proj.phi)
        num += float(np.sum((fit - exact) ** 2))
        den += exact.size
    return float(np.sqrt(num / den)) / truth.vessel.flow.u_peak_m_s


def bic_gamma(case: dict) -> float:
    """gamma minimizing ``chi^2 + ln(N) dof`` on the grid the default uses (decades, then quarter decades)."""
    vol, vp, vel, lev = case["vol"], case["problem"], case["velocity"], case["levels"]
    u = v3.voxel_velocities(vol, vp)
    rhs = np.stack([vp.rhs(u[t]) for t in range(vol.nt)])
    spec = c3._Spectrum(vp, vel.beta, rhs, c3.mass_gram(vp))
    sigma = v3.velocity_noise(vol, vp, lev)
    op = vp.operator()

    def bic(g):
        coef = spec.coefficients(g)
        fit = np.stack([op @ coef[t] for t in range(vol.nt)])
        return float(np.sum(((fit - u) / sigma[None]) ** 2)) + np.log(u.size) * 3.0 * spec.trace(g)

    values = {float(g): bic(float(g)) for g in c3.GAMMAS}
    best = min(values, key=values.__getitem__)
    for e in (-0.75, -0.5, -0.25, 0.25, 0.5, 0.75):
        values[best * 10.0**e] = bic(best * 10.0**e)
    return min(values, key=values.__getitem__)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", default="3,4,5")
    p.add_argument("--snr", default="10,20")
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args()
    lines = [
        "The temporal prior's gamma on a smooth 12-frame tube (module notes of `scripts/vessel_cycle_choice.py`): "
        "the velocity's RMS error over the peak speed with the frames' own fits, and with the prior at the gamma "
        "of the predictive risk (`chi^2 + 2 dof`, the default), of the BIC (`chi^2 + ln(N) dof`) and of GCV (the "
        "criterion without the venc). Development seeds.",
        "Made by `python scripts/vessel_cycle_choice.py`.",
        "",
        "| SNR | seed | frames' own | predictive risk: gamma, error | BIC: gamma, error | GCV: gamma, error |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    with vrec.blas_threads(1):
        for snr in (float(v) for v in args.snr.split(",")):
            for seed in (int(v) for v in args.seeds.split(",")):
                case = setup(seed, snr)
                vol, vp, vel, lev = case["vol"], case["problem"], case["velocity"], case["levels"]
                times, period = vol.trigger_times_ms, vol.cardiac_period_ms
                own = velocity_error(case, vel.coefficients)
                risk, ch = c3.fit_cycle(vol, vp, vel, "temporal", times, period, lev)
                gb = bic_gamma(case)
                u = v3.voxel_velocities(vol, vp)
                bic_coef = c3.solve_prior(vp, vel.beta, gb, np.stack([vp.rhs(u[t]) for t in range(vol.nt)]))
                blind = VolumeAcquisition(vol.magnitude, vol.velocity, vol.affine_mm, None, vol.viscosity_pa_s,
                                          trigger_times_ms=times, cardiac_period_ms=period)  # fmt: skip
                gcv, cg = c3.fit_cycle(blind, vp, vel, "temporal", times, period, lev)
                e_risk = velocity_error(case, risk.coefficients)
                lines.append(
                    f"| {snr:g} | {seed} | {100 * own:.2f} % | {ch.gamma:.3g}, {100 * e_risk:.2f} % "
                    f"| {gb:.3g}, {100 * velocity_error(case, bic_coef):.2f} % "
                    f"| {cg.gamma:.3g}, {100 * velocity_error(case, gcv.coefficients):.2f} % |"
                )  # fmt: skip
                print(lines[-1], flush=True)
    write_report(args.out, "vessel_cycle_choice.md", lines)


if __name__ == "__main__":
    main()
