"""Performance: blending weights across overlaps, rendering, and the boundary pop it removes."""

import math

import pytest
import torch

from volcap_core.production.performance import (
    Performance,
    PerformanceSegment,
    render_performance,
    segments_at,
)
from volcap_core.production.segments import SegmentBudget, plan_segments
from volcap_core.records import ArtifactRef
from volcap_core.splat.camera import look_at
from volcap_core.splat.model import Gaussians3D, Poly4DGS, Poly4DGSConfig, evaluate
from volcap_core.splat.render import render

FPS = 10.0


def ref(i: int) -> ArtifactRef:
    return ArtifactRef(digest="blake3:" + f"{i:02x}" * 32, size=100 + i)


def perf(spans, cores=None) -> Performance:
    n = len(spans)
    cores = cores or [(a if i == 0 else a + (spans[i - 1][1] - a),
                       b if i == n - 1 else spans[i + 1][0]) for i, (a, b) in enumerate(spans)]
    return Performance(name="take", capture=ref(99), fps=FPS, segments=tuple(
        PerformanceSegment(model=ref(i), frames=s, core=c) for i, (s, c) in enumerate(zip(spans, cores))))


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_weights_partition_of_unity_and_continuity():
    p = perf([(0, 12), (9, 21), (18, 30)])
    assert Performance.media_type() == "application/vnd.volcap.performance+json"
    assert Performance.from_json_bytes(p.to_canonical_json()) == p
    prev = None
    for k in range(0, 2951):
        t = k / 100 / FPS                  # 0.01-frame steps over the whole take
        ws = segments_at(p, t)
        assert abs(sum(w for _, w in ws) - 1) < 1e-12 and all(0 < w <= 1 for _, w in ws)
        cur = {s.id: w for s, w in ws}
        for key in set(cur) | set(prev or cur):   # smoothstep over 3 frames: slope <= 0.5/frame
            assert abs(cur.get(key, 0) - (prev or cur).get(key, 0)) <= 1.5 / 3 * 0.01 + 1e-9
        prev = cur
    # inside a core range: one segment; on a shared frame: two
    assert [(s.id, w) for s, w in segments_at(p, 5 / FPS)] == [("000000-000012", 1.0)]
    assert [s.id for s, _ in segments_at(p, 10 / FPS)] == ["000000-000012", "000009-000021"]
    with pytest.raises(ValueError, match="performance take: t = 3 s"):
        segments_at(p, 3.0)


def test_performance_refuses_bad_layouts():
    with pytest.raises(ValueError, match="gap between segment 0"):
        perf([(0, 10), (11, 20)], cores=[(0, 10), (11, 20)])
    with pytest.raises(ValueError, match="three segments would blend"):
        perf([(0, 10), (5, 15), (9, 20)], cores=[(0, 5), (10, 9), (15, 20)])
    with pytest.raises(ValueError, match="core"):
        perf([(0, 10), (8, 20)], cores=[(0, 12), (10, 20)])
    plan = plan_segments((0, 30), SegmentBudget(gaussians_per_frame=10, max_gaussians=120,
                                                width=8, height=8), overlap=3)
    with pytest.raises(ValueError, match="1 models for 3 planned segments"):
        Performance.from_plan("x", ref(0), FPS, plan, [ref(1)])
    p = Performance.from_plan("x", ref(0), FPS, plan, [ref(i) for i in range(3)])
    assert [s.core for s in p.segments] == [s.core for s in plan.segments]
    assert p.frames == (0, 30)


# ------------------------------------------------------------------------------------------------
# Two tiny hand-made segment models of one moving scene


def scene(n=40, seed=3):
    g = torch.Generator().manual_seed(seed)
    xyz = (torch.rand(n, 3, generator=g) * 2 - 1) * torch.tensor([0.35, 0.35, 0.5])
    colour = 0.2 + 0.7 * torch.rand(n, 3, generator=g)
    velocity = torch.randn(n, 3, generator=g) * 0.15      # m/s
    return xyz, colour, velocity


def segment_model(frames, *, seed, jitter=0.02):
    """The scene as one segment would reconstruct it: same motion, its own small errors."""
    xyz, colour, vel = scene()
    g = torch.Generator().manual_seed(seed)
    n = xyz.shape[0]
    t_mid = (frames[0] + frames[1] - 1) / 2 / FPS
    cfg = Poly4DGSConfig(mean_degree=1, quat_degree=0, scale_degree=0, opacity_degree=1,
                         sh_degree=0)
    # mean at t_mid, velocity as the first-order coefficient; long lifespans (opaque throughout)
    m = Poly4DGS.from_points(cfg, xyz + vel * t_mid + jitter * torch.randn(n, 3, generator=g),
                             colour + 0.05 * torch.randn(n, 3, generator=g),
                             scales=torch.full((n,), 0.09), t0=torch.full((n,), t_mid),
                             opacity=0.95, lifespan_s=50.0)
    m.params["means_t"][:, 0] = vel
    return m


def camera_at(k):
    a = 0.6 + 0.02 * k                   # a slow orbit: the camera moves every frame
    return look_at((3 * math.cos(a), 3 * math.sin(a), 0.4), (0, 0, 0), fov_x_deg=35,
                   width=40, height=40)


def step_diffs(frames):
    return [float((b - a).abs().mean()) for a, b in zip(frames, frames[1:])]


def test_boundary_pop_blended_vs_hard_cut():
    spans = [(0, 14), (11, 25)]                    # 3 shared frames: 11, 12, 13
    p = perf(spans)
    models = {p.segments[0].model: segment_model(spans[0], seed=10),
              p.segments[1].model: segment_model(spans[1], seed=20)}
    load = models.__getitem__

    def rgba(out):
        return torch.cat([out["rgb"], out["alpha"]], dim=-1)

    blended, hard = [], []
    for k in range(4, 21):
        t, cam = k / FPS, camera_at(k)
        blended.append(rgba(render_performance(p, load, cam, t, backend="torch")))
        # the hard cut: the segment that owns the frame, switching in the middle of the overlap
        only = p.segments[0] if k < 12.5 else p.segments[1]
        hard.append(rgba(render(evaluate(load(only.model), t), cam, backend="torch")))
    frames = list(range(4, 21))
    d_blend, d_hard = step_diffs(blended), step_diffs(hard)
    inside = [d for k, d in zip(frames, d_blend) if k + 1 <= 10 or k >= 14]  # steps within cores
    across = [d for k, d in zip(frames, d_blend) if 10 <= k <= 13]           # steps touching the overlap
    cut = max(d_hard)
    print(f"\nframe-to-frame mean |ΔRGBA|: inside a segment max {max(inside):.4f} "
          f"(mean {sum(inside) / len(inside):.4f}); across the overlap blended max "
          f"{max(across):.4f}; hard cut {cut:.4f}")
    assert d_hard.index(cut) == frames.index(12)   # the hard cut's jump is the 12 -> 13 step
    assert max(across) < 0.65 * cut                # blending spreads the jump over the overlap
    assert max(across) < 1.6 * max(inside)         # ... to the size of ordinary motion
    # outside the overlap the blend is exactly the owning segment's render
    assert torch.equal(blended[0], hard[0]) and torch.equal(blended[-1], hard[-1])


def sheet_model(frames, *, seed):
    """A single-layer opaque surface (a grid of flat Gaussians in the plane x = 0), as MCMC tends
    to leave real surfaces: one layer of near-opaque splats."""
    g = torch.Generator().manual_seed(seed)
    ys, zs = torch.meshgrid(torch.linspace(-0.4, 0.4, 9), torch.linspace(-0.4, 0.4, 9),
                            indexing="ij")
    n = ys.numel()
    xyz = torch.stack([torch.zeros(n), ys.flatten(), zs.flatten()], dim=1)
    xyz = xyz + 0.005 * torch.randn(n, 3, generator=g)
    t_mid = (frames[0] + frames[1] - 1) / 2 / FPS
    cfg = Poly4DGSConfig(mean_degree=1, quat_degree=0, scale_degree=0, opacity_degree=1,
                         sh_degree=0)
    m = Poly4DGS.from_points(cfg, xyz, torch.full((n, 3), 0.6),
                             scales=torch.tensor([[0.002, 0.035, 0.035]]).expand(n, 3),
                             t0=torch.full((n,), t_mid), opacity=0.99, lifespan_s=50.0)
    return m


def test_image_blend_keeps_alpha_where_gaussian_concatenation_dips():
    spans = [(0, 14), (11, 25)]
    p = perf(spans)
    m0, m1 = sheet_model(spans[0], seed=1), sheet_model(spans[1], seed=2)
    load = {p.segments[0].model: m0, p.segments[1].model: m1}.__getitem__
    t = 12 / FPS                               # the middle of the overlap: weights 0.5 / 0.5
    cam = look_at((3, 0, 0), (0, 0, 0), fov_x_deg=10, width=48, height=48)
    (_, w0), (_, w1) = segments_at(p, t)
    assert abs(w0 - 0.5) < 1e-9 and abs(w1 - 0.5) < 1e-9
    img = render_performance(p, load, cam, t, backend="torch")
    a0 = render(evaluate(m0, t), cam, backend="torch")["alpha"]
    a1 = render(evaluate(m1, t), cam, backend="torch")["alpha"]
    g0, g1 = evaluate(m0, t), evaluate(m1, t)
    cat = Gaussians3D(**{f: torch.cat([getattr(g0, f), getattr(g1, f)]) for f in
                         ("means", "quats", "scales", "sh", "ids")},
                      opacities=torch.cat([w0 * g0.opacities, w1 * g1.opacities]))
    a_cat = render(cat, cam, backend="torch")["alpha"]
    solid = (a0 > 0.9) & (a1 > 0.9)            # pixels both segments see as solid surface
    assert solid.sum() > 20
    print(f"\nmean alpha on solid pixels: image blend {img['alpha'][solid].mean():.3f}, "
          f"opacity-scaled concatenation {a_cat[solid].mean():.3f}")
    assert img["alpha"][solid].min() > 0.9
    assert a_cat[solid].mean() < img["alpha"][solid].mean() - 0.1
    # the image blend is the convex combination of the two renders
    assert torch.allclose(img["alpha"], w0 * a0 + w1 * a1, atol=1e-6)
