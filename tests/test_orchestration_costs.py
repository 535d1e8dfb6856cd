"""What keeps a cached rerun cheap (docs/benchmarks.md, "Cached reruns"): one record read per
cached task, misses from one listing, one scan of the installed distributions per process, no
copy of a file the store already holds, and the command's temporary Prefect API started early and
never outliving the command."""

from __future__ import annotations

import importlib.metadata
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from fsspec.implementations.local import LocalFileSystem

from flows.runtime import run_flow
from tasks import contract
from tasks.contract import RESULTS_PREFIX
from tests.test_ingest import make_capture
from tests.test_task_contract import CALLS, scale_flow
from volcap_core.store import ArtifactStore

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def store(tmp_path) -> ArtifactStore:
    return ArtifactStore(str(tmp_path / "store"))


def test_a_cached_task_reads_its_record_once_and_a_miss_reads_none(prefect_api, store, monkeypatch):
    reads: list[str] = []
    listings: list[str] = []
    real_cat, real_ls = LocalFileSystem.cat_file, LocalFileSystem.ls

    def cat_file(self, path, *args, **kwargs):
        if f"/{RESULTS_PREFIX}/" in str(path):
            reads.append(str(path))
        return real_cat(self, path, *args, **kwargs)

    def ls(self, path, *args, **kwargs):
        if str(path).rstrip("/").endswith(RESULTS_PREFIX):
            listings.append(str(path))
        return real_ls(self, path, *args, **kwargs)

    monkeypatch.setattr(LocalFileSystem, "cat_file", cat_file)
    monkeypatch.setattr(LocalFileSystem, "ls", ls)
    contract._RECORD_INDEX.clear()
    blob = store.put_bytes(b"count")
    CALLS.clear()
    first = run_flow(scale_flow, store=store.url, blob=blob, factors=[11, 12, 13])
    assert first.tasks_run == 3 and reads == [] and len(listings) == 1  # three misses, one listing

    CALLS.clear()
    again = run_flow(scale_flow, store=store.url, blob=blob, factors=[11, 12, 13])
    assert CALLS == [] and again.tasks_cached == 3 and again.result == first.result
    assert len(reads) == 3 and len(set(reads)) == 3  # Prefect's own check and read cost none


def test_a_record_the_listing_names_but_that_is_gone_is_a_miss(prefect_api, store):
    contract._RECORD_INDEX.clear()
    blob = store.put_bytes(b"gone")
    run_flow(scale_flow, store=store.url, blob=blob, factors=[21])
    for record in store.fs.ls(store._p(RESULTS_PREFIX)):
        os.remove(record)  # another machine's gc, after this process listed
    CALLS.clear()
    again = run_flow(scale_flow, store=store.url, blob=blob, factors=[21])
    assert CALLS == ["v1:21"] and again.tasks_run == 1


def test_installed_distributions_are_scanned_once_however_many_threads_ask(monkeypatch):
    calls = []
    real = importlib.metadata.packages_distributions

    def slow():
        calls.append(1)
        time.sleep(0.2)
        return real()

    monkeypatch.setattr(contract, "_DISTRIBUTIONS", None)
    monkeypatch.setattr(contract.importlib.metadata, "packages_distributions", slow)
    contract.library_version.cache_clear()
    try:
        threads = [threading.Thread(target=contract.library_version, args=("numpy",)) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(calls) == 1
    finally:
        contract.library_version.cache_clear()


def test_put_file_check_first_copies_nothing_already_stored(store, tmp_path, monkeypatch):
    f = tmp_path / "scan.ply"
    f.write_bytes(b"ply\n" * 1000)
    ref = store.put_file(f, "application/x-ply")

    def no_copy(*_args, **_kwargs):
        raise AssertionError("copied a file the store holds")

    monkeypatch.setattr(store, "put_stream", no_copy)
    assert store.put_file(f, "application/x-ply", check_first=True) == ref
    f.write_bytes(b"changed")
    monkeypatch.undo()
    new = store.put_file(f, check_first=True)
    assert new.digest != ref.digest and store.get_bytes(new) == b"changed"


# ---------------------------------------------------------------------------------------------
# The command's temporary API (no PREFECT_API_URL)
# ---------------------------------------------------------------------------------------------


def _without_server(home: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env["PREFECT_HOME"] = str(home)
    return env


def _processes_with_home(home: Path) -> list[int]:
    """Processes whose environment names this PREFECT_HOME (the command and its server)."""
    marker = f"PREFECT_HOME={home}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if marker in (entry / "environ").read_bytes().split(b"\0"):
                    found.append(int(entry.name))
            except OSError:
                pass
    return found


def _gone(home: Path, timeout_s: float = 20) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not _processes_with_home(home):
            return True
        time.sleep(0.2)
    return False


@pytest.fixture(scope="module")
def prefect_home(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("prefect-home")  # shared: its database is migrated once


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc")
def test_a_command_without_a_server_runs_on_its_own_temporary_api_and_stops_it(tmp_path, prefect_home):
    capture = make_capture(tmp_path / "cap")
    args = [sys.executable, "-m", "flows.cli", "ingest", str(capture), "--store", str(tmp_path / "store"), "--json"]
    res = subprocess.run(args, cwd=REPO, env=_without_server(prefect_home), capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert (doc["tasks_run"], doc["tasks_cached"], doc["tasks_failed"]) == (7, 0, 0)
    assert _gone(prefect_home), "the temporary API outlived its command"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_the_temporary_api_dies_with_a_killed_command(tmp_path, prefect_home):
    capture = make_capture(tmp_path / "cap")
    env = _without_server(prefect_home)
    proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "ingest", str(capture), "--store",
                             str(tmp_path / "store")], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(_processes_with_home(prefect_home)) < 2:
            time.sleep(0.05)  # the command and the server it started
        assert len(_processes_with_home(prefect_home)) >= 2
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    assert _gone(prefect_home), "a kill -9'd command left its temporary API running"
