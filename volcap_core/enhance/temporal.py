"""Flow-warped temporal conditioning of the detail enhancer (the paper's "Optical Flow Warping").

For frame ``t`` the enhancer is conditioned on its own previous output warped into frame ``t`` and
on a validity mask. The flow is computed between the previous and the current *LQ* inputs (never
the outputs, which do not exist yet for frame ``t``); the previous LQ is warped with the same flow
and compared with the current LQ to give the mask.

Flow convention (every back-end, and a tensor passed instead of a back-end): **backward flow in
pixels**, ``flow[:, y, x] = (dx, dy)`` (x first, then y) such that the current pixel ``(x, y)`` was at
``(x + dx, y + dy)`` in the previous frame, i.e. ``cur(x, y) ≈ prev(x + dx, y + dy)``. Pixel
coordinates are OpenCV's: the centre of the top-left pixel is ``(0, 0)``.

Back-ends (:class:`FlowBackend`):

* exact rendered flow: pass a ``[2, H, W]`` tensor as ``flow`` (pair dataset, shot renderer);
* :class:`DisFlow`: OpenCV DIS optical flow on CPU (default preset ``MEDIUM``), on 8-bit grey
  images made by :func:`to_display_u8` (see there: sRGB, clamped, rounded) and
  ``cv2.cvtColor(RGB2GRAY)``;
* :class:`RaftFlow`: torchvision's RAFT from a *local* weights file, only where torchvision is
  installed; never downloads.

Tone map used wherever linear HDR RGB must become display values (DIS input, the validity mask,
VBench flicker): :func:`to_display` = IEC 61966-2-1 sRGB encoding of ``exposure · rgb`` clamped to
``[0, 1]`` (:func:`volcap_core.colour.srgb_encode`, the contact sheets' display transform); values
above 1 clip. Alpha (coverage) is not a colour: it is clamped to ``[0, 1]`` and left linear.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch
import torch.nn.functional as F

from volcap_core.colour import srgb_encode

__all__ = [
    "DIS_PRESETS",
    "VALIDITY_THRESHOLD",
    "DisFlow",
    "FlowBackend",
    "FlowUnavailable",
    "RaftFlow",
    "in_frame",
    "temporal_condition",
    "to_display",
    "to_display_u8",
    "validity_mask",
    "warp",
]

#: Default validity threshold: a pixel is valid where the warped previous LQ and the current LQ
#: differ by at most this much in **every** channel, measured on display values in ``[0, 1]``
#: (sRGB-encoded, clamped RGB and linear alpha; :func:`to_display`). 0.08 ≈ 20/255 codes: above the
#: LQ noise and bilinear-resampling differences where the flow is right, below the differences at
#: disocclusions and at silhouettes that moved (the measurement behind it: ``docs/enhancer.md``,
#: "Temporal stability").
VALIDITY_THRESHOLD = 0.08

#: OpenCV DIS presets by name.
DIS_PRESETS = {"ultrafast": 0, "fast": 1, "medium": 2}


class FlowUnavailable(RuntimeError):
    """A flow back-end cannot run here (missing package or weights)."""


@runtime_checkable
class FlowBackend(Protocol):
    """``backend(prev, cur) -> flow``: ``prev``, ``cur`` linear RGB ``[3, H, W]``; returns the backward
    flow ``[2, H, W]`` in pixels (x then y): ``cur(x, y) ≈ prev(x + flow[0], y + flow[1])``."""

    def __call__(self, prev: torch.Tensor, cur: torch.Tensor) -> torch.Tensor: ...


# --------------------------------------------------------------------------- tone map

def to_display(x: torch.Tensor, exposure: float = 1.0) -> torch.Tensor:
    """Linear ``[..., C, H, W]`` (C = 3 RGB or 4 RGBA) -> display values in ``[0, 1]``: RGB through
    the sRGB encoding of ``exposure · rgb`` clamped to ``[0, 1]``, alpha clamped, linear."""
    if x.shape[-3] not in (3, 4):
        raise ValueError(f"expected 3 or 4 channels on dim -3, got shape {tuple(x.shape)}")
    rgb = srgb_encode(x[..., :3, :, :].float() * exposure)
    if x.shape[-3] == 3:
        return rgb
    return torch.cat([rgb, x[..., 3:, :, :].float().clamp(0.0, 1.0)], dim=-3)


def to_display_u8(x: torch.Tensor, exposure: float = 1.0) -> torch.Tensor:
    """:func:`to_display` as 8-bit codes: ``rint(255 · display)``, uint8, same layout."""
    return torch.round(to_display(x, exposure) * 255.0).to(torch.uint8)


def _grey_u8(rgb: torch.Tensor, exposure: float) -> np.ndarray:
    import cv2

    if rgb.ndim != 3 or rgb.shape[0] != 3:
        raise ValueError(f"flow back-ends take RGB [3, H, W], got {tuple(rgb.shape)}")
    u8 = to_display_u8(rgb.detach().cpu(), exposure).permute(1, 2, 0).contiguous().numpy()
    return cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY)


# --------------------------------------------------------------------------- back-ends

class DisFlow:
    """OpenCV's DIS optical flow (Kroeger et al. 2016) on CPU.

    Inputs are linear RGB; each is tone-mapped with :func:`to_display_u8` (sRGB, clamped, 8-bit)
    and converted to grey with ``cv2.cvtColor(RGB2GRAY)`` (0.299 R + 0.587 G + 0.114 B on the
    codes). DIS is run from the current to the previous image, which gives the backward flow
    directly (``cur(x) ≈ prev(x + flow)``). ``preset``: ``"medium"`` (default), ``"fast"`` or
    ``"ultrafast"`` (``cv2.DISOPTICAL_FLOW_PRESET_*``); ``exposure`` scales linear RGB before the
    tone map (dark renders); its accuracy on a known shift is in ``docs/enhancer.md``. One OpenCV
    DIS object per instance: use one instance per thread.
    """

    def __init__(self, preset: str = "medium", exposure: float = 1.0):
        import cv2

        if preset not in DIS_PRESETS:
            raise ValueError(f"unknown DIS preset {preset!r}; one of {sorted(DIS_PRESETS)}")
        self.preset = preset
        self.exposure = float(exposure)
        self._dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])

    def __call__(self, prev: torch.Tensor, cur: torch.Tensor) -> torch.Tensor:
        if prev.shape != cur.shape:
            raise ValueError(f"shape mismatch: prev {tuple(prev.shape)} vs cur {tuple(cur.shape)}")
        a, b = _grey_u8(cur, self.exposure), _grey_u8(prev, self.exposure)
        flow = self._dis.calc(a, b, None)  # [H, W, 2] float32: a(x) ≈ b(x + flow)
        return torch.from_numpy(np.ascontiguousarray(flow)).permute(2, 0, 1).to(cur.device)

    def __repr__(self) -> str:
        return f"DisFlow(preset={self.preset!r}, exposure={self.exposure})"


class RaftFlow:
    """torchvision's RAFT (Teed & Deng 2020) with weights from a local file; never downloads.

    ``weights_path``: a state dict for ``torchvision.models.optical_flow.raft_large`` (or
    ``raft_small`` with ``small=True``), e.g. torchvision's ``raft_large_C_T_SKHT_V2-ff5fadd5.pth``
    copied to the machine. Inputs are tone-mapped with :func:`to_display` (sRGB, clamped), scaled to
    ``[-1, 1]`` as torchvision's RAFT transforms do, edge-padded to a multiple of 8 and the flow
    cropped back. RAFT(image1=cur, image2=prev) gives the backward flow directly.
    Raises :class:`FlowUnavailable` without torchvision or without the file.
    """

    def __init__(self, weights_path: str | Path | None, *, small: bool = False, iters: int = 12,
                 device: str | torch.device = "cpu", exposure: float = 1.0):
        try:
            from torchvision.models.optical_flow import raft_large, raft_small
        except ImportError as e:
            raise FlowUnavailable("RaftFlow needs torchvision (not installed here); use DisFlow or an "
                                  "exact rendered flow") from e
        if weights_path is None:
            raise FlowUnavailable("RaftFlow needs a local weights path (weights are never downloaded)")
        path = Path(weights_path)
        if not path.is_file():
            raise FlowUnavailable(f"RaftFlow: no weights file at {path}")
        model = (raft_small if small else raft_large)(weights=None, progress=False)
        state = torch.load(path, map_location="cpu", weights_only=True)
        model.load_state_dict(state)
        self.model = model.eval().to(device)
        self.device = torch.device(device)
        self.iters = int(iters)
        self.exposure = float(exposure)

    @torch.no_grad()
    def __call__(self, prev: torch.Tensor, cur: torch.Tensor) -> torch.Tensor:
        if prev.shape != cur.shape or prev.ndim != 3 or prev.shape[0] != 3:
            raise ValueError(f"RaftFlow takes two RGB [3, H, W], got {tuple(prev.shape)}, {tuple(cur.shape)}")
        h, w = cur.shape[-2:]
        ph, pw = (-h) % 8, (-w) % 8

        def prep(x: torch.Tensor) -> torch.Tensor:
            x = to_display(x.to(self.device), self.exposure)[None] * 2.0 - 1.0
            return F.pad(x, (0, pw, 0, ph), mode="replicate") if ph or pw else x

        flow = self.model(prep(cur), prep(prev), num_flow_updates=self.iters)[-1][0]
        return flow[:, :h, :w].to(cur.device)


# --------------------------------------------------------------------------- warping

def _check_flow(flow: torch.Tensor, h: int, w: int) -> None:
    if not isinstance(flow, torch.Tensor) or flow.shape != (2, h, w):
        got = tuple(flow.shape) if isinstance(flow, torch.Tensor) else type(flow).__name__
        raise ValueError(f"flow must be a tensor [2, {h}, {w}], got {got}")


def _sample_positions(flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    _, h, w = flow.shape
    ys = torch.arange(h, device=flow.device, dtype=torch.float32)[:, None]
    xs = torch.arange(w, device=flow.device, dtype=torch.float32)[None, :]
    return xs + flow[0].float(), ys + flow[1].float()


def in_frame(flow: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """``[1, H, W]`` float, 1 where the sample position ``(x + dx, y + dy)`` lies inside the previous
    frame's pixel-centre rectangle ``[0, W-1] × [0, H-1]`` (± ``eps``), else 0. Outside it bilinear
    interpolation would blend with the zero padding."""
    _check_flow(flow, flow.shape[-2], flow.shape[-1])
    _, h, w = flow.shape
    sx, sy = _sample_positions(flow)
    ok = (sx >= -eps) & (sx <= w - 1 + eps) & (sy >= -eps) & (sy <= h - 1 + eps)
    return ok[None].to(torch.float32)


def warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Backward warp: ``out(x, y) = image(x + dx, y + dy)``, bilinear.

    ``image``: ``[C, H, W]``; ``flow``: ``[2, H, W]`` backward flow in pixels (x then y). Implemented
    with ``grid_sample(mode="bilinear", align_corners=True)``: normalised ``-1`` / ``+1`` are the
    centres of the first / last pixel, so pixel ``x`` maps to ``2x / (W - 1) - 1`` (OpenCV pixel
    centres, no half-pixel shift). Samples whose position is out of frame (:func:`in_frame` = 0)
    are 0 in every channel (not a partial blend with the border). Returns ``[C, H, W]`` in
    ``image``'s dtype.
    """
    if image.ndim != 3:
        raise ValueError(f"warp takes an image [C, H, W], got {tuple(image.shape)}")
    c, h, w = image.shape
    _check_flow(flow, h, w)
    sx, sy = _sample_positions(flow.to(image.device))
    gx = sx * (2.0 / max(w - 1, 1)) - 1.0
    gy = sy * (2.0 / max(h - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], dim=-1)[None]
    out = F.grid_sample(image[None].float(), grid, mode="bilinear", padding_mode="zeros", align_corners=True)[0]
    return (out * in_frame(flow.to(image.device))).to(image.dtype)


def validity_mask(warped_prev_lq: torch.Tensor, cur_lq: torch.Tensor, threshold: float = VALIDITY_THRESHOLD,
                  in_frame_mask: torch.Tensor | None = None) -> torch.Tensor:
    """``[1, H, W]`` float in {0, 1}: 1 where the warped previous LQ matches the current LQ.

    Both ``[C, H, W]`` linear (C = 3 RGB or 4 RGBA) are mapped to display values with
    :func:`to_display` (sRGB-encoded, clamped RGB; alpha clamped to ``[0, 1]``); a pixel is valid
    when ``max_c |warped_prev_lq_c - cur_lq_c| <= threshold`` (units: display values in ``[0, 1]``,
    i.e. 1/255 per 8-bit code; default :data:`VALIDITY_THRESHOLD`) and, when ``in_frame_mask`` is
    given (:func:`in_frame` of the flow used), its sample position was inside the previous frame.
    """
    if warped_prev_lq.shape != cur_lq.shape or cur_lq.ndim != 3:
        raise ValueError(f"expected two [C, H, W] of one shape, got {tuple(warped_prev_lq.shape)} "
                         f"and {tuple(cur_lq.shape)}")
    diff = (to_display(warped_prev_lq) - to_display(cur_lq.to(warped_prev_lq.device))).abs().amax(dim=0, keepdim=True)
    mask = (diff <= threshold).to(torch.float32)
    if in_frame_mask is not None:
        mask = mask * (in_frame_mask.to(mask.device) > 0.5)
    return mask


def temporal_condition(prev_output: torch.Tensor | None, prev_lq: torch.Tensor | None, cur_lq: torch.Tensor,
                       flow: FlowBackend | torch.Tensor | None, *, threshold: float = VALIDITY_THRESHOLD
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """The two temporal conditions of frame ``t``: the warped previous output and the validity mask.

    Args:
        prev_output: the enhancer's output for frame ``t-1``, RGBA ``[4, H, W]``; None for the first
            frame.
        prev_lq, cur_lq: LQ inputs of frames ``t-1`` and ``t``, RGBA ``[4, H, W]`` linear.
        flow: a :class:`FlowBackend` (called on the LQ RGB: ``flow(prev_lq[:3], cur_lq[:3])``), an
            exact backward flow ``[2, H, W]`` (pixels, x then y), or None = zero flow (the previous
            output taken where it was, no motion compensation; the mask still compares the LQs).
        threshold: see :func:`validity_mask`.
    Returns:
        ``(warped_prev_output [4, H, W], mask [1, H, W])`` in ``cur_lq``'s dtype; both all zeros when
        ``prev_output`` is None (first frame; the paper's "replaced with zeros"). Out-of-frame pixels
        are 0 in the warped output and invalid in the mask.
    """
    if cur_lq.ndim != 3:
        raise ValueError(f"cur_lq must be [C, H, W], got {tuple(cur_lq.shape)}")
    c, h, w = cur_lq.shape
    if prev_output is None:
        return cur_lq.new_zeros((c, h, w)), cur_lq.new_zeros((1, h, w))
    if prev_lq is None:
        raise ValueError("prev_lq is required with prev_output (the mask compares the LQ frames)")
    if prev_output.shape != cur_lq.shape or prev_lq.shape != cur_lq.shape:
        raise ValueError(f"shape mismatch: prev_output {tuple(prev_output.shape)}, prev_lq "
                         f"{tuple(prev_lq.shape)}, cur_lq {tuple(cur_lq.shape)}")
    if flow is None:
        f = cur_lq.new_zeros((2, h, w), dtype=torch.float32)
    elif isinstance(flow, torch.Tensor):
        f = flow
    else:
        f = flow(prev_lq[:3], cur_lq[:3])
    _check_flow(f, h, w)
    f = f.to(cur_lq.device, torch.float32)
    inside = in_frame(f)
    warped_out = warp(prev_output, f)
    mask = validity_mask(warp(prev_lq, f), cur_lq, threshold, inside)
    return warped_out.to(cur_lq.dtype), mask.to(cur_lq.dtype)
