#!/usr/bin/env python
"""Time and peak memory of one slice's reconstruction as the options that scale the problem grow.

The checks of ``wss_nlp.pipeline.limits`` refuse options that would not fit in memory and ask for
``--allow-large`` above a time limit, from an estimate made before any work. This script measures what the
estimate predicts: each row reconstructs one seeded phantom slice (circle, h = 1 mm, SNR 25, seed 100, the
default options with the band) in a fresh process with one option changed (``--degree``, ``--angular-order``,
``--n-fourier``, ``--quad-order``, ``--n-phi``), and reports the seconds, the peak resident memory
(``ru_maxrss``) and the estimate of :func:`wss_nlp.pipeline.limits.reconstruction_cost` next to them. A second
table measures what the smallest degrees cost in accuracy (the reason for
:data:`wss_nlp.pipeline.limits.MIN_DEGREE`): the WSS error by ``--degree`` on three phantoms (h = 1 mm, SNR 25,
seed 300). Writes ``scripts/results/option_costs.md``.

    python scripts/option_costs.py [--quick]

About 15 minutes on 2 cores (``--quick``: four rows of the first table).
"""

import argparse
import json
import os
import subprocess
import sys

from _report import RESULTS, write_report

CHILD = """
import json, resource, sys, time
from wss_nlp.synthetic import phantoms
from wss_nlp.app.cli.arguments import options_from_args
from wss_nlp.app.cli.parser import build_parser
from wss_nlp.pipeline import reconstruct
from wss_nlp.pipeline import limits
extra = sys.argv[1:]
acq, _ = phantoms.make_phantom("circle", h_mm=1.0, snr=25, seed=100)
args = build_parser().parse_args(["reconstruct", "in.h5", "-o", "out.h5", *extra])
options = options_from_args(args)
estimate = limits.reconstruction_cost(options, acq.magnitude.shape)
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
t0 = time.perf_counter()
reconstruct(acq, options)
seconds = time.perf_counter() - t0
print(json.dumps({"base": base, "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "s": seconds,
                  "est_s": estimate.seconds, "est_mb": estimate.memory_bytes / 2**20}))
"""

ROWS = [
    [],
    ["--degree", "30"],
    ["--degree", "45"],
    ["--degree", "60"],
    ["--angular-order", "20"],
    ["--n-fourier", "16"],
    ["--n-fourier", "32"],
    ["--n-fourier", "48"],
    ["--quad-order", "8"],
    ["--quad-order", "12"],
    ["--n-phi", "3600"],
    ["--n-phi", "36000"],
]
QUICK = [[], ["--degree", "45"], ["--n-fourier", "32"], ["--n-phi", "36000"]]


def measure(extra: list[str]) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, *extra], check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def degree_table() -> list[str]:
    """WSS relative L2 error and mean WSS error by Zernike degree (default options otherwise, no band)."""
    from wss_nlp.analysis import metrics
    from wss_nlp.models.velocity import VelocityOptions
    from wss_nlp.pipeline import ReconstructionOptions, reconstruct
    from wss_nlp.synthetic import phantoms

    degrees = (0, 1, 2, 3, 4, 6, 10, 20)
    lines = [
        "",
        "WSS relative L2 error (and mean WSS error) by `--degree`, h = 1 mm, SNR 25, seed 300, default options "
        "otherwise (no band); * = flagged SUSPECT:",
        "",
        "| phantom | " + " | ".join(f"degree {d}" for d in degrees) + " |",
        "|---|" + "---|" * len(degrees),
    ]
    for case in ("circle", "laminar", "manufactured"):
        acq, truth = phantoms.make_phantom(case, h_mm=1.0, snr=25, seed=300)
        cells = []
        for d in degrees:
            r = reconstruct(acq, ReconstructionOptions(uncertainty=False, velocity=VelocityOptions(degree=d)))[0]
            e = metrics.compare_slice(r, truth)
            flag = "*" if r.screen.get("suspect") else ""
            cells.append(f"{e.wss_rel_l2:.1%} ({e.mean_wss_rel:+.1%}){flag}")
        lines.append(f"| {case} | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    return lines


REFUSED = [["--degree", "1000"], ["--n-fourier", "500"], ["--n-phi", "1e8"], ["--quad-order", "100"],
           ["--degree", "60", "--angular-order", "60"]]  # fmt: skip


def estimate_table() -> list[str]:
    """What the checks estimate, and decide, for the values issue 42 found hanging or exhausting memory."""
    from wss_nlp.app.cli.arguments import options_from_args
    from wss_nlp.app.cli.parser import build_parser
    from wss_nlp.pipeline import limits
    from wss_nlp.synthetic import phantoms

    acq, _ = phantoms.make_phantom("circle", h_mm=1.0, snr=25, seed=100)
    lines = [
        "",
        f"Estimates on the same slice for options that scale the problem far (limits: {limits.TIME_LIMIT_S:g} s a "
        "slice without --allow-large, the memory available):",
        "",
        "| options | estimate [s] | estimate [GB] |",
        "|---|---|---|",
    ]
    for extra in REFUSED:
        o = options_from_args(build_parser().parse_args(["reconstruct", "in.h5", "-o", "out.h5", *extra]))
        c = limits.reconstruction_cost(o, acq.magnitude.shape)
        lines.append(f"| {' '.join(extra)} | {c.seconds:.3g} | {c.memory_bytes / 2**30:.3g} |")
    return lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    lines = [
        "One slice (circle, h = 1 mm, SNR 25, seed 100; default options with the band), each row in a fresh "
        f"process on {os.cpu_count()} cores shared with other work; `python scripts/option_costs.py`. "
        "'estimate': `wss_nlp.pipeline.limits.reconstruction_cost` (what the checks before any work use).",
        "",
        "| options | seconds | estimate [s] | peak [MB] | added [MB] | estimate [MB] |",
        "|---|---|---|---|---|---|",
    ]
    for extra in QUICK if args.quick else ROWS:
        r = measure(extra)
        lines.append(
            f"| {' '.join(extra) or 'defaults'} | {r['s']:.1f} | {r['est_s']:.1f} | {r['peak']:.0f} | "
            f"{r['peak'] - r['base']:.0f} | {r['est_mb']:.0f} |"
        )
        print(lines[-1], flush=True)
    lines += estimate_table()
    if not args.quick:
        lines += degree_table()
    write_report(args.out, "option_costs.md", lines)


if __name__ == "__main__":
    main()
