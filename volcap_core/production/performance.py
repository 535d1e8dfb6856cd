"""A reconstructed performance: the segment models of one capture, rendered at any time.

A :class:`Performance` record lists the trained Poly4DGS segment models (refs to their
safetensors blobs) with the take indices each was trained on. Rendering at time ``t`` (seconds on
the take's clock, ``take index / fps``) uses the one segment that owns ``t``; inside an overlap it
renders both neighbours and cross-fades their **premultiplied RGBA** with smoothstep weights
(:func:`volcap_core.production.segments.blend_weights`), so a camera path crossing a segment
boundary does not pop.

Why blend images and not Gaussians (the alternative: concatenate both Gaussian sets with opacities
scaled by ``w`` and ``1 − w``): two segments reconstruct the same surfaces with different
Gaussians. Scaling opacities is not a cross-fade: an opaque surface seen through two half-opacity
copies gets ``α = 1 − (1 − o/2)²`` (0.75 for ``o ≈ 1``), so the actor turns partly transparent in
the middle of every overlap, and the two sets interleave in depth, so the composite is a
depth-sorted mix rather than a convex combination of two valid renders. The image blend is exact at
``w ∈ {0, 1}``, keeps alpha correct (a convex combination of premultiplied RGBA is a valid
premultiplied RGBA), and costs a second render only on the few frames of an overlap.
``tests/production/test_performance.py`` measures both the pop and the alpha dip.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import ClassVar

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator

from volcap_core.production.segments import SegmentPlan, blend_weights, check_layout
from volcap_core.records import ArtifactRef, Record
from volcap_core.stage import Box
from volcap_core.splat.camera import Camera
from volcap_core.splat.model import Poly4DGS, evaluate
from volcap_core.splat.render import Backend, render

__all__ = ["Performance", "PerformanceSegment", "gaussians_in_volume", "render_performance", "segments_at"]


class PerformanceSegment(BaseModel):
    """One trained segment: its model blob, the take indices ``[a, b)`` it was trained on and the
    core range no neighbour shares."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    model: ArtifactRef
    frames: tuple[int, int]
    core: tuple[int, int]

    @property
    def id(self) -> str:
        return f"{self.frames[0]:06d}-{self.frames[1]:06d}"


class Performance(Record):
    """A capture's reconstruction: segment models in take order.

    ``capture`` is the ref of the ingested :class:`~volcap_core.capture.Capture` record; ``fps`` its
    frame rate (time ``t`` in seconds is take index ``t · fps``).
    """

    kind: ClassVar[str] = "performance"
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    capture: ArtifactRef
    fps: float = Field(gt=0)
    segments: tuple[PerformanceSegment, ...] = Field(min_length=1)

    @model_validator(mode="after")
    def _layout(self) -> "Performance":
        spans = [s.frames for s in self.segments]
        check_layout(spans, None, None)
        for i, s in enumerate(self.segments):
            a, b = s.frames
            c0, c1 = s.core
            if not (a <= c0 <= c1 <= b):
                raise ValueError(f"segment {i}: core {s.core} is not inside frames {s.frames}")
        return self

    @classmethod
    def from_plan(cls, name: str, capture: ArtifactRef, fps: float, plan: SegmentPlan,
                  models: Sequence[ArtifactRef]) -> "Performance":
        """The performance of a trained :class:`SegmentPlan` (one model per segment, in order)."""
        if len(models) != len(plan.segments):
            raise ValueError(f"{len(models)} models for {len(plan.segments)} planned segments")
        segments = tuple(PerformanceSegment(model=m, frames=s.frames, core=s.core)
                         for s, m in zip(plan.segments, models, strict=True))
        return cls(name=name, capture=capture, fps=fps, segments=segments)

    @property
    def frames(self) -> tuple[int, int]:
        """Take indices ``[a, b)`` the performance covers."""
        return self.segments[0].frames[0], self.segments[-1].frames[1]


def segments_at(performance: Performance, t: float, *,
                tolerance_frames: float = 0.5) -> list[tuple[PerformanceSegment, float]]:
    """The segments to render at ``t`` seconds and their weights (sum 1, smooth in ``t``).

    Inside a core range: that segment, weight 1. Across an overlap: both neighbours, weights going
    smoothly from 1 to 0 (:func:`~volcap_core.production.segments.blend_weights`). ``t`` may be up
    to ``tolerance_frames`` outside the covered frames; beyond, ``ValueError``.
    """
    spans = [s.frames for s in performance.segments]
    try:
        weights = blend_weights(spans, t * performance.fps, tolerance=tolerance_frames)
    except ValueError as exc:
        raise ValueError(f"performance {performance.name}: t = {t:g} s: {exc}") from None
    return [(performance.segments[i], w) for i, w in weights]


def gaussians_in_volume(gaussians, volume: Box | None):
    """The :class:`~volcap_core.splat.Gaussians3D` whose centre is inside ``volume`` (all of them
    when None): the selection :func:`render_performance` renders and the shot's flow follows."""
    if volume is None:
        return gaussians
    lo = torch.tensor(volume[0], dtype=gaussians.means.dtype, device=gaussians.means.device)
    hi = torch.tensor(volume[1], dtype=gaussians.means.dtype, device=gaussians.means.device)
    inside = ((gaussians.means >= lo) & (gaussians.means <= hi)).all(dim=1)
    return gaussians.select(torch.nonzero(inside).squeeze(1))


def render_performance(performance: Performance, load_model: Callable[[ArtifactRef], Poly4DGS],
                       camera: Camera, t: float, backend: Backend = "auto", *,
                       background: torch.Tensor | None = None, volume: Box | None = None
                       ) -> dict[str, torch.Tensor]:
    """Render the performance at ``t`` seconds into ``camera``.

    Args:
        load_model: ref → model on the device to render on. Called once per contributing segment
            per call: cache it (e.g. ``functools.lru_cache``) when rendering many frames.
        backend: as :func:`volcap_core.splat.render.render`.
        background: ``[3]`` linear colour composited under the blend (default: none, so ``rgb``
            is premultiplied by ``alpha``).
        volume: ``((x0, y0, z0), (x1, y1, z1))``: render only the Gaussians whose centre at ``t``
            is inside this box (:func:`~volcap_core.stage.stage_volume`: the performers without the set); None: all.
    Returns:
        ``{"rgb": [H,W,3], "alpha": [H,W,1], "depth": [H,W,1]}``: ``rgb`` and ``alpha`` are the
        weighted sums of the segments' premultiplied renders; ``depth`` the alpha-weighted mean of
        their depths.
    """
    parts = segments_at(performance, t)
    rgb = alpha = depth_acc = None
    with torch.no_grad():
        for seg, w in parts:
            model = load_model(seg.model)
            out = render(gaussians_in_volume(evaluate(model, t), volume), camera, backend=backend)
            wa = w * out["alpha"]
            if rgb is None:
                rgb, alpha, depth_acc = w * out["rgb"], wa, wa * out["depth"]
            else:
                rgb, alpha, depth_acc = rgb + w * out["rgb"], alpha + wa, depth_acc + wa * out["depth"]
        depth = depth_acc / alpha.clamp(min=1e-10)
        if background is not None:
            rgb = rgb + (1.0 - alpha) * background.to(rgb)
    return {"rgb": rgb, "alpha": alpha, "depth": depth}
