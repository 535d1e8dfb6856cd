"""The content-addressed store, the same suite on ``file://``, ``memory://`` and ``s3://``.

The S3 backend is moto's server mode in a subprocess on loopback (``tests/s3_server.py``), reached
only through the environment (``AWS_ENDPOINT_URL``...), exactly as a user would. What the suite
pins down (the store's docstring lists the same guarantees):

- puts and gets of bytes, streams (chunked: a 24 MiB stream is never read whole), files, records,
  trees and directories; named refs;
- a corrupt or missing object is an error naming its digest, never a wrong answer; ``verify``
  finds corrupt objects and dangling refs;
- tree manifests refuse absolute paths, ``..``/``.``/empty segments, backslashes, duplicate paths
  and non-canonical encodings;
- ``gc`` deletes exactly what no ref reaches and is older than the grace period; a re-put
  refreshes an object, even while gc runs; stale temporary files go;
- ``kill -9`` at random moments during puts never leaves an object that does not hash to its name
  (file:// and s3://: a memory:// store dies with its process), and processes writing the same
  content at once all succeed with one valid object;
- a store sees what other processes wrote (no stale listing caches).
"""

from __future__ import annotations

import datetime as dt
import io
import json
import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
import tracemalloc
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import blake3
import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # `tests.s3_server` whether pytest runs as `pytest` or `python -m`
    sys.path.insert(0, str(REPO))

import volcap_core.store as store_mod  # noqa: E402
from tests.s3_server import S3Endpoint, s3_endpoint  # noqa: E402,F401  (fixture, by name)
from volcap_core.digest import CHUNK_BYTES, StreamingDigest, digest_bytes, digest_file  # noqa: E402
from volcap_core.records import MEDIA_BYTES, MEDIA_TREE, ArtifactRef, Record, canonical_json  # noqa: E402
from volcap_core.store import (  # noqa: E402
    DEFAULT_GRACE_S,
    ArtifactStore,
    CorruptObjectError,
    InvalidTreeError,
    MissingObjectError,
    MissingRefError,
    StoreError,
    TreeEntry,
    decode_tree,
    encode_tree,
    normalize_store_url,
    open_store,
)

BACKENDS = ["file", "memory", "s3"]
OBJECT_PATH_RE = re.compile(r"/objects/[0-9a-f]{2}/[0-9a-f]{62}$")


# ---------------------------------------------------------------------------------------------
# Backends
# ---------------------------------------------------------------------------------------------


@dataclass
class Backend:
    """A store plus ways to act *behind its back*, as another process or a bad disk would."""

    kind: str
    store: ArtifactStore
    endpoint: S3Endpoint | None = None

    def again(self) -> ArtifactStore:
        """Another store object on the same URL (what another process would construct)."""
        return ArtifactStore(self.store.url)

    def raw_write(self, path: str, data: bytes) -> None:
        if self.kind == "file":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            Path(path).write_bytes(data)
        elif self.kind == "memory":
            import fsspec

            fsspec.filesystem("memory").pipe_file(path, data)
        else:
            bucket, key = path.split("/", 1)
            self.endpoint.client().put_object(Bucket=bucket, Key=key, Body=data)

    def raw_delete(self, path: str) -> None:
        if self.kind == "file":
            os.unlink(path)
        elif self.kind == "memory":
            import fsspec

            fsspec.filesystem("memory").rm_file(path)
        else:
            bucket, key = path.split("/", 1)
            self.endpoint.client().delete_object(Bucket=bucket, Key=key)

    def raw_files(self, sub: str) -> list[str]:
        """Every file under ``<root>/<sub>``, listed without the store's code or caches."""
        base = self.store._p(sub)
        if self.kind == "file":
            return sorted(str(p) for p in Path(base).rglob("*") if p.is_file())
        if self.kind == "memory":
            import fsspec

            fs = fsspec.filesystem("memory")
            return sorted(p for p in fs.store if p.startswith(base + "/"))
        bucket, prefix = base.split("/", 1)
        out = []
        for page in self.endpoint.client().get_paginator("list_objects_v2").paginate(
                Bucket=bucket, Prefix=prefix + "/"):
            out += [f"{bucket}/{o['Key']}" for o in page.get("Contents", [])]
        return sorted(out)

    def age(self, paths: list[str], seconds: float) -> None:
        """Make ``paths`` ``seconds`` older. S3 cannot backdate: there, real time passes."""
        if self.kind == "file":
            t = time.time() - seconds
            for p in paths:
                os.utime(p, (t, t))
        elif self.kind == "memory":
            import fsspec

            fs = fsspec.filesystem("memory")
            for p in paths:
                fs.store[p].created -= dt.timedelta(seconds=seconds)
        else:
            time.sleep(seconds)


@pytest.fixture(params=BACKENDS)
def backend(request, tmp_path) -> Iterator[Backend]:
    kind = request.param
    if kind == "file":
        yield Backend(kind, ArtifactStore(str(tmp_path / "store")))
    elif kind == "memory":
        store = ArtifactStore(f"memory://volcap-test-{uuid.uuid4().hex[:12]}")
        yield Backend(kind, store)
        store.fs.rm(store.root, recursive=True) if store.fs.exists(store.root) else None
    else:
        endpoint = request.getfixturevalue("s3_endpoint")
        yield Backend(kind, ArtifactStore(endpoint.store_url()), endpoint)


@pytest.fixture
def store(backend) -> ArtifactStore:
    return backend.store


class FakeClock:
    """Stands in for the ``time`` module inside ``volcap_core.store`` only: the store believes
    it is ``offset`` seconds later (the backends keep stamping real time)."""

    def __init__(self, offset: float):
        self.offset = offset

    def time(self) -> float:
        return time.time() + self.offset

    def __getattr__(self, name):
        return getattr(time, name)


class Take(Record):
    kind: ClassVar[str] = "test-take"
    name: str
    frames: list[str]
    notes: dict[str, str] = {}


class Other(Record):
    kind: ClassVar[str] = "test-other"
    value: int


class ChunkedSource(io.RawIOBase):
    """``size`` pseudo-random bytes made on demand; fails a read larger than ``limit``."""

    def __init__(self, size: int, seed: int = 0, limit: int = CHUNK_BYTES):
        self.left, self.limit, self.offset = size, limit, 0
        self.xof = blake3.blake3(f"volcap test stream {seed}".encode())  # one allocation a read
        self.reads: list[int] = []

    def readable(self) -> bool:
        return True

    def read(self, n: int = -1) -> bytes:
        self.reads.append(n)
        assert n is not None and 0 < n <= self.limit, f"read({n}) asks for more than one chunk"
        n = min(n, self.left)
        self.left -= n
        self.offset += n
        return self.xof.digest(length=n, seek=self.offset - n) if n else b""

    @staticmethod
    def expected(size: int, seed: int = 0) -> str:
        src, d = ChunkedSource(size, seed), StreamingDigest()
        while chunk := src.read(CHUNK_BYTES):
            d.update(chunk)
        return d.digest


# ---------------------------------------------------------------------------------------------
# Blobs, streams, files
# ---------------------------------------------------------------------------------------------


def test_put_get_bytes(store):
    ref = store.put_bytes(b"hello volcap")
    assert ref.digest == digest_bytes(b"hello volcap") and ref.digest.startswith("blake3:")
    assert ref.size == 12 and ref.media_type == MEDIA_BYTES
    assert store.get_bytes(ref) == b"hello volcap"
    assert store.get_bytes(ref.digest) == b"hello volcap"
    assert store.exists(ref) and store.size(ref) == 12
    assert store.put_bytes(b"hello volcap") == ref  # same content, same ref, one object
    assert [d for d, _ in store.iter_objects()] == [ref.digest]
    empty = store.put_bytes(b"", media_type="text/plain")
    assert empty.size == 0 and empty.media_type == "text/plain" and store.get_bytes(empty) == b""
    assert store.resolve(ref.digest) == ArtifactRef(digest=ref.digest, size=12)
    with store.open(ref) as f:
        assert f.read() == b"hello volcap"


def test_large_stream_is_copied_in_chunks(backend, tmp_path):
    store = backend.store
    size = 3 * CHUNK_BYTES + 12345  # > 24 MiB
    src = ChunkedSource(size, seed=7)
    if backend.kind == "file":
        tracemalloc.start()
    try:
        ref = store.put_stream(src)
        put_peak = tracemalloc.get_traced_memory()[1] if backend.kind == "file" else 0
        assert src.reads and max(src.reads) <= CHUNK_BYTES
        assert ref.size == size and ref.digest == ChunkedSource.expected(size, seed=7)
        assert store.size(ref) == size
        if backend.kind == "file":
            tracemalloc.reset_peak()
        out = store.get_file(ref, tmp_path / "out" / "big.bin")
        get_peak = tracemalloc.get_traced_memory()[1] if backend.kind == "file" else 0
    finally:
        if backend.kind == "file":
            tracemalloc.stop()
    assert digest_file(out) == (ref.digest, size)
    assert [p.name for p in out.parent.iterdir()] == ["big.bin"]  # no temporary left beside it
    if backend.kind == "file":  # the whole file never sat in memory: about one chunk at a time
        assert put_peak < 2 * CHUNK_BYTES + (4 << 20), put_peak
        assert get_peak < 2 * CHUNK_BYTES + (4 << 20), get_peak
    assert backend.raw_files("tmp") == []


def test_put_file_get_file(store, tmp_path):
    src = tmp_path / "in.bin"
    src.write_bytes(os.urandom(100_000))
    ref = store.put_file(src, media_type="image/x-exr")
    assert (ref.digest, ref.size) == digest_file(src) and ref.media_type == "image/x-exr"
    dest = tmp_path / "a" / "b" / "out.bin"
    assert store.get_file(ref, dest) == dest and dest.read_bytes() == src.read_bytes()
    dest.write_bytes(b"stale")
    store.get_file(ref, dest)  # replaces what was there
    assert dest.read_bytes() == src.read_bytes()


def test_exists_and_missing(store):
    present = store.put_bytes(b"present")
    absent = digest_bytes(b"absent")
    assert store.exists(present) and not store.exists(absent)
    assert store.missing([present, absent, present.digest]) == [absent]
    assert store.missing([]) == []
    for bad in ("sha256:" + "0" * 64, "blake3:" + "A" * 64, "blake3:abc", ""):
        with pytest.raises(ValueError):
            store.exists(bad)


def test_missing_object_is_a_clear_error(store, tmp_path):
    d = digest_bytes(b"never stored")
    for call in (lambda: store.get_bytes(d), lambda: store.get_file(d, tmp_path / "x"),
                 lambda: store.open(d), lambda: store.size(d), lambda: store.get_tree(d),
                 lambda: store.get_record(d, Take), lambda: store.resolve(d)):
        with pytest.raises(MissingObjectError) as exc:
            call()
        assert exc.value.digest == d and d in str(exc.value) and store.url in str(exc.value)
        assert isinstance(exc.value, KeyError) and isinstance(exc.value, StoreError)
    assert not (tmp_path / "x").exists()
    with pytest.raises(MissingObjectError, match=d):
        store.set_ref("dangling", ArtifactRef(digest=d, size=1))
    with pytest.raises(MissingObjectError, match=d):
        store.put_tree({"a.bin": ArtifactRef(digest=d, size=1)})


# ---------------------------------------------------------------------------------------------
# Records and trees
# ---------------------------------------------------------------------------------------------


def test_records_roundtrip(store):
    take = Take(name="take-001 é", frames=["f0", "f1"], notes={"z": "1", "a": "2"})
    ref = store.put_record(take)
    assert ref.media_type == "application/vnd.volcap.test-take+json"
    assert store.get_record(ref, Take) == take
    assert store.get_bytes(ref) == take.to_canonical_json()
    # Same record, same bytes, same digest, whatever the field order it was built in.
    assert store.put_record(Take(notes={"a": "2", "z": "1"}, frames=["f0", "f1"], name="take-001 é")) == ref
    with pytest.raises(StoreError, match=ref.digest):
        store.get_record(ref, Other)
    jref = store.put_json({"b": [1, 2.5, None], "a": "x"})
    assert store.get_bytes(jref) == b'{"a":"x","b":[1,2.5,null]}'
    assert store.get_json(jref) == {"a": "x", "b": [1, 2.5, None]}
    with pytest.raises(ValueError):
        store.put_json({"x": float("nan")})


def test_trees_and_directories(store, tmp_path):
    a, b = store.put_bytes(b"aaa"), store.put_bytes(b"bbbb")
    tree = store.put_tree({"sub/b.bin": b, "a.bin": a})
    assert tree.media_type == MEDIA_TREE
    assert store.put_tree({"a.bin": a, "sub/b.bin": b}) == tree  # insertion order is irrelevant
    assert store.get_tree(tree) == {"a.bin": TreeEntry(a.digest, 3), "sub/b.bin": TreeEntry(b.digest, 4)}
    assert store.get_bytes(tree) == encode_tree({"a.bin": TreeEntry(a.digest, 3),
                                                 "sub/b.bin": TreeEntry(b.digest, 4)})

    src = tmp_path / "src"
    (src / "cam 01" / "deep").mkdir(parents=True)
    (src / "cam 01" / "deep" / "frame_0001.exr").write_bytes(os.urandom(50_000))
    (src / "cam 01" / "empty.txt").write_bytes(b"")
    (src / "été.json").write_text('{"k": 1}')
    (src / "top.bin").write_bytes(b"aaa")  # same content as `a`: stored once
    seen = []
    dref = store.put_directory(src, progress=lambda i, n: seen.append((i, n)))
    assert seen[-1] == (4, 4)
    assert set(store.get_tree(dref)) == {"cam 01/deep/frame_0001.exr", "cam 01/empty.txt",
                                         "été.json", "top.bin"}
    assert store.get_tree(dref)["top.bin"].digest == a.digest
    out = store.get_directory(dref, tmp_path / "out")
    for p in src.rglob("*"):
        if p.is_file():
            assert (out / p.relative_to(src)).read_bytes() == p.read_bytes()
    assert sorted(q.relative_to(out).as_posix() for q in out.rglob("*") if q.is_file()) == \
        sorted(q.relative_to(src).as_posix() for q in src.rglob("*") if q.is_file())
    assert store.put_directory(src) == dref  # deterministic

    (src / "link").symlink_to(src / "top.bin")
    with pytest.raises(InvalidTreeError, match="symbolic link"):
        store.put_directory(src)


BAD_PATHS = ["/etc/passwd", "/abs", "../up", "a/../../b", "a/..", "./a", "a/./b", "a//b", "a/",
             "", "a\\b", "..\\x", "C:/x", "c:x", "a\x00b", ".", ".."]


@pytest.mark.parametrize("path", BAD_PATHS)
def test_tree_paths_rejected(path):
    entry = TreeEntry(digest_bytes(b"x"), 1)
    with pytest.raises(InvalidTreeError):
        encode_tree({path: entry})
    manifest = json.dumps({"entries": {path: {"digest": entry.digest, "size": 1}},
                           "format": "volcap-tree/1"}, sort_keys=True, separators=(",", ":"),
                          ensure_ascii=False).encode()
    with pytest.raises(InvalidTreeError):
        decode_tree(manifest)


def _good_manifest() -> tuple[bytes, str]:
    d = digest_bytes(b"x")
    return encode_tree({"a/b.bin": TreeEntry(d, 1), "c.bin": TreeEntry(d, 1)}), d


def _bad_manifests() -> dict[str, bytes]:
    good, d = _good_manifest()
    e = f'{{"digest":"{d}","size":1}}'
    return {
        "duplicate path": f'{{"entries":{{"a.bin":{e},"a.bin":{e}}},"format":"volcap-tree/1"}}'.encode(),
        "duplicate after escape": f'{{"entries":{{"a.bin":{e},"a\\u002ebin":{e}}},"format":"volcap-tree/1"}}'.encode(),
        "duplicate entry key": f'{{"entries":{{"a.bin":{{"digest":"{d}","size":1,"size":2}}}},"format":"volcap-tree/1"}}'.encode(),
        "spaces": json.dumps(json.loads(good), sort_keys=True).encode(),
        "unsorted keys": f'{{"format":"volcap-tree/1","entries":{{"c.bin":{e}}}}}'.encode(),
        "unsorted paths": f'{{"entries":{{"c.bin":{e},"a.bin":{e}}},"format":"volcap-tree/1"}}'.encode(),
        "trailing newline": good + b"\n",
        "escaped unicode": f'{{"entries":{{"\\u00e9.bin":{e}}},"format":"volcap-tree/1"}}'.encode(),
        "utf-8 BOM": b"\xef\xbb\xbf" + good,
        "not utf-8": good.replace(b"c.bin", b"c\xff.bin"),
        "float size": good.replace(b'"size":1}', b'"size":1.0}', 1),
        "bool size": good.replace(b'"size":1}', b'"size":true}', 1),
        "negative size": good.replace(b'"size":1}', b'"size":-1}', 1),
        "bad digest": good.replace(d.encode(), b"blake3:" + b"0" * 63, 1),
        "extra entry field": good.replace(b'"size":1}', b'"size":1,"z":0}', 1),
        "extra top-level field": good[:-1] + b',"x":1}',
        "wrong format": good.replace(b"volcap-tree/1", b"volcap-tree/2"),
        "not an object": b"[]",
        "not JSON": b"\x00\x01",
        "empty": b"",
    }


@pytest.mark.parametrize("case", sorted(_bad_manifests()))
def test_tree_manifest_rejected(case):
    with pytest.raises(InvalidTreeError):
        decode_tree(_bad_manifests()[case])


def test_tree_manifest_canonical_accepted():
    good, d = _good_manifest()
    assert decode_tree(good) == {"a/b.bin": TreeEntry(d, 1), "c.bin": TreeEntry(d, 1)}
    assert decode_tree(encode_tree({})) == {}


def test_bad_tree_in_store_is_refused(store, tmp_path):
    x = store.put_bytes(b"x")
    e = canonical_json({"digest": x.digest, "size": 1}).decode()
    for path in ("../escaped.bin", "/tmp/abs.bin", "a/../../escaped.bin"):
        evil = store.put_bytes(json.dumps({"entries": {path: json.loads(e)}, "format": "volcap-tree/1"},
                                          sort_keys=True, separators=(",", ":")).encode(), MEDIA_TREE)
        with pytest.raises(InvalidTreeError, match=evil.digest):
            store.get_tree(evil)
        with pytest.raises(InvalidTreeError):
            store.get_directory(evil, tmp_path / "dest" / "inner")
    dup = store.put_bytes(f'{{"entries":{{"a":{e},"a":{e}}},"format":"volcap-tree/1"}}'.encode(), MEDIA_TREE)
    with pytest.raises(InvalidTreeError, match="duplicate"):
        store.get_tree(dup)
    assert not (tmp_path / "escaped.bin").exists() and not (tmp_path / "dest").exists()


# ---------------------------------------------------------------------------------------------
# Refs
# ---------------------------------------------------------------------------------------------


def test_refs(store):
    a, b = store.put_bytes(b"a", "text/plain"), store.put_bytes(b"b")
    assert store.list_refs() == {}
    store.set_ref("captures/demo", a)
    store.set_ref("captures/demo-2", b)
    store.set_ref("calib", b)
    assert store.get_ref("captures/demo") == a  # media type travels with the ref
    assert store.resolve("captures/demo") == a
    assert store.list_refs() == {"calib": b, "captures/demo": a, "captures/demo-2": b}
    assert store.list_refs("captures/") == {"captures/demo": a, "captures/demo-2": b}
    store.set_ref("captures/demo", b)  # moving a ref is an overwrite
    assert store.get_ref("captures/demo") == b
    store.delete_ref("captures/demo")
    assert "captures/demo" not in store.list_refs()
    with pytest.raises(MissingRefError, match="captures/demo"):
        store.get_ref("captures/demo")
    with pytest.raises(MissingRefError, match="nope"):
        store.delete_ref("nope")
    # A name that is only a namespace of other refs is not a ref.
    with pytest.raises(MissingRefError, match="captures"):
        store.get_ref("captures")
    with pytest.raises(MissingRefError):
        store.delete_ref("captures")
    assert store.get_ref("captures/demo-2") == b


@pytest.mark.parametrize("name", ["", "/abs", "../x", "a/../b", "a//b", "a/", ".hidden", "a/.b",
                                  "a b", "a\\b", "-x", "ü", "a\nb"])
def test_bad_ref_names(name, tmp_path):
    store = ArtifactStore(str(tmp_path / "store"))
    ref = store.put_bytes(b"x")
    for call in (lambda: store.set_ref(name, ref), lambda: store.get_ref(name),
                 lambda: store.delete_ref(name)):
        with pytest.raises(ValueError):
            call()
    assert store.list_refs() == {} and not list((tmp_path / "store" / "refs").rglob("*"))


# ---------------------------------------------------------------------------------------------
# Corruption and verify
# ---------------------------------------------------------------------------------------------


def test_corruption_is_detected(backend, tmp_path):
    store = backend.store
    blob = store.put_bytes(os.urandom(5000))
    take = store.put_record(Take(name="t", frames=[blob.digest]))
    tree = store.put_tree({"x.bin": blob})
    good = store.put_bytes(b"fine")
    for ref in (blob, take, tree):  # behind the store's back: a bad disk, a buggy tool
        backend.raw_write(store._object_path(ref.digest), b"tampered " + ref.digest.encode())
    for call in (lambda: store.get_bytes(blob), lambda: store.get_file(blob, tmp_path / "o.bin")):
        with pytest.raises(CorruptObjectError) as exc:
            call()
        assert exc.value.digest == blob.digest and blob.digest in str(exc.value)
        assert exc.value.actual == digest_bytes(b"tampered " + blob.digest.encode())
    assert [p.name for p in tmp_path.iterdir()] == (["store"] if backend.kind == "file" else [])
    with pytest.raises(CorruptObjectError, match=take.digest):
        store.get_record(take, Take)
    with pytest.raises(CorruptObjectError, match=tree.digest):
        store.get_tree(tree)
    # Truncation (what a torn write would leave) is corruption too.
    backend.raw_write(store._object_path(good.digest), b"fin")
    with pytest.raises(CorruptObjectError, match=good.digest):
        store.get_bytes(good)
    # Unverified reads are explicit, and return what is there.
    assert store.get_bytes(blob, verify=False).startswith(b"tampered ")
    report = store.verify()
    assert sorted(report.corrupt) == sorted([blob.digest, take.digest, tree.digest, good.digest])
    assert report.checked == 4 and not report.ok


def test_verify_clean_and_dangling(backend):
    store = backend.store
    x, y = store.put_bytes(b"x" * 1000), store.put_bytes(b"y")
    rec = store.put_record(Take(name="r", frames=[y.digest]))
    store.set_ref("t", store.put_tree({"x": x, "sub/y": y}))
    store.set_ref("r", rec)
    progress = []
    report = store.verify(progress=lambda i, n: progress.append((i, n)))
    assert report.ok and report.checked == 4 and report.bytes >= 1001 and progress[-1] == (4, 4)
    backend.raw_delete(store._object_path(y.digest))
    report = store.verify()
    assert report.corrupt == [] and sorted(report.dangling) == [f"r -> {y.digest}", f"t -> {y.digest}"]
    assert not report.ok


# ---------------------------------------------------------------------------------------------
# Garbage collection
# ---------------------------------------------------------------------------------------------


def _objects(store) -> set[str]:
    return {d for d, _ in store.iter_objects()}


def test_gc_deletes_exactly_the_unreachable(store):
    f1, f2 = store.put_bytes(b"frame 1"), store.put_bytes(b"frame 2")
    tree = store.put_tree({"cam/f1": f1, "cam/f2": f2})
    inner = store.put_bytes(b"mentioned in a record")
    keyed = store.put_bytes(b"a digest used as a key")
    embedded = store.put_bytes(b"a digest inside a longer string")
    nested_tree = store.put_tree({"calib.json": store.put_bytes(b"{}")})
    rec = store.put_record(Take(name="take", frames=[inner.digest, nested_tree.digest],
                                notes={keyed.digest: "first frame",
                                       "uri": f"volcap://{embedded.digest}#0"}))
    store.set_ref("captures/a", tree)
    store.set_ref("takes/b", rec)
    garbage = [store.put_bytes(b"orphan"), store.put_bytes(os.urandom(3000)),
               store.put_tree({"x": store.put_bytes(b"orphan child")})]
    garbage.append(store.put_bytes(b"orphan child"))
    live = {f1.digest, f2.digest, tree.digest, inner.digest, keyed.digest, embedded.digest,
            nested_tree.digest, digest_bytes(b"{}"), rec.digest}

    dry = store.gc(grace_s=0, dry_run=True)
    assert dry.deleted == len(garbage) and _objects(store) == live | {g.digest for g in garbage}
    report = store.gc(grace_s=0)
    assert sorted(report.deleted_digests) == sorted(g.digest for g in garbage)
    assert report.deleted == 4 and report.kept == len(live) and report.deleted_bytes > 3000
    assert _objects(store) == live
    assert store.verify().ok
    assert store.get_record(rec, Take).name == "take"
    for d in live:
        store.get_bytes(d)
    # Roots can also be given for one run (a flow in progress); dropping a ref frees its closure.
    store.delete_ref("captures/a")
    assert store.gc(grace_s=0, extra_roots=[tree.digest]).deleted == 0
    assert store.gc(grace_s=0).deleted == 3  # tree, f1, f2
    assert _objects(store) == live - {tree.digest, f1.digest, f2.digest}


def test_gc_default_grace_keeps_young_objects(backend):
    store = backend.store
    kept = store.put_bytes(b"just written, no ref yet")
    backend.raw_write(store._p("tmp", "inflight.part"), b"partial")
    report = store.gc()
    assert report.deleted == 0 and report.young_unreachable == 1 and report.tmp_deleted == 0
    assert store.exists(kept) and backend.raw_files("tmp") == [store._p("tmp", "inflight.part")]


def test_gc_after_the_grace_period(backend, monkeypatch):
    """With the store's clock past the grace period: stale tmp files and unreachable go."""
    store = backend.store
    live = store.put_bytes(b"live")
    store.set_ref("live", live)
    dead = store.put_bytes(b"dead")
    backend.raw_write(store._p("tmp", "crashed-writer.part"), b"half an obj")
    monkeypatch.setattr(store_mod, "time", FakeClock(DEFAULT_GRACE_S + 60))
    report = store.gc()
    assert report.deleted_digests == [dead.digest] and report.tmp_deleted == 1
    assert backend.raw_files("tmp") == [] and _objects(store) == {live.digest}


def test_gc_spares_objects_refreshed_by_a_put(backend, monkeypatch):
    """A put of an existing object refreshes it, so gc keeps it, even when the put lands while
    gc runs (between its listing and its deletions)."""
    store = backend.store
    before, during, untouched = (store.put_bytes(b"re-put before gc"),
                                 store.put_bytes(b"re-put during gc"),
                                 store.put_bytes(b"never re-put"))
    # S3 cannot backdate: real seconds pass there, and its timestamps have 1 s resolution. The
    # refreshed objects must look younger than the grace period to gc, the untouched one older.
    age, grace = 3.5, 3.0
    backend.age([store._object_path(r.digest) for r in (before, during, untouched)], age)

    def reput(data: bytes) -> None:
        # A writer elsewhere puts the same bytes. Long enough after the first put that the store
        # must refresh (on object storage, a rewrite; a very young object is left as it is).
        with monkeypatch.context() as m:
            m.setattr(store_mod, "time", FakeClock(DEFAULT_GRACE_S))
            ArtifactStore(store.url).put_bytes(data)

    reput(b"re-put before gc")
    listing = store.iter_objects

    def iter_objects_then_a_writer_puts():
        yield from list(listing())
        reput(b"re-put during gc")

    monkeypatch.setattr(store, "iter_objects", iter_objects_then_a_writer_puts)
    report = store.gc(grace_s=grace)
    monkeypatch.undo()
    assert report.deleted_digests == [untouched.digest]
    assert _objects(store) == {before.digest, during.digest}
    assert store.get_bytes(during) == b"re-put during gc"


def test_gc_does_not_read_large_blobs_whole(tmp_path):
    """Reachability sniffs JSON objects; a big binary that merely starts with '{' (a safetensors
    header length can) is not loaded into memory."""
    store = ArtifactStore(str(tmp_path / "store"))

    class Brace(ChunkedSource):
        first = True

        def read(self, n=-1):
            data = super().read(n)
            if self.first:
                self.first = False
                return b"{\x00" + data[2:]
            return data

    big = store.put_stream(Brace(3 * CHUNK_BYTES, seed=3))
    store.set_ref("weights", big)
    tracemalloc.start()
    try:
        report = store.gc(grace_s=0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert report.kept == 1 and report.deleted == 0
    assert peak < CHUNK_BYTES, peak


# ---------------------------------------------------------------------------------------------
# Seeing other processes' writes
# ---------------------------------------------------------------------------------------------


def test_sees_other_writers(backend):
    """What another process writes or deletes is seen at once: no stale listing cache."""
    store = backend.store
    old = store.put_bytes(b"old")
    store.set_ref("old", old)
    # Fill whatever caches the backend keeps: listings of objects/, refs/, the old object's dir.
    assert _objects(store) == {old.digest} and set(store.list_refs()) == {"old"}
    store.gc(grace_s=0, dry_run=True)
    store.verify()
    assert store.exists(old)
    new_data = b"written by another process"
    new = digest_bytes(new_data)
    backend.raw_write(store._object_path(new), new_data)
    backend.raw_write(store._ref_path("new"),
                      canonical_json(ArtifactRef(digest=new, size=len(new_data)).model_dump(mode="json")))
    backend.raw_delete(store._object_path(old.digest))
    backend.raw_delete(store._ref_path("old"))
    for s in (store, backend.again()):
        assert s.exists(new) and not s.exists(old)
        assert _objects(s) == {new} and set(s.list_refs()) == {"new"}
        assert s.get_bytes(new) == new_data and s.missing([new, old]) == [old.digest]
        with pytest.raises(MissingObjectError):
            s.get_bytes(old)
        with pytest.raises(MissingRefError):
            s.get_ref("old")
        assert s.gc(grace_s=0, dry_run=True).deleted == 0 and s.verify().ok


# ---------------------------------------------------------------------------------------------
# Concurrency and crashes
# ---------------------------------------------------------------------------------------------


def test_concurrent_threads_same_content(backend):
    store = backend.store
    size = CHUNK_BYTES + 999
    refs, errors = [], []
    barrier = threading.Barrier(4)

    def put(i):
        try:
            s = store if i % 2 else backend.again()
            barrier.wait()
            refs.append(s.put_stream(ChunkedSource(size, seed=11)))
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=put, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert errors == [] and len(refs) == 4 and len(set(refs)) == 1
    assert refs[0].digest == ChunkedSource.expected(size, seed=11)
    assert _objects(store) == {refs[0].digest} and store.verify().ok
    assert backend.raw_files("tmp") == []


#: A process that imports the store once, then forks a writer per job: kill -9 trials cost
#: milliseconds each instead of an interpreter start. Jobs arrive as JSON lines on stdin.
ZYGOTE = r'''
import io, json, os, random, sys, time, traceback
import volcap_core.store as S
try:
    import s3fs  # noqa: F401 (imported here once, so that forked writers start at once)
except ImportError:
    pass

def writer(job):
    """Put random multi-chunk streams and name each by a ref, until killed."""
    S.CHUNK_BYTES = job["chunk"]
    store = S.ArtifactStore(job["url"])
    log = os.open(job["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    rng = random.Random(job["seed"])
    for i in range(100000):
        data = os.urandom(rng.randint(job["min_size"], job["max_size"]))
        ref = store.put_stream(io.BytesIO(data))
        os.write(log, (ref.digest + "\n").encode())
        store.set_ref(f"{job['refs']}/{i}", ref)

def same_content(job):
    """Put the same content as the other writers of the job, all starting at the same moment."""
    S.CHUNK_BYTES = job["chunk"]
    data = random.Random(job["seed"]).randbytes(job["size"])
    store = S.ArtifactStore(job["url"])
    while time.time() < job["start_at"]:
        time.sleep(0.0005)
    if job["mode"] == "stream":
        ref = store.put_stream(io.BytesIO(data))
    elif job["mode"] == "file":
        ref = store.put_file(job["src"])
    else:
        ref = store.put_bytes(data)
    with open(job["out"], "w") as f:
        f.write(ref.digest)

for line in sys.stdin:
    jobs = json.loads(line)
    pids = []
    for job in jobs:
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                os.environ.update(job.get("env", {}))
                {"writer": writer, "same_content": same_content}[job["kind"]](job)
                code = 0
            except BaseException:
                traceback.print_exc()
            finally:
                sys.stderr.flush()
                os._exit(code)
        pids.append(pid)
    print(json.dumps(pids), flush=True)
    print(json.dumps([os.waitpid(p, 0)[1] for p in pids]), flush=True)
'''


class Zygote:
    def __init__(self, log_path: Path):
        self.log_path = log_path
        self._log = open(log_path, "wb")
        self.proc = subprocess.Popen([sys.executable, "-c", ZYGOTE], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=self._log, text=True, bufsize=1)

    def _line(self):
        line = self.proc.stdout.readline()
        assert line, f"zygote died: {self.log_tail()}"
        return json.loads(line)

    def start(self, jobs: list[dict]) -> list[int]:
        self.proc.stdin.write(json.dumps(jobs) + "\n")
        self.proc.stdin.flush()
        return self._line()

    def wait(self) -> list[int]:
        return self._line()

    def log_tail(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")[-3000:]

    def close(self) -> None:
        try:
            self.proc.stdin.close()
            self.proc.wait(timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        self._log.close()


@pytest.fixture(scope="module")
def zygote(tmp_path_factory) -> Iterator[Zygote]:
    z = Zygote(tmp_path_factory.mktemp("zygote") / "zygote.log")
    yield z
    z.close()


def _job_env(backend: Backend) -> dict[str, str]:
    return dict(backend.endpoint.env) if backend.endpoint else {}


KILL_TRIALS = 20


@pytest.mark.parametrize("backend", ["file", "s3"], indirect=True)
def test_kill_9_during_puts_leaves_no_bad_object(backend, zygote, tmp_path):
    store = backend.store
    rng = random.Random(1234)
    chunk = 256 << 10
    acknowledged: set[str] = set()
    interrupted_writes = 0  # trials whose kill left a partial temporary file: kills hit mid-put
    for trial in range(KILL_TRIALS):
        log = tmp_path / f"trial-{trial}.log"
        tmp_before = set(backend.raw_files("tmp"))
        [pid] = zygote.start([{"kind": "writer", "url": store.url, "log": str(log), "seed": trial,
                               "chunk": chunk, "min_size": 2 * chunk + 1, "max_size": 12 * chunk,
                               "refs": f"trial{trial}", "env": _job_env(backend)}])
        if trial % 2:
            # every other writer is killed at a random moment after its first acknowledged put:
            # on a busy machine (other test workers, other jobs) a writer to S3 may need longer
            # than the whole window to start and put once, and no trial would acknowledge a put
            deadline = time.monotonic() + 60
            while not (log.exists() and log.stat().st_size) and time.monotonic() < deadline:
                time.sleep(0.005)
        time.sleep(rng.uniform(0.01, 0.25 if backend.kind == "file" else 0.5))
        os.kill(pid, signal.SIGKILL)
        [status] = zygote.wait()
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, \
            f"writer ended by itself ({status}): {zygote.log_tail()}"

        objects = backend.raw_files("objects")
        bad_names = [p for p in objects if not OBJECT_PATH_RE.search(p)]
        assert bad_names == [], f"trial {trial}: non-object files under objects/: {bad_names}"
        done = set(log.read_text().split()) if log.exists() else set()
        acknowledged |= done
        present = _objects(store)
        assert done <= present, f"trial {trial}: acknowledged puts missing: {done - present}"
        store.list_refs()  # every ref that exists parses (refs are written atomically too)
        interrupted_writes += bool(set(backend.raw_files("tmp")) - tmp_before)

    print(f"\n{backend.kind}: {KILL_TRIALS} writers killed, {len(acknowledged)} puts acknowledged, "
          f"{interrupted_writes} kills left a partial temporary file")
    report = store.verify()
    assert report.corrupt == [], f"objects that do not hash to their name: {report.corrupt}"
    assert report.dangling == [] and report.checked >= len(acknowledged) > 0
    if backend.kind == "file":
        assert interrupted_writes > 0, "no kill landed during a write: the test proves nothing"
    # The debris of killed writers is only ever temporary files, which gc collects.
    leftovers = backend.raw_files("tmp")
    gc = store.gc(grace_s=0)
    assert gc.tmp_deleted == len(leftovers) and backend.raw_files("tmp") == []
    assert store.verify().ok


@pytest.mark.parametrize("backend", ["file", "s3"], indirect=True)
def test_processes_writing_the_same_content(backend, zygote, tmp_path):
    store = backend.store
    size, seed = 6 * CHUNK_BYTES // 4 + 17, 99  # 12 MiB and a bit
    data = random.Random(seed).randbytes(size)
    src = tmp_path / "src.bin"
    src.write_bytes(data)
    expected = digest_bytes(data)
    del data
    for rnd in range(2):
        modes = ["stream", "stream", "file", "bytes"]
        start_at = time.time() + 0.4
        jobs = [{"kind": "same_content", "url": store.url, "seed": seed, "size": size,
                 "chunk": 1 << 20, "mode": m, "src": str(src), "start_at": start_at,
                 "out": str(tmp_path / f"out-{rnd}-{i}"), "env": _job_env(backend)}
                for i, m in enumerate(modes)]
        zygote.start(jobs)
        statuses = zygote.wait()
        assert statuses == [0] * len(jobs), zygote.log_tail()
        assert {(tmp_path / f"out-{rnd}-{i}").read_text() for i in range(len(jobs))} == {expected}
        assert _objects(store) == {expected}
        assert store.verify().ok and backend.raw_files("tmp") == []
        # The second round races against the object the first one left.


# ---------------------------------------------------------------------------------------------
# Digests and URLs
# ---------------------------------------------------------------------------------------------


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork only")
def test_hashing_in_a_forked_child_does_not_hang():
    """BLAKE3's threads live in a process-wide pool that a forked child does not inherit: a
    child of a process that hashed with threads (multiprocessing's fork, DataLoader workers)
    must still hash, on one thread."""
    data = os.urandom(16 << 20)
    parent = digest_bytes(data)  # large: multi-threaded, starts the pool in this process
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.write(w, (digest_bytes(data) + StreamingDigest().digest).encode())
        finally:
            os._exit(0)
    os.close(w)
    deadline = time.monotonic() + 30
    while not os.waitpid(pid, os.WNOHANG)[0]:
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            pytest.fail("hashing in a forked child hung (BLAKE3 thread pool inherited by fork)")
        time.sleep(0.02)
    with os.fdopen(r, "rb") as f:
        assert f.read().decode().startswith(parent)


def test_digest_helpers(tmp_path):
    data = os.urandom(CHUNK_BYTES + 5)
    p = tmp_path / "f"
    p.write_bytes(data)
    d = digest_bytes(data)
    assert re.fullmatch(r"blake3:[0-9a-f]{64}", d)
    assert digest_file(p) == (d, len(data))
    s = StreamingDigest()
    for i in range(0, len(data), 1000_003):
        s.update(memoryview(data)[i:i + 1000_003])
    assert (s.digest, s.size) == (d, len(data))
    # The BLAKE3 of the empty input, from the specification's test vectors.
    assert digest_bytes(b"") == "blake3:af1349b9f5f9a1a6a0404dea36dcc9499bcb25c9adc112b7cc9a93cae41f3262"


def test_store_urls(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    a = ArtifactStore("rel/store")
    assert a.url == "file://" + str((tmp_path / "rel" / "store").resolve())
    ref = a.put_bytes(b"same store, three spellings")
    assert ArtifactStore(a.url + "/").get_bytes(ref) == b"same store, three spellings"
    assert ArtifactStore(str(tmp_path / "rel" / "store")).exists(ref)
    assert normalize_store_url("s3://bucket/prefix/") == "s3://bucket/prefix"
    monkeypatch.setenv("VOLCAP_STORE", a.url)
    assert open_store().exists(ref) and open_store(str(tmp_path / "other")).url.endswith("/other")


def test_tree_with_a_file_that_is_also_a_folder_is_refused():
    from volcap_core.store import InvalidTreeError, TreeEntry, encode_tree

    e = TreeEntry("blake3:" + "0" * 64, 1)
    with pytest.raises(InvalidTreeError, match="both a file and a folder"):
        encode_tree({"a": e, "a-b": e, "a/b": e})
