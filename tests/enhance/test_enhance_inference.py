"""Enhancer inference: Euler sampling, tiled latents, temporal chaining, low-frequency swap."""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F

from volcap_core.enhance.inference import (
    blend_weights,
    enhance_frame,
    enhance_sequence,
    tile_starts,
    tiled_velocity,
)
from volcap_core.enhance.model import Enhancer, EnhancerConfig, build_enhancer


@pytest.fixture(scope="module")
def model() -> Enhancer:
    """A tiny enhancer whose condition columns are non-zero, as training makes them (at
    initialisation they are zero and the conditions would have no effect at all)."""
    m = build_enhancer(EnhancerConfig.tiny(), seed=0)
    g = torch.Generator().manual_seed(123)
    with torch.no_grad():
        m.transformer.x_embedder.weight[:, 64:] = torch.randn(32, 320, generator=g) * 0.3
    return m


def _frames(t: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = F.avg_pool2d(torch.rand(t, 4, h, w, generator=g), 9, 1, 4, count_include_pad=False)
    return torch.cat([x[:, :3] * 1.5, x[:, 3:]], dim=1)


def test_enhanced_frame_is_rgba_of_the_input_size(model):
    lq = _frames(1, 40, 56)[0]  # not multiples of 16: padded, then cropped back
    out = enhance_frame(model, lq, steps=2, seed=0)
    assert out.shape == (4, 40, 56) and out.dtype == torch.float32
    assert torch.isfinite(out).all()
    assert float(out[3].min()) >= 0.0 and float(out[3].max()) <= 1.0
    assert float(out[:3].min()) >= 0.0
    assert torch.equal(out, enhance_frame(model, lq, steps=2, seed=0))  # deterministic
    assert not torch.equal(out, enhance_frame(model, lq, steps=2, seed=1))


def test_tile_covering_the_frame_equals_untiled(model):
    lq = _frames(1, 96, 128)[0]
    a = enhance_frame(model, lq, steps=3, seed=1)
    assert torch.equal(a, enhance_frame(model, lq, steps=3, seed=1, tile=128))
    assert torch.equal(a, enhance_frame(model, lq, steps=3, seed=1, tile=256, overlap=64))


def test_tiled_inference_is_close_to_untiled_and_seam_free(model):
    lq = _frames(1, 96, 128, seed=2)[0]
    kw = {"steps": 3, "seed": 1, "lowfreq_swap": False}
    a = enhance_frame(model, lq, **kw)
    b = enhance_frame(model, lq, tile=64, overlap=32, **kw)  # 2 x 3 latent tiles of 8, overlap 4
    d = (b - a).abs()
    assert float(d.mean()) < 0.01 * float(a.abs().mean()) + 1e-3 and float(d.max()) < 0.25
    # no seam: the horizontal jumps of the tiled image at tile edges are those of the untiled image
    edges = [32, 64, 96]
    jump = lambda img: torch.stack([(img[..., c] - img[..., c - 1]).abs().mean() for c in edges])  # noqa: E731
    assert torch.allclose(jump(b), jump(a), rtol=0.1, atol=2e-3)


@pytest.mark.parametrize(("n", "tile", "overlap"), [(16, 8, 4), (16, 8, 2), (12, 8, 4), (30, 8, 2), (8, 8, 4)])
def test_blend_weights_fade_tiles_in_and_out(n, tile, overlap):
    """Normalised weights of the tiles along an axis sum to 1 everywhere and each tile's share
    changes by at most 1 / (overlap + 1) between neighbouring samples: no tile cuts in (a hard seam
    would be a jump of 1)."""
    starts = tile_starts(n, tile, overlap)
    assert starts[0] == 0 and starts[-1] + min(tile, n) == n
    total = torch.zeros(n, dtype=torch.float64)
    maps = []
    for s in starts:
        m = torch.zeros(n, dtype=torch.float64)
        m[s:s + min(tile, n)] = blend_weights(s, min(tile, n), n, overlap)
        maps.append(m)
        total += m
    assert float(total.min()) > 0
    for m in maps:
        share = m / total
        assert float((share[1:] - share[:-1]).abs().max()) <= 1.0 / (overlap + 1) + 1e-12 or len(starts) == 1
    torch.testing.assert_close(sum(m / total for m in maps), torch.ones(n, dtype=torch.float64))


def test_tiled_velocity_blends_overlapping_tiles(model):
    g = torch.Generator().manual_seed(0)
    x, cond = torch.randn(1, 32, 12, 16, generator=g), torch.randn(1, 64, 12, 16, generator=g)
    with torch.no_grad():
        full = tiled_velocity(model, x, cond, 0.5, model.prompt())
        tiled = tiled_velocity(model, x, cond, 0.5, model.prompt(), tile=8, overlap=4, tile_batch=2)
        one_by_one = tiled_velocity(model, x, cond, 0.5, model.prompt(), tile=8, overlap=4, tile_batch=1)
    assert tiled.shape == full.shape
    torch.testing.assert_close(tiled, one_by_one, atol=1e-5, rtol=1e-5)
    # the top-left corner is covered by one tile only: exactly that tile's own prediction
    with torch.no_grad():
        corner = tiled_velocity(model, x[..., :8, :8], cond[..., :8, :8], 0.5, model.prompt())
    torch.testing.assert_close(tiled[..., :4, :4], corner[..., :4, :4], atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="even"):
        tiled_velocity(model, x, cond, 0.5, model.prompt(), tile=7, overlap=2)


def test_sequence_conditions_each_frame_on_the_previous_output(model):
    lq = _frames(3, 48, 48, seed=3)
    flows = torch.zeros(2, 2, 48, 48)
    kw = {"steps": 2}
    seq = enhance_sequence(model, lq, flows, seed=5, **kw)
    assert seq.shape == (3, 4, 48, 48)
    # first frame: zero conditions, the same as a lone frame (and as ignoring any previous output)
    first = enhance_frame(model, lq[0], seed=5, **kw)
    assert torch.equal(seq[0], first)
    assert torch.equal(first, enhance_frame(model, lq[0], lq[1], lq[1], flows[0], seed=5, temporal=False, **kw))
    # frame 1 is frame 1 enhanced with frame 0's output warped in (noise seeded seed + t)
    assert torch.equal(seq[1], enhance_frame(model, lq[1], seq[0], lq[0], flows[0], seed=6, **kw))
    alone = enhance_frame(model, lq[1], seed=6, **kw)
    assert (seq[1] - alone).abs().max() > 1e-3
    # changing frame 0 changes frame 1's output; without temporal conditioning it does not
    lq2 = lq.clone()
    lq2[0, :3] *= 0.5
    seq2 = enhance_sequence(model, lq2, flows, seed=5, **kw)
    assert (seq2[1] - seq[1]).abs().max() > 1e-3
    flat = enhance_sequence(model, lq, flows, seed=5, temporal=False, **kw)
    flat2 = enhance_sequence(model, lq2, flows, seed=5, temporal=False, **kw)
    assert torch.equal(flat[1:], flat2[1:]) and torch.equal(flat[1], alone)
    same = enhance_sequence(model, lq[:2], flows[:1], seed=5, same_noise=True, **kw)
    assert torch.equal(same[1], enhance_frame(model, lq[1], seq[0], lq[0], flows[0], seed=5, **kw))


def test_sequence_uses_dis_flow_by_default(model):
    from volcap_core.enhance.temporal import DisFlow

    lq = _frames(2, 32, 32, seed=4)
    seq = enhance_sequence(model, lq, steps=1, seed=0)
    flow = DisFlow()(lq[0, :3], lq[1, :3])
    assert torch.equal(seq[1], enhance_frame(model, lq[1], seq[0], lq[0], flow, steps=1, seed=1))


def test_low_frequency_swap_takes_the_lowest_level_from_the_input(model):
    from volcap_core.colour import srgb_encode_unbounded
    from volcap_core.enhance.pyramid import lowpass

    lq = _frames(1, 64, 64, seed=6)[0]
    lq[3] = 1.0   # an opaque frame: the swap's RGB change is weighted by the swapped alpha
    swapped = enhance_frame(model, lq, steps=2, seed=0)
    raw = enhance_frame(model, lq, steps=2, seed=0, lowfreq_swap=False)
    # the lowest level (5 levels: 2x2 here) of the display-encoded RGB, where the swap is done
    low = lambda img: lowpass(srgb_encode_unbounded(img[:3]), 5)  # noqa: E731
    err = lambda out: float((low(out) - low(lq)).abs().mean())  # noqa: E731
    assert err(swapped) < 0.1 * err(raw)  # not exact: negative light is clamped before and after
    alpha_err = lambda out: float((lowpass(out[3:], 5) - lowpass(lq[3:], 5)).abs().mean())  # noqa: E731
    assert alpha_err(swapped) < 0.2 * alpha_err(raw)  # alpha: linear, clamped to [0, 1] after
    # the high frequencies stay the model's
    def hp(img):  # high-pass of the encoded RGB
        e = srgb_encode_unbounded(img[:3].clamp(min=0.0))
        return e - F.avg_pool2d(e[None], 5, 1, 2, count_include_pad=False)[0]

    assert float((hp(swapped) - hp(raw)).abs().mean()) < 0.5 * float(hp(raw).abs().mean())


def test_low_frequency_swap_leaves_a_black_background_black():
    """The swap runs on display-encoded RGB: a model output whose face is 30 % too dark gets the
    LQ's brightness back without the correction spreading as a haze over the black background
    beside it (in linear light it does, and the display encoding magnifies it near black)."""
    from volcap_core.colour import srgb_encode
    from volcap_core.enhance.inference import swap_low_frequency_encoded
    from volcap_core.enhance.pyramid import swap_low_frequency

    h = w = 256  # 5 levels: an 8x8 lowest level, a 160-px face on black
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    r2 = (yy - 128) ** 2 + (xx - 128) ** 2
    face = (r2 < 80 ** 2).float()
    lq = torch.cat([0.3 * face.expand(3, h, w), face[None]])
    out = torch.cat([0.3 * face.expand(3, h, w) * (0.7 + 0.1 * torch.sin(xx / 2.0)), face[None]])
    swapped = swap_low_frequency_encoded(out, lq)
    black = r2 > 100 ** 2  # background from 20 px beside the face
    haze = lambda img: float(srgb_encode(img[:3]).amax(0)[black].max())  # noqa: E731
    assert haze(swapped) < 0.03  # measured 0.019: 5 codes of 255
    assert haze(swap_low_frequency(out, lq)) > 4 * haze(swapped)  # linear light: 0.148, 38 codes
    # the face's brightness is the LQ's again (display-encoded), its detail the output's
    inside = r2 < 60 ** 2
    mean_face = lambda img: float(srgb_encode(img[:3]).mean(0)[inside].mean())  # noqa: E731
    assert abs(mean_face(swapped) - mean_face(lq)) < 0.2 * abs(mean_face(out) - mean_face(lq))
    row = lambda img: srgb_encode(img[:3])[0, 128, 100:156]  # noqa: E731
    ripple = lambda img: row(img) - row(img).mean()  # noqa: E731
    assert float((ripple(swapped) - ripple(out)).abs().max()) < 0.3 * float(ripple(out).abs().max())
    assert float(swapped[:3].min()) >= 0.0 and float(swapped[3].min()) >= 0.0 and float(swapped[3].max()) <= 1.0


def test_low_frequency_swap_is_the_papers_inside_the_matte_and_adds_no_colour_outside():
    """The RGB change of the swap is weighted by the swapped alpha: where the matte is full it is
    the paper's swap (on encoded RGB) exactly, where it is empty the output's RGB is unchanged, in
    between it is the alpha's share of the change."""
    from volcap_core.colour import srgb_decode_unbounded, srgb_encode_unbounded
    from volcap_core.enhance.inference import swap_low_frequency_encoded
    from volcap_core.enhance.pyramid import swap_low_frequency

    g = torch.Generator().manual_seed(3)
    h = w = 128
    xx = torch.arange(w).float().expand(h, w)
    alpha = ((xx - 40) / 48).clamp(0, 1)            # empty | ramp | full, left to right
    lq = torch.cat([0.4 * alpha.expand(3, h, w), alpha[None]])
    out = torch.cat([(0.25 * alpha + 0.05 * torch.rand(h, w, generator=g)).expand(3, h, w), alpha[None]])
    swapped = swap_low_frequency_encoded(out, lq)

    enc = lambda x: torch.cat([srgb_encode_unbounded(x[:3].clamp(min=0)), x[3:]])  # noqa: E731
    paper = swap_low_frequency(enc(out), enc(lq))
    paper_alpha = paper[3].clamp(0, 1)
    full, empty = paper_alpha >= 1.0, paper_alpha <= 0.0
    assert full.any() and empty.any()
    torch.testing.assert_close(swapped[3], paper_alpha)
    assert torch.allclose(srgb_encode_unbounded(swapped[:3])[:, full], paper[:3, full].clamp(min=0), atol=1e-5)
    torch.testing.assert_close(swapped[:3][:, empty], out[:3][:, empty], atol=1e-6, rtol=1e-5)
    mid = (paper_alpha > 0.2) & (paper_alpha < 0.8)
    want = srgb_decode_unbounded(enc(out)[:3] + paper_alpha * (paper[:3] - enc(out)[:3])).clamp(min=0)
    torch.testing.assert_close(swapped[:3][:, mid], want[:, mid], atol=1e-5, rtol=1e-4)


def test_strength_starts_the_sampler_from_the_noised_lq(model):
    from volcap_core.enhance.inference import img2img_steps
    from volcap_core.enhance.model import decode_rgba, encode_conditions

    assert [img2img_steps(8, s) for s in (1.0, 0.5, 0.3, 0.01)] == [8, 4, 2, 1]
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(ValueError, match="strength"):
            img2img_steps(8, bad)
    lq = _frames(1, 48, 48, seed=7)[0]
    with pytest.raises(ValueError, match="strength"):
        enhance_frame(model, lq, steps=4, strength=0.0)
    calls = []
    hook = model.transformer.register_forward_hook(lambda *a: calls.append(1))
    try:
        enhance_frame(model, lq, steps=8, strength=0.5, seed=0)
    finally:
        hook.remove()
    assert len(calls) == 4  # only the last half of the noise levels are run
    # the start: with a velocity of zero the sampler returns its start, the LQ latents noised to
    # the first noise level run (nearly the LQ through the VAE at a weak strength), or pure noise
    still = copy.deepcopy(model)
    with torch.no_grad():
        still.transformer.proj_out.weight.zero_()
        still.transformer.proj_out.bias.zero_()
        vae_lq = decode_rgba(still, encode_conditions(still, lq[None], None, None)[:, :32])[0].clamp(min=0)
    kw = {"steps": 50, "seed": 0, "lowfreq_swap": False, "mu": 0.0}  # no shift: the last level is 0.02
    err = lambda out: float((out - vae_lq).abs().mean())  # noqa: E731
    # (the random VAE decoder magnifies even 2 % of noise: measured 0.046 against 0.178)
    assert err(enhance_frame(still, lq, strength=0.02, **kw)) < 0.4 * err(enhance_frame(still, lq, **kw))


def test_transparent_pixels_carry_no_colour():
    from volcap_core.enhance.inference import TRANSPARENT, premultiplied

    rgba = torch.rand(2, 4, 8, 8, generator=torch.Generator().manual_seed(0))
    rgba[:, 3] = TRANSPARENT + (1 - TRANSPARENT) * rgba[:, 3]  # visible: alpha >= one 8-bit code
    rgba[:, 3, :4] = 0.5 * TRANSPARENT  # transparent: top half
    out = premultiplied(rgba)
    assert torch.equal(out[:, :3, :4], torch.zeros(2, 3, 4, 8))
    assert torch.equal(out[:, :, 4:], rgba[:, :, 4:]) and torch.equal(out[:, 3], rgba[:, 3])
