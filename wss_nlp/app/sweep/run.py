"""Running a study's cases in local processes or on a Dask cluster, each written atomically, resumable."""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from ...pipeline.results import SliceResult
from typing import Any
from dataclasses import dataclass, field
import numpy as np
from ... import __version__
from ...io import files as wio
from ...analysis import metrics as met
from ...errors import InputError, WssNlpError
from ...pipeline.driver import reconstruct
from .spec import METRICS, Study, _acquisition, case_id, expand, options_for
from .tables import flat_row, write_csv, write_views


@dataclass
class Summary:
    """What a sweep did."""

    total: int
    ran: int
    skipped: int
    failed: int
    seconds: float
    csv_path: str
    rows: list = field(default_factory=list)
    outputs: list = field(default_factory=list)  # tables and figures written


def case_metrics(res, truth) -> dict:
    """The :data:`METRICS` of one slice result (errors NaN without a truth)."""
    nan = float("nan")
    out = dict.fromkeys(METRICS, nan)
    out.update(
        mean_wss_pa=float(res.wss.mean),
        alpha_used=float(res.geometry.alpha),
        beta_used=float(res.velocity.beta) if isinstance(res, SliceResult) else nan,
        mean_wss_std_pa=float(getattr(res.wss, "mean_std", nan)),
    )
    if truth is not None:
        e = met.compare_slice(res, truth)
        out.update(
            radius_err=e.radius_rel_l2,
            radius_max_mm=e.radius_max_mm,
            wss_err=e.wss_rel_l2,
            mean_wss_bias=e.mean_wss_rel,
            mean_wss_true_pa=e.mean_wss_true_pa,
            radius_err_h2=met.radius_h2_error(res.geometry.center, res.geometry.coefficients, truth),
            velocity_err=met.velocity_error(getattr(res, "velocity", None), truth),
        )
    return out


def run_case(params: dict, base_dir: str = ".") -> tuple[dict, bytes | None]:
    """Run one case; returns its record and the bytes of its result file (None on failure).

    Runs anywhere (a local process or a Dask worker): it reads nothing but
    the case's own input and writes nothing but a temporary file, so the
    caller alone decides what lands in the output folder.
    """
    t0 = time.perf_counter()
    cid = case_id(params)
    record: dict[str, Any] = {"id": cid, "params": params, "wss_nlp_version": __version__}
    try:
        options = options_for(params, cid)
        acq, truth = _acquisition(params, base_dir)
        res = reconstruct(acq, options)[0]
        record.update(
            status="ok" if res.converged else "not converged",
            converged=bool(res.converged),
            message="; ".join(res.warnings),
            metrics=case_metrics(res, truth),
        )
        fd, tmp = tempfile.mkstemp(suffix=".h5")
        os.close(fd)
        try:
            wio.write_result(
                tmp,
                [res],
                options.as_dict(),
                argv=["wss-nlp sweep", cid],
                extra_attrs={"sweep_params_json": json.dumps(params, default=str)},
            )
            with open(tmp, "rb") as fh:
                blob = fh.read()
        finally:
            os.remove(tmp)
    except WssNlpError as exc:  # a failed case is a result of the study, not a crash of it
        record.update(status="error", converged=False, message=str(exc), metrics=dict.fromkeys(METRICS, None))
        blob = None
    record["metrics"]["seconds"] = time.perf_counter() - t0
    return record, blob


# ------------------------------------------------------------------ running
def _done(cases_dir: str, cid: str, retry_failed: bool) -> dict | None:
    """The finished record of a case, or None if it has to run (missing, unreadable or, if asked, failed)."""
    path = os.path.join(cases_dir, cid + ".json")
    try:
        with open(path) as fh:
            rec = json.load(fh)
    except (OSError, ValueError):
        return None
    if rec.get("status") == "error" and retry_failed:
        return None
    if rec.get("status") != "error" and not os.path.exists(os.path.join(cases_dir, cid + ".h5")):
        return None
    return rec


class Progress:
    """Progress over a study's cases: a tqdm bar on a terminal, a line per case otherwise (logs, CI)."""

    def __init__(self, total: int, stream=None, skipped: int = 0):
        self.total, self.done, self.failed = total, skipped, 0
        self.stream = stream if stream is not None else sys.stderr
        self.t0 = time.perf_counter()
        self.ran = 0
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.bar = None
        if self.tty:
            from tqdm import tqdm  # only where a bar is drawn: the line form needs nothing

            self.bar = tqdm(total=total, initial=skipped, file=self.stream, unit="case", dynamic_ncols=True)

    def update(self, record: dict) -> None:
        self.done += 1
        self.ran += 1
        self.failed += record["status"] != "ok"
        if self.bar is not None:
            self.bar.set_postfix_str(f"{self.failed} not ok, last {record['id']}: {record['status']}", refresh=False)
            self.bar.update(1)
            if self.done >= self.total:
                self.bar.close()
            return
        el = time.perf_counter() - self.t0
        eta = el / self.ran * (self.total - self.done)
        self.stream.write(
            f"{self.done}/{self.total} cases, {self.failed} not ok, {el:.0f} s elapsed, about {eta:.0f} s left  "
            f"({record['id']}: {record['status']})\n"
        )
        self.stream.flush()


# ---- issue 42: worker processes never outlive the sweep (begin) ----
def _die_with_parent(parent: int) -> None:
    """Worker initializer: end this worker when the sweep's process ends, even by SIGKILL.

    Linux: the kernel sends SIGKILL when the parent dies (``prctl(PR_SET_PDEATHSIG)``; the workers are started
    from the sweep's main thread). Elsewhere, and as a guard against a parent that died before the call, a daemon
    thread compares the parent's id every half second.
    """
    import signal
    import threading

    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the thread below does it
        pass
    if os.getppid() != parent:
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="wss-nlp-parent-watch", daemon=True).start()


# ---- issue 42 (end) ----


def _local_results(pending, base_dir, workers):
    """Yield ``(record, blob)`` as cases finish, in worker processes (in-process for one worker)."""
    if workers <= 1:
        for params in pending:
            yield run_case(params, base_dir)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    # one BLAS thread per process: the cases are the parallelism
    saved = {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    os.environ.update(dict.fromkeys(saved, "1"))
    try:
        pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=mp.get_context("spawn"),
            initializer=_die_with_parent,  # issue 42: no worker outlives a killed sweep
            initargs=(os.getpid(),),
        )
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    futures = [pool.submit(run_case, p, base_dir) for p in pending]
    try:
        for fut in as_completed(futures):
            yield fut.result()
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def _require_dask() -> None:
    try:
        import dask.distributed  # noqa: F401
    except ImportError:
        raise InputError("--scheduler needs dask.distributed: pip install 'wss-nlp[dask]'") from None


def _dask_results(pending, base_dir, scheduler):
    try:
        from dask.distributed import Client, as_completed
    except ImportError as exc:
        raise InputError("--scheduler needs dask.distributed: pip install 'wss-nlp[dask]'") from exc
    try:
        client = Client(scheduler, timeout="20s")
    except (OSError, TimeoutError) as exc:
        raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from exc
    try:
        futures = [client.submit(run_case, p, base_dir, key=f"wss-nlp-{case_id(p)}", pure=False) for p in pending]
        for fut in as_completed(futures):
            yield fut.result()
    finally:
        client.close()


def run_study(
    study: Study,
    outdir: str,
    workers: int | None = None,
    scheduler: str | None = None,
    retry_failed: bool = False,
    stream=None,
) -> Summary:
    """Run every case of ``study`` not yet done in ``outdir``; write results.csv, tables and plots."""
    if scheduler:  # issue 42: refuse a backend that cannot run before anything is written
        _require_dask()
    t0 = time.perf_counter()
    cases_dir = os.path.join(outdir, "cases")
    os.makedirs(cases_dir, exist_ok=True)
    for name in os.listdir(cases_dir):  # leftovers of an interrupted write are never trusted
        if name.endswith(".part"):
            os.remove(os.path.join(cases_dir, name))
    with open(study.source, "rb") as fh:
        wio.atomic_write(os.path.join(outdir, "study.toml"), fh.read())
    cases = expand(study)
    records: dict[str, Any] = {case_id(p): _done(cases_dir, case_id(p), retry_failed) for p in cases}
    pending = [p for p in cases if records[case_id(p)] is None]
    stream = stream if stream is not None else sys.stderr
    stream.write(
        f"study '{study.name}': {len(cases)} cases, {len(cases) - len(pending)} already done, "
        f"{len(pending)} to run" + (f" on {scheduler}" if scheduler else "") + "\n"
    )
    progress = Progress(len(cases), stream, skipped=len(cases) - len(pending))
    workers = workers or os.cpu_count() or 1
    results = (
        _dask_results(pending, study.base_dir, scheduler)
        if scheduler
        else _local_results(pending, study.base_dir, min(workers, max(len(pending), 1)))
    )
    for record, blob in results:
        cid = record["id"]
        if blob is not None:
            wio.atomic_write(os.path.join(cases_dir, cid + ".h5"), blob)
            record["result_file"] = os.path.join("cases", cid + ".h5")
        wio.atomic_write(os.path.join(cases_dir, cid + ".json"), json.dumps(record, indent=1, default=_json_default))
        records[cid] = record
        progress.update(record)
    rows = [flat_row(records[case_id(p)], study) for p in cases]
    csv_path = os.path.join(outdir, "results.csv")
    write_csv(csv_path, rows, study)
    summary = Summary(
        total=len(cases),
        ran=len(pending),
        skipped=len(cases) - len(pending),
        failed=sum(r["status"] != "ok" for r in rows),
        seconds=time.perf_counter() - t0,
        csv_path=csv_path,
        rows=rows,
    )
    summary.outputs = write_views(study, rows, outdir)
    return summary


def _json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return str(x)
