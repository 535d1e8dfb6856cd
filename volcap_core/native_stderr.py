"""What native libraries write to stderr, kept out of a command's error output.

OpenEXR (through OpenImageIO) prints its own diagnostics for a damaged file, one line per failed
chunk, and nanobind prints leak reports while the interpreter shuts down. They write to file
descriptor 2 from C/C++, so replacing ``sys.stderr`` does not catch them: only moving fd 2 does.

:class:`NativeStderr` does that for a whole process: fd 2 is pointed at an anonymous temporary
file, and Python's ``sys.stderr`` is rebound to a duplicate of the original fd 2, so everything
Python writes (logging, tracebacks, ``typer.echo(err=True)``) still reaches the terminal while
whatever C/C++ code writes lands in the file. Being process-wide it needs no lock and is safe with
threads (Prefect runs tasks in worker threads): a capture around each native call could not be,
fd 2 being one per process, and would swallow other threads' output written meanwhile. The
captured text is read back with :meth:`NativeStderr.read_new` (``pread``: the writers' shared file
offset is never moved) and folded into an error message with :meth:`NativeStderr.detail_for`.

Bindings that *print* through Python (to ``sys.stdout``) are caught per thread by
:func:`binding_prints`.

Child processes started meanwhile inherit fd 2 too (Prefect's temporary API server): their stderr
lands in the same file; a file rather than a pipe, so no writer ever blocks or gets SIGPIPE, even
after this process has stopped reading or exited. A crash's own message (a C++ ``terminate``)
would land there as well: :meth:`start` points :mod:`faulthandler` (when enabled) at the real
stderr so a Python traceback of a crash still shows.
"""

from __future__ import annotations

import contextlib
import faulthandler
import io
import os
import sys
import tempfile
import threading
from typing import Iterator, TextIO

#: At most this much captured text is read back at once (the newest part).
MAX_READ_BYTES = 1 << 20


class NativeStderr:
    """fd 2 redirected to a temporary file for this process; Python's ``sys.stderr`` unaffected."""

    def __init__(self) -> None:
        self._file: io.BufferedRandom | None = None
        self._saved_fd: int | None = None
        self._python_stderr: TextIO | None = None
        self._previous_stderr: TextIO | None = None
        self._offset = 0

    @property
    def active(self) -> bool:
        return self._saved_fd is not None

    def start(self) -> "NativeStderr":
        if self.active:
            return self
        for stream in (sys.stderr, sys.__stderr__):
            try:
                if stream is not None:
                    stream.flush()
            except (OSError, ValueError):
                pass
        saved = os.dup(2)
        os.set_inheritable(saved, False)
        self._file = tempfile.TemporaryFile(prefix="volcap-native-stderr-")
        encoding = getattr(sys.stderr, "encoding", None) or "utf-8"
        self._python_stderr = io.TextIOWrapper(io.FileIO(saved, "w", closefd=False), encoding=encoding,
                                               errors="backslashreplace", line_buffering=True)
        os.dup2(self._file.fileno(), 2)
        self._saved_fd = saved
        self._previous_stderr = sys.stderr
        sys.stderr = self._python_stderr
        if faulthandler.is_enabled():
            faulthandler.enable(file=self._python_stderr)
        return self

    def read_new(self) -> str:
        """The text native code wrote to fd 2 since the previous call (at most the newest 1 MiB)."""
        if self._file is None:
            return ""
        fd = self._file.fileno()
        size = os.fstat(fd).st_size
        start = max(self._offset, size - MAX_READ_BYTES)
        data = os.pread(fd, size - start, start) if size > start else b""
        self._offset = size
        return data.decode("utf-8", errors="replace")

    def stop(self) -> None:
        """fd 2 back to the original stream (before an exec, or to show shutdown messages)."""
        if not self.active:
            return
        assert self._saved_fd is not None
        try:
            self._python_stderr.flush()  # type: ignore[union-attr]
        except (OSError, ValueError):
            pass
        os.dup2(self._saved_fd, 2)
        if sys.stderr is self._python_stderr:
            sys.stderr = self._previous_stderr
        if faulthandler.is_enabled():
            faulthandler.enable(file=sys.stderr)
        self._saved_fd = None  # the duplicate stays open: handlers may still hold the wrapper

    def __enter__(self) -> "NativeStderr":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def detail_for(message: str, captured: str, limit: int = 200) -> str | None:
    """The first captured line that names a file named in ``message``, without that name.

    OpenEXR prefixes its lines with the file's path (``/c/C0/000001.exr: (EXR_ERR_CORRUPT_CHUNK)
    Unable to decompress ...``): that line, with the path dropped, is what an error message about
    that file gains. None when no captured line names such a file.
    """
    for line in captured.splitlines():
        head, sep, rest = line.partition(": ")
        head, rest = head.strip(), " ".join(rest.split())
        if sep and rest and len(head) > 1 and head in message and rest not in message:
            return rest if len(rest) <= limit else rest[: limit - 1] + "…"
    return None


class _ThreadRoutedStdout(io.TextIOBase):
    """``sys.stdout`` while some thread captures: that thread's writes go to its buffer, every
    other thread's to the stream that was ``sys.stdout`` before."""

    def __init__(self, original: TextIO) -> None:
        self.original = original
        self.local = threading.local()

    def write(self, text: str) -> int:
        buffer = getattr(self.local, "buffer", None)
        return (buffer or self.original).write(text)

    def flush(self) -> None:
        if getattr(self.local, "buffer", None) is None:
            self.original.flush()


_ROUTER_LOCK = threading.Lock()
_router: _ThreadRoutedStdout | None = None
_router_users = 0


@contextlib.contextmanager
def binding_prints() -> Iterator[io.StringIO]:
    """What a native binding *prints* (to Python's ``sys.stdout``) in this thread, captured.

    The OpenEXR bindings print a failed decode ("Warning: Exception raised reading pixel data ...")
    instead of raising. ``contextlib.redirect_stdout`` is not safe with threads (Prefect decodes in
    several): two overlapping captures restore each other's buffer and silence ``sys.stdout`` for
    good. Here the first capture installs a router, which sends each capturing thread's writes to
    its own buffer and everything else to the real stream, and the last one removes it.
    """
    global _router, _router_users
    buffer = io.StringIO()
    with _ROUTER_LOCK:
        if _router_users == 0:
            _router = _ThreadRoutedStdout(sys.stdout)
            sys.stdout = _router
        _router_users += 1
        router = _router
    router.local.buffer = buffer
    try:
        yield buffer
    finally:
        router.local.buffer = None
        with _ROUTER_LOCK:
            _router_users -= 1
            if _router_users == 0:
                if sys.stdout is router:  # someone else may have rebound it meanwhile: leave theirs
                    sys.stdout = router.original
                _router = None
