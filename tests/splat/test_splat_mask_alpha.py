"""The alpha loss on performer masks (``TrainConfig.mask_alpha_weight``, on every
``mask_alpha_every``-th step): the performers' alpha (the moving Gaussians' coverage, the set in
front occluding) is pulled toward each view's mask."""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import random_gaussians, ring_cameras, single_thread  # noqa: E402, F401  (fixture)

from volcap_core.colour import srgb_decode_unbounded  # noqa: E402
from volcap_core.splat.model import Gaussians3D, Poly4DGSConfig, evaluate  # noqa: E402
from volcap_core.splat.render import render  # noqa: E402
from volcap_core.splat.sh import SH_C0, sh_to_colour  # noqa: E402
from volcap_core.splat.train import (  # noqa: E402
    PointsAtTime,
    SegmentData,
    TrainConfig,
    performer_alpha,
    train_segment,
)

pytestmark = pytest.mark.usefixtures("single_thread")
FPS, FRAMES, SIZE = 10.0, (0, 2), 24


def _scene():
    """Performers (30 Gaussians moving at constant velocity) on a static floor (a grid of flat
    Gaussians at z = -0.45), seen by 5 ring cameras; per view the footage and the performers'
    true coverage (the mask). Returns (data, initial points)."""
    actors = random_gaussians(30, seed=3, sh_degree=0, spread=0.3, scale=(0.05, 0.12))
    actors.opacities[:] = 0.9
    vel = torch.randn(30, 3, generator=torch.Generator().manual_seed(4)) * 0.3
    u = torch.linspace(-1.0, 1.0, 9)
    floor_xyz = torch.stack([*torch.meshgrid(u, u, indexing="ij"), torch.full((9, 9), -0.45)], -1).reshape(-1, 3)
    nf = len(floor_xyz)
    floor = Gaussians3D(floor_xyz, torch.tensor([[1.0, 0, 0, 0]]).repeat(nf, 1),
                        torch.tensor([[0.14, 0.14, 0.01]]).repeat(nf, 1), torch.full((nf,), 0.95),
                        torch.full((nf, 1, 3), 0.1 / SH_C0), torch.arange(nf))
    cams = ring_cameras(5, size=SIZE)

    def at(t: float, flag: bool = False) -> Gaussians3D:
        sh = torch.cat([actors.sh, floor.sh])
        if flag:   # colour 1 on the performers, 0 on the floor: their coverage, occluded by the floor
            sh = torch.cat([torch.full_like(actors.sh, 0.5 / SH_C0), torch.full_like(floor.sh, -0.5 / SH_C0)])
        return Gaussians3D(torch.cat([actors.means + vel * t, floor.means]), torch.cat([actors.quats, floor.quats]),
                           torch.cat([actors.scales, floor.scales]), torch.cat([actors.opacities, floor.opacities]),
                           sh, torch.arange(30 + nf), colour_space="linear" if flag else "srgb_unbounded")

    with torch.no_grad():
        images = {(str(i), f): render(at(f / FPS), c, backend="torch")["rgb"] for i, c in enumerate(cams)
                  for f in range(*FRAMES)}
        masks = {(str(i), f): render(at(f / FPS, True), c, backend="torch")["rgb"][..., 0]
                 for i, c in enumerate(cams) for f in range(*FRAMES)}
    data = SegmentData.build(frames=FRAMES, camera_ids=[str(i) for i in range(5)], fps=FPS,
                             load_image=lambda c, f: images[(c, f)], camera_for=lambda c, f: cams[int(c)],
                             load_matte=lambda c, f: masks[(c, f)])
    g = torch.Generator().manual_seed(9)
    colour = srgb_decode_unbounded(sh_to_colour(actors.sh, actors.means)).clamp(0, 1)
    points = []
    for f in range(*FRAMES):
        # a noisy "dense" cloud: the performers 3 points a Gaussian with 6 cm jitter, the floor as it is
        xyz = torch.cat([(actors.means + vel * f / FPS).repeat(3, 1) + 0.06 * torch.randn(90, 3, generator=g),
                         floor_xyz])
        rgb = torch.cat([colour.repeat(3, 1), torch.full((nf, 3), 0.01)])
        static = torch.cat([torch.zeros(90, dtype=torch.bool), torch.ones(nf, dtype=torch.bool)])
        points.append(PointsAtTime(f / FPS, xyz, rgb, static))
    return data, points


def _matte_error(result, data: SegmentData) -> float:
    """Mean |performers' alpha - mask| over every view."""
    with torch.no_grad():
        errs = [(performer_alpha(result.model, evaluate(result.model, v.time), v.camera, backend="torch")
                 - v.load_matte()).abs().mean() for v in data.views]
    return float(torch.stack(errs).mean())


def test_the_mask_alpha_loss_pulls_the_performers_alpha_toward_the_mask():
    data, points = _scene()
    base = dict(model=Poly4DGSConfig.paper(sh_degree=0), grid_size=4, checkpoint_every=0, eval_every=0,
                held_out_cameras=[], mcmc=dict(refine_start=1000, cap_max=400))
    initial = _matte_error(train_segment(data, points, TrainConfig(**base, steps=0), seed=0), data)
    without = _matte_error(train_segment(data, points, TrainConfig(**base, steps=60), seed=0), data)
    parts = []
    with_loss = train_segment(data, points, TrainConfig(**base, steps=60, mask_alpha_weight=1.0), seed=0,
                              progress=lambda s, n, info: parts.append(info))
    with_ = _matte_error(with_loss, data)
    print(f"mean |performers' alpha - mask|: initial {initial:.4f}, 60 steps without {without:.4f}, "
          f"with the loss {with_:.4f}")
    assert "matte" in parts[-1]   # the term is reported
    assert with_ < 0.8 * without and with_ < 0.8 * initial


def test_the_loss_can_run_on_every_nth_step_only():
    """``mask_alpha_every`` 3: the term (its extra render) is on steps 3, 6, 9 and no other, and it
    still pulls the alpha toward the masks."""
    data, points = _scene()
    base = dict(model=Poly4DGSConfig.paper(sh_degree=0), grid_size=4, checkpoint_every=0, eval_every=0,
                held_out_cameras=[], mcmc=dict(refine_start=1000, cap_max=400))
    seen = []
    train_segment(data, points, TrainConfig(**base, steps=9, mask_alpha_weight=1.0, mask_alpha_every=3), seed=0,
                  progress=lambda s, n, info: seen.append((s, "matte" in info)))
    assert [s for s, on in seen if on] == [3, 6, 9]
    sparse = train_segment(data, points, TrainConfig(**base, steps=60, mask_alpha_weight=1.0, mask_alpha_every=3),
                           seed=0)
    without = train_segment(data, points, TrainConfig(**base, steps=60), seed=0)
    assert _matte_error(sparse, data) < 0.9 * _matte_error(without, data)


def test_off_the_field_leaves_the_config_json_as_it_was():
    """A train-segment key and a stored record hold the config's JSON: off, the fields are not in it."""
    assert "mask_alpha" not in TrainConfig().model_dump_json()
    assert "mask_alpha" not in TrainConfig(mask_alpha_every=1).model_dump_json()
    assert TrainConfig(mask_alpha_weight=0.5).model_dump()["mask_alpha_weight"] == 0.5
    assert TrainConfig(mask_alpha_weight=0.5, mask_alpha_every=4).model_dump()["mask_alpha_every"] == 4
    assert TrainConfig.model_validate_json(TrainConfig().model_dump_json()) == TrainConfig()
