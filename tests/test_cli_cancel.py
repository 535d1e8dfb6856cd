"""SIGINT and SIGTERM stop a running ``volcap`` command within seconds, as a coordinator relies on:
exit 130 / 143, exactly one ``volcap: error: cancelled: …`` line on stderr naming the command and
its flow run, no ``--json`` line, the flow run Cancelled in Prefect's API, nothing half-written in
the store, and a rerun that finishes from what was cached (a training segment from its last
checkpoint). Real commands as subprocesses on tiny synthetic captures (flows/cancellation.py).
"""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from flows.ingest import ingest_flow
from flows.runtime import run_flow
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture

REPO = Path(__file__).resolve().parents[1]
VOLCAP = [sys.executable, "-m", "flows.cli"]
#: What "within seconds" means here: from the signal to the process's exit (2 busy cores).
STOP_WITHIN_S = 10.0


@pytest.fixture
def api_env(prefect_api):
    """The commands talk to the session's Prefect server (the test reads their runs' states) and
    print their task runs' INFO lines, as they do for a user (conftest quiets them to WARNING)."""
    from prefect.settings import PREFECT_API_URL

    return {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "PREFECT_LOGGING_LEVEL": "INFO"}


def _as_from_a_terminal() -> None:
    """The command starts with SIGINT at its default, as from a terminal, whatever the suite was
    started with: a suite run as a background job of a non-interactive shell (``make test &``)
    passes SIGINT ignored down to its children, and volcap rightly keeps it ignored then
    (:func:`test_a_sigint_ignored_at_start_stays_ignored`)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Running:
    """A ``volcap`` command as a subprocess, its stdout read line by line as it comes."""

    def __init__(self, args: list[str], env: dict) -> None:
        self.proc = subprocess.Popen([*VOLCAP, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=env, cwd=REPO, preexec_fn=_as_from_a_terminal)
        self.lines: list[str] = []
        self._queue: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self._queue.put(line)
        self._queue.put(None)

    def wait_for(self, pattern: str, timeout_s: float = 600) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self._queue.get(timeout=1)
            except queue.Empty:
                continue
            if line is None:
                break
            self.lines.append(line)
            if re.search(pattern, line):
                return line
        self.proc.kill()
        raise AssertionError(f"no line matching {pattern!r} (exit {self.proc.poll()}):\n"
                             + "".join(self.lines[-30:]) + self.proc.stderr.read()[-3000:])

    def stop(self, sig: signal.Signals) -> tuple[int, float, str, str]:
        """Send ``sig``; (exit code, seconds to exit, stdout's rest, stderr)."""
        t0 = time.monotonic()
        self.proc.send_signal(sig)
        try:
            code = self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        elapsed = time.monotonic() - t0
        rest = []
        while (line := self._queue.get(timeout=10)) is not None:
            rest.append(line)
        self.lines += rest
        return code, elapsed, "".join(rest), self.proc.stderr.read()


def volcap(*args: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([*VOLCAP, *args], capture_output=True, text=True, env=env, cwd=REPO, timeout=900)


def flow_run_state(lines: list[str]) -> str:
    """The state in Prefect's API of the flow run the command's "View at …/flow-run/ID" names."""
    from prefect.client.orchestration import get_client

    run_id = next(m.group(1) for line in lines if (m := re.search(r"/flow-run/([0-9a-f-]{36})", line)))
    with get_client(sync_client=True) as client:
        return client.read_flow_run(run_id).state.name


def assert_cancelled(code: int, elapsed: float, rest: str, stderr: str, sig: signal.Signals, command: str) -> None:
    assert code == {signal.SIGINT: 130, signal.SIGTERM: 143}[sig], (code, stderr)
    assert elapsed <= STOP_WITHIN_S, f"{sig.name} took {elapsed:.1f} s to stop the command"
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    # "(running …)": the task runs that were running (none between two tasks)
    assert re.fullmatch(rf"volcap: error: cancelled: {re.escape(command)}: flow run '[\w-]+'"
                        rf"( \(running [\w, -]+\))? \({sig.name}\)", lines[0]), lines[0]
    assert not any(line.startswith("{") for line in rest.splitlines()), "a --json line after the cancel"


def assert_store_whole(store: str, env: dict) -> None:
    verify = volcap("store", "verify", "--store", store, "--json", env=env)
    assert verify.returncode == 0, verify.stdout[-2000:] + verify.stderr
    doc = json.loads(verify.stdout.strip().splitlines()[-1])
    assert doc["corrupt"] == [] and doc["dangling"] == [] and doc["checked"] > 0


@pytest.mark.slow
def test_sigint_stops_a_calibration_and_the_rerun_resumes_from_the_cache(api_env, tmp_path):
    """Ctrl-C once the static cameras are calibrated, while the dense points are computed."""
    synthesize_capture(tmp_path / "cap", rig="demo_scene", frames=2, name="cancel-calib",
                       cameras=["S001", "S002", "S003", "S004", "S005", "S006"])
    store = ArtifactStore(str(tmp_path / "store")).url
    run_flow(ingest_flow, store=store, capture_dir=str(tmp_path / "cap"))

    cmd = Running(["calibrate", "captures/cancel-calib", "--store", store, "--json"], api_env)
    cmd.wait_for(r"Task run 'calibrate-static-\w+' - Finished in state Completed")
    code, elapsed, rest, stderr = cmd.stop(signal.SIGINT)
    assert_cancelled(code, elapsed, rest, stderr, signal.SIGINT, "calibrate captures/cancel-calib")
    assert flow_run_state(cmd.lines) == "Cancelled"
    assert_store_whole(store, api_env)

    again = volcap("calibrate", "captures/cancel-calib", "--store", store, "--json", env=api_env)
    assert again.returncode == 0, again.stderr
    doc = json.loads(again.stdout.strip().splitlines()[-1])
    assert doc["tasks_cached"] >= 1 and doc["tasks_failed"] == 0  # the static cameras' task, at least
    assert re.search(r"Task run 'calibrate-static-\w+' - Finished in state Cached", again.stdout)


@pytest.mark.slow
def test_sigterm_stops_a_training_and_the_rerun_resumes_from_its_checkpoint(api_env, tmp_path):
    """SIGTERM mid-training, after its first checkpoint (every 50 of 100 steps): the rerun takes
    the ground-truth calibration and points from the cache and resumes the segment."""
    synthesize_capture(tmp_path / "cap", rig="demo_scene", frames=2, name="cancel-train", write_depth=True,
                       supersample=1, cameras=["S000", "S001", "S002", "S003", "S004", "S005"])
    store = ArtifactStore(str(tmp_path / "store")).url
    run_flow(ingest_flow, store=store, capture_dir=str(tmp_path / "cap"))
    args = ["reconstruct", "captures/cancel-train", "--preset", "test", "--steps", "100", "--max-gaussians", "3000",
            "--ground-truth", "--store", store, "--out", str(tmp_path / "sheets"), "--json"]

    cmd = Running(args, api_env)
    cmd.wait_for(r"segment \[0, 2\): step 60/100,")  # the checkpoint of step 50 is stored
    code, elapsed, rest, stderr = cmd.stop(signal.SIGTERM)
    assert_cancelled(code, elapsed, rest, stderr, signal.SIGTERM, "reconstruct captures/cancel-train")
    assert "train-segment-" in stderr
    assert flow_run_state(cmd.lines) == "Cancelled"
    assert_store_whole(store, api_env)
    assert any(name.startswith("checkpoints/") for name in ArtifactStore(store).list_refs("checkpoints/"))

    again = volcap(*args, env=api_env)
    assert again.returncode == 0, again.stderr
    doc = json.loads(again.stdout.strip().splitlines()[-1])
    assert (doc["tasks_cached"], doc["tasks_run"], doc["tasks_failed"]) == (2, 1, 0)
    assert re.search(r"segment \[0, 2\): resuming from checkpoints/", again.stdout)
    assert "step 20/100," not in again.stdout and "step 100/100," in again.stdout  # steps 1-50 not redone


def _first_file(folder: Path, proc: subprocess.Popen, timeout_s: float = 120) -> None:
    """Wait until the command has written a file under ``folder`` (it is past its start-up)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        if folder.is_dir() and any(p.is_file() for p in folder.rglob("*")):
            return
        time.sleep(0.05)
    raise AssertionError(f"nothing written under {folder} (exit {proc.poll()})")


def test_sigint_stops_a_command_without_a_flow_with_the_one_line(tmp_path):
    """Every command, not only flows: ``volcap synth`` rendering frames."""
    out = tmp_path / "cap"
    proc = subprocess.Popen([*VOLCAP, "synth", str(out), "--frames", "48", "--json"], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=_as_from_a_terminal)
    _first_file(out, proc)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130 and time.monotonic() - t0 <= STOP_WITHIN_S, (proc.returncode, stderr)
    assert stderr.strip().splitlines() == [f"volcap: error: cancelled: synth {out} (SIGINT)"]
    assert stdout.strip() == ""  # no result line


def test_a_sigint_ignored_at_start_stays_ignored(tmp_path):
    """A background job of a non-interactive shell (``volcap … &`` in a script) starts with SIGINT
    ignored, so that Ctrl-C at the terminal leaves it running: volcap keeps it so."""
    out = tmp_path / "cap"
    proc = subprocess.Popen([*VOLCAP, "synth", str(out), "--frames", "3", "--static-only", "--json"], cwd=REPO,
                            text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    _first_file(out, proc)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr
    assert json.loads(stdout.strip().splitlines()[-1])["capture_json"] == str(out / "capture.json")


def test_a_cancelled_run_sets_its_running_deployment_runs_cancelling(prefect_api):
    """A production's segment runs are runs of the train-segment deployment on GPU workers:
    Cancelled would leave their processes training; Cancelling makes their workers stop them.
    The run itself ends Cancelled, and so does a deployment run that never started."""
    from prefect import task
    from prefect.client.orchestration import get_client
    from prefect.states import Running

    from flows.cancellation import mark_cancelled

    @task(name="segment-run")
    def segment_run() -> None:
        """The task that waits on the deployment run (run_deployment)."""

    with get_client(sync_client=True) as client:
        flow_id = client.create_flow_from_name("cancel-test-production")
        parent = client.create_flow_run_from_deployment(
            client.create_deployment(flow_id, "cancel-test-production"), state=Running())
        # (a run created under a task run gives that task run its own state: one task run each)
        waiting = client.create_task_run(segment_run, parent.id, "0", name="segment-run-0")
        waiting_too = client.create_task_run(segment_run, parent.id, "1", name="segment-run-1")
        seg_dep = client.create_deployment(client.create_flow_from_name("cancel-test-segment"), "cancel-test-segment")
        child = client.create_flow_run_from_deployment(seg_dep, parent_task_run_id=waiting.id, state=Running())
        queued = client.create_flow_run_from_deployment(seg_dep, parent_task_run_id=waiting_too.id)   # Scheduled
        client.set_task_run_state(waiting.id, Running(), force=True)

    assert mark_cancelled(str(parent.id), "cancelled by SIGTERM") == ["segment-run-0"]
    with get_client(sync_client=True) as client:
        assert client.read_flow_run(parent.id).state.type.value == "CANCELLED"
        # the task run waiting on the segment run follows that run's state (Prefect mirrors a
        # sub-flow's state onto its parent task run): Cancelled, or Cancelling while its run stops
        assert client.read_task_run(waiting.id).state.type.value in ("CANCELLED", "CANCELLING")
        assert client.read_flow_run(child.id).state.type.value == "CANCELLING"    # its worker stops it
        assert client.read_flow_run(queued.id).state.type.value == "CANCELLED"    # never started: nothing to stop


def test_a_flow_called_in_process_keeps_the_callers_signals(prefect_api):
    """stop_flow_run_on_signal acts only in a process started to run that flow run (a worker's):
    a program or a test calling the flow itself keeps its own SIGINT handling."""
    from prefect import flow

    from flows.cancellation import CANCEL, stop_flow_run_on_signal

    @flow
    def called_here() -> bool:
        return stop_flow_run_on_signal()

    before = signal.getsignal(signal.SIGINT)
    assert called_here() is False
    assert not CANCEL.installed and signal.getsignal(signal.SIGINT) is before
