"""The production flow: one production spec in, every artifact its shots need out.

It reads like the process it runs::

    plan      needed_steps(spec): only what the requested shots need
    ingest    each capture folder (cached: an unchanged folder is not converted again)
    calibrate static cameras once, tracking cameras per camera (none without tracking cameras)
    points    dense points for the frames of each needed segment (per frame, shared by overlaps)
    train     every needed segment at once: runs of the `train-segment` deployment on the GPU
              pool when a Prefect server has it, in-process task runs otherwise
    render    each shot over a performance of its segments: cropped RGBA half-float EXR frames
    enhance   only if a shot asks for it (``enhance: true``): face pairs per actor of those shots,
              their prompt embeddings, one detail enhancer trained on all their pairs, then each
              enhanced shot's frames in order (shots in parallel): ``docs/enhancer.md``

Every step is a cached volcap task (``docs/tasks.md``), so a rerun recomputes only what changed or
never finished. After each step a journal entry (``volcap_core.production.journal``) records what
it ran on, which is how ``volcap plan`` explains why a step is to run.

Segment runs across machines (``docs/operations.md``): ``run_deployment`` with ``timeout=None``
and an idempotency key made of the segment's cache key and the attempt number, so a doubled or
retried trigger never starts the same training twice; a run that ends Crashed (its worker died;
the zombie automation marks it) is submitted again, up to ``max_attempts``, and resumes from the
segment's last checkpoint in the store. ``train_segment_flow`` holds one ``gpu-slots`` slot while
it trains.
"""

from __future__ import annotations

from flows.runtime import reproducible_cpu_defaults

reproducible_cpu_defaults()  # before torch: workers import this module as their entrypoint

import os  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Literal  # noqa: E402

from prefect import flow, get_run_logger, task, unmapped  # noqa: E402
from prefect.cache_policies import NO_CACHE  # noqa: E402

from flows.calibrate import calibrate_capture, point_cloud_for_frames  # noqa: E402
from flows.ingest import ingest_flow  # noqa: E402
from tasks import calibrate as calibrate_tasks  # noqa: E402
from tasks.contract import cached_output, task_identity  # noqa: E402
from tasks.enhance import actor_prompt, enhance_shot, face_pairs, train_enhancer_task  # noqa: E402
from tasks.ingest import fingerprint_camera, ingest_camera, record_capture  # noqa: E402
from tasks.production import assemble_performance, render_shot  # noqa: E402
from tasks.reconstruct import train_segment_task  # noqa: E402
from volcap_core import reconstruction  # noqa: E402
from volcap_core.capture import Capture  # noqa: E402
from volcap_core.digest import digest_bytes  # noqa: E402
from volcap_core.production.journal import (compare_fingerprints, folder_listing_digest,  # noqa: E402
                                            read_entry, write_entry)
from volcap_core.production.spec import (CaptureInfo, ProductionSpec, Step,  # noqa: E402
                                         capture_info_from_folder, load_spec, needed_steps)
from volcap_core.records import ArtifactRef, canonical_json  # noqa: E402
from volcap_core.splat.train import TrainConfig  # noqa: E402
from volcap_core.store import ArtifactStore  # noqa: E402

SEGMENT_DEPLOYMENT = "train-segment-flow/train-segment"
#: The global concurrency limit with one slot per GPU (deploy/setup-pool.sh creates it).
GPU_SLOTS = "gpu-slots"
#: A slot is a lease the holder renews; a dead holder's slot frees itself after this many seconds.
GPU_SLOT_LEASE_S = 120.0
#: Steps of the enhancer half (Face Rig pairs, the diffusion detail enhancer; docs/enhancer.md).
ENHANCER_STEPS = ("face-pairs", "train-enhancer", "enhance-shot")
SegmentRuns = Literal["auto", "local", "deployment"]


# ---------------------------------------------------------------------------------------------
# Store credentials: the environment, or a Prefect Secret block
# ---------------------------------------------------------------------------------------------

#: Names a Prefect ``Secret`` block whose value is a JSON object of environment variables for the
#: store (``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_DEFAULT_REGION``, ``AWS_ENDPOINT_URL``).
STORE_SECRET_ENV = "VOLCAP_STORE_SECRET"
STORE_SECRET_KEYS = ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_DEFAULT_REGION",
                     "AWS_REGION", "AWS_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3")


def store_credentials_from_block() -> list[str]:
    """Put the store credentials of the Secret block named by ``$VOLCAP_STORE_SECRET`` into this
    process's environment (variables already set win). Returns the names set; [] without a block."""
    name = os.environ.get(STORE_SECRET_ENV)
    if not name:
        return []
    from prefect.blocks.system import Secret

    try:
        value = Secret.load(name).get()
    except ValueError as exc:
        raise ValueError(f"{STORE_SECRET_ENV}={name}: no such Secret block on the Prefect server ({exc})") from None
    if isinstance(value, str):
        import json

        try:
            value = json.loads(value)
        except ValueError:
            value = None
    if not isinstance(value, dict) or not all(isinstance(v, str) for v in value.values()):
        raise ValueError(f"Secret block {name!r} must hold a JSON object of strings, e.g. "
                         '{"AWS_ACCESS_KEY_ID": "...", "AWS_SECRET_ACCESS_KEY": "..."}')
    unknown = sorted(set(value) - set(STORE_SECRET_KEYS))
    if unknown:
        raise ValueError(f"Secret block {name!r}: unexpected keys {', '.join(unknown)} "
                         f"(allowed: {', '.join(STORE_SECRET_KEYS)})")
    applied = [k for k in value if k not in os.environ]
    for k in applied:
        os.environ[k] = value[k]
    return applied


# ---------------------------------------------------------------------------------------------
# The production: spec, store, capture facts, needed steps
# ---------------------------------------------------------------------------------------------


@dataclass
class Production:
    """A spec resolved against a store: what :func:`plan_production` and the flow work from."""

    spec: ProductionSpec
    spec_dir: Path
    store: str
    steps: list[Step]
    facts: dict[str, CaptureInfo] = field(default_factory=dict)

    def spec_path(self, path: str | None) -> Path | None:
        """A path written in the spec: relative paths are relative to the spec file, ``~`` expanded;
        None stays None."""
        if path is None:
            return None
        p = Path(path).expanduser()
        return p if p.is_absolute() else (self.spec_dir / p).resolve()

    def folder(self, capture: str) -> Path:
        """A folder capture's path (relative paths are relative to the spec file)."""
        return self.spec_path(self.spec.captures[capture].folder)

    def enhancer_weights(self) -> Path | None:
        """The quality preset's ``enhancer_weights`` (a local FLUX.1 directory), None when not set."""
        return self.spec_path(self.spec.quality_preset().enhancer_weights)

    def enhancer_flow_weights(self) -> Path | None:
        """The quality preset's ``enhancer_flow_weights`` (a local RAFT weights file), None when not set."""
        return self.spec_path(self.spec.quality_preset().enhancer_flow_weights)

    def check_enhancer(self, where: str | Path | None = None) -> None:
        """Before anything runs: an enhanced shot with the FLUX.1 architecture needs its weights
        directory, one with ``enhancer_flow`` RAFT its weights file and torchvision (``ValueError``
        naming the spec and the path otherwise)."""
        if not any(s.kind in ENHANCER_STEPS for s in self.steps):
            return
        from volcap_core.enhance.production import check_flux_directory

        where = where or self.spec.name
        q = self.spec.quality_preset()
        weights = self.enhancer_weights()
        if q.enhancer_architecture == "flux-dev" and weights is None:
            raise ValueError(f"{where}: enhanced shots with enhancer_architecture flux-dev need "
                             "quality.enhancer_weights: a local FLUX.1-dev directory (docs/enhancer.md), or "
                             "enhancer_architecture: tiny or small (CPU models with random weights, trained from "
                             "scratch: tests, the demo, the benchmark)")
        if weights is not None:
            if q.enhancer_architecture != "flux-dev":
                raise ValueError(f"{where}: quality.enhancer_weights is set but enhancer_architecture "
                                 f"is {q.enhancer_architecture}: weights are FLUX.1 weights (use flux-dev)")
            try:
                check_flux_directory(weights)
            except FileNotFoundError as exc:
                raise ValueError(f"{where}: quality.{exc}") from None
        if q.enhancer_flow in ("raft", "raft-small") and any(s.kind == "enhance-shot" for s in self.steps):
            from volcap_core.enhance.production import check_raft_weights

            try:  # the file and torchvision; the weights load when a shot is enhanced
                check_raft_weights(q.enhancer_flow, self.enhancer_flow_weights(),
                                   what=f"{where}: quality.enhancer_flow {q.enhancer_flow}",
                                   knob="quality.enhancer_flow_weights")
            except (FileNotFoundError, RuntimeError) as exc:
                raise ValueError(str(exc)) from None


def open_production(spec_path: str | Path, store: str | None = None,
                    shots: list[str] | None = None) -> Production:
    """Load and validate the spec, choose the store, learn each capture's facts, plan the steps.

    The store: ``store`` if given, else the spec's ``store:``, else ``$VOLCAP_STORE``.
    Nothing is run or written.
    """
    spec_path = Path(spec_path)
    spec = load_spec(spec_path)
    url = store or spec.store or os.environ.get("VOLCAP_STORE")
    if not url:
        raise ValueError(f"{spec_path}: no store: give --store, set 'store:' in the spec or VOLCAP_STORE")
    prod = Production(spec=spec, spec_dir=spec_path.resolve().parent, store=ArtifactStore(url).url, steps=[])
    s = ArtifactStore(prod.store)
    problems: dict[str, str] = {}
    for name, cs in spec.captures.items():
        try:
            if cs.folder is not None:
                prod.facts[name] = capture_info_from_folder(prod.folder(name))
            else:
                prod.facts[name] = CaptureInfo.from_capture(s.get_record(s.resolve(cs.ref), Capture))
        except Exception as exc:  # noqa: BLE001 - reported below only if the capture is needed
            problems[name] = f"{type(exc).__name__}: {exc}"
    try:
        prod.steps = needed_steps(spec, prod.facts, shots=shots)
    except ValueError as exc:
        for name, why in problems.items():
            if f"capture {name!r}" in str(exc):
                raise ValueError(f"{spec_path}: captures.{name}: {why}") from None
        raise ValueError(f"{spec_path}: {exc}") from None
    prod.check_enhancer(spec_path)
    return prod


# ---------------------------------------------------------------------------------------------
# Fingerprints and the plan
# ---------------------------------------------------------------------------------------------


def _versions(*tasks: Any) -> dict[str, Any]:
    return {t.cache_policy.task_name: task_identity(t) for t in tasks}


def has_tracking_step(steps: list[Step], capture: str) -> bool:
    """Whether the plan calibrates ``capture``'s tracking cameras (then the static step is not final)."""
    return any(s.kind == "calibrate-tracking" and s.parameters["capture"] == capture for s in steps)


def step_versions(step: Step, steps: list[Step]) -> dict[str, str]:
    """Name → version of every task a step runs (a bumped version re-runs the step)."""
    if step.kind == "ingest":
        return _versions(fingerprint_camera, ingest_camera, record_capture)
    if step.kind == "calibrate-static":
        final = () if has_tracking_step(steps, step.parameters["capture"]) else (calibrate_tasks.assemble_calibration,)
        return _versions(calibrate_tasks.calibrate_static, *final)
    if step.kind == "calibrate-tracking":
        return _versions(calibrate_tasks.calibrate_tracking_camera, calibrate_tasks.assemble_calibration)
    if step.kind == "dense-points":
        return _versions(calibrate_tasks.dense_points_frame, calibrate_tasks.point_cloud_sequence)
    if step.kind == "train-segment":
        return _versions(train_segment_task)
    if step.kind == "render-shot":
        return _versions(assemble_performance, render_shot)
    if step.kind == "face-pairs":
        return _versions(face_pairs)
    if step.kind == "train-enhancer":
        return _versions(actor_prompt, train_enhancer_task)
    if step.kind == "enhance-shot":
        return _versions(enhance_shot)
    return {}


def _outputs_digest(outputs: dict[str, ArtifactRef]) -> str:
    return digest_bytes(canonical_json({k: v.digest for k, v in sorted(outputs.items())}))


def step_fingerprint(prod: Production, step: Step, done: dict[str, dict[str, ArtifactRef]]
                     ) -> dict[str, Any] | str:
    """What a step's result depends on; a reason string when an input is not known yet."""
    inputs = {}
    for i in step.inputs:
        if i not in done:
            return f"after {i}, which is to run"
        inputs[i] = _outputs_digest(done[i])
    fp: dict[str, Any] = {"kind": step.kind, "versions": step_versions(step, prod.steps), "inputs": inputs,
                          "parameters": step.parameters}
    if step.kind == "ingest":
        fp["source"] = folder_listing_digest(prod.folder(step.parameters["capture"]))
    elif step.kind == "train-enhancer" and prod.enhancer_weights() is not None:
        from volcap_core.enhance.production import directory_fingerprint

        fp["weights"] = directory_fingerprint(prod.enhancer_weights())
    elif step.kind == "enhance-shot" and prod.enhancer_flow_weights() is not None:
        from volcap_core.enhance.production import directory_fingerprint

        fp["flow_weights"] = directory_fingerprint(prod.enhancer_flow_weights())
    elif step.parameters.get("capture_ref"):
        fp["source"] = ArtifactStore(prod.store).resolve(step.parameters["capture_ref"]).digest
    return fp


@dataclass
class PlannedStep:
    step: Step
    status: Literal["cached", "to-run"]
    reason: str | None = None
    outputs: dict[str, ArtifactRef] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        return {"id": self.step.id, "kind": self.step.kind, "status": self.status, "reason": self.reason,
                "inputs": list(self.step.inputs), "outputs": {k: v.digest for k, v in self.outputs.items()},
                "parameters": {k: v for k, v in self.step.parameters.items() if k != "shot_spec"}}


def plan_production(prod: Production) -> list[PlannedStep]:
    """Each needed step, cached or to run (with the reason), from the journal; runs nothing."""
    s = ArtifactStore(prod.store)
    done: dict[str, dict[str, ArtifactRef]] = {}
    plan = []
    for step in prod.steps:
        fp = step_fingerprint(prod, step, done)
        if isinstance(fp, str):
            plan.append(PlannedStep(step, "to-run", fp))
            continue
        entry = read_entry(s, prod.spec.name, step.id)
        if entry is None:
            plan.append(PlannedStep(step, "to-run", "never run"))
            continue
        why = compare_fingerprints(entry.fingerprint, fp)
        if why is None and s.missing(r.digest for r in entry.outputs.values()):
            why = "output missing from the store"
        if why is None:
            done[step.id] = entry.outputs
            plan.append(PlannedStep(step, "cached", None, entry.outputs))
        else:
            plan.append(PlannedStep(step, "to-run", why))
    return plan


# ---------------------------------------------------------------------------------------------
# Segment training: one GPU worker per segment, or in-process
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SegmentJob:
    """The inputs of one ``train-segment`` task run."""

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


# ---------------------------------------------------------------------------------------------
# The flow
# ---------------------------------------------------------------------------------------------


@flow(persist_result=False)
def production_flow(spec: str, store: str | None = None, shots: list[str] | None = None,
                    segment_runs: SegmentRuns = "auto", max_attempts: int = 3,
                    poll_interval_s: float = 5.0) -> dict:
    """Build what the production spec at ``spec`` (a path readable here) needs.

    ``shots``: deliver only these (default all); ``segment_runs``: ``auto`` | ``local`` |
    ``deployment`` (module doc). Returns the refs of every step's outputs and of each shot's frames.
    """
    log = get_run_logger()
    store_credentials_from_block()
    prod = open_production(spec, store, shots)  # refuses an enhancer it cannot build before anything runs
    s = ArtifactStore(prod.store)
    mode = segment_runs_mode(segment_runs)
    log.info("production %s: %d steps, store %s, segments %s", prod.spec.name, len(prod.steps), prod.store, mode)
    done: dict[str, dict[str, ArtifactRef]] = {}

    def finish(step: Step, outputs: dict[str, ArtifactRef]) -> None:
        fp = step_fingerprint(prod, step, done)
        assert not isinstance(fp, str), fp  # every input finished before this step
        write_entry(s, prod.spec.name, step.id, fp, outputs)
        done[step.id] = outputs

    q = prod.spec.quality_preset()
    captures: dict[str, ArtifactRef] = {}
    records: dict[str, Capture] = {}
    calibrations: dict[str, ArtifactRef] = {}
    points: dict[str, ArtifactRef] = {}
    train_steps = [st for st in prod.steps if st.kind == "train-segment"]
    for step in prod.steps:
        p = step.parameters
        if step.kind == "ingest":
            captures[p["capture"]] = ingest_flow(store=prod.store, capture_dir=str(prod.folder(p["capture"])))
            finish(step, {"capture": captures[p["capture"]]})
        elif step.kind == "calibrate-static":
            cap = p["capture"]
            if p.get("capture_ref"):
                captures[cap] = s.resolve(p["capture_ref"])
            records[cap] = s.get_record(captures[cap], Capture)
            _check_rig(prod, cap, records[cap], log)
            if has_tracking_step(prod.steps, cap):
                finish(step, {"static": calibrate_tasks.calibrate_static(prod.store, captures[cap])})
            else:
                calibrations[cap] = calibrate_capture(prod.store, captures[cap])
                finish(step, {"calibration": calibrations[cap]})
        elif step.kind == "calibrate-tracking":
            cap = p["capture"]
            calibrations[cap] = calibrate_capture(prod.store, captures[cap])
            finish(step, {"calibration": calibrations[cap]})
        elif step.kind == "dense-points":
            cap = p["capture"]
            a, b = p["frames"]
            # every point of every frame: training thins them to the segment's budget itself
            # (splat/init.py), after the static/moving split has seen them all
            points[step.id] = point_cloud_for_frames(prod.store, captures[cap], calibrations[cap], list(range(a, b)),
                                                     scale=p["dense_scale"],
                                                     exclude_cameras=reconstruction.default_held_out(records[cap]))
            finish(step, {"points": points[step.id]})

    # every needed segment at once
    jobs = []
    for step in train_steps:
        p = step.parameters
        cap = p["capture"]
        held = reconstruction.default_held_out(records[cap])
        config = q.train_config(held_out=held, max_gaussians=p["gaussians"])
        dense = next(i for i in step.inputs if i.startswith("dense-points:"))
        jobs.append(SegmentJob(capture=captures[cap], calibration=calibrations[cap], points=points[dense],
                               frames=(p["frames"][0], p["frames"][1]), config=config))
    log.info("training %d segment(s) (%s)", len(jobs), mode)
    for step, ref in zip(train_steps, train_segments(prod.store, jobs, mode, max_attempts, poll_interval_s)):
        finish(step, {"segment": ref})

    shots_out = {}
    for step in (st for st in prod.steps if st.kind == "render-shot"):
        p = step.parameters
        segs = [prod_step for prod_step in train_steps if prod_step.id in step.inputs]
        perf = assemble_performance(prod.store, p["capture"], captures[p["capture"]],
                                    [done[st.id]["segment"] for st in segs],
                                    [list(st.parameters["core"]) for st in segs])
        frames = render_shot(prod.store, perf, p["shot_spec"])
        s.set_ref(f"productions/{prod.spec.name}/shots/{p['shot']}", frames)
        s.set_ref(f"productions/{prod.spec.name}/performances/{p['shot']}", perf)
        finish(step, {"performance": perf, "frames": frames})
        shots_out[p["shot"]] = {"frames": frames.digest, "performance": perf.digest,
                                "count": len(s.get_tree(frames))}
        log.info("shot %s: %d frames -> %s", p["shot"], shots_out[p["shot"]]["count"], frames.digest)

    enhance_shots(prod, s, q, captures, done, shots_out, finish, log)

    return {"production": prod.spec.name, "store": prod.store, "segment_runs": mode,
            "steps": {sid: {k: v.digest for k, v in outs.items()} for sid, outs in done.items()},
            "shots": shots_out}


def enhance_shots(prod: Production, s: ArtifactStore, q, captures: dict[str, ArtifactRef],
                  done: dict[str, dict[str, ArtifactRef]], shots_out: dict[str, dict], finish, log) -> None:
    """The enhancer half: face pairs per actor of an enhanced shot, each actor's prompt, one
    enhancer trained on all their pairs, then every enhanced shot at once (frames in order within
    a shot). Nothing when no requested shot has ``enhance: true``."""
    from volcap_core.enhance.production import directory_fingerprint, has_text_encoders

    pairs: dict[str, ArtifactRef] = {}
    for step in (st for st in prod.steps if st.kind == "face-pairs"):
        p = step.parameters
        pairs[p["actor"]] = face_pairs(prod.store, captures[p["face_capture"]], p["actor"], p["subsequences"],
                                       p["subsequence_frames"], p["camera_paths"], p["resolution"],
                                       lq_gaussians=p["lq_gaussians"],
                                       hq_gaussians_per_frame=p["hq_gaussians_per_frame"])
        finish(step, {"pairs": pairs[p["actor"]]})
    enhancer: ArtifactRef | None = None
    for step in (st for st in prod.steps if st.kind == "train-enhancer"):
        p = step.parameters
        weights = prod.enhancer_weights()
        arch = q.enhancer_config()
        fingerprint = directory_fingerprint(weights) if weights is not None else None
        encoders = str(weights) if weights is not None and has_text_encoders(weights) else None
        if weights is not None and encoders is None:
            log.warning("%s has no FLUX.1 text encoders (or transformers is missing): zero prompt embeddings",
                        weights)
        prompts = {a: actor_prompt(prod.store, a, arch, text=p["prompts"].get(a), encoders=encoders,
                                   encoders_fingerprint=fingerprint if encoders else None) for a in p["actors"]}
        if weights is None:
            enhancer = train_enhancer_task(prod.store, [pairs[a] for a in p["actors"]], prompts,
                                           q.enhancer_train_config(), architecture=arch)
        else:
            enhancer = train_enhancer_task(prod.store, [pairs[a] for a in p["actors"]], prompts,
                                           q.enhancer_train_config(), base_weights=str(weights),
                                           base_fingerprint=fingerprint)
        s.set_ref(f"productions/{prod.spec.name}/enhancer", enhancer)
        finish(step, {"enhancer": enhancer, **{f"prompt:{a}": r for a, r in prompts.items()}})
    submitted = []
    # RAFT's weights file (enhancer_flow raft / raft-small): a location, pinned by its fingerprint
    flow_weights = prod.enhancer_flow_weights()
    raft = {} if flow_weights is None else {"flow_weights": str(flow_weights),
                                            "flow_weights_fingerprint": directory_fingerprint(flow_weights)}
    for step in (st for st in prod.steps if st.kind == "enhance-shot"):
        p = step.parameters
        frames = done[f"render-shot:{p['shot']}"]["frames"]
        # the shot's prompt group: its first actor's (a shot of several actors uses that one prompt)
        submitted.append((step, enhance_shot.submit(prod.store, frames, enhancer, p["actors"][0],
                                                    q.enhance_settings(), **raft)))
    for step, future in submitted:
        shot = step.parameters["shot"]
        ref = future.result()
        s.set_ref(f"productions/{prod.spec.name}/enhanced/{shot}", ref)
        finish(step, {"frames": ref})
        shots_out[shot]["enhanced"] = ref.digest
        log.info("shot %s: enhanced -> %s", shot, ref.digest)


def _check_rig(prod: Production, capture: str, record: Capture, log) -> None:
    """The spec may name a capture's rig; the capture's own record is what calibration uses."""
    from hardware.rig import load_rig

    name = prod.spec.captures[capture].rig
    if name is None:
        return
    rig = load_rig(prod.spec.rigs[name], prod.spec_dir)
    if rig.name != record.rig.name:
        log.warning("captures.%s.rig is %s (%s) but the capture was recorded with rig %s: calibrating with %s",
                    capture, name, rig.name, record.rig.name, record.rig.name)


__all__ = ["Production", "PlannedStep", "SegmentJob", "open_production", "plan_production", "production_flow",
           "run_segment_deployment", "segment_runs_mode", "train_segment_flow", "train_segments"]
