"""Stopping a ``volcap`` command on SIGINT (Ctrl-C) or SIGTERM: within seconds, exit 130 / 143,
one line ``volcap: error: cancelled: …`` on stderr, the flow run Cancelled in Prefect's API.

Why not the default behaviour: typer (0.29) turns a KeyboardInterrupt into an exit code that
``standalone_mode=False`` returns instead of raising, so Ctrl-C ended ``volcap calibrate`` with
exit 0 and nothing on stderr; on SIGTERM, Prefect's flow engine raises ``TerminationSignal``,
marks the run Crashed and re-sends the signal to itself, which kills the process with no line.
And neither stops a task running in one of the thread pool's threads: Python cannot interrupt a
thread, and the task runner's exit waits for it (a training segment: minutes).

How: :meth:`Cancellation.install` (``flows.cli.main``, before a command runs) gives SIGINT and
SIGTERM a Python handler that does nothing but let the signal through, and points the
interpreter's wakeup file descriptor at a socket that a watcher thread reads. The C-level signal
handler writes the signal's number there at once, even while the main thread is inside a long
native call that defers Python-level handlers (one that releases the GIL, as pycolmap's SfM does:
SIGTERM during ``calibrate-static`` ended the command in 0.6 s). The watcher then marks the
command's flow run and its sub-flow and task runs that are not final **Cancelled** (bounded to a
few seconds; skipped if the API does not answer), flushes stdout, prints the one line and ends
the process with ``os._exit`` (exit handlers and running threads are not waited for).

What is left is safe by construction: every store write goes to ``tmp/`` and is renamed into
place (docs/store.md), so an interrupted put leaves at most a ``tmp/`` file that ``volcap store
gc`` deletes; finished tasks' results are in the store and their cache records, so a rerun of the
same command reports them cached; a training segment resumes from its last checkpoint
(``checkpoints/<run key>``, stored every ``checkpoint_every`` steps: tasks/reconstruct.py).

A signal that arrives after the command printed its result (:meth:`Cancellation.finished`) is
ignored: the work is done and the process is about to exit 0.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import sys
import threading
import time
from typing import Any, Callable, Iterator

#: Exit code of a command stopped by each signal: 128 + the signal's number, as a shell reports it.
EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}
#: Seconds the watcher gives Prefect's API to record the cancellation before the process ends.
API_GRACE_S = 4.0


class Cancellation:
    """The process's handling of SIGINT/SIGTERM for one command (one per process: :data:`CANCEL`)."""

    def __init__(self) -> None:
        self.command = ""                        # "calibrate captures/NAME": what the line names
        self.flow_run: tuple[str, str] | None = None   # (id, name) of the command's flow run
        self.signal: int | None = None
        self._finished = False
        self._nested = 0
        self._lock = threading.Lock()
        self._installed = False
        self._before_exit: list[Callable[[], None]] = []
        self._report: Callable[[str], None] = lambda line: print(line, file=sys.stderr, flush=True)

    def install(self, command: str, report: Callable[[str], None] | None = None) -> bool:
        """Handle SIGINT and SIGTERM from now on (main thread only; False elsewhere, or on a
        platform without wakeup descriptors). ``report(message)`` prints the one line. A signal
        the process was started with ignored (a background job of a non-interactive shell
        ignores SIGINT) stays ignored."""
        self.command = command
        if report is not None:
            self._report = report
        if self._installed:
            return True
        if threading.current_thread() is not threading.main_thread() or not hasattr(socket, "socketpair"):
            return False
        reader, writer = socket.socketpair()
        writer.setblocking(False)
        # the wakeup descriptor first, so that a signal arriving as the handlers go in is not lost
        signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
        for sig in EXIT_CODES:
            if signal.getsignal(sig) is not signal.SIG_IGN:  # ignored at start (nohup, `cmd &`): stays so
                signal.signal(sig, _let_through)
        self._sockets = (reader, writer)  # kept alive with the process
        threading.Thread(target=self._watch, args=(reader,), name="volcap-cancel", daemon=True).start()
        logging.getLogger("prefect.engine").addFilter(_QuietHook())
        self._installed = True
        return True

    def before_exit(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` (bounded by the API grace) before the cancelled process ends: e.g. stopping
        the command's temporary API server, which ``os._exit`` would not."""
        self._before_exit.append(fn)

    def flow_run_started(self, flow: Any, flow_run: Any, state: Any) -> None:
        """A flow's ``on_running`` hook (:func:`flows.runtime.run_flow`): remember the command's
        own flow run (the first; sub-flows run inside it). Prefect's lines about running the
        hook are demoted to DEBUG (:class:`_QuietHook`): they are not progress."""
        if self.flow_run is None:
            self.flow_run = (str(flow_run.id), str(flow_run.name))

    def finished(self) -> bool:
        """The command is about to print its result: from now on a signal is ignored (not while
        :meth:`nested`). False when a cancellation has already begun (the caller then prints
        nothing and waits to be ended)."""
        with self._lock:
            if self.signal is not None:
                return False
            self._finished = self._finished or self._nested == 0
            return True

    @contextlib.contextmanager
    def nested(self) -> Iterator[None]:
        """A command run as a step of another (``volcap demo`` renders its capture with
        ``synth``): its result line is not the end of the work."""
        self._nested += 1
        try:
            yield
        finally:
            self._nested -= 1

    def wait_if_cancelling(self, grace_s: float = 0.0) -> None:
        """In the main thread, on its way out: if the watcher is ending the process (or starts to
        within ``grace_s``: an exception the signal itself raised, Prefect's ``TerminationSignal``
        or a Crashed run, may reach the main thread first), block until it has; else return."""
        deadline = time.monotonic() + grace_s
        while self.signal is None and time.monotonic() < deadline:
            time.sleep(0.02)
        if self.signal is not None:
            while True:
                time.sleep(1)

    def _watch(self, reader: socket.socket) -> None:
        while True:
            try:
                data = reader.recv(64)
            except OSError:
                return
            for signum in data:
                if signum in EXIT_CODES:
                    self._cancel(signal.Signals(signum))

    def _cancel(self, sig: signal.Signals) -> None:
        with self._lock:
            if self._finished or self.signal is not None:
                return
            self.signal = sig
        running: list[str] = []
        bounded(lambda: running.extend(mark_cancelled(self.flow_run[0], f"cancelled by {sig.name}")
                                       if self.flow_run else ()), API_GRACE_S)
        for fn in self._before_exit:
            bounded(fn, API_GRACE_S)
        what = self.command
        if self.flow_run is not None:
            what += f": flow run {self.flow_run[1]!r}"
            if running:
                what += f" (running {', '.join(running)})"
        try:
            sys.stdout.flush()
        except (OSError, ValueError):
            pass
        try:
            self._report(f"cancelled: {what} ({sig.name})")
        finally:
            os._exit(EXIT_CODES[sig])


class _QuietHook(logging.Filter):
    """On ``prefect.engine``: "Running hook 'flow_run_started' …" and "Hook 'flow_run_started'
    finished …" down to DEBUG (the run's logs keep them)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno == logging.INFO and "'flow_run_started'" in str(record.msg):
            record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return True


def _let_through(signum: int, frame: Any) -> None:
    """The Python-level handler of SIGINT/SIGTERM: nothing (the watcher thread acts). Having one
    is what makes the C-level handler write the signal to the wakeup descriptor."""


def bounded(fn: Callable[[], Any], timeout_s: float) -> None:
    """Call ``fn`` in a daemon thread and wait at most ``timeout_s``; its errors are ignored
    (a cancellation must end the process whatever the API does)."""
    def run() -> None:
        try:
            fn()
        except Exception:  # noqa: BLE001 - best effort
            pass
    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout_s)


def mark_cancelled(flow_run_id: str, message: str) -> list[str]:
    """Set the flow run, its sub-flow runs and their task runs that are not final to Cancelled in
    Prefect's API (what the UI shows); the names of the task runs that were running."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
    from prefect.client.schemas.objects import StateType
    from prefect.states import Cancelled

    from flows.runtime import flow_run_family

    ids = flow_run_family(flow_run_id)
    running = []
    with get_client(sync_client=True) as client:
        for task_run in client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=ids))):
            if task_run.state is not None and not task_run.state.is_final():
                if task_run.state.type == StateType.RUNNING:
                    running.append(task_run.name)
                client.set_task_run_state(task_run.id, Cancelled(message=message), force=True)
        for attempt in range(2):
            # the second pass: on SIGTERM Prefect's own handler (its flow engine's, in the main
            # thread) may have marked the run Crashed meanwhile; the cancellation is the cause
            for run in client.read_flow_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=ids))):
                if run.state is not None and (not run.state.is_final() or run.state.is_crashed()):
                    client.set_flow_run_state(run.id, Cancelled(message=message), force=True)
            time.sleep(0.2 * (1 - attempt))
    return sorted(running)


CANCEL = Cancellation()
