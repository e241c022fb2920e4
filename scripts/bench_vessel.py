#!/usr/bin/env python
"""Speed and memory of the whole-vessel reconstruction (``wss_nlp.vessel.reconstruct``) on 2 cores.

Rows: one frame of an aorta-sized vessel (radius 11 mm) with about 100 mm in view at 2 mm voxels (the straight
tube and the arch), SNR 20, development seed 0; the 20-frame pulsatile arch (a cine: one wall, one factorization,
20 right-hand sides); A/B variants of the one-frame arch in the same run (quadrature points per axis, the outside
level's updates, GCV against a fixed beta, the BLAS's threads). Each row runs in a fresh subprocess (first call:
CasADi's set-up included) whose peak resident memory is read with ``resource.getrusage(RUSAGE_CHILDREN)``; the
phantom is built in the subprocess too, before the clock starts, and its memory is in the peak. Targets (issue 38):
one frame <= 60 s, a 20-frame cine <= 10 min, peak memory <= 4 GB.

    python scripts/bench_vessel.py [--quick] [--out scripts/results]

Writes ``bench_vessel.md``. The machine's load average is printed with the table: the numbers are wall-clock
seconds on a machine shared with other jobs.
"""

import argparse
import json
import os
import resource
import subprocess
import sys

from _report import RESULTS, write_report

ROWS = [
    ("straight, 1 frame", "straight", 1, {}),
    ("arch, 1 frame", "arc", 1, {}),
    ("pulsatile arch, 20 frames", "pulsatile", 20, {}),
]
VARIANTS = [
    ("arch, 1 frame: q = 3 (default 4)", "arc", 1, {"geometry": {"quad_order": 3}}),
    ("arch, 1 frame: no outside-level updates", "arc", 1, {"geometry": {"outside_updates": 0}}),
    ("arch, 1 frame: beta fixed 1e-5 (no GCV)", "arc", 1, {"velocity": {"beta": 1e-5}}),
    ("arch, 1 frame: BLAS threads as installed", "arc", 1, {"blas_threads": 0}),
]


def child(case: str, frames: int, changes: dict) -> None:
    """Run one reconstruction and print its timings as JSON (in a subprocess)."""
    import time

    from wss_nlp.synthetic.vessels import make_vessel_phantom
    from wss_nlp.vessel import geometry3d as g3
    from wss_nlp.vessel import velocity3d as v3
    from wss_nlp.vessel.reconstruct import VesselOptions, reconstruct_vessel

    t0 = time.perf_counter()
    vol, _ = make_vessel_phantom(case, h_mm=2.0, snr=20, seed=0, frames=frames)
    build = time.perf_counter() - t0
    options = VesselOptions(
        geometry=g3.Geometry3DOptions(**changes.get("geometry", {})),
        velocity=v3.Velocity3DOptions(**changes.get("velocity", {})),
        blas_threads=changes.get("blas_threads", 1),
    )
    t0 = time.perf_counter()
    res = reconstruct_vessel(vol, options)
    total = time.perf_counter() - t0
    print(json.dumps({"seconds": total, "steps": res.seconds, "phantom_seconds": build, "shape": list(vol.shape),
                      "frames": vol.nt, "wall_points": int(res.flags.size),
                      "length_mm": float(res.s_mm[-1] - res.s_mm[0]),
                      "voxels_fitted": res.statuses["geometry"][-1]["voxels"],
                      "points": res.statuses["geometry"][-1]["points"]}))  # fmt: skip


def measure(case: str, frames: int, changes: dict) -> dict:
    code = (f"import sys; sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r}); import bench_vessel; "
            f"bench_vessel.child({case!r}, {frames}, {changes!r})")  # fmt: skip
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    row = json.loads(out.stdout.strip().splitlines()[-1])
    # kB, the largest child so far: a smaller child leaves the maximum unchanged
    row["peak_mb"] = after.ru_maxrss / 1024 if after.ru_maxrss > usage.ru_maxrss else float("nan")
    # the child's CPU time (phantom included): on a loaded machine closer to an idle machine's wall-clock time
    row["cpu_seconds"] = (after.ru_utime + after.ru_stime) - (usage.ru_utime + usage.ru_stime)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="the main rows only, no A/B variants")
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args()
    rows = ROWS + ([] if args.quick else VARIANTS)
    lines = [
        "One reconstruction per row in a fresh subprocess (`wss_nlp.vessel.reconstruct.reconstruct_vessel`, "
        "default options unless the row says otherwise), SNR 20, development seed 0, 2 mm voxels; wall-clock "
        "seconds on 2 cores shared with other jobs (load average at the start: "
        f"{', '.join(f'{v:.1f}' for v in os.getloadavg())}). Peak memory: the subprocess's maximum resident set "
        "(`getrusage(RUSAGE_CHILDREN)`, phantom included; blank where a row's peak stayed below an earlier row's); "
        "CPU seconds: the subprocess's user + system time, the phantom's build (its wall-clock seconds in "
        "parentheses) included: the code runs on one thread (BLAS limited to one), so on an idle machine the "
        "wall-clock time is about the CPU time less the phantom's. "
        "Targets: one frame <= 60 s, 20 frames <= 600 s, <= 4096 MB.",
        "Made by `python scripts/bench_vessel.py" + "".join(f" {a}" for a in sys.argv[1:]) + "`.",
        "",
        "| run | grid | length [mm] | fitted voxels / points | seconds | CPU seconds (with phantom) "
        "| mask + centreline | geometry | velocity | cycle model | WSS | band | peak [MB] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    peak_max = 0.0
    for name, case, frames, changes in rows:
        r = measure(case, frames, changes)
        st = r["steps"]
        peak = r["peak_mb"]
        peak_max = max(peak_max, peak if peak == peak else 0.0)
        cells = [name, "x".join(str(v) for v in r["shape"]) + f" x {r['frames']}", f"{r['length_mm']:.0f}",
                 f"{r['voxels_fitted']} / {r['points']}", f"{r['seconds']:.1f}",
                 f"{r['cpu_seconds']:.1f} ({r['phantom_seconds']:.1f})",
                 f"{st['segmentation'] + st['centerline']:.1f}", f"{st['geometry']:.1f}", f"{st['velocity']:.1f}",
                 f"{st['cycle']:.1f}" if "cycle" in st else "", f"{st['wss']:.1f}", f"{st.get('band', 0.0):.1f}",
                 "" if peak != peak else f"{peak:.0f}"]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
        print(lines[-1], file=sys.stderr, flush=True)
    lines += ["", f"Largest peak memory over the rows: {peak_max:.0f} MB."]
    write_report(args.out, "bench_vessel.md", lines)


if __name__ == "__main__":
    main()
