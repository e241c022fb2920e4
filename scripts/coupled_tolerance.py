#!/usr/bin/env python
"""The coupled IPOPT tolerance: what tighter tolerances than the default change, and what they cost.

Four flows not used when the coupled method was built (manufactured lobed wall, Re_tau 549 DNS pipe,
entrance flow, Re_tau 180 DNS in an ellipse), h = 1.5, 0.6, 0.3 mm, SNR 25 and 10, seed 102; default
options with ``--method coupled`` at the tolerances 1e-6 (the reference), 1e-5, 1e-4 (the default,
``CoupledOptions.tol``) and 1e-3: the largest WSS change from the reference relative to the peak WSS, IPOPT
iterations and seconds (summed per flow), and whether every solve converged. Writes
``scripts/results/coupled_tolerance.md``.

    python scripts/coupled_tolerance.py   (about a minute)
"""

import time
from dataclasses import replace

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.synthetic import phantoms
from wss_nlp.models.coupled import CoupledOptions
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

CASES = ("manufactured", "turbulent550", "entrance", "turbulent-ellipse")
TOLERANCES = (1e-6, 1e-5, 1e-4, 1e-3)  # the first is the reference


def main():
    default = CoupledOptions().tol
    names = [f"{tol:.0e}".replace("e-0", "e-") + (" (default)" if tol == default else "") for tol in TOLERANCES]
    lines = [
        "Seed 102, h = 1.5 / 0.6 / 0.3 mm, SNR 25 and 10 (6 slices per flow); default options, `--method coupled`, "
        f"IPOPT tolerance {', '.join(names)}; WSS change from the {names[0]} solve. "
        "Made by `python scripts/coupled_tolerance.py`.",
        "",
        "| flow | "
        + " | ".join(f"max WSS change / peak {n}" for n in names[1:])
        + " | "
        + " | ".join(f"iterations {n}" for n in names)
        + " | "
        + " | ".join(f"s {n}" for n in names)
        + " | converged |",
        "|---|" + "---|" * (3 * len(TOLERANCES) - 1) + "---|",
    ]
    for case in CASES:
        k_tol = len(TOLERANCES)
        change, its, secs, ok = [0.0] * (k_tol - 1), [0] * k_tol, [0.0] * k_tol, True
        for h in (1.5, 0.6, 0.3):
            for snr in (25, 10):
                acq, _ = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=102)
                taus = []
                for k, tol in enumerate(TOLERANCES):
                    opt = ReconstructionOptions(method="coupled", uncertainty=False)
                    opt = replace(opt, coupled=replace(opt.coupled, tol=tol))
                    t0 = time.perf_counter()
                    res = reconstruct(acq, opt)[0]
                    secs[k] += time.perf_counter() - t0
                    its[k] += res.velocity.stats.iterations
                    ok = ok and res.converged
                    taus.append(res.wss.tau)
                peak = np.max(np.abs(taus[0]))
                for k in range(1, k_tol):
                    change[k - 1] = max(change[k - 1], float(np.max(np.abs(taus[k] - taus[0])) / peak))
        lines.append(
            f"| {case} | "
            + " | ".join(f"{c:.1e}" for c in change)
            + " | "
            + " | ".join(str(i) for i in its)
            + " | "
            + " | ".join(f"{s:.1f}" for s in secs)
            + f" | {'all' if ok else 'NO'} |"
        )
    write_report(RESULTS, "coupled_tolerance.md", lines)


if __name__ == "__main__":
    main()
