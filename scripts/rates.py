#!/usr/bin/env python
"""Convergence rates of the geometry identification (Theorem 2.1) against the noise level.

Radius functions in H^k (Fourier coefficients decaying like n^-(k + 1/2 + 0.05)
up to n = 64), noise-free data ``F(R)`` from the same voxel model (this study
isolates the noise; it is not an accuracy test) plus Gaussian noise scaled to
``||eta||_{L^2(D)} = delta``, fits in V_24 with the H^2 penalty and
``alpha = delta^(4/k)`` (a priori) or the discrepancy principle
(``tau = 1.1``). The exponents of ``||R_alpha - R||_{H^r}`` against delta,
r = 0, 1, 2, are fitted by least squares in log-log and compared with
Theorem 2.1's ``1 - r/k``. Writes ``scripts/results/rates.md`` and
``rates.png``.

    python scripts/rates.py [--seeds 3] [--k 3,4]        (about 5 minutes)

The velocity rates (the issue asks for them too) are not measured; see the docs.
"""

import argparse
import os
import sys

import numpy as np

from _report import write_report
from wss_nlp.parameters import rules as pr
from wss_nlp.models import geometry as geo
from wss_nlp.models import measurement as meas
from wss_nlp.core import radius as rad
from wss_nlp.app.plotting import figure_rates, save_figure

N_TRUE, N_FIT, H_MM, R0 = 64, 24, 0.5, 10.0


def truth_coefficients(k: int, rng) -> np.ndarray:
    """A radius in H^k (and not in H^(k+1/10)): random phases, |c_n| ~ n^-(k + 0.55), amplitude 0.6 mm."""
    n = np.arange(1, N_TRUE + 1, dtype=float)
    amp = n ** -(k + 0.55)
    amp *= 0.6 / np.sum(amp)
    phase = rng.uniform(0, 2 * np.pi, N_TRUE)
    return np.concatenate([[R0], amp * np.cos(phase), amp * np.sin(phase)])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--k", default="3,4")
    p.add_argument("--deltas", default="0.3,0.15,0.08,0.04,0.02,0.01")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    args = p.parse_args(argv)
    deltas = np.array([float(x) for x in args.deltas.split(",")])
    n_side = int(2 * (R0 + 3) / H_MM)
    grid = meas.VoxelGrid((n_side, n_side), (H_MM, H_MM), (-(n_side - 1) * H_MM / 2, -(n_side - 1) * H_MM / 2))
    lines = [
        "Geometry rates: fitted exponent of ||R_alpha - R||_{H^r} against delta (Theorem 2.1: 1 - r/k), "
        f"{args.seeds} seeds per point, h = {H_MM} mm, V_{N_FIT}, noise delta in L^2(D).",
        "",
        "| k | rule | r = 0 (theory) | r = 1 (theory) | r = 2 (theory) | within 0.15 |",
        "|---|---|---|---|---|---|",
    ]
    curves = {}
    for k in (int(x) for x in args.k.split(",")):
        for rule in ("a priori", "discrepancy"):
            errs = np.zeros((deltas.size, 3))
            for seed in range(args.seeds):
                rng = np.random.default_rng(1000 * k + seed)
                c_true = truth_coefficients(k, rng)
                problem0 = geo.GeometryProblem(grid, np.zeros(grid.shape), (0.0, 0.0), R0 - 3, R0 + 2.5, R0)
                gopt = geo.GeometryOptions(n_fourier=N_FIT, quad_order=4, tol=1e-10)
                model = meas.annulus_model(grid, (0.0, 0.0), problem0.r0, problem0.r1, 4)
                clean = np.zeros(grid.shape).ravel()
                clean[model.inside] = 1.0
                clean[model.annulus] = meas.magnitude_model(model, c_true, geo.effective_gamma(problem0, gopt))
                noise = rng.standard_normal(clean.size)
                noise /= np.linalg.norm(noise) * np.sqrt(grid.voxel_area)  # unit L^2(D) norm
                for i, delta in enumerate(deltas):
                    m = (clean + delta * noise).reshape(grid.shape)
                    problem = geo.GeometryProblem(grid, m, (0.0, 0.0), problem0.r0, problem0.r1, R0)
                    solver = geo.IpoptGeometrySolver(problem, gopt)
                    if rule == "a priori":
                        g = solver.solve(delta ** (4.0 / k))
                    else:
                        # the discrepancy is measured on the annulus (the rest is noise no R can change)
                        noise_a = delta * np.linalg.norm(noise[model.annulus]) * np.sqrt(grid.voxel_area)
                        g, _ = pr.discrepancy_search(
                            lambda a, prev: (lambda r: (r, r.annulus_residual_norm))(
                                solver.solve(a, None if prev is None else prev.coefficients)
                            ),
                            1.0,
                            noise_a,
                            1.1,
                        )
                    diff = np.zeros(c_true.size)
                    diff[0] = g.coefficients[0] - c_true[0]
                    diff[1 : N_FIT + 1] = g.coefficients[1 : N_FIT + 1]
                    diff[N_TRUE + 1 : N_TRUE + 1 + N_FIT] = g.coefficients[N_FIT + 1 :]
                    diff -= np.concatenate([[0.0], c_true[1:]])
                    errs[i] += [rad.sobolev_norm(diff, r) / args.seeds for r in range(3)]
                print(f"k={k} {rule} seed {seed} done", file=sys.stderr, flush=True)
            slopes = [np.polyfit(np.log(deltas), np.log(errs[:, r]), 1)[0] for r in range(3)]
            theory = [1 - r / k for r in range(3)]
            ok = all(abs(s - t) <= 0.15 for s, t in zip(slopes, theory))
            lines.append(
                f"| {k} | {rule} | "
                + " | ".join(f"{s:.2f} ({t:.2f})" for s, t in zip(slopes, theory))
                + f" | {'yes' if ok else 'no'} |"
            )
            curves[(k, rule)] = errs
    write_report(args.out, "rates.md", lines)
    save_figure(figure_rates(deltas, curves), os.path.join(args.out, "rates.png"))


if __name__ == "__main__":
    main()
