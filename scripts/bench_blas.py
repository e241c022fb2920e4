#!/usr/bin/env python
"""Seconds per default slice with the BLAS limited to one thread (the default) and left as it is.

The matrices of one slice are small (about 120 x 120 normal matrices), where a second BLAS thread costs
more in synchronization than it gains. Laminar phantom, SNR 25, default options (band included); both
settings alternate on the same slices in one run, so the ratio is comparable. Writes
``scripts/results/bench_blas.md``.

    python scripts/bench_blas.py [--repeat 5]
"""

import argparse
import os
import time
from dataclasses import replace

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.models import geometry as geo
from wss_nlp.synthetic import phantoms
from wss_nlp.pipeline import ReconstructionOptions, reconstruct


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    one, free = ReconstructionOptions(), replace(ReconstructionOptions(), blas_threads=0)
    reconstruct(phantoms.make_phantom("laminar", h_mm=1.5, snr=25, seed=0)[0], one)  # warm-up: caches, imports
    lines = [
        f"Laminar phantom, SNR 25, default options, median of {args.repeat} slices per row; seconds per slice on "
        f"this machine ({os.cpu_count()} cores); `python scripts/bench_blas.py`.",
        "",
        "| h [mm] | BLAS 1 thread (default) | BLAS as installed | ratio |",
        "|---|---|---|---|",
    ]
    for h in (1.5, 1.0, 0.6, 0.3):
        t = {"one": [], "free": []}
        for seed in range(args.repeat):
            acq, _ = phantoms.make_phantom("laminar", h_mm=h, snr=25, seed=200 + seed)
            for name, opts in (("one", one), ("free", free)) if seed % 2 == 0 else (("free", free), ("one", one)):
                geo.clear_solvers()  # every timing builds its solvers, as a user's first slice does
                t0 = time.perf_counter()
                reconstruct(acq, opts)
                t[name].append(time.perf_counter() - t0)
        a, b = float(np.median(t["one"])), float(np.median(t["free"]))
        lines.append(f"| {h:g} | {a:.2f} | {b:.2f} | {b / a:.2f}x |")
        print(lines[-1], flush=True)
    write_report(args.out, "bench_blas.md", lines)


if __name__ == "__main__":
    main()
