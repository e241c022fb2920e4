"""Cohorts: ``wss-nlp batch MANIFEST -o DIR`` reconstructs many exams, resumably, with a summary and a report.

The manifest (:mod:`.manifest`) lists the exams, their inputs and their own options; each exam runs where the
executor sends it (:mod:`wss_nlp.app.executor`: local processes, a Dask scheduler, a LocalCluster, SLURM or PBS)
and lands in ``DIR/<id>/`` whole (:mod:`.exam`); the run (:mod:`.run`) skips what is done, writes
``DIR/summary.csv`` and ``DIR/batch.log``, and the report (:mod:`.report`) ``DIR/report.html``. Docs: "Cohorts".
"""

from .manifest import Exam, load_manifest  # noqa: F401
from .exam import ExamTask, run_exam  # noqa: F401
from .run import SUMMARY_COLUMNS, BatchSummary, read_summary, run_batch  # noqa: F401
from .report import write_report  # noqa: F401
