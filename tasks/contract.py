"""The task contract: how every volcap step is declared.

A volcap task is a Prefect task that

- takes a ``store`` URL, artifact references (:class:`ArtifactRef`, records holding refs, lists or
  dicts of them) and plain JSON parameters;
- reads its inputs from the store, calls one ``volcap_core`` function, puts its outputs in the
  store and returns references (JSON, never pickle);
- is cached by a key built from its name, an explicit ``version`` the author bumps when its meaning
  changes, the digests of its input refs (never their location, never re-hashing data), its
  canonical parameters (defaults included: a task's settings are parameters with defaults, so a
  changed default is a changed key) and the versions of the libraries whose numerics its output
  depends on (``libraries``). ``docs/tasks.md`` states the rule; ``tests/test_cache_keys.py``
  checks it for every task.

Declare one like this::

    @volcap_task(name="ingest-camera", version="1", libraries=("OpenEXR", "PyOpenColorIO"))
    def ingest_camera(store: str, raw: ArtifactRef, encoding: str) -> CameraIngest: ...

Where the cache lives: Prefect keeps cache records through a *result storage*; volcap points it
into the artifact store itself (``<store>/prefect/results/<key>``, written atomically), so every
process and machine that shares the store URL shares the cache, whatever Prefect database each
one talks to. Before Prefect trusts a record, :class:`StoreCachePolicy` checks that every object
the cached result references is still in the store; if one is gone (``gc``, a wiped bucket) the
record is dropped and the task recomputes instead of handing out a dangling reference.

Traps of Prefect 3.8 this avoids (see ``../shared/NOTES.md``): ``result_storage_key`` would
silently drop the cache policy (never set it); ``persist_result=False`` disables caching (always
persisted); one storage for keys and results corrupts results (no separate key storage is used);
the default policy includes the flow-run id (replaced); ``task_key`` depends on the install path
(the task's *name* is used instead).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import importlib
import importlib.metadata
import inspect
import json
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import PurePosixPath
from typing import Any, ParamSpec, TypeVar

from prefect import task
from prefect.cache_policies import CachePolicy
from prefect.context import TaskRunContext
from prefect.filesystems import WritableFileSystem
from pydantic import BaseModel, PrivateAttr

from volcap_core.digest import digest_bytes
from volcap_core.records import ArtifactRef, canonical_json
from volcap_core.store import ArtifactStore, _digests_in

P = ParamSpec("P")
T = TypeVar("T")

RESULTS_PREFIX = "prefect/results"
#: Parameter names that say *where* data lives, never *what* it is: excluded from cache keys.
LOCATION_PARAMETERS = ("store",)


# ---------------------------------------------------------------------------------------------
# Result storage inside the artifact store
# ---------------------------------------------------------------------------------------------


class StoreResultStorage(WritableFileSystem):
    """Prefect result storage under ``<store_url>/prefect/results``; atomic writes.

    :class:`StoreCachePolicy` installs one per task run, for the store named by the task's ``store``
    input, so a run on any worker writes its cache records next to its artifacts.
    """

    _block_type_name = "Volcap Store Results"
    _block_type_slug = "volcap-store-results"
    store_url: str
    #: records :class:`StoreCachePolicy` already read and validated for this task run (None: known
    #: absent), so Prefect's own existence check and read that follow cost no request
    _records: dict[str, bytes | None] = PrivateAttr(default_factory=dict)

    def _store(self) -> ArtifactStore:
        return ArtifactStore(self.store_url)

    def _resolve_path(self, path: str) -> PurePosixPath:
        # Prefect makes storage keys "absolute" through this hook and then takes them relative to
        # _resolve_path(""); a virtual root keeps keys plain names inside prefect/results/.
        return PurePosixPath("/") / path

    def _path(self, store: ArtifactStore, key: str) -> str:
        key = key.lstrip("/")
        if "/" in key or key in ("", ".", ".."):
            raise ValueError(f"unexpected result key {key!r}")
        return store._p(RESULTS_PREFIX, key)

    def read_path(self, path: str, **_: Any) -> bytes:  # prefect passes _sync=True
        key = path.lstrip("/")
        if key in self._records:
            record = self._records[key]
            if record is None:
                raise FileNotFoundError(key)
            return record
        store = self._store()
        return store.fs.cat_file(self._path(store, path))

    def write_path(self, path: str, content: bytes, **_: Any) -> None:
        store = self._store()
        if store._local:
            store.fs.makedirs(store._p(RESULTS_PREFIX), exist_ok=True)
        store._write_atomic(self._path(store, path), bytes(content))
        key = path.lstrip("/")
        self._records.pop(key, None)
        _RECORD_INDEX.note_written(store.url, key)

    async def aread_path(self, path: str) -> bytes:
        return self.read_path(path)

    async def awrite_path(self, path: str, content: bytes) -> None:
        self.write_path(path, content)


class _RecordIndex:
    """The names under ``<store>/prefect/results``: one listing serves the cache checks of many
    task runs, instead of one read per task run to learn that a record is absent.

    A listing is reused for ``ttl_s`` seconds; records this process writes are added to it at once.
    A name in the listing is still read (its content is the result) and validated; a name not in it
    is a miss without a request. A record another process writes during those seconds is therefore
    missed and the task computed again: the same outcome as two processes computing a key at once
    (both run, both write the same bytes), which the contract already allows.
    """

    def __init__(self, ttl_s: float):
        self.ttl_s = ttl_s
        self._lock = threading.Lock()
        self._names: dict[str, tuple[float, set[str]]] = {}  # store url -> (listed at, names)
        self.listings = 0

    def names(self, store: ArtifactStore) -> set[str]:
        with self._lock:  # one listing when many task runs start at once
            entry = self._names.get(store.url)
            if entry is not None and time.monotonic() - entry[0] < self.ttl_s:
                return entry[1]
            try:
                listed = {PurePosixPath(p).name for p in store.fs.ls(store._p(RESULTS_PREFIX), detail=False)}
            except FileNotFoundError:
                listed = set()
            self.listings += 1
            self._names[store.url] = (time.monotonic(), listed)
            return listed

    def note_written(self, url: str, key: str) -> None:
        with self._lock:
            entry = self._names.get(url)
            if entry is not None:
                entry[1].add(key)

    def note_dropped(self, url: str, key: str) -> None:
        with self._lock:
            entry = self._names.get(url)
            if entry is not None:
                entry[1].discard(key)

    def clear(self) -> None:
        with self._lock:
            self._names.clear()


#: seconds a listing of cache records is trusted for absent names (see :class:`_RecordIndex`)
RECORD_LISTING_TTL_S = 10.0
_RECORD_INDEX = _RecordIndex(RECORD_LISTING_TTL_S)


def _valid_record(store: ArtifactStore, key: str) -> bytes | None:
    """The cache record of ``key`` if it is stored, readable and every object it references is
    still in the store; a record that fails the last two is dropped. None otherwise."""
    if key not in _RECORD_INDEX.names(store):
        return None
    record = cached_result_record(store, key)
    if record is None:
        _RECORD_INDEX.note_dropped(store.url, key)
        return None
    digests = _record_digests(record)
    if digests is None or store.missing(digests):
        # A record that cannot be read, or that points at objects no longer stored, must not be
        # served: drop it so Prefect sees a miss and the task recomputes its outputs.
        drop_cached_result(store, key)
        _RECORD_INDEX.note_dropped(store.url, key)
        return None
    return record


def cached_result_record(store: ArtifactStore, key: str) -> bytes | None:
    try:
        return store.fs.cat_file(store._p(RESULTS_PREFIX, key))
    except FileNotFoundError:
        return None


def drop_cached_result(store: ArtifactStore, key: str) -> None:
    try:
        store.fs.rm_file(store._p(RESULTS_PREFIX, key))
    except FileNotFoundError:
        pass


def _record_digests(record: bytes) -> set[str] | None:
    """Digests referenced by a Prefect result record; None when the record is unreadable."""
    try:
        doc = json.loads(record)
        result = doc["result"]
        if isinstance(result, str):
            result = json.loads(result)
    except (ValueError, KeyError, TypeError):
        return None
    return set(_digests_in(result))


# ---------------------------------------------------------------------------------------------
# Cache keys
# ---------------------------------------------------------------------------------------------


def canonical_inputs(value: Any, where: str = "input") -> Any:
    """Plain JSON stand-in for an input: refs become their digest, records their JSON.

    Refuses what has no stable, location-free meaning (arbitrary objects, floats like NaN), so a
    task can never be cached on something the key does not really capture.
    """
    if isinstance(value, ArtifactRef):
        return {"$ref": value.digest}
    if isinstance(value, BaseModel):
        return canonical_inputs(value.model_dump(mode="json"), where)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        # option objects of the library (frozen dataclasses): every field is part of the meaning
        return {"$options": type(value).__qualname__,
                **canonical_inputs({f.name: getattr(value, f.name) for f in dataclasses.fields(value)}, where)}
    if isinstance(value, enum.Enum):
        return canonical_inputs(value.value, where)
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise TypeError(f"{where}: dict keys must be strings")
        return {k: canonical_inputs(v, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [canonical_inputs(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"{where}: {type(value).__name__} is not a reference or plain parameter; "
                    "pass artifacts as ArtifactRef and settings as JSON values")


_DISTRIBUTIONS_LOCK = threading.Lock()
_DISTRIBUTIONS: dict[str, list[str]] | None = None


def _module_distributions() -> dict[str, list[str]]:
    """``importlib.metadata.packages_distributions()``, once per process.

    It reads every installed distribution's file list (~0.3 s on a quiet 2-core machine). The first
    keys of a mapped task are computed in many threads at once, and each thread computed it (an
    ``lru_cache`` does not make concurrent callers wait): 12 cameras cost a cached ingest ~8 s.
    """
    global _DISTRIBUTIONS
    with _DISTRIBUTIONS_LOCK:
        if _DISTRIBUTIONS is None:
            _DISTRIBUTIONS = dict(importlib.metadata.packages_distributions())
        return _DISTRIBUTIONS


@functools.lru_cache(maxsize=None)
def library_version(module: str) -> str:
    """The public release of the distribution that provides ``module`` (``torch`` -> ``2.13.0``).

    The local label (``+cpu``, ``+cu128``) is dropped: a CPU coordinator and a CUDA worker of the
    same release must compute the same key for a segment (``flows/segment_runs.py`` collects a
    worker's result by its key), and the label names a build, not a change of the code.
    """
    dists = _module_distributions().get(module, [])
    if dists:
        version = importlib.metadata.version(dists[0])
    else:  # extension modules installed without top-level metadata (OpenEXR)
        version = str(getattr(importlib.import_module(module), "__version__"))
    return version.split("+", 1)[0]


def cache_key(name: str, version: str, inputs: dict[str, Any],
              locations: Iterable[str] = LOCATION_PARAMETERS, libraries: Iterable[str] = ()) -> str:
    """``<name>-<blake3 hex>`` of (name, version, canonical inputs minus location parameters, and
    the release of each library in ``libraries``)."""
    skip = set(locations)
    body: dict[str, Any] = {"task": name, "version": version,
                            "inputs": {k: canonical_inputs(v, k) for k, v in inputs.items() if k not in skip}}
    libs = sorted(set(libraries))
    if libs:
        body["libraries"] = {m: library_version(m) for m in libs}
    return f"{name}-{digest_bytes(canonical_json(body)).split(':', 1)[1]}"


@dataclass
class StoreCachePolicy(CachePolicy):
    """Cache key from task name, version, input digests and parameters; validated against the store."""

    task_name: str = ""
    version: str = ""
    locations: tuple[str, ...] = LOCATION_PARAMETERS
    libraries: tuple[str, ...] = ()

    def key(self, inputs: dict[str, Any]) -> str:
        """The key of a run on ``inputs`` (every parameter, defaults applied)."""
        return cache_key(self.task_name, self.version, inputs, self.locations, self.libraries)

    def compute_key(self, task_ctx: TaskRunContext, inputs: dict[str, Any],
                    flow_parameters: dict[str, Any], **kwargs: Any) -> str | None:
        key = self.key(inputs)
        store = ArtifactStore(inputs["store"])
        # Prefect only accepts result storage saved as a server-side block at decoration time, but
        # the store is a run-time input. The engine takes this run's result store from the task
        # run context right after computing the key (prefect 3.8), so point it into the store here.
        # tests/test_task_contract.py checks the records land in the store.
        storage = StoreResultStorage(store_url=store.url)
        task_ctx.result_store = task_ctx.result_store.model_copy(
            update={"result_storage": storage, "metadata_storage": None})
        # Read (or learn from the listing that there is no) record once, validated; Prefect's
        # existence check and read of the same key are then served from it.
        storage._records[key] = _valid_record(store, key)
        return key


def cached_output(task: Any, store: str, **inputs: Any) -> tuple[str, Any | None]:
    """The cache key a call ``task(store, **inputs)`` would have, and its stored result if any.

    Runs nothing and touches no Prefect API: a planner asks what is cached, and an orchestrator
    collects the result of a run that happened on another machine (the record lives in the
    store). A record whose referenced objects are gone counts as absent, as in the task itself.
    """
    key = task_cache_key(task, store, **inputs)
    s = ArtifactStore(store)
    record = cached_result_record(s, key)
    if record is None:
        return key, None
    digests = _record_digests(record)
    if digests is None or s.missing(digests):
        return key, None
    from prefect.results import ResultRecord

    return key, ResultRecord.deserialize(record).result


def task_cache_key(task: Any, store: str, **inputs: Any) -> str:
    """The cache key a call ``task(store, **inputs)`` would have (defaults applied, as Prefect does)."""
    policy = getattr(task, "cache_policy", None)
    if not isinstance(policy, StoreCachePolicy):
        raise TypeError(f"{getattr(task, 'name', task)!r} is not a volcap task")
    bound = inspect.signature(task.fn).bind(store, **inputs)
    bound.apply_defaults()
    return policy.key(dict(bound.arguments))


def task_identity(task: Any) -> dict[str, Any]:
    """What of a task enters its keys besides the caller's inputs: its version, its library
    releases and its settings' defaults (the production journal compares these to tell a
    coordinator why a step reruns: ``task calibrate-static: default options changed``)."""
    policy = task.cache_policy
    defaults = {k: p.default for k, p in inspect.signature(task.fn).parameters.items()
                if p.default is not inspect.Parameter.empty and k not in policy.locations}
    out: dict[str, Any] = {"version": policy.version, "defaults": canonical_inputs(defaults, policy.task_name)}
    if policy.libraries:
        out["libraries"] = {m: library_version(m) for m in sorted(policy.libraries)}
    return out


def current_run_key() -> str:
    """The cache key of the running volcap task: a stable name for its checkpoints.

    A retried or restarted run of the same task on the same inputs gets the same key, so it finds
    the checkpoints of the run it replaces.
    """
    ctx = TaskRunContext.get()
    policy = getattr(getattr(ctx, "task", None), "cache_policy", None)
    if not isinstance(policy, StoreCachePolicy):
        raise RuntimeError("current_run_key() called outside a volcap task")
    return policy.key(ctx.parameters)


# ---------------------------------------------------------------------------------------------
# Tally of finished task runs (for the one-line summary)
# ---------------------------------------------------------------------------------------------

# Prefect records task-run states from events, asynchronously: reading them back from the API right
# after a flow returns can miss the last few. Hooks run in the task's own engine, synchronously, so
# the tally of this process is exact the moment the flow returns.
_TALLY: list[tuple[str, str]] = []  # (flow_run_id, "run" | "cached" | "failed")
_TALLY_LOCK = threading.Lock()
_HOOK_NAME = "_volcap_tally"


def _volcap_tally(task: Any, task_run: Any, state: Any) -> None:
    outcome = "cached" if state.name == "Cached" else "run" if state.is_completed() else "failed"
    with _TALLY_LOCK:
        _TALLY.append((str(task_run.flow_run_id), outcome))


def tally_for(flow_run_ids: Iterable[str]) -> dict[str, int]:
    """Counts of finished volcap task runs of these flow runs seen by this process."""
    ids = {str(i) for i in flow_run_ids}
    counts = {"run": 0, "cached": 0, "failed": 0}
    with _TALLY_LOCK:
        for fr, outcome in _TALLY:
            if fr in ids:
                counts[outcome] += 1
    return counts


class _QuietTallyHook(logging.Filter):
    """Prefect logs every hook call at INFO; the tally hook is bookkeeping, not news."""

    def filter(self, record: logging.LogRecord) -> bool:
        return _HOOK_NAME not in record.getMessage()


logging.getLogger("prefect.task_runs").addFilter(_QuietTallyHook())


# ---------------------------------------------------------------------------------------------
# The decorator
# ---------------------------------------------------------------------------------------------


def volcap_task(*, name: str, version: str, locations: tuple[str, ...] = (), libraries: Iterable[str] = (),
                retries: int = 0, retry_delay_seconds: float = 0, tags: Iterable[str] = (),
                timeout_seconds: float | None = None) -> Callable[[Callable[P, T]], Any]:
    """Declare a cached, store-backed Prefect task (see the module docstring).

    ``name`` is stable across installs (it, not Prefect's ``task_key``, enters the cache key).
    ``version``: bump it whenever the task's output for the same inputs would change.
    ``locations``: extra parameters that only say where inputs live (e.g. a capture folder whose
    content is already pinned by a digest input); they are left out of the key.
    ``libraries``: modules whose release changes the output's numbers or bytes (``"torch"``,
    ``"pycolmap"``, ``"OpenEXR"``); their public versions enter the key.
    Settings belong in parameters with defaults (an options dataclass is a valid parameter), never
    in module globals the body reads: ``tests/test_cache_keys.py`` refuses a task that reads one.
    The function's first parameter must be ``store: str``.
    """

    def decorate(fn: Callable[P, T]) -> Any:
        params = list(inspect.signature(fn).parameters)
        if not params or params[0] != "store":
            raise TypeError(f"task {name}: the first parameter must be 'store'")
        policy = StoreCachePolicy(task_name=name, version=version,
                                  locations=LOCATION_PARAMETERS + tuple(locations), libraries=tuple(libraries))

        @functools.wraps(fn)
        def run(*args: P.args, **kwargs: P.kwargs) -> T:
            return fn(*args, **kwargs)

        return task(
            run,
            name=name,
            cache_policy=policy,
            persist_result=True,
            result_serializer="json",
            retries=retries,
            retry_delay_seconds=retry_delay_seconds,
            tags=list(tags),
            timeout_seconds=timeout_seconds,
            on_completion=[_volcap_tally],
            on_failure=[_volcap_tally],
        )

    return decorate
