#!/usr/bin/env python
"""A/B timing of two checkouts of wss-nlp on the same cases, alternating in one run (machines are noisy).

``python scripts/bench_ab.py --a OLD_CHECKOUT --b NEW_CHECKOUT [--repeats 5]`` runs every case of :data:`CASES`
in a fresh interpreter per checkout and repeat, A then B then A ..., timing the reconstruction only (imports,
phantom building and the first, warming solve excluded: each run reconstructs the case twice and times the
second), and writes the medians and the B/A ratio to ``scripts/results/bench_ab.md``. Each run imports the
package by its old top-level names (``wss_nlp.phantoms``, ``wss_nlp.reconstruct``), which both versions have.
Made for issue 37 (the one-driver restructuring must keep the speed within 5 %).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

from _report import write_report

#: name -> (phantom call, options call): old top-level names, which every version since 0.1 imports.
CASES = {
    "laminar slice h=1.0 (band)": ('phantoms.make_phantom("laminar", 1.0, 25, 11)', "O()"),
    "turbulent slice h=0.3 (band)": ('phantoms.make_phantom("turbulent", 0.3, 25, 11)', "O()"),
    "coupled turbulent h=0.6": ('phantoms.make_phantom("turbulent", 0.6, 25, 12)', 'O(method="coupled")'),
    "k-space laminar h=1.0": (
        'phantoms.make_phantom("laminar", 1.0, 25, 13, psf=kspace.PSF("hamming", (2.0, 2.0)))',
        "O()",
    ),
    "stack of 6, tapered h=1.0": ('phantoms.make_stack("tapered", 6, 1.0, 2.0, 25, 14)', "O()"),
}

RUN = """
import json, sys, time, warnings
warnings.simplefilter("ignore")
from wss_nlp import phantoms, kspace
from wss_nlp.reconstruct import ReconstructionOptions as O, reconstruct
acq = {acq}[0]
options = {options}
reconstruct(acq, options)
t0, c0 = time.perf_counter(), time.process_time()
reconstruct(acq, options)
print(json.dumps([time.perf_counter() - t0, time.process_time() - c0]))
"""


def time_case(checkout: str, acq: str, options: str) -> list[float]:
    """``[wall seconds, CPU seconds]`` of the second reconstruction of the case in a fresh interpreter."""
    env = dict(os.environ, PYTHONPATH=os.path.abspath(checkout), OMP_NUM_THREADS="1")
    out = subprocess.run(
        [sys.executable, "-c", RUN.format(acq=acq, options=options)], env=env, check=True, capture_output=True,
        text=True,
    )  # fmt: skip
    return [float(t) for t in json.loads(out.stdout.strip().splitlines()[-1])]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--a", required=True, help="the reference checkout (e.g. a git worktree of the old commit)")
    p.add_argument("--b", required=True, help="the checkout to compare")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--label-a", default="A")
    p.add_argument("--label-b", default="B")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    p.add_argument("--only", default="", help="run only the cases whose name contains this text")
    args = p.parse_args()
    lines = [
        "# A/B timing of two checkouts (scripts/bench_ab.py)",
        "",
        f"A = {args.label_a}, B = {args.label_b}; medians of {args.repeats} fresh-process runs each, A and B "
        "alternating; the second reconstruction of each run is timed (seconds, 1 BLAS thread). CPU seconds of the "
        "process are the fairer measure on a shared machine (another job's load lengthens wall time, not CPU time).",
        "",
        "| case | A wall [s] | B wall [s] | B / A wall | A CPU [s] | B CPU [s] | B / A CPU |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, (acq, options) in CASES.items():
        if args.only not in name:
            continue
        times: dict = {"a": [], "b": []}
        for _ in range(args.repeats):
            for key in ("a", "b"):
                times[key].append(time_case(getattr(args, key), acq, options))
        (aw, ac), (bw, bc) = ([statistics.median(t[i] for t in times[k]) for i in (0, 1)] for k in ("a", "b"))
        lines.append(f"| {name} | {aw:.3f} | {bw:.3f} | {bw / aw:.3f} | {ac:.3f} | {bc:.3f} | {bc / ac:.3f} |")
        print(lines[-1], flush=True)
    write_report(args.out, "bench_ab.md", lines)


if __name__ == "__main__":
    main()
