"""``wss-nlp sweep``, ``table`` and ``plot``: parameter studies from a TOML file (:mod:`wss_nlp.app.sweep`)."""

from __future__ import annotations

import logging
import os
import sys
from ...io import files as wio
from ...io import outputs
from ...errors import InputError, WssNlpError

log = logging.getLogger(__name__)  # warnings: the command line shows them once per kind (main)


def _where(items) -> dict:
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise InputError(f"--where takes KEY=VALUE, got {item!r}")
        out[key] = value
    return out


def cmd_sweep(args) -> int:
    from .. import sweep

    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers {args.workers}: must be a whole number >= 1 (default: all cores)")
    study = sweep.load_study(args.study)
    out = args.output_dir or os.path.join("runs", study.name)
    outputs.check_outputs(folders={"-o": out}, inputs=[args.study])
    fresh = not os.path.exists(out)
    try:
        s = sweep.run_study(study, out, workers=args.workers, scheduler=args.scheduler, retry_failed=args.retry_failed)
    except WssNlpError:  # issue 42: a refused sweep leaves no study folder behind (one it made, with no case in it)
        if fresh:
            _remove_unused(out)
        raise
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
    if s.failed:  # issue 42: a sweep with failed cases exits 1
        log.warning(
            f"{s.failed} case(s) failed or did not converge; see the 'status' and 'message' columns of {s.csv_path}"
        )
        return 1
    return 0


def _remove_unused(out: str) -> None:
    """Remove the output folder a refused sweep created, if it holds nothing but the study's copy and no case."""
    import shutil

    cases = os.path.join(out, "cases")
    names = set(os.listdir(out)) if os.path.isdir(out) else set()
    if names <= {"study.toml", "cases"} and not (os.path.isdir(cases) and os.listdir(cases)):
        shutil.rmtree(out, ignore_errors=True)


def cmd_table(args) -> int:
    from .. import sweep

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
    from .. import sweep
    from ..plotting import save_figure

    outputs.check_outputs(files={"-o": args.output})
    rows = sweep.read_csv(args.outdir)
    where = _where(args.where)
    if not sweep.select(rows, where):
        raise InputError(f"{args.outdir}/results.csv: no rows match {where}")
    for k in (args.x, args.y, args.by, args.panels):
        if k is not None and k not in rows[0]:
            raise InputError(f"{args.outdir}/results.csv: no column {k!r}; columns: {', '.join(rows[0])}")
    fig = sweep.plot(rows, args.x, args.y, by=args.by, where=where, panels=args.panels, logx=args.logx)
    out = args.output or os.path.join(args.outdir, f"{args.y}_vs_{args.x}.{args.figure_format}")
    print(f"wrote {save_figure(fig, out, args.dpi)}")
    return 0
