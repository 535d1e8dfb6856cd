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

A worker's flow run (a cancel from the Prefect UI): the worker sets nothing of the above up (its
flow-run process is Prefect's engine, not a ``volcap`` command). On Cancel the run goes
Cancelling; the worker records a "cancel" intent on the run's control channel, sends the process
SIGTERM and waits 30 s before SIGKILL; Prefect's engine stops the flow's main thread, but a task
running in the thread pool (a training segment) kept the process alive until the kill (measured:
docs/operations.md). :func:`stop_flow_run_on_signal`, called first thing by the production
flows, watches for that SIGTERM in the process (the wakeup descriptor alone: Prefect's own
handlers stay) and, **when the runner's intent is "cancel"**, ends it the same way: within
seconds, its runs marked Cancelled, a line in the worker's log. Any other SIGTERM (a pod
eviction, rescheduled by ``PREFECT_FLOW_RUN_EXECUTE_SIGTERM_BEHAVIOR=reschedule``) and SIGINT are
left to Prefect. Runs of deployments a cancelled run started (a production's segment runs on GPU
workers) that are running are set Cancelling, so that their own workers stop them the same way.
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
        #: which signals the watcher acts on (a flow run's process: a runner's cancel only)
        self._acts_on: Callable[[signal.Signals], bool] = lambda sig: True

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

    def watch_flow_run(self, command: str, flow_run: tuple[str, str], report: Callable[[str], None],
                       acts_on: Callable[[signal.Signals], bool]) -> bool:
        """In a flow run's process (:func:`stop_flow_run_on_signal`): the watcher alone, woken by the
        wakeup descriptor, acting on the signals ``acts_on`` accepts; the process's Python-level
        handlers (Prefect's) stay as they are. False off the main thread, when a wakeup descriptor
        is in use already, or once installed."""
        if self._installed or threading.current_thread() is not threading.main_thread():
            return False
        reader, writer = socket.socketpair()
        writer.setblocking(False)
        if signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False) != -1:
            signal.set_wakeup_fd(-1)        # someone else's: left alone (their descriptor is not ours to restore)
            reader.close()
            writer.close()
            return False
        self.command, self._report, self._acts_on, self.flow_run = command, report, acts_on, flow_run
        self._sockets = (reader, writer)
        threading.Thread(target=self._watch, args=(reader,), name="volcap-cancel", daemon=True).start()
        self._installed = True
        return True

    @property
    def installed(self) -> bool:
        """Whether this process handles SIGINT/SIGTERM (a ``volcap`` command, or a flow run's
        process after :func:`stop_flow_run_on_signal`)."""
        return self._installed

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
                if signum in EXIT_CODES and self._acts_on(signal.Signals(signum)):
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


def stop_flow_run_on_signal() -> bool:
    """In a flow run's own process, one a worker started (no ``volcap`` command around it): a
    SIGTERM that the runner sends to **cancel** the run (a cancel from the UI: its control
    channel's intent is "cancel") ends the process as a command's cancel does
    (:class:`Cancellation`): the run, its sub-flow and task runs marked Cancelled, one line
    ``volcap: error: cancelled: FLOW: flow run 'NAME' (running …) (SIGTERM)`` on stderr (the
    worker's log), the process ended at once (exit 143), a task in the thread pool included.
    Any other signal is Prefect's to handle, as before. Called first thing in a flow's body (main
    thread). Only in a process started to run this flow run (``PREFECT__FLOW_RUN_ID``, which
    Prefect's runner and workers set): nothing inside a ``volcap`` command (which handles its
    signals already), in a program or test that calls the flow itself, or off the main thread;
    True when it installed the watcher."""
    from prefect.context import FlowRunContext

    if CANCEL.installed:
        return False
    ctx = FlowRunContext.get()
    if ctx is None or ctx.flow_run is None or os.environ.get("PREFECT__FLOW_RUN_ID") != str(ctx.flow_run.id):
        return False
    return CANCEL.watch_flow_run(ctx.flow.name if ctx.flow is not None else "flow",
                                 (str(ctx.flow_run.id), str(ctx.flow_run.name)),
                                 lambda line: print(f"volcap: error: {line}", file=sys.stderr, flush=True),
                                 lambda sig: sig == signal.SIGTERM and runner_intent() == "cancel")


def runner_intent() -> str | None:
    """The intent the runner that started this flow-run process recorded before signalling it
    ("cancel", "reschedule", "relinquish"), None without one (a plain SIGTERM) or where this
    Prefect has no control channel (3.8's ``prefect._internal.control_listener``, private: read
    defensively, so that another Prefect falls back to its own handling)."""
    try:
        from prefect._internal.control_listener import get_intent
    except ImportError:
        return None
    try:
        return get_intent()
    except Exception:  # noqa: BLE001 - a private API: any failure means "no intent known"
        return None


def mark_cancelled(flow_run_id: str, message: str) -> list[str]:
    """Set the flow run, its sub-flow runs and their task runs that are not final to Cancelled in
    Prefect's API (what the UI shows); the names of the task runs that were running. A sub-flow
    run of a deployment that is running (a segment run on a GPU worker) is set Cancelling
    instead: its worker stops its process (which, with :func:`stop_flow_run_on_signal`, marks it
    Cancelled itself); Cancelled would leave that process training."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
    from prefect.client.schemas.objects import StateType
    from prefect.states import Cancelled, Cancelling

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
                if run.state is None:
                    continue
                if run.id != ids[0] and run.deployment_id is not None and run.state.type in (StateType.RUNNING,
                                                                                            StateType.CANCELLING):
                    if run.state.type == StateType.RUNNING:     # its worker stops it
                        client.set_flow_run_state(run.id, Cancelling(message=message), force=True)
                elif not run.state.is_final() or run.state.is_crashed():
                    client.set_flow_run_state(run.id, Cancelled(message=message), force=True)
            time.sleep(0.2 * (1 - attempt))
    return sorted(running)


CANCEL = Cancellation()
