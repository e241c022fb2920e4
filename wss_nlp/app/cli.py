"""Command-line interface: ``wss-nlp {demo, reconstruct, phantom, analyze, sensitivity, compare, export, sweep, ...}``.

Exit codes: 0 success, 1 solver failure, 2 bad input or usage.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
import time

import numpy as np

from .. import __version__
from ..io import files as wio
from ..analysis import metrics
from ..models import near_wall as nw
from ..io import outputs
from ..synthetic import phantoms
from ..core import schema
from ..errors import InputError, WssNlpError
from ..models.kspace import AcquisitionOptions
from ..models.measurement import DEPHASING_THRESHOLD
from ..pipeline.reconstruct import KSPACE_PASS_TOL, ReconstructionOptions, reconstruct


def _add_reconstruction_arguments(p: argparse.ArgumentParser) -> None:
    """Every reconstruction option, from the options schema (:mod:`wss_nlp.core.schema`)."""
    schema.add_arguments(p, ReconstructionOptions)


def options_from_args(args) -> ReconstructionOptions:
    return schema.from_args(ReconstructionOptions, args)


def _progress(stream):
    t0 = time.perf_counter()

    def report(done, total, res):
        if isinstance(res, wio.FailedSlice):
            stream.write(f"  slice {done}/{total}: FAILED ({res.reason})\n")
            stream.flush()
            return
        flag = "" if res.converged else "  [NOT CONVERGED]"
        stream.write(
            f"  slice {done}/{total}: mean WSS {res.wss.mean:.4g} Pa, {time.perf_counter() - t0:.1f} s elapsed{flag}\n"
        )
        stream.flush()

    return report


def _warn(results, stream) -> None:
    for r in results:
        for msg in r.warnings:
            stream.write(f"wss-nlp: warning: {msg}\n")


def _write_truth(path, truth) -> None:
    """Exact geometry and WSS of a phantom (one group per slice for a stack phantom)."""
    from ..core import radius as rad

    stack = isinstance(truth, phantoms.StackTruth)
    slices = truth.slices if stack else [truth]
    cases = phantoms.STACK_CASES if stack else phantoms.CASES
    with wio.atomic_h5(path) as f:
        for k, v in wio.provenance({"truth": truth.parameters}).items():
            f.attrs[k] = v
        f.attrs["case"] = truth.name
        f.attrs["description"] = cases[truth.name][1]
        for i, sl in enumerate(slices):
            s = metrics.truth_samples(sl)
            g = f.create_group(f"slice_{i:03d}")
            g["geometry/center_mm"] = s["center"]
            g["geometry/phi"] = s["phi"]
            g["geometry/radius_mm"] = s["radius"]
            g["geometry/coefficients"] = rad.fit(s["phi"], s["radius"], 32)
            g["geometry"].attrs["note"] = "coefficients: least-squares projection onto V_32 of the exact radius"
            g["wss/phi"] = s["phi"]
            g["wss/tau_pa"] = s["tau"]
            g["wss"].attrs["mean_pa"] = s["mean_tau"]
            g["velocity_true_m_s"] = sl.velocity_image
            g.attrs["alpha"] = np.nan
            g.attrs["beta"] = np.nan


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


# ------------------------------------------------------------------ commands
def _phantom_cine(args) -> int:
    from ..synthetic import pulsatile

    if args.dicom or args.nifti or args.stack:
        raise InputError("--case womersley writes a time-resolved HDF5 input only (no --dicom, --nifti, --stack)")
    if args.pipe_radius is not None and not args.pipe_radius > 0:
        raise InputError(f"--pipe-radius must be > 0 mm, got {args.pipe_radius}")
    snr = None if args.snr <= 0 else args.snr
    radius = {} if args.pipe_radius is None else {"radius_mm": args.pipe_radius}
    frames, truth = pulsatile.make_cine(
        h_mm=args.h, snr=snr, seed=args.seed, frames=args.frames, venc=args.venc, psf=_phantom_psf(args),
        distension=args.distension or 0.0, shape=args.shape or "circle", **radius,
    )  # fmt: skip
    wio.write_frames(args.output, frames, truth.times_ms, truth.period_ms)
    if args.truth:
        try:
            pulsatile.write_truth(args.truth, truth)
        except BaseException:
            os.remove(args.output)  # the pair is written whole or not at all
            raise
    acq = frames[0]
    print(
        f"wrote {args.output}: {truth.frames[0].name} (Womersley number {truth.flow.womersley(1):.1f}), "
        f"{args.frames} frames over {truth.period_ms:g} ms, h = {args.h} mm, SNR {args.snr:g}, seed {args.seed}, "
        f"{acq.magnitude.shape[2]} x {acq.magnitude.shape[1]} voxels"
    )
    if args.truth:
        tau = truth.tau()
        print(f"wrote {args.truth}: exact WSS over the cycle ({tau.min():.3g} to {tau.max():.3g} Pa)")
    return 0


def _phantom_psf(args):
    """The k-space acquisition a phantom asks for (``--acquisition kspace``), or None for voxel means.

    A phantom has no data to choose a filter from: ``--kspace-filter auto`` acquires without one.
    """
    how = schema.from_args(AcquisitionOptions, args)
    psf = how.psf((args.h, args.h))
    return psf if psf is None or psf.filter != "auto" else dataclasses.replace(psf, filter="none")


def _acquired_text(psf) -> str:
    if psf is None:
        return "voxel means"
    return f"k-space acquisition, {psf.filter} filter, zero-filling {psf.zero_fill[1]:g} x {psf.zero_fill[0]:g}"


def cmd_phantom(args) -> int:
    outputs.check_outputs(
        files={"-o": args.output, "--truth": args.truth}, folders={"--dicom": args.dicom, "--nifti": args.nifti}
    )
    if args.case == "womersley":
        return _phantom_cine(args)
    cine_only = [f for f, v in (("--distension", args.distension), ("--shape", args.shape),
                                ("--pipe-radius", args.pipe_radius)) if v is not None]  # fmt: skip
    if cine_only:
        raise InputError(f"{', '.join(cine_only)}: only for --case womersley (the cine phantom)")
    snr = None if args.snr <= 0 else args.snr
    psf = _phantom_psf(args)
    truth: phantoms.Truth | phantoms.StackTruth
    if args.stack:
        acq, truth = phantoms.make_stack(
            args.stack,
            nz=args.nz,
            h_mm=args.h,
            spacing_mm=args.spacing,
            snr=snr,
            seed=args.seed,
            venc=args.venc,
            swirl_per_s=args.swirl,
            psf=psf,
        )
        args.case = f"{args.stack} stack ({args.nz} slices, {args.spacing:g} mm apart)"
    else:
        acq, truth = phantoms.make_phantom(
            args.case,
            h_mm=args.h,
            snr=snr,
            seed=args.seed,
            venc=args.venc,
            as_phase=not args.velocity,
            psf=psf,
        )
    peak = max(phantoms.peak_velocity(t.flow) for t in getattr(truth, "slices", [truth]))
    if acq.venc_m_s is not None and acq.venc_m_s < peak:
        print(
            f"wss-nlp: warning: venc {acq.venc_m_s:g} m/s is below the peak velocity {peak:.3g} m/s: the phase "
            "wraps (aliasing); 'reconstruct' unwraps it (or refuses it when it cannot)",
            file=sys.stderr,
        )
    with outputs.StagedFolder(args.dicom) as dcm, outputs.StagedFolder(args.nifti) as nii:
        if dcm.path or nii.path:  # the same images as a scanner exports them, for trying 'wss-nlp import'
            from ..synthetic import scanner_exports

            scan = scanner_exports.Scan(
                acq.magnitude,
                acq.velocity_images(),
                float(acq.venc_m_s or 1.25 * peak),
                acq.voxel_size_mm,
                acq.origin_mm,
                slice_spacing_mm=acq.slice_spacing_mm or 1.0,
                acquired_matrix=None
                if acq.acquired_voxel_size_mm is None
                else tuple(  # type: ignore[arg-type]
                    int(round(n * v / a))
                    for n, v, a in zip(acq.magnitude.shape[1:], acq.voxel_size_mm, acq.acquired_voxel_size_mm)
                ),
            )
            if dcm.path:
                scanner_exports.write_dicom(dcm.path, scan, args.vendor)
            if nii.path:
                scanner_exports.write_nifti(nii.path, scan)
        wio.write_acquisition(args.output, acq)
        if args.truth:
            try:
                _write_truth(args.truth, truth)
            except BaseException:
                os.remove(args.output)  # the pair is written whole or not at all
                raise
        dcm.commit()
        nii.commit()
    print(
        f"wrote {args.output}: {args.case}, h = {args.h} mm, SNR {args.snr:g}, seed {args.seed}, "
        f"{acq.magnitude.shape[2]} x {acq.magnitude.shape[1]} voxels ({_acquired_text(psf)})"
    )
    if args.truth:
        means = [t.mean_wss for t in getattr(truth, "slices", [truth])]
        print(f"wrote {args.truth}: exact radius and WSS (mean {min(means):.5g}-{max(means):.5g} Pa)")
    return 0


def _is_time_resolved(path: str) -> bool:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "trigger_times_ms" in f.attrs
    except OSError:
        return False  # read_acquisition names the problem


def _reconstruct_cine(args, options) -> int:
    from ..pipeline import cine

    frames, times, period = wio.read_frames(args.input)
    acq = frames[0]
    print(
        f"{args.input}: {len(frames)} frames over {period:g} ms, {acq.nz} slice(s) of {acq.magnitude.shape[2]} x "
        f"{acq.magnitude.shape[1]} voxels, h = {acq.grid.h:g} mm",
        file=sys.stderr,
    )

    def progress(done, total, seconds):
        sys.stderr.write(f"  frame {done}/{total}: {seconds:.1f} s elapsed\n")
        sys.stderr.flush()

    result = cine.reconstruct_cine(frames, times, period, options, progress=progress)
    with outputs.StagedFolder(args.figures) as staged:
        series = cine.write_result(args.output, result, options.as_dict(), argv=["wss-nlp", *args.argv])
        if staged.path:
            from .plotting import save_cine_figures

            save_cine_figures(series, result, staged.path)
        staged.commit()
    for k, frame in enumerate(result.frames):
        for r in frame:
            for msg in r.warnings:
                sys.stderr.write(f"wss-nlp: warning: frame {k}: {msg}\n")
    for s in series:
        for note in s.notes:
            sys.stderr.write(f"wss-nlp: warning: slice {s.index}: {note}\n")
        print(
            f"slice {s.index}: time-averaged WSS {s.time_average_mean:.4g} Pa, TAWSS {np.mean(s.tawss):.4g} Pa "
            f"(wall mean), OSI {np.min(s.osi):.3f}-{np.max(s.osi):.3f}, peak mean WSS {np.max(s.mean):.4g} Pa at "
            f"{times[int(np.nanargmax(s.mean))]:g} ms; velocity over the cycle: "
            + (f"momentum model ({s.model.harmonics} harmonics)" if s.model and s.model.model == "momentum" else
               "the frames' own fits")
        )  # fmt: skip
    print(f"wrote {args.output}")
    if args.figures:
        print(f"figures in {args.figures}")
    return 0


def cmd_reconstruct(args) -> int:
    options = options_from_args(args)
    outputs.check_outputs(files={"-o": args.output}, folders={"--figures": args.figures}, inputs=[args.input])
    if _is_time_resolved(args.input):
        return _reconstruct_cine(args, options)
    acq = wio.read_acquisition(args.input)
    print(
        f"{args.input}: {acq.nz} slice(s) of {acq.magnitude.shape[2]} x {acq.magnitude.shape[1]} voxels, "
        f"h = {acq.grid.h:g} mm",
        file=sys.stderr,
    )
    results = reconstruct(acq, options, progress=_progress(sys.stderr))
    with outputs.StagedFolder(args.figures) as staged:  # figures and result land together or not at all
        if staged.path:
            _slice_figures(results, acq, staged.path)
        extra = {} if acq.slice_spacing_mm is None else {"slice_spacing_mm": float(acq.slice_spacing_mm)}
        wio.write_result(args.output, results, options.as_dict(), argv=["wss-nlp", *args.argv], extra_attrs=extra)
        staged.commit()
    _warn(results, sys.stderr)
    for r in results:
        if isinstance(r, wio.FailedSlice):
            print(f"slice {r.index}: FAILED: {r.reason}")
            continue
        print(
            f"slice {r.index}: mean WSS {r.wss.mean:.5g} Pa, mean radius {r.geometry.coefficients[0]:.4f} mm, "
            f"converged: {r.converged}"
        )
    if results.stack is not None:
        st = results.stack
        print(
            f"stack: z-regularized over {st.z_smoothing_mm:g} mm ({st.strategy}; segments "
            f"{[f'{s[0]}-{s[-1]}' for s in st.segments]})" + ("" if st.converged else "; NOT CONVERGED")
        )
    print(f"wrote {args.output}")
    if args.figures:
        print(f"figures in {args.figures}")
    return 0


def _slice_figures(results, acq, folder: str) -> None:
    from .plotting import figure_stack, save_figure, save_figures

    for r in results:
        if not isinstance(r, wio.FailedSlice):
            save_figures(r, folder, prefix=f"slice_{r.index:03d}_")
    if len(results) > 1:
        save_figure(figure_stack(results, acq.slice_spacing_mm), os.path.join(folder, "stack_wall_maps.png"))


def cmd_compare(args) -> int:
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
    from ..models import surround  # hook (issue 39): surround model and background phase offset

    for name, rec in surround.read_tissue(args.result).items():
        for line in surround.report_lines(rec):
            print(f"{name}: {line}")
    if args.figures:
        from .plotting import save_parameter_figures

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


def cmd_demo(args) -> int:
    out = args.output_dir
    options = options_from_args(args)
    outputs.check_outputs(folders={"-o": out})
    with outputs.StagedFolder(out) as staged:  # a failed demo leaves nothing half-written
        _demo(args, options, str(staged.path))
        staged.commit()
    print(f"wrote input.h5 (input), truth.h5 (truth), result.h5 (result) and the figures in {out}")
    return 0


def _demo_cine(args, options, out: str) -> None:
    from ..pipeline import cine
    from ..synthetic import pulsatile
    from .plotting import save_cine_figures

    snr = None if args.snr <= 0 else args.snr
    frames, truth = pulsatile.make_cine(h_mm=args.h, snr=snr, seed=args.seed, frames=20)
    print(
        f"wss-nlp {__version__} demo: Womersley flow (Womersley number {truth.flow.womersley(1):.1f}, flow "
        f"reversal), 20 frames over {truth.period_ms:g} ms, h = {args.h} mm, SNR {args.snr:g}, "
        f"seed {args.seed}"
    )
    in_path, truth_path, res_path = (os.path.join(out, n) for n in ("input.h5", "truth.h5", "result.h5"))
    wio.write_frames(in_path, frames, truth.times_ms, truth.period_ms)
    pulsatile.write_truth(truth_path, truth)
    t0 = time.perf_counter()
    frames, times, period = wio.read_frames(in_path)
    result = cine.reconstruct_cine(frames, times, period, options)
    seconds = time.perf_counter() - t0
    series = cine.write_result(res_path, result, options.as_dict(), argv=["wss-nlp", *args.argv])[0]
    for note in series.notes:
        print(f"note: {note}", file=sys.stderr)
    tau = truth.tau()
    ta_true, osi_true = cine.tawss_osi(tau[:, None], result.weights)
    peak = float(np.max(np.abs(tau)))
    rows = [
        ("TAWSS reconstructed [Pa]", f"{np.mean(series.tawss):.4g}"),
        ("TAWSS true [Pa]", f"{ta_true[0]:.4g}"),
        ("TAWSS rel. error", f"{100 * (np.mean(series.tawss) / ta_true[0] - 1):+.1f}%"),
        ("OSI reconstructed (wall mean)", f"{np.mean(series.osi):.3f}"),
        ("OSI true", f"{osi_true[0]:.3f}"),
        ("worst frame error / peak WSS", f"{100 * np.nanmax(np.abs(series.mean - tau)) / peak:.1f}%"),
        (
            "velocity over the cycle",
            {"momentum": "momentum model", "temporal": "temporal prior"}.get(
                series.model.model if series.model else "", "frames' own fits"
            ),
        ),  # fmt: skip
        ("time [s]", f"{seconds:.2f}"),
    ]
    print()
    print(_error_table(rows))
    figs = save_cine_figures([series], result, out, truth_tau=tau)
    print()
    print("figures: " + ", ".join(os.path.basename(f) for f in figs))


def _demo(args, options, out: str) -> None:
    if args.case == "cine":
        return _demo_cine(args, options, out)
    snr = None if args.snr <= 0 else args.snr
    print(f"wss-nlp {__version__} demo: phantom '{args.case}' ({phantoms.CASES[args.case][1]})")
    print(f"  voxel size h = {args.h} mm, SNR {args.snr:g}, seed {args.seed}")
    acq, truth = phantoms.make_phantom(args.case, h_mm=args.h, snr=snr, seed=args.seed)
    in_path, truth_path, res_path = (os.path.join(out, n) for n in ("input.h5", "truth.h5", "result.h5"))
    wio.write_acquisition(in_path, acq)
    _write_truth(truth_path, truth)
    t0 = time.perf_counter()
    results = reconstruct(wio.read_acquisition(in_path), options, progress=_progress(sys.stdout))
    seconds = time.perf_counter() - t0
    wio.write_result(res_path, results, options.as_dict(), argv=["wss-nlp", *args.argv])
    _warn(results, sys.stderr)
    res = results[0]
    err = metrics.compare_slice(res, truth)
    if hasattr(res, "velocity"):
        solvers = [
            (f"{ch.name} ({ch.rule})", f"{ch.chosen:.3g}")
            for ch in (res.alpha_choice, res.beta_choice)
            if ch is not None
        ]
        solvers += [
            ("geometry solver", f"{res.geometry.stats.status}"),
            ("velocity solver", f"{res.velocity.stats.status}"),
        ]
    else:
        solvers = [("method", f"{res.method} (closed-form fits)")]
    rows = _errors_rows(err) + solvers + [("time [s]", f"{seconds:.2f}")]
    if np.isfinite(res.wss.mean_std):
        rows.insert(4, ("mean WSS std (linearized) [Pa]", f"{res.wss.mean_std:.2g}"))
    print()
    print(_error_table(rows))
    from .plotting import save_figures

    figs = save_figures(res, out, truth=truth)
    print()
    print("figures: " + ", ".join(os.path.basename(f) for f in figs))


def _where(items) -> dict:
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise InputError(f"--where takes KEY=VALUE, got {item!r}")
        out[key] = value
    return out


def cmd_sweep(args) -> int:
    from . import sweep

    study = sweep.load_study(args.study)
    out = args.output_dir or os.path.join("runs", study.name)
    outputs.check_outputs(folders={"-o": out}, inputs=[args.study])
    try:
        s = sweep.run_study(study, out, workers=args.workers, scheduler=args.scheduler, retry_failed=args.retry_failed)
    except KeyboardInterrupt:
        print(
            f"\nwss-nlp: interrupted; finished cases are kept in {out}/cases; run the same command again to resume",
            file=sys.stderr,
        )
        return 130
    print(
        f"{s.total} cases ({s.ran} run now, {s.skipped} done before), {s.failed} not ok; "
        f"{s.seconds:.0f} s; table: {s.csv_path}"
    )
    for path in s.outputs:
        print(f"wrote {path}")
    if s.failed:
        print(
            f"wss-nlp: warning: {s.failed} case(s) failed or did not converge; see the 'status' and 'message' "
            f"columns of {s.csv_path}",
            file=sys.stderr,
        )
    return 0


def cmd_table(args) -> int:
    from . import sweep

    outputs.check_outputs(files={"-o": args.output})
    rows = sweep.read_csv(args.outdir)
    md, tex = sweep.table(
        rows,
        args.rows,
        args.cols,
        args.metric,
        _where(args.where),
        args.agg,
        source=os.path.join(args.outdir, "results.csv"),
        bold=not args.no_bold,
    )
    print(tex if args.latex else md, end="")
    if args.output:
        wio.atomic_write(args.output, tex if args.output.endswith(".tex") else md)
        print(f"wrote {args.output}", file=sys.stderr)
    return 0


def cmd_plot(args) -> int:
    from . import sweep
    from .plotting import save_figure

    outputs.check_outputs(files={"-o": args.output})
    rows = sweep.read_csv(args.outdir)
    where = _where(args.where)
    if not sweep.select(rows, where):
        raise InputError(f"{args.outdir}/results.csv: no rows match {where}")
    for k in (args.x, args.y, args.by, args.panels):
        if k is not None and k not in rows[0]:
            raise InputError(f"{args.outdir}/results.csv: no column {k!r}; columns: {', '.join(rows[0])}")
    fig = sweep.plot(rows, args.x, args.y, by=args.by, where=where, panels=args.panels, logx=args.logx)
    out = args.output or os.path.join(args.outdir, f"{args.y}_vs_{args.x}.png")
    print(f"wrote {save_figure(fig, out)}")
    return 0


def cmd_export(args) -> int:
    from ..io import export

    if not args.vtk.endswith((".vtu", ".vtk")):
        raise InputError(f"--vtk {args.vtk}: name a .vtu (VTK XML) or .vtk (legacy VTK) file")
    outputs.check_outputs(files={"--vtk": args.vtk}, inputs=[args.result])
    print(f"wrote {export.write_vtk(args.result, args.vtk, args.slice_spacing)}")
    return 0


def cmd_import(args) -> int:
    from ..io import importing, scanner

    outputs.check_outputs(files={"-o": args.output}, inputs=[p for p in args.paths if os.path.isfile(p)])
    if not args.output.endswith((".h5", ".hdf5")):
        raise InputError(f"-o {args.output}: name an HDF5 file (.h5)")
    wio.check_density(args.density, "--density")
    if args.viscosity is not None and not args.viscosity > 0:
        raise InputError(f"--viscosity {args.viscosity}: must be > 0 Pa*s (e.g. 3.5e-3 for blood)")
    options = scanner.ImportOptions(
        venc_m_s=args.venc,
        viscosity_pa_s=args.viscosity,
        density_kg_m3=args.density,
        flip_through_plane=args.flip_through_plane,
    )
    plane = None
    if args.plane is not None:
        from ..io.plane import Plane

        plane = Plane(
            point=tuple(args.plane[:3]),
            normal=tuple(args.plane[3:]),
            fov_mm=args.plane_fov,
            voxel_mm=args.plane_voxel,
            slices=args.plane_slices,
            spacing_mm=args.plane_spacing,
        )
        plane.check()
    imp = importing.import_paths(args.paths, options, args.phase_units, args.frame_interval, plane)
    scanner.write_import(args.output, imp, argv=["wss-nlp", *args.argv])
    print(f"wrote {args.output}: {imp.summary()}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="wss-nlp",
        description="Vessel geometry, velocity and wall shear stress from phase-contrast MRI "
        "(Egger & Teschner), with every Tikhonov problem posed in CasADi.",
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser(
        "demo",
        help="reconstruct a built-in phantom and report errors against the truth",
        description="Build a phantom, reconstruct it, print errors, write files and figures.",
    )
    d.add_argument(
        "--case",
        choices=[*phantoms.CASES, "cine"],
        default="laminar",
        help="phantom (default %(default)s); cine: Womersley flow over a cycle, TAWSS and OSI",
    )
    d.add_argument("--h", type=float, default=1.0, help="voxel size in mm (default %(default)g)")
    d.add_argument("--snr", type=float, default=25.0, help="signal-to-noise ratio, <= 0 for none (default %(default)g)")
    d.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    d.add_argument("-o", "--output-dir", default="wss_nlp_demo", help="output folder (default %(default)s)")
    _add_reconstruction_arguments(d)
    d.set_defaults(func=cmd_demo)

    r = sub.add_parser(
        "reconstruct",
        help="reconstruct an acquisition file",
        description="Reconstruct geometry, velocity and WSS of every slice of INPUT.",
    )
    r.add_argument("input", help='input HDF5 file (format: docs, "File formats")')
    r.add_argument("-o", "--output", required=True, help="result HDF5 file")
    r.add_argument("--figures", default=None, help="folder for PNG figures of every slice")
    _add_reconstruction_arguments(r)
    r.set_defaults(func=cmd_reconstruct)

    ph = sub.add_parser("phantom", help="write a synthetic acquisition (and its truth)")
    ph.add_argument(
        "--case",
        choices=[*phantoms.CASES, "womersley"],
        default="laminar",
        help="womersley: a time-resolved (cine) phantom, Womersley flow over one cycle (--frames)",
    )
    ph.add_argument("--frames", type=int, default=20, help="womersley: frames over the cycle (default %(default)s)")
    ph.add_argument(
        "--distension",
        type=float,
        default=None,
        metavar="EPS",
        help="womersley: the pipe breathes, radius R0 (1 + EPS sin(omega t)), EPS in [0, 0.3) (default 0: rigid)",
    )
    ph.add_argument(
        "--shape",
        choices=("circle", "ellipse"),
        default=None,
        help="womersley: circular pipe, or elliptic (aspect 1.32, same area, its exact pulsatile flow; rigid)",
    )
    ph.add_argument(
        "--pipe-radius",
        type=float,
        default=None,
        metavar="MM",
        help="womersley: pipe radius in mm (default 10: first harmonic's Womersley number about 14)",
    )
    ph.add_argument("--h", type=float, default=1.0, help="voxel size in mm (default %(default)g)")
    ph.add_argument("--snr", type=float, default=25.0, help="signal-to-noise ratio, <= 0 for none")
    ph.add_argument("--seed", type=int, default=0)
    ph.add_argument("--venc", type=float, default=None, help="velocity encoding in m/s (default 1.25 x peak)")
    ph.add_argument("--velocity", action="store_true", help="store 'velocity' instead of 'phase' + venc")
    ph.add_argument(
        "--stack", choices=list(phantoms.STACK_CASES), default=None, help="a 3D stack phantom instead of one slice"
    )
    ph.add_argument("--nz", type=int, default=10, help="stack: number of slices (default %(default)s)")
    ph.add_argument("--spacing", type=float, default=2.0, help="stack: slice spacing in mm (default %(default)g)")
    ph.add_argument(
        "--swirl",
        type=float,
        default=None,
        help="stack: add in-plane velocity components (4D flow) of a swirl with this rate in 1/s",
    )
    ph.add_argument("-o", "--output", required=True, help="input file to write")
    ph.add_argument("--truth", default=None, help="also write the exact geometry and WSS here")
    ph.add_argument(
        "--dicom", default=None, metavar="FOLDER", help="also write the images as DICOM files (for 'wss-nlp import')"
    )
    ph.add_argument(
        "--vendor",
        choices=["siemens", "philips", "ge", "enhanced"],
        default="siemens",
        help="DICOM convention of --dicom (default %(default)s)",
    )
    ph.add_argument("--nifti", default=None, metavar="FOLDER", help="also write NIfTI files with JSON sidecars")
    schema.add_arguments(ph, AcquisitionOptions)  # acquire in k-space: --acquisition kspace --kspace-filter ...
    ph.set_defaults(func=cmd_phantom)

    a = sub.add_parser(
        "analyze", help="how alpha, beta, the near-wall model and the dephasing passes were chosen (tables, curves)"
    )
    a.add_argument("result", help="result file written by 'wss-nlp reconstruct'")
    a.add_argument("--figures", default=None, help="folder for residual-vs-parameter PNGs")
    a.set_defaults(func=cmd_analyze)

    se = sub.add_parser("sensitivity", help="which parameters and which noise the mean WSS is most sensitive to")
    se.add_argument("result", help="result file written by 'wss-nlp reconstruct'")
    se.set_defaults(func=cmd_sensitivity)

    sw = sub.add_parser(
        "sweep",
        help="run a parameter study from a TOML file (problems/*.toml)",
        description="Expand the study's grid, run the cases in parallel (resumable), write "
        "OUTDIR/results.csv, per-case result files and the study's tables and plots.",
    )
    sw.add_argument("study", help="study file (TOML; see problems/README.md)")
    sw.add_argument("-o", "--output-dir", default=None, help="output folder (default runs/STUDY_NAME)")
    sw.add_argument("--workers", type=int, default=None, help="local worker processes (default: all cores)")
    sw.add_argument(
        "--scheduler",
        default=None,
        help="address of a Dask distributed scheduler (tcp://HOST:PORT) to run the cases on",
    )
    sw.add_argument("--retry-failed", action="store_true", help="run again the cases that failed before")
    sw.set_defaults(func=cmd_sweep)

    tb = sub.add_parser(
        "table",
        help="a paper-style table from a sweep's results.csv",
        description="Pivot a metric over two parameters (mean over seeds); best per row in bold.",
    )
    tb.add_argument("outdir", help="output folder of 'wss-nlp sweep'")
    tb.add_argument("--rows", required=True, help="parameter of the rows (or 'metric' for a single row)")
    tb.add_argument("--cols", required=True, help="parameter of the columns (or 'metric')")
    tb.add_argument("--metric", required=True, help="metric column, e.g. radius_err_h2, wss_err")
    tb.add_argument("--where", nargs="*", default=[], metavar="KEY=VALUE", help="fix other parameters")
    tb.add_argument(
        "--agg", choices=["mean", "median", "max", "min"], default="mean", help="over seeds (default %(default)s)"
    )
    tb.add_argument("--latex", action="store_true", help="print LaTeX instead of Markdown")
    tb.add_argument("--no-bold", action="store_true", help="do not mark the best value of each row")
    tb.add_argument("-o", "--output", default=None, help="also write the table (.tex: LaTeX, else Markdown)")
    tb.set_defaults(func=cmd_table)

    pl = sub.add_parser("plot", help="a metric against a parameter from a sweep's results.csv")
    pl.add_argument("outdir", help="output folder of 'wss-nlp sweep'")
    pl.add_argument("--x", required=True, help="parameter on the x axis, e.g. h")
    pl.add_argument("--y", required=True, help="metric on the y axis, e.g. wss_err")
    pl.add_argument("--by", default=None, help="one line per value of this parameter, e.g. method")
    pl.add_argument("--panels", default=None, help="one panel per value of this parameter, e.g. case")
    pl.add_argument("--where", nargs="*", default=[], metavar="KEY=VALUE", help="fix other parameters")
    pl.add_argument("--logx", action="store_true", help="logarithmic x axis")
    pl.add_argument("-o", "--output", default=None, help="PNG file (default OUTDIR/Y_vs_X.png)")
    pl.set_defaults(func=cmd_plot)

    ex = sub.add_parser(
        "export",
        help="the reconstructed wall with its WSS as a VTK file for ParaView",
        description="A slice becomes a polyline, a stack the wall surface; point data tau_pa (and tau_std_pa, "
        "wss_vector_pa where present).",
    )
    ex.add_argument("result", help="result file written by 'wss-nlp reconstruct'")
    ex.add_argument("--vtk", required=True, help="output file: .vtu (VTK XML) or .vtk (legacy)")
    ex.add_argument(
        "--slice-spacing",
        type=float,
        default=None,
        help="mm between slices (default: the result's slice_spacing_mm, stored by reconstruct)",
    )
    ex.set_defaults(func=cmd_export)

    im = sub.add_parser(
        "import",
        help="scanner exports (DICOM folder/files or NIfTI) to an input file",
        description="Read a magnitude and a phase (or velocity) series from DICOM (Siemens, Philips, GE, enhanced "
        "multi-frame) or NIfTI (with dcm2niix JSON sidecars) and write an input file of the format document; "
        "venc, voxel size, origin, slice spacing and trigger times come from the headers. See the docs page "
        "'Your own data'.",
    )
    im.add_argument("paths", nargs="+", metavar="PATH", help="DICOM folders or files, or NIfTI files")
    im.add_argument("-o", "--output", required=True, help="input file to write (.h5)")
    im.add_argument("--venc", type=float, default=None, metavar="M_S", help="velocity encoding in m/s (overrides)")
    im.add_argument("--viscosity", type=float, default=None, metavar="PA_S", help="dynamic viscosity to store")
    im.add_argument("--density", type=float, default=None, metavar="KG_M3", help="fluid density to store")
    im.add_argument(
        "--flip-through-plane", action="store_true", help="negate the through-plane velocity (forward flow negative)"
    )
    im.add_argument(
        "--phase-units",
        default=None,
        choices=["rad", "siemens", "cm/s", "mm/s", "m/s"],
        help="units of the phase images' values when the headers do not state them",
    )
    im.add_argument(
        "--frame-interval", type=float, default=None, metavar="MS", help="ms between NIfTI frames (if not in header)"
    )
    im.add_argument(
        "--plane",
        type=float,
        nargs=6,
        default=None,
        metavar=("X", "Y", "Z", "NX", "NY", "NZ"),
        help="4D flow (NIfTI magnitude + *_vx/_vy/_vz files): cut the volume by the plane through (X, Y, Z) mm "
        "with normal (NX, NY, NZ), in the affine's world frame",
    )
    im.add_argument("--plane-fov", type=float, default=40.0, metavar="MM", help="side of the plane (default 40)")
    im.add_argument(
        "--plane-voxel", type=float, default=None, metavar="MM", help="plane voxel (default: the volume's largest)"
    )
    im.add_argument("--plane-slices", type=int, default=1, metavar="N", help="parallel slices (a stack; default 1)")
    im.add_argument(
        "--plane-spacing", type=float, default=None, metavar="MM", help="between those slices (default: the voxel)"
    )
    im.set_defaults(func=cmd_import)

    c = sub.add_parser("compare", help="errors of a result file against a truth file")
    c.add_argument("result")
    c.add_argument("truth")
    c.set_defaults(func=cmd_compare)
    return p


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or usage error (2)
        return int(exc.code or 0)
    args.argv = argv
    _show_library_log()
    try:
        return int(args.func(args) or 0)
    except WssNlpError as exc:
        print(f"wss-nlp: error: {_one_line(exc)}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("wss-nlp: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:  # the file system refused (disk full, permissions changed during the run)
        print(f"wss-nlp: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug: one line for the user, the traceback for the report
        if os.environ.get("WSS_NLP_DEBUG"):
            raise
        print(
            f"wss-nlp: internal error: {type(exc).__name__}: {_one_line(exc)}; please report it with the "
            "command line (WSS_NLP_DEBUG=1 shows the traceback)",
            file=sys.stderr,
        )
        return 1


class _StderrHandler(logging.StreamHandler):
    """Writes to the current ``sys.stderr`` (which tests and embedding programs may replace)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def _show_library_log() -> None:
    """The library's INFO messages (stages of long solves) on stderr, indented under the progress lines."""
    logger = logging.getLogger("wss_nlp")
    if not any(isinstance(h, _StderrHandler) for h in logger.handlers):  # main() may run many times in a process
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("  %(message)s"))
        logger.addHandler(handler)
    logger.setLevel(logging.INFO)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
