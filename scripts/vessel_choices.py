#!/usr/bin/env python
"""The whole-vessel reconstruction's default choices, each against its alternative, on development seeds.

One phantom per choice (``synthetic.vessels.make_vessel_phantom``, h = 2 mm), the same mask and centreline for both
variants, WSS vector relative L2 error and wall RMS / bias over the covered visible wall
(``wss_nlp.vessel.metrics``); mean over the seeds:

* the outside level's updates (``Geometry3DOptions.outside_updates``, 4 by default, 0 = the shell's level):
  the arch with tissue around it, SNR 20;
* the map's inner radius (``Velocity3DOptions.inner``: "mean" by default, "min" the 2D rule): the tapering tube,
  SNR 20, and the elliptic arch;
* beta on noise-free data (``velocity3d.NOISE_FREE_BETA`` against GCV's choice, which has no noise to balance):
  the arch without noise;
* the sub-voxel points per axis of the wall fit (``Geometry3DOptions.quad_order``, 4 by default from the 2D rule
  capped at 4): the arch without noise.

    python scripts/vessel_choices.py [--seeds 0,1]

Writes ``vessel_choices.md``.
"""

import argparse
import sys

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.synthetic.vessels import make_vessel_phantom
from wss_nlp.vessel import geometry3d as g3
from wss_nlp.vessel import velocity3d as v3
from wss_nlp.vessel.metrics import accuracy
from wss_nlp.vessel.reconstruct import VesselOptions, reconstruct_vessel, vessel_inputs

CHOICES = [
    ("outside level at the wall", "arc", 20, True,
     [("4 updates (default)", {}), ("shell level (0 updates)", {"geometry": {"outside_updates": 0}})]),
    ("map's inner radius", "taper", 20, False,
     [("mean radius (default)", {}), ("smallest radius (2D rule)", {"velocity": {"inner": "min"}})]),
    ("map's inner radius", "ellipse", 20, False,
     [("mean radius (default)", {}), ("smallest radius (2D rule)", {"velocity": {"inner": "min"}})]),
    ("beta, noise-free data", "arc", None, False,
     [("fixed 1e-5 (default)", {}), ("GCV", {"velocity": {"noise_free_beta": None}})]),
    ("wall fit's points per axis", "arc", None, False,
     [("q = 4 (default)", {}), ("q = 3", {"geometry": {"quad_order": 3}}), ("q = 6", {"geometry": {"quad_order": 6}})]),
]  # fmt: skip


def options(changes: dict) -> VesselOptions:
    return VesselOptions(geometry=g3.Geometry3DOptions(**changes.get("geometry", {})),
                         velocity=v3.Velocity3DOptions(**changes.get("velocity", {})))  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", default="0,1")
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    lines = [
        f"Development seeds {', '.join(map(str, seeds))}; h = 2 mm; mean over the seeds of the WSS vector's relative "
        "L2 error, the wall's RMS distance and its mean signed distance (positive outside) over the covered visible "
        "wall, and the beta used.",
        "Made by `python scripts/vessel_choices.py" + "".join(f" {a}" for a in sys.argv[1:]) + "`.",
        "",
        "| choice | phantom | variant | WSS error | wall RMS [mm] | wall bias [mm] | beta |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for what, case, snr, tissue, variants in CHOICES:
        phantom = f"{case}, SNR {snr if snr else 'inf'}" + (", tissue" if tissue else "")
        rows: dict = {name: [] for name, _ in variants}
        for seed in seeds:
            vol, truth = make_vessel_phantom(case, h_mm=2.0, snr=snr, seed=seed, tissue=tissue)
            inputs = vessel_inputs(vol)
            for name, changes in variants:
                res = reconstruct_vessel(vol, options(changes), inputs.mask, inputs.centerline, inputs.record)
                acc = accuracy(res, truth)
                rows[name].append((acc.wss_rel_l2, acc.wall_rms_mm, acc.wall_bias_mm, res.parameters["beta"]))
                print(what, case, seed, name, f"{100 * acc.wss_rel_l2:.2f} %", file=sys.stderr, flush=True)
        for name, _ in variants:
            a = np.array(rows[name])
            lines.append(f"| {what} | {phantom} | {name} | {100 * a[:, 0].mean():.2f} % | {a[:, 1].mean():.3f} "
                         f"| {a[:, 2].mean():+.3f} | {', '.join(f'{b:.0e}' for b in a[:, 3])} |")  # fmt: skip
    write_report(args.out, "vessel_choices.md", lines)


if __name__ == "__main__":
    main()
