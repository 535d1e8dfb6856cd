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
# the compiled kernels' OpenMP threads sleep between kernels instead of spinning on a core the
# other pytest-xdist worker needs (flows.runtime.reproducible_cpu_defaults)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# Under pytest-xdist (`make test`: one worker per core) each worker's compiled kernels keep to one
# thread: two workers each on every core slowed the other worker's tests (the lego calibration
# fixture 299 s -> 357 s). The kernels' thread-count tests then run in a process of their own on two
# threads (tests/splat/test_composite_numba.py).
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
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

    # generous: on a shared machine under load the server (a Python process importing Prefect's
    # app) has taken over 120 s to answer, and every test of the worker then errors
    with prefect_test_harness(server_startup_timeout=600):
        yield


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real-data checks need {SHARED_DATA} (absent in a clone without ../shared)")
    return SHARED_DATA


#: The longest files of a full run (``make test``, docs/benchmarks.md "Test suite"), longest
#: first, relative to the repository. Whole files go to the two workers in collection order, so a
#: long file collected late (the lego's, ``test_r...``) ran while the other worker had finished:
#: started longest first, the workers end together. A file not listed keeps its place after these.
LONGEST_FILES = (
    "tests/test_real_capture_without_lidar.py",
    "tests/production/test_production_cluster.py",
    "tests/enhance/test_enhance_quality.py",
    "tests/test_calibrate_flow.py",
    "tests/production/test_ui_cancel.py",
    "tests/test_cli_cancel.py",
    "tests/enhance/test_splat_pairs.py",
    "tests/production/test_splat_pairs_production.py",
    "tests/production/test_production_flow.py",
    "tests/test_distorted_capture.py",
    "tests/test_demo_closeup.py",
    "tests/test_reconstruct.py",
)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (``make test``): the :data:`LONGEST_FILES` first, longest first, then
    the other files with slow tests, then the rest; each file's tests together and in their
    order. Workers take whole files (``--dist loadfile``: a module's fixtures are made once) in
    this order, so the long files start early and the workers end together; run in one process,
    the suite keeps its usual order."""
    if not hasattr(config, "workerinput"):
        return
    rank = {REPO / name: i for i, name in enumerate(LONGEST_FILES)}
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    # stable: files of the same rank keep their order
    items.sort(key=lambda item: (rank.get(item.path, len(rank)), item.path not in slow_files))
