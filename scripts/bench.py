#!/usr/bin/env python
"""Seconds per slice for each stage of the decoupled reconstruction.

Laminar phantom at h in {1.5, 1.0, 0.6, 0.3} mm (the 0.3 mm slice has
about 130 x 130 voxels). One warm-up slice builds and caches the velocity
basis (reported separately); the table gives the median of ``--repeat``
slices with different noise. Writes ``scripts/results/bench.md``.

    python scripts/bench.py [--repeat 5]
"""

import argparse
import os
import time

import numpy as np

from _report import write_report
from wss_nlp import phantoms
from wss_nlp import velocity_basis as vb
from wss_nlp.reconstruct import ReconstructionOptions, reconstruct

TARGET_S = 2.0  # issue: a 0.3 mm slice in under 2 s in total on 2 cores

STAGES = ("preprocess", "geometry", "velocity", "dephasing_check", "dephasing_pass", "wss")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--case", default="laminar")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    options = ReconstructionOptions()
    vb.make_basis.cache_clear()
    t0 = time.perf_counter()
    options.velocity.make_basis()
    basis_s = time.perf_counter() - t0
    lines = [
        f"Phantom '{args.case}', SNR 25, median over {args.repeat} slices; seconds per slice on this machine "
        f"({os.cpu_count()} cores). Building the default velocity basis once per process: {basis_s:.2f} s.",
        "",
        "| h [mm] | voxels | " + " | ".join(STAGES) + " | total | target |",
        "|---|---|" + "---|" * (len(STAGES) + 2),
    ]
    for h in (1.5, 1.0, 0.6, 0.3):
        times = []
        for seed in range(args.repeat):
            acq, _ = phantoms.make_phantom(args.case, h_mm=h, snr=25, seed=100 + seed)
            res = reconstruct(acq, options)[0]
            times.append([res.seconds.get(s, 0.0) for s in STAGES])  # the dephasing pass runs only when needed
        med = np.median(np.array(times), axis=0)
        total = float(med.sum())
        target = ("yes" if total < TARGET_S else "NO") if h == 0.3 else ""
        ny, nx = acq.magnitude.shape[1:]
        lines.append(f"| {h:g} | {nx} x {ny} | " + " | ".join(f"{t:.3f}" for t in med) + f" | {total:.2f} | {target} |")
    write_report(args.out, "bench.md", lines)


if __name__ == "__main__":
    main()
