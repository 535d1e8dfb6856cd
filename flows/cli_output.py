"""Where the ``volcap`` command's output goes, so that a failure reads as one line.

The contract (README, after the table of commands; docs/operations.md, 8.):

- stderr carries only the cause of a failure: one line ``volcap: error: ...`` (an expected
  failure: bad input, a missing ref, a refused spec), or ``volcap: internal error: ...`` (a bug),
  always the last line, exit code 1. Usage errors are click's own message, exit code 2.
- stdout carries what the run did: Prefect's INFO logs (one line per finished task run, the
  progress a coordinator watches), the run summary, the command's output and, with ``--json``,
  the JSON object on the last line. Logs are on stdout from the start (:class:`StdoutLogHandler`),
  Python warnings too; after the command's last line nothing more is logged to the console
  (Prefect's services draining, its temporary API server stopping at exit).
- An expected failure's traceback is not printed: Prefect's records that carry it ("Task run
  failed with exception", "Encountered exception during execution") are demoted to DEBUG, so they
  still reach the run's logs in the Prefect API (the UI shows them under the DEBUG level) but not
  the console; a failed task's "Finished in state Failed" line stays, at INFO, as progress.
- What native libraries print on fd 2 (OpenEXR's per-chunk diagnostics, nanobind's leak reports
  at exit) is captured (volcap_core.native_stderr); the line about the file an error names is
  folded into that error's message. The failed decode's objects are released before exit (the
  traceback's frames cleared), so nanobind has no leak to report.
- SIGINT / SIGTERM: exit 130 / 143 and one line ``volcap: error: cancelled: <command>: flow run
  '<name>' (running <task runs>) (SIGINT)``, no ``--json`` line (flows/cancellation.py).
- ``volcap --verbose``: DEBUG logs on the console (the demoted tracebacks included), fd 2 not
  captured, and the failure's traceback on stderr before the ``volcap: error:`` line.

Which exceptions are expected is :func:`is_expected`: volcap's refusals are ``ValueError``
subclasses (IngestError, SpecError, ShotError, CalibrationInputError, ImageReadError), store
errors (StoreError: missing refs and objects, corruption), ``OSError`` and ``KeyError`` from the
environment, and :class:`CommandError`. Anything else is a bug: its traceback stays in the logs.
"""

from __future__ import annotations

import logging
import sys
import traceback
from typing import Any

from volcap_core.native_stderr import NativeStderr, detail_for

#: Prefect's loggers whose records carry a failed run's exception.
RUN_LOGGERS = ("prefect.task_runs", "prefect.flow_runs")
#: Messages of the ``prefect`` logger that are plumbing, not progress (the temporary API server's
#: start, and its stop at interpreter exit, after the command's last line).
PLUMBING_PREFIXES = ("Starting temporary server", "Stopping temporary server")


class CommandError(Exception):
    """A failure to report as one line on stderr with exit code 1."""


def is_expected(exc: BaseException) -> bool:
    """True for a failure the command reports as ``volcap: error:`` without a traceback."""
    if isinstance(exc, (CommandError, ValueError, OSError, KeyError)):
        return True
    store = sys.modules.get("volcap_core.store")
    return store is not None and isinstance(exc, store.StoreError)


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (a long multi-line message, a dump: its first line)."""
    text = str(exc).strip() or type(exc).__name__
    if "\n" in text and len(text) > 400:
        text = text.split("\n")[0]
    return " ".join(text.split())


class _Demote(logging.Filter):
    """On Prefect's run loggers: an expected failure's traceback down to DEBUG, the failed task's
    "Finished in state Failed" line down to INFO. On the ``prefect`` logger: plumbing to DEBUG.

    A logger filter runs after the logger's level check and before any handler's, so the demoted
    record still reaches Prefect's API handler (the run's logs) at its new level.
    """

    def __init__(self) -> None:
        super().__init__()
        self._expected_runs: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if exc is not None and is_expected(exc):
            _set_level(record, logging.DEBUG)
            run = getattr(record, "task_run_id", None)
            if run is not None:
                self._expected_runs.add(str(run))
        elif record.levelno > logging.INFO and str(getattr(record, "task_run_id", None)) in self._expected_runs \
                and str(record.msg).startswith("Finished in state"):
            _set_level(record, logging.INFO)
        elif record.name == "prefect" and str(record.msg).startswith(PLUMBING_PREFIXES):
            _set_level(record, logging.DEBUG)
        return True


class _Threshold(logging.Filter):
    """On the console handler: records below the command's level are dropped (the handler's own
    level would be reset by a later incremental ``dictConfig``; a filter is not)."""

    def __init__(self, level: int) -> None:
        super().__init__()
        self.level = level

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= self.level


class StdoutLogHandler(logging.StreamHandler):
    """The command's console log handler: stdout, Prefect's line format, the command's threshold.

    Installed on the root logger before Prefect is imported. Prefect's ``setup_logging`` then sees
    a handler of the user's on root and leaves root alone, so Prefect's records (propagating from
    ``prefect.*``) reach this handler whenever Prefect gets imported (early, in a thread starting
    the temporary API, or late), with no console handler of its own writing to stderr.
    """

    def __init__(self, threshold: logging.Filter) -> None:
        super().__init__(sys.stdout)
        self.setFormatter(_PrefectLikeFormatter())
        self.addFilter(threshold)

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stdout  # whatever sys.stdout is now (tests replace it)
        super().emit(record)


class _PrefectLikeFormatter(logging.Formatter):
    """Prefect's "standard" console format, the flow or task run named (as PrefectFormatter)."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s.%(msecs)03d | %(levelname)-7s | %(name)s - %(message)s", "%H:%M:%S")

    def formatMessage(self, record: logging.LogRecord) -> str:
        text = super().formatMessage(record)
        run = {"prefect.flow_runs": ("Flow run", "flow_run_name"),
               "prefect.task_runs": ("Task run", "task_run_name")}.get(record.name)
        if run is not None and getattr(record, run[1], None) is not None:
            text = text.replace(f"| {record.name} - ", f"| {run[0]} {getattr(record, run[1])!r} - ", 1)
        return text


def _set_level(record: logging.LogRecord, level: int) -> None:
    record.levelno, record.levelname = level, logging.getLevelName(level)


class CliOutput:
    """The process-wide state of one ``volcap`` invocation: verbosity, native stderr, logging."""

    def __init__(self) -> None:
        self.verbose = False
        self.native = NativeStderr()
        self._logging_routed = False
        self._demote = _Demote()
        self._threshold = _Threshold(logging.INFO)

    def start(self, verbose: bool) -> None:
        """Before any command runs: capture native stderr unless verbose."""
        self.verbose = verbose
        self._threshold.level = logging.DEBUG if verbose else logging.INFO
        if not verbose:
            try:
                self.native.start()
            except OSError:  # no usable fd 2 (closed): nothing to keep quiet
                pass
        root = logging.getLogger()
        if not any(isinstance(h, StdoutLogHandler) for h in root.handlers):
            root.addHandler(StdoutLogHandler(self._threshold))
        for name in (*RUN_LOGGERS, "prefect"):  # logger filters survive Prefect's dictConfig
            logging.getLogger(name).addFilter(self._demote)
        logging.captureWarnings(True)  # Python warnings: a log line on stdout, not stderr

    def route_logging(self) -> None:
        """Once Prefect is imported: any console handler of Prefect's still on stderr (its
        ``prefect._internal`` one; root's when Prefect configured logging before :meth:`start`)
        to stdout, under the command's threshold. Idempotent; called before a flow runs."""
        import prefect.logging.configuration  # noqa: F401 - configures Prefect's logging once

        if self._logging_routed:
            return
        self._logging_routed = True
        for logger in (logging.getLogger(), logging.getLogger("prefect._internal")):
            for handler in logger.handlers:
                if isinstance(handler, logging.StreamHandler) and not isinstance(handler, logging.FileHandler):
                    _to_stdout(handler)
                    handler.addFilter(self._threshold)

    def finish(self) -> None:
        """After the command's last line: Prefect's shutdown messages (its services draining, the
        temporary server stopping) stay off the console unless verbose, so neither stdout's last
        line (``--json``) nor stderr's (the error) is followed by them."""
        if "prefect" in sys.modules:
            self.route_logging()
        if not self.verbose:
            self._threshold.level = logging.CRITICAL + 1

    def report(self, exc: BaseException) -> int:
        """Print the one line for ``exc`` (the traceback first when verbose); the exit code."""
        expected = is_expected(exc)
        message = one_line(exc)
        detail = detail_for(message, self.native.read_new())  # the rest of it: --verbose shows it
        if detail:
            message = f"{message} (decoder: {detail})"
        _clear_frames(exc)  # the frames' locals hold native objects (OpenImageIO readers) until exit
        sys.stdout.flush()
        if self.verbose:
            traceback.print_exception(exc, file=sys.stderr)
        if expected:
            line = f"volcap: error: {message}"
        else:
            line = f"volcap: internal error: {type(exc).__name__}: {message}"
            if not self.verbose:
                line += " (volcap --verbose shows the traceback)"
        print(line, file=sys.stderr, flush=True)
        return 1

    def cancelled(self, message: str) -> None:
        """The one line of a command stopped by SIGINT/SIGTERM (flows/cancellation.py, from its
        watcher thread, just before the process ends): ``volcap: error: cancelled: …``; when
        verbose, first where the main thread was (its stack), as a failure's traceback."""
        if self.verbose:
            import threading

            frame = sys._current_frames().get(threading.main_thread().ident)
            if frame is not None:
                print("main thread when cancelled (most recent call last):", file=sys.stderr)
                traceback.print_stack(frame, file=sys.stderr)
        print(f"volcap: error: {message}", file=sys.stderr, flush=True)


def _to_stdout(handler: logging.StreamHandler) -> None:
    if isinstance(handler, StdoutLogHandler) or handler.stream is sys.stdout:
        return
    handler.setStream(sys.stdout)
    console = getattr(handler, "console", None)  # Prefect's handler prints through a rich Console
    if console is not None:
        console.file = sys.stdout


def _clear_frames(exc: BaseException) -> None:
    """Drop the locals of every finished frame in ``exc``'s chain of causes.

    Prefect keeps the failed run's exception in its state objects until the interpreter exits;
    through the traceback it kept the OpenImageIO reader, spec and type objects of the failed
    decode alive, and nanobind reported them as leaks at exit (30 lines on stderr).
    """
    seen: set[int] = set()
    todo: list[Any] = [exc]
    while todo:
        e = todo.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        tb = e.__traceback__
        while tb is not None:
            try:
                tb.tb_frame.clear()
            except RuntimeError:  # a frame still executing (this one's callers)
                pass
            tb = tb.tb_next
        todo += [e.__cause__, e.__context__]


OUTPUT = CliOutput()
