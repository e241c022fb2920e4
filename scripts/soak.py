#!/usr/bin/env python
"""Soak test: random valid inputs through the command line; no run may fail, hang, lose data or be silently wrong.

Draws ``--n`` inputs (seeded, ``--seed``): single slices of every phantom case and of the two-vessel phantom, and
small stacks; voxel sizes 0.6-1.5 mm, SNR 10-40, venc either the default (1.25 x peak) or 0.55-1.5 x the peak
velocity (so about a third of the draws alias), random sub-voxel offsets; and, as valid but odd files do, the
velocity stored instead of the phase, the magnitude in other units (x 1e-3 to 1e4) or with a constant offset.
Each goes through ``wss-nlp phantom`` (or the factory, for two vessels), the file mutation, and ``wss-nlp
reconstruct`` with default options, in-process (``cli.main``), under a time limit, and is compared with its truth.
Then a study with a failing case goes through ``wss-nlp sweep``. Writes ``scripts/results/soak.md``:

* tracebacks or internal errors; hangs (over ``--timeout`` seconds); refusals of a valid input (and whether each
  is one line naming the file or option); partial outputs (a temporary file, a staged folder, an output after a
  refusal); data loss (an input file changed);
* silent wrong results: exit 0, no flag (a warning with SUSPECT, CHECK UNITS or OBLIQUE PLANE), and a WSS off
  by more than 10 % (relative L2 over the wall) and by more than three bands (the mean WSS off by more than three
  times its linearized standard deviation, where the result has one);
* the sweep's exit code (1: a sweep with a failed case);

all of which must be none, and the WSS errors by case with the largest ones and what their runs said.

The full soak, which writes ``scripts/results/soak.md`` (70 minutes on an idle machine in one process;
``--jobs 2`` runs two inputs at a time)::

    nice -n 10 python scripts/soak.py --n 200 --seed 2026 --jobs 2

``--jobs N`` runs N inputs at a time, each in a process of its own (a row does not depend on N: each input is
drawn before any runs and runs alone in its process). ``--seeds S1,S2,...`` reruns only the draws of
``--n``/``--seed`` whose phantom seed is listed (the seeds the report names), and ``--n 40`` runs the first 40 of
the same 200 draws; such partial runs write ``--report`` (default ``soak_rerun.md``), never ``soak.md``::

    python scripts/soak.py --seeds 209416,937534,321337,777039,174966 --report soak_failures.md
    nice -n 10 python scripts/soak.py --n 40 --jobs 2 --report soak_40.md
"""

import argparse
import concurrent.futures
import contextlib
import hashlib
import io
import multiprocessing
import os
import shutil
import signal
import tempfile
import time

import h5py
import numpy as np

from _report import RESULTS, write_report
from wss_nlp.io import files as wio
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.app.cli import main as cli

SLICE_CASES = list(phantoms.CASES) + ["two_vessels"]
#: Words of a warning that flags a result (the fuzz suite counts the same: tests/test_fuzz.py).
FLAGS = ("SUSPECT", "CHECK UNITS", "OBLIQUE PLANE")
#: A silent wrong result misses the truth by more than this (WSS relative L2) and by more than BANDS bands.
SILENT_WRONG, BANDS = 0.10, 3.0


class Hang(BaseException):
    """Raised by the alarm: a run took longer than --timeout (a BaseException: main() must not catch it)."""


def _alarm(signum, frame):
    raise Hang()


def _digest(path) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def _leftovers(folder) -> list:
    return [n for n in os.listdir(folder) if n.endswith(".part") or n.startswith(".wss-nlp-")]


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
    # valid but odd files: the velocity instead of the phase, the magnitude in other units or with an offset
    odd = rng.random()
    p["file"] = "phase" if odd < 0.6 else "velocity" if odd < 0.75 else "scaled" if odd < 0.9 else "offset"
    p["factor"] = float(10 ** rng.uniform(-3, 4)) if p["file"] == "scaled" else float(rng.uniform(0.5, 20.0))
    return p


def mutate(path: str, p: dict) -> None:
    """The valid odd file the draw asks for (``p["file"]``), written over the phantom's input in place."""
    if p["file"] == "phase":
        return
    with h5py.File(path, "r+") as f:
        if p["file"] == "velocity" and "phase" in f:
            v = f.attrs["venc_m_s"] * f["phase"][()] / np.pi
            del f["phase"]
            f["velocity"] = v
        elif p["file"] in ("scaled", "offset"):
            m = f["magnitude"][()]
            lumen = float(np.percentile(m, 99))
            m = m * p["factor"] if p["file"] == "scaled" else m + p["factor"] * lumen
            del f["magnitude"]
            f["magnitude"] = m


def _peak(p) -> float:
    if p["stack"]:
        _, truth = phantoms.make_stack(p["case"], nz=p["nz"], h_mm=p["h"], snr=None, seed=p["seed"])
        return max(phantoms.peak_velocity(t.flow) for t in truth.slices)
    if p["case"] == "two_vessels":
        return 0.4
    _, truth = phantoms.make_phantom(p["case"], h_mm=p["h"], snr=None, seed=p["seed"])
    return phantoms.peak_velocity(truth.flow)


def run_one(p, folder, timeout: float) -> dict:
    inp, tru, out = (os.path.join(folder, f"{p['k']}_{n}.h5") for n in ("in", "truth", "out"))
    venc = None if p["venc_factor"] is None else p["venc_factor"] * _peak(p)
    err_stream = io.StringIO()
    row = {**p, "rc": None, "seconds": float("nan"), "hang": False, "changed": False, "leftovers": [],
           "wss_err": float("nan"), "mean_err": float("nan"), "mean_std": float("nan"),
           "min_factor": float("nan")}  # fmt: skip
    with contextlib.redirect_stderr(err_stream), contextlib.redirect_stdout(io.StringIO()):
        if p["case"] == "two_vessels":
            acq, truth = phantoms.make_two_vessels(h_mm=p["h"], snr=p["snr"], seed=p["seed"], venc=venc)
            wio.write_acquisition(inp, acq)
            truths = [truth]
            rc0 = 0
        else:
            args = ["phantom", "--h", str(p["h"]), "--snr", str(p["snr"]), "--seed", str(p["seed"]), "-o", inp,
                    "--truth", tru]  # fmt: skip
            args += ["--stack", p["case"], "--nz", str(p["nz"])] if p["stack"] else ["--case", p["case"]]
            args += ["--venc", str(venc)] if venc is not None else []
            rc0 = cli(args)
            truths = metrics.TruthTable.all_from_file(tru) if rc0 == 0 else []
        if rc0 == 0:
            mutate(inp, p)
            before = _digest(inp)
        t0 = time.perf_counter()
        previous = signal.signal(signal.SIGALRM, _alarm)
        signal.alarm(int(timeout))
        try:
            rc = cli(["reconstruct", inp, "-o", out]) if rc0 == 0 else rc0
        except Hang:
            rc, row["hang"] = None, True
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, previous)
        row["seconds"] = time.perf_counter() - t0
    text = err_stream.getvalue()
    lines = text.splitlines()
    errors = [ln for ln in lines if ln.startswith("wss-nlp: error")]
    row.update(
        rc=rc,
        warnings=[ln[len("wss-nlp: warning: ") :] for ln in lines if ln.startswith("wss-nlp: warning:")],
        error=errors[-1] if errors else "",
        traceback="Traceback" in text or "internal error" in text,
        one_line=len(errors) == 1 and lines[-1] == errors[0] and (inp in errors[0] or "--" in errors[0]),
        changed=rc0 == 0 and _digest(inp) != before,
        leftovers=_leftovers(folder) + ([out] if rc not in (0, None) and os.path.exists(out) else []),
    )
    row["flagged"] = any(f in w for w in row["warnings"] for f in FLAGS)
    if rc == 0:
        errs, means, stds, factors = [], [], [], []
        dephasing = wio.read_dephasing(out)  # the smallest predicted magnitude factor of each slice
        for i, d in enumerate(wio.read_result(out)):
            if d.get("failed"):
                continue
            t = truths[i] if len(truths) > 1 else truths[0]  # a phantoms.Truth or a metrics.TruthTable
            e = metrics.compare(d["center"], d["phi"], d["radius"], d["wall_x"], d["wall_y"], d["tau"],
                                d["mean_tau"], t)  # fmt: skip
            errs.append(e.wss_rel_l2)
            factors.append(float(dephasing.get(d["name"], {}).get("min_factor", 1.0)))
            means.append(abs(e.mean_wss_pa - e.mean_wss_true_pa))
            stds.append(d.get("mean_std", float("nan")))
        if errs:
            worst = int(np.argmax(errs))
            row.update(wss_err=float(errs[worst]), mean_err=float(means[worst]), mean_std=float(stds[worst]),
                       min_factor=float(min(factors)))  # fmt: skip
    for name in os.listdir(folder):  # the next run starts from a clean folder (leftovers were counted)
        if name.startswith(f"{p['k']}_") or name in row["leftovers"]:
            path = os.path.join(folder, name)
            if os.path.isfile(path):
                os.remove(path)
    return row


def silent_wrong(r) -> bool:
    """Exit 0, no flag, and off by more than SILENT_WRONG and by more than BANDS bands (where there is a band)."""
    if r["rc"] != 0 or r["flagged"] or not np.isfinite(r["wss_err"]) or r["wss_err"] <= SILENT_WRONG:
        return False
    return not (np.isfinite(r["mean_std"]) and r["mean_err"] <= BANDS * r["mean_std"])


def sweep_with_a_failed_case(folder) -> tuple[int, str]:
    """A study of one valid input and one without a vessel: the sweep must exit 1, the failure recorded."""
    acq, _ = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=1)
    wio.write_acquisition(os.path.join(folder, "good.h5"), acq)
    noise = np.random.default_rng(2).normal(size=(2, *acq.magnitude.shape))
    wio.write_acquisition(os.path.join(folder, "noise.h5"), acq)
    with h5py.File(os.path.join(folder, "noise.h5"), "r+") as f:
        f["magnitude"][...] = np.hypot(*noise)
    study = os.path.join(folder, "s.toml")
    with open(study, "w") as fh:
        fh.write('[study]\nname = "soak"\n[grid]\ninput = ["good.h5", "noise.h5"]\nmethod = "oyre"\n')
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = cli(["sweep", study, "-o", os.path.join(folder, "sweep"), "--workers", "1"])
    return rc, next((ln for ln in err.getvalue().splitlines() if "failed" in ln), "")


def describe(r) -> str:
    venc = "default" if r["venc_factor"] is None else f"{r['venc_factor']:.2f} x peak"
    what = f"{r['case']} stack nz={r['nz']}" if r["stack"] else r["case"]
    odd = {"phase": "", "velocity": ", velocity stored", "scaled": f", magnitude x {r['factor']:.3g}",
           "offset": f", magnitude + {r['factor']:.2g} x its 99th percentile"}[r["file"]]  # fmt: skip
    return f"{what}, h {r['h']:g}, SNR {r['snr']:.0f}, venc {venc}{odd}, seed {r['seed']}"


def run_in_subfolder(d: dict, folder: str, timeout: float) -> dict:
    """:func:`run_one` in a folder of its own (concurrent runs must not count each other's staged files)."""
    sub = os.path.join(folder, str(d["k"]))
    os.mkdir(sub)
    row = run_one(d, sub, timeout)
    shutil.rmtree(sub, ignore_errors=True)
    return row


def _progress(r: dict, n: int) -> None:
    print(
        f"{r['k'] + 1}/{n} {describe(r)}: rc {r['rc']}, WSS err {r['wss_err']:.1%}, min dephasing factor "
        f"{r['min_factor']:.2f}, {len(r['warnings'])} warning(s){' FLAGGED' if r['flagged'] else ''}"
        + (" SILENT WRONG" if silent_wrong(r) else ""),
        flush=True,
    )


def run_all(draws: list, folder: str, timeout: float, jobs: int, n: int) -> list:
    """Every draw through :func:`run_in_subfolder`, ``jobs`` at a time (processes of their own), in draw order."""
    if jobs == 1:
        rows = []
        for d in draws:
            rows.append(run_in_subfolder(d, folder, timeout))
            _progress(rows[-1], n)
        return rows
    # spawn, not fork: CasADi and the BLAS hold threads a forked child would inherit in an unknown state; the
    # alarm that ends a hung run works in each worker, whose tasks run in its main thread
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
        futures = [pool.submit(run_in_subfolder, d, folder, timeout) for d in draws]
        rows = []
        for f in concurrent.futures.as_completed(futures):
            rows.append(f.result())
            _progress(rows[-1], n)
    return sorted(rows, key=lambda r: r["k"])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=200, help="inputs drawn (the first n of the same sequence)")
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--timeout", type=float, default=900.0, help="seconds a run may take before it counts as a hang")
    p.add_argument("--jobs", type=int, default=1, help="inputs run at a time, each in a process of its own")
    p.add_argument("--seeds", default="", help="comma list of phantom seeds: rerun only those draws")
    p.add_argument("--report", default=None, help="file name in --out (default soak.md for the full soak, "
                   "soak_rerun.md otherwise)")  # fmt: skip
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    if args.jobs < 1:
        p.error("--jobs must be at least 1")
    rng = np.random.default_rng(args.seed)
    draws = [draw(rng, k) for k in range(args.n)]
    command = f"python scripts/soak.py --n {args.n} --seed {args.seed}"
    if args.seeds:
        wanted = {int(v) for v in args.seeds.split(",")}
        missing = wanted - {d["seed"] for d in draws}
        if missing:
            p.error(f"--seeds: {sorted(missing)} not among the {args.n} draws of --seed {args.seed}")
        draws = [d for d in draws if d["seed"] in wanted]
        command += f" --seeds {args.seeds}"
    full = not args.seeds and args.n >= 200
    report = args.report or ("soak.md" if full else "soak_rerun.md")
    if args.jobs > 1:
        command += f" --jobs {args.jobs}"
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        rows = run_all(draws, folder, args.timeout, args.jobs, args.n)
        with tempfile.TemporaryDirectory(dir=folder) as sub:
            sweep_rc, sweep_line = sweep_with_a_failed_case(sub)
    failed = [r for r in rows if r["rc"] != 0]
    tracebacks = [r for r in rows if r["traceback"]]
    hangs = [r for r in rows if r["hang"]]
    partial = [r for r in rows if r["leftovers"]]
    lost = [r for r in rows if r["changed"]]
    refused = [r for r in rows if r["rc"] == 2]
    wrong = [r for r in rows if silent_wrong(r)]
    aliased = [r for r in rows if r["venc_factor"] is not None and r["venc_factor"] < 1]
    odd = {k: sum(r["file"] == k for r in rows) for k in ("velocity", "scaled", "offset")}
    lines = [
        f"`{command}`: {len(rows)} random valid inputs through `wss-nlp phantom` and `wss-nlp reconstruct` "
        f"(default options), {time.perf_counter() - t0:.0f} s with {args.jobs} job(s).",
        "",
        f"- runs: {len(rows)} ({sum(r['stack'] for r in rows)} stacks, {len(aliased)} with venc below the peak "
        f"velocity; {odd['velocity']} with the velocity stored, {odd['scaled']} with the magnitude scaled, "
        f"{odd['offset']} with a magnitude offset)",
        f"- tracebacks or internal errors: **{len(tracebacks)}**",
        f"- hangs (over {args.timeout:g} s): **{len(hangs)}**",
        f"- failures (a valid input not reconstructed): **{len(failed)}**, of them refusals (exit 2): {len(refused)}"
        f", each one line naming the file or option: {all(r['one_line'] for r in refused)}",
        f"- partial outputs (temporary files, staged folders, an output after a refusal): **{len(partial)}**",
        f"- data loss (an input file changed): **{len(lost)}**",
        f"- silent wrong results (exit 0, no flag, WSS off by more than {SILENT_WRONG:.0%} and by more than "
        f"{BANDS:g} bands): **{len(wrong)}**",
        f"- runs flagged ({', '.join(FLAGS)}): {sum(r['flagged'] for r in rows)}; runs with any warning: "
        f"{sum(bool(r['warnings']) for r in rows)}; longest run {np.nanmax([r['seconds'] for r in rows]):.0f} s",
        f"- a sweep with a failed case: exit **{sweep_rc}** ({sweep_line.removeprefix('wss-nlp: warning: ')})",
        "",
        "## Failures, hangs, tracebacks, partial outputs, data loss, silent wrong results",
        "",
    ]
    bad = {id(r): r for r in failed + tracebacks + hangs + partial + lost + wrong}.values()
    lines += [
        f"- {describe(r)}: exit {r['rc']}{' (hang)' if r['hang'] else ''}: {r['error']} "
        f"{'leftovers ' + str(r['leftovers']) if r['leftovers'] else ''}"
        f"{' INPUT CHANGED' if r['changed'] else ''}"
        + (f" silent wrong: {r['wss_err']:.1%}" if silent_wrong(r) else "")
        for r in bad
    ] or ["none"]
    lines += [
        "",
        "## WSS relative L2 error by case (worst slice of each run)",
        "",
        "| case | runs | median | max | max unflagged |",
        "|---|---|---|---|---|",
    ]
    for case in sorted({(r["case"], r["stack"]) for r in rows}):
        sel = [r for r in rows if (r["case"], r["stack"]) == case and np.isfinite(r["wss_err"])]
        e = np.array([r["wss_err"] for r in sel])
        u = [r["wss_err"] for r in sel if not r["flagged"]]
        if e.size:
            lines.append(
                f"| {case[0]}{' stack' if case[1] else ''} | {e.size} | {np.median(e):.1%} | {e.max():.1%} | "
                + (f"{max(u):.1%} |" if u else "- |")
            )
    lines += [
        "",
        "## The 15 largest WSS errors and what the run said",
        "",
        "| run | WSS err | mean off / band | min dephasing factor | flagged | warnings |",
        "|---|---|---|---|---|---|",
    ]
    worst = sorted((r for r in rows if np.isfinite(r["wss_err"])), key=lambda r: -r["wss_err"])[:15]
    for r in worst:
        warn = "; ".join(w.replace("|", "/") for w in r["warnings"]) or "none"
        bands = r["mean_err"] / r["mean_std"] if np.isfinite(r["mean_std"]) and r["mean_std"] > 0 else float("nan")
        lines.append(
            f"| {describe(r)} | {r['wss_err']:.1%} | {bands:.1f} | {r['min_factor']:.2f} | "
            f"{'yes' if r['flagged'] else 'no'} | {warn} |"
        )
    write_report(args.out, report, lines)
    return 1 if (failed or tracebacks or hangs or partial or lost or wrong or sweep_rc != 1) else 0


if __name__ == "__main__":
    raise SystemExit(main())
