#!/usr/bin/env python
"""How well do the rules for beta do against the oracle (issue 3)?

For each phantom, h, SNR and seed (alpha fixed at its default), the velocity
problem is solved on the grid beta = 1e-2 2^-n down to 1e-14; the oracle is
the grid value with the smallest WSS error (truth known). Reported: the
oracle error and, for each rule, the ratio of its WSS error to the oracle's
(1.00 = as good as the oracle; the issue asks for <= 1.25). Rules: the fixed
beta 5e-8 (the default before balancing), the discrepancy principle with tau = 1.1 (default) and with the
paper's tau = 2 (estimated noise), GCV, the L-curve and the balancing
principle on the WSS (the default kappa_beta). Also the estimated over the true noise
levels (epsilon: mean over seeds; delta: range over seeds).

A second table asks what the data can determine at all: noise-free data and
the exact geometry (true centre and radius; circle phantom only), WSS error
against beta. Writes ``scripts/results/parameter_rules.md``.

    python scripts/parameter_rules.py [--seeds 3] [--cases laminar,turbulent]   (about 5 minutes)

With ``--kappa`` it writes ``parameter_kappa.md`` instead: the balancing
beta's worst-seed ratio to the oracle for kappa = 2, 2.5, 3, 4 over seeds
0-2 and 21-22, and how often noise-only data exceed kappa (how the default
kappa_beta = 2.5 was chosen; about 20 minutes on 2 cores).
"""

import numpy as np

from _report import study_parser, write_report
from wss_nlp.parameters import noise as nl
from wss_nlp.parameters import rules as pr
from wss_nlp.models import geometry as geo
from wss_nlp.models import measurement as meas
from wss_nlp.synthetic import phantoms
from wss_nlp.models import preprocess as pp
from wss_nlp.core import radius as rad
from wss_nlp.models import velocity as vel
from wss_nlp.models import wss
from wss_nlp.pipeline import ReconstructionOptions
from wss_nlp.core.tikhonov import LinearTikhonov

RULES = ("fixed", "DP tau=1.1", "DP tau=2", "GCV", "L-curve", "balance")
KAPPA = ReconstructionOptions().choice.kappa_beta
FLOOR_BETAS = (1e-7, 1e-9, 1e-11, 1e-13, 1e-14)


class Slice:
    """One phantom slice at the default alpha: the velocity problem, the WSS matrix, the WSS error of any beta."""

    def __init__(self, case: str, h: float, snr: float, seed: int):
        self.acq, self.truth = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
        mag, u = self.acq.magnitude[0], self.acq.velocity_images()[0]
        self.norm = pp.histogram_peaks(mag)
        m = pp.normalize_magnitude(mag, self.norm)
        self.lumen = lum = pp.find_lumen(m, self.acq.grid)
        self.problem = geo.GeometryProblem(self.acq.grid, m, lum.center, lum.r0, lum.r1, lum.r_area)
        g = geo.solve(self.problem, geo.GeometryOptions())
        self.vp = vp = vel.assemble(self.acq.grid, u, g.coefficients, g.center, vel.VelocityOptions())
        self.wss_matrix, xw = wss.wss_matrix(vp.basis, vp.disk_map, self.acq.viscosity_pa_s)
        self.tau_true = self.truth.wss_at_points(xw[0], xw[1])
        self.noise = nl.velocity_noise(u, mag, lum.mask, vp.voxels.index, vp.weights, self.acq.venc_m_s)

    def error(self, beta: float) -> float:
        tau = self.wss_matrix @ vel.solve_cholesky(self.vp, beta)
        return float(np.linalg.norm(tau - self.tau_true) / np.linalg.norm(self.tau_true))


def main(argv=None):
    p = study_parser(__doc__, seeds=3, h="1.5,1.0,0.6,0.3", snr="10,25,50")
    p.add_argument("--kappa", action="store_true", help="the kappa table of the balancing rule instead (see above)")
    args = p.parse_args(argv)
    if args.kappa:
        write_report(args.out, "parameter_kappa.md", kappa_table(args))
        return
    grid = pr.geometric_grid(1e-2, 1e-14)
    rows = []
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            for snr in (float(x) for x in args.snr.split(",")):
                ratios, oracle_err, noise_ratio, delta_ratio = {r: [] for r in RULES}, [], [], []
                for seed in range(args.seeds):
                    sl = Slice(case, h, snr, seed)
                    acq, truth, vp, a, err, noise = sl.acq, sl.truth, sl.vp, sl.wss_matrix, sl.error, sl.noise
                    delta_ratio.append(magnitude_noise_ratio(acq, sl.problem, sl.norm, sl.lumen, snr, seed, case, h))
                    _, e_or = pr.oracle(grid, [err(b) for b in grid])
                    eps = noise.value
                    clean = truth.velocity_image.ravel()[vp.voxels.index]
                    noise_ratio.append(eps / np.sqrt(np.sum(vp.weights * (vp.data - clean) ** 2) / vp.area))

                    def solve(b, prev):
                        c = vel.solve_cholesky(vp, b)
                        return c, vp.residual_norm(c)

                    gcv, res, pen = pr.gcv_curve(vp.tikhonov, grid)
                    chosen = {
                        "fixed": vel.VelocityOptions().beta,
                        "DP tau=1.1": pr.discrepancy_search(solve, 1e-2, eps, 1.1)[1].chosen,
                        "DP tau=2": pr.discrepancy_search(solve, 1e-2, eps, 2.0)[1].chosen,
                        "GCV": grid[int(np.argmin(gcv))],
                        "L-curve": grid[pr.lcurve_corner(res, pen)[0]],
                        "balance": grid[pr.wss_balance(vp.tikhonov, grid, a, noise.details["per_voxel"], KAPPA)[0]],
                    }
                    for r in RULES:
                        ratios[r].append(err(chosen[r]) / e_or)
                    oracle_err.append(e_or)
                rows.append(
                    (
                        case,
                        h,
                        snr,
                        np.mean(oracle_err),
                        {r: max(v) for r, v in ratios.items()},
                        np.mean(noise_ratio),
                        (min(delta_ratio), max(delta_ratio)),
                    )
                )
                print(case, h, snr, "done", flush=True)
    lines = [
        f"WSS error of each beta rule divided by the oracle's (worst over {args.seeds} seeds); alpha fixed "
        "at its default. Oracle: best beta on the grid 1e-2 2^-n (truth known).",
        "",
        "| phantom | h [mm] | SNR | oracle WSS err | " + " | ".join(RULES) + " | eps est/true | delta est/true |",
        "|---|---|---|---|" + "---|" * (len(RULES) + 2),
    ]
    for case, h, snr, eo, r, nr, dr in rows:
        lines.append(
            f"| {case} | {h:g} | {snr:g} | {eo:.1%} | "
            + " | ".join(f"{r[k]:.2f}" for k in RULES)
            + f" | {nr:.2f} | {dr[0]:.2f}-{dr[1]:.2f} |"
        )
    within = {k: np.mean([r[k] <= 1.25 for *_, r, _, _ in rows]) for k in RULES}
    lines += [
        "",
        "Share of rows within 1.25x of the oracle: " + ", ".join(f"{k} {v:.0%}" for k, v in within.items()) + ".",
    ]
    lines += ["", *floor_table(args)]
    write_report(args.out, "parameter_rules.md", lines)


KAPPAS = (2.0, 2.5, 3.0, 4.0)
KAPPA_SEEDS = (0, 1, 2, 21, 22)  # 21, 22: the end-to-end tests' seeds, which no default was chosen on before


def kappa_table(args) -> list[str]:
    """Worst-seed WSS error of the balancing beta over the oracle's, for several kappa, and how often noise alone
    exceeds kappa (noise-only data through the same fit)."""
    grid = pr.geometric_grid(1e-2, 1e-14)
    lines = [
        f"Balancing beta: WSS error over the oracle's, worst of seeds {', '.join(map(str, KAPPA_SEEDS))}; "
        "alpha fixed at its default.",
        "",
        "| phantom | h [mm] | SNR | " + " | ".join(f"kappa = {k:g}" for k in KAPPAS) + " |",
        "|---|---|---|" + "---|" * len(KAPPAS),
    ]
    worst = {}
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            for snr in (float(x) for x in args.snr.split(",")):
                ratio = {k: [] for k in KAPPAS}
                for seed in KAPPA_SEEDS:
                    sl = Slice(case, h, snr, seed)
                    errs = np.array([sl.error(b) for b in grid])
                    _, crit, _ = pr.wss_balance(
                        sl.vp.tikhonov,
                        grid,
                        sl.wss_matrix,
                        sl.noise.details["per_voxel"],
                        KAPPAS[0],
                    )
                    for k in KAPPAS:  # the rule takes the first beta whose criterion is within kappa
                        ratio[k].append(errs[np.flatnonzero(crit <= k)[0]] / errs.min())
                lines.append(
                    f"| {case} | {h:g} | {snr:g} | " + " | ".join(f"{max(v):.2f}" for v in ratio.values()) + " |"
                )
                for k, v in ratio.items():
                    worst.setdefault((case, k), []).append(max(v))
                print(lines[-1], flush=True)
    lines += [
        "",
        "Range over rows of the worst-seed ratio: "
        + "; ".join(f"{case} kappa {k:g}: {min(v):.2f}-{max(v):.2f}" for (case, k), v in worst.items())
        + ".",
        "",
    ]
    lines += noise_only_exceedance()
    return lines


def noise_only_exceedance(draws: int = 400) -> list[str]:
    """How often the balancing criterion exceeds kappa when the data are noise alone (no bias at all)."""
    rng = np.random.default_rng(0)
    grid = pr.geometric_grid(1e-2, 1e-14)
    lines = [
        f"Noise-only data ({draws} draws of the estimated per-voxel phase noise through the same fit, "
        "SNR 25, seed 0): share of draws whose criterion exceeds kappa at beta.",
        "",
        "| phantom | h [mm] | beta | " + " | ".join(f"P(> {k:g})" for k in KAPPAS) + " |",
        "|---|---|---|" + "---|" * len(KAPPAS),
    ]
    for case, h in (("laminar", 1.0), ("laminar", 0.3), ("turbulent", 1.0)):
        sl = Slice(case, h, 25.0, 0)
        sigma, vp = sl.noise.details["per_voxel"], sl.vp
        # the rule itself (analysis.wss_balance), fed data that are noise alone
        crit = np.array(
            [
                pr.wss_balance(
                    LinearTikhonov(vp.operator, vp.weights, sigma * rng.normal(size=sigma.size), vp.gram),
                    grid,
                    sl.wss_matrix,
                    sigma,
                    KAPPAS[0],
                )[1]
                for _ in range(draws)
            ]
        )
        for beta in (1e-6, 1e-7, 1e-8, 1e-9):
            j = int(np.argmin(np.abs(np.log(grid / beta))))
            lines.append(
                f"| {case} | {h:g} | {grid[j]:.2g} | "
                + " | ".join(f"{np.mean(crit[:, j] > k):.3f}" for k in KAPPAS)
                + " |"
            )
    return lines


def magnitude_noise_ratio(acq, problem, norm, lum, snr, seed, case, h) -> float:
    """Estimated over true delta on the annulus; true = |m - clip((clean - m0)/(m1 - m0))| with the same m0, m1.

    The clean magnitude is the same phantom (same seed, hence the same sub-voxel offset) without noise, so
    the difference is the noise alone (after the same normalization and truncation).
    """
    annulus = meas.annulus_model(
        acq.grid, problem.center, problem.r0, problem.r1, geo.quad_order(problem, geo.GeometryOptions())
    ).annulus
    est = nl.magnitude_noise(
        problem.magnitude, acq.magnitude[0], lum.mask, norm.m0, norm.m1, acq.grid.voxel_area, annulus
    ).value
    clean, _ = phantoms.make_phantom(case, h_mm=h, snr=None, seed=seed)
    c = np.clip((clean.magnitude[0] - norm.m0) / (norm.m1 - norm.m0), 0.0, 1.0).ravel()[annulus]
    true = np.sqrt(acq.grid.voxel_area * np.sum((problem.magnitude.ravel()[annulus] - c) ** 2))
    return est / true


def floor_table(args) -> list[str]:
    """WSS error against beta for noise-free data on the exact geometry (what no parameter rule can beat)."""
    lines = [
        "WSS error against beta with noise-free data (seed 0); turbulent on the exact geometry (the true "
        "circle), laminar on the geometry reconstructed from the noise-free magnitude:",
        "",
        "| phantom | h [mm] | " + " | ".join(f"beta = {b:g}" for b in FLOOR_BETAS) + " | best on grid (beta) |",
        "|---|---|" + "---|" * (len(FLOOR_BETAS) + 1),
    ]
    grid = pr.geometric_grid(1e-2, 1e-14)
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            acq, truth = phantoms.make_phantom(case, h_mm=h, snr=None, seed=0)
            if case == "turbulent":
                coef = np.zeros(rad.n_coefficients(geo.GeometryOptions().n_fourier))
                coef[0], centre = truth.lumen.r, np.asarray(truth.center, float)
            else:
                m = pp.normalize_magnitude(acq.magnitude[0], pp.histogram_peaks(acq.magnitude[0]))
                lum = pp.find_lumen(m, acq.grid)
                g = geo.solve(
                    geo.GeometryProblem(acq.grid, m, lum.center, lum.r0, lum.r1, lum.r_area), geo.GeometryOptions()
                )
                coef, centre = g.coefficients, g.center
            vp = vel.assemble(acq.grid, truth.velocity_image, coef, centre, vel.VelocityOptions())
            a, xw = wss.wss_matrix(vp.basis, vp.disk_map, acq.viscosity_pa_s)
            tt = truth.wss_at_points(xw[0], xw[1])

            def err(b):
                return np.linalg.norm(a @ vel.solve_cholesky(vp, b) - tt) / np.linalg.norm(tt)

            b_or, e_or = pr.oracle(grid, [err(b) for b in grid])
            lines.append(
                f"| {case} | {h:g} | "
                + " | ".join(f"{err(b):.1%}" for b in FLOOR_BETAS)
                + f" | {e_or:.1%} ({b_or:.1e}) |"
            )
    return lines


if __name__ == "__main__":
    main()
