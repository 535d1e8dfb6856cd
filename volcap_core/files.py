"""Writing local files so that readers and crashes only ever see the old content or the new.

:func:`open_atomic` (and :func:`write_atomic` for bytes in hand) is the library's one way to do it (EXR frames, contact sheets, synthetic
capture files, CLI outputs, the artifact store on a local disk).
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

__all__ = ["open_atomic", "write_atomic"]


def write_atomic(path: str | os.PathLike[str], data: bytes, *,
                 tmp_dir: str | os.PathLike[str] | None = None) -> None:
    """Replace the local file ``path`` by ``data`` atomically and durably (:func:`open_atomic`)."""
    with open_atomic(path, tmp_dir=tmp_dir) as f:
        f.write(data)


@contextmanager
def open_atomic(path: str | os.PathLike[str], *, tmp_dir: str | os.PathLike[str] | None = None
                ) -> Iterator[BinaryIO]:
    """A binary file to write that replaces the local file ``path`` atomically and durably when
    the ``with`` block ends without an exception (large outputs written in chunks).

    The bytes go to a new temporary file in ``tmp_dir`` (default: ``path``'s own folder), are
    flushed and fsynced, the file is renamed over ``path`` with :func:`os.replace`, and ``path``'s
    folder is fsynced where the platform allows it, so the rename itself survives a power cut.
    A failure at any step (an exception in the block, a full disk, an I/O error reported by fsync,
    a refused rename, an interrupt) leaves ``path`` absent or with its previous content and removes
    the temporary file; only ``kill -9`` or a crash can leave one behind, named
    ``.<name>.<random>.tmp``.

    The file gets the permissions of any newly created file (0666 less the umask), also when it
    replaces an existing one. ``tmp_dir`` must be on the same filesystem as ``path`` (a rename
    across filesystems is not atomic): the artifact store passes its ``tmp/`` folder so that a
    killed writer's debris is where its garbage collection looks. Parent folders are not created.
    """
    path = Path(path)
    tmp = Path(path.parent if tmp_dir is None else tmp_dir) / f".{path.name}.{uuid.uuid4().hex}.tmp"
    # Not tempfile.mkstemp: its files are private (0600), and other users of a shared store (or of
    # a rendered frame) must be able to read the result like any file written with open().
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_dir(path.parent)


def _fsync_dir(folder: Path) -> None:
    """Persist a folder's entries (the rename into it). Not possible everywhere: Windows cannot
    open a folder and some filesystems refuse fsync on one; the file's content is durable anyway."""
    try:
        dir_fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)
