#!/usr/bin/env python
"""The vessel's uncertainty band (``wss_nlp.vessel.band3d``: velocity noise only) against the phantoms' actual
errors.

Phantoms: ``synthetic.vessels.make_vessel_phantom`` (aorta-sized arc, swirl, taper; radius 10-12 mm), h = 2.0 mm,
SNR 20, no tissue, the reported seeds 100-104, default options (``VesselOptions()``). On the covered visible wall
(the truth's visible part, unflagged points), each wall point's axial WSS error against the exact one splits in
two parts, both on the reconstruction's own wall: the **noise part**, the WSS of the velocity fitted to the
measured voxels less the WSS of the same fit (same wall, same beta) to the phantom's noise-free voxel velocities
(``VesselTruth.noise_free_velocity``), which is what the band predicts; and the **bias**, the noise-free fit's
WSS less the exact one (discretization, prior, the wall's error, which includes the magnitude noise's effect on
the wall: the band leaves that out). Columns, mean over the seeds:

* band: RMS of the predicted std of the axial WSS over the covered visible wall (Pa; in % of the RMS exact
  axial WSS);
* noise / band: RMS of the noise part over the band's RMS (1 if the band is right);
* in 2 bands (noise): fraction of points whose noise part lies within 2 predicted std (95.4 % for Gaussian noise);
* bias: RMS of the bias (Pa);
* in 2 bands (total): fraction of points whose whole error lies within 2 predicted std (below 95 % where bias,
  not noise, dominates);
* wall mean: the covered wall's mean |WSS| band (Pa) and the RMS over seeds of its noise part and its bias (Pa);
* band / total s: the band's seconds against the whole reconstruction's.

    python scripts/band_vessel.py [--cases arc,swirl,taper] [--seeds reported] [--h 2.0] [--name band_vessel]
    python scripts/band_vessel.py --from-rows        # the table again from the saved rows

Writes ``scripts/results/<name>.md`` (and the rows as JSON under ``results/studies/``).
"""

import argparse
import dataclasses
import json
import os
import time

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.synthetic.vessels import DEVELOPMENT_SEEDS, REPORTED_SEEDS, make_vessel_phantom
from wss_nlp.vessel import wss3d
from wss_nlp.vessel.reconstruct import reconstruct_vessel


def run(case: str, h: float, seed: int) -> dict:
    vol, truth = make_vessel_phantom(case, h_mm=h, snr=20, seed=seed)
    t0 = time.perf_counter()
    res = reconstruct_vessel(vol)
    seconds = time.perf_counter() - t0
    fits = res.fits
    vel = fits.velocity
    vp = vel.problem
    idx = vp.voxel_index
    clean_u = np.stack([truth.noise_free_velocity[t][:, idx[:, 0], idx[:, 1], idx[:, 2]].T for t in range(vol.nt)])
    coef = np.stack([vp.solve(vel.beta, clean_u[t]) for t in range(vol.nt)])
    ss, pp = (v.ravel() for v in np.meshgrid(res.s_mm, res.phi, indexing="ij"))
    clean = wss3d.wall_wss(res.centerline, fits.geometry, dataclasses.replace(vel, coefficients=coef), ss, pp,
                           mu=fits.mu, pieces=fits.pieces)  # fmt: skip
    s_t, phi_t = truth.locate(res.wall_mm.reshape(-1, 3))
    visible = np.zeros(s_t.size, bool)
    for a, b in truth.visible:
        visible |= (s_t >= a) & (s_t <= b)
    use = visible & (res.flags.ravel() == 0)
    ax_true = truth.vessel.axial_wss(s_t[use], phi_t[use], 0.0)
    tau_true = truth.vessel.wss(s_t[use], phi_t[use], 0.0)
    ax = res.axial_pa[0].ravel()[use]
    ax_clean = clean.axial[0][use]
    band = res.axial_std_pa[0].ravel()[use]
    noise, bias, total = ax - ax_clean, ax_clean - ax_true, ax - ax_true
    area = res.area_mm2.ravel()
    cov = area * (res.flags.ravel() == 0)
    w = cov / cov.sum()  # the band's wall mean: the covered wall (visible or not), area weights
    mean_clean = float(w @ np.linalg.norm(clean.tau[0], axis=1))
    a = area[use] / area[use].sum()
    mean_true_use = float(a @ np.linalg.norm(tau_true, axis=1))
    mean_clean_use = float(a @ np.linalg.norm(clean.tau[0][use], axis=1))

    def rms(v):
        return float(np.sqrt(np.mean(np.square(v))))

    return {
        "case": case, "h": h, "seed": seed, "seconds": seconds, "band_seconds": res.seconds.get("band"),
        "offset_applied": bool(res.parameters.get("offset", {}).get("applied", False)),
        "points": int(use.sum()), "band_rms": rms(band), "true_rms": rms(ax_true), "noise_rms": rms(noise),
        "bias_rms": rms(bias), "in2_noise": float(np.mean(np.abs(noise) <= 2 * band)),
        "in2_total": float(np.mean(np.abs(total) <= 2 * band)), "z_rms": rms(noise / band),
        "mean_pa": res.band["mean_pa"], "mean_std_pa": res.band["mean_std_pa"],
        "mean_noise_pa": res.band["mean_pa"] - mean_clean, "mean_bias_pa": mean_clean_use - mean_true_use,
        "beta": res.parameters["beta"], "n_unknowns": int(vp.size), "load_average": os.getloadavg()[0],
    }  # fmt: skip


def table(rows: list) -> list:
    lines = [
        "| case | band [Pa] (% of RMS axial) | noise / band | in 2 bands (noise) | bias [Pa] | in 2 bands (total) "
        "| wall mean: band, noise, bias [Pa] | band / total s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for case in dict.fromkeys(r["case"] for r in rows):
        rs = [r for r in rows if r["case"] == case]

        def m(key):
            return float(np.mean([r[key] for r in rs]))

        mean_noise = float(np.sqrt(np.mean([r["mean_noise_pa"] ** 2 for r in rs])))
        mean_bias = float(np.sqrt(np.mean([r["mean_bias_pa"] ** 2 for r in rs])))
        lines.append(
            f"| {case} | {m('band_rms'):.3f} ({100 * m('band_rms') / m('true_rms'):.1f} %) | "
            f"{m('noise_rms') / m('band_rms'):.2f} | {100 * m('in2_noise'):.1f} % | {m('bias_rms'):.3f} | "
            f"{100 * m('in2_total'):.1f} % | {m('mean_std_pa'):.2g}, {mean_noise:.2g}, {mean_bias:.2g} | "
            f"{m('band_seconds'):.1f} / {m('seconds'):.0f} |"
        )
    return lines


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="arc,swirl,taper")
    p.add_argument("--seeds", default="reported")
    p.add_argument("--h", type=float, default=2.0)
    p.add_argument("--out", default=RESULTS)
    p.add_argument("--name", default="band_vessel")
    p.add_argument("--from-rows", action="store_true", help="rewrite the table from the saved rows")
    args = p.parse_args()
    rows_path = os.path.join(args.out, "studies", f"{args.name}_rows.json")
    if args.from_rows:
        with open(rows_path) as fh:
            rows = json.load(fh)
    else:
        seeds = {"reported": REPORTED_SEEDS, "dev": DEVELOPMENT_SEEDS}.get(args.seeds)
        seeds = seeds if seeds is not None else tuple(int(v) for v in args.seeds.split(","))
        rows = []
        for case in args.cases.split(","):
            for seed in seeds:
                rows.append(run(case, args.h, seed))
                print(json.dumps(rows[-1]), flush=True)
        os.makedirs(os.path.join(args.out, "studies"), exist_ok=True)
        with open(rows_path, "w") as fh:
            json.dump(rows, fh, indent=1)
    seeds_used = sorted({r["seed"] for r in rows})
    head = [
        f"The band of the axial WSS (velocity noise only) against the actual errors, h = {rows[0]['h']} mm, SNR 20, "
        f"seeds {', '.join(map(str, seeds_used))}, default options; the noise part and the bias on the "
        "reconstruction's own wall. Mean over the seeds (the wall mean's noise part and bias: RMS over the seeds); "
        "seconds: wall clock on 2 cores shared with other jobs (BLAS on one thread). Made by "
        "`python scripts/band_vessel.py` (its docstring defines the columns).",
        "",
    ]
    write_report(args.out, f"{args.name}.md", head + table(rows))


if __name__ == "__main__":
    main()
