"""The executor layer (wss_nlp.app.executor): backends from the command line, local and Dask runs, and the
SLURM/PBS path of dask-jobqueue as far as it goes without a batch system (the job script; a batch run through
a stand-in ``sbatch`` that starts the job on this machine)."""

import math
import os
import stat
import sys
import threading

import pytest

from wss_nlp.app import executor
from wss_nlp.app.cli import main
from wss_nlp.errors import InputError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CLUSTER = """
[slurm]
cores = 4
memory = "16GB"
queue = "normal"
account = "cohort-study"
walltime = "02:00:00"
job_extra_directives = ["--exclusive"]

[pbs]
cores = 2
memory = "8GB"
queue = "workq"
walltime = "01:00:00"

[scale]
jobs = 3
"""


def _square(x):
    if x < 0:
        raise ValueError(f"negative: {x}")
    return x * x


def test_backend_from_the_command_line_options(tmp_path):
    assert executor.backend(workers=3) == executor.Backend("local", 3)
    assert executor.backend(workers=2, scheduler="tcp://h:1").kind == "scheduler"
    assert executor.backend(workers=2, cluster="local") == executor.Backend("localcluster", 2)
    (tmp_path / "c.toml").write_text(CLUSTER)
    b = executor.backend(cluster="slurm", cluster_config=str(tmp_path / "c.toml"))
    assert (b.kind, b.config) == ("slurm", str(tmp_path / "c.toml")) and "SLURM" in b.describe()
    for kwargs, match in [
        ({"workers": 0}, "must be >= 1"),
        ({"scheduler": "tcp://h:1", "cluster": "local"}, "exclude each other"),
        ({"cluster": "slurm"}, "needs --cluster-config"),
        ({"cluster_config": "c.toml"}, "goes with --cluster slurm"),
        ({"cluster": "pbs", "cluster_config": str(tmp_path / "none.toml")}, "cannot read it"),
    ]:
        with pytest.raises(InputError, match=match):
            executor.backend(**kwargs)


def test_local_runs_yield_every_item_and_carry_failures():
    with executor.Executor(executor.Backend("local", 1)) as ex:
        assert list(ex.map(_square, [1, 2, 3])) == [1, 4, 9]
        with pytest.raises(ValueError):  # in this process: the exception as it is
            list(ex.as_completed(_square, [1, -1]))
    # two spawned processes; a function of the standard library, so that they need not import this module
    with executor.Executor(executor.Backend("local", 2)) as ex:
        assert ex.parallel and list(ex.map(math.isqrt, [0, 1, 4, 9, 16])) == [0, 1, 2, 3, 4]
        done = {f.index: f for f in ex.as_completed(math.isqrt, [9, -4, 16])}
    assert sorted(done) == [0, 1, 2] and done[0].result() == 3 and done[2].value == 4
    assert isinstance(done[1].error, ValueError) and "must be nonnegative" in str(done[1].error)


def test_cluster_config_gives_dask_jobqueue_its_keywords(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(CLUSTER)
    keywords, scale = executor.read_cluster_config(str(path), "slurm")
    assert keywords["processes"] == 4 and scale == {"jobs": 3}  # one single-threaded worker per core
    for text, match in [
        ("[pbs]\ncores = 1\nmemory = '1GB'\n", r"no \[slurm\] table"),
        ("[slurm]\ncores = 1\n", "needs 'memory'"),
        ("[slurm]\ncores = 1\nmemory = '1GB'\n[scale]\njobs = 2\nmaximum_jobs = 4\n", "not both"),
        ("[slurm]\ncores = 1\nmemory = '1GB'\n[scale]\njobs = -1\n", "whole number"),
        ("[slurm\n", "not valid TOML"),
    ]:
        path.write_text(text)
        with pytest.raises(InputError, match=match):
            executor.read_cluster_config(str(path), "slurm")


def test_job_scripts_for_slurm_and_pbs(tmp_path, capsys):
    pytest.importorskip("dask_jobqueue")
    path = tmp_path / "c.toml"
    path.write_text(CLUSTER)
    script = executor.job_script("slurm", str(path))
    for line in ("#SBATCH -p normal", "#SBATCH -A cohort-study", "#SBATCH --cpus-per-task=4", "#SBATCH -t 02:00:00",
                 "#SBATCH --exclusive"):  # fmt: skip
        assert line in script, script
    assert "--nworkers 4" in script and "--nthreads 1" in script and sys.executable in script
    pbs = executor.job_script("pbs", str(path))
    assert "#PBS -q workq" in pbs and "walltime=01:00:00" in pbs and "ncpus=2" in pbs
    path.write_text("[slurm]\ncores = 1\nmemory = '1GB'\nqueue_name = 'x'\n")
    with pytest.raises(InputError, match=r"c.toml: \[slurm\]: Got unexpected keyword argument 'queue_name'"):
        executor.job_script("slurm", str(path))
    # the command line shows the script without submitting anything
    path.write_text(CLUSTER)
    (tmp_path / "m.csv").write_text("id,input\na,a.h5\n")
    args = ["batch", str(tmp_path / "m.csv"), "-o", str(tmp_path / "o"), "--cluster", "slurm"]
    assert main([*args, "--cluster-config", str(path), "--job-script"]) == 0
    assert "#SBATCH -A cohort-study" in capsys.readouterr().out and not (tmp_path / "o").exists()


def test_missing_dask_jobqueue_says_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "dask_jobqueue", None)  # as if not installed
    (tmp_path / "c.toml").write_text(CLUSTER)
    with pytest.raises(InputError, match=r"--cluster slurm needs dask-jobqueue: pip install 'wss-nlp\[cluster\]'"):
        executor.job_script("slurm", str(tmp_path / "c.toml"))


def _fake_slurm(folder) -> None:
    """``sbatch`` that runs the job script here in a session of its own (printing the job id SLURM prints), and
    ``scancel`` that ends that session: dask-jobqueue's whole path but the batch system's queue."""
    sbatch = folder / "sbatch"
    sbatch.write_text(  # dask-jobqueue deletes its script once sbatch returns: the job runs a copy
        '#!/bin/sh\njob=$(mktemp)\ncp "$1" "$job"\nsetsid sh "$job" >"$job.log" 2>&1 </dev/null &\n'
        'echo "Submitted batch job $!"\n'
    )
    scancel = folder / "scancel"
    scancel.write_text('#!/bin/sh\nfor j in "$@"; do kill -TERM -- "-$j" 2>/dev/null; done\nexit 0\n')
    for f in (sbatch, scancel):
        f.chmod(f.stat().st_mode | stat.S_IEXEC)


@pytest.mark.slow  # about 30 s: the job's workers start from scratch; the job script is tested above
def test_a_batch_through_slurm_jobs(tmp_path, monkeypatch):
    """``--cluster slurm``: dask-jobqueue submits a job (here to the stand-in sbatch), its workers join the
    scheduler, the exam runs there and lands in the output folder."""
    pytest.importorskip("dask_jobqueue")
    from wss_nlp.io import files as wio
    from wss_nlp.synthetic import phantoms

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    _fake_slurm(bin_dir)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("PYTHONPATH", ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))  # the job's Python
    acq, truth = phantoms.make_phantom("circle", h_mm=2.5, snr=25, seed=5)
    wio.write_acquisition(tmp_path / "a.h5", acq)
    (tmp_path / "m.csv").write_text("id,input\na,a.h5\n")
    (tmp_path / "c.toml").write_text(
        "[slurm]\ncores = 1\nmemory = '2GB'\nwalltime = '00:10:00'\ninterface = 'lo'\n"
        f"log_directory = '{tmp_path / 'logs'}'\n[scale]\njobs = 1\n"
    )
    out = tmp_path / "out"
    args = ["batch", str(tmp_path / "m.csv"), "-o", str(out), "--cluster", "slurm"]
    code = []
    run = threading.Thread(
        target=lambda: code.append(main([*args, "--cluster-config", str(tmp_path / "c.toml"), "--no-uncertainty"])),
        daemon=True,
    )
    run.start()
    run.join(timeout=300)  # a job that never starts would leave the batch waiting for workers: fail instead
    assert code == [0], "the batch did not finish through the stand-in SLURM"
    assert "SLURM" in (out / "batch.log").read_text()
    import csv

    row = next(csv.DictReader(open(out / "summary.csv")))
    # the circle's exact mean WSS 0.28 Pa; h = 2.5 mm at SNR 25 reconstructs it within a few percent
    assert row["status"] == "ok" and float(row["mean_wss_pa"]) == pytest.approx(truth.mean_wss, rel=0.05)
