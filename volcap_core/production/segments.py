"""Segment planning: split a take into overlapping segments that each fit one GPU.

The paper (§"Poly4DGS") observes that the number of Gaussians needed to represent a sequence at a
given quality grows about **linearly with its length**, and trains fixed-length segments
independently, one per GPU. This module turns that into a plan:

1. A :class:`SegmentBudget` says how many Gaussians a segment of ``L`` frames needs,
   ``N(L) = base_gaussians + gaussians_per_frame · L``, and how many one segment may have: an explicit
   ``max_gaussians``, or as many as fit a GPU of ``gpu_memory_bytes`` according to the memory model
   below (the smaller of the two when both are given).
2. Inverting ``N(L) <= cap`` gives the longest allowed segment ``L_max``.
3. :func:`plan_segments` covers ``[start, end)`` with the fewest segments of at most ``L_max``
   frames, neighbours sharing ``overlap`` frames, lengths as equal as the constraints allow.

Memory model (:func:`estimate_training_memory`, all terms in bytes, ``P`` = floats per Gaussian of
the Poly4DGS parameter layout, ``N`` Gaussians, ``W×H`` training resolution)::

    parameters    = 4 P N                      fp32 parameters
    optimizer     = 3 · 4 P N                  gradient + Adam first and second moments
    activations   = 2 · 4 (A + S) N            the slice at t (A floats) and the projection (S) with
                                               their gradients (an upper bound: all Gaussians alive)
    intersections = 24 · τ(H) · N              gsplat's (tile, depth) keys + ids, double-buffered sort
    image         = 384 · W H                  render, alpha, target, grids, sRGB/SSIM maps, grads
    fixed         = 1 GiB                      CUDA context, kernels, allocator slack

with ``A = 3 + 4 + 3 + 1 + 3K + (3 n_μ + 4 n_q + 3 n_s + n_o + 1)`` (mean, quaternion, scale,
opacity, SH of K bases, and the polynomial temporaries), ``S = 30`` (2D mean, conic, depth, radii,
compensation, SH basis and colour) and ``τ(H) = (2 · 3σ_px / 16 + 1)²`` tiles per Gaussian, the
screen footprint of a splat of ``σ_px = 2 px · H / 1080`` mean standard deviation in 16 px tiles.
For the paper's degrees (2, 1, 0, 2) and SH degree 3, ``P = 72``: ~1.15 kB of state and ~0.8 kB of
working memory per Gaussian, ~2 kB in all at 1080p. Every constant is a field of
:class:`MemoryModel`; the estimate is monotone in ``N``, ``W`` and ``H`` (tested). It is a
planning figure, not a measurement: calibrate the model on the GPU you run on.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from typing import ClassVar

from pydantic import BaseModel, ConfigDict, Field, model_validator

from volcap_core.records import Record
from volcap_core.splat.model import Poly4DGSConfig
from volcap_core.splat.sh import num_sh_bases

__all__ = [
    "DEFAULT_OVERLAP",
    "MemoryEstimate",
    "MemoryModel",
    "Segment",
    "SegmentBudget",
    "SegmentPlan",
    "blend_weights",
    "estimate_training_memory",
    "floats_per_gaussian",
    "max_gaussians_for_memory",
    "plan_segments",
    "smoothstep",
]

#: Frames shared by neighbouring segments unless told otherwise (each shared frame is blended).
DEFAULT_OVERLAP = 3
GIB = 1 << 30


# ------------------------------------------------------------------------------------------------
# Memory model


class MemoryModel(BaseModel):
    """The constants of the training-memory estimate (module doc). Override per GPU type."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    bytes_per_float: int = Field(4, gt=0, description="fp32 parameters and states")
    optimizer_copies: int = Field(3, ge=0, description="gradient + Adam m + Adam v per parameter")
    projection_floats: int = Field(30, ge=0, description="per-Gaussian projection/SH temporaries")
    activation_grad_factor: float = Field(2.0, ge=1.0, description="forward + backward copies")
    splat_sigma_px_1080: float = Field(2.0, gt=0, description="mean splat σ at 1080 image rows")
    sigma_extent: float = Field(3.0, gt=0, description="footprint radius in σ")
    tile_size: int = Field(16, gt=0, description="rasterizer tile edge (gsplat: 16 px)")
    bytes_per_intersection: int = Field(24, ge=0, description="int64 key + int32 id, ×2 for sort")
    bytes_per_pixel: int = Field(384, ge=0, description="image-sized buffers of one step")
    fixed_bytes: int = Field(GIB, ge=0, description="CUDA context, kernels, allocator slack")
    usable_fraction: float = Field(0.85, gt=0, le=1, description="share of a GPU a plan may fill")

    def tiles_per_gaussian(self, height: int) -> float:
        """Mean number of tiles a splat's footprint touches at ``height`` image rows."""
        sigma_px = self.splat_sigma_px_1080 * height / 1080.0
        return (2.0 * self.sigma_extent * sigma_px / self.tile_size + 1.0) ** 2


class MemoryEstimate(BaseModel):
    """A training-memory estimate, term by term (bytes)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    num_gaussians: int
    width: int
    height: int
    parameters: int
    optimizer: int
    activations: int
    intersections: int
    image: int
    fixed: int

    @property
    def total(self) -> int:
        return (self.parameters + self.optimizer + self.activations + self.intersections
                + self.image + self.fixed)


def floats_per_gaussian(config: Poly4DGSConfig) -> int:
    """``P``: stored floats per Gaussian of ``config``'s parameter layout (72 for the paper's)."""
    return sum(math.prod(shape) for shape in config.param_shapes().values())


def _activation_floats(config: Poly4DGSConfig) -> int:
    """``A``: floats of one Gaussian's slice at time t plus the polynomial temporaries."""
    c = config
    sliced = 3 + 4 + 3 + 1 + 3 * num_sh_bases(c.sh_degree)
    temporaries = 3 * c.mean_degree + 4 * c.quat_degree + 3 * c.scale_degree + c.opacity_degree
    return sliced + temporaries + (1 if c.temporal else 0)


def _per_gaussian_bytes(height: int, config: Poly4DGSConfig, model: MemoryModel) -> float:
    b, p = model.bytes_per_float, floats_per_gaussian(config)
    state = b * p * (1 + model.optimizer_copies)
    work = model.activation_grad_factor * b * (_activation_floats(config) + model.projection_floats)
    isect = model.bytes_per_intersection * model.tiles_per_gaussian(height)
    return state + work + isect


def estimate_training_memory(num_gaussians: int, width: int, height: int, *,
                             config: Poly4DGSConfig | None = None,
                             model: MemoryModel | None = None) -> MemoryEstimate:
    """GPU memory to train ``num_gaussians`` Gaussians on ``width × height`` views (module doc)."""
    if num_gaussians < 0:
        raise ValueError(f"num_gaussians must be >= 0, got {num_gaussians}")
    if width <= 0 or height <= 0:
        raise ValueError(f"resolution must be positive, got {width}x{height}")
    config = config or Poly4DGSConfig.paper()
    model = model or MemoryModel()
    b, p, n = model.bytes_per_float, floats_per_gaussian(config), num_gaussians
    work = model.activation_grad_factor * b * (_activation_floats(config) + model.projection_floats)
    return MemoryEstimate(
        num_gaussians=n, width=width, height=height,
        parameters=b * p * n,
        optimizer=b * p * n * model.optimizer_copies,
        activations=math.ceil(work * n),
        intersections=math.ceil(model.bytes_per_intersection * model.tiles_per_gaussian(height) * n),
        image=model.bytes_per_pixel * width * height,
        fixed=model.fixed_bytes,
    )


def max_gaussians_for_memory(gpu_memory_bytes: int, width: int, height: int, *,
                             config: Poly4DGSConfig | None = None,
                             model: MemoryModel | None = None) -> int:
    """The most Gaussians whose estimate fits ``usable_fraction`` of ``gpu_memory_bytes``.

    Raises ``ValueError`` when not even the resolution-dependent part fits."""
    config = config or Poly4DGSConfig.paper()
    model = model or MemoryModel()
    empty = estimate_training_memory(0, width, height, config=config, model=model).total
    usable = gpu_memory_bytes * model.usable_fraction
    if usable <= empty:
        raise ValueError(
            f"a GPU of {gpu_memory_bytes / GIB:.1f} GiB ({model.usable_fraction:.0%} usable) cannot "
            f"train at {width}x{height}: the image buffers and fixed overhead alone need "
            f"{empty / GIB:.2f} GiB")
    n = int((usable - empty) // _per_gaussian_bytes(height, config, model))
    # the estimate rounds each term up: step down until it fits exactly
    while n > 0 and estimate_training_memory(n, width, height, config=config,
                                             model=model).total > usable:
        n -= 1
    return n


# ------------------------------------------------------------------------------------------------
# Budget and plan records


class SegmentBudget(BaseModel):
    """How many Gaussians a segment needs and may have.

    ``N(L) = base_gaussians + gaussians_per_frame · L`` for a segment of ``L`` frames (the paper's
    linear growth). The cap is ``max_gaussians``, or what fits ``gpu_memory_bytes`` at
    ``width × height`` (:func:`max_gaussians_for_memory`), the smaller when both are set.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    gaussians_per_frame: int = Field(gt=0)
    base_gaussians: int = Field(0, ge=0)
    max_gaussians: int | None = Field(None, gt=0)
    gpu_memory_bytes: int | None = Field(None, gt=0)
    width: int = Field(3840, gt=0, description="training resolution (for the memory estimate)")
    height: int = Field(2160, gt=0)
    config: Poly4DGSConfig = Field(default_factory=Poly4DGSConfig.paper)
    memory: MemoryModel = Field(default_factory=MemoryModel)

    @model_validator(mode="after")
    def _some_cap(self) -> "SegmentBudget":
        if self.max_gaussians is None and self.gpu_memory_bytes is None:
            raise ValueError("a segment budget needs max_gaussians or gpu_memory_bytes (or both)")
        return self

    def gaussians_for(self, length: int) -> int:
        return self.base_gaussians + self.gaussians_per_frame * length

    def gaussian_cap(self) -> int:
        caps = []
        if self.max_gaussians is not None:
            caps.append(self.max_gaussians)
        if self.gpu_memory_bytes is not None:
            caps.append(max_gaussians_for_memory(self.gpu_memory_bytes, self.width, self.height,
                                                 config=self.config, model=self.memory))
        return min(caps)

    def max_segment_length(self) -> int:
        """``L_max = floor((cap - base) / per_frame)``: the longest segment within the cap."""
        cap = self.gaussian_cap()
        length = (cap - self.base_gaussians) // self.gaussians_per_frame
        if length < 1:
            raise ValueError(
                f"the budget allows no frame per segment: cap {cap} Gaussians, base "
                f"{self.base_gaussians}, {self.gaussians_per_frame} per frame")
        return length

    def memory_for(self, num_gaussians: int) -> MemoryEstimate:
        return estimate_training_memory(num_gaussians, self.width, self.height,
                                        config=self.config, model=self.memory)


class Segment(BaseModel):
    """One segment of a plan: trained on take indices ``[frames[0], frames[1])``; ``core`` is the
    part no neighbour shares (empty for an interior segment exactly ``2·overlap`` long)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    index: int = Field(ge=0)
    frames: tuple[int, int]
    core: tuple[int, int]
    gaussians: int = Field(gt=0, description="Gaussian budget (MCMC cap) of this segment")
    memory_bytes: int = Field(ge=0, description="estimated peak GPU memory of its training")

    @property
    def id(self) -> str:
        """Stable name, e.g. ``000120-000245``: the frames, zero-padded."""
        return f"{self.frames[0]:06d}-{self.frames[1]:06d}"

    @property
    def length(self) -> int:
        return self.frames[1] - self.frames[0]


class SegmentPlan(Record):
    """How a take's frame range is split into segments (see module doc). Deterministic: the same
    range, budget and overlap always give the same plan (and the same digest)."""

    kind: ClassVar[str] = "segment-plan"
    frames: tuple[int, int]
    overlap: int = Field(ge=0)
    max_length: int = Field(gt=0)
    budget: SegmentBudget
    segments: tuple[Segment, ...]

    @model_validator(mode="after")
    def _consistent(self) -> "SegmentPlan":
        check_layout([s.frames for s in self.segments], self.frames, self.overlap)
        n = len(self.segments)
        for i, s in enumerate(self.segments):
            if s.index != i:
                raise ValueError(f"segment {i} has index {s.index}")
            if s.core != core_range(s.frames, self.overlap, first=i == 0, last=i == n - 1):
                raise ValueError(f"segment {i}: core {s.core} does not match frames {s.frames} "
                                 f"with overlap {self.overlap}")
            if s.length > self.max_length:
                raise ValueError(f"segment {i} is {s.length} frames, over max_length "
                                 f"{self.max_length}")
        return self

    def segment_frames(self) -> list[tuple[int, int]]:
        return [s.frames for s in self.segments]

    def segments_for_frames(self, frames: Sequence[float]) -> list[Segment]:
        """The segments that contribute (non-zero blend weight) to any of ``frames`` (take
        indices, fractional allowed), in plan order: what rendering those frames needs."""
        spans = self.segment_frames()
        used: set[int] = set()
        for f in frames:
            used.update(i for i, _ in blend_weights(spans, f))
        return [self.segments[i] for i in sorted(used)]


def core_range(frames: tuple[int, int], overlap: int, *, first: bool, last: bool) -> tuple[int, int]:
    a, b = frames
    return (a if first else a + overlap, b if last else b - overlap)


def check_layout(spans: Sequence[tuple[int, int]], frames: tuple[int, int] | None,
                 overlap: int | None) -> None:
    """Refuse segment spans that do not tile a range in order with disjoint blend zones.

    ``frames`` (when given): the first span starts and the last ends there. ``overlap`` (when
    given): neighbours share exactly that many frames; otherwise any sharing ``>= 0`` is accepted.
    """
    if not spans:
        raise ValueError("no segments")
    for i, (a, b) in enumerate(spans):
        if b <= a:
            raise ValueError(f"segment {i}: empty frame range [{a}, {b})")
    if frames is not None and (spans[0][0] != frames[0] or spans[-1][1] != frames[1]):
        raise ValueError(f"segments cover [{spans[0][0]}, {spans[-1][1]}), not the plan's "
                         f"[{frames[0]}, {frames[1]})")
    for i in range(len(spans) - 1):
        (a0, b0), (a1, b1) = spans[i], spans[i + 1]
        shared = b0 - a1
        if a1 <= a0 or b1 <= b0:
            raise ValueError(f"segments {i} {spans[i]} and {i + 1} {spans[i + 1]} are not in order")
        if shared < 0:
            raise ValueError(f"gap between segment {i} (ends {b0}) and {i + 1} (starts {a1})")
        if overlap is not None and shared != overlap:
            raise ValueError(f"segments {i} and {i + 1} share {shared} frames, not {overlap}")
        if i + 2 < len(spans) and b0 > spans[i + 2][0]:
            raise ValueError(f"segments {i} and {i + 2} share frames: three segments would blend")


def plan_segments(frames: tuple[int, int], budget: SegmentBudget, *,
                  overlap: int = DEFAULT_OVERLAP, max_length: int | None = None) -> SegmentPlan:
    """Cover take indices ``[frames[0], frames[1])`` with the fewest segments the budget allows.

    Args:
        frames: ``(start, end)``, end exclusive.
        budget: Gaussians per frame and the per-segment cap (:class:`SegmentBudget`).
        overlap: frames shared by neighbours (default :data:`DEFAULT_OVERLAP`); the renderer blends
            across them (:func:`blend_weights`).
        max_length: an extra cap on the segment length (frames), e.g. a preview preset's.
    Returns:
        A :class:`SegmentPlan`. A range no longer than ``L_max`` is one segment. Lengths differ by
        at most one frame where the overlap constraints allow it (interior segments must keep
        ``2·overlap`` frames so their two blend zones stay apart).
    Raises:
        ValueError: empty range, negative overlap, ``overlap >= L_max``, or
            ``L_max < 2·overlap + 1`` (an interior segment could own no frame).
    """
    start, end = int(frames[0]), int(frames[1])
    if end <= start:
        raise ValueError(f"empty frame range [{start}, {end})")
    if overlap < 0:
        raise ValueError(f"overlap must be >= 0 frames, got {overlap}")
    limit = budget.max_segment_length()
    if max_length is not None:
        if max_length < 1:
            raise ValueError(f"max_length must be >= 1 frame, got {max_length}")
        limit = min(limit, max_length)
    if overlap >= limit:
        raise ValueError(f"overlap of {overlap} frames >= the maximum segment length of {limit} "
                         f"frames (from the budget{' and max_length' if max_length else ''}): "
                         "neighbours would share whole segments")
    if limit < 2 * overlap + 1:
        raise ValueError(f"the maximum segment length ({limit} frames) must be at least "
                         f"2 × overlap + 1 = {2 * overlap + 1}: an interior segment shares "
                         f"{overlap} frames with each neighbour and needs a frame of its own")
    total = end - start
    if total <= limit:
        lengths = [total]
    else:
        n = -(-(total - overlap) // (limit - overlap))  # ceil: the fewest segments
        lengths = _balanced_lengths(total + (n - 1) * overlap, n, overlap)
        if max(lengths) > limit:  # cannot happen with limit >= 2·overlap + 1 (tested); guard
            raise AssertionError(f"internal: lengths {lengths} exceed {limit}")
    segments, a, n = [], start, len(lengths)
    for i, length in enumerate(lengths):
        span = (a, a + length)
        g = budget.gaussians_for(length)
        segments.append(Segment(index=i, frames=span,
                                core=core_range(span, overlap, first=i == 0, last=i == n - 1),
                                gaussians=g, memory_bytes=budget.memory_for(g).total))
        a = span[1] - overlap
    return SegmentPlan(frames=(start, end), overlap=overlap, max_length=limit, budget=budget,
                       segments=tuple(segments))


def _balanced_lengths(total: int, n: int, overlap: int) -> list[int]:
    """``n`` lengths summing to ``total``, as level as possible, each at least its lower bound
    (ends ``overlap + 1``, interior ``max(2·overlap, 1)``): water-filling, ties to the lowest index."""
    lower = [overlap + 1 if i in (0, n - 1) else max(2 * overlap, 1) for i in range(n)]
    remaining = total - sum(lower)
    if remaining < 0:
        raise AssertionError(f"internal: {n} segments cannot hold {total} frames")
    lengths = list(lower)
    # raise the lowest segment one frame at a time; a heap keeps it O(total log n)
    heap = [(length, i) for i, length in enumerate(lengths)]
    heapq.heapify(heap)
    while remaining:
        length, i = heapq.heappop(heap)
        lengths[i] = length + 1
        remaining -= 1
        heapq.heappush(heap, (length + 1, i))
    return lengths


# ------------------------------------------------------------------------------------------------
# Blend weights across overlaps


def smoothstep(x: float) -> float:
    """``3x² − 2x³`` on [0, 1], clamped outside: C¹, with zero slope at both ends."""
    x = min(1.0, max(0.0, x))
    return x * x * (3.0 - 2.0 * x)


def blend_weights(spans: Sequence[tuple[int, int]], frame: float, *,
                  tolerance: float = 0.5) -> list[tuple[int, float]]:
    """Which segments render take position ``frame`` (a take index, fractional allowed), and how
    much each weighs.

    Neighbours ``i`` and ``i+1`` share the ``k = b_i − a_{i+1}`` frames ``a_{i+1} … b_i − 1``. Frame
    ``f`` stands for the interval ``[f − ½, f + ½]``, so the shared frames span
    ``[a_{i+1} − ½, b_i − ½]`` (length ``k``): across it segment ``i+1``'s weight rises as
    ``smoothstep`` from 0 to 1 and segment ``i``'s falls as one minus that. Every shared frame is
    therefore blended (weights ``smoothstep((j + ½)/k)``, j = 0…k−1), every core frame is pure,
    and a segment is only ever evaluated more than half a frame outside its training frames with
    weight 0. With no overlap (``k = 0``) the switch is at ``b_i − ½``. Weights are non-negative,
    sum to 1 and are C¹ in ``frame`` (for ``k > 0``). Only positive weights are returned, in
    segment order.

    ``frame`` may lie up to ``tolerance`` frames outside ``[a_0, b_last − 1]`` (the edge segment
    is used); beyond that, ``ValueError``.
    """
    if not spans:
        raise ValueError("no segments")
    lo_all, hi_all = spans[0][0], spans[-1][1] - 1
    if not (lo_all - tolerance <= frame <= hi_all + tolerance):
        raise ValueError(f"frame {frame:g} is outside the segments' range [{lo_all}, {hi_all}] "
                         f"(take indices)")

    def rise(j: int) -> float:
        """Weight of segment j+1 against segment j across their shared frames."""
        lo, hi = spans[j + 1][0] - 0.5, spans[j][1] - 0.5
        if hi > lo:
            return smoothstep((frame - lo) / (hi - lo))
        return 1.0 if frame >= lo else 0.0

    out = []
    n = len(spans)
    for i in range(n):
        up = rise(i - 1) if i > 0 else 1.0
        down = 1.0 - rise(i) if i < n - 1 else 1.0
        w = up * down
        if w > 0.0:
            out.append((i, w))
    return out
