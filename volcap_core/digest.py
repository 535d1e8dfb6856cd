"""BLAKE3 digests (``blake3:<64 hex>``), computed in chunks so no file is ever read whole."""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO

import blake3

CHUNK_BYTES = 8 << 20  # 8 MiB: large enough for BLAKE3's SIMD/threads, small enough for memory

#: The process that may use BLAKE3's threads. They live in one process-wide pool, created on first
#: use; a forked child inherits the pool's state but not its threads, and a multi-threaded hash
#: there waits forever (multiprocessing's default fork start on Linux, DataLoader workers...).
#: A child forked after its parent hashed with threads therefore hashes on one thread.
_threads_pid: int | None = None


def _threads_allowed() -> bool:
    global _threads_pid
    pid = os.getpid()
    if _threads_pid is None:
        _threads_pid = pid
    return _threads_pid == pid


def _hasher(size_hint: int = 0) -> blake3.blake3:
    # BLAKE3 can spread one large input over threads; below ~1 MiB the thread start costs more.
    threads = size_hint >= (1 << 20) and _threads_allowed()
    return blake3.blake3(max_threads=blake3.blake3.AUTO if threads else 1)


def digest_bytes(data: bytes | memoryview) -> str:
    h = _hasher(len(data))
    h.update(data)
    return "blake3:" + h.hexdigest()


def digest_stream(stream: BinaryIO, chunk_bytes: int = CHUNK_BYTES) -> tuple[str, int]:
    """Digest and byte count of everything left in ``stream``."""
    h = _hasher(chunk_bytes)
    size = 0
    while chunk := stream.read(chunk_bytes):
        h.update(chunk)
        size += len(chunk)
    return "blake3:" + h.hexdigest(), size


def digest_file(path: str | Path) -> tuple[str, int]:
    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size < CHUNK_BYTES:
            # One read, and threads only where they pay (_hasher): a demo-size frame or a mask
            # hashed in half the time of the chunked loop, whose hasher and 8 MiB read buffer are
            # sized for large files. A file growing meanwhile is still read to its end.
            data = f.read()
            h = _hasher(len(data))
            h.update(data)
            return "blake3:" + h.hexdigest(), len(data)
        return digest_stream(f)


class StreamingDigest:
    """Hash bytes as they pass through a copy loop (``update`` then ``digest``)."""

    def __init__(self) -> None:
        self._h = _hasher(CHUNK_BYTES)
        self.size = 0

    def update(self, chunk: bytes | memoryview) -> None:
        self._h.update(chunk)
        self.size += len(chunk)

    @property
    def digest(self) -> str:
        return "blake3:" + self._h.hexdigest()
