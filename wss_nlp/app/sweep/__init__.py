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

The study's specification (:mod:`.spec`), its execution (:mod:`.run`) and its tables and plots (:mod:`.tables`).
"""

from .spec import DATA_KEYS  # noqa: F401
from .spec import PARAMETERS  # noqa: F401
from .spec import METRICS  # noqa: F401
from .spec import Study  # noqa: F401
from .run import Summary  # noqa: F401
from .spec import load_study  # noqa: F401
from .spec import expand  # noqa: F401
from .spec import case_id  # noqa: F401
from .spec import options_for  # noqa: F401
from .run import case_metrics  # noqa: F401
from .run import run_case  # noqa: F401
from .run import Progress  # noqa: F401
from .run import run_study  # noqa: F401
from .tables import flat_row  # noqa: F401
from .tables import write_csv  # noqa: F401
from .tables import read_csv  # noqa: F401
from .tables import select  # noqa: F401
from .tables import pivot  # noqa: F401
from .tables import render_table  # noqa: F401
from .tables import table  # noqa: F401
from .tables import write_views  # noqa: F401
from .tables import plot  # noqa: F401
