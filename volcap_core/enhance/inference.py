"""Enhance frames with a trained Detail Enhancer: Euler sampling of the rectified flow, tiled.

:func:`enhance_frame` turns one LQ RGBA frame (and, after the first frame, the previous output, the
previous LQ and the flow between the LQ frames) into an enhanced RGBA frame:

1. pad to a multiple of 16 px (edge replication; cropped off at the end);
2. temporal conditions (:func:`~volcap_core.enhance.temporal.temporal_condition`): the previous
   output warped into this frame and the validity mask; zero latents for the first frame;
3. VAE-encode the four conditions over the whole frame (the VAE's own tiling,
   ``vae.enable_tiling()``, for frames larger than its tile);
4. noise ``[2C, H/8, W/8]`` from ``seed`` for the whole frame, then ``steps`` Euler steps
   ``x <- x + (sigma_next - sigma) v`` over :func:`~volcap_core.enhance.model.flux_sigmas` with the
   shift ``mu`` fixed to the training crop's value (:func:`~volcap_core.enhance.model.crop_mu`), not
   the frame's: Flux's automatic shift at full-frame 4K would be far outside its calibrated range,
   and each tile is a training-crop-sized view anyway. With ``strength`` < 1 the sampler starts
   from the LQ instead of pure noise, as diffusers' ``FluxImg2ImgPipeline`` does: of the ``steps``
   noise levels only the last ``round(steps * strength)`` are run, from
   ``x = (1 - sigma_0) z_LQ + sigma_0 noise`` (``z_LQ``: the LQ RGB and alpha latents, the same
   latents as the first two conditions); the LQ's structure then survives the sampling and the
   model only has to add what is missing;
5. the velocity of each step is predicted tile by tile when ``tile`` is smaller than the frame
   (:func:`tiled_velocity`): square latent tiles overlapping by ``overlap``, each seen by the
   transformer as a crop of its own (position ids from its corner), blended by weights that ramp
   linearly across the overlaps (:func:`blend_weights`) and normalised by their sum — the
   MultiDiffusion scheme. Because the blend happens on the velocity at every step of one global
   latent, neighbouring tiles agree and no seam forms;
6. decode the RGB and alpha latents separately (VAE tiling again); RGB back to linear light,
   clamped to >= 0 (below), alpha = mean of the decoded channels in [0, 1];
7. the low-frequency swap (:func:`~volcap_core.enhance.pyramid.swap_low_frequency`, 5 levels) of
   the RGBA output with the LQ input, on the unpadded frame, in the VAE's image space (RGB
   sRGB-encoded, :func:`~volcap_core.enhance.model.rgb_to_vae` without its affine map; alpha as is):
   the space in which the model and its VAE drift at low frequency, and the one a viewer sees. In
   linear light the swap spreads the correction of the bright face over the dark background beside
   it (a 4x4 lowest level of a 128-px crop reaches ~30 px), and near black the display encoding
   magnifies that (linear 0.007 is display 0.08). Even in the encoded space the lowest level
   carries the face's colour a few pixels past the silhouette, so the RGB change is weighted by the
   swapped alpha: ``rgb + alpha (swapped_rgb - rgb)``, exactly the paper's swap inside the matte
   (alpha 1), none outside it (alpha 0), where the LQ says there is no colour to correct. Decoded
   RGB is clamped to >= 0 before it (the decoder can return negative light, which no display shows)
   and after it, alpha to [0, 1]. What each choice measured is in ``docs/enhancer.md`` ("Temporal
   stability").

8. transparent pixels carry no colour: RGB is set to 0 where the enhanced alpha is below
   :data:`TRANSPARENT` (one 8-bit code). The output is premultiplied, as the render is, and a
   render has RGB <= alpha x colour; RGB and alpha are decoded from separate latents, so without
   this the background the matte calls empty keeps the decoder's faint colour, which a compositor
   would add over the plate as a glow (its cost in SSIM: ``docs/benchmarks.md``).

:func:`enhance_sequence` runs it frame by frame in order, each frame conditioned on the previous
frame's output.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
import torch.nn.functional as F

from volcap_core.enhance.model import (
    DEFAULT_GROUP,
    Enhancer,
    crop_mu,
    decode_rgba,
    encode_conditions,
    flux_sigmas,
    image_ids,
    pack,
    predict_velocity,
    unpack,
)

#: Alpha below which an enhanced pixel is transparent and its RGB is set to 0: one 8-bit code.
TRANSPARENT = 1.0 / 255.0

__all__ = ["TRANSPARENT", "blend_weights", "enhance_frame", "enhance_sequence", "img2img_steps", "premultiplied",
           "swap_low_frequency_encoded", "tile_starts", "tiled_velocity"]


def tile_starts(n: int, tile: int, overlap: int) -> list[int]:
    """Starts of tiles of size ``tile`` covering ``[0, n)`` with at least ``overlap`` overlap: a
    stride of ``tile - overlap``, the last tile flush with the end. One tile when ``tile >= n``."""
    if tile >= n:
        return [0]
    if not 0 <= overlap < tile:
        raise ValueError(f"overlap {overlap} must be in [0, tile {tile})")
    stride = tile - overlap
    starts = list(range(0, n - tile, stride))
    return starts + [n - tile]


def blend_weights(start: int, size: int, n: int, overlap: int) -> torch.Tensor:
    """1-D blending weights ``[size]`` of a tile at ``start`` along an axis of length ``n``: a linear
    ramp ``(i + 1) / (overlap + 1)`` over the first ``overlap`` samples when a tile lies before it,
    the mirror ramp at the end when one lies after, 1 elsewhere (and at the frame's borders, where
    no other tile contributes). Always > 0; the blend divides by the summed weights."""
    w = torch.ones(size, dtype=torch.float64)
    if overlap > 0:
        ramp = torch.arange(1, overlap + 1, dtype=torch.float64) / (overlap + 1)
        k = min(overlap, size)
        if start > 0:
            w[:k] = torch.minimum(w[:k], ramp[:k])
        if start + size < n:
            w[size - k:] = torch.minimum(w[size - k:], ramp[:k].flip(0))
    return w


def tiled_velocity(model: Enhancer, x: torch.Tensor, cond: torch.Tensor, sigma: float,
                   prompt: tuple[torch.Tensor, torch.Tensor], *, tile: int | None = None,
                   overlap: int = 0, tile_batch: int = 4) -> torch.Tensor:
    """The velocity ``[1, 2C, h, w]`` of latents ``x [1, 2C, h, w]`` under ``cond [1, 4C, h, w]`` at
    noise level ``sigma``, predicted on ``tile x tile`` latent tiles (even sizes, latent px) that
    overlap by ``overlap`` and are blended by :func:`blend_weights`; ``tile=None`` or a tile that
    covers the latent: one pass over the whole latent. ``tile_batch`` tiles go through the
    transformer together."""
    _, _, h, w = x.shape
    th, tw = (h, w) if tile is None else (min(tile, h), min(tile, w))
    if th % 2 or tw % 2:
        raise ValueError(f"latent tile {th}x{tw} must be even (2x2 packing)")
    pooled, seq = prompt
    if (th, tw) == (h, w):
        v = predict_velocity(model, pack(x), pack(cond), x.new_full((1,), sigma), image_ids(h, w, x.device),
                             prompt)
        return unpack(v, h, w)
    boxes = [(y, xx) for y in tile_starts(h, th, overlap) for xx in tile_starts(w, tw, overlap)]
    acc = torch.zeros_like(x, dtype=torch.float32)
    wsum = torch.zeros((1, 1, h, w), dtype=torch.float32, device=x.device)
    ids = image_ids(th, tw, x.device)
    for i in range(0, len(boxes), tile_batch):
        chunk = boxes[i:i + tile_batch]
        xs = torch.cat([x[:, :, y:y + th, xx:xx + tw] for y, xx in chunk])
        cs = torch.cat([cond[:, :, y:y + th, xx:xx + tw] for y, xx in chunk])
        v = unpack(predict_velocity(model, pack(xs), pack(cs), x.new_full((len(chunk),), sigma), ids,
                                    prompt), th, tw).float()
        for j, (y, xx) in enumerate(chunk):
            wy = blend_weights(y, th, h, overlap)
            wx = blend_weights(xx, tw, w, overlap)
            wt = (wy[:, None] * wx[None, :]).to(acc)
            acc[:, :, y:y + th, xx:xx + tw] += v[j:j + 1] * wt
            wsum[:, :, y:y + th, xx:xx + tw] += wt
    return (acc / wsum).to(x.dtype)


@contextmanager
def _vae_tiling(vae, on: bool) -> Iterator[None]:
    before = getattr(vae, "use_tiling", False)
    if on:
        vae.enable_tiling()
    try:
        yield
    finally:
        vae.use_tiling = before


def _pad16(x: torch.Tensor) -> torch.Tensor:
    h, w = x.shape[-2:]
    ph, pw = (-h) % 16, (-w) % 16
    if ph == 0 and pw == 0:
        return x
    return F.pad(x[None], (0, pw, 0, ph), mode="replicate")[0]


@torch.no_grad()
def enhance_frame(model: Enhancer, lq: torch.Tensor, prev_output: torch.Tensor | None = None,
                  prev_lq: torch.Tensor | None = None, flow=None, *, steps: int = 28, seed: int = 0,
                  tile: int | None = None, overlap: int | None = None, tile_batch: int = 4,
                  group: str = DEFAULT_GROUP, mu: float | None = None, temporal: bool = True,
                  lowfreq_swap: bool = True, lowfreq_levels: int = 5, vae_tiling: bool = True,
                  strength: float = 1.0) -> torch.Tensor:
    """Enhance one frame (see the module docstring for the steps).

    Args:
        lq: ``[4, H, W]`` LQ RGBA, linear RGB (premultiplied), alpha in [0, 1].
        prev_output: the previous frame's enhanced RGBA ``[4, H, W]``, None for the first frame.
        prev_lq: the previous LQ frame ``[4, H, W]`` (needed with ``prev_output``).
        flow: backward flow ``[2, H, W]`` from this frame to the previous one, a
            :class:`~volcap_core.enhance.temporal.FlowBackend`, or None (zero motion).
        steps: Euler steps. seed: the noise (a CPU ``torch.Generator``).
        tile, overlap: latent tiling in **pixels** (multiples of 16); ``tile=None`` (default): the
            whole frame in one pass; ``overlap`` default ``tile // 4`` rounded to 16.
        tile_batch: tiles per transformer call.
        group: prompt group.
        mu: timestep shift; default the training crop's (``model.config.train_crop``).
        temporal: False ignores ``prev_output`` (the "without flow warping" ablation).
        lowfreq_swap, lowfreq_levels: the low-frequency swap and its pyramid depth.
        vae_tiling: let the VAE tile frames larger than its tile size (its own scheme).
        strength: in (0, 1]: the fraction of the ``steps`` noise levels run, starting from the LQ
            latents noised to the first of them (1: from pure noise, Flux's text-to-image scheme).
    Returns:
        ``[4, H, W]`` float32 RGBA on ``lq``'s device: linear premultiplied RGB >= 0 (0 where
        transparent), alpha in [0, 1].
    """
    from volcap_core.enhance.temporal import temporal_condition

    if lq.ndim != 3 or lq.shape[0] != 4:
        raise ValueError(f"lq must be [4, H, W], got {tuple(lq.shape)}")
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    run = img2img_steps(steps, strength)
    dev = model.transformer.x_embedder.weight.device
    dt = model.transformer.dtype
    h, w = lq.shape[-2:]
    lq32 = lq.float()
    warped = mask = None
    if temporal and prev_output is not None:
        warped, mask = temporal_condition(prev_output.float(), None if prev_lq is None else prev_lq.float(),
                                          lq32, flow)
        warped, mask = _pad16(warped)[None].to(dev, dt), _pad16(mask)[None].to(dev, dt)
    lqp = _pad16(lq32)[None].to(dev, dt)
    hp, wp = lqp.shape[-2:]
    lh, lw = hp // 8, wp // 8
    tile_l = overlap_l = None
    if tile is not None:
        if tile % 16:
            raise ValueError(f"tile {tile} px must be a multiple of 16")
        ov = overlap if overlap is not None else (tile // 4) // 16 * 16
        if ov % 16:
            raise ValueError(f"overlap {ov} px must be a multiple of 16")
        tile_l, overlap_l = tile // 8, ov // 8
    c = model.config.latent_channels
    with _vae_tiling(model.vae, vae_tiling):
        cond = encode_conditions(model, lqp, warped, mask).to(dt)
        gen = torch.Generator().manual_seed(int(seed))
        x = torch.randn((1, 2 * c, lh, lw), generator=gen).to(dev)  # float32 state, whatever the model
        sigmas = flux_sigmas(steps, crop_mu(model.config.train_crop, model.config) if mu is None else mu)
        if run < steps:
            sigmas = sigmas[steps - run:]
            s0 = float(sigmas[0])
            x = (1.0 - s0) * cond[:, :2 * c].float() + s0 * x
        prompt = model.prompt(group)
        for s, s_next in zip(sigmas[:-1].tolist(), sigmas[1:].tolist()):
            v = tiled_velocity(model, x, cond, s, prompt, tile=tile_l, overlap=overlap_l or 0,
                               tile_batch=tile_batch)
            x = x + (s_next - s) * v
        out = decode_rgba(model, x)[0, :, :h, :w].float()
    out = torch.cat([out[:3].clamp(min=0.0), out[3:]])  # no negative light (module docstring, 7.)
    if lowfreq_swap:
        out = swap_low_frequency_encoded(out, lq32.to(out.device), lowfreq_levels)
    return premultiplied(out).to(lq.device)


def premultiplied(rgba: torch.Tensor) -> torch.Tensor:
    """``[..., 4, H, W]`` with RGB set to 0 where alpha < :data:`TRANSPARENT` (module docstring, 8.)."""
    a = rgba[..., 3:, :, :]
    return torch.cat([rgba[..., :3, :, :] * (a >= TRANSPARENT).to(rgba.dtype), a], dim=-3)


def swap_low_frequency_encoded(output: torch.Tensor, lq: torch.Tensor, levels: int = 5) -> torch.Tensor:
    """The low-frequency swap of RGBA ``output`` with ``lq`` (``[..., 4, H, W]``, linear RGB) done
    on sRGB-encoded RGB and linear alpha, the RGB change weighted by the swapped alpha (module
    docstring, 7.); returns linear RGB >= 0 and alpha in [0, 1]. Where the swapped alpha is 1 this
    is exactly the paper's swap."""
    from volcap_core.colour import srgb_decode_unbounded, srgb_encode_unbounded
    from volcap_core.enhance.pyramid import swap_low_frequency

    rgb = srgb_encode_unbounded(output[..., :3, :, :].clamp(min=0.0))
    enc = torch.cat([rgb, output[..., 3:, :, :]], dim=-3)
    enc_lq = torch.cat([srgb_encode_unbounded(lq[..., :3, :, :].clamp(min=0.0)), lq[..., 3:, :, :]], dim=-3)
    y = swap_low_frequency(enc, enc_lq, levels)
    alpha = y[..., 3:, :, :].clamp(0.0, 1.0)
    rgb = rgb + alpha * (y[..., :3, :, :] - rgb)   # the colour change stays inside the matte
    return torch.cat([srgb_decode_unbounded(rgb).clamp(min=0.0), alpha], dim=-3)


def img2img_steps(steps: int, strength: float) -> int:
    """How many of ``steps`` noise levels a sampler of ``strength`` in (0, 1] runs:
    ``round(steps * strength)``, at least 1."""
    if not 0.0 < strength <= 1.0:
        raise ValueError(f"strength must be in (0, 1], got {strength}")
    return max(1, min(steps, round(steps * strength)))


@torch.no_grad()
def enhance_sequence(model: Enhancer, lq_frames: torch.Tensor, flows=None, *, seed: int = 0,
                     same_noise: bool = False,
                     progress: Callable[[int, int], None] | None = None, **frame_kwargs) -> torch.Tensor:
    """Enhance ``lq_frames [T, 4, H, W]`` in order: frame ``t > 0`` is conditioned on the output
    of frame ``t - 1`` warped by the flow between the LQ frames; frame 0 gets zeros.

    Args:
        flows: ``[T-1, 2, H, W]`` exact backward flows (``flows[t-1]`` takes frame ``t`` to
            ``t-1``; :class:`~volcap_core.enhance.pairs.PairSet`'s convention), a
            :class:`~volcap_core.enhance.temporal.FlowBackend` called on consecutive LQ RGB
            frames, or None: OpenCV DIS (:class:`~volcap_core.enhance.temporal.DisFlow`).
        seed, same_noise: frame ``t`` is sampled from noise seeded ``seed + t`` (independent per
            frame), or ``seed`` for every frame when ``same_noise``.
        progress: ``progress(t, T)`` after each frame.
        frame_kwargs: passed to :func:`enhance_frame` (steps, tile, overlap, group, temporal, ...).
    Returns:
        ``[T, 4, H, W]`` float32 RGBA.
    """
    if lq_frames.ndim != 4 or lq_frames.shape[1] != 4:
        raise ValueError(f"lq_frames must be [T, 4, H, W], got {tuple(lq_frames.shape)}")
    n = lq_frames.shape[0]
    if flows is None and n > 1 and frame_kwargs.get("temporal", True):
        from volcap_core.enhance.temporal import DisFlow

        flows = DisFlow()
    if isinstance(flows, torch.Tensor) and tuple(flows.shape[:2]) != (n - 1, 2):
        raise ValueError(f"flows must be [{n - 1}, 2, H, W], got {tuple(flows.shape)}")
    outs: list[torch.Tensor] = []
    for t in range(n):
        if t == 0:
            prev = prev_lq = flow = None
        else:
            prev, prev_lq = outs[-1], lq_frames[t - 1]
            flow = flows[t - 1] if isinstance(flows, torch.Tensor) else flows
        outs.append(enhance_frame(model, lq_frames[t], prev, prev_lq, flow,
                                  seed=seed if same_noise else seed + t, **frame_kwargs))
        if progress is not None:
            progress(t + 1, n)
    return torch.stack(outs)
