"""LQ/HQ training and evaluation pairs made directly from a synthetic Face Rig capture, until the
Face Rig pair dataset (LQ/HQ Poly4DGS renders) exists; and the bicubic/unsharp-mask baseline.

HQ: the capture's frames as RGBA (:func:`load_face_capture_sequences`). LQ: a synthetic degradation
of each HQ frame (:func:`make_degraded_pairs`) that imitates what a sparse Gaussian-splat render
does to a face: lost fine detail, soft edges (in alpha too) and blotchy colour errors that change
from frame to frame (so an LQ sequence flickers, as LQ renders do), at the HQ frame size.

Degradation, exactly (per frame, all channels unless said; ``h, w = ceil(H / scale), ceil(W / scale)``):

1. downsample to ``h × w``: ``F.interpolate(mode="bilinear", antialias=True, align_corners=False)``;
2. Gaussian blur, σ = ``blur_sigma`` LQ pixels (separable, radius ``ceil(3σ)``, edge replication);
3. splat-like softening of colour (RGB only): ``rgb ← rgb · (1 + n)`` with ``n`` white Gaussian noise
   per channel and frame (``torch.Generator`` seeded with ``seed``), blurred with σ = ``splat_sigma``
   LQ pixels and rescaled to standard deviation ``noise_sigma`` (multiplicative, so premultiplied
   black background stays black);
4. upsample back to ``H × W``: ``F.interpolate(mode="bicubic", align_corners=False)``;
5. RGB clamped to ``>= 0``, alpha to ``[0, 1]``.

Geometry is unchanged, so an exact flow between HQ frames (when one exists) is also the LQ's; the
synthetic capture renders none, so :class:`PairSet` ``flow`` is None for capture pairs.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "PairSet",
    "bicubic_unsharp",
    "gaussian_blur",
    "load_face_capture_sequences",
    "make_degraded_pairs",
    "make_face_pair_sets",
]


@dataclass
class PairSet:
    """One LQ/HQ sequence.

    ``lq``, ``hq``: ``[T, 4, H, W]`` float32 linear RGBA (RGB premultiplied by alpha where the source
    had an alpha); ``flow``: ``[T - 1, 2, H, W]`` exact backward flows when available
    (``flow[t]``: from frame ``t + 1`` to frame ``t``, pixels, x then y; the convention of
    :mod:`volcap_core.enhance.temporal`), else None; ``name``: e.g. the camera id.
    """

    lq: torch.Tensor
    hq: torch.Tensor
    flow: torch.Tensor | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if self.lq.ndim != 4 or self.lq.shape[1] != 4:
            raise ValueError(f"lq must be [T, 4, H, W], got {tuple(self.lq.shape)}")
        if self.hq.shape != self.lq.shape:
            raise ValueError(f"hq {tuple(self.hq.shape)} and lq {tuple(self.lq.shape)} differ in shape")
        t, _, h, w = self.lq.shape
        if self.flow is not None and self.flow.shape != (t - 1, 2, h, w):
            raise ValueError(f"flow must be [{t - 1}, 2, {h}, {w}], got {tuple(self.flow.shape)}")

    def __len__(self) -> int:
        return self.lq.shape[0]


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of ``[N, C, H, W]`` (σ in pixels, radius ``ceil(3σ)``, edge
    replication); σ <= 0 returns ``x``."""
    if sigma <= 0:
        return x
    r = max(1, math.ceil(3.0 * sigma))
    k = torch.exp(-torch.arange(-r, r + 1, dtype=torch.float64) ** 2 / (2.0 * sigma * sigma))
    k = (k / k.sum()).to(x.dtype)
    n, c, h, w = x.shape
    y = x.reshape(n * c, 1, h, w)
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    y = F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return y.reshape(n, c, h, w)


def make_degraded_pairs(face_frames_hq: torch.Tensor, scale: int = 4, blur_sigma: float = 0.6,
                        seed: int = 0, *, noise_sigma: float = 0.03, splat_sigma: float = 1.0,
                        flow: torch.Tensor | None = None, name: str = "") -> PairSet:
    """LQ frames for HQ frames ``[T, 4, H, W]`` (linear RGBA) by the degradation in the module
    docstring; returns a :class:`PairSet` (``flow``, if given, is passed through: the degradation
    moves nothing). Deterministic for a given ``seed``."""
    hq = face_frames_hq
    if hq.ndim != 4 or hq.shape[1] != 4:
        raise ValueError(f"face_frames_hq must be [T, 4, H, W], got {tuple(hq.shape)}")
    if scale < 1:
        raise ValueError(f"scale must be >= 1, got {scale}")
    hq = hq.float()
    t, _, h, w = hq.shape
    lh, lw = math.ceil(h / scale), math.ceil(w / scale)
    low = F.interpolate(hq, size=(lh, lw), mode="bilinear", antialias=True, align_corners=False)
    low = gaussian_blur(low, blur_sigma)
    if noise_sigma > 0:
        g = torch.Generator().manual_seed(int(seed))
        n = gaussian_blur(torch.randn((t, 3, lh, lw), generator=g), splat_sigma)
        n = n * (noise_sigma / n.std().clamp(min=1e-12))
        low = torch.cat([low[:, :3] * (1.0 + n), low[:, 3:]], dim=1)
    lq = F.interpolate(low, size=(h, w), mode="bicubic", align_corners=False)
    lq = torch.cat([lq[:, :3].clamp(min=0.0), lq[:, 3:].clamp(0.0, 1.0)], dim=1)
    return PairSet(lq=lq.contiguous(), hq=hq.contiguous(), flow=flow, name=name)


def bicubic_unsharp(lq: torch.Tensor, size: tuple[int, int] | None = None, *, amount: float = 1.0,
                    sigma: float = 2.0) -> torch.Tensor:
    """The benchmark's classical floor: bicubic resize to ``size = (H, W)`` (skipped when None or
    already that size; LQ from :func:`make_degraded_pairs` is already HQ-sized), then an unsharp
    mask ``x + amount · (x - gaussian_blur(x, sigma))`` (σ in output pixels). RGB clamped to
    ``>= 0``, alpha to ``[0, 1]``. ``lq``: ``[C, H, W]`` or ``[T, C, H, W]``, C = 3 or 4.
    Defaults (amount 1, σ 2 px ≈ scale / 2) suit the ×4 degradation; stronger settings score
    higher on the synthetic faces but halo on sharper content, and this is a floor, not a
    contender (figures in ``docs/enhancer.md``, "Pairs")."""
    single = lq.ndim == 3
    x = lq[None] if single else lq
    if x.ndim != 4 or x.shape[1] not in (3, 4):
        raise ValueError(f"lq must be [C, H, W] or [T, C, H, W] with C = 3 or 4, got {tuple(lq.shape)}")
    x = x.float()
    if size is not None and tuple(size) != tuple(x.shape[-2:]):
        x = F.interpolate(x, size=tuple(size), mode="bicubic", align_corners=False)
    x = x + amount * (x - gaussian_blur(x, sigma))
    out = torch.cat([x[:, :3].clamp(min=0.0), x[:, 3:].clamp(0.0, 1.0)], dim=1)
    return out[0] if single else out


# --------------------------------------------------------------------------- the synthetic capture

def _read_mask(path: Path) -> np.ndarray:
    from volcap_core.imageio.read import read_exr_native

    pixels, _ = read_exr_native(path)  # one channel "Z": coverage in [0, 1]
    return np.asarray(pixels, np.float32).reshape(pixels.shape[0], pixels.shape[1], -1)[..., 0]


def load_face_capture_sequences(capture_json: str | Path, cameras: Sequence[str] | None = None,
                                frames: int | Sequence[int] | None = None, size: tuple[int, int] | None = None,
                                *, premultiply: bool = True) -> dict[str, torch.Tensor]:
    """HQ RGBA sequences from a (synthetic Face Rig) capture: ``{camera id: [T, 4, H, W]}``.

    Args:
        capture_json: the capture's ``capture.json`` (as :func:`volcap_core.synth.synthesize_face_capture`
            returns it).
        cameras: camera ids to read (default: all cameras of the capture, in its order).
        frames: take indices: an int ``n`` = the first ``n``, a sequence = those, None = all of the take.
        size: ``(H, W)`` to resize to (bilinear, antialiased), None = native.
        premultiply: multiply RGB by alpha (a performer render over black, as a Gaussian-splat render
            of the performer is, in the EXR premultiplied convention).
    Frames are read with :meth:`volcap_core.capture.CaptureFolder.load` (scene-linear Rec.709). Alpha is the
    capture's ground-truth performer coverage (``ground_truth/masks/<camera>/<take index>.exr``,
    written by ``synthesize_face_capture(write_depth=True)``); where the capture has no masks,
    alpha = 1 (and premultiplying changes nothing).
    """
    from volcap_core.capture import CaptureFolder

    capture_json = Path(capture_json)
    capture = CaptureFolder.open(capture_json.parent)
    has = capture.camera_ids
    ids = has if cameras is None else list(cameras)
    missing = [c for c in ids if c not in has]
    if missing:
        raise ValueError(f"{capture_json}: no camera {', '.join(missing)} (it has {', '.join(has)})")
    n_take = capture.frame_count
    if frames is None:
        take = list(range(n_take))
    elif isinstance(frames, int):
        take = list(range(frames))
    else:
        take = [int(k) for k in frames]
    if not take:
        raise ValueError("no frames requested")
    bad = [k for k in take if not 0 <= k < n_take]
    if bad:
        raise ValueError(f"take indices {bad} outside the take's {n_take} frames")
    gt = capture.ground_truth_path
    out: dict[str, torch.Tensor] = {}
    for cid in ids:
        seq = []
        for k in take:
            rgb = capture.load(cid, k)
            mask_path = gt / "masks" / cid / f"{k:06d}.exr" if gt is not None else None
            if mask_path is not None and mask_path.is_file():
                alpha = np.clip(_read_mask(mask_path), 0.0, 1.0)
                if alpha.shape != rgb.shape[:2]:
                    raise ValueError(f"{mask_path}: mask {alpha.shape} vs frame {rgb.shape[:2]}")
            else:
                alpha = np.ones(rgb.shape[:2], np.float32)
            if premultiply:
                rgb = rgb * alpha[..., None]
            seq.append(torch.from_numpy(np.concatenate([rgb, alpha[..., None]], axis=2)).permute(2, 0, 1))
        x = torch.stack(seq).float()
        if size is not None and tuple(size) != tuple(x.shape[-2:]):
            x = F.interpolate(x, size=tuple(size), mode="bilinear", antialias=True, align_corners=False)
            x = torch.cat([x[:, :3].clamp(min=0.0), x[:, 3:].clamp(0.0, 1.0)], dim=1)
        out[cid] = x.contiguous()
    return out


def make_face_pair_sets(capture_json: str | Path, cameras: Sequence[str] | None = None,
                        frames: int | Sequence[int] | None = None, size: tuple[int, int] | None = None,
                        *, scale: int = 4, blur_sigma: float = 0.6, seed: int = 0, **degrade) -> list[PairSet]:
    """:func:`load_face_capture_sequences` + :func:`make_degraded_pairs`, one :class:`PairSet` per
    camera (named by it; noise seeded by ``seed`` and the camera id, flow None)."""
    seqs = load_face_capture_sequences(capture_json, cameras, frames, size)
    return [make_degraded_pairs(hq, scale, blur_sigma, zlib.crc32(f"{seed}/{cid}".encode()), name=cid, **degrade)
            for cid, hq in seqs.items()]
