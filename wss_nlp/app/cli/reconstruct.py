"""``wss-nlp reconstruct``: one input file (slices, stacks, cine) to a result file, with progress and figures."""

from __future__ import annotations

import contextlib
import os
import sys
import time
import numpy as np
from ...io import files as wio
from ...io import outputs, ranges
from ...pipeline import methods
from ...pipeline.driver import reconstruct, segments_in_parallel, stack_applies
from .arguments import options_from_args


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
    """Every slice's warnings, each kind said once with the slices it applies to."""
    from ...pipeline.cine import group_warnings

    items = [(r.index, _strip_slice(msg, r.index)) for r in results for msg in r.warnings]
    for line in group_warnings(items, len(results), what="slice"):
        stream.write(f"wss-nlp: warning: {line}\n")


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
    print(
        f"{args.input}: {len(frames)} frames over {period:g} ms, {acq.nz} slice(s) of {acq.magnitude.shape[2]} x "
        f"{acq.magnitude.shape[1]} voxels, h = {acq.grid.h:g} mm",
        file=sys.stderr,
    )

    def progress(done, total, seconds):
        sys.stderr.write(f"  frame {done}/{total}: {seconds:.1f} s elapsed\n")
        sys.stderr.flush()

    parallel = acq.nz > 1 and not stack_applies(acq, options) and methods.of(options).ties_slices
    with _segments_in_parallel(args, parallel, "each frame's geometry starts from the previous frame's wall"):
        result = cine.reconstruct_cine(frames, times, period, options, progress=progress)
    with outputs.StagedFolder(args.figures) as staged:
        series = cine.write_result(
            args.output, result, options.as_dict(), argv=["wss-nlp", *args.argv], notes=timing_notes
        )
        if staged.path:
            from ..plotting import save_cine_figures

            save_cine_figures(series, result, staged.path)
        staged.commit()
    for line in cine.cycle_warnings(result, series):  # each kind once, with the slices and frames it applies to
        sys.stderr.write(f"wss-nlp: warning: {line}\n")
    for note in timing_notes:
        sys.stderr.write(f"wss-nlp: warning: {note}\n")
    for s in series:
        print(_cycle_summary(s, times))
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
    parallel = acq.nz > 1 and not stack_applies(acq, options) and methods.of(options).ties_slices
    with _segments_in_parallel(args, parallel):
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
    from ..plotting import figure_stack, save_figure, save_figures, save_tissue_figures

    for r in results:
        if not isinstance(r, wio.FailedSlice):
            save_figures(r, folder, prefix=f"slice_{r.index:03d}_")
            save_tissue_figures(r, acq.magnitude[r.index], folder, prefix=f"slice_{r.index:03d}_")
    if len(results) > 1:
        save_figure(figure_stack(results, acq.slice_spacing_mm), os.path.join(folder, "stack_wall_maps.png"))


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
