#!/usr/bin/env python
"""Reproduces the single-case numbers quoted in the README's "How the defaults were chosen".

1. Penalty order: mean-WSS error on a noise-free circular Poiseuille phantom
   (h = 0.6 mm) with ||Delta v||^2 (t = 1) and ||Delta^2 v||^2 (t = 2), beta = 1e-4,
   Zernike degree 10, inner radius = min R (so Poiseuille flow maps to 1 - |xi|^2).
2. Geometry alpha: radius error of the laminar phantom (SNR 25, seeds 0-2,
   h = 1.5 and 0.6 mm) for alpha from 1e-4 to 1e-2.
3. Coupled vs decoupled on the turbulent phantom (h = 1 mm, SNR 10, seed 0)
   with the default beta and with beta = 1e-9 and 3e-11 (README, "Coupled
   geometry and velocity").

    python scripts/claims.py      (about a minute)
"""

import os

import numpy as np

from _report import write_report
from wss_nlp import geometry as geo
from wss_nlp import metrics, phantoms
from wss_nlp import velocity as vel
from wss_nlp.reconstruct import ReconstructionOptions, reconstruct


def main():
    lines = ["Penalty order, noise-free circle, h = 0.6 mm, beta = 1e-4:", "",
             "| penalty | mean-WSS error |", "|---|---|"]
    acq, truth = phantoms.make_phantom("circle", h_mm=0.6, snr=None, seed=1)
    for t in (1, 2):
        vo = vel.VelocityOptions(degree=10, angular_order=None, inner_fraction=1.0, laplacian_power=t, beta=1e-4)
        res = reconstruct(acq, ReconstructionOptions(velocity=vo))[0]
        lines.append(f"| t = {t} | {metrics.compare_slice(res, truth).mean_wss_rel:+.3%} |")
    lines += ["", "Geometry alpha, laminar phantom, SNR 25, seeds 0-2: radius rel. L2 error (max over seeds):", "",
              "| h [mm] | " + " | ".join(f"alpha {a:g}" for a in (1e-4, 1e-3, 4e-3, 1e-2)) + " |",
              "|---|---|---|---|---|"]
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
    lines += ["", "Turbulent phantom, h = 1 mm, SNR 10, seed 0: radius / WSS rel. L2 error:", "",
              "| beta | decoupled | coupled |", "|---|---|---|"]
    acq, truth = phantoms.make_phantom("turbulent", h_mm=1.0, snr=10, seed=0)
    for beta in (5e-8, 1e-9, 3e-11):
        cells = []
        for method in ("decoupled", "coupled"):
            opts = ReconstructionOptions(method=method, uncertainty=False, velocity=vel.VelocityOptions(beta=beta))
            e = metrics.compare_slice(reconstruct(acq, opts)[0], truth)
            cells.append(f"{e.radius_rel_l2:.2%} / {e.wss_rel_l2:.1%}")
        lines.append(f"| {beta:g} | " + " | ".join(cells) + " |")
    write_report(os.path.join(os.path.dirname(__file__), "results"), "claims.md", lines)


if __name__ == "__main__":
    main()
