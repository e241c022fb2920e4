"""A study's results as a tidy CSV, pivot tables (Markdown, LaTeX) and plots.

``results.csv`` is written with the standard library, so a sweep runs without pandas; reading it back and the
pivot tables go through pandas (``read_csv``, ``pivot_table``, ``to_markdown``, ``Styler.to_latex``), an optional
extra: ``pip install 'wss-nlp[study]'``. Without it a sweep still writes its cases and ``results.csv`` and says in
one line how to get the tables.
"""

from __future__ import annotations

import csv
import io
import logging
import os
from typing import TYPE_CHECKING

import numpy as np
from ...io import files as wio
from ...errors import InputError
from .spec import AGGREGATES, METRICS, Study, _input_path

if TYPE_CHECKING:
    import pandas as pd

logger = logging.getLogger(__name__)

#: The columns of a case's outcome in results.csv.
_STATUS_COLUMNS = ("status", "converged", "message", "result_file")

#: How to get what the tables need (pandas; jinja2 for pandas' LaTeX writer).
STUDY_EXTRA = "pip install 'wss-nlp[study]'"


def _pandas():
    """pandas, imported when a table is made (an optional extra: a sweep runs without it)."""
    try:
        import pandas
    except ImportError:
        raise InputError(f"the study tables need pandas: {STUDY_EXTRA}") from None
    return pandas


def _have_study_extra() -> bool:
    """Whether pandas and jinja2 (the tables' optional extra) import."""
    try:
        import jinja2  # noqa: F401
        import pandas  # noqa: F401
    except ImportError:
        return False
    return True


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
    """``results.csv``: one row per case (the standard library's writer: a sweep needs no pandas)."""
    cols = list(study.grid) + ["id", *_STATUS_COLUMNS] + list(study.metrics)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    wio.atomic_write(path, buf.getvalue().encode())


def read_frame(outdir: str) -> pd.DataFrame:
    """``OUTDIR/results.csv`` as a pandas data frame, numbers, booleans and NaN parsed by pandas.

    Only ``nan`` (how the writer spells a missing metric) is missing: an empty message or result file stays the
    empty string.
    """
    path = os.path.join(outdir, "results.csv")
    if not os.path.exists(path):
        raise InputError(f"{path}: no such file; run 'wss-nlp sweep STUDY.toml -o {outdir}' first")
    return _pandas().read_csv(path, keep_default_na=False, na_values=["nan"])


def read_csv(outdir: str) -> list[dict]:
    """Rows of ``OUTDIR/results.csv`` with numbers parsed (:func:`read_frame`'s records, Python scalars)."""
    return read_frame(outdir).to_dict("records")


# ------------------------------------------------------------------ tables and plots
def select(rows: list, where: dict) -> list:
    """Rows whose columns equal every ``where`` value (numbers compared as floats)."""

    def eq(a, b):
        try:
            return float(a) == float(b)
        except (TypeError, ValueError):
            return str(a) == str(b)

    return [r for r in rows if all(eq(r.get(k), v) for k, v in where.items())]


def _fixed_check(frame: pd.DataFrame, free: set, where: str) -> None:
    """Error if a parameter other than ``free`` (and seed) varies: the table would mix cases silently."""
    params = [k for k in frame.columns if k not in set(METRICS) | {"id", *_STATUS_COLUMNS} and k not in free]
    varying = {
        k: sorted(set(frame[k].astype(str))) for k in params if k != "seed" and frame[k].astype(str).nunique() > 1
    }
    if varying:
        hint = " ".join(f"{k}={v[0]}" for k, v in varying.items())
        raise InputError(
            f"{where}: parameter(s) {', '.join(f'{k} {v}' for k, v in varying.items())} vary but "
            f"are neither rows nor columns; fix them with --where (e.g. --where {hint})"
        )


def pivot(
    rows,
    row_key: str,
    col_key: str,
    metric: str,
    where: dict | None = None,
    agg: str = "mean",
    source: str = "results.csv",
):
    """``(row values, col values, matrix, counts, flagged)``: ``agg`` of ``metric`` over the seeds.

    A pandas ``pivot_table`` of the rows (a list of dicts or a data frame) matching ``where``. Failed cases
    (status "error") are left out; ``flagged`` counts the cases of each cell whose solver did not converge (they
    are included, and marked in the rendered table). Rows and columns keep the order in which their values first
    appear; a value whose cases all failed keeps its row or column, with empty cells.

    ``row_key`` or ``col_key`` may be ``"metric"`` for a one-row table (as the paper's Table 3).
    """
    if agg not in AGGREGATES:
        raise InputError(f"{source}: unknown aggregate {agg!r}; one of {', '.join(AGGREGATES)}")
    pd = _pandas()
    records = rows.to_dict("records") if isinstance(rows, pd.DataFrame) else rows
    frame = pd.DataFrame(select(records, where or {}))
    if frame.empty:
        raise InputError(f"{source}: no rows match {where}")
    for k in (row_key, col_key):
        if k != "metric" and k not in frame.columns:
            raise InputError(f"{source}: no column {k!r}; columns: {', '.join(frame.columns)}")
    if metric not in frame.columns:
        raise InputError(f"{source}: no metric {metric!r}; columns: {', '.join(frame.columns)}")
    _fixed_check(frame, {row_key, col_key}, source)
    frame = frame.assign(**{"metric": metric} if "metric" in (row_key, col_key) else {})
    values = pd.to_numeric(frame[metric], errors="coerce")
    keep = frame.assign(_value=values, _flag=(frame["status"] != "ok").astype(int))
    keep = keep[(keep["status"] != "error") & np.isfinite(values)]
    rv, cv = list(pd.unique(frame[row_key])), list(pd.unique(frame[col_key]))

    def table(value: str, how: str) -> np.ndarray:
        # aggregates by name ("mean", "max", ...): pandas' own, not a NumPy callable (that path is deprecated)
        t = keep.pivot_table(index=row_key, columns=col_key, values=value, aggfunc=how, sort=False)
        return t.reindex(index=rv, columns=cv).to_numpy(dtype=float)

    if keep.empty:
        nan = np.full((len(rv), len(cv)), np.nan)
        return rv, cv, nan, np.zeros(nan.shape, dtype=int), np.zeros(nan.shape, dtype=int)
    mat = table("_value", agg)
    cnt = np.nan_to_num(table("_value", "count")).astype(int)
    flagged = np.nan_to_num(table("_flag", "sum")).astype(int)
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

    Cells with a non-converged case (``flagged > 0``) carry a dagger. The cells are formatted here (digits, bold,
    dagger); pandas lays them out: ``DataFrame.to_markdown`` (a pipe table) and ``Styler.to_latex`` (a ``table``
    float, centred, its caption above the tabular, a double rule under the header; the Styler needs jinja2).
    """
    pd = _pandas()
    flagged = np.zeros(mat.shape, dtype=int) if flagged is None else flagged

    def lab(v):
        return f"{v:g}" if isinstance(v, float) else str(v)

    md_rows, tex_rows = [], []
    for i, a in enumerate(rv):
        b = _best(mat[i], metric) if bold else None
        cells_md = [_fmt(x, metric) + ("†" if flagged[i, j] else "") for j, x in enumerate(mat[i])]
        cells_tex = [c.replace("†", r"$^\dagger$") for c in cells_md]
        if b is not None:
            cells_md[b] = f"**{cells_md[b]}**"
            cells_tex[b] = rf"\textbf{{{cells_tex[b]}}}"
        md_rows.append([lab(a), *cells_md])
        tex_rows.append([lab(a), *cells_tex])
    cols = [lab(c) for c in cv]
    md_frame = pd.DataFrame(md_rows, columns=[f"{row_key} \\ {col_key}", *cols], dtype=str)
    # the cells are strings already formatted: tabulate's number parsing would rewrite "1.0050" as "1.005"
    md = md_frame.to_markdown(
        index=False, tablefmt="pipe", disable_numparse=True, colalign=("left",) + ("right",) * len(cols)
    )
    corner = f"${row_key.replace('_', ' ')}\\setminus {col_key.replace('_', ' ')}$"
    tex_frame = pd.DataFrame(tex_rows, columns=[corner, *cols], dtype=str)
    try:
        styler = tex_frame.style
    except ImportError:  # pandas' Styler imports jinja2
        raise InputError(f"the LaTeX study tables need jinja2: {STUDY_EXTRA}") from None
    tex = (
        styler.hide(axis="index")
        .set_table_styles([{"selector": "midrule", "props": ":hline\\hline;"}], overwrite=False)
        .to_latex(
            column_format="c||" + "|".join("c" * len(cv)),
            position="ht!",
            position_float="centering",
            caption=caption or metric.replace("_", " "),
        )
    )
    return md + "\n", tex


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
    """Tables and plots the study file asks for (``[[tables]]``, ``[[plots]]``).

    The tables need pandas (and jinja2 for LaTeX): without them the tables are skipped with one warning that
    says how to get them; ``results.csv`` and the plots are written all the same.
    """
    out: list[str] = []
    tables = list(study.tables)
    if tables and not _have_study_extra():
        logger.warning(
            "%d study table(s) not written: they need pandas and jinja2 (%s; then 'wss-nlp table %s ...')",
            len(tables),
            STUDY_EXTRA,
            outdir,
        )
        tables = []
    for i, spec in enumerate(tables):
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
        from ..plotting import save_figure

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
    from ..plotting import figure_sweep

    return figure_sweep(
        select(rows, where or {}), x, y, by=by, panels=panels, logx=logx, title=title, ylabel=METRICS.get(y, y)
    )
