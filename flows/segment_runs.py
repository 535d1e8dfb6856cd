"""The segment fan-out: train many Poly4DGS segments at once, on GPU workers or in this process.

One concept for every flow that trains several segments of a capture: the production's
``train-segment`` step (its Scene Rig segments) and the facerig_pairs flow (the Face Rig HQ and
LQ models of each sub-sequence). A :class:`SegmentJob` is the inputs of one ``train-segment``
task run; :func:`train_segments` trains a list of them at once and returns their SegmentModel
refs in order, by one of two ways (:func:`segment_runs_mode` chooses from ``segment_runs``):

    local       Prefect's map of the ``train-segment`` task in this process (its thread pool)
    deployment  one ``segment-run`` task per job, each a run of the ``train-segment`` deployment
                (``train_segment_flow`` on the ``gpu`` pool); ``auto`` picks it when the Prefect
                API this process talks to has that deployment, else local

Either way the task is the same cached ``train-segment`` task with the same inputs, so a job has
one cache key wherever it trains and a rerun finds it, whichever way trained it.

Segment runs across machines (``docs/operations.md``): ``run_deployment`` with ``timeout=None``
and an idempotency key made of the segment's cache key and the attempt number, so a doubled or
retried trigger never starts the same training twice; a run that ends Crashed (its worker died;
the zombie automation marks it) is submitted again, up to ``max_attempts``, and resumes from the
segment's last checkpoint in the store. ``train_segment_flow`` holds one ``gpu-slots`` slot while
it trains.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from prefect import flow, get_run_logger, task, unmapped
from prefect.cache_policies import NO_CACHE

from flows.cancellation import stop_flow_run_on_signal
from flows.store_credentials import store_credentials_from_block
from tasks.contract import cached_output, task_identity
from tasks.reconstruct import train_segment_task
from volcap_core.records import ArtifactRef
from volcap_core.splat.train import TrainConfig

#: The ``train-segment`` deployment (deploy/prefect.yaml) as Prefect names it: flow name / deployment name.
SEGMENT_DEPLOYMENT = "train-segment-flow/train-segment"
#: The global concurrency limit with one slot per GPU (deploy/setup-pool.sh creates it).
GPU_SLOTS = "gpu-slots"
#: A slot is a lease the holder renews; a dead holder's slot frees itself after this many seconds.
GPU_SLOT_LEASE_S = 120.0
SegmentRuns = Literal["auto", "local", "deployment"]


@dataclass(frozen=True)
class SegmentJob:
    """The inputs of one ``train-segment`` task run: a capture's frames ``[first, end)`` trained to
    ``config`` (its Gaussian budget, held-out cameras) from ``points``."""

    capture: ArtifactRef
    calibration: ArtifactRef
    points: ArtifactRef
    frames: tuple[int, int]
    config: TrainConfig
    seed: int = 0

    def task_inputs(self) -> dict[str, Any]:
        return {"capture": self.capture, "calibration": self.calibration, "points": self.points,
                "frames": list(self.frames), "config": self.config, "seed": self.seed}

    def deployment_parameters(self, store: str) -> dict[str, Any]:
        return {"store": store, "capture": self.capture.model_dump(mode="json"),
                "calibration": self.calibration.model_dump(mode="json"),
                "points": self.points.model_dump(mode="json"), "frames": list(self.frames),
                "config": self.config.model_dump(mode="json"), "seed": self.seed}


def segment_runs_mode(requested: SegmentRuns) -> Literal["local", "deployment"]:
    """``auto``: the deployment when the Prefect API this process talks to has it, else local."""
    if requested == "local":
        return "local"
    from prefect.client.orchestration import get_client
    from prefect.exceptions import ObjectNotFound
    from prefect.settings import PREFECT_API_URL

    if requested == "auto" and not PREFECT_API_URL.value():
        return "local"
    try:
        with get_client(sync_client=True) as client:
            client.read_deployment_by_name(SEGMENT_DEPLOYMENT)
    except ObjectNotFound:
        if requested == "deployment":
            raise ValueError(f"segment_runs='deployment' but the Prefect server at {PREFECT_API_URL.value()} "
                             f"has no deployment {SEGMENT_DEPLOYMENT!r}: run `env -u VOLCAP_HOME prefect deploy --all "
                             "--prefect-file deploy/prefect.yaml` (docs/operations.md)") from None
        return "local"
    return "deployment"


@task(name="segment-run", cache_policy=NO_CACHE, persist_result=False)
def run_segment_deployment(store: str, job: SegmentJob, max_attempts: int = 3,
                           poll_interval_s: float = 5.0) -> ArtifactRef:
    """Train one segment as a run of the ``train-segment`` deployment; its SegmentModel ref.

    Already cached: no run. Otherwise one run per attempt, idempotency key ``<cache key>/attempt-N``
    (a rerun of this production finds the same runs instead of starting new ones). Crashed (the
    worker died): the next attempt, which resumes from the segment's checkpoint. Failed or
    Cancelled: an error naming the run.
    """
    from prefect.deployments import run_deployment

    log = get_run_logger()
    a, b = job.frames
    key, ref = cached_output(train_segment_task, store, **job.task_inputs())
    if ref is not None:
        log.info("segment [%d, %d): cached", a, b)
        return ref
    for attempt in range(max_attempts):
        run = run_deployment(SEGMENT_DEPLOYMENT, parameters=job.deployment_parameters(store), timeout=None,
                             poll_interval=poll_interval_s, idempotency_key=f"{key}/attempt-{attempt}",
                             flow_run_name=f"segment-{a:06d}-{b:06d}-attempt-{attempt}",
                             tags=["volcap", "segment"])
        state = run.state
        if state is not None and state.is_completed():
            break
        if state is not None and state.is_crashed():
            log.warning("segment [%d, %d): run %s crashed (%s); submitting attempt %d of %d", a, b, run.name,
                        state.message, attempt + 2, max_attempts)
            continue
        raise RuntimeError(f"segment [{a}, {b}): run {run.name} ({run.id}) ended "
                           f"{state.name if state else 'without a state'}: {state.message if state else ''}")
    else:
        raise RuntimeError(f"segment [{a}, {b}): {max_attempts} runs crashed; see the train-segment runs "
                           f"with idempotency keys {key}/attempt-*")
    _, ref = cached_output(train_segment_task, store, **job.task_inputs())
    if ref is None:
        raise RuntimeError(f"segment [{a}, {b}): run {run.name} completed but its result is not in store "
                           f"{store} under key {key}: do the workers use this store URL, and the same volcap "
                           f"release and libraries as this coordinator ({task_identity(train_segment_task)})? "
                           "(docs/tasks.md, 'What is not in a key')")
    return ref


@flow(persist_result=False)
def train_segment_flow(store: str, capture: dict, calibration: dict, points: dict, frames: list[int],
                       config: dict, seed: int = 0) -> str:
    """One segment on one GPU worker: hold a ``gpu-slots`` slot and run the ``train-segment`` task
    (which resumes from the segment's last checkpoint in the store). Returns the SegmentModel digest."""
    from prefect.concurrency.sync import concurrency

    stop_flow_run_on_signal()  # a cancel (the UI's, or its production's) ends the training within seconds
    store_credentials_from_block()
    job = SegmentJob(capture=ArtifactRef.model_validate(capture), calibration=ArtifactRef.model_validate(calibration),
                     points=ArtifactRef.model_validate(points), frames=(frames[0], frames[1]),
                     config=TrainConfig.model_validate(config), seed=seed)
    _, ref = cached_output(train_segment_task, store, **job.task_inputs())
    if ref is None:
        with concurrency(GPU_SLOTS, occupy=1, strict=True, lease_duration=GPU_SLOT_LEASE_S):
            ref = train_segment_task(store, **job.task_inputs())
    return ref.digest


def train_segments(store: str, jobs: list[SegmentJob], mode: Literal["local", "deployment"],
                   max_attempts: int, poll_interval_s: float) -> list[ArtifactRef]:
    """Every segment at once; SegmentModel refs in the order of ``jobs``."""
    if not jobs:
        return []
    if mode == "deployment":
        futures = run_segment_deployment.map(unmapped(store), jobs, unmapped(max_attempts),
                                             unmapped(poll_interval_s))
    else:
        futures = train_segment_task.map(unmapped(store), [j.capture for j in jobs],
                                         [j.calibration for j in jobs], [j.points for j in jobs],
                                         [list(j.frames) for j in jobs], [j.config for j in jobs],
                                         [j.seed for j in jobs])
    return [f.result() for f in futures]


__all__ = ["GPU_SLOTS", "GPU_SLOT_LEASE_S", "SEGMENT_DEPLOYMENT", "SegmentJob", "SegmentRuns", "run_segment_deployment",
           "segment_runs_mode", "train_segment_flow", "train_segments"]
