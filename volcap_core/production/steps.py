"""The step kinds of a production plan, each with its parameters as a pydantic model.

A :class:`Step` is one unit of work of a plan (:func:`~volcap_core.production.spec.needed_steps`):
a stable id, the ids of the steps whose outputs it reads, and its parameters, an instance of its
kind's model below. The model is the kind: ``Step.kind`` is its parameters' ``kind``, and each
model builds itself from what the planner knows (a segment, an actor, a shot) and the quality
preset, so what a kind takes from the preset is written once, here.

The parameters are part of a step's fingerprint in the production journal
(:mod:`~volcap_core.production.journal`): a changed field re-runs the step. The flows layer keeps
its own table of the same kinds (``flows/production.py``: the tasks each runs, what else its
fingerprint reads, how it runs).
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, SerializeAsAny, computed_field, create_model

from volcap_core.production.presets import (ENHANCER_TRAINING_FIELDS, ENHANCING_FIELDS, TRAINING_FIELDS,
                                            QualityPreset)
from volcap_core.production.segments import Segment

__all__ = ["STEP_KINDS", "CalibrateStatic", "CalibrateTracking", "DensePoints", "EnhanceShot", "FacePairs", "Ingest",
           "RenderShot", "Step", "StepKind", "StepParameters", "TrainEnhancer", "TrainSegment"]

StepKind = Literal["ingest", "calibrate-static", "calibrate-tracking", "dense-points",
                   "train-segment", "render-shot", "face-pairs", "train-enhancer", "enhance-shot"]


class StepParameters(BaseModel):
    """The parameters of one step; a subclass per kind names it in ``kind``."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: ClassVar[StepKind]

    def as_json(self) -> dict[str, Any]:
        """The parameters as plain JSON: what the journal fingerprints and ``volcap plan --json`` shows."""
        return self.model_dump(mode="json")


def _preset_fields(name: str, fields: tuple[str, ...]) -> type[StepParameters]:
    """A parameters model of the :class:`~volcap_core.production.presets.QualityPreset` fields
    ``fields``, typed as the preset types them (the step carries them so a changed one re-runs it)."""
    preset = QualityPreset.model_fields
    return create_model(name, __base__=StepParameters, **{f: (preset[f].annotation, ...) for f in fields})


class Ingest(StepParameters):
    """Convert a capture folder into a Capture record (``flows/ingest.py``)."""

    kind: ClassVar[StepKind] = "ingest"
    capture: str
    folder: str


class _CaptureSource(StepParameters):
    """A calibration of ``capture``: ingested by the plan, or already in the store (``capture_ref``,
    a ref name or digest; left out of the JSON when the plan ingests it)."""

    capture: str
    capture_ref: str | None = None

    def as_json(self) -> dict[str, Any]:
        out = super().as_json()
        if self.capture_ref is None:
            del out["capture_ref"]
        return out


class CalibrateStatic(_CaptureSource):
    """Calibrate the static cameras; the capture's final calibration when it has no tracking cameras.
    ``rig``: the rig the spec names for the capture (checked against the capture's own)."""

    kind: ClassVar[StepKind] = "calibrate-static"
    rig: str | None


class CalibrateTracking(_CaptureSource):
    """Calibrate the tracking cameras per frame on the static calibration: the final calibration."""

    kind: ClassVar[StepKind] = "calibrate-tracking"


class DensePoints(StepParameters):
    """Dense points of take indices ``[frames[0], frames[1])``, matched at ``dense_scale`` of the
    footage's resolution."""

    kind: ClassVar[StepKind] = "dense-points"
    capture: str
    frames: tuple[int, int]
    dense_scale: float

    @classmethod
    def for_segment(cls, capture: str, segment: Segment, quality: QualityPreset) -> "DensePoints":
        return cls(capture=capture, frames=segment.frames, dense_scale=quality.dense_scale)


class TrainSegment(_preset_fields("TrainingSchedule", TRAINING_FIELDS)):
    """Train one segment of a plan: its frames, its core (the frames no neighbour shares), its
    Gaussian budget (``gaussians``, the training's cap) and estimated memory, and the preset's
    training fields (:data:`~volcap_core.production.presets.TRAINING_FIELDS`)."""

    kind: ClassVar[StepKind] = "train-segment"
    capture: str
    segment: int
    frames: tuple[int, int]
    core: tuple[int, int]
    overlap: int
    gaussians: int
    memory_bytes: int

    def as_json(self) -> dict[str, Any]:
        # the alpha loss's, the frozen set's and MCMC's opacity regulariser's fields at their
        # defaults are left out: the journals of plans made before they existed keep their fingerprints
        out = super().as_json()
        for name in ("mask_alpha_weight", "mask_alpha_every", "set_frozen_from", "opacity_reg"):
            if out.get(name) == QualityPreset.model_fields[name].default:
                del out[name]
        return out

    @classmethod
    def for_segment(cls, capture: str, segment: Segment, overlap: int, quality: QualityPreset) -> "TrainSegment":
        return cls(capture=capture, segment=segment.index, frames=segment.frames, core=segment.core,
                   overlap=overlap, gaussians=segment.gaussians, memory_bytes=segment.memory_bytes,
                   **quality.training())


class RenderShot(StepParameters):
    """Render a shot over the performance of its segments; ``shot_spec`` is the shot's JSON
    (``docs/shots.md``), what the render task reads."""

    kind: ClassVar[StepKind] = "render-shot"
    shot: str
    capture: str
    frames: tuple[int, int]
    enhance: bool
    shot_spec: dict[str, Any]


class FacePairs(StepParameters):
    """An actor's LQ/HQ training pairs from their Face Rig capture, at the preset's Face Rig sizes;
    ``method`` the preset's ``pair_method``: ``splat`` (Gaussian-splat pairs, the facerig_pairs
    flow) or ``interim`` (degraded frames; left out of the JSON, so the fingerprints of the plans
    made before the field existed stay).

    Gaussian-splat pairs only (each left out of the JSON while unset): ``calibration``, the spec's
    ``actors[].face_calibration`` (a Calibration ref, or ``ground-truth``; None: the calibrate
    flow); ``lq_range`` ``measured`` when the LQ range is counted in the actor's Scene Rig segments
    (the step's ``train-segment`` inputs), as actor ``actor_index`` of their ground truth (None:
    its only actor), else the preset's ``face_lq_gaussians``."""

    kind: ClassVar[StepKind] = "face-pairs"
    actor: str
    face_capture: str
    subsequences: int
    subsequence_frames: int
    camera_paths: int
    hq_gaussians_per_frame: int
    lq_gaussians: tuple[int, int]
    resolution: int
    window: Literal["performer", "head"]
    method: Literal["splat", "interim"] = "interim"
    calibration: str | None = None
    lq_range: Literal["measured", "preset"] = "preset"
    actor_index: int | None = None

    @classmethod
    def for_actor(cls, actor: str, face_capture: str, quality: QualityPreset) -> "FacePairs":
        return cls(actor=actor, face_capture=face_capture, subsequences=quality.face_subsequences,
                   subsequence_frames=quality.face_subsequence_frames, camera_paths=quality.face_camera_paths,
                   hq_gaussians_per_frame=quality.face_hq_gaussians_per_frame,
                   lq_gaussians=quality.face_lq_gaussians, resolution=quality.pair_resolution,
                   window=quality.pair_window, method=quality.pair_method)

    def as_json(self) -> dict[str, Any]:
        out = super().as_json()
        if self.method == "interim":
            del out["method"]
        for name, unset in (("calibration", None), ("lq_range", "preset"), ("actor_index", None)):
            if out[name] == unset:
                del out[name]
        return out


class TrainEnhancer(_preset_fields("EnhancerTraining", ENHANCER_TRAINING_FIELDS)):
    """One detail enhancer on the pairs of ``actors``, each with their prompt, and the preset's
    enhancer training fields (:data:`~volcap_core.production.presets.ENHANCER_TRAINING_FIELDS`)."""

    kind: ClassVar[StepKind] = "train-enhancer"
    actors: tuple[str, ...]
    steps: int
    prompts: dict[str, str | None]

    @classmethod
    def for_actors(cls, prompts: dict[str, str | None], quality: QualityPreset) -> "TrainEnhancer":
        return cls(actors=tuple(prompts), steps=quality.enhancer_steps, prompts=prompts,
                   **quality.enhancer_training())


class EnhanceShot(_preset_fields("Enhancing", ENHANCING_FIELDS)):
    """Enhance a rendered shot's frames in order; ``actors``: those it features (the first one's
    prompt is the shot's), and the preset's sampling and flow fields
    (:data:`~volcap_core.production.presets.ENHANCING_FIELDS`)."""

    kind: ClassVar[StepKind] = "enhance-shot"
    shot: str
    actors: tuple[str, ...]

    @classmethod
    def for_shot(cls, shot: str, actors: list[str], quality: QualityPreset) -> "EnhanceShot":
        return cls(shot=shot, actors=tuple(actors), **quality.enhancing())


#: Every step kind's parameters model, by kind, in the order a plan lists them.
STEP_KINDS: dict[str, type[StepParameters]] = {
    m.kind: m for m in (Ingest, CalibrateStatic, CalibrateTracking, DensePoints, TrainSegment, RenderShot,
                        FacePairs, TrainEnhancer, EnhanceShot)}


class Step(BaseModel):
    """One unit of work of a plan. ``id`` is stable (``<kind>:<subject>``): the same spec and
    capture facts always give the same ids, so a plan can be compared with the journal.
    ``inputs``: the ids of the steps whose outputs it reads."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str
    inputs: tuple[str, ...] = ()
    parameters: SerializeAsAny[StepParameters]

    @computed_field  # type: ignore[prop-decorator]
    @property
    def kind(self) -> StepKind:
        return self.parameters.kind
