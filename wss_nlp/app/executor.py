"""Where independent tasks run: this process, local worker processes, or a Dask cluster (a scheduler's address, a
LocalCluster, SLURM or PBS jobs through dask-jobqueue); one layer for sweeps, batches and the slices of one file.

A :class:`Backend` says where; an :class:`Executor` (a context manager) starts it, runs a function over items
and shuts it down:

* ``local`` with one worker: in this process, one item after the other (no start-up cost, exceptions as they are);
* ``local`` with ``N > 1`` workers: ``N`` spawned processes (:class:`concurrent.futures.ProcessPoolExecutor`),
  each with one BLAS thread: the items are the parallelism;
* ``scheduler``: an existing ``dask.distributed`` scheduler (``tcp://HOST:PORT``); its workers need wss-nlp
  installed and must see the files under the same paths;
* ``localcluster``: a Dask ``LocalCluster`` of ``N`` single-threaded worker processes started for the run;
* ``slurm`` / ``pbs``: a dask-jobqueue cluster whose keywords (cores, memory, queue, account, walltime, ...) come
  from a TOML file (:func:`read_cluster_config`); :func:`job_script` shows the job script it submits.

Dask and dask-jobqueue are optional (``pip install 'wss-nlp[dask]'``, ``'wss-nlp[cluster]'``), imported only when
a Dask backend is used; a missing one is an :class:`~wss_nlp.errors.InputError` saying what to install.
"""

from __future__ import annotations

import os
import sys
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from ..errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

#: The kinds of backend.
KINDS = ("local", "scheduler", "localcluster", "slurm", "pbs")
#: The dask-jobqueue cluster class of each batch system.
JOBQUEUE = {"slurm": "SLURMCluster", "pbs": "PBSCluster"}
#: Environment variables that set the BLAS threads of a process started by a local pool.
BLAS_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@dataclass(frozen=True)
class Backend:
    """Where tasks run (module notes): ``kind`` one of :data:`KINDS`.

    ``workers``: processes for ``local`` and ``localcluster``; ``address``: the scheduler's (``scheduler``);
    ``config``: the TOML file of dask-jobqueue keywords (``slurm``, ``pbs``).
    """

    kind: str = "local"
    workers: int = 1
    address: str | None = None
    config: str | None = None

    def describe(self) -> str:
        """One line for logs: where the tasks run."""
        if self.kind == "local":
            return "this process" if self.workers <= 1 else f"{self.workers} local processes"
        if self.kind == "scheduler":
            return f"the Dask scheduler at {self.address}"
        if self.kind == "localcluster":
            return f"a Dask LocalCluster of {self.workers} processes"
        return f"a Dask {self.kind.upper()} cluster (dask-jobqueue, {self.config})"

    @property
    def dask(self) -> bool:
        return self.kind != "local"


def backend(
    workers: int | None = None,
    scheduler: str | None = None,
    cluster: str | None = None,
    cluster_config: str | None = None,
) -> Backend:
    """The backend the command-line options name (``--workers``, ``--scheduler``, ``--cluster``,
    ``--cluster-config``), checked: ``cluster`` is ``local`` (a LocalCluster), ``slurm`` or ``pbs``.

    Without ``workers`` the local kinds use every core.
    """
    if workers is not None and workers < 1:
        raise InputError(f"--workers {workers}: must be >= 1")
    if scheduler and cluster:
        raise InputError("--scheduler and --cluster exclude each other: connect to a running scheduler, or start one")
    if cluster_config and cluster not in JOBQUEUE:
        raise InputError("--cluster-config goes with --cluster slurm or --cluster pbs")
    n = workers or os.cpu_count() or 1
    if scheduler:
        return Backend("scheduler", n, address=scheduler)
    if cluster is None:
        return Backend("local", n)
    if cluster == "local":
        return Backend("localcluster", n)
    if cluster not in JOBQUEUE:
        raise InputError(f"--cluster {cluster}: choose local, slurm or pbs")
    if cluster_config is None:
        raise InputError(f"--cluster {cluster} needs --cluster-config FILE (dask-jobqueue keywords; docs, 'Cohorts')")
    read_cluster_config(cluster_config, cluster)  # a bad file costs nothing yet
    return Backend(cluster, n, config=cluster_config)


@dataclass
class Finished:
    """One finished task: the index of its item, and its value or the exception it raised."""

    index: int
    value: Any = None
    error: BaseException | None = None

    def result(self):
        """The value, or the task's exception raised again."""
        if self.error is not None:
            raise self.error
        return self.value


class Executor:
    """Runs a function over items on a :class:`Backend`; a context manager that starts and stops the backend.

    ``as_completed`` yields each item's :class:`Finished` as it finishes; ``map`` yields the values in the
    items' order. Leaving the context cancels what has not started (Ctrl-C, an error in the caller).
    """

    def __init__(self, where: Backend):
        self.backend = where
        self._pool: Any = None
        self._client: Any = None
        self._cluster: Any = None

    # ------------------------------------------------------------ start and stop
    def __enter__(self) -> Executor:
        b = self.backend
        if b.kind == "local":
            if b.workers > 1:
                self._pool = _process_pool(b.workers)
            return self
        Client = _dask_client_class()
        if b.kind == "scheduler":
            try:
                self._client = Client(b.address, timeout="20s")
            except (OSError, TimeoutError) as exc:
                raise InputError(f"cannot reach the Dask scheduler at {b.address}: {exc}") from exc
            return self
        try:
            if b.kind == "localcluster":
                from dask.distributed import LocalCluster

                self._cluster = LocalCluster(
                    n_workers=b.workers, threads_per_worker=1, processes=True, dashboard_address=None
                )
            else:
                self._cluster = jobqueue_cluster(b.kind, b.config)
                _scale(self._cluster, read_cluster_config(b.config, b.kind)[1])  # type: ignore[arg-type]
            self._client = Client(self._cluster)
        except BaseException:
            self._close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._close()

    def _close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    @property
    def parallel(self) -> bool:
        """Whether items run side by side (anything but one local worker)."""
        return self.backend.kind != "local" or self.backend.workers > 1

    # ------------------------------------------------------------ running
    def as_completed(self, fn: Callable, items: Iterable, keys: Iterable[str] | None = None) -> Iterator[Finished]:
        """``fn(item)`` for every item, yielded as they finish (in this process: in order).

        ``keys`` name the tasks on a Dask dashboard (default ``wss-nlp-<index>``). A task's exception is carried
        in its :class:`Finished` (call ``.result()`` to raise it); a lost worker process is such an exception.
        """
        items = list(items)
        if self._pool is None and self._client is None:
            for i, item in enumerate(items):
                yield Finished(i, fn(item))  # exceptions as they are: the caller's own code ran them
            return
        if self._pool is not None:
            from concurrent.futures import as_completed

            futures = {self._pool.submit(fn, item): i for i, item in enumerate(items)}
            for fut in as_completed(futures):
                yield _finished(futures[fut], fut)
            return
        from dask.distributed import as_completed as dask_completed

        names = list(keys) if keys is not None else [f"wss-nlp-{i}" for i in range(len(items))]
        token = uuid.uuid4().hex[:8]  # a rerun in the same session must not meet the old tasks' keys
        dask_futures = {
            self._client.submit(fn, item, key=f"{name}-{token}", pure=False): i
            for i, (name, item) in enumerate(zip(names, items))
        }
        for fut in dask_completed(dask_futures):
            yield _finished(dask_futures[fut], fut)

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        """``fn(item)`` for every item, in the items' order (a task's exception is raised when its turn comes)."""
        items = list(items)
        if self._pool is None and self._client is None:
            yield from (fn(item) for item in items)
            return
        if self._pool is not None:
            futures = [self._pool.submit(fn, item) for item in items]
        else:
            token = uuid.uuid4().hex[:8]
            futures = [
                self._client.submit(fn, item, key=f"wss-nlp-map-{i}-{token}", pure=False)
                for i, item in enumerate(items)
            ]
        for fut in futures:
            yield fut.result()


def results(where: Backend, fn: Callable, items: Iterable, keys: Iterable[str] | None = None) -> Iterator:
    """``fn(item)`` for every item as they finish, on ``where`` (started before the first and stopped after the
    last, or when the caller stops iterating); a task's exception is raised."""
    with Executor(where) as ex:
        for done in ex.as_completed(fn, items, keys):
            yield done.result()


def _finished(index: int, fut) -> Finished:
    try:
        return Finished(index, fut.result())
    except Exception as exc:  # the task's own exception, or the pool's for a lost worker
        return Finished(index, error=exc)


def _die_with_parent(parent: int) -> None:
    """Worker initializer: end this worker when the process that started it ends, even by SIGKILL.

    Linux: the kernel sends SIGKILL when the parent dies (``prctl(PR_SET_PDEATHSIG)``; the workers are started
    from the parent's main thread). Elsewhere, and as a guard against a parent that died before the call, a daemon
    thread compares the parent's id every half second.
    """
    import signal
    import threading
    import time

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


def _process_pool(workers: int):
    """``workers`` spawned processes with one BLAS thread each (the environment is restored for this process)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    saved = {k: os.environ.get(k) for k in BLAS_ENV}
    os.environ.update(dict.fromkeys(saved, "1"))
    try:
        return ProcessPoolExecutor(
            max_workers=workers,
            mp_context=mp.get_context("spawn"),
            initializer=_die_with_parent,  # issue 42: no worker outlives a killed sweep, batch or reconstruct
            initargs=(os.getpid(),),
        )
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _dask_client_class():
    try:
        from dask.distributed import Client
    except ImportError as exc:
        raise InputError("running on Dask needs dask.distributed: pip install 'wss-nlp[dask]'") from exc
    return Client


# ---------------------------------------------------------------- dask-jobqueue
def read_cluster_config(path: str, kind: str) -> tuple[dict, dict]:
    """``(cluster keywords, scale)`` of a cluster file for ``kind`` (``slurm`` or ``pbs``).

    The file is TOML: a table named after the batch system holds the keywords of dask-jobqueue's
    ``SLURMCluster`` / ``PBSCluster`` (``cores``, ``memory``, ``processes``, ``queue``, ``account``, ``walltime``,
    ``job_extra_directives``, ...); an optional ``[scale]`` table says how many jobs to submit: ``jobs = N``, or
    ``minimum_jobs`` / ``maximum_jobs`` for an adaptive cluster (default one job). Without ``processes`` each job
    runs ``cores`` single-threaded workers (a reconstruction is one thread's work).
    """
    if kind not in JOBQUEUE:
        raise InputError(f"--cluster {kind}: a cluster file is for slurm or pbs")
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except OSError as exc:
        raise InputError(f"--cluster-config {path}: cannot read it ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None
    keywords = data.get(kind)
    if not isinstance(keywords, dict):
        raise InputError(
            f"{path}: no [{kind}] table; put dask-jobqueue's {JOBQUEUE[kind]} keywords there (docs, 'Cohorts')"
        )
    for key in ("cores", "memory"):
        if key not in keywords:
            raise InputError(f"{path}: [{kind}] needs '{key}' (dask-jobqueue requires it)")
    keywords = dict(keywords)
    keywords.setdefault("processes", keywords["cores"])
    scale = data.get("scale", {"jobs": 1})
    if not isinstance(scale, dict) or not set(scale) <= {"jobs", "minimum_jobs", "maximum_jobs"}:
        raise InputError(f"{path}: [scale] takes jobs = N, or minimum_jobs and maximum_jobs")
    for key, value in scale.items():
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise InputError(f"{path}: [scale] {key} must be a whole number >= 0, got {value!r}")
    if "jobs" in scale and len(scale) > 1:
        raise InputError(f"{path}: [scale] takes jobs = N (fixed) or minimum_jobs/maximum_jobs (adaptive), not both")
    return keywords, scale


def jobqueue_cluster(kind: str, config: str | None):
    """The dask-jobqueue cluster of ``kind`` with the keywords of file ``config`` (no job submitted yet)."""
    try:
        import dask_jobqueue
    except ImportError as exc:
        raise InputError(f"--cluster {kind} needs dask-jobqueue: pip install 'wss-nlp[cluster]'") from exc
    if config is None:
        raise InputError(f"--cluster {kind} needs --cluster-config FILE")
    keywords, _ = read_cluster_config(config, kind)
    keywords.setdefault("scheduler_options", {"dashboard_address": None})
    try:
        return getattr(dask_jobqueue, JOBQUEUE[kind])(**keywords)
    except (TypeError, ValueError) as exc:
        first = " ".join(str(exc).split(".")[0].split())
        raise InputError(f"{config}: [{kind}]: {first}") from None


def _scale(cluster, scale: dict) -> None:
    if "jobs" in scale:
        cluster.scale(jobs=scale["jobs"])
    else:
        cluster.adapt(minimum_jobs=scale.get("minimum_jobs", 0), maximum_jobs=scale.get("maximum_jobs", 1))


def job_script(kind: str, config: str) -> str:
    """The job script a ``--cluster`` run would submit (each job starts Dask workers), without submitting it."""
    cluster = jobqueue_cluster(kind, config)
    try:
        return cluster.job_script()
    finally:
        cluster.close()
