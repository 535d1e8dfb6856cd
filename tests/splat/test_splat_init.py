"""Initial Gaussians of a segment: static/moving split, floater filter, voxel thinning, the coloured
scan, and what the model makes of them (shared static Gaussians, short-lived moving ones)."""

import numpy as np
import pytest
import torch

from volcap_core.splat.camera import look_at
from volcap_core.splat.init import (
    classify_static,
    colour_scan,
    drop_isolated,
    initial_gaussians,
    voxel_thin,
)
from volcap_core.splat.model import Poly4DGSConfig, evaluate
from volcap_core.splat.train import PointsAtTime, TrainConfig, View, init_budget, init_model


def _wall(rng, n=4000):
    """Points on the plane y = 3 (a wall), x, z in [-2, 2]."""
    return np.stack([rng.uniform(-2, 2, n), np.full(n, 3.0), rng.uniform(-2, 2, n)], 1)


def _blob(rng, centre, n=600, r=0.15):
    return np.asarray(centre) + rng.normal(0, r / 2, (n, 3))


def test_static_split_by_scan_and_by_persistence():
    rng = np.random.default_rng(0)
    wall = _wall(rng)                                          # on the scan
    prop = _blob(rng, (1.0, 1.0, 0.5), 300, 0.1)               # not on the scan, never moves
    frames = []
    for f in range(4):
        actor = _blob(rng, (-1.0 + 0.4 * f, 1.0, 1.0))         # moves 0.4 m per frame
        frames.append(np.concatenate([wall[rng.choice(len(wall), 2000)],
                                      prop + rng.normal(0, 0.003, prop.shape), actor]))
    def scan_distance(x):       # the scan is the wall
        return np.abs(x[:, 1] - 3.0) + 10 * (np.abs(x[:, 0]) > 2)

    out = classify_static(frames, scan_distance=scan_distance)
    for f, st in zip(frames, out):
        assert st[:2000].all()                                  # the scanned wall
        assert st[2000:2300].mean() > 0.95                      # the prop, by persistence
        assert st[2300:].mean() < 0.05                          # the actor moves
    # without a scan, a single frame has nothing to call static
    assert not classify_static([frames[0]])[0].any()


def test_drop_isolated_removes_sparse_floaters_keeps_dense_surfaces():
    rng = np.random.default_rng(1)
    actor = _blob(rng, (0, 0, 1), 3000, 0.3)
    floaters = rng.uniform(-4, 4, (100, 3))
    keep = drop_isolated(np.concatenate([actor, floaters]))
    assert keep[:3000].mean() > 0.97 and keep[3000:].mean() < 0.1
    # scale-free: the same cloud in millimetres gives the same answer
    keep_mm = drop_isolated(1000 * np.concatenate([actor, floaters]))
    assert (keep_mm == keep).all()
    assert drop_isolated(actor[:5]).all()                       # too few points to judge


def test_voxel_thin_meets_the_budget_and_spreads_points():
    rng = np.random.default_rng(2)
    # a dense patch and a sparse far region: uniform sampling would keep mostly the dense patch
    dense = rng.uniform(0, 0.5, (20000, 3))
    sparse = rng.uniform(0, 5, (2000, 3)) + np.array([5, 0, 0])
    pts = np.concatenate([dense, sparse])
    idx = voxel_thin(pts, 2000, np.random.default_rng(0))
    assert len(idx) == 2000 and len(np.unique(idx)) == 2000
    assert (idx >= 20000).mean() > 0.3                          # uniform sampling: 9 %
    again = voxel_thin(pts, 2000, np.random.default_rng(0))
    assert (again == idx).all()                                 # deterministic for a seed
    assert len(voxel_thin(pts[:10], 100, np.random.default_rng(0))) == 10


def test_initial_gaussians_pool_static_once_and_respect_the_budget():
    rng = np.random.default_rng(3)
    wall = _wall(rng, 20000)
    frames = []
    for f in range(6):
        actor = _blob(rng, (0.2 * f, 1.0, 1.0), 1500)
        xyz = np.concatenate([wall[rng.choice(len(wall), 5000)], actor])
        static = np.r_[np.ones(5000, bool), np.zeros(1500, bool)]
        frames.append((f / 24, xyz, np.full((len(xyz), 3), 0.5), static))
    split = initial_gaussians(frames, budget=6000, static_share=0.5, seed=0)
    assert len(split.xyz) <= 6000
    assert split.counts["static"] == 3000                       # half the budget, pooled once
    assert np.allclose(split.t0[split.static], 2.5 / 24)        # centred mid-segment
    moving_t0 = np.unique(split.t0[~split.static])
    assert len(moving_t0) == 6                                  # every frame keeps its moving points
    # scales: a fraction of the neighbour spacing of the thinned pool, never a room-sized splat
    assert split.scale.max() < 0.5 and split.scale.min() > 0


def test_static_gaussians_live_for_the_segment_moving_ones_for_about_a_frame():
    rng = np.random.default_rng(4)
    wall = _wall(rng, 3000).astype(np.float32)
    pts = []
    for f in range(8):
        actor = _blob(rng, (0.1 * f, 1.0, 1.0), 400).astype(np.float32)
        xyz = np.concatenate([wall, actor])
        st = torch.from_numpy(np.r_[np.ones(3000, bool), np.zeros(400, bool)])
        pts.append(PointsAtTime(f / 24, torch.from_numpy(xyz), torch.full((len(xyz), 3), 0.4), st))
    cfg = TrainConfig(model=Poly4DGSConfig.paper(sh_degree=0), mcmc=dict(cap_max=10000))
    assert init_budget(cfg) == 7000
    model = init_model(pts, cfg, frame_interval_s=1 / 24, generator=torch.Generator().manual_seed(0))
    n_static = int((model.params["log_lambdas"][:, 0] < -30).sum())
    assert 2500 <= n_static <= 3000                              # one copy of the wall, not eight
    alive = [len(evaluate(model, f / 24)) for f in range(8)]
    moving_alive = [a - n_static for a in alive]
    # at each instant: the wall plus at most about five frames' worth of actor Gaussians (σ = 0.7 frame)
    assert all(a >= n_static for a in alive)
    assert max(moving_alive) <= 5 * 400
    with pytest.raises(ValueError, match="no initial points"):
        init_model([PointsAtTime(0.0, torch.zeros(0, 3), torch.zeros(0, 3))], cfg,
                   frame_interval_s=1 / 24)


def test_colour_scan_takes_the_median_of_the_views_that_see_a_point():
    # a wall at y = 3 and a pillar in front of part of it, seen by three cameras
    rng = np.random.default_rng(5)
    wall = _wall(rng, 6000)
    size = 64
    views = []
    for k, x in enumerate((-1.0, 0.0, 1.0)):
        cam = look_at((x, -2.0, 0.0), (0.0, 3.0, 0.0), (0.0, 0.0, 1.0), fov_x_deg=70.0,
                      width=size, height=size)
        img = torch.full((size, size, 3), 0.2 + 0.1 * k)        # each camera sees another shade
        views.append(View(str(k), 0, 0.0, cam, img))
    rgb, seen = colour_scan(wall, views)
    assert seen.mean() > 0.3
    # the median of 0.2, 0.3, 0.4 where all three see the point; a seen point has a real colour
    assert np.allclose(np.median(rgb[seen], axis=0), 0.3, atol=0.051)
    assert (rgb[~seen] == 0).all()
    # a point hidden behind the wall (y = 4) is seen by no camera
    _, seen_behind = colour_scan(np.concatenate([wall, [[0.0, 4.0, 0.0]]]), views)
    assert not seen_behind[-1]


def test_the_moving_budget_goes_where_moving_points_are():
    from volcap_core.splat.init import _fair_shares

    assert _fair_shares([0, 100, 5000, 5000], 3000) == [0, 100, 1450, 1450]
    assert _fair_shares([10, 10], 1000) == [10, 10]
    assert _fair_shares([], 50) == []
    rng = np.random.default_rng(6)
    wall = _wall(rng, 5000)
    frames = [(0.0, wall, np.full((5000, 3), 0.5), np.ones(5000, bool))]      # e.g. the coloured scan
    frames += [(f / 24, _blob(rng, (f * 0.2, 1, 1), 800), np.full((800, 3), 0.5), None) for f in range(3)]
    split = initial_gaussians(frames, budget=3000, static_share=0.5, seed=0)
    # the scan-only cloud has no moving point: its share is not lost
    assert split.counts["static"] == 1500 and split.counts["moving"] >= 1450


def test_zoom_points_lie_on_the_clouds_surface_at_the_cameras_resolution():
    """A 2 cm grid of points on the plane z = 0, seen by a narrow camera 1 m above (~2 mm a pixel):
    the camera's points lie on the plane, one per 2×2 block inside the cloud's silhouette, coloured
    by the footage's block means; a dense zoom part does not make the sweep's points "isolated"."""
    from volcap_core.splat.init import drop_isolated, finest_footprint, footprint_levels, zoom_points

    c = np.arange(-0.1, 0.1001, 0.02)
    x, y = np.meshgrid(c, c, indexing="ij")
    cloud = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    K = np.array([[500.0, 0, 63.5], [0, 500.0, 63.5], [0, 0, 1]])
    W = np.eye(4)
    W[:3, :3] = np.diag([1.0, -1.0, -1.0])      # looking down -z from z = 1
    W[2, 3] = 1.0
    image = np.random.default_rng(0).uniform(0, 1, (128, 128, 3))
    xyz, rgb, foot = zoom_points(cloud, K, W, image, stride_px=2)
    assert len(xyz) > 0.5 * 64 * 64 * (0.2 * 500 / 128) ** 2 / 1.6      # most of the card's blocks
    assert np.abs(xyz[:, 2]).max() < 1e-6 and np.abs(xyz[:, :2]).max() <= 0.1 + 2 * 2 / 500   # within a block
    assert np.allclose(foot, 1 / 500)
    # each point's colour is its 2x2 block's mean: re-project and compare
    pc = xyz @ W[:3, :3].T + W[:3, 3]
    uv = pc[:, :2] / pc[:, 2:] @ K[:2, :2].T + K[:2, 2]
    i, j = np.floor(uv[:, 1] / 2).astype(int), np.floor(uv[:, 0] / 2).astype(int)
    blocks = image.reshape(64, 2, 64, 2, 3).mean(axis=(1, 3))
    assert np.allclose(rgb, blocks[i, j])
    assert np.allclose(finest_footprint(cloud, [(K, W, 128, 128)]), 1 / 500)
    # the zoom camera framed one corner (a face); the rest of the card has only the sweep's points
    corner = (xyz[:, 0] < -0.04) & (xyz[:, 1] < -0.04)
    both = np.concatenate([cloud, xyz[corner]])
    level = footprint_levels(np.concatenate([np.full(len(cloud), 0.016), foot[corner]]), 0.016, -3)
    assert set(level[: len(cloud)]) == {0} and set(level[len(cloud):]) == {-3}
    assert drop_isolated(both, groups=level)[: len(cloud)].mean() > 0.9
    assert drop_isolated(both)[: len(cloud)].mean() < 0.7     # judged against the zoom's density


def _textured_plane_view(camera, rng_phases):
    """The footage of the plane z = 0 painted with a band-limited texture (waves of 4-20 cm, what a
    1 cm pixel still resolves), seen by a splat ``camera``: ``(K, world_to_camera, width, height,
    load)`` as ``photo_depth`` takes its neighbours."""
    K, W = camera.opencv_K(), camera.world_to_camera.double().numpy()
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ W[:3, :3]      # world directions
    centre = -W[:3, :3].T @ W[:3, 3]
    hit = centre + rays * (-centre[2] / rays[..., 2:3])
    grey = 0.4 + sum(0.08 * np.sin(2 * np.pi * (hit[..., 0] * kx + hit[..., 1] * ky) + ph)
                     for kx, ky, ph in rng_phases)
    image = np.repeat(grey[..., None], 3, -1) * np.array([1.0, 0.9, 0.8])
    return K, W, camera.width, camera.height, lambda: image


def test_zoom_points_take_the_depth_their_neighbours_confirm():
    """Under a second. A textured floor seen by a zoom camera (~2 mm a pixel) and three wide cameras
    around it (~11 mm a pixel), and a coarse cloud 4 cm above the floor (a sweep's surface off the
    true one): lifted to the cloud's z-buffer the zoom points float 4 cm above the floor; with the
    wide cameras as neighbours each takes the depth they confirm by photo-consistency, on the floor
    to a few millimetres, and the pixels no neighbour sees are dropped."""
    from volcap_core.splat.init import zoom_points

    g = np.random.default_rng(3)
    waves = [(kx, ky, g.uniform(0, 2 * np.pi)) for kx, ky in g.uniform(-1, 1, (8, 2)) * 25]   # 1/m
    zoom = look_at((0.1, -0.2, 1.5), (0, 0, 0), up=(0, 1, 0), fov_x_deg=9.0, width=96, height=96)
    wide = [look_at((1.2 * np.cos(a), 1.2 * np.sin(a), 1.6), (0, 0, 0), up=(0, 0, 1), fov_x_deg=40.0,
                    width=128, height=128) for a in (0.3, 2.4, 4.4)]
    Kz, Wz, _, _, load = _textured_plane_view(zoom, waves)
    image = load()
    neighbours = [_textured_plane_view(c, waves) for c in wide]
    c = np.arange(-0.3, 0.3001, 0.02)
    x, y = np.meshgrid(c, c, indexing="ij")
    cloud = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.04)], 1)

    lifted, _, _ = zoom_points(cloud, Kz, Wz, image, stride_px=2)
    own, rgb, foot = zoom_points(cloud, Kz, Wz, image, stride_px=2, neighbours=neighbours)
    assert np.median(np.abs(lifted[:, 2] - 0.04)) < 0.003          # the buffer: fronto-parallel splats
    assert len(own) > 0.8 * len(lifted)
    assert np.median(np.abs(own[:, 2])) < 0.003 and np.percentile(np.abs(own[:, 2]), 90) < 0.01
    # the points stay on their own pixels' rays
    pc = own @ Wz[:3, :3].T + Wz[:3, 3]
    uv = pc[:, :2] / pc[:, 2:] @ Kz[:2, :2].T + Kz[:2, 2]
    assert np.abs((uv - 0.5 + 1) % 2 - 1).max() < 1e-4                 # block centres
    assert np.allclose(foot, pc[:, 2] / Kz[0, 0])
    # no neighbour sees it: nothing is confirmed
    elsewhere = [_textured_plane_view(look_at((5.0, 5.0, 1.6), (6, 6, 0), up=(0, 0, 1), fov_x_deg=40.0,
                                               width=96, height=96), waves)]
    assert len(zoom_points(cloud, Kz, Wz, image, stride_px=2, neighbours=elsewhere)[0]) == 0
