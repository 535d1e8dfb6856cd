"""Running flows and telling the coordinator what happened.

Every flow run ends with one line: tasks run, tasks cached, tasks failed, wall time. The counts
come from Prefect's own record of the run (the API), so they are what the UI shows.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any
from uuid import UUID


def quiet_prefect_defaults(log_level: str = "WARNING") -> None:
    """Offline-friendly Prefect settings, unless the user set them.

    The command line keeps Prefect's INFO logs (on stdout, flows/cli_output.py): one line per
    finished task run is the progress a coordinator watches.
    """
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", log_level)


def reproducible_cpu_defaults() -> None:
    """One CPU thread per process for torch's OpenMP/MKL pools, unless the user chose otherwise.

    The one setting under which CPU training is bit-reproducible (resuming from a checkpoint relies
    on it; docs/poly4dgs.md "Reproducibility"). OpenMP reads it when torch is imported, so the entry
    points set it before anything imports torch: ``volcap`` (``flows.cli.main``, whose environment
    ``volcap worker`` hands to its flow runs), ``deploy/worker.sh``, the deployments' job
    environment (``deploy/prefect.yaml``) and ``tests/conftest.py``. Set ``OMP_NUM_THREADS`` to
    trade this for speed.

    The compiled kernels (numba) still run on every core (:mod:`volcap_core.kernel_threads`: their
    bits do not depend on the thread count), and ``OMP_WAIT_POLICY=PASSIVE`` makes their OpenMP
    threads sleep between kernels instead of spinning: two training processes on 2 cores took the
    demo segment's 150 steps in 30.7 s each instead of 38.0, one alone in 24.3 instead of 24.0
    (docs/benchmarks.md, "Rasterizer").
    """
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


#: The temporary server's process: it asks the kernel for SIGTERM when the command's process dies
#: (Linux's PR_SET_PDEATHSIG; a ``kill -9``'d command then leaves no server behind), leaves if the
#: command is already gone, then runs ``python -m uvicorn ARGS`` exactly.
_SERVER_BOOT = """
import os, runpy, signal, sys
parent = int(sys.argv[1])
try:
    import ctypes
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
except Exception:
    pass
if os.getppid() != parent:
    sys.exit(0)
sys.argv = ["uvicorn", *sys.argv[2:]]
runpy.run_module("uvicorn", run_name="__main__", alter_sys=True)
"""


def skip_final_collection() -> None:
    """Make the interpreter's exit skip its last cyclic garbage collection (call it first thing).

    After a flow run the process holds Prefect's, pydantic's and volcap's object graphs; tearing
    them down took 0.4-0.9 s of a cached ``volcap ingest``'s ~3 s after its last line was printed.
    This registers, before anything else, an exit handler (so it runs after all the others:
    Prefect's, which send the run's last events and logs, and logging's) that freezes every
    object out of the collector. Refcounting still closes files and flushes streams; only
    garbage in reference cycles is left to the OS, as it is on any ``os._exit``. Not with
    ``--verbose`` (or ``VOLCAP_VERBOSE``), which shows native output: nanobind (OpenImageIO,
    OpenEXR) then reports the objects left alive at exit as leaks.
    """
    import atexit
    import gc
    import sys

    def freeze() -> None:
        verbose = os.environ.get("VOLCAP_VERBOSE", "").strip().lower() in ("1", "true", "yes", "on")
        if not verbose and "--verbose" not in sys.argv[1:]:
            gc.freeze()

    atexit.register(freeze)


class _TemporaryApi:
    """The temporary Prefect API server of one command: what a flow run starts itself when no API
    is configured (the uvicorn command line and environment of Prefect 3.8's
    ``SubprocessASGIServer``), started by volcap at the beginning of the command instead."""

    def __init__(self) -> None:
        import importlib.util
        import socket
        import subprocess
        import sys

        spec = importlib.util.find_spec("prefect")
        if spec is None or spec.origin is None:
            raise RuntimeError("prefect is not installed")
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{port}/api"
        self.ready = False
        env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1", "PREFECT__SERVER_FINAL": "1"}
        self.process = subprocess.Popen(
            [sys.executable, "-c", _SERVER_BOOT, str(os.getpid()),
             "--app-dir", os.path.dirname(os.path.dirname(spec.origin)),
             "--factory", "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port", str(port),
             "--log-level", "error", "--lifespan", "on"], env=env,
            # its own process group: a terminal's Ctrl-C (sent to the whole foreground group) must not
            # stop the server before the cancelled command has marked its flow run Cancelled in it;
            # the parent-death signal (_SERVER_BOOT) still ends it with the command
            start_new_session=True)

    def wait(self, timeout_s: float) -> bool:
        import urllib.request

        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.process.poll() is None:
            try:
                with urllib.request.urlopen(f"{self.url}/health", timeout=2) as response:
                    if response.status == 200:
                        self.ready = True
                        return True
            except OSError:
                pass
            time.sleep(0.05)
        return False

    def stop(self, grace_s: float = 5.0) -> None:
        import subprocess

        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def _profile_names_an_api() -> bool:
    """Whether the active Prefect profile sets PREFECT_API_URL (read without importing Prefect:
    a quick answer for the common configured case; Prefect's own settings decide afterwards)."""
    import tomllib

    path = os.environ.get("PREFECT_PROFILES_PATH") or os.path.join(
        os.environ.get("PREFECT_HOME") or os.path.expanduser("~/.prefect"), "profiles.toml")
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except (OSError, ValueError):
        return False
    active = os.environ.get("PREFECT_PROFILE") or doc.get("active") or "ephemeral"
    return bool((doc.get("profiles") or {}).get(active, {}).get("PREFECT_API_URL"))


_API: _TemporaryApi | None = None


def start_api_early() -> None:
    """Start the temporary Prefect API server now, when no API is configured.

    Without ``PREFECT_API_URL`` (environment, Prefect profile or ``prefect.toml``) a flow run
    starts a temporary server (a uvicorn subprocess, 4-14 s on 2 cores) when it first needs the
    API: after the command imported its flows (torch, pycolmap, kornia; seconds) and Prefect's
    server module (another 1.5-2.5 s spent only to start it). Started here, first, the server comes
    up while the command imports, and the command reaches it as a server at ``PREFECT_API_URL``.
    :func:`run_flow` waits until it answers; if it does not, the variable is removed again and
    the flow run starts Prefect's own temporary server as before. With a configured server
    (docs/operations.md) nothing is started.
    """
    global _API
    if _API is not None or os.environ.get("PREFECT_API_URL") or _profile_names_an_api():
        return
    try:
        api = _TemporaryApi()
    except Exception:  # noqa: BLE001 - the flow run starts Prefect's own
        return
    import atexit

    atexit.register(api.stop)
    from prefect.settings import PREFECT_API_URL  # imports prefect while the server starts

    if PREFECT_API_URL.value():  # configured elsewhere (prefect.toml, .env): that server is the one
        api.stop(grace_s=0.5)
        return
    _API = api
    _set_api_url(api.url)


def stop_temporary_api(grace_s: float = 2.0) -> None:
    """Stop this command's temporary API server now (volcap's early one, or Prefect's own
    fallback), for a process about to end by ``os._exit`` (a cancelled command), which runs no
    exit handler. Prefect's server may outlive its parent otherwise (docs: shared NOTES)."""
    if _API is not None:
        _API.stop(grace_s=grace_s)
    import sys

    server = sys.modules.get("prefect.server.api.server")
    for instance in list(getattr(getattr(server, "SubprocessASGIServer", None), "_instances", {}).values()):
        try:
            instance.stop()
        except Exception:  # noqa: BLE001 - best effort on the way out
            pass


def _set_api_url(url: str | None) -> None:
    from prefect.context import refresh_global_settings_context

    if url is None:
        os.environ.pop("PREFECT_API_URL", None)
    else:
        os.environ["PREFECT_API_URL"] = url
    refresh_global_settings_context()  # Prefect read its settings when it was imported


def _wait_for_early_api() -> None:
    global _API
    if _API is None or _API.ready:
        return
    from prefect.settings import PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS

    # Prefect's own limit counts only its sleeps between polls; a first start (database
    # migrations) on a busy machine took 36 s: allow real time.
    if not _API.wait(max(120.0, float(PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS.value()))):
        _API.stop()
        _API = None
        _set_api_url(None)


def _heartbeats_without_join() -> None:
    """Let a flow run end without waiting for its heartbeat thread.

    Prefect 3.8's sync flow engine joins the flow run's heartbeat thread when the run ends, and
    the thread sleeps in 1-second steps between its checks: every flow run and sub-flow run ended
    0-1 s late (0.5 s on average; the cached demo has three: a third of its flow time). Prefect's
    async engine passes ``join_on_exit=False``: the thread then stops by itself at its next step,
    sending nothing more. The sync engine gets the same here. Heartbeats during the run (what
    marks a dead run Crashed) are unchanged. Skipped if Prefect's function no longer has that
    parameter.
    """
    import functools
    import inspect

    from prefect import flow_engine

    send = getattr(flow_engine, "_send_heartbeats", None)
    if send is None or getattr(send, "volcap_no_join", False):
        return
    try:
        if "join_on_exit" not in inspect.signature(send).parameters:
            return
    except (TypeError, ValueError):
        return
    patched = functools.partial(send, join_on_exit=False)
    patched.volcap_no_join = True  # type: ignore[attr-defined]
    flow_engine._send_heartbeats = patched


@dataclass
class RunSummary:
    flow_run_id: str
    state: str
    tasks_run: int
    tasks_cached: int
    tasks_failed: int
    wall_s: float
    result: Any = None

    def line(self) -> str:
        return (f"{self.state.lower()}: {self.tasks_run} tasks run, {self.tasks_cached} cached, "
                f"{self.tasks_failed} failed, {self.wall_s:.1f} s wall")

    def counts(self) -> dict[str, Any]:
        return {"tasks_run": self.tasks_run, "tasks_cached": self.tasks_cached,
                "tasks_failed": self.tasks_failed, "wall_s": round(self.wall_s, 3),
                "flow_run_id": self.flow_run_id, "state": self.state}


def flow_run_family(flow_run_id: UUID | str) -> list[UUID]:
    """The flow run and its sub-flow runs, any depth (flow runs are created synchronously)."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterParentFlowRunId

    ids = [UUID(str(flow_run_id))]
    with get_client(sync_client=True) as client:
        frontier = list(ids)
        while frontier:
            children = client.read_flow_runs(
                flow_run_filter=FlowRunFilter(parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=frontier)))
            frontier = [c.id for c in children if c.id not in ids]
            ids.extend(frontier)
    return ids


def count_task_runs(flow_run_id: UUID | str) -> tuple[int, int, int]:
    """(run, cached, failed) volcap task runs of the flow run and its sub-flows, in this process."""
    from tasks.contract import tally_for

    counts = tally_for(flow_run_family(flow_run_id))
    return counts["run"], counts["cached"], counts["failed"]


def run_flow(flow: Any, *, on_running: Any = None, **parameters: Any) -> RunSummary:
    """Run ``flow(**parameters)`` in this process; raise its exception after summarising it.

    The summary (with the exception's message) is attached as ``exc.run_summary``.
    ``on_running(flow, flow_run, state)``: called (as a Prefect ``on_running`` hook, after the
    flow's own) when the flow run starts; the command line learns its flow run from it, to mark it
    Cancelled on SIGINT/SIGTERM (flows/cancellation.py).
    """
    _wait_for_early_api()
    _heartbeats_without_join()
    if on_running is not None:
        flow = flow.with_options(on_running=[*flow.on_running_hooks, on_running])
    t0 = time.perf_counter()
    state = flow(**parameters, return_state=True)
    wall = time.perf_counter() - t0
    run, cached, failed = count_task_runs(state.state_details.flow_run_id)
    summary = RunSummary(str(state.state_details.flow_run_id), state.name, run, cached, failed, wall)
    if state.is_completed():
        summary.result = state.result()
        return summary
    try:
        state.result()
    except BaseException as exc:  # noqa: BLE001 - re-raised with the summary attached
        exc.run_summary = summary  # type: ignore[attr-defined]
        raise
    raise RuntimeError(f"flow ended in state {state.name}")
