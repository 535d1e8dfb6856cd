"""Training objective (paper §"Training Objective").

    L_total = (1 - λ_ssim)·L1 + λ_ssim·(1 - SSIM)           in unbounded sRGB (both images encoded)
              + λ_e·(mean E - 1)² + λ_b·(-mean B)            exposure / black-level grids
              (+ the 3DGS-MCMC regularisers, :func:`volcap_core.splat.mcmc.mcmc_regulariser`)

with λ_ssim = 0.2 (3DGS), λ_e = 10, λ_b = 0.05 (paper). The prediction and the target are linear;
both go through :func:`~volcap_core.colour.srgb_encode_unbounded` so the loss sees the same
perceptually spaced values the paper trains on, HDR values included (65504 -> ~107). SSIM and
PSNR are :mod:`volcap_core.image_metrics`' (SSIM with 3DGS's zero padding here).
"""

from __future__ import annotations

import torch

from volcap_core.colour import srgb_encode, srgb_encode_unbounded
from volcap_core.image_metrics import psnr, ssim
from volcap_core.splat.grids import black_level_regulariser, exposure_regulariser

__all__ = ["reconstruction_loss", "grid_regularisers", "display_metrics"]


def reconstruction_loss(pred_linear: torch.Tensor, target_linear: torch.Tensor, *,
                        ssim_weight: float = 0.2) -> tuple[torch.Tensor, dict[str, float]]:
    """``(1 - w)·L1 + w·(1 - SSIM)`` between the unbounded-sRGB encodings of two linear images.

    Args:
        pred_linear: ``[H, W, 3]`` adjusted rendering (linear).
        target_linear: ``[H, W, 3]`` captured image (linear, HDR allowed).
        ssim_weight: w, 0.2 as in 3DGS.
    Returns:
        ``(loss, {"l1": ..., "ssim": ...})``.
    """
    p = srgb_encode_unbounded(pred_linear)
    t = srgb_encode_unbounded(target_linear)
    l1 = (p - t).abs().mean()
    s = ssim(p, t, padding="same")
    loss = (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - s)
    return loss, {"l1": float(l1.detach()), "ssim": float(s.detach())}


def grid_regularisers(exposure_all: torch.Tensor, black_view: torch.Tensor, *,
                      exposure_weight: float = 10.0,
                      black_weight: float = 0.05) -> tuple[torch.Tensor, dict[str, float]]:
    """``λ_e (mean E - 1)² + λ_b (-mean B)`` (paper eq. 4-5).

    Args:
        exposure_all: ``[C, 3, h, w]`` every training camera's exposure grid.
        black_view: ``[3, h, w]`` the current view's black-level grid.
    Returns:
        ``(loss, parts)``.
    """
    le = exposure_regulariser(exposure_all)
    lb = black_level_regulariser(black_view)
    return exposure_weight * le + black_weight * lb, {"exposure": float(le.detach()),
                                                      "black": float(lb.detach())}


def display_metrics(pred_linear: torch.Tensor, target_linear: torch.Tensor) -> tuple[float, float]:
    """(PSNR dB, SSIM) of two linear images after display encoding (sRGB, clamped to [0, 1]):
    what a viewer sees, the measure reported for held-out views. Args: ``[H, W, 3]`` each."""
    p = srgb_encode(pred_linear.detach())
    t = srgb_encode(target_linear.detach())
    pad = "valid" if min(p.shape[:2]) > 11 else "same"
    return float(psnr(p, t)), float(ssim(p, t, padding=pad))
