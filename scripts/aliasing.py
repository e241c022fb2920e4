#!/usr/bin/env python
"""Aliased phantoms: what the input screen does and what it costs in WSS accuracy.

For each phantom case, voxel size and venc (as a fraction of the peak
velocity; 1.25 is the unaliased default), the same phantom (same seed:
geometry, offset and noise draws) is acquired with that venc and
reconstructed with default options but without the band. Reports the
screen's outcome (voxels unwrapped, refused) and the WSS relative L2 error
against the unaliased default-venc reconstruction of the same seed. The
issue-18 criterion is the ratio <= 1.5. Writes ``scripts/results/aliasing.md``.

    python scripts/aliasing.py [--seeds 2] [--cases laminar,manufactured,circle,turbulent] [--h 1.5,1.0,0.6]

About 6 minutes on 2 cores.
"""

import numpy as np

from _report import study_parser, write_report
from wss_nlp import metrics, phantoms
from wss_nlp.errors import InputError
from wss_nlp.reconstruct import ReconstructionOptions, reconstruct

FRACTIONS = (0.8, 0.6, 0.45, 0.35)
SEED0 = 300  # seeds 300.. : not used by any test or by the choice of the screen's thresholds


def main(argv=None):
    p = study_parser(__doc__, seeds=2, h="1.5,1.0,0.6")
    p.set_defaults(cases="laminar,manufactured,circle,turbulent")
    args = p.parse_args(argv)
    opts = ReconstructionOptions(uncertainty=False)
    lines = [f"Seeds {SEED0}-{SEED0 + args.seeds - 1}, SNR 25, default options without the band; "
             "`python scripts/aliasing.py`.", "",
             "Each cell: WSS relative L2 error with the aliased venc / with the default venc (same seed), worst "
             "ratio over the seeds, and the screen's outcome (voxels unwrapped, mean over seeds; `refused` = "
             "input error).", "",
             "| case | h [mm] | unaliased (venc 1.25 x peak) | " + " | ".join(f"venc {f:g} x peak" for f in FRACTIONS)
             + " |", "|---|---|---|" + "---|" * len(FRACTIONS)]
    for case in args.cases.split(","):
        for h in (float(v) for v in args.h.split(",")):
            base, cells = [], {f: [] for f in FRACTIONS}
            for seed in range(SEED0, SEED0 + args.seeds):
                acq, truth = phantoms.make_phantom(case, h_mm=h, snr=25, seed=seed)
                e0 = metrics.compare_slice(reconstruct(acq, opts)[0], truth).wss_rel_l2
                base.append(e0)
                peak = phantoms.peak_velocity(truth.flow)
                for f in FRACTIONS:
                    acq1, _ = phantoms.make_phantom(case, h_mm=h, snr=25, seed=seed, venc=f * peak)
                    try:
                        r = reconstruct(acq1, opts)[0]
                    except InputError:
                        cells[f].append(None)
                        continue
                    cells[f].append((metrics.compare_slice(r, truth).wss_rel_l2, e0, r.screen["aliased_voxels"]))
                print(f"{case} h {h:g} seed {seed} done", flush=True)
            row = f"| {case} | {h:g} | {np.mean(base):.1%} |"
            for f in FRACTIONS:
                got = [c for c in cells[f] if c is not None]
                refused = len(cells[f]) - len(got)
                if not got:
                    row += " refused |"
                    continue
                ratio = max(e1 / e0 for e1, e0, _ in got)
                mark = "" if ratio <= 1.5 else " **>1.5x**"
                row += (f" {np.mean([c[0] for c in got]):.1%} ({ratio:.2f}x{mark}), "
                        f"{np.mean([c[2] for c in got]):.0f} unwrapped" + (f", {refused} refused" if refused else "")
                        + " |")
            lines.append(row)
    write_report(args.out, "aliasing.md", lines)


if __name__ == "__main__":
    main()
