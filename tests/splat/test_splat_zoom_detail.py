"""A zoom camera's detail survives reconstruction (issue 28) with the route to the performers at
the tracking cameras' resolution: the zoom cameras' points, thinned finer where they resolve
finer, small initial scales there (``docs/poly4dgs.md``, "Performers at the tracking cameras'
resolution"; the demo preset's since 2026-11-28, "The zoom points' depth").

The scene: a textured card (8 mm squares of random colour under 4 cm patches of light and shade)
seen by four wide "static" cameras (~2.6 cm per pixel there) and one narrow "zoom" camera (~4 mm
per pixel), the dense points sampled at the static cameras' 2 cm spacing and coloured by their
blur, as the demo's plane sweep gives them. The zoom points keep the depth the wide cameras
confirm (``splat.init.photo_depth``): the shade patches are what they resolve. Measured
2026-11-28 after 40 steps: the zoom camera's detail (render gradient energy over the footage's,
``splat.scoring.score_region``) 0.080 (20.9 dB) with the dense points alone (the demo's 5-8 %),
0.249 (23.2 dB) with the route.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from _splat_scenes import single_thread  # noqa: E402, F401  (fixture)
from volcap_core.production.presets import named_preset
from volcap_core.reconstruction import with_footprints, with_zoom_points
from volcap_core.splat.camera import look_at
from volcap_core.splat.model import Gaussians3D
from volcap_core.splat.render import render
from volcap_core.splat.scoring import score_region
from volcap_core.splat.train import PointsAtTime, SegmentData, TrainConfig, render_views, train_segment

SQUARE = 0.008     # texture squares (m)
HALF = 0.1         # the card spans [-HALF, HALF]² at z = 0


def _card() -> tuple[Gaussians3D, np.ndarray]:
    """Flat Gaussians 4 mm apart; colour constant per 8 mm square. Returns (Gaussians, palette)."""
    g = np.random.default_rng(7)
    n_sq = int(round(2 * HALF / SQUARE))
    palette = g.uniform(0.05, 0.9, (n_sq, n_sq, 3))
    # over 4 cm patches of light and shade: what the wide cameras resolve too (a face's hair,
    # brows, eyes), so they can confirm the zoom points' depth
    patch = int(round(0.04 / SQUARE))
    shade = g.uniform(0.3, 1.0, (-(-n_sq // patch), -(-n_sq // patch)))
    palette *= np.kron(shade, np.ones((patch, patch)))[:n_sq, :n_sq, None]
    step = SQUARE / 2
    c = np.arange(-HALF + step / 2, HALF, step)
    x, y = np.meshgrid(c, c, indexing="ij")
    ix = np.clip(((x + HALF) / SQUARE).astype(int), 0, n_sq - 1)
    iy = np.clip(((y + HALF) / SQUARE).astype(int), 0, n_sq - 1)
    rgb = palette[ix, iy].reshape(-1, 3)
    n = x.size
    means = torch.tensor(np.stack([x.ravel(), y.ravel(), np.zeros(n)], 1), dtype=torch.float32)
    sh = torch.zeros(n, 1, 3)
    sh[:, 0] = (torch.tensor(rgb, dtype=torch.float32) ** (1 / 2.2) - 0.5) / 0.2820948
    gauss = Gaussians3D(means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                        scales=torch.tensor([[0.6 * step, 0.6 * step, 0.0005]]).repeat(n, 1),
                        opacities=torch.full((n,), 0.99), sh=sh, ids=torch.arange(n))
    return gauss, palette


def _scene():
    gt, palette = _card()
    size = 48
    cams = {f"s{i}": look_at((0.3 * sx, 0.3 * sy, 1.0), (0, 0, 0), up=(0, 1, 0), fov_x_deg=60, width=size,
                             height=size) for i, (sx, sy) in enumerate([(1, 1), (-1, 1), (1, -1), (-1, -1)])}
    cams["zoom"] = look_at((0.0, 0.05, 1.0), (0, 0, 0), up=(0, 1, 0), fov_x_deg=11.0, width=size, height=size)
    with torch.no_grad():
        out = {c: render(gt, cam, backend="torch") for c, cam in cams.items()}
    data = SegmentData.build(frames=(0, 1), camera_ids=sorted(cams), fps=24.0, lazy=False,
                             load_image=lambda c, f: out[c]["rgb"], camera_for=lambda c, f: cams[c])
    # the "plane sweep": points 2 cm apart, coloured by the 2 cm blur of the texture
    c = np.arange(-HALF + 0.01, HALF, 0.02)
    x, y = np.meshgrid(c, c, indexing="ij")
    n_sq = palette.shape[0]
    k = int(round(0.02 / SQUARE))
    blur = palette[: n_sq // k * k, : n_sq // k * k].reshape(n_sq // k, k, n_sq // k, k, 3).mean(axis=(1, 3))
    ix = np.clip(((x + HALF) / 0.02).astype(int), 0, blur.shape[0] - 1)
    iy = np.clip(((y + HALF) / 0.02).astype(int), 0, blur.shape[1] - 1)
    xyz = torch.tensor(np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1), dtype=torch.float32)
    points = [PointsAtTime(0.0, xyz, torch.tensor(blur[ix, iy].reshape(-1, 3), dtype=torch.float32))]
    return data, points, out["zoom"]["alpha"][..., 0] > 0.5


def _zoom_detail(config: TrainConfig, zoom_points: bool) -> tuple[float, float]:
    data, points, card = _scene()
    points = with_footprints(points, data)
    if zoom_points:
        points = with_zoom_points(points, data, [], config.init_zoom_stride_px)
    result = train_segment(data, points, config, seed=0)
    [view] = [v for v in data.views if v.camera_id == "zoom"]
    rgb = result.grids.apply(render_views(result.model, [view], config)[0], "zoom")
    sc = score_region(rgb, view.load(), card)
    return sc.detail, sc.psnr


#: the route as measured on the demo segment (docs/poly4dgs.md, run "C")
ROUTE = dict(init_static_share=0.4, init_zoom_stride_px=2, init_finest_level=-2, init_moving_scale_px=2.0,
             performer_view_weight=1.5, mcmc={"moving_weight": 4.0})


#: the demo preset before the route: the dense points alone, a uniform camera schedule, MCMC's
#: uniform growth
DENSE_ONLY = dict(init_zoom_stride_px=None, performer_view_weight=0.0, mcmc={"moving_weight": 1.0})


def _config(**overrides) -> TrainConfig:
    return named_preset("demo").train_config(max_gaussians=4_000, steps=40, eval_every=0, checkpoint_every=0,
                                             **overrides)


pytestmark = pytest.mark.usefixtures("single_thread")


def test_the_route_keeps_a_zoom_cameras_detail():
    """~3 s on 2 quiet cores (15-45 s on the loaded ones): two 40-step trainings of a 5-camera,
    48-px scene."""
    detail, psnr = _zoom_detail(_config(**ROUTE), zoom_points=True)
    detail_before, psnr_before = _zoom_detail(_config(**DENSE_ONLY), zoom_points=False)
    print(f"zoom detail {detail:.3f} ({psnr:.1f} dB); dense points alone {detail_before:.3f} ({psnr_before:.1f} dB)")
    assert detail_before < 0.2
    assert detail >= 0.2, f"zoom camera's detail {detail:.3f} fell back towards {detail_before:.3f}"
    assert psnr >= psnr_before


def test_the_demo_preset_keeps_a_zoom_cameras_detail():
    """The demo preset as it is (its zoom points, when it has them, as the reconstruction adds them)
    against the dense points alone: a preset that drops the route falls back to their detail. ~3 s
    on 2 quiet cores."""
    demo = _config()
    detail, psnr = _zoom_detail(demo, zoom_points=demo.init_zoom_stride_px is not None)
    detail_before, psnr_before = _zoom_detail(_config(**DENSE_ONLY), zoom_points=False)
    print(f"demo preset: zoom detail {detail:.3f} ({psnr:.1f} dB); dense points alone {detail_before:.3f} "
          f"({psnr_before:.1f} dB)")
    assert detail >= 0.2, f"the demo preset's zoom detail {detail:.3f} fell back towards {detail_before:.3f}"
    assert psnr >= psnr_before
