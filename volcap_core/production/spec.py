"""The production spec (YAML) and the planner that decides what it needs.

A production spec names the captures, the rigs they come from, the actors, the shots to deliver
and a quality preset (:mod:`volcap_core.production.presets`; format and example in
``docs/production-spec.md``). :func:`load_spec`
validates it with pydantic and reports every problem with its field path, the offending value and
the YAML line. :func:`needed_steps` turns a spec into the list of
:class:`~volcap_core.production.steps.Step` s it needs — and no more:

- a capture no requested shot shows is not touched (unless it sets ``reconstruct: true``);
- no tracking-camera calibration for a capture whose rig has no tracking cameras;
- only the segments that the requested shots' frames fall into (with their blend neighbours);
- no Face Rig work (face captures, face pairs, enhancer) unless a requested shot has
  ``enhance: true``, and then only for the actors in those shots.

Everything here is pure: no store, no Prefect. Each step's parameters are its kind's model
(:mod:`~volcap_core.production.steps`); the flows layer maps each kind to the tasks it runs and
marks which steps are already cached (``volcap plan``).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from hardware.validation_errors import clean_loc, format_validation_error
from volcap_core.capture import Performer
from volcap_core.production.presets import PRESETS, QualityPreset
from volcap_core.production.segments import Segment, SegmentPlan
from volcap_core.production.shot import Shot, ShotError, load_shot
from volcap_core.production.steps import (CalibrateStatic, CalibrateTracking, DensePoints, EnhanceShot, FacePairs,
                                          Ingest, RenderShot, Step, TrainEnhancer, TrainSegment)

__all__ = [
    "GROUND_TRUTH",
    "SPEC_FORMAT",
    "ActorSpec",
    "CaptureInfo",
    "CaptureSpec",
    "ProductionSpec",
    "SpecError",
    "capture_info_from_folder",
    "check_face_capture",
    "largest_image",
    "load_spec",
    "needed_steps",
    "parse_spec",
    "segment_plan_for",
]

SPEC_FORMAT = "volcap-production/1"
NAME = r"^[A-Za-z0-9_.-]+$"
#: ``actors[].face_calibration: ground-truth``: a synthetic face capture's true cameras and depth
#: points, as ``volcap reconstruct --ground-truth`` uses them
GROUND_TRUTH = "ground-truth"


class SpecError(ValueError):
    """An invalid production spec; one line per problem (field path, message, value, YAML line)."""


class QualitySelection(BaseModel):
    """``quality: {preset: NAME, <field>: <override>...}``: a preset of
    :data:`volcap_core.production.presets.PRESETS`, single :class:`~volcap_core.production.presets.QualityPreset` fields
    replaced."""

    model_config = ConfigDict(extra="allow", frozen=True)
    preset: str


# ------------------------------------------------------------------------------------------------
# Spec models


class CaptureSpec(BaseModel):
    """A capture: a folder to ingest, or one already in the store (named ref or digest)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    folder: str | None = Field(None, description="capture folder with capture.json")
    ref: str | None = Field(None, description="store ref name (captures/NAME) or blake3 digest")
    rig: str | None = Field(None, description="a key of the spec's rigs")
    frames: tuple[int, int] | None = Field(None, description="take indices [start, end) to use")
    reconstruct: bool = Field(False, description="train every segment even if no shot needs it")

    @model_validator(mode="after")
    def _one_source(self) -> "CaptureSpec":
        if (self.folder is None) == (self.ref is None):
            raise ValueError("give exactly one of 'folder' and 'ref' "
                             f"({'both' if self.folder else 'neither'} given)")
        if self.frames is not None and not 0 <= self.frames[0] < self.frames[1]:
            raise ValueError(f"frames must be [start, end) with 0 <= start < end, got "
                             f"{list(self.frames)}")
        return self


class ActorSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str = Field(pattern=NAME)
    captures: tuple[str, ...] = Field(min_length=1, description="scene captures the actor is in")
    face_capture: str | None = Field(None, description="Face Rig capture for the enhancer")
    face_calibration: str | None = Field(
        None, min_length=1, description="the face capture's calibration for Gaussian-splat pairs: a Calibration "
        "in the store (a ref name such as imported-calibrations/NAME, as `volcap import-calibration` stores "
        "it, or a blake3 digest), or 'ground-truth' (a synthetic capture's true cameras and depth points); "
        "unset: calibrated by the calibrate flow (SfM)")
    index: int | None = Field(None, ge=0, description="the actor's index in its captures (a synthetic "
                              "capture's ground_truth/scene.json actors); a face capture that names its "
                              "performer must then name this index")
    prompt: str | None = Field(None, description="the enhancer's text prompt for this actor's group "
                               "(embedded once when the FLUX.1 text encoders are there; else zeros)")


class ProductionSpec(BaseModel):
    """A validated production spec (``docs/production-spec.md``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    format: Literal["volcap-production/1"] = SPEC_FORMAT
    name: str = Field(pattern=NAME)
    store: str | None = Field(None, description="store URL shared by every worker")
    quality: str | QualitySelection = "production"
    rigs: dict[str, str] = Field(default_factory=dict,
                                 description="name → built-in rig or rig JSON path")
    captures: dict[str, CaptureSpec] = Field(min_length=1)
    actors: tuple[ActorSpec, ...] = ()
    shots: tuple[Shot, ...] = ()

    @field_validator("store")
    @classmethod
    def _no_credentials(cls, v: str | None) -> str | None:
        if v is not None and re.match(r"^[a-z][a-z0-9+.-]*://[^/@]*@", v):
            raise ValueError("the store URL must not carry credentials: give them in the "
                             "environment (AWS_ACCESS_KEY_ID, ...) or a Prefect block")
        return v

    @field_validator("captures", "rigs")
    @classmethod
    def _names(cls, v: dict) -> dict:
        for name in v:
            if not re.match(NAME, name):
                raise ValueError(f"name {name!r} may only use letters, digits, '_', '.', '-'")
        return v

    @field_validator("shots", mode="before")
    @classmethod
    def _load_shot_files(cls, v: Any, info: ValidationInfo) -> Any:
        if not isinstance(v, (list, tuple)):
            return v
        base = Path((info.context or {}).get("base_dir", "."))
        out = []
        for i, entry in enumerate(v):
            if isinstance(entry, str):
                try:
                    out.append(load_shot(base / entry, where=entry))
                except ShotError as exc:
                    raise ValueError(f"shot file {i}: {exc}") from None
            else:
                out.append(entry)
        return out

    @model_validator(mode="after")
    def _references(self) -> "ProductionSpec":
        problems: list[str] = []
        preset = self.quality if isinstance(self.quality, str) else self.quality.preset
        where = "quality" if isinstance(self.quality, str) else "quality.preset"
        if preset not in PRESETS:
            problems.append(f"{where}: unknown preset {preset!r} (known: {', '.join(PRESETS)})")
        elif not isinstance(self.quality, str):
            try:
                self.quality_preset()
            except ValidationError as exc:
                problems += [f"quality.{line}" for line in format_validation_error(exc)]
        for name, cap in self.captures.items():
            if cap.rig is not None and cap.rig not in self.rigs:
                problems.append(f"captures.{name}.rig: {cap.rig!r} is not one of rigs "
                                f"({', '.join(self.rigs) or 'none defined'})")
        seen: set[str] = set()
        for i, actor in enumerate(self.actors):
            if actor.name in seen:
                problems.append(f"actors[{i}].name: actor {actor.name!r} is listed twice")
            seen.add(actor.name)
            for j, c in enumerate(actor.captures):
                if c not in self.captures:
                    problems.append(f"actors[{i}].captures[{j}]: unknown capture {c!r} "
                                    f"(known: {', '.join(self.captures)})")
            if actor.face_calibration is not None and actor.face_capture is None:
                problems.append(f"actors[{i}].face_calibration: set, but actor {actor.name!r} has no "
                                "face_capture to calibrate")
            if actor.face_capture is not None:
                if actor.face_capture not in self.captures:
                    problems.append(f"actors[{i}].face_capture: unknown capture "
                                    f"{actor.face_capture!r} (known: {', '.join(self.captures)})")
                elif actor.face_capture in actor.captures:
                    problems.append(f"actors[{i}].face_capture: {actor.face_capture!r} is also one "
                                    "of the actor's scene captures")
        shot_names: set[str] = set()
        for i, shot in enumerate(self.shots):
            where = f"shots[{i}] ({shot.name})"
            if shot.name in shot_names:
                problems.append(f"{where}.name: shot {shot.name!r} is listed twice")
            shot_names.add(shot.name)
            if shot.performance not in self.captures:
                problems.append(f"{where}.performance: unknown capture {shot.performance!r} "
                                f"(known: {', '.join(self.captures)})")
                continue
            for a in shot.actors:
                actor = self.actor(a)
                if actor is None:
                    problems.append(f"{where}.actors: unknown actor {a!r}")
                elif shot.performance not in actor.captures:
                    problems.append(f"{where}.actors: actor {a!r} is not in capture "
                                    f"{shot.performance!r} (actors[{self.actors.index(actor)}]"
                                    ".captures)")
            if shot.enhance:
                featured = self.shot_actors(shot)
                if not featured:
                    problems.append(f"{where}.enhance: true, but no actor is in capture "
                                    f"{shot.performance!r}: nothing to enhance")
                for actor in featured:
                    if actor.face_capture is None:
                        problems.append(
                            f"{where}.enhance: true needs a face capture for actor {actor.name!r} "
                            f"(actors[{self.actors.index(actor)}].face_capture is not set)")
        if problems:
            raise ValueError("\n".join(problems))
        return self

    # -- helpers ---------------------------------------------------------------------------------

    def actor(self, name: str) -> ActorSpec | None:
        return next((a for a in self.actors if a.name == name), None)

    def shot(self, name: str) -> Shot:
        for s in self.shots:
            if s.name == name:
                return s
        raise KeyError(f"spec {self.name} has no shot {name!r} "
                       f"(shots: {', '.join(s.name for s in self.shots)})")

    def shot_actors(self, shot: Shot) -> list[ActorSpec]:
        """The actors a shot features: its ``actors``, or every actor of its capture."""
        if shot.actors:
            return [a for a in self.actors if a.name in shot.actors]
        return [a for a in self.actors if shot.performance in a.captures]

    def quality_preset(self) -> QualityPreset:
        """The preset with the spec's overrides applied."""
        if isinstance(self.quality, str):
            return PRESETS[self.quality]
        return PRESETS[self.quality.preset].with_overrides(**(self.quality.model_extra or {}))


def _yaml_line(text: str, loc: Sequence[int | str]) -> int | None:
    """1-based line of the YAML node at ``loc`` (the deepest that exists)."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return None
    line = node.start_mark.line + 1 if node is not None else None
    for part in loc:
        if isinstance(node, yaml.MappingNode) and isinstance(part, str):
            nxt = next((v for k, v in node.value if getattr(k, "value", None) == part), None)
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int) and part < len(node.value):
            nxt = node.value[part]
        else:
            nxt = None
        if nxt is None:
            break
        node, line = nxt, nxt.start_mark.line + 1
    return line


_LOC_RE = re.compile(r"^([A-Za-z_][\w]*(?:\.[\w.-]+|\[\d+\])*)")


def _loc_from_text(path: str) -> list[int | str]:
    """``actors[1].captures[0]`` → ``['actors', 1, 'captures', 0]`` (best effort)."""
    out: list[int | str] = []
    for name, index in re.findall(r"([^.\[\]]+)|\[(\d+)\]", path):
        out.append(int(index) if index else name)
    return out


def parse_spec(data: Mapping[str, Any], *, base_dir: str | Path = ".", text: str | None = None,
               origin: str = "<spec>") -> ProductionSpec:
    """Validate an already parsed spec. Shot file paths resolve against ``base_dir``."""
    try:
        return ProductionSpec.model_validate(dict(data), context={"base_dir": str(base_dir)})
    except ValidationError as exc:
        lines = []
        errors = [e for e in exc.errors() if not (e.get("type") == "too_short" and any(
            len(o.get("loc", ())) > len(e["loc"]) and tuple(o["loc"][:len(e["loc"])]) == tuple(e["loc"])
            for o in exc.errors()))]
        for err, line in zip(errors, format_validation_error(exc), strict=True):
            loc = clean_loc(err.get("loc", ()))
            if loc:
                ln = _yaml_line(text, loc) if text else None
                lines.append(line + (f" [line {ln}]" if ln else ""))
                continue
            # whole-spec cross-reference checks: one problem per line, each starting with its path
            for m in line.removeprefix("(top level): ").split("\n"):
                path = _LOC_RE.match(m)
                ln = _yaml_line(text, _loc_from_text(path.group(1))) if (text and path) else None
                lines.append(m + (f" [line {ln}]" if ln else ""))
        raise SpecError(f"{origin}: invalid production spec:\n  " + "\n  ".join(lines)) from None


def load_spec(path: str | Path) -> ProductionSpec:
    """Read and validate a production spec YAML file (shot paths relative to its folder).

    Raises :class:`SpecError` with one line per problem: field path, message, value, YAML line."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise SpecError(f"{path}: spec file not found") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise SpecError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise SpecError(f"{path}: a production spec is a YAML mapping, got {type(data).__name__}")
    return parse_spec(data, base_dir=path.parent, text=text, origin=str(path))


# ------------------------------------------------------------------------------------------------
# Planning


class CaptureInfo(BaseModel):
    """What the planner must know about a capture before anything runs.

    ``width``/``height``: the largest camera image, long side by short side (for the segment
    memory estimate; a portrait camera counts as its landscape size, so a folder's rig sensors and
    the ingested capture's images give the same figures: :func:`largest_image`).
    ``segment_plan``: the plan to use; None plans from the spec's quality preset.
    ``name``: the capture's name as recorded (capture.json's, the record's); ``performer``: whose
    actor it films, when it says (:class:`~volcap_core.capture.Performer`); ``ground_truth``:
    whether it carries ground truth (a synthetic capture). None: not known."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    has_tracking_cameras: bool
    fps: float = Field(gt=0)
    frame_count: int = Field(gt=0)
    width: int = Field(3840, gt=0)
    height: int = Field(2160, gt=0)
    segment_plan: SegmentPlan | None = None
    name: str | None = None
    performer: Performer | None = None
    ground_truth: bool | None = None

    @classmethod
    def from_capture(cls, capture, segment_plan: SegmentPlan | None = None) -> "CaptureInfo":
        """From an ingested :class:`~volcap_core.capture.Capture` record (tracking cameras: those
        of its rig that the capture actually recorded)."""
        tracking = any(capture.rig.camera(c.id).role.tracks for c in capture.cameras)
        width, height = largest_image((c.width, c.height) for c in capture.cameras)
        return cls(has_tracking_cameras=tracking, fps=capture.fps, frame_count=capture.frame_count,
                   width=width, height=height, segment_plan=segment_plan, name=capture.name,
                   performer=capture.performer, ground_truth=capture.ground_truth is not None)


def largest_image(sizes: Iterable[tuple[int, int]]) -> tuple[int, int]:
    """``(long side, short side)`` of the largest of ``(width, height)`` camera images (pixels)."""
    sizes = list(sizes)
    return max(max(w, h) for w, h in sizes), max(min(w, h) for w, h in sizes)


def capture_info_from_folder(folder: str | Path) -> CaptureInfo:
    """From a capture folder's ``capture.json`` and its rig (nothing is ingested or decoded)."""
    from volcap_core.capture import CaptureFolder

    capture = CaptureFolder.open(folder)
    listed = set(capture.camera_ids)
    cams = [c for c in capture.rig.cameras if c.id in listed] or list(capture.rig.cameras)
    width, height = largest_image((c.sensor.width_px, c.sensor.height_px) for c in cams)
    return CaptureInfo(has_tracking_cameras=any(c.role.tracks for c in cams), fps=capture.fps,
                       frame_count=capture.frame_count, width=width, height=height, name=capture.name,
                       performer=capture.description.performer,
                       ground_truth=capture.description.ground_truth is not None)


def check_face_capture(spec: ProductionSpec, actor: ActorSpec, capture_info: Mapping[str, CaptureInfo]) -> None:
    """An actor's face capture must film that actor: when the face capture names its performer
    (``CaptureInfo.performer``, from its capture.json or record), the performer's capture must be
    one of the actor's ``captures`` (compared by the names the captures record) and, when the
    actor sets ``index``, the performer's actor that index. A face capture that names no
    performer (real captures) is accepted, as is one whose facts are not known here.
    ``ValueError``, one line naming the actor, the face capture and whose actor it films."""
    fc = actor.face_capture
    face = capture_info.get(fc) if fc is not None else None
    if face is None or face.performer is None:
        return
    i = spec.actors.index(actor)
    p = face.performer
    names = {c: capture_info[c].name for c in actor.captures if c in capture_info and capture_info[c].name}
    whose = f"actor {p.actor} of the capture named {p.capture!r}"
    if p.capture not in names.values():
        known = ", ".join(f"{c} ({names[c]!r})" if c in names else f"{c} (name not known)" for c in actor.captures)
        raise ValueError(f"actors[{i}].face_capture: {fc!r} films {whose}, which is not one of actor "
                         f"{actor.name!r}'s captures: {known}")
    if actor.index is not None and p.actor != actor.index:
        raise ValueError(f"actors[{i}].face_capture: {fc!r} films {whose}, but actor {actor.name!r} is "
                         f"actor {actor.index} there (actors[{i}].index)")


def segment_plan_for(spec: ProductionSpec, capture: str, info: CaptureInfo) -> SegmentPlan:
    """The capture's segment plan: ``info.segment_plan``, or one from the quality preset
    (:meth:`~volcap_core.production.presets.QualityPreset.plan_segments`, as ``volcap reconstruct`` plans)."""
    if info.segment_plan is not None:
        return info.segment_plan
    q = spec.quality_preset()
    cap = spec.captures[capture]
    frames = cap.frames or (0, info.frame_count)
    if frames[1] > info.frame_count:
        raise ValueError(f"captures.{capture}.frames: [{frames[0]}, {frames[1]}) reaches past the "
                         f"take's {info.frame_count} frames")
    return q.plan_segments(frames, info.width, info.height)


def _shot_take_frames(shot: Shot, fps: float) -> list[float]:
    """Take positions (fractional take indices) of every frame of ``shot``."""
    return [shot.time_at(f) * fps for f in shot.frame_numbers()]


def needed_steps(spec: ProductionSpec, capture_info: Mapping[str, CaptureInfo], *,
                 shots: Iterable[str] | None = None) -> list[Step]:
    """The steps the spec needs, in dependency order (every step after its inputs).

    Args:
        spec: the validated spec.
        capture_info: facts per capture name (:class:`CaptureInfo`); needed for every capture a
            requested shot shows, every face capture of an actor in an enhanced shot, and every
            capture with ``reconstruct: true``.
        shots: names of the shots to deliver (default: all of the spec's).
    Returns:
        Steps with stable ids::

            ingest:C  calibrate-static:C  calibrate-tracking:C  dense-points:C:SEG
            train-segment:C:SEG  render-shot:S  face-pairs:A  train-enhancer:A1+A2  enhance-shot:S

        (C capture, SEG ``aaaaaa-bbbbbb`` take indices, S shot, A actor). A capture given by
        ``ref`` is already ingested: no ingest step, its ref is a parameter of its calibration.
        One enhancer is trained on the face pairs of every actor in an enhanced shot (the paper
        trains one model on all actors' pairs). Gaussian-splat face pairs (``pair_method:
        splat``) come after the actor's segments that measure their LQ range (:func:`_splat_pairs`).
    """
    requested = [spec.shot(n) for n in shots] if shots is not None else list(spec.shots)
    q = spec.quality_preset()

    def info(capture: str, why: str) -> CaptureInfo:
        if capture not in capture_info:
            raise ValueError(f"no capture info for capture {capture!r} ({why})")
        return capture_info[capture]

    # which segments of which capture are needed, and by whom
    needed_segments: dict[str, dict[str, Segment]] = {}   # capture -> {seg id -> Segment}
    shot_segments: dict[str, list[str]] = {}
    plans: dict[str, SegmentPlan] = {}
    for shot in requested:
        cap = shot.performance
        ci = info(cap, f"shown by shot {shot.name!r}")
        plan = plans.setdefault(cap, segment_plan_for(spec, cap, ci))
        try:
            segs = plan.segments_for_frames(_shot_take_frames(shot, ci.fps))
        except ValueError as exc:
            raise ValueError(f"shot {shot.name!r} (frames [{shot.frames[0]}, {shot.frames[1]}) at "
                             f"{shot.fps:g} fps, time offset {shot.time_offset_s:g} s) shows "
                             f"times capture {cap!r} does not cover: {exc}") from None
        bucket = needed_segments.setdefault(cap, {})
        for s in segs:
            bucket[s.id] = s
        shot_segments[shot.name] = [f"train-segment:{cap}:{s.id}" for s in segs]
    for cap, cs in sorted(spec.captures.items()):
        if cs.reconstruct:
            ci = info(cap, "reconstruct: true")
            plan = plans.setdefault(cap, segment_plan_for(spec, cap, ci))
            bucket = needed_segments.setdefault(cap, {})
            for s in plan.segments:
                bucket[s.id] = s

    enhanced = [s for s in requested if s.enhance]
    enhance_actors = sorted({a.name for s in enhanced for a in spec.shot_actors(s)})
    face_captures = {a: spec.actor(a).face_capture for a in enhance_actors}
    for actor in spec.actors:
        check_face_capture(spec, actor, capture_info)

    steps: list[Step] = []
    calibrated: dict[str, str] = {}

    def calibrate(cap: str, ci: CaptureInfo) -> str:
        """Ingest + calibration steps of a capture (once); returns its final calibration's id."""
        if cap in calibrated:
            return calibrated[cap]
        cs = spec.captures[cap]
        inputs: tuple[str, ...] = ()
        if cs.folder is not None:
            steps.append(Step(id=f"ingest:{cap}", parameters=Ingest(capture=cap, folder=cs.folder)))
            inputs = (f"ingest:{cap}",)
        rig = spec.rigs.get(cs.rig) if cs.rig else None
        steps.append(Step(id=f"calibrate-static:{cap}", inputs=inputs,
                          parameters=CalibrateStatic(capture=cap, capture_ref=cs.ref, rig=rig)))
        final = f"calibrate-static:{cap}"
        if ci.has_tracking_cameras:
            steps.append(Step(id=f"calibrate-tracking:{cap}", inputs=(*inputs, final),
                              parameters=CalibrateTracking(capture=cap, capture_ref=cs.ref)))
            final = f"calibrate-tracking:{cap}"
        calibrated[cap] = final
        return final

    for cap in sorted(needed_segments):
        ci = capture_info[cap]
        calib = calibrate(cap, ci)
        ingest = (f"ingest:{cap}",) if spec.captures[cap].folder is not None else ()
        plan = plans[cap]
        for seg in sorted(needed_segments[cap].values(), key=lambda s: s.index):
            points = f"dense-points:{cap}:{seg.id}"
            steps.append(Step(id=points, inputs=(*ingest, calib), parameters=DensePoints.for_segment(cap, seg, q)))
            steps.append(Step(id=f"train-segment:{cap}:{seg.id}", inputs=(*ingest, calib, points),
                              parameters=TrainSegment.for_segment(cap, seg, plan.overlap, q)))
    for shot in requested:
        steps.append(Step(id=f"render-shot:{shot.name}", inputs=tuple(shot_segments[shot.name]),
                          parameters=RenderShot(shot=shot.name, capture=shot.performance, frames=shot.frames,
                                                enhance=shot.enhance, shot_spec=shot.model_dump(mode="json"))))
    if enhanced:
        pair_ids = []
        for actor in enhance_actors:
            fc = face_captures[actor]
            info(fc, f"face capture of actor {actor!r}")
            # the interim pairs read the ingested frames alone: no calibration of the face capture
            # (the demo_face rig's 8 cameras, 45 degrees apart around a head, give the static SfM no
            # matches at all); the Gaussian-splat pairs calibrate it inside their flow, or take the
            # spec's face_calibration, and measure the LQ range in the actor's segments
            ingest: tuple[str, ...] = ()
            if spec.captures[fc].folder is not None:
                ingest = (f"ingest:{fc}",)
                if not any(st.id == ingest[0] for st in steps):
                    steps.append(Step(id=ingest[0], parameters=Ingest(capture=fc, folder=spec.captures[fc].folder)))
            pid = f"face-pairs:{actor}"
            pairs = FacePairs.for_actor(actor, fc, q)
            measured: tuple[str, ...] = ()
            if pairs.method == "splat":
                pairs, measured = _splat_pairs(spec, spec.actor(actor), pairs, capture_info, needed_segments)
            steps.append(Step(id=pid, inputs=(*ingest, *measured), parameters=pairs))
            pair_ids.append(pid)
        enhancer = "train-enhancer:" + "+".join(enhance_actors)
        steps.append(Step(id=enhancer, inputs=tuple(pair_ids), parameters=TrainEnhancer.for_actors(
            {a: spec.actor(a).prompt for a in enhance_actors}, q)))
        for shot in enhanced:
            steps.append(Step(id=f"enhance-shot:{shot.name}", inputs=(f"render-shot:{shot.name}", enhancer),
                              parameters=EnhanceShot.for_shot(shot.name, [a.name for a in spec.shot_actors(shot)], q)))
    _check_order(steps)
    return steps


def _splat_pairs(spec: ProductionSpec, actor: ActorSpec, pairs: FacePairs, capture_info: Mapping[str, CaptureInfo],
                 needed_segments: Mapping[str, Mapping[str, Segment]]) -> tuple[FacePairs, tuple[str, ...]]:
    """An actor's Gaussian-splat face-pairs parameters and the segment steps it measures the LQ range in.

    The face capture's calibration is the actor's ``face_calibration`` (``ground-truth`` refused for a
    capture known to carry none). The LQ range is measured in every segment this production trains
    of the actor's captures that carry ground truth (the head positions the count needs: a synthetic
    capture's true heads; a real capture has no head track yet), as the actor's ``index`` there, or
    the one its face capture names as its performer; with no such segment the preset's
    ``face_lq_gaussians``."""
    i = spec.actors.index(actor)
    fc = actor.face_capture
    if actor.face_calibration == GROUND_TRUTH and capture_info[fc].ground_truth is False:
        raise ValueError(f"actors[{i}].face_calibration: {GROUND_TRUTH}, but actor {actor.name!r}'s face capture "
                         f"{fc!r} carries no ground truth (only synthetic captures do): give its Calibration "
                         "(a store ref, as `volcap import-calibration` stores it) or leave it unset to calibrate "
                         "it by SfM")
    segments = tuple(f"train-segment:{c}:{seg.id}" for c in actor.captures
                     if c in needed_segments and capture_info[c].ground_truth
                     for seg in sorted(needed_segments[c].values(), key=lambda s: s.index))
    index = actor.index
    performer = capture_info[fc].performer
    if index is None and performer is not None:
        index = performer.actor
    return pairs.model_copy(update={"calibration": actor.face_calibration,
                                    "lq_range": "measured" if segments else "preset",
                                    "actor_index": index if segments else None}), segments


def _check_order(steps: Sequence[Step]) -> None:
    seen: set[str] = set()
    for s in steps:
        if s.id in seen:
            raise AssertionError(f"internal: step {s.id} planned twice")
        missing = [i for i in s.inputs if i not in seen]
        if missing:
            raise AssertionError(f"internal: step {s.id} before its inputs {missing}")
        seen.add(s.id)
