#!/usr/bin/env python
"""Cohorts on more than one core: ``wss-nlp batch`` over 20 small exams on a Dask LocalCluster of 2 workers
against 1 worker, and ``reconstruct --workers 2`` on a 20-slice stack of independent slices against serial.

Exams: single slices (circle and laminar phantoms alternating, h = 1.5 mm, SNR 25, seeds 0-19, default options,
band included). Each batch is timed whole, as a user waits for it: the cluster's start, every worker's first
imports and solver builds, the exams, the summary and the report; the two worker counts alternate over
``--repeat`` rounds in this one run, so the ratio is comparable. The stack: the tapered phantom, 20 slices 2 mm
apart, h = 1.5 mm, ``--z-smoothing 0`` (independent slices), timed serially in this process (warm) and with 2
local worker processes (their start included, as ``reconstruct --workers 2`` pays it); the two results are
compared bit for bit. The machine's load average is printed: on a shared machine a second worker gets less
than a second core. Writes ``scripts/results/bench_batch.md``.

    python scripts/bench_batch.py [--repeat 2]
"""

import argparse
import os
import tempfile
import time

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.app import executor
from wss_nlp.app.batch import run_batch
from wss_nlp.io import files as wio
from wss_nlp.models.stack import StackOptions
from wss_nlp.pipeline import ReconstructionOptions, driver, reconstruct
from wss_nlp.synthetic import phantoms


def _cohort(folder: str, n: int) -> str:
    lines = ["id,input"]
    for k in range(n):
        acq, _ = phantoms.make_phantom(("circle", "laminar")[k % 2], h_mm=1.5, snr=25, seed=k)
        wio.write_acquisition(os.path.join(folder, f"e{k:02d}.h5"), acq)
        lines.append(f"e{k:02d},e{k:02d}.h5")
    path = os.path.join(folder, "manifest.csv")
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    return path


def _batch_seconds(manifest: str, workers: int, folder: str) -> tuple[float, float]:
    """Wall seconds of a whole batch, and the exams' own seconds summed (what the workers spent on exams)."""
    out = tempfile.mkdtemp(dir=folder)
    t0 = time.perf_counter()
    s = run_batch(manifest, out, executor.Backend("localcluster", workers), vtk=False, stream=open(os.devnull, "w"))
    seconds = time.perf_counter() - t0
    assert s.ran == s.total and s.failed == 0, s
    return seconds, float(sum(r["seconds"] for r in s.rows))


def _same(a, b) -> bool:
    return all(
        np.array_equal(x.wss.tau, y.wss.tau)
        and np.array_equal(x.wss.tau_std, y.wss.tau_std)
        and np.array_equal(x.geometry.coefficients, y.geometry.coefficients)
        and np.array_equal(x.velocity.coefficients, y.velocity.coefficients)
        and x.warnings == y.warnings
        for x, y in zip(a, b)
    )


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--exams", type=int, default=20)
    p.add_argument("--slices", type=int, default=20)
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    lines = [
        f"`python scripts/bench_batch.py --repeat {args.repeat}`: seconds of wall time on this machine "
        f"({os.cpu_count()} cores, shared: load average {os.getloadavg()[0]:.1f} at the start); median of "
        f"{args.repeat} round(s), the settings alternating.",
        "",
        "| what | 1 worker | 2 workers | speed-up |",
        "|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory() as folder:
        manifest = _cohort(folder, args.exams)
        t: dict = {1: [], 2: []}
        busy: dict = {1: [], 2: []}
        for r in range(args.repeat):
            for w in (1, 2) if r % 2 == 0 else (2, 1):
                wall, exams = _batch_seconds(manifest, w, folder)
                t[w].append(wall)
                busy[w].append(exams / wall)
                print(f"batch, {w} worker(s): {wall:.1f} s, exams' own seconds / wall {exams / wall:.2f}", flush=True)
        one, two = float(np.median(t[1])), float(np.median(t[2]))
        lines.append(
            f"| `wss-nlp batch`, {args.exams} single-slice exams (LocalCluster, start included) | {one:.1f} | "
            f"{two:.1f} | {one / two:.2f}x |"
        )
        lines.append(
            f"| the same: exams' own seconds summed over the wall time (exams running at once) | "
            f"{np.median(busy[1]):.2f} | {np.median(busy[2]):.2f} | |"
        )

    acq, _ = phantoms.make_stack("tapered", nz=args.slices, h_mm=1.5, spacing_mm=2.0, snr=25, seed=0)
    options = ReconstructionOptions(stack=StackOptions(z_smoothing_mm=0.0))
    reconstruct(phantoms.make_phantom("laminar", h_mm=1.5, snr=25, seed=99)[0], options)  # this process warm
    s: dict = {1: [], 2: [], "warm": []}
    same = True
    for r in range(args.repeat):
        for w in (1, 2) if r % 2 == 0 else (2, 1):
            t0 = time.perf_counter()
            if w == 1:
                serial = reconstruct(acq, options)
                s[1].append(time.perf_counter() - t0)
            else:
                with executor.Executor(executor.backend(workers=2)) as ex, driver.segments_in_parallel(ex.map):
                    parallel = reconstruct(acq, options)
                    s[2].append(time.perf_counter() - t0)
                    t1 = time.perf_counter()  # again on the started workers: the solves alone
                    again = reconstruct(acq, options)
                    s["warm"].append(time.perf_counter() - t1)
                same = same and _same(parallel, again)
            print(f"stack, {w} worker(s): {s[w][-1]:.1f} s" + (f", started: {s['warm'][-1]:.1f} s" if w == 2 else ""))
        same = same and _same(serial, parallel)
    one, two, warm = float(np.median(s[1])), float(np.median(s[2])), float(np.median(s["warm"]))
    lines.append(
        f"| `reconstruct --workers 2`, {args.slices}-slice stack, independent slices (serial warm; workers' start "
        f"included) | {one:.1f} | {two:.1f} | {one / two:.2f}x |"
    )
    lines.append(
        f"| the same on workers already started (the solves alone) | {one:.1f} | {warm:.1f} | {one / warm:.2f}x |"
    )
    lines += [
        "",
        f"Stack results with 2 workers bit for bit those of the serial run: {'yes' if same else 'NO'} (WSS, its "
        "band, radius and velocity coefficients, warnings of every slice).",
    ]
    write_report(args.out, "bench_batch.md", lines)


if __name__ == "__main__":
    main()
