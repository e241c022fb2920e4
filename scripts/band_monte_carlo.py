#!/usr/bin/env python
"""The linearized WSS band against Monte Carlo (issue: within 20 % on a phantom).

One noise-free acquisition of a phantom; the band is computed from one noisy
draw and compared with the sample standard deviation of tau(phi) and of the
mean over ``--draws`` further draws (fresh complex noise each, default
options otherwise, with the fixed beta 5e-8). Also the cost of the band against one solve. Writes
``scripts/results/band.md`` and ``band.png``.

    python scripts/band_monte_carlo.py [--draws 200] [--h 1.5,1.0] [--case laminar]   (about 5 minutes)

With ``--stack NZ`` the phantom is a stack of ``NZ`` slices 2 mm apart
(``--case`` a stack case, e.g. ``curved``) reconstructed with z-regularization
(default z smoothing); the band of every slice (:mod:`wss_nlp.uncertainty.stack_band`)
against the draws' spread, one row per slice. Writes ``band_stack.md``.

    python scripts/band_monte_carlo.py --stack 5 --case curved --h 1.5 --draws 100   (about 15 minutes)
"""

import argparse
import os
import sys

import numpy as np

from _report import write_report
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.synthetic import phantoms
from wss_nlp.app.plotting import figure_band_check, save_figure
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

TARGET_REL = 0.2  # issue: the band agrees with Monte Carlo within 20 %
TARGET_COST = 3.0  # issue: the full band costs at most 3x one solve
# The band is linearized at a given beta (a data-driven beta is held at its value), so the Monte-Carlo draws
# keep beta fixed too: the table checks the band, not the spread of the beta rule.
FIXED_BETA = ReconstructionOptions(choice=ChoiceOptions(beta_rule="fixed"))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--draws", type=int, default=200)
    p.add_argument("--case", default="laminar")
    p.add_argument("--h", default="1.5,1.0")
    p.add_argument("--snr", type=float, default=25.0)
    p.add_argument("--seed", type=int, default=4)
    p.add_argument("--stack", type=int, default=0, help="number of slices of a z-regularized stack (0: one slice)")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    args = p.parse_args(argv)
    if args.stack:
        return stack_rows(args)
    lines = [
        f"Phantom '{args.case}', SNR {args.snr:g}, {args.draws} Monte-Carlo draws per row (seed {args.seed}); "
        "linearized band from one draw; cost: median over the draws of the solve and of the band.",
        "",
        "| h [mm] | mean-WSS std: linearized | Monte Carlo | ratio | RMS over angles of tau std: linearized | "
        "Monte Carlo | ratio | band s / solve s | targets (20 %, 3x) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for h in (float(x) for x in args.h.split(",")):
        acq0, _ = phantoms.make_phantom(args.case, h_mm=h, snr=None, seed=args.seed)
        rng = np.random.default_rng(2024)
        band = reconstruct(phantoms.noisy_copy(acq0, args.snr, rng), FIXED_BETA)[0]
        means, taus, solve_s, band_s = [], [], [], []
        for i in range(args.draws):
            r = reconstruct(phantoms.noisy_copy(acq0, args.snr, rng), FIXED_BETA)[0]
            means.append(r.wss.mean)
            taus.append(r.wss.tau)
            band_s.append(r.seconds.get("uncertainty", np.nan))
            solve_s.append(
                sum(
                    v
                    for k, v in r.seconds.items()
                    if k in ("preprocess", "geometry", "velocity", "dephasing_check", "dephasing_pass", "wss")
                )
            )
            if (i + 1) % 20 == 0:
                print(f"h={h}: {i + 1}/{args.draws} draws", file=sys.stderr, flush=True)
        mc_mean = float(np.std(means, ddof=1))
        mc_tau = np.std(np.array(taus), axis=0, ddof=1)
        lin_rms, mc_rms = float(np.sqrt(np.mean(band.wss.tau_std**2))), float(np.sqrt(np.mean(mc_tau**2)))
        cost = float(np.median(band_s) / np.median(solve_s))
        ok = (
            abs(band.wss.mean_std / mc_mean - 1) <= TARGET_REL
            and abs(lin_rms / mc_rms - 1) <= TARGET_REL
            and cost <= TARGET_COST
        )
        lines.append(
            f"| {h:g} | {band.wss.mean_std:.3g} | {mc_mean:.3g} | {band.wss.mean_std / mc_mean:.2f} | "
            f"{lin_rms:.3g} | {mc_rms:.3g} | {lin_rms / mc_rms:.2f} | {cost:.2f} | {'yes' if ok else 'NO'} |"
        )
        save_figure(
            figure_band_check(band.wss.phi, band.wss.tau_std, mc_tau, args.draws),
            os.path.join(args.out, f"band_h{h:g}.png"),
        )
    write_report(args.out, "band.md", lines)


def stack_rows(args) -> None:
    """One row per slice of a z-regularized stack: each slice's band against the spread over the draws."""
    lines = [
        f"Stack '{args.case}' of {args.stack} slices 2 mm apart, z-regularized (default z smoothing), SNR "
        f"{args.snr:g}, {args.draws} Monte-Carlo draws (seed {args.seed}), beta fixed; band of each slice from "
        "one draw (wss_nlp.uncertainty.stack_band). Made by `python scripts/band_monte_carlo.py"
        + "".join(f" {a}" for a in sys.argv[1:])
        + "`.",
        "",
        "| h [mm] | slice | mean-WSS std: linearized | Monte Carlo | ratio | RMS of tau std: linearized | "
        "Monte Carlo | ratio | within 20 % |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for h in (float(x) for x in args.h.split(",")):
        acq0, _ = phantoms.make_stack(args.case, nz=args.stack, h_mm=h, snr=None, seed=args.seed)
        rng = np.random.default_rng(2024)
        band = reconstruct(phantoms.noisy_copy(acq0, args.snr, rng), FIXED_BETA)
        opts = ReconstructionOptions(uncertainty=False, choice=ChoiceOptions(beta_rule="fixed"))
        means, taus = [], []
        for i in range(args.draws):
            res = reconstruct(phantoms.noisy_copy(acq0, args.snr, rng), opts)
            means.append([r.wss.mean for r in res])
            taus.append([r.wss.tau for r in res])
            if (i + 1) % 20 == 0:
                print(f"h={h}: {i + 1}/{args.draws} draws", file=sys.stderr, flush=True)
        mc_mean = np.std(np.array(means), axis=0, ddof=1)
        mc_tau = np.std(np.array(taus), axis=0, ddof=1)
        for k, r in enumerate(band):
            lin_rms, mc_rms = float(np.sqrt(np.mean(r.wss.tau_std**2))), float(np.sqrt(np.mean(mc_tau[k] ** 2)))
            ratio_mean, ratio_rms = r.wss.mean_std / mc_mean[k], lin_rms / mc_rms
            ok = abs(ratio_mean - 1) <= TARGET_REL and abs(ratio_rms - 1) <= TARGET_REL
            lines.append(
                f"| {h:g} | {k} | {r.wss.mean_std:.3g} | {mc_mean[k]:.3g} | {ratio_mean:.2f} | {lin_rms:.3g} | "
                f"{mc_rms:.3g} | {ratio_rms:.2f} | {'yes' if ok else 'NO'} |"
            )
            print(lines[-1], flush=True)
    write_report(args.out, "band_stack.md", lines)


if __name__ == "__main__":
    main()
