#!/usr/bin/env python
"""How far the pulsatile arch phantom's axial flow is from the momentum balance (Womersley) model (issue 38, item 7).

The momentum model of 2D cine (``wss_nlp.models.womersley``) writes the axial velocity of a cross-section as
``u(r, t) = Re sum_n A_n S_n(r / R) exp(i n omega t)``, ``S_n`` Womersley's profiles of fully developed flow in a
straight rigid pipe (``rho u_t = G(t) + mu Delta u``). Here the best such series (``n <= K``, least squares over
the cross-section and the cycle, the phantom's own radius, period and viscosity) is fitted to the exact axial
velocity of ``synthetic.vessels``' pulsatile arch (``make_vessel_phantom('pulsatile')``: a parabolic-blunt blend
skewed towards the outer wall with swirl) on two cross-sections, and its wall shear stress compared with the
phantom's exact axial WSS. No reconstruction: the numbers measure the model's reach on this flow, not a fit to
data.

    python scripts/vessel_womersley_gap.py [--harmonics 8] [--out scripts/results]

Writes ``vessel_womersley_gap.md``.
"""

import argparse

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.models.womersley import shape, wall_slope, womersley_parameter
from wss_nlp.synthetic import vessels as vs


def section_gap(vessel, s_mm: float, harmonics: int, n_rho: int = 24, n_phi: int = 32, n_t: int = 64) -> dict:
    flow = vessel.flow
    radius = float(vessel.section.a_mm)
    period_s = flow.period_ms / 1000.0
    omega = 2 * np.pi / period_s
    nu = flow.viscosity_pa_s / flow.density_kg_m3
    x, wq = np.polynomial.legendre.leggauss(n_rho)
    rho = 0.5 * (x + 1)
    w_rho = 0.5 * wq * rho  # area weights rho d rho
    phi = np.linspace(-np.pi, np.pi, n_phi, endpoint=False)
    times = np.arange(n_t) * flow.period_ms / n_t
    f = vessel.centreline.frame(np.array([s_mm]))
    rr, pp = np.meshgrid(rho * radius, phi, indexing="ij")
    pts = f.point + rr.reshape(-1, 1) * (np.cos(pp).reshape(-1, 1) * f.n1 + np.sin(pp).reshape(-1, 1) * f.n2)
    u = np.stack([vessel.velocity(pts, float(t)) @ f.tangent[0] for t in times])  # (n_t, n_rho * n_phi) axial, m/s
    weights = np.broadcast_to(w_rho[:, None], rr.shape).ravel()
    lams = [womersley_parameter(n, radius, omega, nu) for n in range(harmonics + 1)]
    cols, slopes = [], []
    for n, lam in enumerate(lams):
        prof = np.broadcast_to(shape(rho, lam)[:, None], rr.shape).ravel()
        phase = np.exp(1j * n * omega * times / 1000.0)
        z = phase[:, None] * prof[None, :]
        cols.append(z.real)
        slopes.append((wall_slope(lam) * phase).real)
        if n > 0:
            cols.append(-z.imag)
            slopes.append(-(wall_slope(lam) * phase).imag)
    a = np.stack([c.ravel() for c in cols], axis=1)
    sw = np.sqrt(np.tile(weights, n_t))
    coef, *_ = np.linalg.lstsq(a * sw[:, None], u.ravel() * sw, rcond=None)
    fit = (a @ coef).reshape(u.shape)
    rel_u = float(np.sqrt(np.sum(weights * (fit - u) ** 2) / np.sum(weights * u**2)))
    # the wall shear stress: tau . t = -mu du/dr at r = R (1/mm -> 1/m: x 1000)
    tau_fit = -flow.viscosity_pa_s * 1000.0 / radius * (np.stack(slopes, axis=1) @ coef)  # (n_t,), one per time
    tau_true = np.stack([vessel.axial_wss(np.full(n_phi, s_mm), phi, float(t)) for t in times])  # (n_t, n_phi)
    rel_tau = float(np.sqrt(np.sum((tau_fit[:, None] - tau_true) ** 2) / np.sum(tau_true**2)))
    tawss_true = np.mean(np.abs(tau_true), axis=0)
    tawss_fit = np.mean(np.abs(tau_fit))
    return {"s_mm": s_mm, "alpha": abs(lams[1]) if harmonics else 0.0, "stokes_mm": 1000 * np.sqrt(2 * nu / omega),
            "rel_u": rel_u, "rel_tau": rel_tau,
            "tawss_spread": float(np.max(tawss_true) / np.min(tawss_true)),
            "tawss_rel": float(np.sqrt(np.mean((tawss_fit - tawss_true) ** 2) / np.mean(tawss_true**2)))}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--harmonics", type=int, default=8)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args()
    vessel, _ = vs.CASES["pulsatile"][0]({})
    # the manufactured profile is the same in the local coordinates of every section (straight leg or bend: the
    # numbers agree to rounding), so one section stands for all: the apex of the bend
    sections = [("apex of the bend (s = 87 mm)", 40.0 + 30.0 * np.pi / 2)]
    lines = [
        "The pulsatile arch phantom's exact axial velocity on a cross-section (the same on every one) against the "
        f"best momentum-balance (Womersley) series with {args.harmonics} harmonics (least squares over the section "
        "and 64 instants of the cycle; the phantom's radius 11 mm, period 1 s, viscosity 3.5e-3 Pa s, density "
        "1060 kg/m^3). Relative L2 errors over the section and cycle; the WSS is the axial part at the wall over 32 "
        "angles; TAWSS spread: the largest over the smallest true TAWSS around the wall (a Womersley profile has one "
        "value).",
        "Made by `python scripts/vessel_womersley_gap.py"
        + (f" --harmonics {args.harmonics}`." if args.harmonics != 8 else "`."),
        "",
        "| section | Womersley number | Stokes layer [mm] | axial velocity rel. error | axial WSS rel. error "
        "| TAWSS rel. error | true TAWSS spread around the wall |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, s in sections:
        r = section_gap(vessel, s, args.harmonics)
        lines.append(
            f"| {name} | {r['alpha']:.1f} | {r['stokes_mm']:.2f} | {100 * r['rel_u']:.1f} % | "
            f"{100 * r['rel_tau']:.1f} % | {100 * r['tawss_rel']:.1f} % | {r['tawss_spread']:.2f} |"
        )
    write_report(args.out, "vessel_womersley_gap.md", lines)


if __name__ == "__main__":
    main()
