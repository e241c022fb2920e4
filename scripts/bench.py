#!/usr/bin/env python
"""Seconds per slice for each stage of the reconstruction, the band's cost and the coupled method's.

Laminar phantom at h in {1.5, 1.0, 0.6, 0.3} mm (the 0.3 mm slice has
about 130 x 130 voxels). One warm-up slice builds and caches the velocity
basis (reported separately); the table gives the median of ``--repeat``
slices with different noise, each timed as a user's first slice (the
geometry solvers are built inside the timing). "solve" is the decoupled
reconstruction without the band (issue 19: at most 0.25 s at every h);
"band" the sensitivities and band on top of it (issue 19: at most one
solve, and solve + band at most 0.5 s); "coupled" a whole ``--method
coupled`` run without the band, including its decoupled start (issue 19:
at most 3x the decoupled time at h = 0.3 mm). "off" is the same solve with
``--near-wall off`` (the paper's basis alone; issue 13: the default with
its near-wall choice within 1.5x of it). The ratios come from the same
slices in one run. Writes ``scripts/results/bench.md`` (``--name`` for
another file, e.g. with ``--case turbulent``).

    python scripts/bench.py [--repeat 5] [--case laminar] [--name bench.md]
"""

import argparse
import gc
import os
import time
from dataclasses import replace

import numpy as np

from _report import write_report
from wss_nlp.models import geometry as geo
from wss_nlp.synthetic import phantoms
from wss_nlp.core import velocity_basis as vb
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

TARGET_S = 0.25  # issue 19: a default slice without the band in at most 0.25 s at every h
TARGET_WITH_BAND = 0.5  # issue 19: ... and with the band in at most 0.5 s
TARGET_BAND = 1.0  # issue 19: the band within one solve
TARGET_COUPLED = 3.0  # issue 19: coupled at h = 0.3 mm within 3x the decoupled time
TARGET_OFF = 1.5  # issue 13: the near-wall choice within 1.5x the plain solve

STAGES = ("preprocess", "geometry", "velocity", "dephasing_check", "dephasing_pass", "wss")


def fresh() -> None:
    """Every timing builds its solvers, as a user's first slice does, and does not collect the previous run's
    garbage (CasADi callbacks sit in reference cycles that only the cyclic collector frees)."""
    geo.clear_solvers()
    gc.collect()


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--case", default="laminar")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    p.add_argument("--name", default="bench.md")
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
        "| h [mm] | voxels | " + " | ".join(STAGES) + " | solve (<= 0.25) | off | solve / off (<= 1.5) | band | "
        "solve + band (<= 0.5) | band / solve (<= 1) | coupled | coupled / solve (<= 3 at 0.3 mm) |",
        "|---|---|" + "---|" * (len(STAGES) + 8),
    ]
    coupled = ReconstructionOptions(method="coupled", uncertainty=False)
    plain = ReconstructionOptions(uncertainty=False, velocity=replace(options.velocity, near_wall="off"))
    for h in (1.5, 1.0, 0.6, 0.3):
        times, band, coup, off = [], [], [], []
        for seed in range(args.repeat):
            acq, _ = phantoms.make_phantom(args.case, h_mm=h, snr=25, seed=100 + seed)
            fresh()
            res = reconstruct(acq, options)[0]
            times.append([res.seconds.get(s, 0.0) for s in STAGES])  # the dephasing pass runs only when needed
            band.append(res.seconds.get("uncertainty", np.nan))
            fresh()
            off.append(sum(reconstruct(acq, plain)[0].seconds.get(s, 0.0) for s in STAGES))
            fresh()
            t0 = time.perf_counter()
            reconstruct(acq, coupled)
            coup.append(time.perf_counter() - t0)
        med = np.median(np.array(times), axis=0)
        total = float(med.sum())
        b, c, o = float(np.median(band)), float(np.median(coup)), float(np.median(off))

        def mark(ok: bool) -> str:
            return "" if ok else " (over)"

        coup_ok = mark(c / total <= TARGET_COUPLED) if h == 0.3 else ""
        ny, nx = acq.magnitude.shape[1:]
        lines.append(
            f"| {h:g} | {nx} x {ny} | "
            + " | ".join(f"{t:.3f}" for t in med)
            + f" | {total:.2f}{mark(total <= TARGET_S)} | {o:.2f} | {total / o:.2f}{mark(total / o <= TARGET_OFF)} | "
            f"{b:.2f} | {total + b:.2f}{mark(total + b <= TARGET_WITH_BAND)} | {b / total:.2f}"
            f"{mark(b / total <= TARGET_BAND)} | {c:.2f} | {c / total:.1f}{coup_ok} |"
        )
    write_report(args.out, args.name, lines)


if __name__ == "__main__":
    main()
