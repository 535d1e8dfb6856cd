"""The production flow: one production spec in, every artifact its shots need out.

It reads like the process it runs::

    plan      needed_steps(spec): only what the requested shots need
    ingest    each capture folder (cached: an unchanged folder is not converted again)
    calibrate static cameras once, tracking cameras per camera (none without tracking cameras)
    points    dense points for the frames of each needed segment (per frame, shared by overlaps)
    train     every needed segment at once (flows/segment_runs.py): runs of the `train-segment`
              deployment on the GPU pool when a Prefect server has it, in-process task runs otherwise
    render    each shot over a performance of its segments: cropped RGBA half-float EXR frames
    enhance   only if a shot asks for it (``enhance: true``): face pairs per actor of those shots
              (Gaussian-splat pairs: their Face Rig models fan out as the segments do),
              their prompt embeddings, one detail enhancer trained on all their pairs, then each
              enhanced shot's frames in order (shots in parallel): ``docs/enhancer.md``

Each step kind (``volcap_core.production.steps``) has one entry in :data:`STEP_KINDS`: the tasks
it runs, what its fingerprint reads beside its parameters, and how it runs; the flow runs the plan
kind by kind in :data:`PHASES`. Every step is a cached volcap task (``docs/tasks.md``), so a rerun
recomputes only what changed or never finished. After each step a journal entry
(``volcap_core.production.journal``) records what it ran on, which is how ``volcap plan`` explains
why a step is to run.

Segments (the ``train-segment`` steps, and the Face Rig models of ``face-pairs``) fan out through
``flows/segment_runs.py``: runs of the ``train-segment`` deployment on GPU workers, or task runs in
this process, as ``segment_runs`` chooses once for the whole production.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from prefect import flow, get_run_logger

from flows.calibrate import calibrate_capture, point_cloud_for_frames
from flows.cancellation import stop_flow_run_on_signal
from flows.facerig_pairs import facerig_pairs_flow
from flows.ingest import ingest_flow
from flows.segment_runs import SegmentJob, SegmentRuns, segment_runs_mode, train_segments
from flows.store_credentials import store_credentials_from_block
from tasks import calibrate as calibrate_tasks
from tasks import facerig
from tasks.contract import task_identity
from tasks.enhance import actor_prompt, enhance_shot, face_pairs, train_enhancer_task
from tasks.ingest import fingerprint_camera, ingest_camera, record_capture
from tasks.production import assemble_performance, render_shot
from tasks.reconstruct import ground_truth_calibration, ground_truth_points, train_segment_task
from volcap_core import reconstruction
from volcap_core.capture import Capture
from volcap_core.digest import digest_bytes
from volcap_core.enhance.production import (check_flux_directory, check_raft_weights, directory_fingerprint,
                                            has_text_encoders)
from volcap_core.production.journal import compare_fingerprints, folder_listing_digest, read_entry, write_entry
from volcap_core.production.presets import QualityPreset
from volcap_core.production.spec import (GROUND_TRUTH, CaptureInfo, ProductionSpec, capture_info_from_folder, load_spec,
                                         needed_steps)
from volcap_core.production.steps import Step
from volcap_core.records import ArtifactRef, canonical_json
from volcap_core.splat.train import TrainConfig
from volcap_core.store import ArtifactStore

#: Steps of the enhancer half (Face Rig pairs, the diffusion detail enhancer; docs/enhancer.md).
ENHANCER_STEPS = ("face-pairs", "train-enhancer", "enhance-shot")


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
        """Before anything runs: a Gaussian-splat face-pairs step's ``face_calibration`` ref must be
        in the store; an enhanced shot with the FLUX.1 architecture needs its weights
        directory, one with ``enhancer_flow`` RAFT its weights file and torchvision (``ValueError``
        naming the spec and the path otherwise)."""
        if not any(s.kind in ENHANCER_STEPS for s in self.steps):
            return
        where = where or self.spec.name
        for step in self.steps:   # a splat face-pairs step's face_calibration ref names a record in the store
            if step.kind == "face-pairs" and step.parameters.calibration not in (None, GROUND_TRUTH):
                try:
                    _face_calibration(self, step)
                except ValueError as exc:
                    raise ValueError(f"{where}: {exc}") from None
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


def final_calibration(steps: Sequence[Step], capture: str) -> str:
    """The id of the step whose output is ``capture``'s calibration: its tracking-camera step when the
    plan has one, else its static step."""
    tracking = f"calibrate-tracking:{capture}"
    return tracking if any(s.id == tracking for s in steps) else f"calibrate-static:{capture}"


def step_versions(step: Step, steps: Sequence[Step]) -> dict[str, Any]:
    """Name → identity of every task a step runs (a bumped version re-runs the step)."""
    kind = STEP_KINDS[step.kind]
    final = step.id == final_calibration(steps, step.parameters.capture) if kind.final_tasks else False
    return _versions(*kind.tasks, *(kind.final_tasks if final else ()))


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
    source = STEP_KINDS[step.kind].source
    return {"kind": step.kind, "versions": step_versions(step, prod.steps), "inputs": inputs,
            "parameters": step.parameters.as_json(), **(source(prod, step) if source else {})}


@dataclass
class PlannedStep:
    step: Step
    status: Literal["cached", "to-run"]
    reason: str | None = None
    outputs: dict[str, ArtifactRef] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        return {"id": self.step.id, "kind": self.step.kind, "status": self.status, "reason": self.reason,
                "inputs": list(self.step.inputs), "outputs": {k: v.digest for k, v in self.outputs.items()},
                "parameters": {k: v for k, v in self.step.parameters.as_json().items() if k != "shot_spec"}}


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
# Step kinds: what each runs, what its fingerprint reads, how it runs
# ---------------------------------------------------------------------------------------------


@dataclass
class ProductionRun:
    """One run of a production: the plan, where each step's outputs went, the shots delivered."""

    prod: Production
    mode: Literal["local", "deployment"]
    max_attempts: int
    poll_interval_s: float
    log: Any
    done: dict[str, dict[str, ArtifactRef]] = field(default_factory=dict)
    shots: dict[str, dict[str, Any]] = field(default_factory=dict)
    store: ArtifactStore = field(init=False)
    quality: QualityPreset = field(init=False)
    steps: dict[str, Step] = field(init=False)
    _captures: dict[str, ArtifactRef] = field(default_factory=dict, init=False, repr=False)
    _records: dict[str, Capture] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self.store = ArtifactStore(self.prod.store)
        self.quality = self.prod.spec.quality_preset()
        self.steps = {s.id: s for s in self.prod.steps}

    def finish(self, step: Step, outputs: dict[str, ArtifactRef]) -> None:
        """Journal the step's fingerprint and outputs; later steps read its outputs."""
        fp = step_fingerprint(self.prod, step, self.done)
        assert not isinstance(fp, str), fp  # every input finished before this step
        write_entry(self.store, self.prod.spec.name, step.id, fp, outputs)
        self.done[step.id] = outputs

    def capture(self, name: str) -> ArtifactRef:
        """A capture's Capture record: its ingest step's output, or the spec's ``ref`` resolved (once)."""
        if name not in self._captures:
            ingested = self.done.get(f"ingest:{name}")
            self._captures[name] = (ingested["capture"] if ingested
                                    else self.store.resolve(self.prod.spec.captures[name].ref))
        return self._captures[name]

    def record(self, name: str) -> Capture:
        if name not in self._records:
            self._records[name] = self.store.get_record(self.capture(name), Capture)
        return self._records[name]

    def output(self, step: Step, kind: str, name: str) -> ArtifactRef:
        """Output ``name`` of the input of ``step`` of kind ``kind`` (its first, in plan order)."""
        return self.done[next(i for i in step.inputs if self.steps[i].kind == kind)][name]

    def calibration(self, capture: str) -> ArtifactRef:
        """The final calibration of ``capture``."""
        return self.done[final_calibration(self.prod.steps, capture)]["calibration"]

    def result(self) -> dict[str, Any]:
        return {"production": self.prod.spec.name, "store": self.prod.store, "segment_runs": self.mode,
                "steps": {sid: {k: v.digest for k, v in outs.items()} for sid, outs in self.done.items()},
                "shots": self.shots}


def run_ingest(run: ProductionRun, steps: list[Step]) -> None:
    [step] = steps
    p = step.parameters
    run.finish(step, {"capture": ingest_flow(store=run.prod.store, capture_dir=str(run.prod.folder(p.capture)))})


def run_calibrate_static(run: ProductionRun, steps: list[Step]) -> None:
    """The static cameras; with no tracking step after it, the capture's whole calibration."""
    [step] = steps
    cap = step.parameters.capture
    _check_rig(run.prod, cap, run.record(cap), run.log)
    if final_calibration(run.prod.steps, cap) == step.id:
        run.finish(step, {"calibration": calibrate_capture(run.prod.store, run.capture(cap))})
    else:
        run.finish(step, {"static": calibrate_tasks.calibrate_static(run.prod.store, run.capture(cap))})


def run_calibrate_tracking(run: ProductionRun, steps: list[Step]) -> None:
    [step] = steps
    run.finish(step, {"calibration": calibrate_capture(run.prod.store, run.capture(step.parameters.capture))})


def run_dense_points(run: ProductionRun, steps: list[Step]) -> None:
    """Every point of every frame: training thins them to the segment's budget itself
    (splat/init.py), after the static/moving split has seen them all."""
    [step] = steps
    p = step.parameters
    a, b = p.frames
    points = point_cloud_for_frames(run.prod.store, run.capture(p.capture), run.calibration(p.capture),
                                    list(range(a, b)), scale=p.dense_scale,
                                    exclude_cameras=reconstruction.default_held_out(
                                        run.record(p.capture), tracking=run.quality.held_out_tracking))
    run.finish(step, {"points": points})


def segment_train_config(quality: QualityPreset, record: Capture, gaussians: int) -> TrainConfig:
    """A train-segment step's TrainConfig: the preset's, its held-out cameras by the preset's rule
    (:func:`~volcap_core.reconstruction.default_held_out`), at the step's Gaussian budget. The
    demo checks its segment against this before it runs a production on it."""
    held = reconstruction.default_held_out(record, tracking=quality.held_out_tracking)
    return quality.train_config(held_out=held, max_gaussians=gaussians)


def run_train_segments(run: ProductionRun, steps: list[Step]) -> None:
    """Every needed segment at once, each to its plan's Gaussian budget."""
    jobs = []
    for step in steps:
        p = step.parameters
        config = segment_train_config(run.quality, run.record(p.capture), p.gaussians)
        jobs.append(SegmentJob(capture=run.capture(p.capture), calibration=run.calibration(p.capture),
                               points=run.output(step, "dense-points", "points"), frames=p.frames, config=config))
    run.log.info("training %d segment(s) (%s)", len(jobs), run.mode)
    for step, ref in zip(steps, train_segments(run.prod.store, jobs, run.mode, run.max_attempts,
                                               run.poll_interval_s)):
        run.finish(step, {"segment": ref})


def run_render_shot(run: ProductionRun, steps: list[Step]) -> None:
    """The shot's performance (its segments, each owning its core) and its frames."""
    [step] = steps
    p = step.parameters
    segments = [run.steps[i] for i in step.inputs]
    perf = assemble_performance(run.prod.store, p.capture, run.capture(p.capture),
                                [run.done[s.id]["segment"] for s in segments],
                                [list(s.parameters.core) for s in segments])
    frames = render_shot(run.prod.store, perf, p.shot_spec)
    run.store.set_ref(f"productions/{run.prod.spec.name}/shots/{p.shot}", frames)
    run.store.set_ref(f"productions/{run.prod.spec.name}/performances/{p.shot}", perf)
    run.finish(step, {"performance": perf, "frames": frames})
    run.shots[p.shot] = {"frames": frames.digest, "performance": perf.digest,
                         "count": len(run.store.get_tree(frames))}
    run.log.info("shot %s: %d frames -> %s", p.shot, run.shots[p.shot]["count"], frames.digest)


def run_face_pairs(run: ProductionRun, steps: list[Step]) -> None:
    """An actor's pairs by the preset's ``pair_method``: ``splat``, the facerig_pairs flow on the
    face capture -> a PairDataset; ``interim``, the ``face-pairs`` task (degraded frames) -> a
    FacePairSet. The splat pairs' face capture is calibrated as the step says (the spec's
    ``face_calibration``: a Calibration ref, or ``ground-truth``; unset: the calibrate flow's
    tasks), and their LQ range is measured in the step's ``train-segment`` inputs (``lq-range``,
    recorded ``measured`` with the measurement's digest; none: the preset's, recorded ``preset``).
    Its Face Rig models train as this run's segments do (its ``segment_runs`` mode)."""
    [step] = steps
    p = step.parameters
    if p.method == "splat":
        kw: dict[str, Any] = {}
        if p.calibration == GROUND_TRUTH:
            kw["ground_truth"] = True
        elif p.calibration is not None:
            kw["calibration"] = _face_calibration(run.prod, step).digest
        segments = [run.steps[i] for i in step.inputs if run.steps[i].kind == "train-segment"]
        if p.lq_range == "measured":
            measurement = facerig.measured_lq_range(run.prod.store, [run.done[s.id]["segment"] for s in segments],
                                                    [list(s.parameters.core) for s in segments], p.actor_index)
            measured = run.store.get_json(measurement)
            run.log.info("LQ range of %s: %d-%d Gaussians a frame, measured over %d frame(s) of %d segment(s)",
                         p.actor, measured["low"], measured["high"], measured["frames"], len(segments))
            kw.update(lq_range=(measured["low"], measured["high"]), lq_range_source="measured",
                      lq_measurement=measurement.digest)
        out = facerig_pairs_flow(store=run.prod.store, capture=run.capture(p.face_capture).digest, actor=p.actor,
                                 quality=run.quality, segment_runs=run.mode, max_attempts=run.max_attempts,
                                 poll_interval_s=run.poll_interval_s, **kw)
        run.finish(step, {"pairs": out["dataset"]})
        return
    pairs = face_pairs(run.prod.store, run.capture(p.face_capture), p.actor, p.subsequences, p.subsequence_frames,
                       p.camera_paths, p.resolution, lq_gaussians=list(p.lq_gaussians),
                       hq_gaussians_per_frame=p.hq_gaussians_per_frame, window=p.window)
    run.finish(step, {"pairs": pairs})


def run_train_enhancer(run: ProductionRun, steps: list[Step]) -> None:
    """Each actor's prompt embedding, then one enhancer on all their pairs: from the preset's
    FLUX.1 weights when it names them, else the CPU architecture from scratch."""
    [step] = steps
    p = step.parameters
    q = run.quality
    weights = run.prod.enhancer_weights()
    arch = q.enhancer_config()
    fingerprint = directory_fingerprint(weights) if weights is not None else None
    encoders = str(weights) if weights is not None and has_text_encoders(weights) else None
    if weights is not None and encoders is None:
        run.log.warning("%s has no FLUX.1 text encoders (or transformers is missing): zero prompt embeddings",
                        weights)
    prompts = {a: actor_prompt(run.prod.store, a, arch, text=p.prompts.get(a), encoders=encoders,
                               encoders_fingerprint=fingerprint if encoders else None) for a in p.actors}
    pairs = [run.done[f"face-pairs:{a}"]["pairs"] for a in p.actors]
    if weights is None:
        enhancer = train_enhancer_task(run.prod.store, pairs, prompts, q.enhancer_train_config(), architecture=arch)
    else:
        enhancer = train_enhancer_task(run.prod.store, pairs, prompts, q.enhancer_train_config(),
                                       base_weights=str(weights), base_fingerprint=fingerprint)
    run.store.set_ref(f"productions/{run.prod.spec.name}/enhancer", enhancer)
    run.finish(step, {"enhancer": enhancer, **{f"prompt:{a}": r for a, r in prompts.items()}})


def run_enhance_shots(run: ProductionRun, steps: list[Step]) -> None:
    """Every enhanced shot at once (frames in order within a shot), each with its first actor's
    prompt; RAFT's weights file (``enhancer_flow`` raft / raft-small) as a location pinned by its
    fingerprint."""
    flow_weights = run.prod.enhancer_flow_weights()
    raft = {} if flow_weights is None else {"flow_weights": str(flow_weights),
                                            "flow_weights_fingerprint": directory_fingerprint(flow_weights)}
    submitted = [(step, enhance_shot.submit(run.prod.store, run.output(step, "render-shot", "frames"),
                                            run.output(step, "train-enhancer", "enhancer"),
                                            step.parameters.actors[0], run.quality.enhance_settings(), **raft))
                 for step in steps]
    for step, future in submitted:
        shot = step.parameters.shot
        ref = future.result()
        run.store.set_ref(f"productions/{run.prod.spec.name}/enhanced/{shot}", ref)
        run.finish(step, {"frames": ref})
        run.shots[shot]["enhanced"] = ref.digest
        run.log.info("shot %s: enhanced -> %s", shot, ref.digest)


def _folder_source(prod: Production, step: Step) -> dict[str, Any]:
    """An ingest reads its folder: the listing digest stands in for the files."""
    return {"source": folder_listing_digest(prod.folder(step.parameters.capture))}


def _ref_source(prod: Production, step: Step) -> dict[str, Any]:
    """A calibration of a capture given by ref reads what the ref names now."""
    ref = step.parameters.capture_ref
    return {"source": ArtifactStore(prod.store).resolve(ref).digest} if ref else {}


def _face_calibration(prod: Production, step: Step) -> ArtifactRef:
    """The Calibration a splat face-pairs step names (its actor's ``face_calibration`` ref), resolved
    now; ``ValueError`` naming the actor and the field when the store has no such ref."""
    from volcap_core.store import MissingRefError

    p = step.parameters
    try:
        return ArtifactStore(prod.store).resolve(p.calibration)
    except (MissingRefError, FileNotFoundError):
        i = next(k for k, a in enumerate(prod.spec.actors) if a.name == p.actor)
        raise ValueError(f"actors[{i}].face_calibration: {p.calibration!r} is not in store {prod.store} "
                         "(a ref name such as imported-calibrations/NAME, as `volcap import-calibration` "
                         "stores it, or a blake3 digest)") from None


def _pairs_source(prod: Production, step: Step) -> dict[str, Any]:
    """Gaussian-splat pairs run the facerig_pairs flow's tasks and ``lq-range`` (their identities)
    and read the Calibration their ``face_calibration`` ref names now; interim pairs only
    ``face-pairs`` (nothing added: their fingerprints stay as they were)."""
    p = step.parameters
    if p.method != "splat":
        return {}
    source = {"splat_tasks": _versions(calibrate_tasks.calibrate_static, calibrate_tasks.assemble_calibration,
                                       calibrate_tasks.dense_points_frame, calibrate_tasks.point_cloud_sequence,
                                       ground_truth_calibration, ground_truth_points, train_segment_task,
                                       facerig.face_paths, facerig.render_pairs, facerig.measured_lq_range,
                                       facerig.pair_dataset)}
    if p.calibration not in (None, GROUND_TRUTH):
        source["face_calibration"] = _face_calibration(prod, step).digest
    return source


def _weights_source(prod: Production, step: Step) -> dict[str, Any]:
    """The enhancer trains from the preset's FLUX.1 directory when it names one."""
    weights = prod.enhancer_weights()
    return {} if weights is None else {"weights": directory_fingerprint(weights)}


def _flow_weights_source(prod: Production, step: Step) -> dict[str, Any]:
    """A shot's enhancement reads RAFT's weights file when the preset names one."""
    weights = prod.enhancer_flow_weights()
    return {} if weights is None else {"flow_weights": directory_fingerprint(weights)}


@dataclass(frozen=True)
class StepKindRun:
    """How the flow runs one step kind (``volcap_core.production.steps``).

    ``tasks``: the volcap tasks it runs (their identities are in its fingerprint); ``final_tasks``:
    those it runs only as its capture's final calibration. ``run(run, steps)``: runs ``steps`` (one,
    or with ``together`` every step of the kind at once) and journals each. ``source``: what its
    fingerprint reads besides its parameters and inputs (files outside the store)."""

    tasks: tuple[Any, ...]
    run: Callable[[ProductionRun, list[Step]], None]
    source: Callable[[Production, Step], dict[str, Any]] | None = None
    final_tasks: tuple[Any, ...] = ()
    together: bool = False


STEP_KINDS: dict[str, StepKindRun] = {
    "ingest": StepKindRun((fingerprint_camera, ingest_camera, record_capture), run_ingest, _folder_source),
    "calibrate-static": StepKindRun((calibrate_tasks.calibrate_static,), run_calibrate_static, _ref_source,
                                    final_tasks=(calibrate_tasks.assemble_calibration,)),
    "calibrate-tracking": StepKindRun((calibrate_tasks.calibrate_tracking_camera, calibrate_tasks.assemble_calibration),
                                      run_calibrate_tracking, _ref_source),
    "dense-points": StepKindRun((calibrate_tasks.dense_points_frame, calibrate_tasks.point_cloud_sequence),
                                run_dense_points),
    "train-segment": StepKindRun((train_segment_task,), run_train_segments, together=True),
    "render-shot": StepKindRun((assemble_performance, render_shot), run_render_shot),
    "face-pairs": StepKindRun((face_pairs,), run_face_pairs, _pairs_source),
    "train-enhancer": StepKindRun((actor_prompt, train_enhancer_task), run_train_enhancer, _weights_source),
    "enhance-shot": StepKindRun((enhance_shot,), run_enhance_shots, _flow_weights_source, together=True),
}

#: The order the flow runs a plan in: what the segments need (in plan order), every segment at
#: once, the shots, then the enhancer half (nothing without an enhanced shot).
PHASES = (("ingest", "calibrate-static", "calibrate-tracking", "dense-points"), ("train-segment",),
          ("render-shot",), ("face-pairs",), ("train-enhancer",), ("enhance-shot",))


def batches(steps: Sequence[Step]) -> Iterator[list[Step]]:
    """The plan's steps as the flow runs them: phase by phase, one step at a time, or a whole
    phase at once for a kind that runs ``together``."""
    for phase in PHASES:
        todo = [s for s in steps if s.kind in phase]
        if todo and STEP_KINDS[todo[0].kind].together:
            yield todo
        else:
            yield from ([s] for s in todo)


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
    stop_flow_run_on_signal()  # a worker's run: a cancel (the UI's) ends it within seconds, thread-pool tasks too
    log = get_run_logger()
    store_credentials_from_block()
    prod = open_production(spec, store, shots)  # refuses an enhancer it cannot build before anything runs
    run = ProductionRun(prod, segment_runs_mode(segment_runs), max_attempts, poll_interval_s, log)
    log.info("production %s: %d steps, store %s, segments %s", prod.spec.name, len(prod.steps), prod.store, run.mode)
    for steps in batches(prod.steps):
        STEP_KINDS[steps[0].kind].run(run, steps)
    return run.result()


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


__all__ = ["PHASES", "STEP_KINDS", "PlannedStep", "Production", "ProductionRun", "StepKindRun", "open_production",
           "plan_production", "production_flow", "step_fingerprint", "step_versions"]
