"""Offline image and video metrics of the detail enhancer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from volcap_core import image_metrics
from volcap_core.enhance.metrics import (
    PSNR_CAP_DB,
    MetricUnavailable,
    fid,
    frechet_distance,
    fvd,
    lpips,
    psnr,
    ssim,
    temporal_flickering,
    tpsnr,
    warp_error,
)
from volcap_core.enhance.temporal import warp


def _video(t=5, c=4, h=24, w=32, seed=0):
    return torch.rand(t, c, h, w, generator=torch.Generator().manual_seed(seed))


def test_psnr_and_ssim_reuse_the_project_metrics():
    x = _video(1)[0]
    y = (x + 0.05 * torch.randn(x.shape, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    assert psnr(x, x) == pytest.approx(PSNR_CAP_DB)                 # capped, finite
    mse = float(((x.double() - y.double()) ** 2).mean())
    assert psnr(x, y) == pytest.approx(10 * math.log10(1 / mse), abs=1e-6)
    assert psnr(x, y) == pytest.approx(float(image_metrics.psnr(x, y)), abs=1e-3)
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-6)
    s = ssim(x, y)
    assert 0 < s < 1
    assert s == pytest.approx(float(image_metrics.ssim(x.movedim(0, -1), y.movedim(0, -1), padding="valid")), abs=1e-6)


def test_tpsnr():
    static = _video(1).expand(6, -1, -1, -1)
    ref = _video(1, seed=3).expand(6, -1, -1, -1)
    assert tpsnr(static, ref) == pytest.approx(PSNR_CAP_DB)        # both static: same (zero) change
    flick = static + 0.02 * torch.tensor([0, 1, 0, 1, 0, 1.0])[:, None, None, None]
    # every temporal difference is ±0.02 everywhere: MSE = 4e-4 (to float32 rounding of the input)
    assert tpsnr(flick, static) == pytest.approx(10 * math.log10(1 / 4e-4), abs=1e-4)
    # a video moving exactly like the reference, offset by a constant, is temporally perfect
    moving = _video(6, seed=4)
    assert tpsnr(moving.double() + 0.1, moving.double()) > 150   # float64 rounding of the offset only
    assert tpsnr(moving + 0.1, moving) > 120                      # float32 rounding of the offset only
    with pytest.raises(ValueError):
        tpsnr(static[:1], ref[:1])


def test_temporal_flickering_vbench_formula():
    const = torch.full((8, 3, 16, 16), 0.3)
    assert temporal_flickering(const) == 1.0
    u8 = torch.zeros(4, 3, 8, 8, dtype=torch.uint8)
    u8[1::2] = 51                                            # |diff| = 51 codes on every pair
    assert temporal_flickering(u8) == pytest.approx((255 - 51) / 255)
    # float, display-encoded: 0.2 -> 51
    assert temporal_flickering(u8.float() / 255, linear=False) == pytest.approx((255 - 51) / 255)
    # linear float goes through the sRGB tone map: 0.0 and 1.0 -> 0 and 255 codes; alpha is ignored
    lin = torch.zeros(2, 4, 8, 8)
    lin[1, :3] = 1.0
    lin[0, 3] = 1.0
    assert temporal_flickering(lin) == 0.0


def test_warp_error_zero_for_exactly_warped_frames():
    g = torch.Generator().manual_seed(5)
    t, h, w = 4, 20, 28
    frames = [torch.rand(4, h, w, generator=g)]
    flows = []
    for i in range(t - 1):
        f = torch.zeros(2, h, w)
        f[0], f[1] = -(i + 1.0), 1.0 * (i % 2)           # integer moves: exact bilinear samples
        flows.append(f)
        nxt = warp(frames[-1], f)
        frames.append(nxt)
    frames, flows = torch.stack(frames), torch.stack(flows)
    assert warp_error(frames, flows) == pytest.approx(0.0, abs=1e-12)
    # a perturbed frame shows up, in the frames' units squared
    noisy = frames.clone()
    noisy[2] += 0.1
    assert warp_error(noisy, flows) > 1e-3
    # an occlusion mask excluding everything of pair 1 skips it
    masks = torch.ones(t - 1, 1, h, w)
    masks[1] = 0
    e = warp_error(noisy, flows, masks)
    assert e > 1e-3
    with pytest.raises(ValueError, match="flows"):
        warp_error(frames, flows[:1])


def test_frechet_distance_closed_form():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 3))
    mu, cov = a.mean(0), np.cov(a, rowvar=False)
    assert frechet_distance(mu, cov, mu, cov) == pytest.approx(0.0, abs=1e-6)
    assert frechet_distance(mu, cov, mu + [1.0, 2.0, 0.0], cov) == pytest.approx(5.0, abs=1e-6)
    # isotropic covariances: tr(s1 + s2 - 2 sqrt(s1 s2)) = d (σ1 - σ2)²
    assert frechet_distance(np.zeros(4), np.eye(4), np.zeros(4), 9 * np.eye(4)) == pytest.approx(16.0)


def test_weight_metrics_refuse_without_weights(tmp_path):
    x = torch.rand(2, 3, 16, 16)
    for call in (lambda p: lpips(x, x, p), lambda p: fid(x, x, p), lambda p: fvd([x], [x], p)):
        with pytest.raises(MetricUnavailable, match="local path"):
            call(None)
        with pytest.raises(MetricUnavailable, match="no weights file"):
            call(tmp_path / "absent.pt")


class _InceptionStandIn(torch.nn.Module):
    """A TorchScript stand-in with the call of StyleGAN3's Inception detector (uint8 [N, 3, H, W],
    ``return_features``) -> [N, 6] features: per-channel mean and spread of the image. Not the real
    network (its weights cannot be shipped): it checks the plumbing (display conversion, batching,
    the Fréchet distance of the features)."""

    def forward(self, x: torch.Tensor, return_features: bool = True) -> torch.Tensor:
        assert x.dtype == torch.uint8
        f = x.float() / 255.0
        return torch.cat([f.mean(dim=(2, 3)), f.std(dim=(2, 3))], dim=1)


class _I3DStandIn(torch.nn.Module):
    """The same for StyleGAN-V's I3D call (videos [N, 3, T, H, W] in [-1, 1]) -> [N, 4] features:
    mean colour and mean absolute temporal difference."""

    def forward(self, x: torch.Tensor, rescale: bool = False, resize: bool = True,
                return_features: bool = True) -> torch.Tensor:
        assert float(x.min()) >= -1.0 and float(x.max()) <= 1.0
        motion = (x[:, :, 1:] - x[:, :, :-1]).abs().mean(dim=(1, 2, 3, 4))
        return torch.cat([x.mean(dim=(2, 3, 4)), motion[:, None]], dim=1)


def test_fid_and_fvd_run_a_local_torchscript_detector(tmp_path):
    inception = tmp_path / "inception.pt"
    torch.jit.script(_InceptionStandIn()).save(str(inception))
    i3d = tmp_path / "i3d.pt"
    torch.jit.script(_I3DStandIn()).save(str(i3d))
    g = torch.Generator().manual_seed(0)
    real = torch.rand(40, 3, 16, 16, generator=g) * 0.5
    assert fid(real, real, inception, batch=7) == pytest.approx(0.0, abs=1e-6)
    brighter = fid(real, real * 1.5, inception)
    assert brighter > 1e-3 and fid(real, real * 2.0, inception) > brighter  # grows with the change
    videos = [torch.rand(10, 3, 8, 8, generator=g) * 0.5 for _ in range(6)]
    still = [v[:1] + 0.01 * torch.rand(10, 3, 8, 8, generator=g) for v in videos]  # nearly frozen
    assert fvd(videos, videos, i3d) == pytest.approx(0.0, abs=1e-6)
    assert fvd(videos, still, i3d) > 1e-3  # the frozen videos lose most of their motion
