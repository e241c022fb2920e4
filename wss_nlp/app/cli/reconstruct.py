"""``wss-nlp reconstruct``: one input file (slices, stacks, cine) to a result file, with progress and figures."""

from __future__ import annotations

import logging
import contextlib
import os
import sys
import time
import numpy as np
from ...io import files as wio
from ...errors import InputError
from ...io import outputs, ranges
from ...pipeline import methods
from ...pipeline.driver import reconstruct, segments_in_parallel, stack_applies
from .arguments import options_from_args

log = logging.getLogger(__name__)  # warnings: the command line shows them once per kind (main)


#: In a log (not a terminal), a joint solve's progress is written at most this often, besides each new stage (s).
STAGE_INTERVAL_S = 10.0


def _progress(stream, quiet: bool = False, total: int | None = None):
    """Per-slice progress on ``stream``: a tqdm bar on a terminal, a line per slice otherwise (logs, CI, tests);
    nothing with ``--quiet``. ``total``: the slices to come (the bar's length before the first slice is done).

    The callback's ``stage(text)`` shows how far a z-tied segment's joint solve got (its stages, IPOPT iterations
    and sweeps: :func:`wss_nlp.pipeline.driver.reconstruct`) before its slices are done together: in the bar's
    text on a terminal; in a log a line for each new stage and otherwise at most every :data:`STAGE_INTERVAL_S`.
    """
    t0 = time.perf_counter()
    bar = None
    tty = hasattr(stream, "isatty") and stream.isatty()
    said_stage, said_at = "", -np.inf  # the last stage line written to a log, and when

    def open_bar(total: int | None):
        nonlocal bar
        if bar is None:
            from tqdm import tqdm

            bar = tqdm(total=total, file=stream, unit="slice", dynamic_ncols=True)
        return bar

    def report(done, total, res):
        if quiet:
            return
        failed = isinstance(res, wio.FailedSlice)
        flag = "" if failed or res.converged else "  [NOT CONVERGED]"
        text = f"FAILED ({res.reason})" if failed else f"mean WSS {res.wss.mean:.4g} Pa"
        if tty:
            b = open_bar(total)
            b.set_postfix_str(f"slice {done}: {text}{flag}", refresh=False)
            b.update(done - b.n)
            if done >= total:
                b.close()
            return
        elapsed = "" if failed else f", {time.perf_counter() - t0:.1f} s elapsed"
        stream.write(f"  slice {done}/{total}: {text}{elapsed}{flag}\n")
        stream.flush()

    def stage(text: str) -> None:
        nonlocal said_stage, said_at
        if quiet:
            return
        if tty:
            open_bar(total).set_postfix_str(text)
            return
        now = time.perf_counter()
        kind = text.split(": ")[1] if text.count(": ") >= 1 else text  # "slices 0-9: geometry: IPOPT ..." -> geometry
        if kind != said_stage or now - said_at >= STAGE_INTERVAL_S:
            stream.write(f"  {text}, {now - t0:.1f} s elapsed\n")
            stream.flush()
            said_stage, said_at = kind, now

    report.stage = stage  # type: ignore[attr-defined]  # the driver's optional stage reports
    return report


def _warn(results) -> None:
    """Every slice's warnings to the log, each kind said once with the slices it applies to."""
    from ...pipeline.cine import group_warnings

    items = [(r.index, _strip_slice(msg, r.index)) for r in results for msg in r.warnings]
    for line in group_warnings(items, len(results), what="slice"):
        log.warning(line)


def _strip_slice(message: str, index: int) -> str:
    """A slice's warning without its ``slice N: `` prefix (the grouped line names the slices)."""
    prefix = f"slice {index}: "
    return message[len(prefix) :] if message.startswith(prefix) else message


def _cycle_summary(s, times) -> str:
    """One line per slice of a cine result: the cycle's WSS, TAWSS, OSI and the model over the cycle."""
    if np.all(np.isfinite(s.tawss)):
        cycle = (f"time-averaged WSS {s.time_average_mean:.4g} Pa, TAWSS {np.mean(s.tawss):.4g} Pa (wall mean), "
                 f"OSI {np.min(s.osi):.3f}-{np.max(s.osi):.3f}")  # fmt: skip
    else:
        cycle = "TAWSS and OSI not computed (the frames do not cover the cycle)"
    peak = int(np.nanargmax(np.abs(s.mean)))
    model = s.model.model if s.model is not None else "independent"
    if model == "momentum":
        how = f"the momentum model ({s.model.harmonics} harmonics"
        v = s.model.viscosity
        if v.get("mode") == "fit":
            lo, hi = v["implied_interval_pa_s"]
            how += (f"; the frames imply {1e3 * v['implied_pa_s']:.3g} mPa s, 95 % {1e3 * lo:.3g}-{1e3 * hi:.3g}, "
                    f"stated {1e3 * v['stated_pa_s']:.3g}" + ("" if v["agrees"] else " OUTSIDE"))  # fmt: skip
        how += ")"
    elif model == "temporal":
        how = "the frames' fits tied by a temporal prior"
    else:
        how = "the frames' own fits"
    return (f"slice {s.index}: {cycle}, peak mean WSS {s.mean[peak]:.4g} Pa at {times[peak]:g} ms; velocity over the "
            f"cycle: {how}")  # fmt: skip


def _input_frame(path: str) -> dict:
    """The input's attributes a result keeps so that ``export`` places the wall in the scanner's world frame.

    ``import_json`` (the import record: directions and first slice position, :mod:`wss_nlp.io.export`) and
    ``slice_spacing_mm``, where the input has them.
    """
    import h5py

    with h5py.File(path, "r") as f:
        return {k: f.attrs[k] for k in ("import_json", "slice_spacing_mm") if k in f.attrs}


def _is_time_resolved(path: str) -> bool:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "trigger_times_ms" in f.attrs
    except OSError:
        return False  # read_acquisition names the problem


def _reconstruct_cine(args, options) -> int:
    from ...pipeline import cine

    frames, times, period = wio.read_frames(args.input)
    timing_notes = ranges.check_frames(times, period, args.input, options.screen.allow_unphysical)
    acq = frames[0]
    if not args.quiet:
        print(
            f"{args.input}: {len(frames)} frames over {period:g} ms, {acq.nz} slice(s) of {acq.magnitude.shape[2]} x "
            f"{acq.magnitude.shape[1]} voxels, h = {acq.grid.h:g} mm",
            file=sys.stderr,
        )

    def progress(done, total, seconds):
        if args.quiet:
            return
        sys.stderr.write(f"  frame {done}/{total}: {seconds:.1f} s elapsed\n")
        sys.stderr.flush()

    parallel = acq.nz > 1 and not stack_applies(acq, options) and methods.of(options).ties_slices
    with _segments_in_parallel(args, parallel, "each frame's geometry starts from the previous frame's wall"):
        result = cine.reconstruct_cine(frames, times, period, options, progress=progress)
    with outputs.StagedFolder(args.figures) as staged:
        series = cine.write_result(
            args.output,
            result,
            options.as_dict(),
            argv=["wss-nlp", *args.argv],
            notes=timing_notes,
            attrs=_input_frame(args.input),  # the input's frame, for export in world coordinates
        )
        if staged.path:
            from ..plotting import save_cine_figures

            save_cine_figures(series, result, staged.path, fmt=args.figure_format, dpi=args.dpi)
        staged.commit()
    for line in cine.cycle_warnings(result, series):  # each kind once, with the slices and frames it applies to
        log.warning(line)
    for note in timing_notes:
        log.warning(note)
    for s in series:
        print(_cycle_summary(s, times))
    print(f"wrote {args.output}")
    if args.figures:
        print(f"figures in {args.figures}")
    return 0


def cmd_reconstruct(args) -> int:
    from ...io.volume import is_volume_file

    if is_volume_file(args.input):
        from .vessel import reconstruct_volume

        return reconstruct_volume(args)
    for flag, value in (("--mask", args.mask), ("--centerline", args.centerline), ("--baseline", args.baseline)):
        if value:
            raise InputError(
                f"{flag}: for a 4D flow volume file (wss-nlp import without --plane); {args.input} is not one"
            )
    options = options_from_args(args)
    outputs.check_outputs(files={"-o": args.output}, folders={"--figures": args.figures}, inputs=[args.input])
    if _is_time_resolved(args.input):
        return _reconstruct_cine(args, options)
    acq = wio.read_acquisition(args.input)
    if not args.quiet:
        print(
            f"{args.input}: {acq.nz} slice(s) of {acq.magnitude.shape[2]} x {acq.magnitude.shape[1]} voxels, "
            f"h = {acq.grid.h:g} mm",
            file=sys.stderr,
        )
    parallel = acq.nz > 1 and not stack_applies(acq, options) and methods.of(options).ties_slices
    with _segments_in_parallel(args, parallel):
        results = reconstruct(acq, options, progress=_progress(sys.stderr, args.quiet, acq.nz))
    with outputs.StagedFolder(args.figures) as staged:  # figures and result land together or not at all
        if staged.path:
            _slice_figures(results, acq, staged.path, args.figure_format, args.dpi)
        extra = {k: v for k, v in _input_frame(args.input).items() if k == "import_json"}
        if acq.slice_spacing_mm is not None:
            extra["slice_spacing_mm"] = float(acq.slice_spacing_mm)
        wio.write_result(args.output, results, options.as_dict(), argv=["wss-nlp", *args.argv], extra_attrs=extra)
        staged.commit()
    _warn(results)
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


def _slice_figures(results, acq, folder: str, fmt: str = "png", dpi: float | None = None) -> None:
    from ..plotting import figure_stack, save_figure, save_figures, save_tissue_figures

    for r in results:
        if not isinstance(r, wio.FailedSlice):
            prefix = f"slice_{r.index:03d}_"
            save_figures(r, folder, prefix=prefix, fmt=fmt, dpi=dpi)
            save_tissue_figures(r, acq.magnitude[r.index], folder, prefix=prefix, fmt=fmt, dpi=dpi)
    if len(results) > 1:
        save_figure(figure_stack(results, acq.slice_spacing_mm), os.path.join(folder, f"stack_wall_maps.{fmt}"), dpi)


@contextlib.contextmanager
def _segments_in_parallel(args, parallel: bool, frames: str = ""):
    """``--workers N`` / ``--scheduler``: the independent slices in parallel (:mod:`wss_nlp.app.executor`), the
    rest serial with a note saying why."""
    workers, scheduler = args.workers, args.scheduler
    if workers <= 1 and not scheduler:
        yield
        return
    if frames:
        print(f"wss-nlp: note: cine frames run one after another ({frames})", file=sys.stderr)
    if not parallel:
        print(
            "wss-nlp: note: --workers: nothing here runs in parallel (one slice, slices tied along z by one solve "
            "per segment, or a classical baseline, which fits slice by slice); --z-smoothing 0 makes the slices of "
            "a stack independent",
            file=sys.stderr,
        )
        yield
        return
    from .. import executor

    with executor.Executor(executor.backend(workers, scheduler)) as ex, segments_in_parallel(ex.map):
        yield
