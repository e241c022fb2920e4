#!/usr/bin/env python
"""Would a hold-out check flag the offset a polynomial cannot interpolate into the vessel? (issue 39, a doubt)

The offset flag (``wss_nlp.models.offset``) asks two things of the fitted offset at the vessel: its deviation from
the static voxels' noise, and its change with one polynomial order more (the order spread). On a field the
polynomials do not hold (the smooth family's bump under the lumen) the order spread was a third to a fifth of the
offset actually left, so a residual of 0.3-0.5 % of the venc might pass unflagged. A more principled check is a
hold-out: refit the chosen order on the static tissue away from the vessel and predict the static tissue near it
(within two vessel radii of its centre); a noise-weighted mean residual there beyond its own noise deviation says
the field changes near the vessel in a way the far tissue does not show.

This study computes that check on the in-vivo phantom's slices (the preprocessing's own static tissue, inliers and
noise, caught from ``offset.correct``) and sets it beside the offset actually left at the vessel: per slice the true
residual, the fit's deviation, the order spread and the hold-out bias with its deviation. The check is not in the
library; this table is why (the session note and the docs say what it shows).

    python scripts/offset_holdout.py [--seeds dev|reported] [--h 1.5,1.0,0.6]

Writes ``scripts/results/offset_holdout[_dev].md``.
"""

import argparse
import warnings

import numpy as np

from _report import RESULTS, write_report
from wss_nlp.models import offset as off
from wss_nlp.models import surround
from wss_nlp.synthetic import invivo

NEAR_RADII = 2.0  # the held-out static tissue: within this many vessel radii of its centre


def holdout(fit: off.OffsetFit, pts, values, noise, near) -> tuple[float, float]:
    """``(bias, std)`` in m/s: the chosen order refitted on the inliers away from the vessel predicts those near it.

    ``bias = sum w r / sum w`` over the near inliers (``w = 1 / noise^2``, ``r`` the prediction's residual); ``std``
    from the near voxels' noise and the far fit's covariance (both scaled by chi^2/dof where it exceeds 1)."""
    inl = fit.inliers
    p, y, w, nr = pts[inl], values[inl], 1.0 / noise[inl] ** 2, near[inl]
    a = off.design((p - fit.centre) / fit.scale, fit.order)
    far = ~nr
    if nr.sum() < 12 or far.sum() < off.MIN_PER_COEFFICIENT * a.shape[1]:
        return float("nan"), float("nan")
    sw = np.sqrt(w[far])
    c = np.linalg.lstsq(a[far] * sw[:, None], y[far] * sw, rcond=None)[0]
    inflate = max(1.0, float(np.sum(w[far] * (y[far] - a[far] @ c) ** 2)) / max(int(far.sum()) - a.shape[1], 1))
    cov = np.linalg.pinv(a[far].T @ (a[far] * w[far][:, None])) * inflate
    wn = w[nr]
    bias = float(np.sum(wn * (y[nr] - a[nr] @ c)) / wn.sum())
    g = wn @ a[nr] / wn.sum()
    return bias, float(np.sqrt(inflate / wn.sum() + g @ cov @ g))


def row(case: str, h: float, seed: int) -> dict:
    acq, truth = invivo.make_invivo(case, h, seed=seed)
    caught: dict = {}
    real = off.correct

    def spy(velocity, magnitude, spacing, origin, sigma, flowing, vessel_mm, radius, venc, **kw):
        out = real(velocity, magnitude, spacing, origin, sigma, flowing, vessel_mm, radius, venc, **kw)
        caught.update(args=(velocity, magnitude, spacing, origin, sigma, vessel_mm, radius, venc), out=out)
        return out

    off.correct = spy
    try:
        surround.preprocess(acq.magnitude[0], acq.velocity_images()[0], acq.grid, acq.source, venc=acq.venc_m_s)
    finally:
        off.correct = real
    u, mag, spacing, origin, sigma, vessel_mm, radius, venc = caught["args"]
    _, rec, static = caught["out"]  # static: the fit's inliers on the image
    coords = off.coordinates(u.shape, spacing, origin)
    pts = np.stack([c[static] for c in coords], axis=1)
    noise = venc * sigma / (np.pi * np.asarray(mag)[static])
    fit = off.fit_offset(pts, np.asarray(u)[static], noise)  # the same fit on its own consensus
    near = np.hypot(*(pts - np.asarray(vessel_mm)[None, :]).T) < NEAR_RADII * radius
    bias, std = holdout(fit, pts, np.asarray(u)[static], noise, near)
    cy, cx = vessel_mm
    true_c = float(truth.offset_at(np.array([cx]), np.array([cy]))[0])
    return {
        "case": case, "h": h, "seed": seed, "family": invivo.OFFSET_FAMILIES[seed % 3],
        "left": 100 * (true_c - rec.at_vessel_m_s) / venc, "std": 100 * rec.at_vessel_std_m_s / venc,
        "spread": 100 * rec.at_vessel_order_spread_m_s / venc, "bias": 100 * bias / venc, "bias_std": 100 * std / venc,
        "flagged": rec.uncertain,
    }  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", choices=("reported", "dev"), default="reported")
    p.add_argument("--cases", default="laminar,turbulent")
    p.add_argument("--h", default="1.5,1.0,0.6")
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args()
    warnings.simplefilter("ignore", DeprecationWarning)
    seeds = invivo.REPORTED_SEEDS if args.seeds == "reported" else invivo.DEV_SEEDS
    rows = [row(c, float(h), s) for c in args.cases.split(",") for h in args.h.split(",") for s in seeds]
    lines = [
        f"The offset left at the vessel and what would flag it, {args.seeds} seeds {list(seeds)}, SNR 25, all in % of "
        "the venc (`scripts/offset_holdout.py`): left = true minus fitted offset at the vessel's centre; std = its "
        "predicted deviation; spread = the order spread; hold-out = the mean residual of the static tissue within "
        f"{NEAR_RADII:g} vessel radii predicted from the tissue beyond, +- its deviation; flagged = the library's flag "
        "(std or spread > 0.1 %).",
        "",
        "| case | h [mm] | seed | offset field | left | std | spread | hold-out | significant (> 2 dev.) | flagged |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sig = abs(r["bias"]) > 2 * r["bias_std"]
        lines.append(
            f"| {r['case']} | {r['h']:g} | {r['seed']} | {r['family']} | {r['left']:+.3f} | {r['std']:.3f} | "
            f"{r['spread']:.3f} | {r['bias']:+.3f} +- {r['bias_std']:.3f} | {'yes' if sig else 'no'} | "
            f"{'yes' if r['flagged'] else 'no'} |"
        )
    unflagged_sig = [r for r in rows if not r["flagged"] and abs(r["bias"]) > 2 * r["bias_std"]]
    missed = [r for r in rows if not r["flagged"] and abs(r["left"]) > 0.3]
    lines += [
        "",
        f"Slices the library leaves unflagged with more than 0.3 % left: {len(missed)}; unflagged slices the hold-out "
        f"would flag (|bias| > 2 deviations): {len(unflagged_sig)}. The hold-out's own deviation, median "
        f"{np.median([r['bias_std'] for r in rows]):.3f} % (the fit's: {np.median([r['std'] for r in rows]):.3f} %).",
    ]
    write_report(args.out, f"offset_holdout{'' if args.seeds == 'reported' else '_dev'}.md", lines)


if __name__ == "__main__":
    main()
