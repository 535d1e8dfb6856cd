"""Production tasks: assembling a performance from trained segments, rendering a shot over it, and
rendering a shot's truth from a synthetic capture."""

from __future__ import annotations

from tasks.contract import volcap_task
from volcap_core import reconstruction
from volcap_core.capture import Capture
from volcap_core.production.performance import Performance, PerformanceSegment
from volcap_core.production.shot import load_shot, render_shot_frames
from volcap_core.production.truth import render_truth_frames, truth_world_of
from volcap_core.records import MEDIA_EXR, ArtifactRef
from volcap_core.stage import stage_volume
from volcap_core.store import ArtifactStore


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


__all__ = ["assemble_performance", "render_shot", "render_shot_truth"]
