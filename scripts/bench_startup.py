#!/usr/bin/env python
"""Start-up cost of the command line: ``wss-nlp --help`` and ``import wss_nlp.app.cli``, medians of repeated runs.

Issue 19 target: ``wss-nlp --help`` within 0.5 s. Heavy modules used by one function (scipy.interpolate,
scipy.optimize) are imported where used; the normal CDF comes from scipy.special instead of scipy.stats.
Writes ``scripts/results/bench_startup.md``.

    python scripts/bench_startup.py [--runs 7]
"""

import argparse
import shutil
import subprocess
import sys
import time

import numpy as np

from _report import RESULTS, write_report

TARGET_HELP_S = 0.5


def _median_seconds(cmd: list[str], runs: int) -> float:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=7)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    exe = shutil.which("wss-nlp") or sys.exit("wss-nlp is not installed (pip install -e .)")
    rows = [
        ("python -c pass (interpreter floor)", _median_seconds([sys.executable, "-c", "pass"], args.runs)),
        (
            "python -c 'import wss_nlp.app.cli'",
            _median_seconds([sys.executable, "-c", "import wss_nlp.app.cli"], args.runs),
        ),
        ("wss-nlp --help", _median_seconds([exe, "--help"], args.runs)),
    ]
    lines = [
        f"Median of {args.runs} runs, warm file cache, this machine (2 cores); `python scripts/bench_startup.py`.",
        "",
        "| command | seconds | target |",
        "|---|---|---|",
    ]
    for name, sec in rows:
        target = ("yes" if sec <= TARGET_HELP_S else "NO") + f" (<= {TARGET_HELP_S:g} s)" if "--help" in name else ""
        lines.append(f"| `{name}` | {sec:.2f} | {target} |")
    write_report(args.out, "bench_startup.md", lines)


if __name__ == "__main__":
    main()
