"""Image similarity: PSNR, SSIM and detail, the measures every stage of volcap reports.

Both the Poly4DGS training loss and held-out scoring (``volcap_core.splat``) and the Detail
Enhancer's evaluation (``volcap_core.enhance.metrics``) measure images with these two functions,
so that a dB or an SSIM means the same thing in every table. They live in a top-level module that
imports nothing of ``volcap_core``: both packages import it downward, and the enhancer does not
reach into the reconstruction library for its metrics.

SSIM is Wang et al.'s with an 11×11 Gaussian window (σ = 1.5), population statistics,
C1 = (0.01 L)², C2 = (0.03 L)². ``padding="valid"`` reproduces scikit-image's
``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False)`` and
kornia's ``ssim(..., padding="valid")``; ``padding="same"`` zero-pads like 3DGS's training loss.

Region figures (a performer or face mask): :func:`region_psnr` is PSNR over the region's pixels,
:func:`region_ssim` the mean of the ``padding="same"`` SSIM map over them (the windows still read
the pixels around the region, so a silhouette's edge counts).

**Detail** (:func:`detail`): how much of the truth's fine structure an output holds, the measure
PSNR cannot give on a smooth close-up (a blurred face loses little PSNR). It is the ratio of
gradient energies over a region::

    detail = Σ_region |∇ output|² / Σ_region |∇ truth|²

with ``∇`` the forward differences along x and along y of each channel (a difference counts when
both of its pixels are in the region), summed over channels, on the images as given: the callers
pass display sRGB (IEC 61966-2-1, clamped to [0, 1]) so that a shadow's texture weighs as the eye
weighs it. 1 = as much detail as the truth; a blur gives < 1; added noise or ringing > 1 (it is
energy, not correctness: read it beside PSNR/SSIM, which see the noise). No colour fit is part of
the measure: a caller whose output and truth differ in exposure (a held-out camera's footage)
applies its scoring protocol's transform first.
"""

from __future__ import annotations

import functools
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["detail", "gradient_energy", "psnr", "region_psnr", "region_ssim", "ssim"]


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


def _region(mask: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    m = mask if isinstance(mask, torch.Tensor) else torch.as_tensor(np.asarray(mask))
    if m.dtype != torch.bool:
        m = m >= 0.5
    if tuple(m.shape) != tuple(shape[:2]):
        raise ValueError(f"region mask {tuple(m.shape)} does not match the image {tuple(shape[:2])}")
    return m


def region_psnr(x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, data_range: float = 1.0) -> float | None:
    """PSNR in dB over the pixels of a region. ``x``, ``y``: ``[H, W, C]``; ``mask``: ``[H, W]``
    bool (or weights, region = ``>= 0.5``). None when the region is empty. Identical images give
    200 dB at ``data_range = 1`` (MSE floored at 1e-20, as :func:`psnr`)."""
    if x.shape != y.shape:
        raise ValueError(f"shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    m = _region(mask, x.shape).to(x.device)
    if not bool(m.any()):
        return None
    mse = float(((x - y) ** 2)[m].mean())
    return float(10.0 * np.log10(data_range ** 2 / max(mse, 1e-20)))


def region_ssim(x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, data_range: float = 1.0) -> float | None:
    """Mean of the ``padding="same"`` SSIM map (:func:`ssim`) over a region's pixels and channels.
    ``x``, ``y``: ``[H, W, C]``; ``mask``: ``[H, W]``. None when the region is empty."""
    if x.shape != y.shape:
        raise ValueError(f"shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    m = _region(mask, x.shape).to(x.device)
    if not bool(m.any()):
        return None
    smap = ssim(x, y, data_range=data_range, padding="same", reduction="none")   # [H, W, C]
    return float(smap[m].mean())


def gradient_energy(x: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """``Σ |∇x|²`` over a region: the squared forward differences along x and y of every channel of
    ``x [H, W, C]``, each counted when both of its pixels are in ``mask [H, W]`` (None: all)."""
    x = x.double()
    dx = (x[:, 1:] - x[:, :-1]) ** 2
    dy = (x[1:] - x[:-1]) ** 2
    if mask is None:
        return float(dx.sum() + dy.sum())
    m = _region(mask, x.shape).to(x.device)
    mx = (m[:, 1:] & m[:, :-1])[..., None]
    my = (m[1:] & m[:-1])[..., None]
    return float((dx * mx).sum() + (dy * my).sum())


def detail(output: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor | None = None) -> float | None:
    """The detail measure of the module doc: ``gradient_energy(output) / gradient_energy(truth)``
    over a region (``[H, W, C]`` images, display-encoded by the caller; ``mask [H, W]`` or None).
    None when the truth has no gradient there (an empty or flat region)."""
    if output.shape != truth.shape:
        raise ValueError(f"shape mismatch {tuple(output.shape)} vs {tuple(truth.shape)}")
    e_truth = gradient_energy(truth, mask)
    if not e_truth > 0:
        return None
    return gradient_energy(output, mask) / e_truth
