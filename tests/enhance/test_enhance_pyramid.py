"""Laplacian pyramid with OpenCV's pyrDown/pyrUp convention, and the low-frequency swap."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from volcap_core.enhance.pyramid import (
    laplacian_pyramid,
    lowpass,
    pyr_down,
    pyr_up,
    pyramid_sizes,
    reconstruct,
    swap_low_frequency,
)


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.permute(1, 2, 0).numpy()


@pytest.mark.parametrize("hw", [(1, 1), (1, 5), (2, 3), (7, 9), (8, 8), (13, 6), (45, 80)])
def test_pyr_down_and_up_match_opencv(hw):
    h, w = hw
    a = np.random.default_rng(h * 100 + w).random((h, w, 3), dtype=np.float32)
    t = torch.from_numpy(a).permute(2, 0, 1)
    ref = cv2.pyrDown(a).reshape((h + 1) // 2, (w + 1) // 2, 3)
    np.testing.assert_allclose(_hwc(pyr_down(t)), ref, rtol=0, atol=1e-6)
    # pyrUp to every size OpenCV allows: 2n and 2n - 1 on each axis
    for oh in (2 * h - 1, 2 * h):
        for ow in (2 * w - 1, 2 * w):
            ref = cv2.pyrUp(a, dstsize=(ow, oh)).reshape(oh, ow, 3)
            np.testing.assert_allclose(_hwc(pyr_up(t, (oh, ow))), ref, rtol=0, atol=1e-6)


def test_pyramid_matches_opencv_pyramid():
    a = np.random.default_rng(1).random((67, 93), dtype=np.float32)
    pyr = laplacian_pyramid(torch.from_numpy(a), 3)
    g = a
    for k in range(3):
        low = cv2.pyrDown(g)
        band = g - cv2.pyrUp(low, dstsize=(g.shape[1], g.shape[0]))
        np.testing.assert_allclose(pyr[k].numpy(), band, rtol=0, atol=2e-6)
        g = low
    np.testing.assert_allclose(pyr[-1].numpy(), g, rtol=0, atol=1e-6)


@pytest.mark.parametrize("shape", [(4, 64, 64), (4, 135, 240), (2, 3, 37, 51)])
def test_exact_reconstruction(shape):
    x = torch.randn(shape, generator=torch.Generator().manual_seed(0)) * 3.0
    pyr = laplacian_pyramid(x, 5)
    assert len(pyr) == 6
    assert [tuple(p.shape[-2:]) for p in pyr] == pyramid_sizes(shape[-2], shape[-1], 5)
    torch.testing.assert_close(reconstruct(pyr), x, rtol=0, atol=1e-5)
    x64 = x.double()
    assert (reconstruct(laplacian_pyramid(x64, 5)) - x64).abs().max() < 1e-12


def test_4k_lowest_level_is_120x68():
    # the paper: "a 5-level Laplacian pyramid ... the lowest level (120 × 68 pixels)"
    assert pyramid_sizes(2160, 3840, 5)[-1] == (68, 120)
    assert pyramid_sizes(2160, 3840, 5) == [(2160, 3840), (1080, 1920), (540, 960), (270, 480),
                                            (135, 240), (68, 120)]
    x = torch.zeros(1, 2160, 3840)   # one channel: 33 MB
    x[0, ::7, ::5] = 1.0
    low = lowpass(x, 5)
    assert tuple(low.shape) == (1, 68, 120)
    assert tuple(laplacian_pyramid(x, 5)[-1].shape) == (1, 68, 120)
    # and OpenCV agrees on the size chain
    assert cv2.pyrDown(np.zeros((135, 240), np.float32)).shape == (68, 120)


def test_swap_keeps_output_high_frequencies():
    g = torch.Generator().manual_seed(2)
    lq = torch.rand(4, 96, 160, generator=g)
    yy, xx = torch.meshgrid(torch.arange(96), torch.arange(160), indexing="ij")
    checker = ((xx + yy) % 2).float() * 2 - 1          # Nyquist: pyrDown removes it exactly
    output = lq + 0.1 * checker
    swapped = swap_low_frequency(output, lq)
    torch.testing.assert_close(swapped, output, rtol=0, atol=1e-5)


def test_swap_takes_lq_low_frequency():
    g = torch.Generator().manual_seed(3)
    lq = torch.rand(4, 96, 160, generator=g)
    offset = torch.tensor([0.2, -0.1, 0.05, 0.0])[:, None, None]
    output = lq + offset                                   # a global intensity shift
    torch.testing.assert_close(swap_low_frequency(output, lq), lq, rtol=0, atol=1e-5)
    # a shift plus detail: the shift goes, the detail stays; float64 so that only the maths is tested
    lq64, offset64 = lq.double(), offset.double()
    detail = torch.randn(4, 96, 160, generator=g, dtype=torch.float64) * 0.05
    with_detail = lq64 + detail
    torch.testing.assert_close(swap_low_frequency(with_detail + offset64, lq64),
                               swap_low_frequency(with_detail, lq64), rtol=0, atol=1e-12)
    # what the swap changes is only the expanded residual difference (band-pass levels untouched)
    swapped = swap_low_frequency(with_detail, lq64)
    change = lowpass(lq64, 5) - lowpass(with_detail, 5)
    for size in reversed(pyramid_sizes(96, 160, 5)[:-1]):
        change = pyr_up(change, size)
    torch.testing.assert_close(swapped - with_detail, change, rtol=0, atol=1e-12)
    assert change.abs().max() < 0.01          # the detail is zero-mean noise: its residual is small


def test_swap_batched_and_errors():
    x = torch.rand(2, 4, 40, 72)
    y = torch.rand(2, 4, 40, 72)
    s = swap_low_frequency(x, y, levels=3)
    for i in range(2):
        torch.testing.assert_close(s[i], swap_low_frequency(x[i], y[i], levels=3), rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        swap_low_frequency(x, y[:, :3])
    with pytest.raises(ValueError, match="goes to 7 or 8 px"):
        pyr_up(torch.rand(3, 4, 4), (10, 8))
