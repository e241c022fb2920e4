#!/usr/bin/env python
"""Thin wall layers (issue 13): the plain basis (``--near-wall off``) against the default ``--near-wall auto``.

For laminar-type phantoms (laminar, circle, fourier, manufactured), the
developing entrance flow and the turbulent ones (DNS at Re_tau 180, 549,
998; the Re_tau 180 profile in an elliptic lumen) at h = 1.5, 1.0, 0.6 mm,
SNR 25, on report seeds 100.. (development used seeds 1 and 2): WSS
relative L2 error of the plain basis and of ``--near-wall auto``, the model and
layer scale auto chose, and the Oyre baseline for reference. Writes
``scripts/results/near_wall.md``.

    python scripts/near_wall.py [--seeds 3] [--h 1.5,1.0,0.6] [--snr 25] [--cases ...] [--name near_wall.md]
"""

import sys
import time

import numpy as np

from _report import study_parser, write_report
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.models import velocity as vel
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

CASES = "laminar,circle,fourier,manufactured,entrance,turbulent,turbulent550,turbulent1000,turbulent-ellipse"
FIRST_SEED = 100


def main() -> None:
    p = study_parser(__doc__, seeds=3, h="1.5,1.0,0.6", snr="25")
    p.set_defaults(cases=CASES)
    p.add_argument("--name", default="near_wall.md", help="file name of the table in --out")
    args = p.parse_args()
    snr = float(args.snr)
    plain = ReconstructionOptions(uncertainty=False, velocity=vel.VelocityOptions(near_wall="off"))
    auto = ReconstructionOptions(uncertainty=False)  # the default: --near-wall auto
    oyre = ReconstructionOptions(uncertainty=False, method="oyre")
    lines = [
        f"SNR {snr:g}, seeds {FIRST_SEED}-{FIRST_SEED + args.seeds - 1}; WSS relative L2 error, mean (max) over seeds.",
        "Made by `python scripts/near_wall.py" + "".join(f" {a}" for a in sys.argv[1:]) + "`.",
        "",
        "| phantom | h [mm] | --near-wall off | default (auto) | chosen (l/R, per seed) | Oyre baseline |",
        "|---|---|---|---|---|---|",
    ]
    t0 = time.perf_counter()
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            errs = {"default": [], "auto": [], "oyre": []}
            chosen = []
            for seed in range(FIRST_SEED, FIRST_SEED + args.seeds):
                acq, truth = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
                for name, opts in (("default", plain), ("auto", auto), ("oyre", oyre)):
                    res = reconstruct(acq, opts)[0]
                    errs[name].append(metrics.compare_slice(res, truth).wss_rel_l2)
                    if name == "auto":
                        nwc = res.near_wall
                        chosen.append(nwc.model if nwc.model == "plain" else f"{nwc.model} {nwc.scale_ratio:.4f}")

            def cell(v):
                return f"{100 * np.mean(v):.1f}% ({100 * np.max(v):.1f}%)"

            lines.append(
                f"| {case} | {h:g} | {cell(errs['default'])} | {cell(errs['auto'])} | {', '.join(chosen)} | "
                f"{cell(errs['oyre'])} |"
            )
            print(lines[-1], flush=True)
    lines += ["", f"({time.perf_counter() - t0:.0f} s)"]
    write_report(args.out, args.name, lines)


if __name__ == "__main__":
    main()
