#!/usr/bin/env python
"""Accuracy of the default reconstruction on the built-in phantoms.

For the laminar (Poiseuille, elliptic pipe) and turbulent (DNS mean profile,
Re_tau 180.9) phantoms at h in {1.5, 1.0, 0.6, 0.3} mm, SNR 25 and several
seeds: radius relative L2 error, WSS relative L2 error and mean-WSS error
against the exact values. Writes ``scripts/results/accuracy.md`` and
``accuracy.csv`` and prints the Markdown table.

    python scripts/accuracy.py [--seeds 5] [--snr 25] [--cases laminar,turbulent]

With ``--auto`` it instead compares the data-driven parameters (the
discrepancy principle for both, the balancing principle for both, and the
fixed alpha with the balancing beta), all on the paper's velocity basis
(``--near-wall off``), with the oracle over an alpha-beta grid (alpha = 1e-3 4^k, k = -4..4; beta = 1e-2 2^-n down to
1e-14; truth known) at SNR 10, 25 and 50, 3 seeds, and writes
``accuracy_auto.md`` (issue 3: auto within 1.25x of the oracle).

With ``--unseen`` it compares the default (balancing) beta with the former
fixed beta 5e-8 on the manufactured, fourier and circle phantoms (SNR 10 and
25, seeds 31-33) and writes ``accuracy_unseen.md``.
"""

import csv
import os
import sys
import time

import numpy as np

from _report import study_parser, write_report
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.parameters import rules as pr
from wss_nlp.models import geometry as geo
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.models import velocity as vel
from wss_nlp.models import wss
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

TARGET_RADIUS = 0.005  # issue: geometry error <= 0.5 % at every h
TARGET_WSS_LAMINAR = 0.05  # issue: laminar WSS error <= 5 % at every h
TARGET_ORACLE_RATIO = 1.25  # issue 3: auto WSS error within 1.25x of the oracle over an alpha-beta grid

#: The parameter rules on the paper's basis (``--near-wall off``), for the rules and the oracle: the near-wall
#: layer (a later default, docs "Thin wall layers") would compare a richer model with a plain-basis oracle.
PLAIN = vel.VelocityOptions(near_wall="off")


def oracle_wss_error(acq, truth) -> float:
    """Smallest WSS error over the alpha-beta grid (default pipeline otherwise, dephasing pass included)."""
    best = np.inf
    betas = pr.geometric_grid(1e-2, 1e-14)
    for k in range(-4, 5):
        opts = ReconstructionOptions(
            geometry=geo.GeometryOptions(alpha=1e-3 * 4.0**k),
            uncertainty=False,
            velocity=PLAIN,
            choice=ChoiceOptions(beta_rule="fixed"),
        )  # beta is scanned below; the fixed rule skips a search
        res = reconstruct(acq, opts)[0]
        g = res.geometry
        vp = vel.assemble(
            res.grid, res.velocity_image, g.coefficients, g.center, opts.velocity, basis=res.velocity.basis
        )
        a, xw = wss.wss_matrix(vp.basis, vp.disk_map, acq.viscosity_pa_s)  # tau is linear in the coefficients
        tt = truth.wss_at_points(xw[0], xw[1])
        for b in betas:
            best = min(best, np.linalg.norm(a @ vel.solve_cholesky(vp, b) - tt) / np.linalg.norm(tt))
    return float(best)


AUTO_RULES = {
    "discrepancy": ReconstructionOptions(
        uncertainty=False, velocity=PLAIN, choice=ChoiceOptions(alpha_rule="discrepancy", beta_rule="discrepancy")
    ),
    "balance": ReconstructionOptions(
        uncertainty=False, velocity=PLAIN, choice=ChoiceOptions(alpha_rule="balance", beta_rule="balance")
    ),
    "fixed alpha, balance beta": ReconstructionOptions(
        uncertainty=False, velocity=PLAIN, choice=ChoiceOptions(alpha_rule="fixed", beta_rule="balance")
    ),
}


def auto_study(args) -> None:
    names = list(AUTO_RULES)
    lines = [
        "WSS relative L2 error with alpha and beta from the discrepancy principle, from the balancing "
        "principle, and with the fixed default alpha and the balancing beta, against the oracle over the "
        "alpha-beta grid (truth known); mean over 3 seeds, ratio = worst seed. The paper's velocity basis "
        "(--near-wall off) throughout.",
        "",
        "| phantom | h [mm] | SNR | "
        + " | ".join(names)
        + " | oracle | "
        + " | ".join(f"{k} / oracle" for k in names)
        + " | within 1.25x ("
        + ", ".join(names)
        + ") |",
        "|---|---|---|" + "---|" * (2 * len(names) + 2),
    ]
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            for snr in (10.0, 25.0, 50.0):
                errs = {k: [] for k in names}
                e_or = []
                for seed in range(3):
                    acq, truth = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
                    for k in names:
                        errs[k].append(metrics.compare_slice(reconstruct(acq, AUTO_RULES[k])[0], truth).wss_rel_l2)
                    e_or.append(oracle_wss_error(acq, truth))
                ratio = {k: max(x / y for x, y in zip(v, e_or)) for k, v in errs.items()}
                ok = ", ".join("yes" if ratio[k] <= TARGET_ORACLE_RATIO else "no" for k in names)
                lines.append(
                    f"| {case} | {h:g} | {snr:g} | "
                    + " | ".join(f"{np.mean(v):.1%}" for v in errs.values())
                    + f" | {np.mean(e_or):.1%} | "
                    + " | ".join(f"{r:.2f}" for r in ratio.values())
                    + f" | {ok} |"
                )
                print(lines[-1], file=sys.stderr, flush=True)
    write_report(args.out, "accuracy_auto.md", lines)


UNSEEN_CASES = ("manufactured", "fourier", "circle")
UNSEEN_SEEDS = (31, 32, 33)  # used by no other study or test


def unseen_study(args) -> None:
    """The default (balancing) beta against the former fixed beta 5e-8 on the other phantoms (kappa was set on
    laminar and turbulent; the fixed beta was chosen on manufactured and fourier among others)."""
    lines = [
        "WSS relative L2 error, default options (balancing beta) against the fixed beta 5e-8; mean (max) over "
        f"seeds {', '.join(map(str, UNSEEN_SEEDS))}.",
        "",
        "| phantom | h [mm] | SNR | balancing beta (default) | fixed beta 5e-8 |",
        "|---|---|---|---|---|",
    ]
    for case in UNSEEN_CASES:
        for h in (float(x) for x in args.h.split(",")):
            for snr in (10.0, 25.0):
                e = {"balance": [], "fixed": []}
                for seed in UNSEEN_SEEDS:
                    acq, truth = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
                    for rule, v in e.items():
                        res = reconstruct(
                            acq, ReconstructionOptions(uncertainty=False, choice=ChoiceOptions(beta_rule=rule))
                        )[0]
                        v.append(metrics.compare_slice(res, truth).wss_rel_l2)
                lines.append(
                    f"| {case} | {h:g} | {snr:g} | "
                    + " | ".join(f"{np.mean(v):.1%} ({max(v):.1%})" for v in e.values())
                    + " |"
                )
                print(lines[-1], file=sys.stderr, flush=True)
    write_report(args.out, "accuracy_unseen.md", lines)


def main(argv=None):
    p = study_parser(__doc__, seeds=5, h="1.5,1.0,0.6,0.3")
    p.add_argument("--snr", type=float, default=25.0)
    p.add_argument("--auto", action="store_true", help="auto vs oracle parameters instead (see above)")
    p.add_argument(
        "--unseen",
        action="store_true",
        help="default vs fixed beta on the manufactured, fourier and circle phantoms instead (see above)",
    )
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    if args.auto:
        auto_study(args)
        return
    if args.unseen:
        unseen_study(args)
        return
    options = ReconstructionOptions()
    rows = []
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            errs = []
            t0 = time.perf_counter()
            for seed in range(args.seeds):
                acq, truth = phantoms.make_phantom(case, h_mm=h, snr=args.snr, seed=seed)
                res = reconstruct(acq, options)[0]
                e = metrics.compare_slice(res, truth)
                errs.append((e.radius_rel_l2, e.wss_rel_l2, e.mean_wss_rel, res.converged))
            e = np.array(errs, dtype=float)
            rows.append(
                {
                    "case": case,
                    "h_mm": h,
                    "snr": args.snr,
                    "seeds": args.seeds,
                    "radius_err_mean": e[:, 0].mean(),
                    "radius_err_max": e[:, 0].max(),
                    "wss_err_mean": e[:, 1].mean(),
                    "wss_err_max": e[:, 1].max(),
                    "mean_wss_err_mean": e[:, 2].mean(),
                    "mean_wss_err_absmax": np.abs(e[:, 2]).max(),
                    "all_converged": bool(e[:, 3].all()),
                }
            )
            print(f"{case} h={h}: done in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    with open(os.path.join(args.out, "accuracy.csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = [
        f"SNR {args.snr:g}, {args.seeds} seeds per row, default options; mean (max) over seeds.",
        "",
        "| phantom | h [mm] | radius rel. L2 err | WSS rel. L2 err | mean-WSS err (mean, max abs) | targets met* |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        ok = r["radius_err_max"] <= TARGET_RADIUS
        if r["case"] == "laminar":
            ok = ok and r["wss_err_max"] <= TARGET_WSS_LAMINAR
        lines.append(
            f"| {r['case']} | {r['h_mm']:g} | {r['radius_err_mean']:.2%} ({r['radius_err_max']:.2%}) | "
            f"{r['wss_err_mean']:.1%} ({r['wss_err_max']:.1%}) | {r['mean_wss_err_mean']:+.1%} "
            f"({r['mean_wss_err_absmax']:.1%}) | {'yes' if ok else 'NO'} |"
        )
    lines += [
        "",
        "*Targets checked on every seed: radius error <= 0.5 % (all phantoms) and WSS error <= 5 % "
        "(laminar only; the issue sets no WSS target for the turbulent phantom).",
    ]
    write_report(args.out, "accuracy.md", lines)


if __name__ == "__main__":
    main()
