"""Progress over many tasks (a sweep's cases, a batch's exams): a tqdm bar on a terminal, a line per task elsewhere."""

from __future__ import annotations

import sys
import time


class Progress:
    """Progress over ``total`` tasks, with the failures counted as they come.

    On a terminal a tqdm bar (tasks done, failures, the last task and its status, elapsed time, time left); on
    anything else (a log, CI) one line per finished task. Tasks done before this run (``skipped``) count as done.

    Parameters
    ----------
    total : int
        Tasks in all.
    stream : file or None
        Where to draw (default ``sys.stderr``).
    skipped : int
        Tasks already done when the run starts.
    unit : str
        What a task is called ("case", "exam").
    bad : str
        What a task whose status is not ``"ok"`` is called ("not ok", "failed").
    """

    def __init__(self, total: int, stream=None, skipped: int = 0, unit: str = "case", bad: str = "not ok"):
        self.total, self.done, self.failed = total, skipped, 0
        self.unit, self.bad = unit, bad
        self.stream = stream if stream is not None else sys.stderr
        self.t0 = time.perf_counter()
        self.ran = 0
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.bar = None
        if self.tty:
            from tqdm import tqdm  # only where a bar is drawn: the line form needs nothing

            self.bar = tqdm(total=total, initial=skipped, file=self.stream, unit=unit, dynamic_ncols=True)

    def update(self, record: dict) -> None:
        """One task finished; ``record`` has its ``id`` and ``status``."""
        self.done += 1
        self.ran += 1
        self.failed += record["status"] != "ok"
        if self.bar is not None:
            self.bar.set_postfix_str(
                f"{self.failed} {self.bad}, last {record['id']}: {record['status']}", refresh=False
            )
            self.bar.update(1)
            if self.done >= self.total:
                self.bar.close()
            return
        el = time.perf_counter() - self.t0
        eta = el / self.ran * (self.total - self.done)
        self.stream.write(
            f"{self.done}/{self.total} {self.unit}s, {self.failed} {self.bad}, {el:.0f} s elapsed, about {eta:.0f} s "
            f"left  ({record['id']}: {record['status']})\n"
        )
        self.stream.flush()

    def close(self) -> None:
        """End the bar early (an interrupted run)."""
        if self.bar is not None:
            self.bar.close()
