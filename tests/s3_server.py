"""A real S3-compatible server on loopback for tests: moto's server mode, as a subprocess.

Use it from any test file (there is deliberately no conftest hook: import the fixture)::

    from tests.s3_server import s3_endpoint  # noqa: F401  (pytest finds the fixture by name)

    def test_something(s3_endpoint):
        store = ArtifactStore(s3_endpoint.store_url())     # s3://<bucket>/<unique prefix>

``s3_endpoint`` is session-scoped: one server per pytest session, started on first use only.
While it lives, ``os.environ`` carries ``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``,
``AWS_SECRET_ACCESS_KEY`` and ``AWS_DEFAULT_REGION`` (so a bare ``s3://`` URL works, in this
process and in every subprocess it starts, exactly as in production); they are restored after.

The server is a separate process (``python -m moto.server -H 127.0.0.1 -p PORT``), so tests that
``kill -9`` writer processes never share a process with it; it is always killed at teardown, even
when a test or the start itself fails. Outside pytest, :func:`moto_s3_server` is a plain context
manager.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

os.environ["DO_NOT_TRACK"] = "1"

#: Environment variables the fixture owns while the server lives (others that could redirect or
#: re-credential boto are removed for the duration: a developer's profile must not leak in).
_OWNED_VARS = (
    "AWS_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3", "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY",
    "AWS_SESSION_TOKEN", "AWS_SECURITY_TOKEN", "AWS_DEFAULT_REGION", "AWS_REGION", "AWS_PROFILE",
    "AWS_CONFIG_FILE", "AWS_SHARED_CREDENTIALS_FILE", "AWS_IGNORE_CONFIGURED_ENDPOINT_URLS",
    "NO_PROXY", "no_proxy", "DO_NOT_TRACK",
)


@dataclass
class S3Endpoint:
    """A running moto S3 server with one bucket."""

    url: str  # http://127.0.0.1:PORT
    bucket: str
    env: dict[str, str]  # what a client (or a subprocess) needs to reach it
    process: subprocess.Popen = field(repr=False)
    log_path: Path = field(repr=False)

    def store_url(self, prefix: str | None = None) -> str:
        """``s3://<bucket>/<prefix>``; a fresh unique prefix when none is given."""
        return f"s3://{self.bucket}/{prefix or 'volcap-' + uuid.uuid4().hex[:12]}"

    def client(self):
        """A boto3 S3 client talking to the server directly (bypasses fsspec and its caches)."""
        import boto3

        return boto3.client(
            "s3", endpoint_url=self.url, region_name=self.env["AWS_DEFAULT_REGION"],
            aws_access_key_id=self.env["AWS_ACCESS_KEY_ID"],
            aws_secret_access_key=self.env["AWS_SECRET_ACCESS_KEY"],
        )

    def log_tail(self, n: int = 2000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-n:]
        except OSError:
            return ""


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_healthy(url: str, proc: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # never via a proxy
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"moto server exited with status {proc.returncode} during start")
        try:
            with opener.open(f"{url}/moto-api/data.json", timeout=2) as resp:
                if resp.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, OSError):
            pass
        if time.monotonic() > deadline:
            raise TimeoutError(f"moto server at {url} not healthy after {timeout:.0f} s")
        time.sleep(0.1)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()  # SIGKILL: nothing to flush, and a wedged server must not hang teardown
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        pass


@contextlib.contextmanager
def moto_s3_server(bucket: str = "volcap-test", region: str = "us-east-1",
                   start_timeout: float = 60.0, attempts: int = 3) -> Iterator[S3Endpoint]:
    """Start ``python -m moto.server`` on 127.0.0.1 (free port), create ``bucket``, yield, kill.

    Does not touch ``os.environ``; :func:`s3_endpoint` does. Retries on another port when the
    chosen one was taken between probing and binding.
    """
    log_dir = Path(tempfile.mkdtemp(prefix="volcap-moto-"))
    last_error: Exception | None = None
    for attempt in range(attempts):
        port = _free_port()
        url = f"http://127.0.0.1:{port}"
        log_path = log_dir / f"moto-{port}.log"
        child_env = {k: v for k, v in os.environ.items() if k not in _OWNED_VARS}
        child_env.update(DO_NOT_TRACK="1", NO_PROXY="127.0.0.1,localhost", no_proxy="127.0.0.1,localhost")
        with open(log_path, "wb") as log:
            proc = subprocess.Popen(
                [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=child_env,
                start_new_session=True,  # a Ctrl-C in the terminal is the test runner's, not its
            )
        try:
            try:
                _wait_healthy(url, proc, start_timeout)
            except (RuntimeError, TimeoutError) as exc:
                last_error = exc
                _stop(proc)
                continue
            env = {
                "AWS_ENDPOINT_URL": url,
                "AWS_ACCESS_KEY_ID": "testing",
                "AWS_SECRET_ACCESS_KEY": "testing",
                "AWS_DEFAULT_REGION": region,
                "NO_PROXY": "127.0.0.1,localhost",
                "no_proxy": "127.0.0.1,localhost",
                "DO_NOT_TRACK": "1",
            }
            endpoint = S3Endpoint(url=url, bucket=bucket, env=env, process=proc, log_path=log_path)
            endpoint.client().create_bucket(Bucket=bucket)
            yield endpoint
            return
        finally:
            _stop(proc)
    tail = (log_dir / f"moto-{port}.log").read_text(errors="replace")[-2000:]
    raise RuntimeError(f"could not start moto's S3 server after {attempts} attempts: {last_error}\n{tail}")


def _clear_s3fs_instances() -> None:
    """s3fs caches filesystem instances (with their endpoint and credentials): start clean."""
    try:
        import s3fs
    except ImportError:
        return
    s3fs.S3FileSystem.clear_instance_cache()


@pytest.fixture(scope="session")
def s3_endpoint() -> Iterator[S3Endpoint]:
    """A moto S3 server for the session, with its env vars exported in ``os.environ``."""
    pytest.importorskip("moto.server", reason="moto[server] is needed for the s3:// backend")
    pytest.importorskip("s3fs")
    saved = {k: os.environ.get(k) for k in _OWNED_VARS}
    with moto_s3_server() as endpoint:
        for k in _OWNED_VARS:
            os.environ.pop(k, None)
        os.environ.update(endpoint.env)
        _clear_s3fs_instances()
        try:
            yield endpoint
        finally:
            _clear_s3fs_instances()
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
            os.environ["DO_NOT_TRACK"] = "1"
