#!/usr/bin/env python
"""Reproduces the single-case numbers quoted in the docs' "How the defaults were chosen".

1. Penalty order: mean-WSS error on a noise-free circular Poiseuille phantom
   (h = 0.6 mm) with ||Delta v||^2 (t = 1) and ||Delta^2 v||^2 (t = 2), beta = 1e-4,
   Zernike degree 10, inner radius = min R (so Poiseuille flow maps to 1 - |xi|^2).
2. Geometry alpha: radius error of the laminar phantom (SNR 25, seeds 0-2,
   h = 1.5 and 0.6 mm) for alpha from 1e-4 to 1e-2.
3. Coupled vs decoupled on the turbulent phantom (h = 1 mm, SNR 10, seed 0)
   with the default beta and with beta = 1e-9 and 3e-11 (docs, "Coupled
   geometry and velocity").
4. Oyre baseline, fit range 3h vs the default 0.5 R, noise-free circle at
   h = 0.25 mm (docs, "Classical baselines").
5. Circumferential WSS of the swirl phantom (tapered stack, 10 slices, h = 1 mm,
   swirl 20/s): default beta, beta = 1e-11, inner fraction 1 (docs, "Stacks of slices").
6. Kaczmarz geometry sweeps for z smoothing l = dz and 2 dz, 12 slices, SNR 25.

    python scripts/claims.py      (about three minutes)
"""

import os

import numpy as np

from _report import write_report
from wss_nlp.pipeline import driver
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.models import baselines as bl
from wss_nlp.models import geometry as geo
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.models import stack
from wss_nlp.models import velocity as vel
from wss_nlp.pipeline import ReconstructionOptions, reconstruct


def main():
    lines = [
        "Penalty order, noise-free circle, h = 0.6 mm, beta = 1e-4:",
        "",
        "| penalty | mean-WSS error |",
        "|---|---|",
    ]
    acq, truth = phantoms.make_phantom("circle", h_mm=0.6, snr=None, seed=1)
    for t in (1, 2):
        vo = vel.VelocityOptions(degree=10, angular_order=None, inner_fraction=1.0, laplacian_power=t, beta=1e-4)
        res = reconstruct(acq, ReconstructionOptions(velocity=vo, choice=ChoiceOptions(beta_rule="fixed")))[0]
        lines.append(f"| t = {t} | {metrics.compare_slice(res, truth).mean_wss_rel:+.3%} |")
    lines += [
        "",
        "Geometry alpha, laminar phantom, SNR 25, seeds 0-2: radius rel. L2 error (max over seeds):",
        "",
        "| h [mm] | " + " | ".join(f"alpha {a:g}" for a in (1e-4, 1e-3, 4e-3, 1e-2)) + " |",
        "|---|---|---|---|---|",
    ]
    for h in (1.5, 0.6):
        row = []
        for alpha in (1e-4, 1e-3, 4e-3, 1e-2):
            errs = []
            for seed in range(3):
                acq, truth = phantoms.make_phantom("laminar", h_mm=h, snr=25, seed=seed)
                opts = ReconstructionOptions(geometry=geo.GeometryOptions(alpha=alpha))
                errs.append(metrics.compare_slice(reconstruct(acq, opts)[0], truth).radius_rel_l2)
            row.append(f"{np.max(errs):.2%}")
        lines.append(f"| {h:g} | " + " | ".join(row) + " |")
    lines += [
        "",
        "Turbulent phantom, h = 1 mm, SNR 10, seed 0: radius / WSS rel. L2 error:",
        "",
        "| beta | decoupled | coupled |",
        "|---|---|---|",
    ]
    acq, truth = phantoms.make_phantom("turbulent", h_mm=1.0, snr=10, seed=0)
    for beta in (5e-8, 1e-9, 3e-11):
        cells = []
        for method in ("decoupled", "coupled"):
            opts = ReconstructionOptions(
                method=method,
                uncertainty=False,
                velocity=vel.VelocityOptions(beta=beta),
                choice=ChoiceOptions(beta_rule="fixed"),
            )
            e = metrics.compare_slice(reconstruct(acq, opts)[0], truth)
            cells.append(f"{e.radius_rel_l2:.2%} / {e.wss_rel_l2:.1%}")
        lines.append(f"| {beta:g} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Oyre baseline, noise-free circle, h = 0.25 mm: mean-WSS error by fit range:",
        "",
        "| fit range | mean-WSS error | WSS rel. L2 error |",
        "|---|---|---|",
    ]
    acq, truth = phantoms.make_phantom("circle", h_mm=0.25, snr=None, seed=0)
    for label, fraction in (("3 h", 3 * 0.25 / 10.0), ("0.5 R (default)", 0.5)):
        opts = ReconstructionOptions(method="oyre", baseline=bl.BaselineOptions(oyre_range_fraction=fraction))
        e = metrics.compare_slice(reconstruct(acq, opts)[0], truth)
        lines.append(f"| {label} | {e.mean_wss_rel:+.1%} | {e.wss_rel_l2:.1%} |")
    lines += [
        "",
        "Swirl phantom (tapered stack, 10 slices, h = 1 mm, 20/s): mean circumferential WSS error over the slices:",
        "",
        "| data | velocity options | circumferential error |",
        "|---|---|---|",
    ]
    for snr in (None, 25.0):
        acq, truth = phantoms.make_stack("tapered", nz=10, h_mm=1.0, spacing_mm=2.0, snr=snr, seed=0, swirl_per_s=20.0)
        variants = [("beta 5e-8 (former default)", vel.VelocityOptions(), "fixed")]
        if snr is None:
            variants += [
                ("beta 1e-11", vel.VelocityOptions(beta=1e-11), "fixed"),
                ("inner fraction 1", vel.VelocityOptions(inner_fraction=1.0), "balance"),
            ]
        for name, vo, rule in variants:
            res = reconstruct(
                acq, ReconstructionOptions(uncertainty=False, velocity=vo, choice=ChoiceOptions(beta_rule=rule))
            )
            errs = []
            for k, r in enumerate(res):
                z = 2.0 * k
                slope = -(2 * np.pi / 80) * np.sin(2 * np.pi * z / 80)
                errs.append(
                    r.wss.vector.circumferential.mean() / (2 * acq.viscosity_pa_s * 20.0 * np.sqrt(1 + slope**2)) - 1
                )
            lines.append(f"| {'noise-free' if snr is None else f'SNR {snr:g}'} | {name} | {np.mean(errs):+.1%} |")
    lines += [
        "",
        "Kaczmarz geometry sweeps (first pass, second pass), 12 slices, h = 1 mm, SNR 25, seed 0:",
        "",
        "| phantom | l = dz | l = 2 dz |",
        "|---|---|---|",
    ]
    for case in ("tapered", "curved"):
        acq, _ = phantoms.make_stack(case, nz=12, h_mm=1.0, spacing_mm=2.0, snr=25, seed=0)
        cells = []
        for ell in (2.0, 4.0):
            _, info = driver.reconstruct_stack(
                acq,
                ReconstructionOptions(uncertainty=False),
                stack.StackOptions(z_smoothing_mm=ell, strategy="kaczmarz"),
            )
            cells.append(str(info.sweeps["geometry"]))
        lines.append(f"| {case} | " + " | ".join(cells) + " |")
    write_report(os.path.join(os.path.dirname(__file__), "results"), "claims.md", lines)


if __name__ == "__main__":
    main()
