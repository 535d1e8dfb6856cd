"""Running flows and telling the coordinator what happened.

Every flow run ends with one line: tasks run, tasks cached, tasks failed, wall time. The counts
come from Prefect's own record of the run (the API), so they are what the UI shows.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any
from uuid import UUID


def quiet_prefect_defaults(log_level: str = "WARNING") -> None:
    """Offline-friendly Prefect settings, unless the user set them.

    The command line keeps Prefect's INFO logs (on stderr): one line per finished task run is the
    progress a coordinator watches.
    """
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", log_level)


def reproducible_cpu_defaults() -> None:
    """One CPU thread per process for torch's OpenMP/MKL pools, unless the user chose otherwise.

    Call before torch is imported. Measured: CPU training of the same segment from the same seed gave
    different Gaussians in 1 run of 4 with 2 threads, even with ``torch.set_num_threads(1)`` inside
    the task's worker thread; with ``OMP_NUM_THREADS=1`` for the process, 4 of 4 were bit-identical
    (resuming from a checkpoint relies on that). On the 2-core machines here one thread is also
    faster (two threads spin against each other). Set ``OMP_NUM_THREADS`` to trade this for speed.
    """
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")


@dataclass
class RunSummary:
    flow_run_id: str
    state: str
    tasks_run: int
    tasks_cached: int
    tasks_failed: int
    wall_s: float
    result: Any = None

    def line(self) -> str:
        return (f"{self.state.lower()}: {self.tasks_run} tasks run, {self.tasks_cached} cached, "
                f"{self.tasks_failed} failed, {self.wall_s:.1f} s wall")

    def counts(self) -> dict[str, Any]:
        return {"tasks_run": self.tasks_run, "tasks_cached": self.tasks_cached,
                "tasks_failed": self.tasks_failed, "wall_s": round(self.wall_s, 3),
                "flow_run_id": self.flow_run_id, "state": self.state}


def flow_run_family(flow_run_id: UUID | str) -> list[UUID]:
    """The flow run and its sub-flow runs, any depth (flow runs are created synchronously)."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterParentFlowRunId

    ids = [UUID(str(flow_run_id))]
    with get_client(sync_client=True) as client:
        frontier = list(ids)
        while frontier:
            children = client.read_flow_runs(
                flow_run_filter=FlowRunFilter(parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=frontier)))
            frontier = [c.id for c in children if c.id not in ids]
            ids.extend(frontier)
    return ids


def count_task_runs(flow_run_id: UUID | str) -> tuple[int, int, int]:
    """(run, cached, failed) volcap task runs of the flow run and its sub-flows, in this process."""
    from tasks.contract import tally_for

    counts = tally_for(flow_run_family(flow_run_id))
    return counts["run"], counts["cached"], counts["failed"]


def run_flow(flow: Any, **parameters: Any) -> RunSummary:
    """Run ``flow(**parameters)`` in this process; raise its exception after summarising it.

    The summary (with the exception's message) is attached as ``exc.run_summary``.
    """
    t0 = time.perf_counter()
    state = flow(**parameters, return_state=True)
    wall = time.perf_counter() - t0
    run, cached, failed = count_task_runs(state.state_details.flow_run_id)
    summary = RunSummary(str(state.state_details.flow_run_id), state.name, run, cached, failed, wall)
    if state.is_completed():
        summary.result = state.result()
        return summary
    try:
        state.result()
    except BaseException as exc:  # noqa: BLE001 - re-raised with the summary attached
        exc.run_summary = summary  # type: ignore[attr-defined]
        raise
    raise RuntimeError(f"flow ended in state {state.name}")
