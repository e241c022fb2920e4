"""The cohort report of a batch: ``DIR/report.html`` with the distributions across exams, the flagged and failed
exams with their reasons, and every exam's thumbnail.

The page is plain HTML with no script, readable offline and in a browser from the output folder; its figure
(``report_distributions.png``: mean WSS, TAWSS, OSI and radius across the exams) is drawn by
:func:`wss_nlp.app.plotting.figure_cohort`, the thumbnails by each exam (:mod:`wss_nlp.app.batch.exam`).
"""

from __future__ import annotations

import html
import os

import numpy as np

from ... import __version__
from ...io import files as wio

#: The quantities whose distributions the report draws: summary column -> panel title.
DISTRIBUTIONS = {
    "mean_wss_pa": "mean WSS [Pa]",
    "tawss_pa": "TAWSS [Pa] (cine)",
    "osi_mean": "OSI, wall mean (cine)",
    "radius_mm": "mean radius [mm]",
}

_STYLE = """
body { font-family: sans-serif; margin: 2em; max-width: 75em; }
table { border-collapse: collapse; margin: 1em 0; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: left; vertical-align: top; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.failed td { background: #fde8e8; }
tr.flagged td { background: #fff6e0; }
img.thumb { width: 320px; }
"""


def write_report(outdir: str, rows: list[dict], records: dict) -> list[str]:
    """Write ``report.html`` and its figure into ``outdir``; returns their paths.

    ``rows``: the summary's rows (:func:`wss_nlp.app.batch.run.summary_rows`); ``records``: each exam's record
    by id (its whole flags and warnings).
    """
    from .. import plotting

    values = {title: {r["id"]: _number(r.get(col)) for r in rows if r["status"] == "ok"}
              for col, title in DISTRIBUTIONS.items()}  # fmt: skip
    flagged = {r["id"] for r in rows if r["status"] == "ok" and r.get("flags")}
    figure = plotting.save_figure(
        plotting.figure_cohort(values, flagged), os.path.join(outdir, "report_distributions.png")
    )
    failed = [r for r in rows if r["status"] != "ok"]
    parts = [
        "<!doctype html>",
        '<html><head><meta charset="utf-8">',
        f"<title>wss-nlp batch: {_e(os.path.basename(os.path.abspath(outdir)))}</title>",
        f"<style>{_STYLE}</style></head><body>",
        "<h1>Cohort report</h1>",
        f"<p>{len(rows)} exam(s): {len(rows) - len(failed)} ok ({len(flagged)} flagged), {len(failed)} failed. "
        f"Every number is in <a href='summary.csv'>summary.csv</a>, every exam's record in "
        f"<code>ID/exam.json</code>; wss-nlp {_e(__version__)}.</p>",
        "<h2>Distributions across the exams</h2>",
        "<p>Each point is an exam (open orange circles: flagged); boxes span the quartiles.</p>",
        f"<img src='{_e(os.path.basename(figure))}' alt='distributions across the exams'>",
    ]
    parts.append("<h2>Flagged exams</h2>")
    if flagged:
        parts.append("<table><tr><th>exam</th><th>why</th></tr>")
        for r in rows:
            if r["id"] in flagged:
                reasons = "".join(f"<li>{_e(f)}</li>" for f in records[r["id"]].get("flags", []))
                parts.append(f"<tr><td>{_link(r)}</td><td><ul>{reasons}</ul></td></tr>")
        parts.append("</table>")
    else:
        parts.append("<p>None.</p>")
    parts.append("<h2>Failed exams</h2>")
    if failed:
        parts.append("<table><tr><th>exam</th><th>error</th><th>input</th></tr>")
        for r in failed:
            parts.append(
                f"<tr class='failed'><td>{_link(r)}</td><td>{_e(r['error'])}</td><td>{_e(r['input'])}</td></tr>"
            )
        parts.append("</table>")
    else:
        parts.append("<p>None.</p>")
    parts.append("<h2>Every exam</h2>")
    parts.append(
        "<table><tr><th>exam</th><th>status</th><th>kind</th><th>mean WSS [Pa]</th><th>TAWSS [Pa]</th>"
        "<th>OSI (mean)</th><th>radius [mm]</th><th>solver</th><th>WSS</th></tr>"
    )
    for r in rows:
        cls = "failed" if r["status"] != "ok" else "flagged" if r["id"] in flagged else ""
        thumb = os.path.join(r["id"], "thumbnail.png")
        image = (f"<a href='{_e(thumb)}'><img class='thumb' src='{_e(thumb)}' alt='WSS of {_e(r['id'])}'></a>"
                 if os.path.exists(os.path.join(outdir, thumb)) else "")  # fmt: skip
        cells = "".join(
            f"<td class='num'>{_fmt(r.get(c))}</td>" for c in ("mean_wss_pa", "tawss_pa", "osi_mean", "radius_mm")
        )
        parts.append(
            f"<tr class='{cls}'><td>{_link(r)}</td><td>{_e(r['status'])}</td><td>{_e(r.get('kind', ''))}</td>"
            f"{cells}<td>{_e(r.get('solver_status', ''))}</td><td>{image}</td></tr>"
        )
    parts.append("</table></body></html>")
    path = os.path.join(outdir, "report.html")
    wio.atomic_write(path, "\n".join(parts) + "\n")
    return [path, figure]


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def _fmt(value) -> str:
    x = _number(value)
    return "" if not np.isfinite(x) else f"{x:.4g}"


def _link(row: dict) -> str:
    return f"<a href='{_e(row['id'])}/'>{_e(row['id'])}</a>"


def _e(text) -> str:
    return html.escape(str(text), quote=True)
