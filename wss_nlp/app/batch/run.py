"""Running a batch: which exams need to run, running them on a backend, the summary table, the log and the report.

:func:`run_batch` compares every exam of the manifest with the record its folder holds (``DIR/<id>/exam.json``):
an exam runs again only when its key changed (the input's content, its options, the outputs asked for or the
software version), when it never finished, when it crashed (``failure`` ``crash``), or, with
``retry_failed``, when it failed on its input. The others are kept untouched. The exams that run go to the
executor (:mod:`wss_nlp.app.executor`), one bar counts them and their failures, ``DIR/batch.log`` records the
run; at the end ``DIR/summary.csv`` (and ``summary.parquet`` with pyarrow) and ``DIR/report.html`` are written
from every exam's record, so a resumed run ends with the summary an uninterrupted one writes.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import logging
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ... import __version__
from ...io import files as wio
from .. import executor
from ..progress import Progress
from .exam import STAGING, ExamTask, commit, failed_record, run_exam, short_flag
from .manifest import Exam, input_digest, load_manifest

#: The columns of summary.csv, in order, with what they hold (docs, "Cohorts").
SUMMARY_COLUMNS = {
    "id": "the exam's id (its folder)",
    "status": "ok or failed (an exam with flags is ok; see flags)",
    "error": "the one-line message of a failure",
    "failure": "input (the data or options; kept until they change) or crash (run again next time)",
    "input": "the manifest's input (paths joined by ';')",
    "kind": "slice, stack, cine or cine stack",
    "n_slices": "slices",
    "n_frames": "frames (1 for steady data)",
    "failed_slices": "slices that could not be reconstructed (their reasons are flags)",
    "mean_wss_pa": "mean WSS over the wall of every reconstructed slice, arc-length weighted [Pa]; cine: its "
    "average over the cycle",
    "tawss_pa": "cine: time-averaged WSS magnitude, arc-length mean over the wall [Pa]",
    "osi_mean": "cine: oscillatory shear index, arc-length mean over the wall",
    "osi_max": "cine: largest OSI on the wall",
    "radius_mm": "mean radius R_0 over the slices (and frames) [mm]",
    "alpha": "geometry regularization chosen (median over slices and frames)",
    "beta": "velocity regularization chosen (median; NaN for the classical baselines)",
    "near_wall": "near-wall model(s) chosen (plain or a layer family)",
    "cycle_model": "cine: the velocity model over the cycle (independent, temporal, momentum)",
    "method": "reconstruction method",
    "solver_status": "converged, or which slices did not",
    "flags": "why to look twice (SUSPECT findings, failed slices or frames, no convergence), separated by ' | '",
    "n_warnings": "warnings in the exam's record (exam.json)",
    "options": "the manifest's option columns set for this exam",
    "seconds": "wall time of the exam [s]",
    "wss_nlp_version": "software version that computed it",
    "input_sha256": "SHA-256 of the input's content",
    "result_file": "the exam's result file",
}
_INTEGERS = ("n_slices", "n_frames", "failed_slices", "n_warnings")
_NUMBERS = (*_INTEGERS, "mean_wss_pa", "tawss_pa", "osi_mean", "osi_max", "radius_mm", "alpha", "beta", "seconds")
#: The batch's own log lines go here (written to DIR/batch.log only).
log = logging.getLogger("wss_nlp.app.batch")


@dataclass
class BatchSummary:
    """What a batch run did and where its tables are."""

    total: int
    ran: int
    skipped: int
    failed: int
    flagged: int
    seconds: float
    csv_path: str
    parquet_path: str | None
    report_path: str
    log_path: str
    rows: list = field(default_factory=list)


def run_batch(
    manifest: str | Sequence[Exam],
    outdir: str,
    where: executor.Backend | None = None,
    figures: bool = False,
    vtk: bool = True,
    retry_failed: bool = False,
    defaults: argparse.Namespace | Sequence[str] | None = None,
    stream=None,
) -> BatchSummary:
    """Run every exam of ``manifest`` (a file, :func:`~wss_nlp.app.batch.manifest.load_manifest`, or its exams)
    that is not done in ``outdir`` on ``where`` (default: this process), then write the summary and the report.

    ``figures``: every figure of every exam in ``DIR/<id>/figures``; ``vtk``: the wall as ``wall.vtu`` (needs
    meshio); ``retry_failed``: run again the exams that failed on their input; ``defaults``: options for every
    exam (see :func:`~wss_nlp.app.batch.manifest.load_manifest`); ``stream``: where the progress goes (stderr).
    """
    t0 = time.perf_counter()
    exams = load_manifest(manifest, defaults) if isinstance(manifest, str) else list(manifest)
    where = where or executor.Backend()
    if vtk:
        _require_meshio()
    outdir = os.path.abspath(outdir)
    os.makedirs(outdir, exist_ok=True)
    _clean(outdir, exams)
    log_path = os.path.join(outdir, "batch.log")
    handler = logging.FileHandler(log_path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.propagate = False  # the terminal shows the bar; the log file has the lines
    try:
        return _run(exams, outdir, where, figures, vtk, retry_failed, stream, t0, log_path)
    except KeyboardInterrupt:
        log.info("interrupted; finished exams are kept, the same command resumes")
        raise
    finally:
        log.removeHandler(handler)
        handler.close()


def _run(exams, outdir, where, figures, vtk, retry_failed, stream, t0, log_path) -> BatchSummary:
    outputs = {"figures": bool(figures), "vtk": bool(vtk)}
    records: dict = {}
    tasks: list[ExamTask] = []
    why: dict = {"new": 0, "changed": 0, "failed before": 0}
    for exam in exams:
        previous = read_record(os.path.join(outdir, exam.id))
        digest, stat = input_digest(exam.inputs, previous)
        key = hashlib.sha256((digest + exam.settings_json(outputs)).encode()).hexdigest()
        reason = _rerun(previous, key, retry_failed, os.path.join(outdir, exam.id))
        if reason is None:
            records[exam.id] = previous
            continue
        why[reason] += 1
        tasks.append(ExamTask(exam, outdir, key, digest, stat, figures, vtk))
    stream = stream if stream is not None else sys.stderr
    done_before = len(exams) - len(tasks)
    failed_before = sum(r["status"] != "ok" for r in records.values())
    head = (
        f"batch: {len(exams)} exams, {done_before} done before"
        + (f" ({failed_before} failed on their input; --retry-failed runs them)" if failed_before else "")
        + f", {len(tasks)} to run"
        + (f" ({', '.join(f'{n} {k}' for k, n in why.items() if n)}) on {where.describe()}" if tasks else "")
    )
    stream.write(head + "\n")
    log.info("%s; wss-nlp %s", head, __version__)
    if tasks:
        for name in ("summary.csv", "summary.parquet", "report.html"):  # a partial run has no summary
            if os.path.exists(os.path.join(outdir, name)):
                os.remove(os.path.join(outdir, name))
    progress = Progress(len(exams), stream, skipped=done_before, unit="exam", bad="failed")
    try:
        with executor.Executor(where if tasks else executor.Backend()) as ex:  # nothing to run: start nothing
            keys = [f"wss-nlp-exam-{t.exam.id}" for t in tasks]
            for done in ex.as_completed(run_exam, tasks, keys):
                if done.error is None:
                    record = done.value
                else:  # the worker was lost (or the exam's code could not even start): a crash, run again next time
                    task = tasks[done.index]
                    record = failed_record(task, f"worker lost: {type(done.error).__name__}: {done.error}")
                    _commit_record(outdir, record)
                records[record["id"]] = record
                progress.update(record)
                log.info("%s", _line(record))
    except BaseException:
        progress.close()
        raise
    # every exam of this run is committed: what is left in the staging folder is the half of an exam whose worker
    # was lost (Dask ran the exam again elsewhere)
    shutil.rmtree(os.path.join(outdir, STAGING), ignore_errors=True)
    rows = summary_rows(exams, records)
    csv_path, parquet_path = write_summary(outdir, rows)
    from .report import write_report

    report_path = write_report(outdir, rows, records)[0]
    failed = sum(r["status"] != "ok" for r in rows)
    flagged = sum(r["status"] == "ok" and bool(r["flags"]) for r in rows)
    summary = BatchSummary(
        total=len(exams),
        ran=len(tasks),
        skipped=done_before,
        failed=failed,
        flagged=flagged,
        seconds=time.perf_counter() - t0,
        csv_path=csv_path,
        parquet_path=parquet_path,
        report_path=report_path,
        log_path=log_path,
        rows=rows,
    )
    log.info(
        "batch finished: %d exams (%d run now), %d failed, %d flagged; %s; %s",
        len(rows), len(tasks), failed, flagged, csv_path, report_path,
    )  # fmt: skip
    return summary


def read_record(folder: str) -> dict | None:
    """The record of a finished exam (``exam.json``), or None (never run, or unreadable)."""
    try:
        with open(os.path.join(folder, "exam.json")) as fh:
            record = json.load(fh)
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and "key" in record and "status" in record else None


def _rerun(previous: dict | None, key: str, retry_failed: bool, folder: str) -> str | None:
    """Why an exam has to run (``new``, ``changed``, ``failed before``), or None when its record stands."""
    if previous is None:
        return "new"
    if previous.get("key") != key:
        return "changed"
    if previous["status"] == "ok":
        return None if os.path.exists(os.path.join(folder, "result.h5")) else "new"
    if previous.get("failure") == "input" and not retry_failed:
        return None
    return "failed before"


def _clean(outdir: str, exams: Sequence[Exam]) -> None:
    """Remove what an interrupted run left: exams being built, older exam folders being replaced."""
    shutil.rmtree(os.path.join(outdir, STAGING), ignore_errors=True)
    for exam in exams:
        prefix = exam.id + ".old-"
        for name in os.listdir(outdir):
            if name.startswith(prefix):
                shutil.rmtree(os.path.join(outdir, name), ignore_errors=True)


def _commit_record(outdir: str, record: dict) -> None:
    import tempfile

    staging = os.path.join(outdir, STAGING)
    os.makedirs(staging, exist_ok=True)
    stage = tempfile.mkdtemp(prefix=f"{record['id']}.", dir=staging)
    with open(os.path.join(stage, "exam.json"), "w") as fh:
        json.dump(record, fh, indent=1)
    commit(stage, os.path.join(outdir, record["id"]))


def _line(record: dict) -> str:
    """One line of batch.log for a finished exam."""
    if record["status"] != "ok":
        return f"{record['id']}: failed ({record.get('failure')}): {record['error']}"
    m = record["metrics"]
    text = f"{record['id']}: ok, {m['kind']}, mean WSS {m['mean_wss_pa']:.4g} Pa, {record['seconds']:.1f} s"
    if record.get("flags"):
        text += "; flags: " + " | ".join(short_flag(f) for f in record["flags"])
    return text


def summary_rows(exams: Sequence[Exam], records: dict) -> list[dict]:
    """One row of :data:`SUMMARY_COLUMNS` per exam, in the manifest's order, from the exams' records."""
    rows = []
    for exam in exams:
        rec = records[exam.id]
        m = rec.get("metrics") or {}
        flags = list(dict.fromkeys(short_flag(f) for f in rec.get("flags", [])))
        row = {
            "id": exam.id,
            "status": rec["status"],
            "error": rec.get("error", ""),
            "failure": rec.get("failure", ""),
            "input": exam.input_text,
            **{k: m.get(k, "") for k in SUMMARY_COLUMNS if k in m},
            "flags": " | ".join(flags),
            "n_warnings": len(rec.get("warnings", [])),
            "options": "; ".join(f"{k}={v}" for k, v in (rec.get("columns") or {}).items()),
            "seconds": rec.get("seconds", float("nan")),
            "wss_nlp_version": rec.get("wss_nlp_version", ""),
            "input_sha256": rec.get("input_sha256", ""),
            "result_file": os.path.join(exam.id, "result.h5") if rec["status"] == "ok" else "",
        }
        rows.append({k: row.get(k, "") for k in SUMMARY_COLUMNS})
    return rows


def write_summary(outdir: str, rows: list[dict]) -> tuple[str, str | None]:
    """``summary.csv`` (always) and ``summary.parquet`` (when pyarrow is installed); returns their paths."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(SUMMARY_COLUMNS), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(k, v) for k, v in row.items()})
    csv_path = os.path.join(outdir, "summary.csv")
    wio.atomic_write(csv_path, buf.getvalue())
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:  # optional: pip install 'wss-nlp[parquet]'
        return csv_path, None
    kinds = {
        k: pa.int64() if k in _INTEGERS else pa.float64() if k in _NUMBERS else pa.string() for k in SUMMARY_COLUMNS
    }
    columns = {k: pa.array([_parquet(k, r[k]) for r in rows], type=kinds[k]) for k in SUMMARY_COLUMNS}
    parquet_path = os.path.join(outdir, "summary.parquet")
    tmp = parquet_path + ".part"
    pq.write_table(pa.table(columns), tmp)
    os.replace(tmp, parquet_path)
    return csv_path, parquet_path


def read_summary(outdir: str) -> list[dict]:
    """The rows of ``DIR/summary.csv`` (numbers as floats, empty cells as NaN)."""
    path = os.path.join(outdir, "summary.csv")
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        from ...errors import InputError

        raise InputError(f"{path}: cannot read it ({exc.strerror or exc}); run 'wss-nlp batch' first") from None
    return [{k: _parquet(k, v) for k, v in r.items()} for r in rows]


def _cell(key: str, value):
    x = _parquet(key, value)
    if key in _INTEGERS:
        return "" if x is None else str(x)
    if key in _NUMBERS:
        return "" if not np.isfinite(x) else repr(x)  # repr: every digit, read back exactly
    return x


def _parquet(key: str, value):
    """The cell as a number (integers: None when missing; floats: NaN) or text."""
    if key in _NUMBERS:
        try:
            x = float(value)
        except (TypeError, ValueError):
            x = float("nan")
        if key in _INTEGERS:
            return int(x) if np.isfinite(x) else None
        return x
    return "" if value is None else str(value)


def _require_meshio() -> None:
    try:
        import meshio  # noqa: F401
    except ImportError:
        from ...errors import InputError

        raise InputError(
            "batch writes each exam's wall as VTK with meshio: pip install 'wss-nlp[vtk]', or pass --no-vtk"
        ) from None
