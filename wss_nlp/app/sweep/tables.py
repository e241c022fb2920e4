"""A study's results as a tidy CSV, pivot tables (Markdown, LaTeX) and plots."""

from __future__ import annotations

import csv
import io
import os
import numpy as np
from ...io import files as wio
from ...errors import InputError
from .spec import AGGREGATES, METRICS, Study, _input_path

#: The columns of a case's outcome in results.csv.
_STATUS_COLUMNS = ("status", "converged", "message", "result_file")


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
