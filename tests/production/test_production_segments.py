"""Segment planning: coverage, overlap, budget → length, memory estimate, blend weights."""

import math

import pytest

from volcap_core.production.segments import (
    GIB,
    MemoryModel,
    SegmentBudget,
    SegmentPlan,
    blend_weights,
    estimate_training_memory,
    floats_per_gaussian,
    max_gaussians_for_memory,
    plan_segments,
    smoothstep,
)
from volcap_core.splat.model import Poly4DGSConfig


def budget(per_frame=1000, cap=10_000, **kw):
    return SegmentBudget(gaussians_per_frame=per_frame, max_gaussians=cap, width=64, height=64, **kw)


def assert_covers(plan: SegmentPlan, start: int, end: int, overlap: int):
    segs = plan.segments
    assert segs[0].frames[0] == start and segs[-1].frames[1] == end
    for s in segs:
        assert 0 < s.length <= plan.max_length
        assert s.gaussians == plan.budget.gaussians_for(s.length) <= plan.budget.gaussian_cap()
    for s0, s1 in zip(segs, segs[1:]):
        assert s0.frames[1] - s1.frames[0] == overlap           # neighbours share `overlap` frames
    # every frame is in exactly one core, or shared by exactly two neighbours (never three)
    for f in range(start, end):
        in_core = [s for s in segs if s.core[0] <= f < s.core[1]]
        holders = [s for s in segs if s.frames[0] <= f < s.frames[1]]
        assert (len(in_core), len(holders)) in ((1, 1), (0, 2)), (f, in_core, holders)


def test_budget_gives_the_segment_length_linear_in_gaussians():
    b = budget(per_frame=1000, cap=10_000)
    assert b.max_segment_length() == 10
    assert budget(per_frame=2000, cap=10_000).max_segment_length() == 5        # twice the need
    assert budget(per_frame=1000, cap=20_000).max_segment_length() == 20       # twice the budget
    assert budget(per_frame=1000, cap=10_000, base_gaussians=3000).max_segment_length() == 7
    plan = plan_segments((0, 100), b, overlap=3)
    assert plan.max_length == 10
    assert_covers(plan, 0, 100, 3)
    assert len(plan.segments) == math.ceil((100 - 3) / (10 - 3))              # the fewest
    lengths = [s.length for s in plan.segments]
    assert max(lengths) - min(lengths) <= 1                                   # balanced


def test_plans_are_valid_for_every_small_configuration():
    for overlap in range(0, 5):
        for limit in range(2 * overlap + 1, 2 * overlap + 8):
            for total in range(1, 45):
                plan = plan_segments((7, 7 + total), budget(cap=1000 * limit), overlap=overlap)
                assert_covers(plan, 7, 7 + total, overlap if len(plan.segments) > 1 else 0)
                n = len(plan.segments)
                assert n == 1 if total <= limit else n == -(-(total - overlap) // (limit - overlap))


def test_plan_is_deterministic_and_a_record():
    p1 = plan_segments((0, 500), budget(cap=40_000), overlap=4)
    p2 = plan_segments((0, 500), budget(cap=40_000), overlap=4)
    assert p1.to_canonical_json() == p2.to_canonical_json()
    assert SegmentPlan.media_type() == "application/vnd.volcap.segment-plan+json"
    assert SegmentPlan.from_json_bytes(p1.to_canonical_json()) == p1
    assert [s.id for s in p1.segments][:2] == ["000000-000040", "000036-000076"]


def test_short_range_is_one_segment_with_a_full_core():
    plan = plan_segments((10, 14), budget(cap=10_000), overlap=3)
    (seg,) = plan.segments
    assert seg.frames == seg.core == (10, 14) and seg.gaussians == 4000


@pytest.mark.parametrize("kwargs, match", [
    (dict(frames=(5, 5)), "empty frame range"),
    (dict(frames=(0, 100), overlap=-1), "overlap must be >= 0"),
    (dict(frames=(0, 100), overlap=10), r"overlap of 10 frames >= the maximum segment length of 10"),
    (dict(frames=(0, 100), overlap=12), r"overlap of 12 frames >= the maximum"),
    (dict(frames=(0, 100), overlap=5), r"at least 2 × overlap \+ 1 = 11"),
    (dict(frames=(0, 100), overlap=2, max_length=0), "max_length must be >= 1"),
])
def test_plan_errors_are_clear(kwargs, match):
    frames = kwargs.pop("frames")
    with pytest.raises(ValueError, match=match):
        plan_segments(frames, budget(cap=10_000), **kwargs)


def test_budget_errors():
    with pytest.raises(ValueError, match="max_gaussians or gpu_memory_bytes"):
        SegmentBudget(gaussians_per_frame=10)
    with pytest.raises(ValueError, match="allows no frame per segment"):
        budget(per_frame=20_000, cap=10_000).max_segment_length()
    with pytest.raises(ValueError, match="cannot train at 3840x2160"):
        max_gaussians_for_memory(2 * GIB, 3840, 2160)


def test_memory_estimate_is_monotone_and_inverts():
    cfg = Poly4DGSConfig.paper()
    assert floats_per_gaussian(cfg) == 72                 # 3+6+4+4+3+1+2+1+3+45
    assert floats_per_gaussian(Poly4DGSConfig.static(sh_degree=0)) == 14
    totals = [estimate_training_memory(n, 1920, 1080).total for n in (0, 1, 10**5, 10**6, 10**7)]
    assert totals == sorted(totals) and len(set(totals)) == len(totals)
    by_res = [estimate_training_memory(10**6, w, h).total
              for w, h in ((640, 360), (1920, 1080), (3840, 2160), (4096, 4096))]
    assert by_res == sorted(by_res) and len(set(by_res)) == len(by_res)
    per_g = (estimate_training_memory(10**6, 1920, 1080).total
             - estimate_training_memory(0, 1920, 1080).total) / 10**6
    assert 1800 < per_g < 2200                            # ~2 kB per Gaussian at 1080p (doc)
    for gpu in (24 * GIB, 80 * GIB):
        n = max_gaussians_for_memory(gpu, 3840, 2160)
        usable = gpu * MemoryModel().usable_fraction
        assert estimate_training_memory(n, 3840, 2160).total <= usable
        assert estimate_training_memory(n + 1, 3840, 2160).total > usable
    # a GPU budget caps the segment length; a bigger GPU allows longer segments
    small = SegmentBudget(gaussians_per_frame=100_000, gpu_memory_bytes=24 * GIB)
    big = SegmentBudget(gaussians_per_frame=100_000, gpu_memory_bytes=80 * GIB)
    assert 0 < small.max_segment_length() < big.max_segment_length()
    plan = plan_segments((0, 2000), big)
    assert all(s.memory_bytes <= 80 * GIB * 0.85 for s in plan.segments)


def test_blend_weights_partition_of_unity_and_continuity():
    spans = [s.frames for s in plan_segments((0, 60), budget(cap=16_000), overlap=4).segments]
    grid = [i / 100 for i in range(-50, 59 * 100 + 51)]
    prev = None
    for f in grid:
        ws = blend_weights(spans, f)
        assert 1 <= len(ws) <= 2
        assert all(w > 0 for _, w in ws)
        assert abs(sum(w for _, w in ws) - 1.0) < 1e-12
        dense = [0.0] * len(spans)
        for i, w in ws:
            dense[i] = w
        if prev is not None:   # smoothstep over 4 frames: slope <= 1.5/4 per frame
            assert max(abs(a - b) for a, b in zip(dense, prev)) <= 1.5 / 4 * 0.01 + 1e-9
        prev = dense
    # core frames are pure, every shared frame is blended
    for i, (_, b) in enumerate(spans[:-1]):
        a1 = spans[i + 1][0]
        for f in range(a1, b):
            assert len(blend_weights(spans, f)) == 2
        assert blend_weights(spans, a1 - 1) == [(i, 1.0)]
        assert blend_weights(spans, b) == [(i + 1, 1.0)]
    with pytest.raises(ValueError, match="outside the segments' range"):
        blend_weights(spans, 60.0)


def test_blend_without_overlap_switches_between_frames():
    spans = [(0, 5), (5, 10)]
    assert blend_weights(spans, 4.0) == [(0, 1.0)]
    assert blend_weights(spans, 4.49) == [(0, 1.0)]
    assert blend_weights(spans, 4.5) == [(1, 1.0)]
    assert smoothstep(-1) == 0 and smoothstep(0.5) == 0.5 and smoothstep(2) == 1
