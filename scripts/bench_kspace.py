#!/usr/bin/env python
"""Cost of the k-space measurement model against the box model on the same slice, in one run.

Issue 14's target: a slice within 2x the box model's time. The laminar phantom acquired in k-space
(Hamming filter, no zero-filling), SNR 25, seed 0, at each h: median wall time of ``reconstruct`` with
``--acquisition box`` and with ``--acquisition kspace`` (default options otherwise, no band: the target is
the solve's), their ratio, and the k-space slice's split into geometry, velocity and dephasing passes. Writes
``scripts/results/bench_kspace.md``.

    python scripts/bench_kspace.py [--h 1.5,1.0,0.6,0.3] [--runs 3] [--case laminar] [--method coupled]

With ``--method coupled`` both columns are the coupled method (box or k-space model), the split adds the
coupled solve's seconds; ``scripts/results/bench_kspace_coupled.md``.
"""

import argparse
import sys
import time

import numpy as np

from _report import RESULTS, write_report
from bench import fresh
from wss_nlp.models import kspace
from wss_nlp.synthetic import phantoms as ph
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

TARGET_RATIO = 2.0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--h", default="1.5,1.0,0.6,0.3")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--case", default="laminar")
    p.add_argument("--method", choices=("decoupled", "coupled"), default="decoupled")
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    psf = kspace.PSF("hamming", (1.0, 1.0))
    lines = [
        f"Phantom '{args.case}' acquired in k-space (Hamming, F = 1), SNR 25, seed 0; medians of {args.runs} "
        f"runs, both models in one run; no uncertainty band; method {args.method}.",
        "Made by `python scripts/bench_kspace.py" + "".join(f" {a}" for a in sys.argv[1:]) + "`.",
        "",
        f"| h [mm] | box [s] | k-space [s] | ratio (target <= {TARGET_RATIO:g}) | k-space geometry / velocity / "
        "dephasing" + (" / coupled" if args.method == "coupled" else "") + " [s] | passes box / k-space | "
        "smallest predicted magnitude factor box / k-space (a pass below 0.99) |",
        "|---|---|---|---|---|---|---|",
    ]
    for h in (float(v) for v in args.h.split(",")):
        acq, _ = ph.make_phantom(args.case, h_mm=h, snr=25.0, seed=0, psf=psf)
        times: dict = {"box": [], "kspace": []}
        split: dict = {}
        for _ in range(args.runs):
            for model in times:
                how = kspace.AcquisitionOptions(model, "hamming")
                options = ReconstructionOptions(method=args.method, uncertainty=False, acquisition=how)
                fresh()  # every timing builds its solvers, as a user's first slice does
                t0 = time.perf_counter()
                r = reconstruct(acq, options)[0]
                times[model].append(time.perf_counter() - t0)
                split[model] = (r.seconds, r.dephasing)
        box, ksp = float(np.median(times["box"])), float(np.median(times["kspace"]))
        sec = split["kspace"][0]
        deph = sec.get("dephasing_check", 0.0) + sec.get("dephasing_pass", 0.0)
        passes = " / ".join(str(split[m][1].passes or 0) for m in times)
        factors = " / ".join(f"{split[m][1].min_factor:.3f}" for m in times)
        lines.append(
            f"| {h:g} | {box:.2f} | {ksp:.2f} | {ksp / box:.1f}{'' if ksp / box <= TARGET_RATIO else ' (missed)'} | "
            f"{sec['geometry']:.2f} / {sec['velocity']:.2f} / {deph:.2f}"
            + (f" / {sec['coupled']:.2f}" if "coupled" in sec else "")
            + f" | {passes} | {factors} |"
        )
    write_report(args.out, "bench_kspace.md" if args.method == "decoupled" else "bench_kspace_coupled.md", lines)


if __name__ == "__main__":
    main()
