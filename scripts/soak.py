#!/usr/bin/env python
"""Soak test: random valid phantoms through the command line; no run may fail.

Draws ``--n`` phantoms (seeded, ``--seed``): single slices of every phantom
case and of the two-vessel phantom, and small stacks; voxel sizes 0.6-1.5 mm,
SNR 10-40, venc either the default (1.25 x peak) or 0.55-1.5 x the peak
velocity (so about a third of the draws alias), random sub-voxel offsets. Each
goes through ``wss-nlp phantom`` (or the factory, for two vessels) and
``wss-nlp reconstruct`` with default options, in-process (``cli.main``), and
is compared with its truth. Writes ``scripts/results/soak.md``: the failures
(a non-zero exit, or a valid input refused; must be none) and the largest
WSS errors with the warnings their runs printed.

    python scripts/soak.py [--n 200] [--seed 2026]

About 15 minutes on 2 cores.
"""

import argparse
import contextlib
import io
import os
import tempfile
import time

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.io import files as wio
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.app.cli import main as cli

SLICE_CASES = list(phantoms.CASES) + ["two_vessels"]


def draw(rng, k: int) -> dict:
    stack = rng.random() < 0.15
    p = {"k": k, "stack": bool(stack), "seed": int(rng.integers(0, 10**6)), "snr": float(rng.uniform(10, 40))}
    if stack:
        p.update(
            case=str(rng.choice(list(phantoms.STACK_CASES))),
            nz=int(rng.integers(3, 6)),
            h=float(rng.choice([1.5, 1.0])),
        )
    else:
        p.update(case=str(rng.choice(SLICE_CASES)), h=float(rng.choice([1.5, 1.0, 0.6])))
    p["venc_factor"] = None if rng.random() < 0.5 else float(rng.uniform(0.55, 1.5))
    return p


def _peak(p) -> float:
    if p["stack"]:
        _, truth = phantoms.make_stack(p["case"], nz=p["nz"], h_mm=p["h"], snr=None, seed=p["seed"])
        return max(phantoms.peak_velocity(t.flow) for t in truth.slices)
    if p["case"] == "two_vessels":
        return 0.4
    _, truth = phantoms.make_phantom(p["case"], h_mm=p["h"], snr=None, seed=p["seed"])
    return phantoms.peak_velocity(truth.flow)


def run_one(p, folder) -> dict:
    inp, tru, out = (os.path.join(folder, f"{p['k']}_{n}.h5") for n in ("in", "truth", "out"))
    venc = None if p["venc_factor"] is None else p["venc_factor"] * _peak(p)
    err_stream = io.StringIO()
    with contextlib.redirect_stderr(err_stream), contextlib.redirect_stdout(io.StringIO()):
        if p["case"] == "two_vessels":
            acq, truth = phantoms.make_two_vessels(h_mm=p["h"], snr=p["snr"], seed=p["seed"], venc=venc)
            wio.write_acquisition(inp, acq)
            truths = [truth]
            rc0 = 0
        else:
            args = [
                "phantom",
                "--h",
                str(p["h"]),
                "--snr",
                str(p["snr"]),
                "--seed",
                str(p["seed"]),
                "-o",
                inp,
                "--truth",
                tru,
            ]
            args += ["--stack", p["case"], "--nz", str(p["nz"])] if p["stack"] else ["--case", p["case"]]
            args += ["--venc", str(venc)] if venc is not None else []
            rc0 = cli(args)
            truths = metrics.TruthTable.all_from_file(tru) if rc0 == 0 else []
        t0 = time.perf_counter()
        rc = cli(["reconstruct", inp, "-o", out]) if rc0 == 0 else rc0
        sec = time.perf_counter() - t0
    text = err_stream.getvalue()
    row = {
        **p,
        "rc": rc,
        "seconds": sec,
        "warnings": [ln[len("wss-nlp: warning: ") :] for ln in text.splitlines() if ln.startswith("wss-nlp: warning:")],
        "error": next((ln for ln in text.splitlines() if ln.startswith("wss-nlp: error")), ""),
        "wss_err": float("nan"),
    }
    if rc == 0:
        errs = []
        for i, d in enumerate(wio.read_result(out)):
            if d.get("failed"):
                continue
            t = truths[i] if len(truths) > 1 else truths[0]  # a phantoms.Truth or a metrics.TruthTable
            errs.append(
                metrics.compare(
                    d["center"], d["phi"], d["radius"], d["wall_x"], d["wall_y"], d["tau"], d["mean_tau"], t
                ).wss_rel_l2
            )
        row["wss_err"] = float(np.max(errs)) if errs else float("nan")
    return row


def describe(r) -> str:
    venc = "default" if r["venc_factor"] is None else f"{r['venc_factor']:.2f} x peak"
    what = f"{r['case']} stack nz={r['nz']}" if r["stack"] else r["case"]
    return f"{what}, h {r['h']:g}, SNR {r['snr']:.0f}, venc {venc}, seed {r['seed']}"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=200)
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    draws = [draw(rng, k) for k in range(args.n)]
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        for d in draws:
            rows.append(run_one(d, folder))
            r = rows[-1]
            print(
                f"{r['k'] + 1}/{args.n} {describe(r)}: rc {r['rc']}, WSS err {r['wss_err']:.1%}, "
                f"{len(r['warnings'])} warning(s)",
                flush=True,
            )
    failed = [r for r in rows if r["rc"] != 0]
    aliased = [r for r in rows if r["venc_factor"] is not None and r["venc_factor"] < 1]
    lines = [
        f"`python scripts/soak.py --n {args.n} --seed {args.seed}`: {args.n} random valid phantoms through "
        f"`wss-nlp phantom` and `wss-nlp reconstruct` (default options), {time.perf_counter() - t0:.0f} s.",
        "",
        f"- runs: {len(rows)} ({sum(r['stack'] for r in rows)} stacks, {len(aliased)} with venc below the peak "
        "velocity)",
        f"- failures (non-zero exit): **{len(failed)}**",
        f"- runs with warnings: {sum(bool(r['warnings']) for r in rows)}; flagged SUSPECT (velocity residual "
        f"> 3 x noise): {sum(any('SUSPECT' in w for w in r['warnings']) for r in rows)}",
        "",
        "## Failures",
        "",
    ]
    lines += [f"- {describe(r)}: exit {r['rc']}: {r['error']}" for r in failed] or ["none"]
    lines += [
        "",
        "## WSS relative L2 error by case (worst slice of each run)",
        "",
        "| case | runs | median | max |",
        "|---|---|---|---|",
    ]
    for case in sorted({(r["case"], r["stack"]) for r in rows}):
        e = np.array([r["wss_err"] for r in rows if (r["case"], r["stack"]) == case and np.isfinite(r["wss_err"])])
        if e.size:
            lines.append(f"| {case[0]}{' stack' if case[1] else ''} | {e.size} | {np.median(e):.1%} | {e.max():.1%} |")
    lines += [
        "",
        "## The 15 largest WSS errors and what the run said",
        "",
        "| run | WSS err | warnings |",
        "|---|---|---|",
    ]
    worst = sorted((r for r in rows if np.isfinite(r["wss_err"])), key=lambda r: -r["wss_err"])[:15]
    for r in worst:
        warn = "; ".join(w.replace("|", "/") for w in r["warnings"]) or "none"
        lines.append(f"| {describe(r)} | {r['wss_err']:.1%} | {warn} |")
    write_report(args.out, "soak.md", lines)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
