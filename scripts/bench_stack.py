#!/usr/bin/env python
"""Cost of z-regularized stacks: Kaczmarz sweeps for 10, 50 and 100 slices, and the coupled NLP for small stacks.

Tapered-tube phantom (``phantoms.make_stack``), h = 1 mm, slices 2 mm apart,
SNR 25, default options (z smoothing over one slice spacing, dephasing pass on) with the
uncertainty band (``wss_nlp.uncertainty.stack_band``), timed apart from the solve. One run
measures every row, so the ratios (seconds per slice) are comparable.
Issue 6 targets: Kaczmarz cost linear in the number of slices, 100 slices
in under 60 s on 2 cores. Writes ``scripts/results/bench_stack.md``.

    python scripts/bench_stack.py [--sizes 10,50,100] [--coupled 4,8]
"""

import argparse
import time
from dataclasses import replace

from _report import RESULTS, write_report
from wss_nlp.pipeline import driver
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.synthetic import phantoms
from wss_nlp.models import stack
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

TARGET_100_S = 60.0  # issue 6: 100 slices at h = 1 mm in under 60 s on 2 cores


def run(acq, strategy, method="decoupled"):
    t0 = time.perf_counter()
    _, info = driver.reconstruct_stack(
        acq,
        ReconstructionOptions(method=method, choice=ChoiceOptions(beta_rule="fixed")),
        stack.StackOptions(strategy=strategy),
    )
    total = time.perf_counter() - t0
    band = info.seconds.get("uncertainty", 0.0)
    return total - band, band, info


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="10,50,100")
    p.add_argument("--coupled", default="4,8")
    p.add_argument("--method-coupled", default="5", help="slices of the coupled-method rows (h = 1.5 mm)")
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    lines = [
        "Tapered-tube stack, h = 1 mm, slices 2 mm apart, SNR 25, z smoothing over one slice spacing; "
        "seconds on this machine (2 cores), one run; total = the solve without the band.",
        "",
        "| slices | strategy | total [s] | per slice [s] | build [s] | geometry [s] | velocity [s] | "
        "dephasing check [s] | sweeps (geometry, velocity; per pass) | converged | target | band [s] | "
        "band / solve |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    rows = [(int(n), "coupled") for n in args.coupled.split(",") if n] + [
        (int(n), "kaczmarz") for n in args.sizes.split(",") if n
    ]
    for n, strategy in rows:
        acq, _ = phantoms.make_stack("tapered", nz=n, h_mm=1.0, spacing_mm=2.0, snr=25, seed=0)
        sec, band, info = run(acq, strategy)
        t = info.seconds
        sweeps = f"{info.sweeps.get('geometry', '-')}, {info.sweeps.get('velocity', '-')}"
        target = ("yes" if sec < TARGET_100_S else "NO") if n == 100 and strategy == "kaczmarz" else ""
        lines.append(
            f"| {n} | {strategy} | {sec:.1f} | {sec / n:.3f} | {t.get('geometry_build', 0):.1f} | "
            f"{t.get('geometry', 0):.1f} | {t.get('velocity', 0):.1f} | {t.get('dephasing_check', 0):.1f} | "
            f"{sweeps} | {info.converged} | "
            f"{target} | {band:.1f} | {band / sec:.2f} |"
        )
        print(f"{n} {strategy}: {sec:.1f} s + band {band:.1f} s", flush=True)
    lines += [
        "",
        "The coupled method (`--method coupled`, one NLP over the segment's walls and velocities after the "
        "decoupled solve) on the curved-tube stack, h = 1.5 mm, slices 2 mm apart, SNR 15, and slice by slice "
        "(`--z-smoothing 0`) for reference:",
        "",
        "| slices | z-regularized: total [s] | of which the coupled NLP [s] | band [s] | slice by slice: total [s] |",
        "|---|---|---|---|---|",
    ]
    for n in (int(x) for x in args.method_coupled.split(",") if x):
        acq, _ = phantoms.make_stack("curved", nz=n, h_mm=1.5, spacing_mm=2.0, snr=15, seed=3)
        sec, band, info = run(acq, "auto", "coupled")
        t0 = time.perf_counter()
        opts = ReconstructionOptions(method="coupled", uncertainty=False, choice=ChoiceOptions(beta_rule="fixed"))
        reconstruct(acq, replace(opts, stack=stack.StackOptions(z_smoothing_mm=0.0)))
        alone = time.perf_counter() - t0
        lines.append(f"| {n} | {sec:.1f} | {info.seconds.get('coupled', 0):.1f} | {band:.1f} | {alone:.1f} |")
        print(lines[-1], flush=True)
    write_report(args.out, "bench_stack.md", lines)


if __name__ == "__main__":
    main()
