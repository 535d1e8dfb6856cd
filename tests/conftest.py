"""Shared fixtures: an isolated Prefect API for the session, paths to the shared real data."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

# Before anything imports torch: one OpenMP/MKL thread, as the CLI does (bit-reproducible CPU
# training; see flows.runtime.reproducible_cpu_defaults).
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
# A throw-away Prefect home per test session: no state leaks between runs or into ~/.prefect.
# Under pytest-xdist every worker is a session of its own, started by the controller with the
# controller's environment: a worker that inherited the controller's throw-away home makes its
# own, or the workers would share one home (the SQLite database of every command's temporary
# API, Prefect's local result storage). A PREFECT_HOME set before pytest started is kept.
_THROWAWAY_HOME = "VOLCAP_TEST_THROWAWAY_PREFECT_HOME"
if "PREFECT_HOME" not in os.environ or (
        os.environ.get("PYTEST_XDIST_WORKER")
        and os.environ["PREFECT_HOME"] == os.environ.get(_THROWAWAY_HOME)):
    _worker = os.environ.get("PYTEST_XDIST_WORKER")
    _home = tempfile.mkdtemp(prefix=f"volcap-prefect-home-{_worker + '-' if _worker else ''}")
    os.environ["PREFECT_HOME"] = os.environ[_THROWAWAY_HOME] = _home
    atexit.register(shutil.rmtree, _home, ignore_errors=True)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def prefect_api():
    """One temporary Prefect server for the whole session (its start costs seconds)."""
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real-data checks need {SHARED_DATA} (absent in a clone without ../shared)")
    return SHARED_DATA


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (``make test``): the files with slow tests first, each file's tests
    together and in their order. Workers take whole files (``--dist loadfile``: a module's
    fixtures are made once) in this order, so the long files start early and the workers end
    together; run in one process, the suite keeps its usual order."""
    if not hasattr(config, "workerinput"):
        return
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow_files)  # stable: the rest keeps its order
