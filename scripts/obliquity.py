#!/usr/bin/env python
"""Planes off the vessel's axis: the tilt measured from the in-plane velocity, the WSS before and after the
correction, and the single-component shape check on elliptic lumens (``wss_nlp.pipeline.obliquity``).

Two tables, written to ``scripts/results/obliquity.md``:

1. 4D-flow tubes (``synthetic.scanner_exports.make_flow_volume``, radius 6 mm, peak 0.8 m/s, SNR 25, 1 mm voxels)
   cut through a point on the axis by planes tilted 0-30 degrees from the cross-section, imported as
   ``wss-nlp import --plane`` does (nearest voxel), reconstructed with default options (no band): the tilt the
   import measures, the mean WSS's error against the exact ``2 mu u / R`` before (the 2D WSS) and after the
   correction, and whether the slice is flagged.
2. Elliptic phantoms (laminar 13 x 10 mm, turbulent-ellipse 14 x 11 mm, fourier) at h = 1 and 1.5 mm, SNR 10 and
   25, seeds 300-301: the lumen's aspect, the velocity-weighted one, their ratio and the angle between their
   axes, which the check compares with ``MAX_ASPECT_MISMATCH`` and ``MAX_AXES_ANGLE_DEG``.

    python scripts/obliquity.py [--seeds 2]

About 10 minutes on 2 cores.
"""

import argparse
import tempfile

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.io import importing
from wss_nlp.io.plane import Plane
from wss_nlp.io.scanner import ImportOptions
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
from wss_nlp.pipeline.obliquity import MAX_ASPECT_MISMATCH, MAX_AXES_ANGLE_DEG, MIN_ASPECT, shape_check
from wss_nlp.synthetic import phantoms
from wss_nlp.synthetic import scanner_exports as se


def planes(seeds: int) -> list[str]:
    lines = [
        "| seed | tilt [deg] | measured [deg] | mean WSS err, 2D | corrected | flagged |",
        "|---|---|---|---|---|---|",
    ]
    options = ReconstructionOptions(uncertainty=False)
    for seed in range(seeds):
        vol = se.make_flow_volume(seed=seed, snr=25, peaks_m_s=(0.8,))
        with tempfile.TemporaryDirectory() as tmp:
            paths = se.write_flow_volume(tmp, vol)
            a = np.cross(vol.axis, np.eye(3)[int(np.argmin(np.abs(vol.axis)))])
            a /= np.linalg.norm(a)
            for deg in (0, 10, 20, 30):
                normal = np.cos(np.radians(deg)) * vol.axis + np.sin(np.radians(deg)) * a
                plane = Plane(point=tuple(vol.center + 2 * vol.axis), normal=tuple(normal), fov_mm=34.0)
                fluid = ImportOptions(viscosity_pa_s=vol.viscosity_pa_s, venc_m_s=vol.venc_m_s)
                imp = importing.import_paths(paths, fluid, "m/s", None, plane)
                res = reconstruct(imp.frame(0, "plane"), options)[0]
                rec = res.screen.get("obliquity", {})
                factor = rec.get("mean_factor", 1.0)
                truth = vol.wss_pa(0)
                flagged = "OBLIQUE" if any("OBLIQUE PLANE" in w for w in res.warnings) else ""
                flagged += " SUSPECT" if res.screen.get("suspect") else ""
                lines.append(
                    f"| {seed} | {deg} | {imp.record['plane']['tilt_deg']:.1f} | "
                    f"{res.wss.mean / factor / truth - 1:+.1%} | {res.wss.mean / truth - 1:+.1%} | "
                    f"{flagged.strip() or 'no'} |"
                )
                print(lines[-1], flush=True)
    return lines


def shapes(seeds: int) -> list[str]:
    lines = [
        "| phantom | h [mm] | SNR | seed | lumen aspect | flow aspect | ratio | axes [deg] | flagged |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    options = ReconstructionOptions(uncertainty=False)
    worst_ratio, worst_angle = 1.0, 0.0
    for case in ("laminar", "turbulent-ellipse", "fourier"):
        for h in (1.0, 1.5):
            for snr in (10.0, 25.0):
                for seed in range(300, 300 + seeds):
                    acq, _ = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
                    res = reconstruct(acq, options)[0]
                    note, rec = shape_check(res)
                    if "flow_aspect" not in rec:  # below MIN_ASPECT: not elliptic enough for the check to run
                        lines.append(
                            f"| {case} | {h:g} | {snr:g} | {seed} | {rec['lumen_aspect']:.3f} | - | - | - | "
                            f"not checked (aspect < {MIN_ASPECT:g}) |"
                        )
                        print(lines[-1], flush=True)
                        continue
                    ratio = max(rec["flow_aspect"], rec["lumen_aspect"]) / min(rec["flow_aspect"], rec["lumen_aspect"])
                    worst_ratio, worst_angle = max(worst_ratio, ratio), max(worst_angle, rec["axes_angle_deg"])
                    lines.append(
                        f"| {case} | {h:g} | {snr:g} | {seed} | {rec['lumen_aspect']:.3f} | {rec['flow_aspect']:.3f} "
                        f"| {ratio:.3f} | {rec['axes_angle_deg']:.1f} | {'yes' if note else 'no'} |"
                    )
                    print(lines[-1], flush=True)
    lines += [
        "",
        f"Largest ratio {worst_ratio:.3f} (limit {MAX_ASPECT_MISMATCH:g}), largest angle between the axes "
        f"{worst_angle:.1f} degrees (limit {MAX_AXES_ANGLE_DEG:g}).",
    ]
    return lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    lines = [
        f"`python scripts/obliquity.py --seeds {args.seeds}`.",
        "",
        "## Planes cut off the axis of a 4D-flow tube",
        "",
        *planes(args.seeds),
        "",
        "## The shape check on elliptic lumens whose flow follows their shape",
        "",
        *shapes(args.seeds),
    ]
    write_report(args.out, "obliquity.md", lines)


if __name__ == "__main__":
    main()
