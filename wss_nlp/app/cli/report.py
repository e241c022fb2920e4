"""``wss-nlp analyze``, ``compare`` and ``sensitivity``: what a result file says, how it was chosen, its errors."""

from __future__ import annotations

import json

import numpy as np
from ...io import files as wio
from ...analysis import metrics
from ...models import near_wall as nw
from ...models import surround
from ...io import outputs
from ...errors import InputError
from ...models.measurement import DEPHASING_THRESHOLD
from ...pipeline.driver import KSPACE_PASS_TOL
from ..table import LEFT, RIGHT, text_table


def _error_table(rows) -> str:
    """``(quantity, formatted value)`` rows as the two-column table ``compare`` and ``demo`` print."""
    return text_table(rows, headers=("quantity", "value"))


def _chosen_table(values, chosen: str, headers: tuple[str, str], fmt: str, indent: str = "    ") -> str:
    """Candidate models and their criterion values, smallest first, the chosen one marked (``analyze``)."""
    rows = [
        (model, format(value, fmt), "<- chosen" if model == chosen else "")
        for model, value in sorted(values, key=lambda kv: kv[1])
    ]
    return text_table(rows, headers=(*headers, ""), align=(RIGHT, RIGHT, LEFT), indent=indent)


def _errors_rows(err: metrics.Errors):
    return [
        ("radius rel. L2 error", f"{err.radius_rel_l2:.3%}"),
        ("radius max. error [mm]", f"{err.radius_max_mm:.4f}"),
        ("WSS rel. L2 error", f"{err.wss_rel_l2:.2%}"),
        ("mean WSS reconstructed [Pa]", f"{err.mean_wss_pa:.5g}"),
        ("mean WSS true [Pa]", f"{err.mean_wss_true_pa:.5g}"),
        ("mean WSS rel. error", f"{err.mean_wss_rel:+.2%}"),
    ]


def cmd_compare(args) -> int:
    from .vessel import compare_volume, is_vessel_result

    if is_vessel_result(args.result):
        return compare_volume(args)

    layout, truth_layout = wio.result_layout(args.result), wio.result_layout(args.truth)
    if ("cine" in layout) != ("cine" in truth_layout):
        raise InputError(
            f"{args.result} is a {layout} result but {args.truth} a {truth_layout} truth: compare needs a "
            "time-resolved truth for a time-resolved result (wss-nlp phantom --case cine --truth)"
        )
    if "cine" in layout:
        return _compare_cine(args)
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


def _compare_cine(args) -> int:
    """``compare`` of a time-resolved result: the frames' mean WSS, TAWSS, OSI, radius and the fitted viscosity."""
    import h5py

    rec, truths = wio.read_result(args.result), wio.read_result(args.truth)
    models = wio.read_cine_models(args.result)
    if len(truths) > 1 and len(truths) != len(rec):
        raise InputError(f"{args.truth} has {len(truths)} slices but {args.result} has {len(rec)}")
    with h5py.File(args.truth, "r") as f:
        true_mu, rho = f.attrs.get("viscosity_pa_s"), f.attrs.get("density_kg_m3")
    true_nu = float(true_mu / rho) if true_mu is not None and rho is not None else None
    for i, d in enumerate(rec):
        truth = truths[i] if len(truths) > 1 else truths[0]
        for key in ("time_ms", "mean_tau_t"):
            if key not in d or key not in truth:
                raise InputError(f"{args.result} or {args.truth}: {d['name']} lacks the time-resolved {key}")
        try:
            err = metrics.compare_cine(d, truth, models.get(d["name"]), true_nu)
        except InputError as exc:
            raise InputError(f"{args.result} against {args.truth}: {exc}") from None
        rows = [
            ("frames", f"{err.frames}"),
            ("worst frame |mean WSS err| / peak", f"{err.worst_frame_rel_peak:.2%}"),
            ("  at [ms]", f"{err.worst_frame_time_ms:g}"),
            ("rms frame error / peak", f"{err.rms_frame_rel_peak:.2%}"),
            ("TAWSS rel. error (wall mean)", "not computed" if np.isnan(err.tawss_rel) else f"{err.tawss_rel:+.2%}"),
            ("OSI error (wall mean)", "not computed" if np.isnan(err.osi_abs) else f"{err.osi_abs:+.4f}"),
            ("radius max. error [mm]", f"{err.radius_max_mm:.4f}"),
        ]
        if err.scale != 1.0:
            rows.insert(1, ("stated / true viscosity", f"{err.scale:.4g}"))
        if np.isfinite(err.nu_rel):
            rows += [("fitted kinematic viscosity rel. error", f"{err.nu_rel:+.2%}"),
                     ("  truth inside its 95 % interval", "yes" if err.nu_inside else "NO")]  # fmt: skip
        scaled = " (reference: the truth's WSS times the stated over the true viscosity: the stress scales with it)"
        print(f"{d['name']} against {args.truth}" + (scaled if err.scale != 1.0 else "") + ":")
        print(_error_table(rows))
    return 0


def cmd_analyze(args) -> int:
    from .vessel import analyze_volume, is_vessel_result

    if is_vessel_result(args.result):
        return analyze_volume(args)
    outputs.check_outputs(folders={"--figures": args.figures}, inputs=[args.result])
    layout = wio.result_layout(args.result)
    choices = _one_slice(wio.read_choices(args.result), args)
    if "cine" in layout:
        _analyze_cycle(args.result, choices)
    else:
        _analyze_choices(choices)
    for name, rec in _one_slice(wio.read_near_wall(args.result), args).items():
        print(f"{name}: near-wall model '{rec['model']}'" + _layer_text(rec))
        print(f"    {rec['criterion']}")
        print(_chosen_table(rec["values"].items(), rec["model"], ("model", "criterion"), ".2f"))
        if rec["ambiguous"]:
            print(f"    AMBIGUOUS: margin {rec['margin']:.2f}; another model fits almost as well")
    for name, rec in _one_slice(wio.read_dephasing(args.result), args).items():
        print(f"{name}: {_dephasing_text(rec)}")
    # the surround model, the phase offset (issue 39)
    for name, rec in _one_slice(surround.read_tissue(args.result), args).items():
        for line in surround.report_lines(rec):
            print(f"{name}: {line}")
    if args.figures:
        from ..plotting import save_parameter_figures

        flat = {name.replace("/", "_"): per for name, per in choices.items()}  # one figure file per record
        with outputs.StagedFolder(args.figures) as staged:
            save_parameter_figures(flat, str(staged.path), fmt=args.figure_format, dpi=args.dpi)
            paths = staged.commit()
        print(f"{len(paths)} figure(s) in {args.figures}")
    return 0


def _analyze_choices(choices: dict) -> None:
    """Each record's alpha and beta choice with its curve (a slice or a stack's slices)."""
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
                crit = bool(ch.criterion.size)
                rows = [
                    (f"{p:.4g}", f"{ch.residuals[i]:.4g}")
                    + ((f"{ch.criterion[i]:.4g}",) if crit else ())
                    + ("<- chosen" if p == ch.chosen else "",)
                    for i, p in enumerate(ch.parameters)
                ]
                heads = ("parameter", "residual") + (("criterion",) if crit else ()) + ("",)
                print(text_table(rows, headers=heads, align=(RIGHT,) * (len(heads) - 1) + (LEFT,), indent="    "))


def _analyze_cycle(path: str, choices: dict) -> None:
    """A time-resolved result: each slice's model over the cycle and why, the viscosity the frames imply, and
    one line per frame for its alpha and beta (the frames' full curves: ``--figures``)."""
    for name, rec in wio.read_cine_models(path).items():
        print(f"{name}: velocity over the cycle: {_cycle_model_text(rec)}")
        if rec.get("criterion"):
            print(f"    {rec['criterion']}")
        chosen = {"momentum": f"momentum K={rec.get('harmonics')}"}.get(rec.get("model", ""), rec.get("model"))
        if rec.get("bic"):
            print(_chosen_table(rec["bic"].items(), chosen, ("velocity model", "BIC"), ".1f"))
        if rec.get("margin") is not None:
            print(f"    margin {rec['margin']:.1f} beyond the {rec.get('evidence_required', 10):g} BIC units required")
        walls = rec.get("walls", {})
        if walls:
            print(f"    walls: {walls.get('how', '')}")
        viscosity = rec.get("viscosity", {})
        if viscosity:
            print(f"    viscosity: {_viscosity_text(viscosity)}")
        if rec.get("tawss_note"):
            print(f"    TAWSS and OSI: {rec['tawss_note']}")
        if rec["failed_frames"]:
            print(f"    failed frames: {rec['failed_frames']}")
        rows = []
        for k, t in enumerate(rec["time_ms"]):
            per = choices.get(f"{name}/frame_{k:03d}", {})
            rules = ", ".join(f"{c.name} {c.rule}" + ("" if c.satisfied else " (not reached)") for c in per.values())
            alpha = rec["alpha"][k] if k < rec["alpha"].size else np.nan
            beta = rec["beta"][k] if k < rec["beta"].size else np.nan
            rows.append((f"{k}", f"{t:.4g}", f"{alpha:.4g}", f"{beta:.4g}", rules))
        heads = ("frame", "t [ms]", "alpha", "beta", "rules")
        print(text_table(rows, headers=heads, align=(RIGHT,) * 4 + (LEFT,), indent="    "))


def _cycle_model_text(rec: dict) -> str:
    model = rec.get("model", "independent")
    if model == "momentum":
        return (f"the momentum model (Womersley) with {rec.get('harmonics')} harmonic(s), fitted to frames "
                f"{rec.get('frames_used')}")  # fmt: skip
    if model == "temporal":
        return "the frames' fits tied by a periodic temporal prior"
    return "each frame's own fit"


def _viscosity_text(v: dict) -> str:
    stated = f"stated {1e3 * v['stated_pa_s']:.4g} mPa s, density {v['density_kg_m3']:g} kg/m^3"
    if v.get("mode") != "fit":
        return f"{stated}; the Stokes layer from it (Womersley number {v['womersley_number']:.3g})"
    lo, hi = v["implied_interval_pa_s"]
    text = (
        f"{stated}; the frames imply {1e3 * v['implied_pa_s']:.4g} mPa s ({100 * v['level']:.0f} % interval "
        f"{1e3 * lo:.4g}-{1e3 * hi:.4g}; kinematic {v['nu_m2_s']:.4g} m^2/s, Womersley number "
        f"{v['womersley_number']:.3g}), walls moved {1e3 * v['wall_offset_mm']:+.3g} um "
        f"(+- {1e3 * v['wall_offset_std_mm']:.2g} um); "
    )
    if v.get("at_bound"):
        return text + "AT THE BOUND of the fit: the flow may not be Womersley flow"
    if not v.get("determined"):
        return text + "the data do not determine it"
    return text + ("the stated value lies inside the interval" if v["agrees"] else "the stated value lies OUTSIDE")


def _one_slice(per_slice: dict, args) -> dict:
    """The records of slice ``--slice K`` alone (every slice without it); a K the file lacks is bad input."""
    if getattr(args, "slice", None) is None:
        return per_slice
    import h5py

    with h5py.File(args.result, "r") as f:
        names = sorted(k for k in f if k.startswith("slice_"))
    name = f"slice_{args.slice:03d}"
    if name not in names:
        raise InputError(
            f"{args.result}: no slice {args.slice} (--slice); the file has slices 0 to {len(names) - 1}"
            if names
            else f"{args.result}: no slices in this file (--slice)"
        )
    return {k: v for k, v in per_slice.items() if k == name or k.startswith(name + "/")}  # a cine slice's frames


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
    from .vessel import is_vessel_result, sensitivity_volume

    if is_vessel_result(args.result):
        return sensitivity_volume(args)
    layout = wio.result_layout(args.result)
    recs = wio.read_sensitivity(args.result)
    if "cine" in layout:
        _cycle_sensitivity(args.result)
    elif not recs:
        import h5py

        with h5py.File(args.result, "r") as f:
            options = json.loads(f.attrs.get("options_json", "{}"))
            stack = "stack_json" in f.attrs
        if options.get("uncertainty", True) is False:
            raise InputError(f"{args.result}: reconstructed with --no-uncertainty: no band or sensitivity records; "
                             "reconstruct without it")  # fmt: skip
        if stack:
            return _stack_band(args.result)
        raise InputError(f"{args.result}: no sensitivity records (a baseline method, or written by an older version)")
    for name, rec in recs.items():
        print(f"{name}: mean WSS {rec['mean_pa']:.4g} Pa +- {rec['mean_std_pa']:.2g} Pa (1 std, linearized)")
        rows = [(cause, f"{delta:+.3e}", f"{delta / rec['mean_pa']:+.2%}") for cause, delta in sensitivity_table(rec)]
        print(text_table(rows, headers=("what changes", "mean WSS change [Pa]", "relative"), indent="  "))
    return 0


def _stack_band(path: str) -> int:
    """A z-coupled stack: its joint band per slice; per-parameter derivatives exist for slices solved alone."""
    print(
        f"{path}: a z-coupled stack: its band is the stack's joint linearization (wss/tau_std_pa); the "
        "per-parameter sensitivities are computed for slices reconstructed alone (reconstruct one slice for them)"
    )
    for d in wio.read_result(path):
        if d.get("failed"):
            print(f"{d['name']}: FAILED slice")
            continue
        std = d.get("mean_std", float("nan"))
        print(f"{d['name']}: mean WSS {d['mean_tau']:.4g} Pa +- {std:.2g} Pa (1 std, the stack's joint band)")
    return 0


def _cycle_sensitivity(path: str) -> None:
    """A time-resolved result: what moves each slice's cycle-averaged WSS (the momentum model's record), before the
    tables of the frames that kept their own fit."""
    for name, rec in wio.read_cine_models(path).items():
        sens = rec.get("sensitivity")
        if rec.get("model") != "momentum" or not sens:
            why = "each frame's own fit: the tables of those frames follow" if rec.get("model") != "temporal" else \
                "the temporal prior: its band (wss/tau_std_pa) holds the velocity noise only"  # fmt: skip
            print(f"{name}: velocity over the cycle from {why}")
            continue
        print(f"{name}: the momentum model's sensitivities (linearized; the velocity noise through the model, its "
              "viscosity and wall offset included)")  # fmt: skip
        for what, key in (("cycle-averaged mean WSS", "time_mean"), ("TAWSS (wall mean)", "tawss")):
            value = sens[f"{key}_pa"]
            print(f"  {what} {value:.4g} Pa +- {sens[f'{key}_std_pa']:.2g} Pa (1 std)")
            rows = [
                ("stated viscosity +10 %", 0.1 * value),
                ("fitted viscosity + 1 std", sens[f"{key}_d_ln_nu_pa"] * sens["std_ln_nu"]),
                ("wall offset + 1 std", sens[f"{key}_d_offset_pa_per_mm"] * sens["std_offset_mm"]),
                ("viscosity's layer +10 %", sens[f"{key}_d_ln_nu_pa"] * np.log(1.1)),
                ("velocity noise (1 std)", sens[f"{key}_std_pa"]),
            ]
            cells = [
                (cause, f"{delta:+.3e}", f"{delta / value if value else np.nan:+.2%}")
                for cause, delta in sorted(rows, key=lambda r: -abs(r[1]))
            ]
            print(text_table(cells, headers=("what changes", "change [Pa]", "relative"), indent="    "))
