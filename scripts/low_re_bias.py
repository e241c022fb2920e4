#!/usr/bin/env python
"""Where the low_re layer's small scale at SNR 10 comes from (issue 41): a diagnosis on development seeds.

At Re_tau 549 and SNR 10 the default (``low_re``) chose a layer scale ``l`` 1.0-1.3 % below the DNS's viscous
length ``R/Re_tau`` (``scripts/results/low_re_scale.md``, report seeds 100-107), and its mean WSS came out 2-3 %
high, while ``wall_law``'s scale looked unbiased. This script separates the ways the noise reaches ``l``. Its
default seeds are development seeds 300.. (``--first-seed``); the report seeds 100-109 served once, for the check
of the correction below (``low_re_bias_report*.md``).

``--part sources`` (default): for each family (``--near-wall low_re`` and ``wall_law``) and seed, four
reconstructions of the same phantom (same sub-voxel offset):

* ``A``: as acquired (noisy magnitude and phase);
* ``B``: the noise-free magnitude with the noisy phase: the geometry is noise-free, the velocity is not;
* ``C``: the noisy magnitude with the noise-free phase: the geometry sees the noise, the velocity does not;
* ``D``: both noise-free.

``B``, ``C`` and ``D`` are given the per-voxel velocity noise that ``A``'s layer choice estimated (by voxel; a voxel
``A`` did not fit takes ``A``'s largest), so that their layer criterion, and the beta it picks with the layer, are
``A``'s: only the data differ. Each row gives the chosen scale over ``R/Re_tau``, the fitted mean radius over the
true one, and the signed error of the mean WSS, mean +- standard error over the seeds.

``--part levels``: counterfactuals on the geometry's input, as acquired otherwise: ``base`` (the default);
``lumen`` (the normalization's lumen level ``m1``, Appendix B's histogram peak, replaced by the noise-free image's:
an oracle, to attribute the bias, not a method); ``rician`` (each fitted voxel's normalized magnitude corrected by
its expected bias under Rician noise at the fitted geometry: :func:`expected_normalized`, with the phantom's complex
noise level; a prototype here, not in the library, applied to the dephasing pass's data, so it acts only on slices
that get a dephasing pass); ``both``. Columns as above plus the WSS relative L2 error; ``--paired`` (two families)
adds the paired difference of their WSS errors on the same draws.

``--part geometry``: the same correction on any phantom with the default options (``--cases laminar``: whether
the other phantoms' rows would move): radius and WSS relative L2 errors and the mean WSS error.

    python scripts/low_re_bias.py [--part sources|levels|geometry] [--cases turbulent550] [--h 1.5,1.0] [--snr 10]
        [--seeds 8] [--first-seed 300] [--families low_re,wall_law]
        [--variants base,lumen,rician,both] [--paired] [--name ...]
"""

import collections
import dataclasses
import sys
import time

import numpy as np
from scipy import special

from _report import study_parser, write_report
from wss_nlp.analysis import metrics
from wss_nlp.models import geometry as geo
from wss_nlp.models import preprocess as pp
from wss_nlp.models import surround
from wss_nlp.models import velocity as vel
from wss_nlp.parameters import layer
from wss_nlp.pipeline import ReconstructionOptions, reconstruct, steps
from wss_nlp.synthetic import phantoms


# ---------------------------------------------------------------- instrumentation (study only)
# The layer choice is wrapped to record the velocity problem, the per-voxel noise and the choice of each call,
# and (when SIGMA_IMAGE is set) to replace the noise by a given per-voxel image: B-D reuse A's noise.
CALLS: list = []
SIGMA_IMAGE: dict = {}
_choose_layer = layer.choose_layer


def _recording_choose_layer(vp, sigma, mode, vopt, nu_m2_s=None, around=None, reynolds=None):
    if "image" in SIGMA_IMAGE:
        s = SIGMA_IMAGE["image"][vp.voxels.index]
        sigma = np.where(np.isfinite(s), s, np.nanmax(SIGMA_IMAGE["image"]))
    out = _choose_layer(vp, sigma, mode, vopt, nu_m2_s, around, reynolds)
    CALLS.append({"vp": vp, "sigma": np.asarray(sigma, float), "choice": out[1]})
    return out


layer.choose_layer = _recording_choose_layer

# The normalization's lumen level (Appendix B's m1), replaced when LEVEL holds one (the oracle of --part levels).
LEVEL: dict = {}
_peaks = surround._peaks


def _level_peaks(raw, velocity, venc, source):
    norm = _peaks(raw, velocity, venc, source)
    return dataclasses.replace(norm, m1=LEVEL["m1"]) if "m1" in LEVEL else norm


surround._peaks = _level_peaks

# The Rician expected-value correction of the dephasing pass's geometry data (when RICIAN holds the noise level).
RICIAN: dict = {}
_predict_dephasing = steps.predict_dephasing


def expected_normalized(f, m0: float, m1: float, sigma: float, lumen: float | None = None, n: int = 257):
    r"""``E[T((r - m0)/(m1 - m0))]`` for a voxel of lumen fraction ``f``: ``r`` Rician of amplitude
    ``S = L f + B (1 - f)`` and complex noise ``sigma`` per channel, ``T`` Appendix B's clip to [0, 1].

    ``L`` (``lumen``, default :math:`\sqrt{m_1^2 - \sigma^2}`) and :math:`B = \sqrt{\max(m_0^2 - \sigma^2, 0)}`
    invert the Rician mode, which the histogram peaks estimate (mode ~ :math:`\sqrt{S^2 + \sigma^2}`: exact at
    ``S = 0``, :math:`S + \sigma^2/2S` for large ``S``). The Rice density is integrated by the trapezoid rule on
    ``n`` points over ``S +- 7 sigma``.
    """
    f = np.asarray(f, float)
    big_l = np.sqrt(max(m1**2 - sigma**2, 0.0)) if lumen is None else lumen
    big_b = np.sqrt(max(m0**2 - sigma**2, 0.0))
    s = big_l * np.clip(f, 0.0, None) + big_b * (1 - np.clip(f, 0.0, 1.0))
    lo, hi = np.maximum(s - 7 * sigma, 0.0), s + 7 * sigma
    r = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.0, 1.0, n)[None, :]
    # Rice density r/sigma^2 exp(-(r^2 + S^2)/2 sigma^2) I_0(r S/sigma^2), with I_0(z) = i0e(z) e^z
    p = r / sigma**2 * np.exp(-((r - s[:, None]) ** 2) / (2 * sigma**2)) * special.i0e(r * s[:, None] / sigma**2)
    x = np.clip((r - m0) / (m1 - m0), 0.0, 1.0)
    return np.trapezoid(p * x, r, axis=1) / np.trapezoid(p, r, axis=1)


def _rician_predict_dephasing(data, vp, v, geometry, options, window=None):
    corr, v = _predict_dephasing(data, vp, v, geometry, options, window)
    if "sigma" in RICIAN and data.psf is None:
        problem = dataclasses.replace(data.problem, magnitude=data.magnitude)
        fit = geo.model_image(problem, options.geometry, geometry).ravel()
        e = expected_normalized(fit, data.norm.m0, data.norm.m1, RICIAN["sigma"], LEVEL.get("m1"))
        m = np.asarray(corr.magnitude, float).ravel() - (e - fit)
        corr = dataclasses.replace(corr, magnitude=m.reshape(np.shape(corr.magnitude)))
    return corr, v


steps.predict_dephasing = _rician_predict_dephasing


# ---------------------------------------------------------------- parts
def _options(family: str) -> ReconstructionOptions:
    return ReconstructionOptions(uncertainty=False, velocity=vel.VelocityOptions(near_wall=family))


def _run(acq, truth, opts) -> dict:
    CALLS.clear()
    res = reconstruct(acq, opts)[0]
    last = CALLS[-1]
    ell = truth.flow.radius_mm / truth.flow.re_tau
    cmp = metrics.compare_slice(res, truth)
    return {
        "l": last["choice"].scale_mm / ell,
        "R": float(res.geometry.coefficients[0]) / truth.flow.radius_mm,
        "W": cmp.mean_wss_rel,
        "E": cmp.wss_rel_l2,
        "call": last,
    }


def _pm(v, scale: float = 1.0, fmt: str = ".4f") -> str:
    v = scale * np.asarray(v, float)
    return f"{np.mean(v):{fmt}} +- {np.std(v, ddof=1) / np.sqrt(v.size):{fmt.lstrip('+')}}"


def sources(args, seeds) -> list[str]:
    lines = [
        f"Development seeds {seeds[0]}-{seeds[-1]}, `--near-wall <family>`; mean +- standard error over the seeds. "
        "A: as acquired; B: noise-free magnitude, noisy phase; C: noisy magnitude, noise-free phase; D: both "
        "noise-free; B-D with A's per-voxel velocity noise in the layer criterion.",
        "",
        "| phantom | h [mm] | SNR | family | data | l / l_true | R / R_true | mean WSS error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    given = dataclasses.replace(ReconstructionOptions().choice, noise_velocity=1.0)  # replaced per voxel below
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            for snr in (float(s) for s in args.snr.split(",")):
                for family in args.families.split(","):
                    opts = _options(family)
                    rows: dict = collections.defaultdict(lambda: collections.defaultdict(list))
                    for seed in seeds:
                        acq, truth = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
                        clean, _ = phantoms.make_phantom(case, h_mm=h, snr=None, seed=seed)
                        SIGMA_IMAGE.clear()
                        a = _run(acq, truth, opts)
                        image = np.full(acq.magnitude[0].size, np.nan)
                        image[a["call"]["vp"].voxels.index] = a["call"]["sigma"]
                        SIGMA_IMAGE["image"] = image
                        runs = {
                            "A": a,
                            "B": _run(dataclasses.replace(acq, magnitude=clean.magnitude), truth,
                                      dataclasses.replace(opts, choice=given)),
                            "C": _run(dataclasses.replace(acq, phase=clean.phase), truth, opts),
                            "D": _run(clean, truth, dataclasses.replace(opts, choice=given)),
                        }  # fmt: skip
                        SIGMA_IMAGE.clear()
                        for key, r in runs.items():
                            for q in "lRW":
                                rows[key][q].append(r[q])
                    for key in "ABCD":
                        r = rows[key]
                        lines.append(
                            f"| {case} | {h:g} | {snr:g} | {family} | {key} | {_pm(r['l'])} | {_pm(r['R'])} | "
                            f"{_pm(r['W'], 100, '+.2f')} % |"
                        )
                        print(lines[-1], flush=True)
    return lines


VARIANTS = ("base", "lumen", "rician", "both")


def levels(args, seeds) -> list[str]:
    variants = args.variants.split(",")
    lines = [
        f"Seeds {seeds[0]}-{seeds[-1]}, `--near-wall <family>`, as acquired; mean +- standard error over the seeds. "
        "base: the default; lumen: the normalization's lumen level m1 from the noise-free image (an oracle); "
        "rician: the dephasing pass's geometry data corrected by their expected Rician bias at the fitted geometry "
        "(prototype in this script, with the phantom's complex noise level); both."
        + (
            " Paired: the difference of the WSS relative L2 error of the two families on the same draws (first - "
            "second, points, mean +- standard error) and on how many seeds the first was better."
            if args.paired
            else ""
        ),
        "",
        "| phantom | h [mm] | SNR | family | geometry data | l / l_true | R / R_true | mean WSS error | "
        "WSS rel. L2 error |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    families = args.families.split(",")
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            for snr in (float(s) for s in args.snr.split(",")):
                errors: dict = {}
                for family in families:
                    opts = _options(family)
                    rows: dict = collections.defaultdict(lambda: collections.defaultdict(list))
                    for seed in seeds:
                        acq, truth = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
                        clean, _ = phantoms.make_phantom(case, h_mm=h, snr=None, seed=seed)
                        m1_clean = pp.histogram_peaks(clean.magnitude[0]).m1
                        for variant in variants:
                            LEVEL.clear()
                            RICIAN.clear()
                            if variant in ("lumen", "both"):
                                LEVEL["m1"] = m1_clean
                            if variant in ("rician", "both"):
                                RICIAN["sigma"] = 1.0 / snr  # the phantom's complex noise (lumen signal 1)
                            r = _run(acq, truth, opts)
                            for q in "lRWE":
                                rows[variant][q].append(r[q])
                        LEVEL.clear()
                        RICIAN.clear()
                    for variant in variants:
                        r = rows[variant]
                        errors[family, variant] = np.asarray(r["E"])
                        lines.append(
                            f"| {case} | {h:g} | {snr:g} | {family} | {variant} | {_pm(r['l'])} | {_pm(r['R'])} | "
                            f"{_pm(r['W'], 100, '+.2f')} % | {_pm(r['E'], 100, '.2f')} % |"
                        )
                        print(lines[-1], flush=True)
                if args.paired and len(families) == 2:
                    for variant in variants:
                        d = errors[families[0], variant] - errors[families[1], variant]
                        lines.append(
                            f"| {case} | {h:g} | {snr:g} | {families[0]} - {families[1]} | {variant} | | | | "
                            f"{_pm(d, 100, '+.2f')} ({int(np.sum(d < 0))}/{d.size} better) |"
                        )
                        print(lines[-1], flush=True)
    return lines


def geometry(args, seeds) -> list[str]:
    lines = [
        f"Seeds {seeds[0]}-{seeds[-1]}, default options; mean over the seeds. base: as the library does it; rician: "
        "the dephasing pass's geometry data corrected by their expected Rician bias (as in --part levels).",
        "",
        "| phantom | h [mm] | SNR | geometry data | radius rel. L2 error | WSS rel. L2 error | mean WSS error |",
        "|---|---|---|---|---|---|---|",
    ]
    for case in args.cases.split(","):
        for h in (float(x) for x in args.h.split(",")):
            for snr in (float(s) for s in args.snr.split(",")):
                out: dict = {"base": [], "rician": []}
                for seed in seeds:
                    acq, truth = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
                    for variant, values in out.items():
                        RICIAN.clear()
                        if variant == "rician":
                            RICIAN["sigma"] = 1.0 / snr
                        res = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
                        cmp = metrics.compare_slice(res, truth)
                        values.append((cmp.radius_rel_l2, cmp.wss_rel_l2, cmp.mean_wss_rel))
                    RICIAN.clear()
                for variant, values in out.items():
                    r, e, w = 100 * np.mean(values, axis=0)
                    lines.append(f"| {case} | {h:g} | {snr:g} | {variant} | {r:.3f} % | {e:.2f} % | {w:+.2f} % |")
                    print(lines[-1], flush=True)
    return lines


def main(argv=None) -> None:
    p = study_parser(__doc__, seeds=8, h="1.5,1.0", snr="10")
    p.set_defaults(cases="turbulent550")
    p.add_argument("--part", choices=("sources", "levels", "geometry"), default="sources")
    p.add_argument("--first-seed", type=int, default=300, help="development seeds 300..; 100-109 are the report's")
    p.add_argument("--families", default="low_re,wall_law", help="the --near-wall families compared")
    p.add_argument("--variants", default=",".join(VARIANTS), help="--part levels: the geometry data compared")
    p.add_argument("--paired", action="store_true", help="--part levels: paired rows for two families")
    p.add_argument("--name", default=None, help="file name of the table in --out")
    args = p.parse_args(argv)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    t0 = time.perf_counter()
    lines = {"sources": sources, "levels": levels, "geometry": geometry}[args.part](args, seeds)
    made = "Made by `python scripts/low_re_bias.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])) + "`."
    lines = [made, ""] + lines + ["", f"({time.perf_counter() - t0:.0f} s)"]
    write_report(args.out, args.name or f"low_re_bias_{args.part}.md", lines)


if __name__ == "__main__":
    main()
