"""``wss-nlp demo``: a built-in phantom reconstructed end to end, its errors printed and its figures written."""

from __future__ import annotations

import os
import sys
import time
import numpy as np
from ...pipeline.results import SliceResult
from ... import __version__
from ...io import files as wio
from ...analysis import metrics
from ...io import outputs
from ...synthetic import invivo, phantoms
from ...pipeline.driver import reconstruct
from .arguments import options_from_args
from .phantom import _write_truth
from .reconstruct import _progress, _warn
from .report import _error_table, _errors_rows


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
    from ...pipeline import cine
    from ...synthetic import pulsatile
    from ..plotting import save_cine_figures

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
    figs = save_cine_figures([series], result, out, truth_tau=tau, fmt=args.figure_format, dpi=args.dpi)
    print()
    print("figures: " + ", ".join(os.path.basename(f) for f in figs))


def _demo(args, options, out: str) -> None:
    if args.case == "cine":
        return _demo_cine(args, options, out)
    snr = None if args.snr <= 0 else args.snr
    tissue = args.case in invivo.INVIVO_CASES  # the vessel in tissue (issue 39)
    what = (invivo.INVIVO_CASES if tissue else phantoms.CASES)[args.case][1]
    print(f"wss-nlp {__version__} demo: phantom '{args.case}' ({what})")
    print(f"  voxel size h = {args.h} mm, SNR {args.snr:g}, seed {args.seed}")
    if tissue:
        acq, truth = invivo.make_case(args.case, h_mm=args.h, snr=snr, seed=args.seed)
    else:
        acq, truth = phantoms.make_phantom(args.case, h_mm=args.h, snr=snr, seed=args.seed)
    in_path, truth_path, res_path = (os.path.join(out, n) for n in ("input.h5", "truth.h5", "result.h5"))
    wio.write_acquisition(in_path, acq)
    _write_truth(truth_path, truth)
    t0 = time.perf_counter()
    results = reconstruct(wio.read_acquisition(in_path), options, progress=_progress(sys.stdout, args.quiet))
    seconds = time.perf_counter() - t0
    wio.write_result(res_path, results, options.as_dict(), argv=["wss-nlp", *args.argv])
    _warn(results)
    res = results[0]
    err = metrics.compare_slice(res, truth)
    if isinstance(res, SliceResult):
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
    from ..plotting import save_figures, save_tissue_figures

    fmt, dpi = args.figure_format, args.dpi
    figs = save_figures(res, out, truth=truth, fmt=fmt, dpi=dpi) + save_tissue_figures(
        res, acq.magnitude[0], out, fmt=fmt, dpi=dpi
    )
    print()
    print("figures: " + ", ".join(os.path.basename(f) for f in figs))
