"""Production tasks: assembling a performance from trained segments, rendering a shot over it,
rendering a shot's truth from a synthetic capture, and scoring a shot against that truth."""

from __future__ import annotations

import json

from tasks.contract import volcap_task
from volcap_core import reconstruction
from volcap_core.capture import Capture
from volcap_core.contact_sheet import encode_png
from volcap_core.production.closeup import score_shot_exrs
from volcap_core.production.performance import Performance, PerformanceSegment
from volcap_core.production.shot import load_shot, render_shot_frames
from volcap_core.production.truth import render_truth_frames, truth_world_of
from volcap_core.records import MEDIA_EXR, MEDIA_PNG, ArtifactRef
from volcap_core.stage import stage_volume
from volcap_core.store import ArtifactStore
from volcap_core.synth.ground_truth import FACE_MARGIN_M


@volcap_task(name="assemble-performance", version="1")
def assemble_performance(store: str, name: str, capture: ArtifactRef, segments: list[ArtifactRef],
                         cores: list[list[int]]) -> ArtifactRef:
    """A :class:`Performance` from trained segment records (take order) and their core ranges."""
    s = ArtifactStore(store)
    records = [s.get_record(ref, reconstruction.SegmentModel) for ref in segments]
    for ref, rec in zip(segments, records):
        if rec.capture.digest != capture.digest:
            raise ValueError(f"segment {ref.digest} was trained on capture {rec.capture.digest}, "
                             f"not {capture.digest} (performance {name})")
    entries = tuple(PerformanceSegment(model=rec.model, frames=rec.frames, core=tuple(core))
                    for rec, core in zip(records, cores, strict=True))
    return s.put_record(Performance(name=name, capture=capture, fps=records[0].fps, segments=entries))


@volcap_task(name="render-shot", version="3", libraries=("torch", "OpenEXR"))
def render_shot(store: str, performance: ArtifactRef, shot: dict) -> ArtifactRef:
    """Every frame of ``shot`` (a shot's JSON, ``docs/shots.md``) over ``performance``: a tree of
    ``<frame:06d>.exr`` files, linear premultiplied RGBA half float cropped to the actors, the
    camera in each header, and from the second frame on the exact backward flow to the previous
    frame in half channels ``flow.x``, ``flow.y`` (none across a segment boundary; v3).
    ``content: stage`` shots render only the Gaussians inside the capture's stage volume (the
    performers, not the set)."""
    s = ArtifactStore(store)
    perf = s.get_record(performance, Performance)
    stage = stage_volume(s.get_record(perf.capture, Capture).rig.stage_size_m)
    return s.put_tree({name: s.put_bytes(exr, MEDIA_EXR)
                       for name, exr in render_shot_frames(load_shot(shot), perf, s.get_bytes, stage=stage)})


@volcap_task(name="render-truth", version="1", libraries=("numpy", "cv2", "OpenEXR"))
def render_shot_truth(store: str, capture: ArtifactRef, shot: dict, supersample: int = 2) -> ArtifactRef:
    """The truth of every frame of ``shot`` (a shot's JSON) from the synthetic ``capture``'s stored
    ground truth (:mod:`volcap_core.production.truth`): a tree of ``<frame:06d>.exr`` named like the
    shot's render frames, each encoded as they are (RGBA half, linear, premultiplied, cropped to its
    alpha, the camera in the header), at ``supersample`` x ``supersample`` samples per pixel.
    ``content: stage`` shots: the performers over nothing. A capture without synthetic ground truth
    is refused (``capture X has no synthetic ground truth``)."""
    s = ArtifactStore(store)
    world = truth_world_of(s, s.get_record(capture, Capture))
    return s.put_tree({name: s.put_bytes(exr, MEDIA_EXR)
                       for name, exr in render_truth_frames(load_shot(shot), world, supersample=supersample)})


@volcap_task(name="score-shot", version="1", libraries=("torch", "numpy", "OpenEXR", "OpenImageIO", "cv2"))
def score_shot(store: str, truth: ArtifactRef, render: ArtifactRef, capture: ArtifactRef,
               enhanced: ArtifactRef | None = None, actors: list[int] | None = None,
               margin_m: float = FACE_MARGIN_M) -> ArtifactRef:
    """Score a shot of a synthetic capture against its truth
    (:func:`volcap_core.production.closeup.score_shot_exrs`; ``docs/shots.md``, "Scoring a shot").

    ``truth``, ``render``, ``enhanced``: trees of ``<frame:06d>.exr`` (the truth renderer's, the
    render-shot task's, the enhancer's), the same names in each; ``capture``: the capture record,
    whose ground truth's ``scene.json`` gives the faces (``actors``: their indices, None = all).
    Returns the JSON of the scores with ``contact_sheet``, the ref of the PNG sheet
    (truth | render | enhanced | errors at the first, middle and last frame)."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    if cap.ground_truth is None:
        raise ValueError(f"capture {cap.name} is not synthetic: it has no truth to score a shot against")
    gt = s.get_tree(cap.ground_truth)
    if "scene.json" not in gt:
        raise ValueError(f"capture {cap.name}: its ground truth has no scene.json")
    scene = json.loads(s.get_bytes(gt["scene.json"].digest))

    def frames(tree: ArtifactRef) -> list[tuple[str, bytes]]:
        return [(name, s.get_bytes(e.digest)) for name, e in sorted(s.get_tree(tree).items())]

    scores, sheet = score_shot_exrs(frames(truth), frames(render), scene,
                                    enhanced=frames(enhanced) if enhanced is not None else None,
                                    actors=actors, margin_m=margin_m)
    scores["contact_sheet"] = s.put_bytes(encode_png(sheet), MEDIA_PNG).model_dump(mode="json")
    return s.put_json(scores)


__all__ = ["assemble_performance", "render_shot", "render_shot_truth", "score_shot"]
