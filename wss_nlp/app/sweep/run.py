"""Running a study's cases in local processes or on a Dask cluster, each written atomically, resumable."""

from __future__ import annotations

import functools
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
from .. import executor
from ..progress import Progress
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


def _case_in(base_dir: str, params: dict) -> tuple[dict, bytes | None]:
    """:func:`run_case` with the study's folder bound first (a picklable task for the executor); ``run_case`` is
    looked up when the task runs, as ``run_case(params, base_dir)``."""
    return run_case(params, base_dir)


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


def _require_dask() -> None:
    try:
        import dask.distributed  # noqa: F401
    except ImportError:
        raise InputError("--scheduler needs dask.distributed: pip install 'wss-nlp[dask]'") from None


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
    where = executor.backend(workers=min(workers, max(len(pending), 1)), scheduler=scheduler)
    task = functools.partial(_case_in, study.base_dir)
    results = executor.results(where, task, pending, keys=[f"wss-nlp-{case_id(p)}" for p in pending])
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
