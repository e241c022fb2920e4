"""``wss-nlp``'s entry point: parse, dispatch, turn errors into one line and an exit code, show the library's log.

Exit codes (:data:`wss_nlp.app.cli.parser.EXIT_CODES`): 0 success, 1 a solver failed, 2 bad input (including a
file system that refused), 3 internal error. A closed pipe (``wss-nlp analyze out.h5 | head``) ends quietly with 0.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from ...errors import WssNlpError
from ...io.outputs import os_error_text
from .parser import build_parser


class Terminated(BaseException):
    """SIGTERM arrived: unwinds like KeyboardInterrupt, so that every ``with`` and ``finally`` removes what the run
    had staged (temporary files, staged figure folders) before the process exits."""


@contextlib.contextmanager
def _terminate_as_exception():
    """SIGTERM raises :class:`Terminated` in the main thread while the command runs (the previous handler after)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv=None) -> int:
    try:
        return _main(list(sys.argv[1:] if argv is None else argv))
    except BrokenPipeError:  # the reader went away (| head): what it read is all it wanted
        _silence_stdout()
        return 0


def _main(argv: list[str]) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or usage error (2)
        return int(exc.code or 0)
    args.argv = argv
    handler = _show_library_log(logging.WARNING if args.quiet else logging.DEBUG if args.verbose else logging.INFO)
    repeats = _RepeatedWarnings()
    handler.addFilter(repeats)
    try:
        with _terminate_as_exception():
            try:
                return int(args.func(args) or 0)
            finally:  # the counts before an error line, which stays the last line
                handler.removeFilter(repeats)
                for line in repeats.summary():
                    print(f"wss-nlp: warning: {line}", file=sys.stderr)
    except BrokenPipeError:
        raise  # main's: not a file system error
    except WssNlpError as exc:
        print(f"wss-nlp: error: {_one_line(exc)}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("wss-nlp: interrupted; nothing half-written was left", file=sys.stderr)
        return 130
    except Terminated:
        print("wss-nlp: terminated (SIGTERM); nothing half-written was left", file=sys.stderr)
        return 128 + signal.SIGTERM
    except MemoryError:
        print(
            "wss-nlp: error: out of memory; reduce the options that scale the problem (--degree, --n-fourier, "
            "--quad-order, --n-phi) or the image, or run on a machine with more memory",
            file=sys.stderr,
        )
        return 2
    except OSError as exc:  # the file system refused (disk full, permissions changed during the run)
        print(f"wss-nlp: error: {_one_line(os_error_text(exc))}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug: one line for the user, the traceback for the report
        if os.environ.get("WSS_NLP_DEBUG"):
            raise
        print(
            f"wss-nlp: internal error: {type(exc).__name__}: {_one_line(exc)}; please report it with the "
            "command line (WSS_NLP_DEBUG=1 shows the traceback)",
            file=sys.stderr,
        )
        return 3


class _StderrHandler(logging.StreamHandler):
    """Writes to the current ``sys.stderr`` (which tests and embedding programs may replace)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


class _LogFormatter(logging.Formatter):
    """Warnings and errors as ``wss-nlp: warning: ...`` (as the command line's own), the rest indented under the
    progress lines."""

    def format(self, record: logging.LogRecord) -> str:
        text = record.getMessage()
        if record.levelno >= logging.WARNING:
            return f"wss-nlp: {record.levelname.lower()}: {text}"
        return f"  {text}"


class _RepeatedWarnings(logging.Filter):
    """Each kind of warning said once (kinds: :func:`wss_nlp.pipeline.cine.warning_kind`, numbers aside); the
    repeats are counted and said in one line each at the end of the command (:meth:`summary`)."""

    def __init__(self) -> None:
        super().__init__()
        self.kinds: dict[str, list] = {}  # kind -> [the first message, repeats]

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        from ...pipeline.cine import warning_kind

        message = record.getMessage()
        kind = warning_kind(message)
        if kind not in self.kinds:
            self.kinds[kind] = [message, 0]
            return True
        self.kinds[kind][1] += 1
        return False

    def summary(self) -> list[str]:
        """One line per kind that repeated: how often, after the first message's text."""
        return [f"{n} more like '{message}'" for message, n in self.kinds.values() if n]


def _silence_stdout() -> None:
    """Point stdout at the null device, so that the interpreter's final flush does not fail on the closed pipe."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # stdout replaced by an object without a descriptor (tests, notebooks)
        pass


def _show_library_log(level: int = logging.INFO) -> logging.Handler:
    """The library's messages on stderr: INFO (stages of long solves) indented under the progress lines, warnings
    as ``wss-nlp: warning: ...``. Returns the handler.

    ``--quiet`` raises the level to WARNING, ``--verbose`` lowers it to DEBUG.
    """
    logger = logging.getLogger("wss_nlp")
    handler = next((h for h in logger.handlers if isinstance(h, _StderrHandler)), None)
    if handler is None:  # main() may run many times in a process
        handler = _StderrHandler()
        handler.setFormatter(_LogFormatter())
        logger.addHandler(handler)
    logger.setLevel(level)
    return handler


def _one_line(exc: BaseException | str) -> str:
    return " ".join(str(exc).split())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
