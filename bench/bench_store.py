"""Store throughput against a plain fsspec copy, and BLAKE3 hashing speed.

    python bench/bench_store.py [--size-mb 256] [--dir /fast/disk/tmp] [--repeat 3] [--no-memory]

What it measures, on one large file of random bytes (best of ``--repeat`` runs):

- ``put``: ``ArtifactStore.put_file`` (hash while copying in 8 MiB chunks, fsync, atomic rename)
  against fsspec's own copy of the same file into the same filesystem (``put_file``: no hashing,
  and on a local disk no fsync: the kernel's zero-copy path); ``put vs +fsync`` compares with
  that copy followed by an fsync, the durability the store gives;
- ``get``: ``ArtifactStore.get_file`` (copy out in chunks, verifying the digest, atomic rename)
  against fsspec's ``get_file``;
- BLAKE3 on bytes already in memory, on one thread and with ``AUTO`` threads, and
  ``digest_file`` (the chunked streaming path the store uses) on the source file.

``file://`` is the real case; ``memory://`` is printed for reference (it measures Python copies).
The source file is in the page cache after being written, so reads are memory-speed: the figures
are the store's CPU cost over a copy, not the disk's.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import blake3
import fsspec

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from volcap_core.digest import CHUNK_BYTES, digest_file  # noqa: E402
from volcap_core.store import ArtifactStore  # noqa: E402

MB = 1 << 20


def best_of(repeat: int, run: Callable[[], None], setup: Callable[[], None] | None = None) -> float:
    """Best wall time of ``run`` over ``repeat`` runs, ``setup`` untimed before each."""
    best = float("inf")
    for _ in range(repeat):
        if setup:
            setup()
        t = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - t)
    return best


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def make_source(path: Path, size: int) -> None:
    with open(path, "wb") as f:
        left = size
        while left:
            n = min(CHUNK_BYTES, left)
            f.write(os.urandom(n))
            left -= n


def bench_backend(kind: str, src: Path, work: Path, size: int, repeat: int) -> list[tuple]:
    rows = []
    if kind == "file":
        base = work / "stores"
        url_of = lambda: str(base / uuid.uuid4().hex)  # noqa: E731
        fs = fsspec.filesystem("file")
        plain_dst = str(work / "plain.bin")
    else:
        base = None
        url_of = lambda: f"memory://bench-{uuid.uuid4().hex}"  # noqa: E731
        fs = fsspec.filesystem("memory")
        plain_dst = f"/bench-plain-{uuid.uuid4().hex}/plain.bin"
    out = work / "out.bin"

    stores: list[ArtifactStore] = []

    def fresh_store() -> None:  # a put of present content is a no-op: each run gets a new store
        for s in stores:
            s.fs.rm(s.root, recursive=True)
        stores.clear()
        stores.append(ArtifactStore(url_of()))

    refs = []
    t_put = best_of(repeat, lambda: refs.append(stores[0].put_file(src)), fresh_store)
    store, ref = stores[0], refs[-1]

    def clear_plain() -> None:
        if fs.exists(plain_dst):
            fs.rm_file(plain_dst)

    t_put_plain = best_of(repeat, lambda: fs.put_file(str(src), plain_dst), clear_plain)
    rows.append((kind, "put", size / MB / t_put, size / MB / t_put_plain))
    if kind == "file":  # the store fsyncs before its rename; the same durability for the copy
        def put_and_fsync() -> None:
            fs.put_file(str(src), plain_dst)
            fd = os.open(plain_dst, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)

        t_put_sync = best_of(repeat, put_and_fsync, clear_plain)
        rows.append((kind, "put vs +fsync", size / MB / t_put, size / MB / t_put_sync))

    def clear_out() -> None:
        out.unlink(missing_ok=True)

    t_get = best_of(repeat, lambda: store.get_file(ref, out), clear_out)
    t_get_plain = best_of(repeat, lambda: fs.get_file(plain_dst, str(out)), clear_out)
    rows.append((kind, "get (verified)", size / MB / t_get, size / MB / t_get_plain))

    clear_out()
    clear_plain()
    for s in stores:
        s.fs.rm(s.root, recursive=True)
    if base is not None:
        shutil.rmtree(base, ignore_errors=True)
    return rows


def bench_hash(src: Path, size: int, repeat: int) -> list[tuple[str, float]]:
    n = min(size, 512 * MB)
    with open(src, "rb") as f:
        buf = f.read(n)  # the benchmark may hold its input; the store never does
    rows = []
    for label, threads in (("BLAKE3 in memory, 1 thread", 1), ("BLAKE3 in memory, AUTO threads", blake3.blake3.AUTO)):
        t = best_of(repeat, lambda: blake3.blake3(buf, max_threads=threads).hexdigest())
        rows.append((label, n / t / 1e9))
    del buf
    t = best_of(repeat, lambda: digest_file(src))
    rows.append((f"digest_file ({CHUNK_BYTES // MB} MiB chunks, page cache)", size / t / 1e9))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size-mb", type=int, default=256, help="size of the test file (default 256)")
    ap.add_argument("--dir", default=None, help="work directory (default: a temporary one)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure; the best is kept")
    ap.add_argument("--no-memory", action="store_true", help="skip the memory:// reference rows")
    args = ap.parse_args(argv)

    size = args.size_mb * MB
    work = Path(tempfile.mkdtemp(prefix="volcap-bench-", dir=args.dir))
    try:
        src = work / "src.bin"
        make_source(src, size)
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        print(f"machine: {cpu_name()}, {cpus} usable CPU(s); Python {platform.python_version()}, "
              f"blake3 {getattr(blake3, '__version__', '?')}, fsspec {fsspec.__version__}")
        print(f"file: {args.size_mb} MiB of random bytes in {work} (best of {args.repeat})\n")

        hash_rows = bench_hash(src, size, args.repeat)
        rows = bench_backend("file", src, work, size, args.repeat)
        if not args.no_memory:
            rows += bench_backend("memory", src, work, size, args.repeat)

        print(f"{'backend':<8} {'operation':<16} {'store MB/s':>11} {'fsspec MB/s':>12} {'store/fsspec':>13}")
        for kind, op, store_mbs, plain_mbs in rows:
            print(f"{kind:<8} {op:<16} {store_mbs:>11.0f} {plain_mbs:>12.0f} {store_mbs / plain_mbs:>13.2f}")
        print()
        for label, gbs in hash_rows:
            print(f"{label:<45} {gbs:>6.2f} GB/s")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
