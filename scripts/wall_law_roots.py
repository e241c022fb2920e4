#!/usr/bin/env python
"""The law of the wall's self-consistent scales: how many roots of u_tau l = nu, and how far apart.

For turbulent phantoms (Re_tau 180 in a circle and an ellipse, Re_tau 549 and 998), h = 1.5 and 0.6 mm,
SNR 25 and 10, seeds 100-101, default options: every root the first pass finds (its l/R, its criterion
above the chosen root's, the mean WSS of its fit relative to the chosen fit's). A rival root within
``near_wall.AMBIGUOUS_MARGIN`` of the chosen one would put the two scales' WSS spread in the record and
flag the slice when it exceeds the band. The roots are read by wrapping the private
``choice._wall_law_scale``. Writes ``scripts/results/wall_law_roots.md``.

    python scripts/wall_law_roots.py   (about 1 minute)
"""

from _report import RESULTS, write_report
from wss_nlp.models import near_wall as nw
from wss_nlp.synthetic import phantoms
from wss_nlp.parameters import layer as choice
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

CASES = ("turbulent", "turbulent-ellipse", "turbulent550", "turbulent1000")
SEEDS = (100, 101)


def main():
    found: list = []
    real_scale, real_choose = choice._wall_law_scale, choice.choose_layer
    disk_map: list = []

    def choose(vp, *args, **kwargs):
        disk_map[:] = [vp.disk_map]
        return real_choose(vp, *args, **kwargs)

    def mean_wss(score, x):  # over the viscosity: only ratios are reported
        _, basis, _, coefficients = score(x)
        return choice._mean_wall_slope(basis, coefficients, disk_map[0])

    def scale(score, *args):
        x, how, rivals = real_scale(score, *args)
        if args[-1] is None:  # the first pass (a dephasing pass follows the chosen root only)
            best = score(x)[0]
            found.append([(2.0**r, c - best, mean_wss(score, r) / mean_wss(score, x)) for c, r in rivals])
        return x, how, rivals

    choice._wall_law_scale, choice.choose_layer = scale, choose
    lines = [
        f"Seeds {SEEDS[0]}-{SEEDS[-1]}, default options, first pass. Made by `python scripts/wall_law_roots.py`.",
        "",
        "| flow | h [mm] | SNR | slices | roots per slice | other roots: criterion above the chosen | "
        "their mean WSS / the chosen fit's |",
        "|---|---|---|---|---|---|---|",
    ]
    closest = float("inf")
    for case in CASES:
        for h in (1.5, 0.6):
            for snr in (25.0, 10.0):
                found.clear()
                for seed in SEEDS:
                    acq, _ = phantoms.make_phantom(case, h_mm=h, snr=snr, seed=seed)
                    reconstruct(acq, ReconstructionOptions(uncertainty=False))
                rivals = [r for slice_rivals in found for r in slice_rivals]
                counts = sorted({1 + len(s) for s in found})
                gaps = f"{min(r[1] for r in rivals):.0f}-{max(r[1] for r in rivals):.0f}" if rivals else "-"
                ratios = f"{min(r[2] for r in rivals):.2f}-{max(r[2] for r in rivals):.2f}" if rivals else "-"
                closest = min([closest] + [r[1] for r in rivals])
                lines.append(
                    f"| {case} | {h:g} | {snr:g} | {len(found)} | {', '.join(map(str, counts))} | {gaps} | {ratios} |"
                )
    lines += ["", f"Closest rival: {closest:.0f} above the chosen root (ambiguity margin {nw.AMBIGUOUS_MARGIN:g})."]
    write_report(RESULTS, "wall_law_roots.md", lines)


if __name__ == "__main__":
    main()
