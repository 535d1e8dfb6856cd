"""Image and video metrics of the detail enhancer (the paper's Table 2 columns that compute offline).

Layouts: images ``[..., C, H, W]``, videos ``[T, C, H, W]`` (channel-first, as the enhancer works).
Values are whatever the caller passes (the benchmark decides between linear and display-encoded
values and between RGB and RGBA); ``data_range`` is the peak (1.0 for ``[0, 1]`` images).

* :func:`psnr` is the project's :func:`volcap_core.image_metrics.psnr` (``10 log10(L² / MSE)`` over all
  elements, MSE floored at 1e-20): identical inputs give a finite **cap of 200 dB** at
  ``data_range = 1`` (not ``inf``), so means over frames stay finite.
* :func:`ssim` is :func:`volcap_core.image_metrics.ssim` (Gaussian 11×11, σ = 1.5, Wang et al.'s
  constants) on channel-first input, ``padding="valid"`` by default: the mean over the region where
  the window fits, as scikit-image's ``structural_similarity(gaussian_weights=True,
  use_sample_covariance=False)`` computes it.
* :func:`tpsnr`: PSNR of temporal differences, ``10 log10(L² / mean((Δf - Δr)²))`` with
  ``Δf_t = f_{t+1} - f_t``, pooled over all pairs (same 200 dB cap).
* :func:`temporal_flickering`: VBench's score ``(255 - mean_t mean|f_t - f_{t+1}|) / 255`` on uint8
  RGB frames; float frames go through :func:`volcap_core.enhance.temporal.to_display_u8` first
  (sRGB encoding, clamped, rounded; ``linear=False`` skips the encoding for display-encoded input).
  A constant video scores exactly 1.
* :func:`warp_error`: masked frame-to-frame warp error (Lai et al. 2018): per consecutive pair,
  ``sum(M · |f_t - warp(f_{t-1}, flow_t)|²) / (C · sum(M))``, averaged over pairs; ``M`` = in-frame
  mask of the flow × optional occlusion masks.
* LPIPS, FID, FVD need backbone weights no wheel ships: they take a local weights path and raise
  :class:`MetricUnavailable` without it (tests skip). FID and FVD use the standard TorchScript
  detectors (StyleGAN3's ``inception-2015-12-05.pt``, StyleGAN-V's ``i3d_torchscript.pt``) with
  :func:`frechet_distance`, which itself needs no weights.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from volcap_core.enhance.temporal import FlowBackend, in_frame, to_display_u8, warp
from volcap_core.image_metrics import psnr as _psnr
from volcap_core.image_metrics import ssim as _ssim

__all__ = [
    "MetricUnavailable",
    "fid",
    "frechet_distance",
    "fvd",
    "lpips",
    "psnr",
    "ssim",
    "temporal_flickering",
    "tpsnr",
    "warp_error",
]

#: PSNR of identical inputs at data_range 1 (MSE floored at 1e-20 by :func:`volcap_core.image_metrics.psnr`).
PSNR_CAP_DB = 200.0


class MetricUnavailable(RuntimeError):
    """A metric needs weights (or a package) that are not available here."""


def psnr(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0) -> float:
    """PSNR in dB over all elements (any equal shapes); identical inputs -> 200 dB at ``data_range = 1``."""
    if x.shape != y.shape:
        raise ValueError(f"shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    return float(_psnr(x.double(), y.double(), data_range))


def ssim(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0, padding: str = "valid") -> float:
    """Mean SSIM of channel-first ``[..., C, H, W]`` images (each channel separately, then the mean)."""
    if x.shape != y.shape:
        raise ValueError(f"shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    if x.ndim < 3:
        raise ValueError(f"expected [..., C, H, W], got {tuple(x.shape)}")
    return float(_ssim(x.movedim(-3, -1).float(), y.movedim(-3, -1).float(), data_range=data_range,
                       padding=padding))


def _video(frames: torch.Tensor, name: str) -> None:
    if not isinstance(frames, torch.Tensor) or frames.ndim != 4:
        raise ValueError(f"{name} must be a video [T, C, H, W]")
    if frames.shape[0] < 2:
        raise ValueError(f"{name}: a temporal metric needs at least 2 frames, got {frames.shape[0]}")


def tpsnr(frames: torch.Tensor, reference: torch.Tensor, data_range: float = 1.0) -> float:
    """PSNR between the temporal differences of ``frames`` and of ``reference`` (both ``[T, C, H, W]``),
    pooled over the ``T - 1`` pairs. A video whose frame-to-frame changes equal the reference's
    (e.g. both static) gets the 200 dB cap."""
    _video(frames, "frames")
    if frames.shape != reference.shape:
        raise ValueError(f"shape mismatch {tuple(frames.shape)} vs {tuple(reference.shape)}")
    f, r = frames.double(), reference.double()
    return float(_psnr(f[1:] - f[:-1], r[1:] - r[:-1], data_range))


def temporal_flickering(frames: torch.Tensor, *, linear: bool = True) -> float:
    """VBench temporal flickering: ``(255 - mean over pairs of mean|f_t - f_{t+1}|) / 255`` on uint8 RGB.

    ``frames``: ``[T, C, H, W]`` (C = 3 or 4; only RGB is scored, as VBench scores RGB videos):
    uint8 as is; float through :func:`to_display_u8` (sRGB, clamped, rounded) when ``linear``, else
    ``rint(255 · clamp(x, 0, 1))`` (already display-encoded). 1.0 = no change between frames.
    """
    _video(frames, "frames")
    if frames.dtype == torch.uint8:
        u8 = frames[:, :3]
    elif linear:
        u8 = to_display_u8(frames[:, :3])
    else:
        u8 = torch.round(frames[:, :3].float().clamp(0.0, 1.0) * 255.0).to(torch.uint8)
    v = u8.to(torch.float64)
    diffs = (v[1:] - v[:-1]).abs().mean(dim=(1, 2, 3))  # per pair, as VBench's cal_score
    return float((255.0 - diffs.mean()) / 255.0)


def warp_error(frames: torch.Tensor, flows: torch.Tensor | FlowBackend, masks: torch.Tensor | None = None) -> float:
    """Masked frame-to-frame warp error (mean squared, in the frames' units²).

    Args:
        frames: ``[T, C, H, W]``.
        flows: ``[T - 1, 2, H, W]`` backward flows, ``flows[t]`` from frame ``t + 1`` to frame ``t``
            (``frames[t+1](x) ≈ frames[t](x + flows[t])``), or a :class:`FlowBackend` run on the
            frames' RGB (for reference-free use; an exact or reference flow is better).
        masks: optional ``[T - 1, 1, H, W]`` validity (e.g. non-occluded) masks, multiplied with the
            flows' in-frame masks.
    Returns:
        mean over pairs of ``sum(M · |f_{t+1} - warp(f_t)|²) / (C · sum(M))``; pairs with an empty mask
        are skipped (NaN if all are).
    """
    _video(frames, "frames")
    t, c, h, w = frames.shape
    if isinstance(flows, torch.Tensor):
        if flows.shape != (t - 1, 2, h, w):
            raise ValueError(f"flows must be [{t - 1}, 2, {h}, {w}], got {tuple(flows.shape)}")
        flow_list = list(flows)
    else:
        flow_list = [flows(frames[i, :3], frames[i + 1, :3]) for i in range(t - 1)]
    if masks is not None and masks.shape != (t - 1, 1, h, w):
        raise ValueError(f"masks must be [{t - 1}, 1, {h}, {w}], got {tuple(masks.shape)}")
    errs = []
    for i, f in enumerate(flow_list):
        m = in_frame(f.float())
        if masks is not None:
            m = m * masks[i].float()
        warped = warp(frames[i].float(), f.float())
        denom = m.sum() * c
        if denom > 0:
            errs.append(float(((frames[i + 1].float() - warped) ** 2 * m).sum() / denom))
    return float(np.mean(errs)) if errs else float("nan")


# --------------------------------------------------------------------------- weight-based metrics

def _weights(path: str | Path | None, metric: str, what: str) -> Path:
    if path is None:
        raise MetricUnavailable(f"{metric} needs {what} given by a local path (no weights ship with any "
                                "installed package and nothing is downloaded)")
    p = Path(path)
    if not p.is_file():
        raise MetricUnavailable(f"{metric}: no weights file at {p}")
    return p


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray) -> float:
    """``|μ1 - μ2|² + tr(Σ1 + Σ2 - 2 (Σ1 Σ2)^½)`` (the FID/FVD formula; Heusel et al. 2017), with
    the usual ε·I regularisation when the product is singular."""
    from scipy import linalg

    mu1, mu2 = np.atleast_1d(np.asarray(mu1, np.float64)), np.atleast_1d(np.asarray(mu2, np.float64))
    s1, s2 = np.atleast_2d(np.asarray(sigma1, np.float64)), np.atleast_2d(np.asarray(sigma2, np.float64))
    diff = mu1 - mu2
    covmean, _ = linalg.sqrtm(s1 @ s2, disp=False)
    if not np.isfinite(covmean).all():
        off = np.eye(s1.shape[0]) * 1e-6
        covmean = linalg.sqrtm((s1 + off) @ (s2 + off))
    covmean = covmean.real
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * np.trace(covmean))


def _stats(feats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    feats = np.asarray(feats, np.float64)
    return feats.mean(0), np.cov(feats, rowvar=False)


@torch.no_grad()
def fid(real: torch.Tensor, fake: torch.Tensor, weights_path: str | Path | None, *, batch: int = 16,
        linear: bool = True) -> float:
    """FID between two image sets ``[N, C, H, W]`` (RGB used; linear float -> :func:`to_display_u8`).

    ``weights_path``: StyleGAN3's TorchScript Inception (``inception-2015-12-05.pt``), called as
    ``detector(uint8 [N, 3, H, W], return_features=True)`` -> 2048-d pool features (it resizes to
    299² itself). Raises :class:`MetricUnavailable` without the file.
    """
    path = _weights(path=weights_path, metric="FID", what="the TorchScript Inception-v3 detector")
    det = torch.jit.load(str(path), map_location="cpu").eval()

    def feats(x: torch.Tensor) -> np.ndarray:
        u8 = x[:, :3] if x.dtype == torch.uint8 else (to_display_u8(x[:, :3]) if linear else
                                                       torch.round(x[:, :3].clamp(0, 1) * 255).to(torch.uint8))
        return torch.cat([det(u8[i:i + batch], return_features=True) for i in range(0, len(u8), batch)]).numpy()

    return frechet_distance(*_stats(feats(real)), *_stats(feats(fake)))


@torch.no_grad()
def fvd(real: Sequence[torch.Tensor] | torch.Tensor, fake: Sequence[torch.Tensor] | torch.Tensor,
        weights_path: str | Path | None, *, linear: bool = True) -> float:
    """FVD between two sets of videos, each ``[T, C, H, W]`` (T >= 10 for I3D; RGB used).

    ``weights_path``: StyleGAN-V's TorchScript I3D (``i3d_torchscript.pt``), called as
    ``detector(videos [N, 3, T, H, W] in [-1, 1], rescale=False, resize=True, return_features=True)``
    -> 400-d features. Raises :class:`MetricUnavailable` without the file.
    """
    path = _weights(path=weights_path, metric="FVD", what="the TorchScript I3D detector")
    det = torch.jit.load(str(path), map_location="cpu").eval()

    def feats(videos) -> np.ndarray:
        out = []
        for v in videos:
            d = to_display_u8(v[:, :3]).float() / 255.0 if linear and v.dtype != torch.uint8 else (
                v[:, :3].float() / 255.0 if v.dtype == torch.uint8 else v[:, :3].float().clamp(0, 1))
            x = (d * 2.0 - 1.0).permute(1, 0, 2, 3)[None]  # [1, 3, T, H, W]
            out.append(det(x, rescale=False, resize=True, return_features=True))
        return torch.cat(out).numpy()

    return frechet_distance(*_stats(feats(real)), *_stats(feats(fake)))


@torch.no_grad()
def lpips(x: torch.Tensor, y: torch.Tensor, weights_path: str | Path | None, *, net: str = "alex",
          linear: bool = True) -> float:
    """LPIPS (Zhang et al. 2018) of two image batches ``[N, C, H, W]`` (RGB used), mean over N.

    Needs the ``lpips`` package (its linear-layer weights ship in the wheel) and torchvision, and
    ``weights_path``: the torchvision state dict of the backbone (``alexnet-owt-7be5be79.pth`` for
    ``net="alex"``, ``vgg16-397923af.pth`` for ``"vgg"``); the backbone is built untrained and these
    weights loaded, so nothing is downloaded. Inputs: linear float -> sRGB display values, scaled to
    ``[-1, 1]``. Raises :class:`MetricUnavailable` otherwise.
    """
    path = _weights(path=weights_path, metric="LPIPS", what=f"the {net} backbone weights")
    try:
        import lpips as _lpips
    except ImportError as e:
        raise MetricUnavailable("LPIPS needs the 'lpips' package (not installed here)") from e
    model = _lpips.LPIPS(net=net, pretrained=True, pnet_rand=True, verbose=False)
    state = torch.load(path, map_location="cpu", weights_only=True)
    # torchvision's "features.<i>.<param>" -> lpips' "slice<k>.<i>.<param>" (lpips keeps indices)
    target = model.net.state_dict()
    by_index = {k.split(".", 1)[1]: k for k in target}
    mapped = {by_index[k.split(".", 1)[1]]: v for k, v in state.items()
              if k.startswith("features.") and k.split(".", 1)[1] in by_index}
    if len(mapped) != len(target):
        raise MetricUnavailable(f"LPIPS: {path} does not hold the torchvision {net} backbone "
                                f"({len(mapped)} of {len(target)} tensors matched)")
    model.net.load_state_dict(mapped)
    model.eval()

    def prep(t: torch.Tensor) -> torch.Tensor:
        d = to_display_u8(t[:, :3]).float() / 255.0 if linear else t[:, :3].float().clamp(0, 1)
        return d * 2.0 - 1.0

    return float(model(prep(x), prep(y)).mean())
