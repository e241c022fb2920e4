#!/usr/bin/env python
"""The k-space dephasing passes with and without the first-order prediction that skips a final pass.

A k-space slice repeats its dephasing pass until the wall moves less than ``KSPACE_PASS_TOL`` voxels
(``wss_nlp.pipeline.driver``). With ``KSPACE_PASS_PREDICTION`` (the default) a pass whose move the geometry's
first-order response (``IpoptGeometrySolver.response``) predicts below that tolerance is not run; without
it, it is run and then ends the iteration. Both on the same development slices (seeds 0, 1; not the
report seeds 100-104 of ``scripts/kspace.py``): three flows, three acquisitions (no filter F = 1, Hamming
F = 1, Hamming F = 2), h 1.5-0.3 mm, SNR 25 and 10, the k-space model with the acquisition's filter.
Per flow and acquisition: passes run, slices with a pass fewer, the largest change of the WSS curve
(relative to its peak), the mean |mean-WSS error| both ways and the seconds per slice (each slice builds
its solvers). Writes ``scripts/results/kspace_passes.md``.

    python scripts/kspace_passes.py [--seeds 2] [--cases laminar,turbulent,manufactured] [--h 1.5,1.0,0.6,0.3]
                                    [--snr 25,10]
"""

import sys
import time

import numpy as np

from _report import study_parser, write_report
from bench import fresh
from wss_nlp.models import kspace
from wss_nlp.synthetic import phantoms as ph
from wss_nlp.pipeline import ReconstructionOptions
from wss_nlp.pipeline import driver as rc

ACQUISITIONS = {
    "none, F = 1": kspace.PSF("none", (1.0, 1.0)),
    "hamming, F = 1": kspace.PSF("hamming", (1.0, 1.0)),
    "hamming, F = 2": kspace.PSF("hamming", (2.0, 2.0)),
}


def _run(acq, psf, predict: bool) -> tuple:
    rc.KSPACE_PASS_PREDICTION = predict
    options = ReconstructionOptions(uncertainty=False, acquisition=kspace.AcquisitionOptions("kspace", psf.filter))
    fresh()
    t0 = time.perf_counter()
    r = rc.reconstruct(acq, options)[0]
    return r, time.perf_counter() - t0


def main(argv=None):
    p = study_parser(__doc__, seeds=2, h="1.5,1.0,0.6,0.3", snr="25,10")
    p.set_defaults(cases="laminar,turbulent,manufactured")
    args = p.parse_args(argv)
    lines = [
        f"Development seeds 0-{args.seeds - 1}, SNR {args.snr}, h {args.h} mm per row; k-space model with the "
        "acquisition's filter, defaults otherwise (no band). 'skip' = KSPACE_PASS_PREDICTION on (the default), "
        "'run' = off.",
        "Made by `python scripts/kspace_passes.py" + "".join(f" {a}" for a in sys.argv[1:]) + "`.",
        "",
        "| case | acquisition | slices | passes run / skip | slices with a pass fewer | largest WSS change "
        "[% of peak] | mean WSS err run / skip | s per slice run / skip |",
        "|---|---|---|---|---|---|---|---|",
    ]
    totals = np.zeros(4)
    try:
        for case in args.cases.split(","):
            for name, psf in ACQUISITIONS.items():
                passes, fewer, change, errors, seconds = np.zeros(2), 0, 0.0, [[], []], np.zeros(2)
                slices = 0
                for h in (float(v) for v in args.h.split(",")):
                    for snr in (float(v) for v in args.snr.split(",")):
                        for seed in range(args.seeds):
                            acq, truth = ph.make_phantom(case, h_mm=h, snr=snr, seed=seed, psf=psf)
                            out = [_run(acq, psf, predict) for predict in (False, True)]
                            counts = [r.dephasing.passes or 0 for r, _ in out]
                            passes += counts
                            fewer += counts[1] < counts[0]
                            taus = [r.wss.tau for r, _ in out]
                            change = max(change, float(np.max(np.abs(taus[1] - taus[0])) / np.max(np.abs(taus[0]))))
                            for i, (r, dt) in enumerate(out):
                                errors[i].append(abs(r.wss.mean - truth.mean_wss) / abs(truth.mean_wss))
                                seconds[i] += dt
                            slices += 1
                totals += [slices, fewer, *passes]
                lines.append(
                    f"| {case} | {name} | {slices} | {passes[0]:.0f} / {passes[1]:.0f} | {fewer} | "
                    f"{100 * change:.3f} | "
                    f"{100 * np.mean(errors[0]):.2f} % / {100 * np.mean(errors[1]):.2f} % | "
                    f"{seconds[0] / slices:.2f} / {seconds[1] / slices:.2f} |"
                )
    finally:
        rc.KSPACE_PASS_PREDICTION = True
    lines += [
        "",
        f"All: {totals[0]:.0f} slices, {totals[1]:.0f} with a pass fewer, passes {totals[2]:.0f} / {totals[3]:.0f}.",
    ]
    write_report(args.out, "kspace_passes.md", lines)


if __name__ == "__main__":
    main()
