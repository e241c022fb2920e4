"""Declarative parameter studies: a TOML file -> a grid of cases -> a tidy table.

A study file (``problems/*.toml``) has a ``[study]`` table (name,
description, optional ``metrics``), a ``[grid]`` table whose list values are
crossed (scalars are held fixed) and optional ``[[tables]]`` / ``[[plots]]``
written after the run. ``wss-nlp sweep STUDY.toml -o OUTDIR`` runs it:

* every case is one reconstruction of a phantom (``case``, ``h``, ``snr``,
  ``seed``) or of an input file (``input``), with the options the grid sets;
* cases run in local processes or on a Dask cluster and are written as they
  finish, each atomically: ``cases/ID.h5`` (the result file) then
  ``cases/ID.json`` (parameters, metrics, status). A case counts as done only
  when its JSON exists, so a crash or Ctrl-C never leaves a half case that
  a rerun would trust, and a rerun skips what is done;
* ``results.csv`` (one row per case: every parameter, metric and solver
  status) is rewritten at the end.

Grid keys (:data:`PARAMETERS`) and metrics (:data:`METRICS`) are listed in
the docs, section "Parameter sweeps".
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import sys
import tempfile
import time
from typing import Any
from dataclasses import dataclass, field

import numpy as np

from .. import __version__
from ..io import files as wio
from ..analysis import metrics as met
from ..synthetic import phantoms
from ..core import schema
from ..errors import InputError, WssNlpError
from ..pipeline.driver import reconstruct
from ..pipeline.options import METHODS, ReconstructionOptions

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

#: Data keys: which acquisition a case reconstructs.
DATA_KEYS = ("case", "h", "snr", "seed", "venc", "input")

#: Option keys of the study grid: every ``toml`` key of the options schema (:func:`wss_nlp.core.schema.toml_keys`), and
#: ``M`` = ``degree`` (Zernike basis) or ``max_eigenvalue`` (eigenfunction basis).
PARAMETERS = (*schema.toml_keys(ReconstructionOptions), "M")


#: Metrics of one case (NaN where they do not apply, e.g. velocity_err of a baseline, errors without a truth).
METRICS = {
    "radius_err": "radius relative L2 error",
    "radius_err_h2": "radius relative H^2 error (paper Table 1)",
    "radius_max_mm": "largest radius error [mm]",
    "velocity_err": "velocity relative L2 error on the reference disk (paper Table 2 uses H^2)",
    "wss_err": "WSS relative L2 error (paper Table 3)",
    "mean_wss_bias": "signed relative error of the mean WSS",
    "mean_wss_pa": "mean WSS [Pa]",
    "mean_wss_true_pa": "true mean WSS [Pa]",
    "mean_wss_std_pa": "linearized standard deviation of the mean WSS [Pa] (with uncertainty = true)",
    "alpha_used": "alpha used",
    "beta_used": "beta used",
    "seconds": "wall time of the case [s]",
}

_STATUS_COLUMNS = ("status", "converged", "message", "result_file")


@dataclass(frozen=True)
class Study:
    """A parsed study file."""

    name: str
    description: str
    grid: dict  # key -> list of values (scalars already wrapped)
    metrics: tuple
    tables: tuple = ()
    plots: tuple = ()
    source: str = ""
    base_dir: str = "."

    @property
    def varying(self) -> list[str]:
        return [k for k, v in self.grid.items() if len(v) > 1]


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


# ------------------------------------------------------------------ parsing
def _values(key: str, spec, src: str) -> list:
    """A grid entry: a scalar, a list, ``{range = [a, b]}`` (integers, b excluded) or ``{start, stop, num, log}``."""
    if isinstance(spec, list):
        if not spec:
            raise InputError(f"{src}: grid.{key} is an empty list")
        return spec
    if isinstance(spec, dict):
        if "range" in spec:
            r = spec["range"]
            if not (isinstance(r, list) and len(r) in (2, 3) and all(isinstance(x, int) for x in r)):
                raise InputError(f"{src}: grid.{key}.range must be [start, stop] or [start, stop, step] integers")
            return list(range(*r))
        if {"start", "stop", "num"} <= set(spec):
            f = np.geomspace if spec.get("log", False) else np.linspace
            return [float(x) for x in f(spec["start"], spec["stop"], int(spec["num"]))]
        raise InputError(
            f"{src}: grid.{key} must be a value, a list, {{range = [a, b]}} or {{start, stop, num, log}}; got {spec!r}"
        )
    return [spec]


def load_study(path) -> Study:
    """Read and check a study file; every problem is reported with the file and the key."""
    src = str(path)
    if not os.path.exists(src):
        raise InputError(f"{src}: no such study file")
    try:
        with open(src, "rb") as fh:
            doc = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{src}: not valid TOML ({exc})") from exc
    except UnicodeDecodeError:
        raise InputError(f"{src}: not a TOML study file (not UTF-8 text); see problems/README.md") from None
    except IsADirectoryError:
        raise InputError(f"{src}: is a folder; name a study file (problems/*.toml)") from None
    unknown_tables = set(doc) - {"study", "grid", "tables", "plots"}
    if unknown_tables:
        raise InputError(
            f"{src}: unknown table(s) {sorted(unknown_tables)}; expected [study], [grid], [[tables]], [[plots]]"
        )
    head = doc.get("study", {})
    if "name" not in head:
        raise InputError(f"{src}: [study] needs a name")
    grid_doc = doc.get("grid", {})
    unknown = [k for k in grid_doc if k not in DATA_KEYS and k not in PARAMETERS]
    if unknown:
        raise InputError(f"{src}: unknown grid key(s) {unknown}; known: {', '.join(DATA_KEYS + tuple(PARAMETERS))}")
    grid = {k: _values(k, v, src) for k, v in grid_doc.items()}
    if ("case" in grid) == ("input" in grid):
        raise InputError(f"{src}: the grid needs exactly one of 'case' (phantoms) and 'input' (files)")
    if "input" in grid:
        extra = [k for k in ("h", "snr", "seed", "venc") if k in grid]
        if extra:
            raise InputError(f"{src}: {extra} describe phantoms and cannot be combined with 'input'")
    else:
        bad = [c for c in grid["case"] if c not in phantoms.CASES]
        if bad:
            raise InputError(f"{src}: unknown phantom case(s) {bad}; choose from {', '.join(phantoms.CASES)}")
        grid.setdefault("h", [1.0])
        grid.setdefault("snr", [25.0])
        grid.setdefault("seed", [0])
    bad = [m for m in grid.get("method", []) if m not in METHODS]
    if bad:
        raise InputError(f"{src}: unknown method(s) {bad}; choose from {', '.join(METHODS)}")
    names = tuple(head.get("metrics", METRICS))
    bad = [m for m in names if m not in METRICS]
    if bad:
        raise InputError(f"{src}: unknown metric(s) {bad}; known: {', '.join(METRICS)}")
    study = Study(
        name=str(head["name"]),
        description=str(head.get("description", "")),
        grid=grid,
        metrics=names,
        tables=tuple(doc.get("tables", ())),
        plots=tuple(doc.get("plots", ())),
        source=src,
        base_dir=os.path.dirname(os.path.abspath(src)),
    )
    for spec in study.tables + study.plots:
        _check_view(study, spec)
    for params in expand(study):  # fail now, not after an hour of computing, on options that cannot be built
        options_for(params, src)
    return study


def _check_view(study: Study, spec: dict) -> None:
    keys = set(study.grid) | {"seed"}
    for role in ("rows", "cols", "x", "by"):
        if role in spec and spec[role] not in keys and spec[role] != "metric":
            raise InputError(f"{study.source}: table/plot {role} = {spec[role]!r} is not a grid key")
    metric = spec.get("metric", spec.get("y"))
    if metric is None or metric not in METRICS:
        raise InputError(f"{study.source}: table/plot needs 'metric' (or 'y') from {', '.join(METRICS)}")


def expand(study: Study) -> list[dict]:
    """The cases of the grid: the cross product of all lists, in the order the keys appear."""
    keys = list(study.grid)
    cases: list[dict] = [{}]
    for k in keys:
        cases = [{**c, k: v} for c in cases for v in study.grid[k]]
    return cases


def case_id(params: dict) -> str:
    """A readable, stable identifier: the data keys, then a hash of every parameter."""
    digest = hashlib.sha1(json.dumps(params, sort_keys=True, default=str).encode()).hexdigest()[:10]
    if "case" in params:
        head = f"{params['case']}_h{params['h']:g}_snr{params['snr']:g}_s{params['seed']}"
    else:
        head = os.path.splitext(os.path.basename(_input_path(params["input"])))[0]
    return f"{head}_{params.get('method', 'decoupled')}_{digest}"


def _input_path(entry) -> str:
    return entry["file"] if isinstance(entry, dict) else str(entry)


def options_for(params: dict, where: str = "") -> ReconstructionOptions:
    """ReconstructionOptions for one case (defaults for everything the case does not set)."""
    keys = {k: v for k, v in params.items() if k not in DATA_KEYS}
    if "M" in keys:
        keys["max_eigenvalue" if params.get("basis") == "eigen" else "degree"] = keys.pop("M")
    try:
        return schema.build(ReconstructionOptions, keys, where)
    except InputError as exc:
        raise InputError(f"{where}: {exc} (case {params})") from exc


# ------------------------------------------------------------------ one case
def _acquisition(params: dict, base_dir: str):
    if "case" in params:
        return phantoms.make_phantom(
            params["case"],
            h_mm=float(params["h"]),
            snr=None if params["snr"] in (None, 0) else float(params["snr"]),
            seed=int(params["seed"]),
            venc=params.get("venc"),
        )
    entry = params["input"]
    path = os.path.join(base_dir, _input_path(entry))
    truth = None
    if isinstance(entry, dict) and entry.get("truth"):
        truth = met.TruthTable.from_file(os.path.join(base_dir, entry["truth"]))
    return wio.read_acquisition(path), truth


def case_metrics(res, truth) -> dict:
    """The :data:`METRICS` of one slice result (errors NaN without a truth)."""
    nan = float("nan")
    out = dict.fromkeys(METRICS, nan)
    out.update(
        mean_wss_pa=float(res.wss.mean),
        alpha_used=float(res.geometry.alpha),
        beta_used=float(res.velocity.beta) if hasattr(res, "velocity") else nan,
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
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"))
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


def flat_row(record: dict, study: Study) -> dict:
    """One CSV row: parameters (inputs by file name), status columns, metrics."""
    row = {}
    for k in study.grid:
        v = record["params"][k]
        row[k] = _input_path(v) if k == "input" else v
    row.update(
        id=record["id"],
        status=record["status"],
        converged=record["converged"],
        message=record.get("message", ""),
        result_file=record.get("result_file", ""),
    )
    for m in study.metrics:
        v = record["metrics"].get(m)
        row[m] = float("nan") if v is None else v
    return row


def write_csv(path: str, rows: list, study: Study) -> None:
    cols = list(study.grid) + ["id", *_STATUS_COLUMNS] + list(study.metrics)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    wio.atomic_write(path, buf.getvalue().encode())


def read_csv(outdir: str) -> list[dict]:
    """Rows of ``OUTDIR/results.csv`` with numbers parsed."""
    path = os.path.join(outdir, "results.csv")
    if not os.path.exists(path):
        raise InputError(f"{path}: no such file; run 'wss-nlp sweep STUDY.toml -o {outdir}' first")
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        for k, v in r.items():
            r[k] = _parse(v)
    return rows


def _parse(text: str):
    if text in ("True", "False"):
        return text == "True"
    try:
        f = float(text)
    except ValueError:
        return text
    return int(f) if f.is_integer() and "." not in text and "e" not in text.lower() and "nan" not in text else f


# ------------------------------------------------------------------ tables and plots
def select(rows: list, where: dict) -> list:
    """Rows whose columns equal every ``where`` value (numbers compared as floats)."""

    def eq(a, b):
        try:
            return float(a) == float(b)
        except (TypeError, ValueError):
            return str(a) == str(b)

    return [r for r in rows if all(eq(r.get(k), v) for k, v in where.items())]


def _fixed_check(rows: list, free: set, where: str) -> None:
    """Error if a parameter other than ``free`` (and seed) varies: the table would mix cases silently."""
    params = [k for k in rows[0] if k not in set(METRICS) | {"id", *_STATUS_COLUMNS}]
    varying = {
        k: sorted({str(r[k]) for r in rows})
        for k in params
        if k not in free and k != "seed" and len({str(r[k]) for r in rows}) > 1
    }
    if varying:
        hint = " ".join(f"{k}={v[0]}" for k, v in varying.items())
        raise InputError(
            f"{where}: parameter(s) {', '.join(f'{k} {v}' for k, v in varying.items())} vary but "
            f"are neither rows nor columns; fix them with --where (e.g. --where {hint})"
        )


AGGREGATES: dict[str, Any] = {"mean": np.mean, "median": np.median, "max": np.max, "min": np.min}


def pivot(
    rows: list,
    row_key: str,
    col_key: str,
    metric: str,
    where: dict | None = None,
    agg: str = "mean",
    source: str = "results.csv",
):
    """``(row values, col values, matrix, counts, flagged)``: ``agg`` of ``metric`` over the seeds.

    Failed cases (status "error") are left out; ``flagged`` counts the cases
    of each cell whose solver did not converge (they are included, and marked
    in the rendered table).

    ``row_key`` or ``col_key`` may be ``"metric"`` for a one-row table (as the paper's Table 3).
    """
    sel = select(rows, where or {})
    if not sel:
        raise InputError(f"{source}: no rows match {where}")
    for k in (row_key, col_key):
        if k != "metric" and k not in sel[0]:
            raise InputError(f"{source}: no column {k!r}; columns: {', '.join(sel[0])}")
    if metric not in sel[0]:
        raise InputError(f"{source}: no metric {metric!r}; columns: {', '.join(sel[0])}")
    _fixed_check(sel, {row_key, col_key}, source)
    f = AGGREGATES[agg]

    def key_values(k):
        return [metric] if k == "metric" else list(dict.fromkeys(r[k] for r in sel))

    rv, cv = key_values(row_key), key_values(col_key)
    mat = np.full((len(rv), len(cv)), np.nan)
    cnt = np.zeros((len(rv), len(cv)), dtype=int)
    flagged = np.zeros((len(rv), len(cv)), dtype=int)
    for i, a in enumerate(rv):
        for j, b in enumerate(cv):
            cell = [
                r
                for r in sel
                if (row_key == "metric" or r[row_key] == a)
                and (col_key == "metric" or r[col_key] == b)
                and r["status"] != "error"
                and np.isfinite(float(r[metric]))
            ]
            if cell:
                mat[i, j], cnt[i, j] = f([float(r[metric]) for r in cell]), len(cell)
                flagged[i, j] = sum(r["status"] != "ok" for r in cell)
    return rv, cv, mat, cnt, flagged


def _best(values: np.ndarray, metric: str) -> int | None:
    ok = np.isfinite(values)
    if not ok.any() or not (
        metric.endswith("_err") or metric.endswith("_bias") or metric.endswith("_h2") or metric == "radius_max_mm"
    ):
        return None
    return int(np.nanargmin(np.where(ok, np.abs(values), np.nan)))


def _fmt(x: float, metric: str) -> str:
    if not np.isfinite(x):
        return "-"
    if metric.endswith("_err") or metric.endswith("_h2") or metric == "mean_wss_bias":
        return f"{x:.4f}" if metric != "mean_wss_bias" else f"{x:+.4f}"
    return f"{x:.4g}"


def render_table(
    rv, cv, mat, row_key, col_key, metric, caption: str = "", flagged=None, bold: bool = True
) -> tuple[str, str]:
    """Markdown and LaTeX of a pivot, the best value of each row in bold (smallest absolute error).

    Cells with a non-converged case (``flagged > 0``) carry a dagger.
    """
    flagged = np.zeros(mat.shape, dtype=int) if flagged is None else flagged

    def lab(v):
        return f"{v:g}" if isinstance(v, float) else str(v)

    corner = f"{row_key} \\ {col_key}"
    md = [f"| {corner} | " + " | ".join(lab(c) for c in cv) + " |", "|---" * (len(cv) + 1) + "|"]
    tex = [
        r"\begin{table}[ht!]",
        r"\centering",
        r"\begin{tabular}{c||" + "|".join("c" * len(cv)) + "}",
        f"${row_key.replace('_', ' ')}\\setminus {col_key.replace('_', ' ')}$ & "
        + " & ".join(lab(c) for c in cv)
        + r" \\",
        r"\hline",
        r"\hline",
    ]
    for i, a in enumerate(rv):
        b = _best(mat[i], metric) if bold else None
        cells_md = [_fmt(x, metric) + ("†" if flagged[i, j] else "") for j, x in enumerate(mat[i])]
        cells_tex = [c.replace("†", r"$^\dagger$") for c in cells_md]
        if b is not None:
            cells_md[b] = f"**{cells_md[b]}**"
            cells_tex[b] = rf"\textbf{{{cells_tex[b]}}}"
        md.append(f"| {lab(a)} | " + " | ".join(cells_md) + " |")
        tex.append(f"{lab(a)} & " + " & ".join(cells_tex) + r" \\")
    tex += [r"\end{tabular}", rf"\caption{{{caption or metric.replace('_', ' ')}}}", r"\end{table}"]
    return "\n".join(md) + "\n", "\n".join(tex) + "\n"


def table(rows, rows_key, cols_key, metric, where=None, agg="mean", caption="", source="results.csv", bold=True):
    """Markdown and LaTeX of one paper-style table from sweep rows (``bold=False`` when columns are not rivals)."""
    rv, cv, mat, cnt, flagged = pivot(rows, rows_key, cols_key, metric, where, agg, source)
    md, tex = render_table(rv, cv, mat, rows_key, cols_key, metric, caption, flagged, bold)
    n = cnt[cnt > 0]
    note = (
        f"\n{agg} of {metric} ({METRICS[metric]}) over {n.min()}-{n.max()} case(s) per cell"
        + (f"; {where}" if where else "")
        + ("; bold: smallest absolute value in the row" if bold else "")
        + (
            f"; †: the cell includes {flagged.sum()} case(s) whose solver did not converge (see results.csv)"
            if flagged.any()
            else ""
        )
        + ".\n"
    )
    return md + note, tex


def write_views(study: Study, rows: list, outdir: str) -> list[str]:
    """Tables and plots the study file asks for (``[[tables]]``, ``[[plots]]``)."""
    out = []
    for i, spec in enumerate(study.tables):
        name = spec.get("name", f"table{i + 1}")
        md, tex = table(
            rows,
            spec["rows"],
            spec["cols"],
            spec["metric"],
            spec.get("where"),
            spec.get("agg", "mean"),
            spec.get("caption", ""),
            os.path.join(outdir, "results.csv"),
            spec.get("bold", True),
        )
        for ext, text in (("md", md), ("tex", tex)):
            path = os.path.join(outdir, f"{name}.{ext}")
            wio.atomic_write(path, text)
            out.append(path)
    for i, spec in enumerate(study.plots):
        from .plotting import save_figure

        name = spec.get("name", f"plot{i + 1}")
        fig = plot(
            rows,
            spec["x"],
            spec["y"],
            by=spec.get("by"),
            where=spec.get("where"),
            panels=spec.get("panels"),
            logx=spec.get("logx", False),
            title=spec.get("title", ""),
        )
        out.append(save_figure(fig, os.path.join(outdir, f"{name}.png")))
    return out


def plot(
    rows: list,
    x: str,
    y: str,
    by: str | None = None,
    where: dict | None = None,
    panels: str | None = None,
    logx: bool = False,
    title: str = "",
):
    """Metric ``y`` against parameter ``x`` over the rows matching ``where`` (:func:`~.plotting.figure_sweep`)."""
    from .plotting import figure_sweep

    return figure_sweep(
        select(rows, where or {}), x, y, by=by, panels=panels, logx=logx, title=title, ylabel=METRICS.get(y, y)
    )
