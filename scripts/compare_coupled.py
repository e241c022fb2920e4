#!/usr/bin/env python
"""Coupled vs decoupled reconstruction: accuracy (where the magnitude is poor and where it is good) and cost.

For each phantom, h, SNR and seed, reconstructs with ``--method decoupled``
and ``--method coupled`` (default options otherwise, with the fixed beta 5e-8,
the default when the table was made) and reports the mean
(max) radius and WSS relative L2 errors, the share of seeds on which the
coupled error is smaller, and seconds per slice (the coupled time includes
its decoupled warm start). Writes ``scripts/results/coupled.md``.

    python scripts/compare_coupled.py [--seeds 5] [--snr 6,10,25] [--h 1.5,1.0]   (about 4 minutes)
"""

import sys
import time

import numpy as np

from _report import study_parser, write_report
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.errors import WssNlpError
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

TARGET_TIME_RATIO = 5.0  # issue: the coupled solve at h = 1 mm takes at most 5x the decoupled time


def main(argv=None):
    args = study_parser(__doc__, seeds=5, h="1.5,1.0", snr="6,10,25").parse_args(argv)
    methods = ("decoupled", "coupled")
    rows = []
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            for snr in (float(x) for x in args.snr.split(",")):
                err = {m: [] for m in methods}
                sec = {m: [] for m in methods}
                status, failed = [], 0
                for seed in range(args.seeds):
                    acq, truth = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
                    try:
                        out = {}
                        for m in methods:
                            t0 = time.perf_counter()
                            opts = ReconstructionOptions(
                                method=m, uncertainty=False, choice=ChoiceOptions(beta_rule="fixed")
                            )
                            out[m] = (reconstruct(acq, opts)[0], time.perf_counter() - t0)
                    except WssNlpError as exc:  # both methods share the preprocessing; count, report, go on
                        failed += 1
                        print(f"{case} h={h} snr={snr} seed={seed}: {exc}", file=sys.stderr)
                        continue
                    for m, (res, seconds) in out.items():
                        sec[m].append(seconds)
                        e = metrics.compare_slice(res, truth)
                        err[m].append((e.radius_rel_l2, e.wss_rel_l2))
                    status.append(out["coupled"][0].converged)
                if not status:
                    continue
                e = {m: np.array(v) for m, v in err.items()}
                rows.append(
                    (
                        case,
                        h,
                        snr,
                        e,
                        {m: float(np.median(v)) for m, v in sec.items()},
                        f"{sum(status)}/{len(status)}" + (f" ({failed} failed)" if failed else ""),
                    )
                )
                print(f"{case} h={h} snr={snr} done", file=sys.stderr, flush=True)
    lines = [
        f"Default options with the fixed beta 5e-8, {args.seeds} seeds per row; errors mean (max) over seeds; "
        "'better' = share of seeds "
        "on which the coupled error is smaller; seconds: median per slice (coupled includes its decoupled "
        "start); 'converged': coupled solves that converged / seeds reconstructed (seeds whose preprocessing "
        "failed are counted apart).",
        "",
        "| phantom | h [mm] | SNR | radius err decoupled | radius err coupled | better | WSS err decoupled | "
        "WSS err coupled | better | s decoupled | s coupled | ratio | coupled converged |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case, h, snr, e, s, ok in rows:
        d, c = e["decoupled"], e["coupled"]
        ratio = s["coupled"] / s["decoupled"]
        lines.append(
            f"| {case} | {h:g} | {snr:g} | {d[:, 0].mean():.2%} ({d[:, 0].max():.2%}) | "
            f"{c[:, 0].mean():.2%} ({c[:, 0].max():.2%}) | {np.mean(c[:, 0] < d[:, 0]):.0%} | "
            f"{d[:, 1].mean():.1%} ({d[:, 1].max():.1%}) | {c[:, 1].mean():.1%} ({c[:, 1].max():.1%}) | "
            f"{np.mean(c[:, 1] < d[:, 1]):.0%} | {s['decoupled']:.2f} | {s['coupled']:.2f} | {ratio:.1f}"
            f"{'' if h != 1.0 else (' (target <= 5)' if ratio <= TARGET_TIME_RATIO else ' (target 5 MISSED)')} | "
            f"{ok} |"
        )
    write_report(args.out, "coupled.md", lines)


if __name__ == "__main__":
    main()
