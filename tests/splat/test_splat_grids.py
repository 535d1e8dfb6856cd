"""Exposure/black-level grids: the matrix upsample equals the FFT zero-padding reference (and
scipy's resample), is exact at the grid samples, keeps constants, and applies as (C + B)·E."""

import numpy as np
import pytest
import scipy.signal
import torch

from volcap_core.splat.grids import (
    ExposureGrids,
    apply_grids,
    black_level_regulariser,
    exposure_regulariser,
    fft_upsample,
    upsample_grid,
)


@pytest.mark.parametrize("H,W", [(64, 96), (45, 77), (32, 32), (20, 50), (1080 // 8, 1920 // 8)])
def test_matrix_upsample_equals_fft_reference(H, W):
    g = torch.randn(2, 3, 32, 32, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    ref = fft_upsample(g, H, W)
    torch.testing.assert_close(upsample_grid(g, H, W), ref, atol=1e-12, rtol=1e-12)
    sp = scipy.signal.resample(scipy.signal.resample(g.numpy(), H, axis=-2), W, axis=-1)
    np.testing.assert_allclose(ref.numpy(), sp, atol=1e-12)


def test_exact_at_grid_samples_and_constant_stays_constant():
    g = torch.rand(3, 32, 32, dtype=torch.float64)
    up = upsample_grid(g, 96, 64)
    torch.testing.assert_close(up[:, ::3, ::2], g, atol=1e-12, rtol=0)
    c = torch.full((3, 32, 32), 0.7)
    torch.testing.assert_close(upsample_grid(c, 50, 71), torch.full((3, 50, 71), 0.7))
    # float32 path agrees with float64
    torch.testing.assert_close(upsample_grid(g.float(), 96, 64), up.float(), atol=1e-5, rtol=0)


def test_apply_is_black_then_exposure_and_differentiable():
    rgb = torch.rand(16, 24, 3)
    E = torch.full((3, 32, 32), 2.0, requires_grad=True)
    B = torch.full((3, 32, 32), 0.1, requires_grad=True)
    out = apply_grids(rgb, E, B)
    torch.testing.assert_close(out, (rgb + 0.1) * 2.0)
    out.sum().backward()
    assert torch.isfinite(E.grad).all() and torch.isfinite(B.grad).all()
    assert apply_grids(rgb, None, None) is rgb


def test_regularisers_and_identity_grids():
    grids = ExposureGrids.identity(["a", "b"])
    assert float(exposure_regulariser(grids.exposure)) == 0.0
    assert float(black_level_regulariser(grids.black[0])) == 0.0
    rgb = torch.rand(8, 8, 3)
    torch.testing.assert_close(grids.apply(rgb, "b"), rgb)
    assert float(exposure_regulariser(grids.exposure * 1.5)) == pytest.approx(0.25)
