#!/usr/bin/env python
"""Whole-vessel WSS from 4D flow (``wss_nlp.vessel.reconstruct``) against the phantoms' exact WSS, beside the
wall-normal fit most 4D flow tools use (``wss_nlp.vessel.baseline``), on the same segmentation.

Phantoms: ``synthetic.vessels.make_vessel_phantom`` (aorta-sized: arc, swirl, taper, ellipse, helix, radius
10-12 mm, about 100 mm in view, grid turned at random against the vessel), SNR 20, voxels h = 2.0 and 2.5 mm,
without and with tissue around the vessel; the pulsatile arch (20 frames over the cycle: TAWSS and OSI); the
carotid-sized tube (radius 3 mm). Default options throughout (``VesselOptions()``). Measures
(``wss_nlp.vessel.metrics``): the WSS vector's relative L2 error over the covered visible wall (all frames), the
wall's RMS distance from the true wall over h, the coverage of the visible wall, TAWSS's relative L2 error and
OSI's RMS error; mean (max) over the seeds. Seeds: the reported seeds 100-104 (``--seeds reported``) or the
development seeds (``--seeds dev`` or a comma list) for tuning.

    python scripts/vessel_accuracy.py [--seeds reported] [--cases arc,swirl,taper,ellipse,helix] [--h 2.0,2.5]
        [--tissue no,yes] [--pulsatile] [--carotid] [--voxel 1.6x1.6x2.5;2x2x3] [--out scripts/results]
        [--name vessel_accuracy]
    python scripts/vessel_accuracy.py --merge NAME1,NAME2,...   # one table from runs split by --name

Writes ``<name>.md`` (and the rows as JSON under ``results/studies/``).
"""

import argparse
import json
import os
import sys
import time

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.synthetic.vessels import DEVELOPMENT_SEEDS, REPORTED_SEEDS, make_vessel_phantom
from wss_nlp.vessel.baseline import baseline_vessel
from wss_nlp.vessel.metrics import accuracy
from wss_nlp.vessel.reconstruct import reconstruct_vessel, vessel_inputs

AORTA = "arc,swirl,taper,ellipse,helix"


def run(case, h, tissue, seed, frames=1, options=None, voxel=None) -> dict:
    """One phantom, reconstructed and scored; ``voxel`` (three edge lengths, mm) gives anisotropic voxels, whose
    row is keyed by ``h`` = the largest edge and labelled by the triple."""
    extra = {} if voxel is None else {"voxel_mm": tuple(voxel)}
    vol, truth = make_vessel_phantom(case, h_mm=h, snr=20, seed=seed, tissue=tissue, frames=frames, **extra)
    t0 = time.perf_counter()
    inputs = vessel_inputs(vol)
    res = reconstruct_vessel(vol, options, inputs.mask, inputs.centerline, inputs.record)
    seconds = time.perf_counter() - t0
    base = baseline_vessel(vol, inputs.mask, inputs.centerline, inputs.record, options, s=res.s_mm, phi=res.phi)
    ours, theirs = accuracy(res, truth), accuracy(base, truth)
    return {"case": case, "h": h, "voxel": None if voxel is None else [float(v) for v in voxel],
            "tissue": tissue, "seed": seed, "frames": frames, "seconds": seconds,
            "ours": ours.as_dict(), "baseline": theirs.as_dict(), "beta": res.parameters["beta"],
            "cycle": _cycle(res.parameters.get("cycle")),
            "statuses": [s["status"] for s in res.statuses["geometry"]]}  # fmt: skip


def _cycle(record) -> dict | None:
    """The cine's cycle model (wss_nlp.vessel.cycle3d) without its curve: model, gamma, criterion values."""
    return None if record is None else {k: record.get(k) for k in ("model", "gamma", "how", "values", "margin")}


def _save_rows(out: str, name: str, rows: list) -> None:
    os.makedirs(os.path.join(out, "studies"), exist_ok=True)
    with open(os.path.join(out, "studies", f"{name}_rows.json"), "w") as fh:
        json.dump(rows, fh, indent=1)


def _size(row: dict) -> str:
    """The h column: the voxel size, or the anisotropic voxel's three edges (rows before --voxel have no key)."""
    voxel = row.get("voxel")
    return f"{row['h']:g}" if not voxel else " x ".join(f"{v:g}" for v in voxel)


def _fmt(values, scale=100.0, digits=1, suffix=" %") -> str:
    v = np.asarray(values, float) * scale
    if not np.any(np.isfinite(v)):  # nothing covered on any seed (every wall point flagged): no error to measure
        return "none covered"
    if not np.all(np.isfinite(v)):
        k = int(np.sum(np.isfinite(v)))
        v = v[np.isfinite(v)]
        return f"{np.mean(v):.{digits}f}{suffix} ({np.max(v):.{digits}f}; {k} of {np.size(values)} seeds covered)"
    return f"{np.mean(v):.{digits}f}{suffix} ({np.max(v):.{digits}f})"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", default="reported")
    p.add_argument("--cases", default=AORTA)
    p.add_argument("--h", default="2.0,2.5")
    p.add_argument("--tissue", default="no,yes")
    p.add_argument("--pulsatile", action="store_true")
    p.add_argument("--carotid", action="store_true")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument(
        "--voxel",
        default="",
        help="anisotropic voxels instead of --h: semicolon list of triples, e.g. '1.6x1.6x2.5;2x2x3' (mm)",
    )
    p.add_argument("--out", default=RESULTS)
    p.add_argument("--name", default="vessel_accuracy")
    p.add_argument("--merge", default="", help="make the table from these runs' saved rows (comma list of --name)")
    args = p.parse_args()
    if args.merge:
        rows = []
        for name in args.merge.split(","):
            with open(os.path.join(args.out, "studies", f"{name}_rows.json")) as fh:
                rows += json.load(fh)
        unique: dict = {}  # a case run twice (split runs that overlap) counts once: the first run's row
        for r in rows:
            unique.setdefault((r["case"], _size(r), r["tissue"], r["seed"]), r)
        rows = list(unique.values())
        seeds = tuple(sorted({r["seed"] for r in rows}))
        write_report(args.out, f"{args.name}.md", table(rows, seeds, sys.argv[1:]))
        return
    seeds = {"reported": REPORTED_SEEDS, "dev": DEVELOPMENT_SEEDS}.get(args.seeds)
    seeds = tuple(int(s) for s in args.seeds.split(",")) if seeds is None else seeds
    hs = [float(v) for v in args.h.split(",")]
    tissues = [v == "yes" for v in args.tissue.split(",")]
    cases = [c for c in args.cases.split(",") if c]
    rows = []
    voxels = [tuple(float(v) for v in t.split("x")) for t in args.voxel.split(";") if t]
    if any(len(v) != 3 for v in voxels):
        p.error(f"--voxel: give triples such as 1.6x1.6x2.5, got {args.voxel!r}")
    sizes: list = [(h, None) for h in hs] if not voxels else [(max(v), v) for v in voxels]
    jobs = [(c, h, v, t, 1) for c in cases for h, v in sizes for t in tissues]
    if args.pulsatile:
        jobs += [("pulsatile", h, v, t, args.frames) for h, v in sizes for t in tissues]
    if args.carotid:
        jobs += [("carotid", h, v, t, 1) for h, v in sizes for t in tissues]
    for case, h, voxel, tissue, frames in jobs:
        for seed in seeds:
            row = run(case, h, tissue, seed, frames, voxel=voxel)
            rows.append(row)
            o, b = row["ours"], row["baseline"]
            print(f"{case} h={h} tissue={tissue} seed={seed}: ours {100 * o['wss_rel_l2']:.1f} % "
                  f"(wall {o['wall_rms_mm'] / h:.3f} h, cov {100 * o['coverage']:.0f} %), baseline "
                  f"{100 * b['wss_rel_l2']:.1f} %, {row['seconds']:.0f} s", file=sys.stderr, flush=True)  # fmt: skip
            _save_rows(args.out, args.name, rows)  # after every run: a stopped run keeps what it finished
    write_report(args.out, f"{args.name}.md", table(rows, seeds, sys.argv[1:]))


def table(rows, seeds, argv) -> list[str]:
    lines = [
        f"Seeds {', '.join(str(s) for s in seeds)}; SNR 20; default options (`VesselOptions()`); mean (max) over the "
        "seeds. WSS: relative L2 error of the WSS vector over the covered visible wall (area-weighted, all frames); "
        "wall: RMS distance of the reconstructed wall from the true wall over h; coverage: covered visible wall "
        "area over the visible wall's. Baseline: the wall-normal fit on the same mask and grid "
        "(`wss_nlp.vessel.baseline`). Targets (issue 38): WSS <= 8 % at h = 2.0 mm and <= 12 % at h = 2.5 mm, wall "
        "<= 0.25 h, coverage >= 90 %; pulsatile TAWSS <= 10 %, OSI within 0.05. Anisotropic voxels: h is the "
        "three edges, the wall RMS is over the largest. Coverage can exceed 100 % by the "
        "reconstructed wall's area being slightly larger than the true one. Seconds: wall clock of mask, centreline "
        "and reconstruction (not the baseline) on the machine as it was, shared; `scripts/bench_vessel.py` times.",
        "Made by `python scripts/vessel_accuracy.py" + "".join(f" {a}" for a in argv) + "`.",
        "",
        "| case | h [mm] | tissue | seeds | WSS ours | WSS baseline | wall RMS / h ours | wall RMS / h baseline "
        "| coverage | TAWSS ours | TAWSS baseline | OSI RMS ours | OSI RMS baseline | seconds |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    keys = []
    for r in rows:
        k = (r["case"], _size(r), r["tissue"])
        if k not in keys:
            keys.append(k)
    for case, size, tissue in keys:
        sel = [r for r in rows if (r["case"], _size(r), r["tissue"]) == (case, size, tissue)]
        h = sel[0]["h"]
        o = {k: [r["ours"][k] for r in sel] for k in sel[0]["ours"]}
        b = {k: [r["baseline"][k] for r in sel] for k in sel[0]["baseline"]}
        pulsatile = sel[0]["frames"] > 1
        cells = [
            case, size, "yes" if tissue else "no", ",".join(str(r["seed"]) for r in sel),
            _fmt(o["wss_rel_l2"]), _fmt(b["wss_rel_l2"]),
            _fmt(np.asarray(o["wall_rms_mm"]) / h, 1.0, 3, ""), _fmt(np.asarray(b["wall_rms_mm"]) / h, 1.0, 3, ""),
            _fmt(o["coverage"], 100.0, 1),
            _fmt(o["tawss_rel_l2"]) if pulsatile else "", _fmt(b["tawss_rel_l2"]) if pulsatile else "",
            _fmt(o["osi_rms"], 1.0, 3, "") if pulsatile else "", _fmt(b["osi_rms"], 1.0, 3, "") if pulsatile else "",
            f"{np.mean([r['seconds'] for r in sel]):.0f}",
        ]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return lines


if __name__ == "__main__":
    main()
