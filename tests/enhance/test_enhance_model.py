"""The enhancer's network: widening, latents, packing, schedule, persistence (tiny model, CPU)."""

from __future__ import annotations

import copy
import socket

import numpy as np
import pytest
import torch

from volcap_core.enhance.model import (
    FLUX_SCALING_FACTOR,
    FLUX_SHIFT_FACTOR,
    Enhancer,
    EnhancerConfig,
    PromptEmbedding,
    _base_transformer,
    _vae,
    build_enhancer,
    crop_mu,
    decode,
    encode,
    encode_conditions,
    enhancer_from_bytes,
    enhancer_to_bytes,
    flux_mu,
    flux_sigmas,
    gray_to_vae,
    image_ids,
    pack,
    predict_velocity,
    rgb_to_vae,
    unpack,
    vae_to_gray,
    vae_to_rgb,
    widen_transformer,
)


def _base_forward(transformer, tokens, sigma, ids, prompt):
    pooled, seq = prompt
    return transformer(hidden_states=tokens, encoder_hidden_states=seq[None], pooled_projections=pooled[None],
                       timestep=sigma, img_ids=ids, txt_ids=torch.zeros(seq.shape[0], 3), return_dict=False)[0]


def _inputs(cfg: EnhancerConfig, seed: int = 0, h: int = 8, w: int = 8):
    g = torch.Generator().manual_seed(seed)
    n, L = (h // 2) * (w // 2), cfg.packed_channels
    noisy = torch.randn(1, n, 2 * L, generator=g)
    cond = torch.randn(1, n, 4 * L, generator=g)
    prompt = (torch.randn(int(cfg.transformer["pooled_projection_dim"]), generator=g),
              torch.randn(cfg.prompt_tokens, int(cfg.transformer["joint_attention_dim"]), generator=g))
    return noisy, cond, prompt, image_ids(h, w)


# ----------------------------------------------------------------------------------- widening

def test_widened_model_keeps_pretrained_outputs():
    """New x_embedder columns are zero and the alpha head copies the RGB head: whatever the new
    inputs hold, both heads reproduce the un-widened model's prediction from the noise RGB slot."""
    cfg = EnhancerConfig.tiny()
    torch.manual_seed(3)
    base = _base_transformer(cfg)
    wide = copy.deepcopy(base)
    widen_transformer(wide, cfg.packed_channels)
    assert wide.config.in_channels == 6 * 64 and wide.config.out_channels == 2 * 64
    assert wide.x_embedder.weight.shape == (32, 384) and wide.proj_out.weight.shape == (128, 32)
    L = cfg.packed_channels
    noisy, cond, prompt, ids = _inputs(cfg)
    sigma = torch.tensor([0.7])
    with torch.no_grad():
        ref = _base_forward(base, noisy[..., :L], sigma, ids, prompt)
        for new_inputs in (torch.zeros(1, noisy.shape[1], 5 * L), torch.cat([noisy[..., L:], cond], -1)):
            out = _base_forward(wide, torch.cat([noisy[..., :L], new_inputs], -1), sigma, ids, prompt)
            torch.testing.assert_close(out[..., :L], ref, atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(out[..., L:], ref, atol=1e-5, rtol=1e-5)
        # the check is real: one non-zero new column moves the output when the new inputs are non-zero
        # (random, not constant: LayerNorm removes a vector added equally to every feature)
        wide.x_embedder.weight[:, 3 * L] = torch.randn(32, generator=torch.Generator().manual_seed(1))
        moved = _base_forward(wide, torch.cat([noisy[..., :L], noisy[..., L:], cond], -1), sigma, ids, prompt)
    assert (moved[..., :L] - ref).abs().max() > 1e-3


def test_widening_refuses_a_widened_model():
    m = build_enhancer(EnhancerConfig.tiny())
    with pytest.raises(ValueError, match="not a base Flux model"):
        widen_transformer(m.transformer, 64)


def test_from_pretrained_widens_a_base_flux_directory_offline(tmp_path, monkeypatch):
    """A FLUX.1-layout directory (transformer/ with 64 inputs, vae/) loads with local files only and
    is widened on load; the network is cut off (any connection attempt fails the test)."""
    cfg = EnhancerConfig.tiny()
    torch.manual_seed(5)
    base, vae = _base_transformer(cfg), _vae(cfg)
    base.save_pretrained(tmp_path / "transformer")
    vae.save_pretrained(tmp_path / "vae")

    def no_network(*a, **k):
        raise AssertionError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(socket, "create_connection", no_network)
    model = Enhancer.from_pretrained(tmp_path)
    assert model.transformer.config.in_channels == 384 and model.transformer.config.out_channels == 128
    assert model.config.transformer == cfg.transformer
    L = cfg.packed_channels
    noisy, cond, prompt, ids = _inputs(cfg, seed=1)
    with torch.no_grad():
        ref = _base_forward(base, noisy[..., :L], torch.tensor([0.3]), ids, prompt)
        out = predict_velocity(model, noisy, cond, torch.tensor([0.3]), ids, prompt)
    torch.testing.assert_close(out[..., :L], ref, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out[..., L:], ref, atol=1e-5, rtol=1e-5)


# -------------------------------------------------------------------------------- persistence

def _trained_like(seed: int = 0) -> Enhancer:
    """A tiny enhancer whose new columns are non-zero (as after training) and that holds a prompt."""
    m = build_enhancer(EnhancerConfig.tiny(), seed=seed)
    g = torch.Generator().manual_seed(seed + 100)
    with torch.no_grad():
        m.transformer.x_embedder.weight[:, 64:] = torch.randn(32, 320, generator=g) * 0.05
    m.set_prompt("actors-a", PromptEmbedding(torch.randn(32, generator=g), torch.randn(8, 32, generator=g)))
    return m


def test_save_pretrained_from_pretrained_round_trip_offline(tmp_path, monkeypatch):
    m = _trained_like()
    m.save_pretrained(tmp_path / "enh")
    monkeypatch.setattr(socket.socket, "connect", lambda *a, **k: (_ for _ in ()).throw(AssertionError("net")))
    m2 = Enhancer.from_pretrained(tmp_path / "enh")
    assert m2.config == m.config
    assert m2.groups == ["actors-a"]
    sd, sd2 = m.state_dict(), m2.state_dict()
    assert sd.keys() == sd2.keys()
    for k in sd:
        assert torch.equal(sd[k], sd2[k]), k
    noisy, cond, _, ids = _inputs(m.config, seed=2)
    with torch.no_grad():
        a = predict_velocity(m, noisy, cond, torch.tensor([0.4]), ids, m.prompt("actors-a"))
        b = predict_velocity(m2, noisy, cond, torch.tensor([0.4]), ids, m2.prompt("actors-a"))
    assert torch.equal(a, b)


def test_bytes_round_trip_is_exact_and_stable():
    m = _trained_like(seed=1)
    data = enhancer_to_bytes(m)
    m2 = enhancer_from_bytes(data)
    assert m2.config == m.config and m2.groups == m.groups
    for k, v in m.state_dict().items():
        assert torch.equal(v, m2.state_dict()[k]), k
    assert enhancer_to_bytes(m2) == data
    assert enhancer_to_bytes(m) == data


def test_prompt_embeddings():
    cfg = EnhancerConfig.tiny()
    z = PromptEmbedding.zeros(cfg)
    assert z.pooled.shape == (32,) and z.sequence.shape == (8, 32) and not z.pooled.any()
    full = PromptEmbedding.zeros(EnhancerConfig.flux_dev())
    assert full.pooled.shape == (768,) and full.sequence.shape == (512, 4096)
    p = PromptEmbedding(torch.arange(32.0), torch.ones(8, 32))
    q = PromptEmbedding.from_bytes(p.to_bytes())
    assert torch.equal(q.pooled, p.pooled) and torch.equal(q.sequence, p.sequence)
    m = build_enhancer(cfg)
    pooled, seq = m.prompt("nobody")  # a group never given one reads zeros
    assert not pooled.any() and seq.shape == (8, 32)
    m.ensure_prompt("g.with.dots")
    assert m.groups == ["g.with.dots"]
    with pytest.raises(ValueError, match="do not fit"):
        m.set_prompt("bad", PromptEmbedding(torch.zeros(7), torch.zeros(8, 32)))


# ------------------------------------------------------------------------------ VAE, latents

def test_vae_encode_decode_shapes_and_flux_scaling():
    cfg = EnhancerConfig.tiny()
    assert cfg.vae["scaling_factor"] == FLUX_SCALING_FACTOR == 0.3611
    assert cfg.vae["shift_factor"] == FLUX_SHIFT_FACTOR == 0.1159
    assert EnhancerConfig.flux_dev().vae["latent_channels"] == 16
    m = build_enhancer(cfg)
    x = torch.rand(2, 3, 48, 64, generator=torch.Generator().manual_seed(0)) * 2 - 1
    with torch.no_grad():
        z = encode(m.vae, x)
        raw = m.vae.encode(x).latent_dist.mode()
        assert z.shape == (2, 16, 6, 8)
        torch.testing.assert_close(z, (raw - 0.1159) * 0.3611)
        y = decode(m.vae, z)
        assert y.shape == (2, 3, 48, 64)
        torch.testing.assert_close(y, m.vae.decode(raw).sample, atol=1e-5, rtol=1e-5)


def test_image_maps_to_vae_range_and_back():
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(3, 8, 8, generator=g) * 3.0  # HDR: no clamp either way
    torch.testing.assert_close(vae_to_rgb(rgb_to_vae(rgb)), rgb, atol=1e-5, rtol=1e-5)
    assert float(rgb_to_vae(torch.zeros(3, 1, 1)).max()) == -1.0
    assert abs(float(rgb_to_vae(torch.ones(3, 1, 1)).min()) - 1.0) < 1e-6
    a = torch.rand(1, 8, 8, generator=g)
    v = gray_to_vae(a)
    assert v.shape == (3, 8, 8) and torch.equal(v[0], v[2])
    torch.testing.assert_close(vae_to_gray(v), a)


def test_first_frame_conditions_are_zero_latents():
    m = build_enhancer(EnhancerConfig.tiny())
    lq = torch.rand(2, 4, 32, 32, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        c = encode_conditions(m, lq, None, None)
        assert c.shape == (2, 64, 4, 4)
        assert not c[:, 32:].any() and c[:, :32].abs().sum() > 0
        d = encode_conditions(m, lq, lq, lq[:, 3:], keep=torch.tensor([True, False]))
        assert d[0, 32:].abs().sum() > 0 and not d[1, 32:].any()
        torch.testing.assert_close(d[:, :32], c[:, :32])


def _flux_pipeline_functions() -> dict:
    """``calculate_shift`` and ``FluxPipeline``'s packing helpers, taken from diffusers' source:
    the module cannot be imported without ``transformers`` (its text encoders), so its functions
    are compiled alone (they need only torch)."""
    import ast
    import importlib.util
    from pathlib import Path

    spec = importlib.util.find_spec("diffusers")
    src = (Path(spec.origin).parent / "pipelines" / "flux" / "pipeline_flux.py").read_text()
    wanted = {"calculate_shift", "_pack_latents", "_unpack_latents", "_prepare_latent_image_ids"}
    nodes = [n for n in ast.walk(ast.parse(src)) if isinstance(n, ast.FunctionDef) and n.name in wanted]
    for n in nodes:
        n.decorator_list = []
    ns: dict = {"torch": torch}
    exec(compile(ast.Module(body=nodes, type_ignores=[]), "pipeline_flux.py", "exec"), ns)
    assert wanted <= ns.keys()
    return ns


def test_packing_matches_diffusers_flux_pipeline():
    ref = _flux_pipeline_functions()
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(2, 16, 6, 8, generator=g), torch.randn(2, 16, 6, 8, generator=g)
    pa = pack(a)
    assert torch.equal(pa, ref['_pack_latents'](a, 2, 16, 6, 8))
    assert torch.equal(unpack(pa, 6, 8), a)
    assert torch.equal(unpack(pa, 6, 8), ref['_unpack_latents'](pa, 48, 64, 8))
    # concatenating packed tensors on the last axis == concatenating latents on channels
    assert torch.equal(pack(torch.cat([a, b], 1)), torch.cat([pack(a), pack(b)], -1))
    assert torch.equal(image_ids(6, 8), ref['_prepare_latent_image_ids'](1, 3, 4, "cpu", torch.float32))


def test_sigma_schedule_matches_diffusers_flow_match_scheduler():
    from diffusers import FlowMatchEulerDiscreteScheduler

    calculate_shift = _flux_pipeline_functions()["calculate_shift"]
    cfg = EnhancerConfig.flux_dev()
    for seq_len in (256, 1024, 4096):
        assert abs(flux_mu(seq_len, cfg) - calculate_shift(seq_len)) < 1e-12
    assert abs(crop_mu(1024, cfg) - 1.15) < 1e-12 and abs(crop_mu(256, cfg) - 0.5) < 1e-12
    sched = FlowMatchEulerDiscreteScheduler(use_dynamic_shifting=True, base_shift=0.5, max_shift=1.15,
                                            base_image_seq_len=256, max_image_seq_len=4096)
    for steps, mu in ((28, 1.15), (4, 0.5), (10, 0.8)):
        sched.set_timesteps(sigmas=np.linspace(1.0, 1.0 / steps, steps), mu=mu)
        ours = flux_sigmas(steps, mu)
        assert ours.shape == (steps + 1,) and ours[0] == 1.0 and ours[-1] == 0.0
        np.testing.assert_allclose(ours.numpy(), sched.sigmas.numpy(), atol=1e-6)
