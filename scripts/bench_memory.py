#!/usr/bin/env python
"""Peak memory of one slice's reconstruction, each configuration in a fresh process.

Issue 19 asks for ``--method coupled`` at h = 0.3 mm within 1 GB peak, with
the band too. Each row runs one reconstruction of a seeded phantom (SNR 25,
seed 100) in its own Python process and reports the process's peak resident
memory (``ru_maxrss``), the resident memory after the imports and the
phantom (the baseline the reconstruction adds to), and the seconds of the
reconstruction. Writes ``scripts/results/bench_memory.md``.

    python scripts/bench_memory.py [--h 1.0 0.3]
"""

import argparse
import json
import os
import subprocess
import sys

from _report import write_report

TARGET_MB = 1024  # issue 19: coupled at h = 0.3 mm within 1 GB, with the band too

CHILD = """
import json, resource, sys, time
from wss_nlp.synthetic import phantoms
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
case, h, method, band = sys.argv[1], float(sys.argv[2]), sys.argv[3], sys.argv[4] == "1"
acq, _ = phantoms.make_phantom(case, h_mm=h, snr=25, seed=100)
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
t0 = time.perf_counter()
reconstruct(acq, ReconstructionOptions(method=method, uncertainty=band))
seconds = time.perf_counter() - t0
print(json.dumps({"base": base, "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "s": seconds}))
"""


def measure(case: str, h: float, method: str, band: bool) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, case, str(h), method, "1" if band else "0"],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--h", type=float, nargs="+", default=[1.0, 0.3])
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    args = p.parse_args(argv)
    lines = [
        "Peak resident memory of one slice's reconstruction (SNR 25, seed 100), each row in a fresh process; "
        f"{os.cpu_count()} cores. 'baseline': after the imports and the phantom. Target (issue 19): "
        f"coupled at h = 0.3 mm within {TARGET_MB} MB, with the band too.",
        "",
        "| phantom | h [mm] | method | band | baseline [MB] | peak [MB] | seconds |",
        "|---|---|---|---|---|---|---|",
    ]
    for case in ("laminar", "turbulent"):
        for h in args.h:
            for method, band in (("decoupled", True), ("coupled", False), ("coupled", True)):
                r = measure(case, h, method, band)
                over = " (over)" if method == "coupled" and h == 0.3 and r["peak"] > TARGET_MB else ""
                lines.append(
                    f"| {case} | {h:g} | {method} | {'yes' if band else 'no'} | {r['base']:.0f} | "
                    f"{r['peak']:.0f}{over} | {r['s']:.2f} |"
                )
    write_report(args.out, "bench_memory.md", lines)


if __name__ == "__main__":
    main()
