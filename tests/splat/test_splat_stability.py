"""Extreme inputs give finite values and finite gradients through the whole training pipeline:
model slice -> render -> exposure/black grids -> loss -> backward. Each guard is documented in
docs/poly4dgs.md ("Numerical guards")."""

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import random_gaussians, ring_cameras  # noqa: E402

from volcap_core.splat.grids import apply_grids  # noqa: E402
from volcap_core.splat.loss import grid_regularisers, reconstruction_loss  # noqa: E402
from volcap_core.splat.mcmc import MCMCConfig, inject_noise, mcmc_regulariser  # noqa: E402
from volcap_core.splat.model import Gaussians3D, Poly4DGS, Poly4DGSConfig, evaluate  # noqa: E402
from volcap_core.splat.render import render  # noqa: E402

CAM = ring_cameras(1, size=16)[0]


def _model(n=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = Poly4DGS.from_points(Poly4DGSConfig(mean_degree=2, quat_degree=1, scale_degree=1,
                                            opacity_degree=2, sh_degree=1),
                             0.3 * torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g),
                             scales=torch.full((n,), 0.1), t0=torch.zeros(n), opacity=0.8)
    for k in ("means_t", "quats_t", "scales_t"):
        m.params[k].normal_(0, 0.1, generator=g)
    return m


def _pipeline(m, t=0.0, target=None, exposure=None, black=None):
    for v in m.params.values():
        v.requires_grad_(True)
        v.grad = None
    E = (exposure if exposure is not None else torch.ones(3, 4, 4)).clone().requires_grad_(True)
    B = (black if black is not None else torch.zeros(3, 4, 4)).clone().requires_grad_(True)
    out = render(evaluate(m, t), CAM, backend="torch")
    pred = apply_grids(out["rgb"], E, B)
    tgt = target if target is not None else torch.full((16, 16, 3), 0.3)
    loss = reconstruction_loss(pred, tgt)[0] + grid_regularisers(E[None], B)[0]
    loss = loss + mcmc_regulariser(m, MCMCConfig()) + out["depth"].mean() * 1e-3
    loss.backward()
    assert torch.isfinite(loss), "loss"
    for v in out.values():
        assert torch.isfinite(v).all()
    for k, v in m.params.items():
        assert v.grad is None or torch.isfinite(v.grad).all(), k
    assert torch.isfinite(E.grad).all() and torch.isfinite(B.grad).all()
    return out


@pytest.mark.parametrize("t", [1e3, -1e3, 1e7, -1e12, 1e30])
def test_time_far_outside_the_segment(t):
    m = _model()
    m.params["log_lambdas"].fill_(-30.0)  # λ ≈ 1e-13: still alive far away
    _pipeline(m, t)


@pytest.mark.parametrize("log_lam", [-math.inf, -50.0, 0.0, math.log(1e8)])
@pytest.mark.parametrize("t", [0.0, 1e-6, 0.05, 10.0])
def test_lambda_from_zero_to_1e8(log_lam, t):
    m = _model()
    m.params["log_lambdas"].fill_(log_lam)
    _pipeline(m, t)


@pytest.mark.parametrize("scale", [1e-8, 1e-4, 1.0, 1e3])
def test_scales_from_1e_minus_8_to_1e3(scale):
    m = _model()
    m.params["scales"].fill_(math.log(scale))
    m.params["scales_t"].zero_()
    out = _pipeline(m)
    if scale >= 1.0:
        assert out["alpha"].max() > 0.1  # large Gaussians still render (camera outside them)


@pytest.mark.parametrize("norm", [0.0, 1e-30, 1e-10, 1e-4])
def test_quaternions_of_norm_near_zero(norm):
    m = _model()
    m.params["quats"][:] = torch.tensor([1.0, 0.2, -0.3, 0.1]) * norm
    m.params["quats_t"].zero_()
    _pipeline(m)


def test_hdr_targets_and_negative_unbounded_srgb_colours():
    m = _model()
    m.params["sh0"][:4] = -5.0  # SH colour 0.5 - 5·0.28 < 0: negative unbounded sRGB
    target = torch.logspace(-6, math.log10(65504.0), 16 * 16 * 3).reshape(16, 16, 3)
    _pipeline(m, target=target)


@pytest.mark.parametrize("e", [1e-6, 1e-30, 0.0, -0.5])
def test_exposure_toward_zero(e):
    _pipeline(_model(), exposure=torch.full((3, 4, 4), e), black=torch.full((3, 4, 4), -0.1))


def test_gaussians_behind_and_at_camera_plane():
    m = _model()
    with torch.no_grad():
        c, fwd = CAM.centre, CAM.world_to_camera[2, :3]
        m.params["means"][0] = c
        m.params["means"][1] = c - 2 * fwd
        m.params["means"][2] = c + 1e-12 * fwd
        m.params["means_t"][:3] = 0
    _pipeline(m)


def test_noise_with_extreme_scales_stays_finite():
    m = _model()
    with torch.no_grad():
        m.params["scales"][:4] = 200.0      # clamped log-scale
        m.params["scales"][4:] = -200.0
        m.params["opacities"][:] = -50.0
    inject_noise(m, 1.6e-4, MCMCConfig(), torch.Generator().manual_seed(0))
    assert torch.isfinite(m.params["means"]).all()


_NAMES = ("means", "quats", "scales", "opacities", "sh")


def _image_and_grads(g: Gaussians3D):
    """Render, apply exposure/black grids, loss, backward: the output and every gradient."""
    leaves = {n: getattr(g, n).clone().requires_grad_(True) for n in _NAMES}
    E = torch.full((3, 4, 4), 1.1).requires_grad_(True)
    B = torch.full((3, 4, 4), 0.01).requires_grad_(True)
    out = render(Gaussians3D(**leaves, ids=g.ids), CAM, backend="torch")
    pred = apply_grids(out["rgb"], E, B)
    loss = reconstruction_loss(pred, torch.full((16, 16, 3), 0.3))[0] + out["depth"].mean() * 1e-3
    loss = loss + out["alpha"].mean()
    loss.backward()
    return out, {n: leaves[n].grad for n in _NAMES}, E.grad, B.grad


def test_non_finite_gaussians_are_culled_without_poisoning_the_others():
    # before: the NaN colour made the image and every gradient NaN, the grids' included
    valid = random_gaussians(6, seed=3, sh_degree=1, scale=(0.05, 0.2))
    bad = random_gaussians(4, seed=4, sh_degree=1, scale=(0.05, 0.2))
    bad.means = valid.means[:4] + 0.01           # in view, on top of valid ones
    bad.sh[0, 1] = math.nan                      # NaN colour (SH), finite geometry
    bad.scales[1, 0] = math.inf                  # infinite scale
    bad.sh[2, 0] = 1e30                          # finite SH whose decoded colour overflows to inf
    bad.means[3, 2] = -math.inf                  # infinite mean
    both = Gaussians3D(*(torch.cat([getattr(bad, n)[:2], getattr(valid, n), getattr(bad, n)[2:]])
                         for n in _NAMES), ids=torch.arange(10))
    out_v, grads_v, E_v, B_v = _image_and_grads(valid)
    out_b, grads_b, E_b, B_b = _image_and_grads(both)
    assert out_v["alpha"].max() > 0.3
    for k in out_v:
        assert torch.isfinite(out_b[k]).all(), k
        assert torch.equal(out_b[k], out_v[k]), k
    assert torch.equal(E_b, E_v) and torch.equal(B_b, B_v)
    for n in _NAMES:
        assert torch.isfinite(grads_b[n]).all(), n
        assert torch.equal(grads_b[n][2:8], grads_v[n]), n
        # the culled Gaussians themselves: exactly zero gradient, like any culled Gaussian
        assert (grads_b[n][:2] == 0).all() and (grads_b[n][8:] == 0).all(), n
