"""``wss-nlp analyze``, ``compare`` and ``sensitivity``: what a result file says, how it was chosen, its errors."""

from __future__ import annotations

import numpy as np
from ...io import files as wio
from ...analysis import metrics
from ...models import near_wall as nw
from ...models import surround
from ...io import outputs
from ...errors import InputError
from ...models.measurement import DEPHASING_THRESHOLD
from ...pipeline.driver import KSPACE_PASS_TOL


def _error_table(rows) -> str:
    head = f"{'quantity':<34}{'value':>14}"
    lines = [head, "-" * len(head)]
    lines += [f"{k:<34}{v:>14}" for k, v in rows]
    return "\n".join(lines)


def _errors_rows(err: metrics.Errors):
    return [
        ("radius rel. L2 error", f"{err.radius_rel_l2:.3%}"),
        ("radius max. error [mm]", f"{err.radius_max_mm:.4f}"),
        ("WSS rel. L2 error", f"{err.wss_rel_l2:.2%}"),
        ("mean WSS reconstructed [Pa]", f"{err.mean_wss_pa:.5g}"),
        ("mean WSS true [Pa]", f"{err.mean_wss_true_pa:.5g}"),
        ("mean WSS rel. error", f"{err.mean_wss_rel:+.2%}"),
    ]


def _refuse_time_resolved(path: str, role: str) -> None:
    """compare takes single-frame results and truths; a cine's are refused by name, not by a traceback."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            cine = "trigger_times_ms" in f.attrs
    except OSError:
        return  # the readers below name what is wrong with the file
    if cine:
        raise InputError(
            f"{path}: a time-resolved (cine) {role}; 'compare' compares single-frame results with a phantom's truth "
            "(a cine's TAWSS and OSI against its truth: scripts/cine.py)"
        )


def cmd_compare(args) -> int:
    _refuse_time_resolved(args.result, "result")
    _refuse_time_resolved(args.truth, "truth")
    truths = metrics.TruthTable.all_from_file(args.truth)
    rec = wio.read_result(args.result)
    if len(truths) > 1 and len(truths) != len(rec):
        raise InputError(f"{args.truth} has {len(truths)} slices but {args.result} has {len(rec)}")
    for i, d in enumerate(rec):
        truth = truths[i] if len(truths) > 1 else truths[0]
        if d.get("failed"):
            print(f"{d['name']}: FAILED slice, nothing to compare")
            continue
        if "wall_x" not in d:
            raise InputError(f"{args.result}: {d['name']} has no wss/wall_x_mm; was it written by wss-nlp?")
        err = metrics.compare(
            d["center"], d["phi"], d["radius"], d["wall_x"], d["wall_y"], d["tau"], d["mean_tau"], truth
        )
        print(f"{d['name']} against {args.truth}:")
        print(_error_table(_errors_rows(err)))
    return 0


def cmd_analyze(args) -> int:
    outputs.check_outputs(folders={"--figures": args.figures}, inputs=[args.result])
    choices = wio.read_choices(args.result)
    for name, per in choices.items():
        print(f"{name}:")
        if not per:
            print("  (no parameter-choice record: written by an older version)")
        for ch in per.values():
            print(f"  {ch.name}: rule '{ch.rule}', chosen {ch.chosen:.4g}")
            if ch.rule == "discrepancy":
                print(
                    f"    noise {ch.noise:.4g} ({ch.noise_method}); threshold tau x noise = {ch.threshold:.4g}"
                    + ("" if ch.satisfied else "; NOT reached (model error dominates)")
                )
            if ch.rule == "balance":
                what, unit = ("radius", "mm") if ch.name == "alpha" else ("WSS", "m/s")
                print(
                    f"    noise {ch.noise:.4g} {unit} ({ch.noise_method}); criterion = largest {what} difference "
                    f"to a smaller {ch.name} in noise standard deviations, admissible <= kappa = {ch.tau:g}"
                )
            if ch.parameters.size:
                head = f"    {'parameter':>12} {'residual':>12}" + (f" {'criterion':>12}" if ch.criterion.size else "")
                print(head)
                for i, p in enumerate(ch.parameters):
                    mark = "  <- chosen" if p == ch.chosen else ""
                    crit = f" {ch.criterion[i]:12.4g}" if ch.criterion.size else ""
                    print(f"    {p:12.4g} {ch.residuals[i]:12.4g}{crit}{mark}")
    for name, rec in wio.read_near_wall(args.result).items():
        print(f"{name}: near-wall model '{rec['model']}'" + _layer_text(rec))
        print(f"    {rec['criterion']}")
        for model, value in sorted(rec["values"].items(), key=lambda kv: kv[1]):
            print(f"    {model:>12}: {value:12.2f}" + ("  <- chosen" if model == rec["model"] else ""))
        if rec["ambiguous"]:
            print(f"    AMBIGUOUS: margin {rec['margin']:.2f}; another model fits almost as well")
    for name, rec in wio.read_dephasing(args.result).items():
        print(f"{name}: {_dephasing_text(rec)}")
    for name, rec in surround.read_tissue(args.result).items():  # the surround model, the phase offset (issue 39)
        for line in surround.report_lines(rec):
            print(f"{name}: {line}")
    if args.figures:
        from ..plotting import save_parameter_figures

        with outputs.StagedFolder(args.figures) as staged:
            save_parameter_figures(choices, str(staged.path))
            paths = staged.commit()
        print(f"{len(paths)} figure(s) in {args.figures}")
    return 0


def _dephasing_text(rec: dict) -> str:
    """One line on a slice's dephasing passes (:func:`wss_nlp.io.files.read_dephasing`)."""
    text = (
        f"dephasing: {rec['passes']} pass(es) on corrected magnitudes; smallest predicted magnitude factor "
        f"{rec['min_factor']:.4g} (a pass below {1 - DEPHASING_THRESHOLD:g})"
    )
    if rec["next_move"] is not None:
        text += (
            f"; a further pass predicted to move the wall {rec['next_move']:.2g} voxel "
            f"(passes stop below {KSPACE_PASS_TOL:g})"
        )
    return text


def _layer_text(rec: dict) -> str:
    if rec["model"] == "plain":
        return ""
    std_log = rec.get("scale_std_log", float("nan"))
    pm = f" +- {100 * (np.exp(std_log) - 1):.2g} %" if np.isfinite(std_log) else ""
    scale = f"l = {rec['scale_mm'] * 1000:.3g} um{pm} (l/R = {rec['scale_ratio']:.3g})"
    wss_spread = rec.get("scale_wss_spread", float("nan"))
    if wss_spread is not None and np.isfinite(wss_spread):  # scales the data hardly tell apart, and their WSS
        lo, hi = rec["scale_interval"]
        scale += (
            f"; l/R {lo:.3g}-{hi:.3g} within {nw.AMBIGUOUS_MARGIN:g} of its criterion, "
            f"mean WSS {100 * wss_spread:.2g} % apart"
        )
    return f", layer scale {scale}, margin {rec['margin']:.3g}"


def sensitivity_table(rec: dict) -> list[tuple[str, float]]:
    """What moves the mean WSS, largest first: ``(cause, change of mean tau in Pa)``.

    Parameters change by +10 % (alpha, beta, gamma) or by half a voxel
    (centre), to first order; noise enters as one standard deviation of the
    linearized band.
    """
    d = dict(zip(rec["names"], rec["d_mean"]))
    h = rec["h_mm"]
    rows = [
        ("alpha +10 %", 0.1 * rec["alpha"] * d["alpha"]),
        ("beta +10 %", 0.1 * rec["beta"] * d["beta"]),
        ("gamma +10 %", 0.1 * rec["gamma"] * d["gamma"]),
        ("centre x + h/2", 0.5 * h * d["center_x"]),
        ("centre y + h/2", 0.5 * h * d["center_y"]),
        ("magnitude noise (1 std)", rec["mean_std_magnitude_pa"]),
        ("velocity noise (1 std)", rec["mean_std_velocity_pa"]),
    ]
    return sorted(rows, key=lambda r: -abs(r[1]))


def cmd_sensitivity(args) -> int:
    recs = wio.read_sensitivity(args.result)
    if not recs:
        raise InputError(f"{args.result}: no sensitivity records; reconstruct without --no-uncertainty")
    for name, rec in recs.items():
        print(f"{name}: mean WSS {rec['mean_pa']:.4g} Pa +- {rec['mean_std_pa']:.2g} Pa (1 std, linearized)")
        print(f"  {'what changes':<26} {'mean WSS change [Pa]':>22} {'relative':>10}")
        for cause, delta in sensitivity_table(rec):
            print(f"  {cause:<26} {delta:>+22.3e} {delta / rec['mean_pa']:>+10.2%}")
    return 0
