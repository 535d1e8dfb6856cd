"""The task contract: cache keys, Cached states, sharing through the store, vanished outputs."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from prefect import flow, unmapped

from flows.runtime import run_flow
from tasks.contract import RESULTS_PREFIX, cache_key, canonical_inputs, volcap_task
from volcap_core.records import ArtifactRef
from volcap_core.store import ArtifactStore

CALLS: list[str] = []


@volcap_task(name="test-scale", version="1")
def scale(store: str, blob: ArtifactRef, factor: int) -> ArtifactRef:
    CALLS.append(f"v1:{factor}")
    s = ArtifactStore(store)
    return s.put_bytes(s.get_bytes(blob) * factor)


@volcap_task(name="test-scale", version="2")
def scale_v2(store: str, blob: ArtifactRef, factor: int) -> ArtifactRef:
    CALLS.append(f"v2:{factor}")
    s = ArtifactStore(store)
    return s.put_bytes(s.get_bytes(blob) * factor)


@flow
def scale_flow(store: str, blob: ArtifactRef, factors: list[int], version: int = 1) -> list[ArtifactRef]:
    t = scale if version == 1 else scale_v2
    return [f.result() for f in t.map(unmapped(store), unmapped(blob), factors)]


@pytest.fixture
def store(tmp_path) -> ArtifactStore:
    return ArtifactStore(str(tmp_path / "store"))


def test_key_ignores_location_and_size_but_not_content_version_or_params():
    a = ArtifactRef(digest="blake3:" + "a" * 64, size=3)
    b = ArtifactRef(digest="blake3:" + "b" * 64, size=3)
    k = cache_key("t", "1", {"store": "file:///x", "blob": a, "factor": 2})
    assert k == cache_key("t", "1", {"store": "s3://elsewhere", "blob": a, "factor": 2})
    assert k != cache_key("t", "1", {"store": "file:///x", "blob": b, "factor": 2})
    assert k != cache_key("t", "2", {"store": "file:///x", "blob": a, "factor": 2})
    assert k != cache_key("t", "1", {"store": "file:///x", "blob": a, "factor": 3})
    assert k != cache_key("u", "1", {"store": "file:///x", "blob": a, "factor": 2})


def test_inputs_without_a_stable_meaning_are_refused():
    with pytest.raises(TypeError, match="not a reference or plain parameter"):
        canonical_inputs({"x": object()})
    with pytest.raises(ValueError):
        cache_key("t", "1", {"x": float("nan")})


def test_task_must_take_store_first():
    with pytest.raises(TypeError, match="first parameter must be 'store'"):
        @volcap_task(name="bad", version="1")
        def bad(blob: ArtifactRef) -> None: ...


def test_hit_miss_version_bump_and_cached_state(prefect_api, store):
    blob = store.put_bytes(b"ab")
    CALLS.clear()
    first = run_flow(scale_flow, store=store.url, blob=blob, factors=[2, 3])
    assert sorted(CALLS) == ["v1:2", "v1:3"] and (first.tasks_run, first.tasks_cached) == (2, 0)
    # cache records live in the store, not in Prefect's database
    assert len(store.fs.ls(store._p(RESULTS_PREFIX))) == 2

    CALLS.clear()
    again = run_flow(scale_flow, store=store.url, blob=blob, factors=[2, 3])
    assert CALLS == [] and (again.tasks_run, again.tasks_cached) == (0, 2)
    assert again.result == first.result

    CALLS.clear()
    changed = run_flow(scale_flow, store=store.url, blob=blob, factors=[2, 5])  # one parameter changed
    assert CALLS == ["v1:5"] and (changed.tasks_run, changed.tasks_cached) == (1, 1)

    CALLS.clear()
    other = store.put_bytes(b"cd")  # changed input
    run_flow(scale_flow, store=store.url, blob=other, factors=[2])
    assert CALLS == ["v1:2"]

    CALLS.clear()
    bumped = run_flow(scale_flow, store=store.url, blob=blob, factors=[2, 3], version=2)
    assert sorted(CALLS) == ["v2:2", "v2:3"] and bumped.tasks_cached == 0


def test_vanished_output_or_torn_record_recomputes(prefect_api, store):
    blob = store.put_bytes(b"xy")
    first = run_flow(scale_flow, store=store.url, blob=blob, factors=[4])
    out = first.result[0]
    os.remove(store._object_path(out.digest))  # e.g. collected by gc, or a wiped bucket
    CALLS.clear()
    again = run_flow(scale_flow, store=store.url, blob=blob, factors=[4])
    assert CALLS == ["v1:4"] and store.get_bytes(out) == b"xy" * 4

    # A torn cache record (a crash mid-write on a filesystem without atomic rename) is a miss.
    record = store.fs.ls(store._p(RESULTS_PREFIX))[0]
    Path(record).write_text('{"metadata": {"storage_key": ')
    CALLS.clear()
    torn = run_flow(scale_flow, store=store.url, blob=blob, factors=[4])
    assert CALLS == ["v1:4"] and torn.tasks_failed == 0


SCRIPT = textwrap.dedent("""
    import json, os, sys
    sys.path.insert(0, {repo!r})
    from flows.runtime import run_flow
    from tests.test_task_contract import scale_flow, CALLS
    from volcap_core.records import ArtifactRef
    from prefect.testing.utilities import prefect_test_harness
    with prefect_test_harness(server_startup_timeout=120):
        s = run_flow(scale_flow, store=sys.argv[1], blob=ArtifactRef.model_validate_json(sys.argv[2]), factors=[2, 7])
    print(json.dumps({{"calls": CALLS, "run": s.tasks_run, "cached": s.tasks_cached}}))
""")


def test_cache_is_shared_by_processes_that_share_the_store(prefect_api, store, tmp_path):
    """Another process with its own Prefect database sees this process's cache through the store."""
    blob = store.put_bytes(b"shared")
    run_flow(scale_flow, store=store.url, blob=blob, factors=[2])
    script = tmp_path / "other.py"
    repo = str(Path(__file__).resolve().parents[1])
    script.write_text(SCRIPT.format(repo=repo))
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "other-prefect-home")}
    env.pop("PREFECT_API_URL", None)
    out = subprocess.run([sys.executable, str(script), store.url, blob.model_dump_json()], env=env, cwd=repo,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    import json
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res == {"calls": ["v1:7"], "run": 1, "cached": 1}


@volcap_task(name="test-offset", version="1")
def offset(store: str, blob: ArtifactRef, pad: int = 1, label: str = "x") -> ArtifactRef:
    s = ArtifactStore(store)
    return s.put_bytes(s.get_bytes(blob) + label.encode() * pad)


@flow
def offset_flow(store: str, blob: ArtifactRef) -> ArtifactRef:
    return offset(store, blob, pad=2)


def test_cached_output_predicts_the_key_and_reads_a_result_without_running(prefect_api, store):
    """What a planner and an orchestrator of remote runs rely on: the key a call would have
    (defaults applied) and the stored result, with nothing run; gone outputs read as absent."""
    from tasks.contract import cached_output

    blob = store.put_bytes(b"ab")
    key, before = cached_output(offset, store.url, blob=blob, pad=2)
    assert before is None
    out = run_flow(offset_flow, store=store.url, blob=blob).result
    key2, after = cached_output(offset, store.url, blob=blob, pad=2, label="x")
    assert key2 == key and after == out and isinstance(after, ArtifactRef)
    assert store.get_bytes(after) == b"abxx"
    assert cached_output(offset, store.url, blob=blob, pad=3)[1] is None
    store.fs.rm_file(store._object_path(out.digest))
    assert cached_output(offset, store.url, blob=blob, pad=2)[1] is None
