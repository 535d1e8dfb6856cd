"""Image similarity: PSNR and SSIM, the measures every stage of volcap reports.

Both the Poly4DGS training loss and held-out scoring (``volcap_core.splat``) and the Detail
Enhancer's evaluation (``volcap_core.enhance.metrics``) measure images with these two functions,
so that a dB or an SSIM means the same thing in every table. They live in a top-level module that
imports nothing of ``volcap_core``: both packages import it downward, and the enhancer does not
reach into the reconstruction library for its metrics.

SSIM is Wang et al.'s with an 11×11 Gaussian window (σ = 1.5), population statistics,
C1 = (0.01 L)², C2 = (0.03 L)². ``padding="valid"`` reproduces scikit-image's
``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False)`` and
kornia's ``ssim(..., padding="valid")``; ``padding="same"`` zero-pads like 3DGS's training loss.
"""

from __future__ import annotations

import functools
from typing import Literal

import torch
import torch.nn.functional as F

__all__ = ["psnr", "ssim"]


@functools.lru_cache(maxsize=8)
def _gauss_1d(size: int, sigma: float) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()


#: Axes up to this length are blurred with one dense band matrix; longer ones in blocks of
#: :data:`_BLOCK` outputs (see :func:`_blur_axis`).
_DENSE_MAX = 512
_BLOCK = 64


@functools.lru_cache(maxsize=32)
def _band_matrix(n_out: int, window_size: int, sigma: float) -> torch.Tensor:
    """``M [n_out + window_size - 1, n_out]`` float64 with ``M[j + k, j] = g[k]``: ``x @ M`` is the
    valid correlation of ``x`` with the Gaussian window (symmetric, so also the convolution)."""
    g = _gauss_1d(window_size, sigma)
    m = torch.zeros(n_out + window_size - 1, n_out, dtype=torch.float64)
    for j in range(n_out):
        m[j:j + window_size, j] = g
    return m


def _blur_axis(t: torch.Tensor, window_size: int, sigma: float, same: bool) -> torch.Tensor:
    """1D Gaussian filter along the last axis of ``t``, zero padding (``same``) or none (valid),
    as matrix products: an axis of up to :data:`_DENSE_MAX` samples is one product with a band
    matrix; a longer one is cut into blocks of :data:`_BLOCK` outputs that each read their
    ``_BLOCK + window_size - 1`` inputs (an ``unfold`` view), so the work stays linear in the
    length (a dense 1920-wide band matrix would do 170x the multiply-adds of the filter)."""
    n = t.shape[-1]
    halo = window_size - 1
    n_out = n if same else n - halo
    if n_out < 1:
        raise ValueError(f"image axis of {n} px is shorter than the {window_size}-px window")
    b = n_out if n_out <= _DENSE_MAX else _BLOCK
    nb = -(-n_out // b)
    left = window_size // 2 if same else 0
    right = nb * b + halo - n - left
    p = F.pad(t, (left, right)) if left or right else t
    m = _band_matrix(b, window_size, sigma).to(t)
    if nb == 1:
        out = p @ m
    else:
        out = (p.unfold(-1, b + halo, b) @ m).flatten(-2)
    return out[..., :n_out] if out.shape[-1] != n_out else out


def ssim(x: torch.Tensor, y: torch.Tensor, *, data_range: float = 1.0, window_size: int = 11,
         sigma: float = 1.5, padding: Literal["same", "valid"] = "same",
         reduction: Literal["mean", "none"] = "mean") -> torch.Tensor:
    """Structural similarity of channel-last images.

    The Gaussian blurs are separable and computed as matrix products (:func:`_blur_axis`), not
    ``conv2d``: on one CPU thread the ``conv2d`` backward of a one-channel 11-tap filter
    dominated a Poly4DGS training step (timings in ``docs/poly4dgs.md``, "Loss"). Same values to
    float rounding (tested against the ``conv2d`` form).

    Args:
        x, y: ``[..., H, W, C]`` images (any leading batch dims), same shape.
        data_range: L in C1 = (0.01 L)², C2 = (0.03 L)².
        window_size, sigma: Gaussian window (px).
        padding: ``"same"`` (zero padding, output H×W) or ``"valid"`` (output shrinks by
            window_size - 1 per axis, scikit-image's cropped mean).
        reduction: ``"mean"`` -> scalar; ``"none"`` -> the SSIM map ``[..., H', W', C]``.
    Returns:
        mean SSIM (scalar) or the map.
    """
    if x.shape != y.shape:
        raise ValueError(f"shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    same = padding == "same"

    def blur(t):  # [..., C, H, W] -> [..., C, H', W']: along W, then along H
        t = _blur_axis(t, window_size, sigma, same)
        return _blur_axis(t.transpose(-1, -2), window_size, sigma, same).transpose(-1, -2)

    a, b = x.movedim(-1, -3), y.movedim(-1, -3)   # channel-first views
    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a * mu_a
    var_b = blur(b * b) - mu_b * mu_b
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    num = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
    s = num / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    if reduction == "mean":
        return s.mean()
    return s.movedim(-3, -1)


def psnr(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB: ``10 log10(L² / MSE)``. Args: any equal shapes."""
    mse = torch.mean((x - y) ** 2)
    return 10.0 * torch.log10(data_range ** 2 / mse.clamp(min=1e-20))
