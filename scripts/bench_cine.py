#!/usr/bin/env python
"""Cost of a cine slice: 20 frames against one slice, in one run (issue 15 target: within 10x one slice).

The Womersley phantom (``wss_nlp.synthetic.pulsatile.make_cine``) at h = 1 mm, SNR 25: the median time of one frame
reconstructed alone (the single-frame pipeline, default options as cine frames get them: plain basis, with
the uncertainty band) against ``wss_nlp.pipeline.cine.reconstruct_cine`` of all frames (the default: frames sharing
one lumen box and its built solvers, warm starts, then the momentum model's fit and choice), and their
ratio; also the cine run without the momentum model (``--cine-model independent``). The geometry solver
cache is cleared before each timing (a user's first series builds them). Writes
``scripts/results/bench_cine.md``.

    python scripts/bench_cine.py [--frames 20] [--h 1.0] [--runs 3] [--clock wall|cpu]

``--clock cpu`` times the process's CPU time instead of the wall clock: on a machine shared with other jobs
(run with OPENBLAS_NUM_THREADS=1, one thread) it is what the run costs on an idle core. Also timed: the cine run
with the Stokes layer from the stated viscosity (``--cine-viscosity stated``), against issue 40's target (20 frames
within 3 s with the viscosity fitted).
"""

import argparse
import sys
import time
from dataclasses import replace

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.pipeline import cine
from wss_nlp.synthetic import pulsatile
from wss_nlp.models import womersley
from wss_nlp.models import geometry as geo
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

TARGET_RATIO = 10.0
TARGET_CINE_S = 3.0  # issue 40: a 20-frame cine slice, the viscosity fitted


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--h", type=float, default=1.0)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--out", default=RESULTS)
    p.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    args = p.parse_args(argv)
    clock = time.perf_counter if args.clock == "wall" else time.process_time
    clock_text = "wall clock" if args.clock == "wall" else "CPU time of the process (one BLAS thread)"
    frames, truth = pulsatile.make_cine(h_mm=args.h, snr=25, seed=0, frames=args.frames)
    options = ReconstructionOptions()
    plain = replace(options, velocity=replace(options.velocity, near_wall="off"))
    independent = replace(options, cine=womersley.CineModelOptions(model="independent"))
    stated = replace(options, cine=womersley.CineModelOptions(viscosity="stated"))
    singles, cines, frames_only, stated_times = [], [], [], []
    for _ in range(args.runs):
        geo.clear_solvers()  # every timing builds its solvers, as a user's first series does
        t0 = clock()
        reconstruct(frames[1], plain)
        singles.append(clock() - t0)
        geo.clear_solvers()
        t0 = clock()
        cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, options)
        cines.append(clock() - t0)
        geo.clear_solvers()
        t0 = clock()
        cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, independent)
        frames_only.append(clock() - t0)
        geo.clear_solvers()
        t0 = clock()
        cine.reconstruct_cine(frames, truth.times_ms, truth.period_ms, stated)
        stated_times.append(clock() - t0)
    one, all_frames = float(np.median(singles)), float(np.median(cines))
    ratio = all_frames / one
    lines = [
        f"Womersley phantom, h = {args.h:g} mm, SNR 25, {args.frames} frames; medians of {args.runs} runs "
        f"(ratios in one run); {clock_text}.",
        "Made by `python scripts/bench_cine.py" + "".join(f" {a}" for a in sys.argv[1:]) + "`.",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| one frame alone [s] | {one:.2f} |",
        f"| {args.frames} frames (cine, viscosity fitted) [s] (target <= {TARGET_CINE_S:g}) | {all_frames:.2f}"
        f"{'' if all_frames <= TARGET_CINE_S else ' (missed)'} |",
        f"| {args.frames} frames, --cine-viscosity stated [s] | {float(np.median(stated_times)):.2f} |",
        f"| ratio (target <= {TARGET_RATIO:g}) | {ratio:.1f}{'' if ratio <= TARGET_RATIO else ' (missed)'} |",
        f"| {args.frames} frames, --cine-model independent [s] | {float(np.median(frames_only)):.2f} |",
        f"| ratio without the momentum model | {float(np.median(frames_only)) / one:.1f} |",
    ]
    write_report(args.out, "bench_cine.md", lines)


if __name__ == "__main__":
    main()
