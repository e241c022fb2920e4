#!/usr/bin/env python
"""Does z-regularization help? Stacks reconstructed slice by slice vs with z-regularization (issue 6).

3D phantoms ``tapered`` and ``curved`` (``phantoms.make_stack``), 12 slices
2 mm apart, h = 1 mm, SNR 10 and 25, 3 seeds, default options otherwise (fixed beta 5e-8)
(dephasing pass on, no band); ``turbulent`` (a straight pipe with the Re_tau 549 DNS profile in every slice)
with the default beta rule, as the near-wall layer needs its BIC beta. "independent": ``--z-smoothing 0``;
"z-regularized": the default (second differences, l = one slice spacing);
"z-reg., first order": ``z_order = 1``; for ``turbulent`` also "z-reg., plain basis" (``--near-wall off``:
what z-regularized stacks did before they took the near-wall layer). Errors are means over all slices and
seeds (max over slices in parentheses). Writes ``scripts/results/stack_accuracy.md``.

    python scripts/stack_accuracy.py [--seeds 3]
"""

from dataclasses import replace

import numpy as np

from _report import study_parser, write_report
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.models import stack
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

VARIANTS = {
    "independent": stack.StackOptions(z_smoothing_mm=0.0),
    "z-regularized (default)": stack.StackOptions(),
    "z-reg., first order": stack.StackOptions(z_order=1),
}


def main(argv=None):
    p = study_parser(__doc__, seeds=3, h="1.0", snr="10,25")
    p.set_defaults(cases="tapered,curved,turbulent")
    args = p.parse_args(argv)
    lines = [
        "12 slices 2 mm apart, h = 1 mm; mean over slices and seeds (max over slices); beta fixed (5e-8) for "
        "tapered and curved, by the default rule for turbulent. Made by `python scripts/stack_accuracy.py`.",
        "",
        "| phantom | SNR | variant | radius rel. L2 err | WSS rel. L2 err | mean-WSS err |",
        "|---|---|---|---|---|---|",
    ]
    for case in args.cases.split(","):
        for snr in (float(s) for s in args.snr.split(",")):
            variants = dict(VARIANTS)
            if case == "turbulent":
                variants["z-reg., plain basis"] = stack.StackOptions()
            for name, st in variants.items():
                rad_e, wss_e, bias = [], [], []
                for seed in range(args.seeds):
                    acq, truth = phantoms.make_stack(
                        case, nz=12, h_mm=float(args.h), spacing_mm=2.0, snr=snr, seed=seed
                    )
                    rule = "balance" if case == "turbulent" else "fixed"
                    options = ReconstructionOptions(uncertainty=False, stack=st, choice=ChoiceOptions(beta_rule=rule))
                    if name == "z-reg., plain basis":
                        options = replace(options, velocity=replace(options.velocity, near_wall="off"))
                    res = reconstruct(acq, options)
                    for r, t in zip(res, truth.slices):
                        e = metrics.compare_slice(r, t)
                        rad_e.append(e.radius_rel_l2)
                        wss_e.append(e.wss_rel_l2)
                        bias.append(e.mean_wss_rel)
                lines.append(
                    f"| {case} | {snr:g} | {name} | {np.mean(rad_e):.2%} ({np.max(rad_e):.2%}) | "
                    f"{np.mean(wss_e):.1%} ({np.max(wss_e):.1%}) | {np.mean(bias):+.1%} |"
                )
                print(lines[-1], flush=True)
    write_report(args.out, "stack_accuracy.md", lines)


if __name__ == "__main__":
    main()
