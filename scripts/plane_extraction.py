#!/usr/bin/env python
"""4D flow cut by a plane (``wss-nlp import ... --plane``): the reconstruction's errors on the extracted slice.

Phantom: ``wss_nlp.synthetic.scanner_exports.make_flow_volume``: Poiseuille flow in a tube of radius 6 mm tilted up to
about 30 degrees through a rotated grid of anisotropic voxels, every velocity component measured as a phase
(complex voxel mean, complex Gaussian noise), two frames (peak 0.8 and 0.4 m/s). Written as NIfTI, imported
with ``--plane`` through a point on the axis with the axis as normal, reconstructed with default options.
Each plane voxel takes the nearest volume voxel's values (the product's choice) or, for comparison, the
trilinear interpolants. Report seeds 0.. (the tests use seeds 40..). Writes
``scripts/results/plane_extraction.md``.

    python scripts/plane_extraction.py [--seeds 5] [--snr 25,10] [--voxels 1.0,1.5]
"""

import sys
import tempfile
import time

import numpy as np

from _report import study_parser, write_report
from wss_nlp.io import importing, scanner
from wss_nlp.synthetic import scanner_exports as se
from wss_nlp.io.plane import Plane
from wss_nlp.pipeline import ReconstructionOptions, reconstruct


def main() -> None:
    p = study_parser(__doc__, seeds=5, h="", snr="25,10")
    p.add_argument("--voxels", default="1.0,1.5", help="volume voxel scales (edges scale x (1.0, 1.1, 0.9) mm)")
    args = p.parse_args()
    options = ReconstructionOptions(uncertainty=False)
    lines = [
        f"Seeds 0-{args.seeds - 1}, two frames each (peak 0.8 and 0.4 m/s), tube radius 6 mm; errors of the "
        "reconstruction on the extracted plane: radius relative L2 about the true axis, mean WSS relative (mean |.| "
        "and max |.| over the seeds and frames the result does not flag SUSPECT, and the mean signed); how many "
        "slices the result flags SUSPECT, with their errors.",
        "Made by `python scripts/plane_extraction.py" + "".join(f" {a}" for a in sys.argv[1:]) + "`.",
        "",
        "| volume voxel [mm] | SNR | plane values | radius err | mean WSS err, unflagged | signed | flagged "
        "SUSPECT (their errors) | near-wall models |",
        "|---|---|---|---|---|---|---|---|",
    ]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for scale in (float(v) for v in args.voxels.split(",")):
            voxel = tuple(scale * np.array([1.0, 1.1, 0.9]))
            n = int(np.ceil(40 / scale))
            for snr in (float(v) for v in args.snr.split(",")):
                rows = {0: ([], [], [], []), 1: ([], [], [], [])}
                for seed in range(args.seeds):
                    vol = se.make_flow_volume(seed=seed, snr=snr, n=n, voxel_mm=voxel)
                    paths = se.write_flow_volume(f"{tmp}/{seed}", vol)
                    for order in (0, 1):
                        plane = Plane(
                            point=tuple(vol.center + 2 * vol.axis),
                            normal=tuple(vol.axis),
                            fov_mm=26.0,
                            order=order,
                        )
                        fluid = scanner.ImportOptions(viscosity_pa_s=vol.viscosity_pa_s, venc_m_s=vol.venc_m_s)
                        imp = importing.import_paths(paths, fluid, "m/s", None, plane)
                        for it in range(imp.nt):
                            res = reconstruct(imp.frame(it, f"seed {seed} frame {it}"), options)[0]
                            e1, e2, _ = plane.axes()  # the true axis meets the plane at (c . e1, c . e2)
                            r = np.hypot(res.wss.wall_x - vol.center @ e1, res.wss.wall_y - vol.center @ e2)
                            rows[order][0].append(np.sqrt(np.mean((r - vol.radius_mm) ** 2)) / vol.radius_mm)
                            rows[order][1].append(res.wss.mean / vol.wss_pa(it) - 1)
                            rows[order][2].append(res.near_wall.model if res.near_wall else "plain")
                            rows[order][3].append(bool(res.screen.get("suspect")))
                for order, name in ((0, "nearest voxel (default)"), (1, "trilinear")):
                    r_err, w_err, models, suspect = (np.asarray(v) for v in rows[order])
                    ok = ~suspect
                    w = np.abs(w_err[ok])
                    flagged = np.abs(w_err[suspect])
                    unflagged = (
                        f"{100 * np.mean(w):.1f}% ({100 * np.max(w):.1f}%) | {100 * np.mean(w_err[ok]):+.1f}%"
                        if ok.any()
                        else "all flagged | -"
                    )
                    counts = {m: int(np.sum(models == m)) for m in sorted(set(models))}
                    lines.append(
                        f"| {', '.join(f'{v:.3g}' for v in voxel)} | {snr:g} | {name} | "
                        f"{100 * np.mean(r_err):.2f}% ({100 * np.max(r_err):.2f}%) | "
                        f"{unflagged} | "
                        f"{int(suspect.sum())} of {suspect.size}"
                        + (f" ({100 * flagged.min():.0f}-{100 * flagged.max():.0f}%)" if flagged.size else "")
                        + f" | {', '.join(f'{m} {c}' for m, c in counts.items())} |"
                    )
                    print(lines[-1], flush=True)
    lines += ["", f"({time.perf_counter() - t0:.0f} s)"]
    write_report(args.out, "plane_extraction.md", lines)


if __name__ == "__main__":
    main()
