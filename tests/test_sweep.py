"""Parameter sweeps (wss_nlp.app.sweep): grid expansion, resume, Dask, tables and plots, bad input."""

import glob
import json
import os

import numpy as np
import pytest

from wss_nlp.io import files as wio
from wss_nlp.synthetic import phantoms
from wss_nlp.app import sweep
from wss_nlp.app.cli import main
from wss_nlp.errors import InputError

SMALL = """
[study]
name = "small"
[grid]
case = "circle"
h = [1.5, 1.2]
seed = {range = [0, 2]}
method = ["decoupled", "oyre", "stalder"]
uncertainty = false

[[tables]]
name = "t"
rows = "h"
cols = "method"
metric = "wss_err"

[[plots]]
name = "p"
x = "h"
y = "wss_err"
by = "method"
"""


def _study(tmp_path, text=SMALL, name="s.toml"):
    path = tmp_path / name
    path.write_text(text)
    return sweep.load_study(path)


def _metrics(outdir):
    return {r["id"]: r for r in sweep.read_csv(outdir)}


def test_grid_expansion(tmp_path):
    s = _study(
        tmp_path,
        """
[study]
name = "g"
metrics = ["wss_err"]
[grid]
case = ["circle", "laminar"]
h = {start = 1.5, stop = 0.3, num = 3, log = true}
seed = {range = [0, 4, 2]}
alpha = [1e-3, "auto"]
N = 6
M = [10, 14]
""",
    )
    cases = sweep.expand(s)
    assert len(cases) == 2 * 3 * 2 * 2 * 2  # the cross product of the lists; N is fixed
    np.testing.assert_allclose(s.grid["h"], [1.5, np.sqrt(1.5 * 0.3), 0.3])
    assert s.grid["seed"] == [0, 2] and s.grid["snr"] == [25.0]
    ids = [sweep.case_id(c) for c in cases]
    assert len(set(ids)) == len(ids)
    assert ids == [sweep.case_id(dict(c)) for c in sweep.expand(sweep.load_study(tmp_path / "s.toml"))]  # stable
    o = sweep.options_for({"case": "circle", "alpha": "auto", "N": 6, "M": 14, "beta": "gcv", "quad_order": 3})
    assert o.alpha_rule == "balance" and o.beta_rule == "gcv"  # 'auto' = the balancing principle
    assert sweep.options_for({"alpha": "discrepancy", "beta": "discrepancy"}).beta_rule == "discrepancy"
    with pytest.raises(InputError, match="beta must be a number or one of auto"):
        sweep.options_for({"beta": "magic"})
    fixed = sweep.options_for({"beta": 1e-7, "alpha": 4e-3})  # numbers are used as given, not replaced by a rule
    assert (fixed.beta_rule, fixed.velocity.beta, fixed.alpha_rule, fixed.geometry.alpha) == (
        "fixed",
        1e-7,
        "fixed",
        4e-3,
    )
    assert sweep.options_for({}).beta_rule == "balance"  # the default
    assert o.geometry.n_fourier == 6 and o.velocity.degree == 14
    assert o.geometry.quad_order == o.velocity.quad_order == 3
    assert sweep.options_for({"basis": "eigen", "M": 300.0}).velocity.max_eigenvalue == 300.0


@pytest.mark.parametrize(
    "text, match",
    [
        ("[study]\nname='x'\n[grid]\ncase='circle'\nfoo=[1]\n", "unknown grid key"),
        ("[study]\nname='x'\n[grid]\nh=[1.0]\n", "exactly one of 'case'"),
        ("[study]\nname='x'\n[grid]\ncase='circle'\nmethod=['magic']\n", "unknown method"),
        ("[study]\nname='x'\n[grid]\ncase='nope'\n", "unknown phantom case"),
        ("[study]\nname='x'\n[grid]\ncase='circle'\nalpha=[-1.0]\n", "alpha"),
        (
            "[study]\nname='x'\n[grid]\ncase='circle'\n[[tables]]\nrows='h'\ncols='beta'\nmetric='wss_err'\n",
            "not a grid",
        ),
        ("[study]\nname='x'\n[grid]\ncase='circle'\nseed={range=[0.5, 2]}\n", "integers"),
        ("[study]\nname='x'\n[grid\n", "not valid TOML"),
    ],
)
def test_bad_study_files_name_the_file_and_the_problem(tmp_path, text, match):
    with pytest.raises(InputError, match=match) as exc:
        _study(tmp_path, text)
    assert "s.toml" in str(exc.value)


def test_sweep_resumes_after_interruption(tmp_path, monkeypatch):
    s = _study(tmp_path)
    full = str(tmp_path / "full")
    sweep.run_study(s, full, workers=1)

    out = str(tmp_path / "out")
    calls, real = [], sweep.run_case

    def interrupted(params, base_dir="."):
        if len(calls) == 5:
            raise KeyboardInterrupt  # Ctrl-C while the sixth case runs
        calls.append(params)
        return real(params, base_dir)

    monkeypatch.setattr(sweep.run, "run_case", interrupted)  # where run_study looks it up
    with pytest.raises(KeyboardInterrupt):
        sweep.run_study(s, out, workers=1)
    assert not os.path.exists(os.path.join(out, "results.csv"))  # no table from a partial run
    assert len(glob.glob(os.path.join(out, "cases", "*.json"))) == 5
    # debris of a crash: a half-written file and a record whose result file is missing are not trusted
    open(os.path.join(out, "cases", "junk.h5.part"), "w").close()
    first = sorted(glob.glob(os.path.join(out, "cases", "*.json")))[0]
    os.remove(first[:-5] + ".h5")

    calls.clear()
    monkeypatch.setattr(sweep.run, "run_case", lambda p, b=".": (calls.append(p), real(p, b))[1])
    summary = sweep.run_study(s, out, workers=1)
    assert summary.ran == len(calls) == 12 - 4 and summary.skipped == 4
    assert not glob.glob(os.path.join(out, "cases", "*.part"))
    a, b = _metrics(full), _metrics(out)
    assert a.keys() == b.keys()
    for cid in a:  # same code, same seeds, same process: identical numbers
        assert a[cid]["wss_err"] == b[cid]["wss_err"] and a[cid]["status"] == b[cid]["status"] == "ok"
    # a third run has nothing to do
    assert sweep.run_study(s, out, workers=1).ran == 0


def test_local_processes_and_dask_cluster_agree(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    s = _study(tmp_path)
    local = str(tmp_path / "local")
    sweep.run_study(s, local, workers=2)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        remote = str(tmp_path / "dask")
        summary = sweep.run_study(s, remote, scheduler=c.scheduler_address)
    assert summary.ran == 12 and summary.failed == 0
    a, b = _metrics(local), _metrics(remote)
    assert a.keys() == b.keys()
    for cid in a:
        for m in ("wss_err", "radius_err", "mean_wss_bias", "radius_err_h2", "velocity_err"):
            x, y = a[cid][m], b[cid][m]
            if np.isnan(x):
                assert np.isnan(y)
                continue
            # same code and inputs; only BLAS threading may differ between the two kinds of worker process,
            # which moves IPOPT's and the Cholesky solves' last bits (measured <= 1e-12 relative)
            assert abs(x - y) <= 1e-9 * abs(x), (cid, m, x, y)
    # the result files are complete reconstructions in the public format
    d = wio.read_result(os.path.join(remote, a[next(iter(a))]["result_file"]))[0]
    assert d["tau"].shape == (360,)


def test_failed_case_is_recorded_and_the_rest_run(tmp_path):
    """A case that fails only when it runs (no vessel in the image: the files read and their ranges are valid, so
    the checks before the run pass) is recorded with its message, and the other cases run."""
    acq, truth = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=0)
    wio.write_acquisition(tmp_path / "good.h5", acq)
    from wss_nlp.app.cli.phantom import _write_truth

    _write_truth(str(tmp_path / "good_truth.h5"), truth)
    noise = np.random.default_rng(5).normal(size=(2, *acq.magnitude.shape))
    import h5py

    wio.write_acquisition(tmp_path / "bad.h5", acq)
    with h5py.File(tmp_path / "bad.h5", "r+") as f:
        f["magnitude"][...] = np.hypot(*noise)  # Rayleigh noise alone: no vessel
    s = _study(
        tmp_path,
        """
[study]
name = "files"
[grid]
input = [{file = "good.h5", truth = "good_truth.h5"}, "bad.h5"]
method = ["decoupled", "oyre"]
uncertainty = false
""",
    )
    summary = sweep.run_study(s, str(tmp_path / "out"), workers=1)
    rows = {(r["input"], r["method"]): r for r in summary.rows}
    assert summary.failed == 2
    for m in ("decoupled", "oyre"):
        assert rows[("bad.h5", m)]["status"] == "error" and (
            "vessel" in rows[("bad.h5", m)]["message"] or "lumen" in rows[("bad.h5", m)]["message"]
        )  # noise alone: no vessel, or a "lumen" of noise touching the border (the flow-aware lumen's words)
        assert "bad.h5" in rows[("bad.h5", m)]["message"]
        assert rows[("good.h5", m)]["status"] == "ok" and rows[("good.h5", m)]["wss_err"] < 0.3
    rec = json.load(open(os.path.join(tmp_path, "out", "cases", rows[("bad.h5", "oyre")]["id"] + ".json")))
    assert rec["status"] == "error"
    assert not os.path.exists(os.path.join(tmp_path, "out", "cases", rows[("bad.h5", "oyre")]["id"] + ".h5"))


ROWS = [  # a known table: wss_err = h * (method index + 1) + seed / 100
    {"h": h, "method": m, "seed": s, "case": "c", "status": "ok", "wss_err": h * (k + 1) + s / 100, "id": ""}
    for h in (1.0, 0.5)
    for k, m in enumerate(("b", "a", "c"))
    for s in (0, 1)
]


def _cells(line: str) -> list[str]:
    """A Markdown table row's cells, without the padding pandas' to_markdown adds to align the columns."""
    return [c.strip() for c in line.strip().strip("|").split("|")]


def test_table_pivots_means_and_marks_the_best():
    md, tex = sweep.table(ROWS, "h", "method", "wss_err")
    lines = md.splitlines()
    assert _cells(lines[0]) == ["h \\ method", "b", "a", "c"]
    assert set(lines[1]) <= set("|:-")  # the pipe table's alignment row
    assert _cells(lines[2]) == ["1", "**1.0050**", "2.0050", "3.0050"]  # mean over seeds 0, 1
    assert _cells(lines[3]) == ["0.5", "**0.5050**", "1.0050", "1.5050"]
    assert len({len(line) for line in lines[:4]}) == 1  # columns padded to one width
    assert r"\textbf{1.0050}" in tex and r"\begin{tabular}{c||c|c|c}" in tex
    assert "1 & \\textbf{1.0050} & 2.0050 & 3.0050 \\\\" in tex.splitlines()
    assert tex.splitlines()[:3] == [r"\begin{table}[ht!]", r"\centering", r"\caption{wss err}"]
    md, _ = sweep.table(ROWS, "metric", "h", "wss_err", where={"method": "a"}, agg="max")
    assert _cells(md.splitlines()[2]) == ["wss_err", "2.0100", "**1.0100**"]


def test_table_refuses_to_mix_unfixed_parameters():
    rows = ROWS + [dict(r, case="d") for r in ROWS]
    with pytest.raises(InputError, match="case .* vary .* --where case=c"):
        sweep.table(rows, "h", "method", "wss_err")
    assert sweep.table(rows, "h", "method", "wss_err", where={"case": "d"})[0]


def test_cli_sweep_table_plot(tmp_path, capsys):
    (tmp_path / "s.toml").write_text(SMALL.replace("h = [1.5, 1.2]", "h = 1.5").replace("{range = [0, 2]}", "0"))
    out = str(tmp_path / "o")
    assert main(["sweep", str(tmp_path / "s.toml"), "-o", out, "--workers", "1"]) == 0
    text = capsys.readouterr().out
    assert "3 cases (3 run now, 0 done before), 0 not ok" in text
    assert os.path.exists(os.path.join(out, "t.md")) and os.path.exists(os.path.join(out, "p.png"))
    assert (
        main(
            [
                "table",
                out,
                "--rows",
                "h",
                "--cols",
                "method",
                "--metric",
                "radius_err",
                "--latex",
                "-o",
                str(tmp_path / "t.tex"),
            ]
        )
        == 0
    )
    assert r"\textbf" in capsys.readouterr().out and (tmp_path / "t.tex").read_text().startswith(r"\begin{table}")
    assert main(["plot", out, "--x", "h", "--y", "wss_err", "--by", "method", "-o", str(tmp_path / "f.png")]) == 0
    assert (tmp_path / "f.png").stat().st_size > 1000
    assert main(["table", out, "--rows", "h", "--cols", "nope", "--metric", "wss_err"]) == 2
    assert "no column 'nope'" in capsys.readouterr().err
    assert main(["table", str(tmp_path / "missing"), "--rows", "h", "--cols", "method", "--metric", "wss_err"]) == 2
    assert main(["sweep", str(tmp_path / "nope.toml")]) == 2


def test_table_marks_cells_with_non_converged_cases():
    rows = [dict(r) for r in ROWS]
    rows[0]["status"] = "not converged"  # h = 1, method b, seed 0: still averaged, but flagged
    rows[1]["status"] = "error"  # h = 1, method b, seed 1: left out of the mean
    md, tex = sweep.table(rows, "h", "method", "wss_err")
    assert _cells(md.splitlines()[2]) == ["1", "**1.0000†**", "2.0050", "3.0050"]
    assert "1 case(s) whose solver did not converge" in md and r"$^\dagger$" in tex


def test_progress_draws_a_bar_on_a_terminal_and_a_line_per_case_elsewhere():
    """sweep.Progress: on a terminal a tqdm bar that ends at total/total with the count of failed cases; in a
    log one line per case with its id and status (cases done before count as done)."""
    import io

    from wss_nlp.app.sweep import Progress

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    tty = Terminal()
    bar = Progress(3, tty, skipped=1)
    bar.update({"id": "a", "status": "ok"})
    bar.update({"id": "b", "status": "error"})
    assert "3/3" in tty.getvalue() and "1 not ok" in tty.getvalue() and tty.getvalue().endswith("\n")
    log = io.StringIO()
    lines = Progress(2, log)
    lines.update({"id": "a", "status": "ok"})
    lines.update({"id": "b", "status": "error"})
    rows = log.getvalue().splitlines()
    assert rows[0].startswith("1/2 cases, 0 not ok") and rows[0].endswith("(a: ok)")
    assert rows[1].startswith("2/2 cases, 1 not ok") and rows[1].endswith("(b: error)")


def test_results_csv_reads_back_with_its_types(tmp_path):
    """write_csv (standard library) then read_csv (pandas): numbers, booleans, a missing metric (nan) and an empty
    message come back as they went in."""
    study = _study(tmp_path)
    record = {
        "params": {**{k: v[0] for k, v in study.grid.items()}, "h": 1.5, "seed": 3, "uncertainty": False},
        "id": "x",
        "status": "ok",
        "converged": True,
        "message": "",
        "result_file": "cases/x.h5",
        "metrics": {"wss_err": 0.0125, "radius_err": None},
    }
    sweep.write_csv(str(tmp_path / "results.csv"), [sweep.flat_row(record, study)], study)
    (row,) = sweep.read_csv(str(tmp_path))
    assert row["h"] == 1.5 and row["seed"] == 3 and isinstance(row["seed"], int)
    assert row["converged"] is True and row["uncertainty"] is False
    assert row["message"] == "" and row["status"] == "ok" and row["case"] == "circle"
    assert row["wss_err"] == 0.0125 and np.isnan(row["radius_err"])


def test_without_pandas_a_sweep_says_in_one_line_how_to_get_the_tables(tmp_path, monkeypatch, caplog):
    import sys

    study = _study(tmp_path, SMALL.split("[[plots]]")[0])  # the table alone: a plot costs seconds of matplotlib
    monkeypatch.setitem(sys.modules, "pandas", None)  # import fails as if pandas were not installed
    with caplog.at_level("WARNING", logger="wss_nlp"):
        written = sweep.write_views(study, ROWS, str(tmp_path))
    assert written == [] and not list(tmp_path.glob("t.*"))  # no t.md, no t.tex
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "1 study table(s) not written" in warning and "pip install 'wss-nlp[study]'" in warning
    with pytest.raises(InputError, match=r"need pandas: pip install 'wss-nlp\[study\]'"):
        sweep.table(ROWS, "h", "method", "wss_err")
