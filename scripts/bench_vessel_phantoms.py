#!/usr/bin/env python
"""Cost and quadrature accuracy of the 4D flow vessel phantoms (``wss_nlp.synthetic.vessels``).

Times ``make_vessel_phantom`` for the aorta-sized cases at h = 2 mm (SNR 20, seed 0): the arc (radius 11 mm, about
100 mm of centreline in view) with one frame, with tissue, and the pulsatile arc with 20 frames; and the helix and
carotid for reference. Each row is one build in one run (the machine is shared: seconds vary by about 30 %).

Then the accuracy of the voxel means by refining: ``--voxels`` voxels the wall of the arc case crosses (seed 0,
h = 2 mm; the elliptic case too) with ``n_wall`` points per axis, the lumen fraction against ``n_wall = 48`` (the
two-level rule's fraction equals the plain midpoint rule's exactly) and the noise-free velocity against the
plain ``32^3`` midpoint rule (whose own error, about that of ``n_wall = 24``, limits the last row). Issue 38
targets: one frame well under a minute, 20 frames well under ten. Writes ``scripts/results/bench_vessel_phantoms.md``.

    python scripts/bench_vessel_phantoms.py [--voxels 300]
"""

import argparse
import time

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.synthetic import vessels as vs

TARGET_ONE_S = 60.0  # issue 38: one frame of the aorta-sized case well under a minute
TARGET_CINE_S = 600.0  # issue 38: a 20-frame cine well under ten minutes


def timed(case, **kw):
    t0 = time.perf_counter()
    vol, truth = vs.make_vessel_phantom(case, h_mm=2.0, snr=20, seed=0, **kw)
    return time.perf_counter() - t0, vol, truth


def refinement(case: str, nvox: int, levels) -> list[str]:
    _, truth = vs.make_vessel_phantom(case, h_mm=2.0, snr=None, seed=0, n_wall=4)
    cut = np.argwhere((truth.lumen_fraction > 0) & (truth.lumen_fraction < 1))
    idx = cut[np.random.default_rng(0).choice(len(cut), min(nvox, len(cut)), replace=False)]
    venc = truth.venc_m_s[0]

    def means(n, **kw):
        return vs.voxel_means(truth.vessel, truth.affine_mm, idx, n, [0.0], truth.venc_m_s, **kw)

    ref_fraction = means(48).fraction  # the plain 48^3 rule's fraction exactly
    ref_velocity = venc * np.angle(means(32, cells=1).encoded[0]) / np.pi
    rows = []
    for n in levels:
        t0 = time.perf_counter()
        m = means(n)
        sec = time.perf_counter() - t0
        df = m.fraction - ref_fraction
        dv = venc * np.angle(m.encoded[0]) / np.pi - ref_velocity  # (3, V) m/s
        cells = "plain" if vs.wall_cells(n) == n else vs.wall_cells(n)
        rows.append(
            f"| {case} | {n} | {cells} | {np.sqrt(np.mean(df**2)):.1e} | {np.max(np.abs(df)):.1e} | "
            f"{np.sqrt(np.mean(dv**2)):.1e} | {np.max(np.abs(dv)):.1e} | {1e3 * sec / len(idx):.2f} |"
        )
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--voxels", type=int, default=300)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    lines = [
        "Building the vessel phantoms (`make_vessel_phantom`, h = 2 mm, SNR 20, seed 0, default n_wall = 12, "
        "n_inner = 3); seconds on this machine (2 cores, shared), one build per row.",
        "",
        "| case | frames | tissue | grid | voxels | wall voxels | seconds | target |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for case, kw in (
        ("arc", {}),
        ("arc", {"tissue": True}),
        ("pulsatile", {"frames": 20}),
        ("helix", {}),
        ("carotid", {}),
    ):
        sec, vol, truth = timed(case, **kw)
        c = truth.parameters["counts"]
        target = ""
        if case == "arc" and not kw:
            target = "yes" if sec < TARGET_ONE_S else "NO"
        if kw.get("frames") == 20:
            target = "yes" if sec < TARGET_CINE_S else "NO"
        lines.append(
            f"| {case} | {vol.nt} | {'yes' if kw.get('tissue') else 'no'} | {'x'.join(map(str, vol.shape))} | "
            f"{c['voxels']} | {c['wall_voxels']} | {sec:.1f} | {target} |"
        )
        print(lines[-1], flush=True)
    lines += [
        "",
        f"Voxel means of {args.voxels} wall voxels (lumen fraction strictly between 0 and 1) of each case, seed 0, "
        "h = 2 mm, noise-free, by the two-level rule with n_wall points per axis (sub-cells per axis: "
        "`wall_cells`): the lumen fraction against n_wall = 48 (equal to the plain 48^3 midpoint rule's), the "
        "velocity (m/s, the three components; venc 1.04 m/s) against the plain 32^3 rule; ms per voxel for one frame.",
        "",
        "| case | n_wall | sub-cells | fraction RMS | fraction max | velocity RMS [m/s] | velocity max [m/s] | "
        "ms / voxel |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for case in ("arc", "ellipse"):
        lines += refinement(case, args.voxels, (4, 8, 12, 16, 24))
    write_report(args.out, "bench_vessel_phantoms.md", lines)


if __name__ == "__main__":
    main()
