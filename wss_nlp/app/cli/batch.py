"""``wss-nlp batch``: many exams from a manifest, on local processes or Dask, resumable, with a cohort report
(:mod:`wss_nlp.app.batch`)."""

from __future__ import annotations

import logging
import sys

from ...io import outputs

log = logging.getLogger(__name__)  # warnings: the command line shows them once per kind (main)


def cmd_batch(args) -> int:
    """Run a batch; exit 0 when every exam succeeded, 1 when any failed (2: bad manifest or options)."""
    from .. import executor
    from ..batch import load_manifest, run_batch

    if args.job_script:
        if args.cluster not in executor.JOBQUEUE:
            from ...errors import InputError

            raise InputError("--job-script shows what --cluster slurm or --cluster pbs submits; name one")
        where = executor.backend(args.workers, None, args.cluster, args.cluster_config)
        print(executor.job_script(where.kind, where.config or ""), end="")
        return 0
    outputs.check_outputs(folders={"-o": args.output_dir}, inputs=[args.manifest])
    exams = load_manifest(args.manifest, defaults=args)  # the command line's options are every exam's defaults
    where = executor.backend(args.workers, args.scheduler, args.cluster, args.cluster_config)
    quiet = _quiet_library_log()  # each exam's log goes to DIR/<id>/exam.log; the terminal has the bar
    try:
        s = run_batch(
            exams, args.output_dir, where, figures=args.figures, vtk=not args.no_vtk, retry_failed=args.retry_failed
        )
    except KeyboardInterrupt:
        print(
            f"\nwss-nlp: interrupted; finished exams are kept in {args.output_dir}; run the same command again to "
            "resume",
            file=sys.stderr,
        )
        return 130
    finally:
        quiet()
    print(
        f"{s.total} exams ({s.ran} run now, {s.skipped} done before): {s.total - s.failed} ok ({s.flagged} "
        f"flagged), {s.failed} failed; {s.seconds:.0f} s"
    )
    for path in (s.csv_path, s.parquet_path, s.report_path, s.log_path):
        if path:
            print(f"wrote {path}")
    if s.failed:
        log.warning(f"{s.failed} exam(s) failed; see the 'error' column of {s.csv_path}")
        return 1
    return 0


def _quiet_library_log():
    """Silence the library's log on the terminal (main shows it there) for the batch; returns the undo."""
    logger = logging.getLogger("wss_nlp")
    saved = []
    for h in logger.handlers:
        if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler):
            saved.append((h, h.level))
            h.setLevel(logging.CRITICAL + 1)

    def undo():
        for h, level in saved:
            h.setLevel(level)

    return undo
