"""``write_atomic`` and ``open_atomic``: the library's one way to replace a local file (old or new content, never torn)."""

from __future__ import annotations

import os
import stat

import pytest

from volcap_core import files
from volcap_core.files import write_atomic


def test_writes_and_replaces_with_ordinary_permissions(tmp_path):
    path = tmp_path / "frame.bin"
    write_atomic(path, b"first")
    write_atomic(str(path), b"second, longer")
    assert path.read_bytes() == b"second, longer"
    assert [p.name for p in tmp_path.iterdir()] == ["frame.bin"]
    plain = tmp_path / "plain"
    plain.write_bytes(b"")  # what open() gives a new file under this umask
    assert stat.S_IMODE(path.stat().st_mode) == stat.S_IMODE(plain.stat().st_mode)


@pytest.mark.parametrize("failing", ["fsync", "replace"])
def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch, failing):
    path = tmp_path / "calibration.json"
    write_atomic(path, b'{"version": 1}')
    calls = []

    def broken(*args):
        calls.append(args)
        raise OSError(5, "Input/output error")

    # fsync is where a write that did not reach the disk is reported; replace is the last step.
    monkeypatch.setattr(files.os, failing, broken)
    with pytest.raises(OSError, match="Input/output error"):
        write_atomic(path, b'{"version": 2, "half-written": true}')
    assert calls, f"os.{failing} was never reached"
    assert path.read_bytes() == b'{"version": 1}'
    assert [p.name for p in tmp_path.iterdir()] == ["calibration.json"]


def test_temporary_folder_holds_the_bytes_in_flight_only(tmp_path, monkeypatch):
    final_dir, tmp_dir = tmp_path / "objects", tmp_path / "tmp"
    final_dir.mkdir()
    tmp_dir.mkdir()
    seen = []
    real_replace = os.replace

    def replace(src, dst):
        seen.append(os.path.dirname(src))
        real_replace(src, dst)

    monkeypatch.setattr(files.os, "replace", replace)
    write_atomic(final_dir / "ab12", b"payload", tmp_dir=tmp_dir)
    assert seen == [str(tmp_dir)]
    assert (final_dir / "ab12").read_bytes() == b"payload"
    assert list(tmp_dir.iterdir()) == [] and [p.name for p in final_dir.iterdir()] == ["ab12"]


def test_missing_folder_is_an_error_not_created(tmp_path):
    with pytest.raises(FileNotFoundError):
        write_atomic(tmp_path / "no" / "such" / "file.bin", b"x")
    assert list(tmp_path.iterdir()) == []


def test_a_chunked_write_that_raises_midway_leaves_the_old_file(tmp_path):
    """``open_atomic``: an exception after some chunks (a digest mismatch, a lost connection) keeps
    the previous content; a block that ends normally replaces it."""
    path = tmp_path / "frame.exr"
    write_atomic(path, b"old frame")
    with pytest.raises(RuntimeError, match="connection lost"):
        with files.open_atomic(path) as out:
            out.write(b"new frame, first chunk")
            raise RuntimeError("connection lost")
    assert path.read_bytes() == b"old frame"
    assert [p.name for p in tmp_path.iterdir()] == ["frame.exr"]
    with files.open_atomic(path) as out:
        for chunk in (b"new ", b"frame"):
            out.write(chunk)
    assert path.read_bytes() == b"new frame"
