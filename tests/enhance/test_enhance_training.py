"""Enhancer training: the flow-matching objective, LoRA, temporal-condition sampling, resumption."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from volcap_core.checkpoint import AdamState, adam_step
from volcap_core.enhance.lora import LoRALinear, add_lora, merge_lora
from volcap_core.enhance.model import (
    EnhancerConfig,
    build_enhancer,
    crop_mu,
    encode_conditions,
    encode_target,
    image_ids,
    pack,
    predict_velocity,
    shift_sigma,
)
from volcap_core.enhance.pairs import PairSet, make_degraded_pairs
from volcap_core.enhance.training import (
    EnhancerTrainConfig,
    _sample,
    flow_matching_loss,
    sample_sigmas,
    train_enhancer,
    trainable_parameters,
)


def _face_like(t: int = 3, h: int = 64, w: int = 64, seed: int = 0) -> torch.Tensor:
    """Smooth RGBA frames ``[t, 4, h, w]`` drifting right by one pixel per frame (a disc of
    coverage, premultiplied colour)."""
    g = torch.Generator().manual_seed(seed)
    tex = F.avg_pool2d(torch.rand(1, 3, h, w + t, generator=g), 7, 1, 3)
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                            indexing="ij")
    frames = []
    for i in range(t):
        rgb = tex[0, :, :, t - i:t - i + w]
        alpha = ((xx - w / 2 - i) ** 2 + (yy - h / 2) ** 2 < (0.4 * h) ** 2).float()[None]
        frames.append(torch.cat([rgb * alpha, alpha]))
    return torch.stack(frames)


def _pairs(t: int = 3, seed: int = 0) -> PairSet:
    return make_degraded_pairs(_face_like(t, seed=seed), scale=4, seed=seed)


def test_one_pair_overfits_on_a_fixed_batch():
    """30 Adam steps on one fixed (crop, sigma, noise) batch drive the flow-matching loss down."""
    model = build_enhancer(EnhancerConfig.tiny(), seed=0)
    cfg = EnhancerTrainConfig(finetune="full", lr=2e-3)
    params = trainable_parameters(model, cfg)
    pairs = _pairs()
    g = torch.Generator().manual_seed(0)
    lq, hq = pairs.lq[1:2], pairs.hq[1:2]
    with torch.no_grad():
        x0 = encode_target(model, hq)
        cond = encode_conditions(model, lq, None, None)
    noise = torch.randn(x0.shape, generator=g)
    sigma = torch.tensor([0.6])
    prompt = tuple(p[None] for p in model.prompt())
    adam = AdamState.zeros_like({k: p.detach() for k, p in params.items()})
    losses = []
    for _ in range(30):
        for p in params.values():
            p.grad = None
        loss = flow_matching_loss(model, x0, cond, sigma, noise, prompt)
        loss.backward()
        adam_step(params, {k: 2e-3 for k in params}, adam, eps=1e-8)
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0], losses


def test_flow_matching_target_is_noise_minus_clean():
    """At sigma = 1 the input is pure noise; a model predicting ``noise - x0`` has zero loss."""
    model = build_enhancer(EnhancerConfig.tiny(), seed=0)
    g = torch.Generator().manual_seed(1)
    x0, noise = torch.randn(1, 32, 4, 4, generator=g), torch.randn(1, 32, 4, 4, generator=g)
    cond = torch.zeros(1, 64, 4, 4)
    prompt = tuple(p[None] for p in model.prompt())
    with torch.no_grad():
        pred = predict_velocity(model, pack(noise), pack(cond), torch.tensor([1.0]), image_ids(4, 4), prompt)
        loss = flow_matching_loss(model, x0, cond, torch.tensor([1.0]), noise, prompt)
    torch.testing.assert_close(loss, F.mse_loss(pred, pack(noise - x0)))


def test_sigma_sampling_is_shifted_logit_normal():
    cfg = EnhancerTrainConfig()
    mu = crop_mu(1024, EnhancerConfig.flux_dev())
    s = sample_sigmas(20000, cfg, mu, torch.Generator().manual_seed(0))
    assert float(s.min()) > 0 and float(s.max()) < 1
    # the median of sigmoid(N(0, 1)) is 0.5, shifted by Flux's shift at 1024 px (mu = 1.15)
    assert abs(float(s.median()) - float(shift_sigma(torch.tensor(0.5), mu))) < 0.01
    flat = sample_sigmas(20000, cfg.model_copy(update={"resolution_shift": False}), mu,
                         torch.Generator().manual_seed(0))
    assert abs(float(flat.median()) - 0.5) < 0.01


def test_lora_starts_at_the_base_model_and_merges():
    model = build_enhancer(EnhancerConfig.tiny(), seed=0)
    g = torch.Generator().manual_seed(2)
    noisy, cond = torch.randn(1, 16, 128, generator=g), torch.randn(1, 16, 256, generator=g)
    args = (torch.tensor([0.5]), image_ids(8, 8), model.prompt())
    with torch.no_grad():
        ref = predict_velocity(model, noisy, cond, *args)
    n = add_lora(model, rank=4, generator=torch.Generator().manual_seed(0))
    # double block: q k v out + added q k v out + 2 ff + 2 ff_context; single: q k v, proj_mlp, proj_out
    assert n == 12 + 5
    assert add_lora(model, rank=4) == 0  # already wrapped
    params = trainable_parameters(model, EnhancerTrainConfig(finetune="lora"))
    assert sum(".lora_" in k for k in params) == 2 * n
    assert {k for k in params if ".lora_" not in k} == {
        "transformer.x_embedder.weight", "transformer.x_embedder.bias",
        "transformer.proj_out.weight", "transformer.proj_out.bias"}
    assert not any(p.requires_grad for k, p in model.named_parameters() if k not in params)
    with torch.no_grad():
        torch.testing.assert_close(predict_velocity(model, noisy, cond, *args), ref, atol=0, rtol=0)
        for m in model.modules():
            if isinstance(m, LoRALinear):
                m.lora_B.normal_(0, 0.1, generator=g)
        adapted = predict_velocity(model, noisy, cond, *args)
        assert (adapted - ref).abs().max() > 1e-3
        assert merge_lora(model) == n
        assert not any(isinstance(m, LoRALinear) for m in model.modules())
        torch.testing.assert_close(predict_velocity(model, noisy, cond, *args), adapted, atol=1e-5, rtol=1e-5)


def test_previous_output_during_training_is_the_warped_previous_hq():
    """With the temporal conditions kept, a sample's previous output is frame t-1 of the HQ warped by
    the flow (here exact: the frames drift one pixel right, so the backward flow is dx = -1)."""
    hq = _face_like(3)
    flow = torch.zeros(2, 2, 64, 64)
    flow[:, 0] = -1.0
    pairs = [make_degraded_pairs(hq, seed=0, flow=flow)]
    cfg = EnhancerTrainConfig(crop=64, drop_temporal=0.0)
    g = torch.Generator().manual_seed(0)
    seen = set()
    for _ in range(20):
        state = g.get_state()
        i_t = torch.randint(1, (1,), generator=g), int(torch.randint(3, (1,), generator=g))
        g.set_state(state)
        lq, hq_crop, warped, mask, keep, group = _sample(pairs, _flows(pairs), cfg, 64, g)
        t = i_t[1]
        seen.add(t)
        assert group == "default" and torch.equal(hq_crop, hq[t]) and torch.equal(lq, pairs[0].lq[t])
        if t == 0:
            assert not keep and not warped.any() and not mask.any()
        else:
            assert keep
            # interior columns: warped previous HQ == current HQ (the content moved by exactly 1 px)
            torch.testing.assert_close(warped[:, :, 1:], hq[t][:, :, 1:], atol=1e-5, rtol=1e-5)
            assert float(mask[:, :, 1:].mean()) > 0.95 and not mask[:, :, 0].any()
    assert seen == {0, 1, 2}


def _flows(pairs):
    from volcap_core.enhance.training import _Flows

    return _Flows(pairs, "auto")


def test_temporal_conditions_are_dropped_with_the_configured_probability():
    pairs = [_pairs(4)]
    cfg = EnhancerTrainConfig(crop=32, drop_temporal=0.5, flow="zero")
    g = torch.Generator().manual_seed(0)
    kept = [_sample(pairs, _flows(pairs), cfg, 32, g)[4] for _ in range(200)]
    # frames 1-3 of 4 (3/4 of the draws) keep their conditions half the time: 3/8 overall
    assert 0.29 < sum(kept) / len(kept) < 0.46


def _final_state(result) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in result.model.state_dict().items()}


@pytest.mark.parametrize("finetune,vae_steps", [("lora", 0), ("full", 3)])
def test_resume_is_bit_identical(finetune, vae_steps):
    pairs = [_pairs(3, seed=0), _pairs(2, seed=1)]
    cfg = EnhancerTrainConfig(steps=4, batch=2, crop=48, lr=1e-3, finetune=finetune, lora_rank=4,
                              checkpoint_every=2, prev_output_noise=0.01, train_prompts=True, seed=7,
                              vae_steps=vae_steps, vae_batch=2, vae_crop=32)
    blobs: dict[int, bytes] = {}
    full = train_enhancer(build_enhancer(EnhancerConfig.tiny(), seed=0), pairs, cfg,
                          checkpoint=lambda b, s: blobs.__setitem__(s, b))
    assert sorted(blobs) == [2, 4] and len(full.losses) == 4
    assert len(full.vae_losses) == vae_steps
    assert full.model.config.train_crop == 48  # inference's timestep shift follows the training crop
    resumed = train_enhancer(build_enhancer(EnhancerConfig.tiny(), seed=0), pairs, cfg, resume_from=blobs[2])
    assert resumed.losses == full.losses and resumed.steps == 4
    assert resumed.vae_losses == full.vae_losses
    a, b = _final_state(full), _final_state(resumed)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    # and training did move the model away from its initialisation (the VAE only when pre-trained)
    init = build_enhancer(EnhancerConfig.tiny(), seed=0).state_dict()
    changed = sum(not torch.equal(a[k], init[k]) for k in init)
    assert changed > 0
    vae_changed = sum(not torch.equal(a[k], init[k]) for k in init if k.startswith("vae."))
    assert (vae_changed > 0) == (vae_steps > 0)
    # same seed, no interruption: the same run again
    again = train_enhancer(build_enhancer(EnhancerConfig.tiny(), seed=0), pairs, cfg)
    assert again.losses == full.losses


def test_vae_pretraining_learns_to_reconstruct_and_is_deterministic():
    """A few VAE steps on smooth frames lower the reconstruction loss (from a random VAE that
    destroys the image) and the same seed gives the same weights."""
    from volcap_core.enhance.training import train_vae, vae_loss

    frames = torch.cat([_face_like(3, seed=0), _face_like(3, seed=1)])
    cfg = EnhancerTrainConfig(vae_steps=60, vae_lr=3e-3, vae_batch=2, crop=32)
    models = [build_enhancer(EnhancerConfig.tiny(), seed=0) for _ in range(2)]
    with torch.no_grad():
        before = float(vae_loss(models[0], frames, 0.0))  # whole 64x64 frames, not the 32-px crops
    losses = train_vae(models[0], frames, cfg)
    assert len(losses) == 60 and losses == train_vae(models[1], frames, cfg)
    with torch.no_grad():
        after = float(vae_loss(models[0], frames, 0.0))
    # measured: 1.85 -> 0.74 (2 s on one thread)
    assert after < 0.6 * before, (before, after)
    for (k, p), (_, q) in zip(models[0].vae.state_dict().items(), models[1].vae.state_dict().items()):
        assert torch.equal(p, q), k
    assert not any(p.requires_grad for p in models[0].vae.parameters())


def test_vae_stages_continue_the_pretraining_at_their_rates():
    """``vae_stages`` are further :func:`train_vae` runs after the first ``vae_steps``, stage ``k``
    with its rate and the crop stream of ``seed + k``; no stages is left out of the JSON (cache keys
    of configs written before the field existed are unchanged)."""
    from volcap_core.enhance.training import train_vae

    pairs = [_pairs(3, seed=0)]
    cfg = EnhancerTrainConfig(steps=1, crop=32, finetune="full", flow="zero", vae_steps=3, vae_batch=2,
                              vae_crop=32, vae_lr=3e-3, seed=5, vae_stages=((2, 1e-3), (1, 3e-4)))
    result = train_enhancer(build_enhancer(EnhancerConfig.tiny(), seed=0), pairs, cfg)
    assert len(result.vae_losses) == 6
    by_hand = build_enhancer(EnhancerConfig.tiny(), seed=0)
    frames = torch.cat([p.hq.float() for p in pairs] + [p.lq.float() for p in pairs])
    losses = train_vae(by_hand, frames, cfg)
    losses += train_vae(by_hand, frames, cfg.model_copy(update={"vae_steps": 2, "vae_lr": 1e-3, "seed": 6}))
    losses += train_vae(by_hand, frames, cfg.model_copy(update={"vae_steps": 1, "vae_lr": 3e-4, "seed": 7}))
    assert losses == result.vae_losses
    for k, v in by_hand.vae.state_dict().items():
        assert torch.equal(v, result.model.vae.state_dict()[k]), k
    assert "vae_stages" not in EnhancerTrainConfig().model_dump_json()
    assert EnhancerTrainConfig.model_validate_json(cfg.model_dump_json()) == cfg
    with pytest.raises(ValueError, match="vae_steps"):
        EnhancerTrainConfig(vae_stages=((10, 1e-3),))
    with pytest.raises(ValueError, match="rate"):
        EnhancerTrainConfig(vae_steps=1, vae_stages=((10, 0.0),))


def test_lr_decay_scales_the_rate_from_its_steps():
    """``lr_decay``: after the warm-up, the rate is ``lr`` times the factor of the last pair
    reached; none is left out of the JSON (existing configs keep their cache keys)."""
    cfg = EnhancerTrainConfig(lr=1e-3, warmup_steps=10, lr_decay=((100, 0.2), (50, 0.5)))
    assert cfg.rate(5) == pytest.approx(5e-4)
    assert cfg.rate(10) == pytest.approx(1e-3) and cfg.rate(49) == pytest.approx(1e-3)
    assert cfg.rate(50) == pytest.approx(5e-4) and cfg.rate(99) == pytest.approx(5e-4)
    assert cfg.rate(100) == pytest.approx(2e-4) and cfg.rate(10_000) == pytest.approx(2e-4)
    assert EnhancerTrainConfig(lr=1e-3).rate(7) == 1e-3
    assert "lr_decay" not in EnhancerTrainConfig().model_dump_json()
    assert EnhancerTrainConfig.model_validate_json(cfg.model_dump_json()) == cfg
    with pytest.raises(ValueError, match="factor"):
        EnhancerTrainConfig(lr_decay=((10, 0.0),))


def test_resume_refuses_another_configuration():
    pairs = [_pairs(2)]
    cfg = EnhancerTrainConfig(steps=1, crop=32, finetune="lora", lora_rank=2, flow="zero")
    blobs = []
    train_enhancer(build_enhancer(EnhancerConfig.tiny()), pairs, cfg, checkpoint=lambda b, s: blobs.append(b))
    with pytest.raises(ValueError, match="lora_rank"):
        train_enhancer(build_enhancer(EnhancerConfig.tiny()), pairs, cfg.model_copy(update={"lora_rank": 3}),
                       resume_from=blobs[0])


def test_bfloat16_frozen_weights_train_float32_adapters_and_resume_exactly():
    """``frozen_dtype="bfloat16"`` (how FLUX.1 LoRA training fits a GPU): the frozen base weights
    and the VAE are halved, the adapters and widened layers stay float32 master weights, the loss
    falls, a resumed run is bit-identical, and the merged model is one bfloat16 model that
    enhances a frame."""
    from volcap_core.enhance.inference import enhance_frame

    pairs = [_pairs(3, seed=0)]
    cfg = EnhancerTrainConfig(steps=40, batch=2, crop=48, lr=2e-3, finetune="lora", lora_rank=4,
                              checkpoint_every=20, seed=3, frozen_dtype="bfloat16")
    seen: dict[str, set] = {}

    def watch(step, total, info):
        if step == 1:
            for name, p in model.transformer.named_parameters():
                kind = "lora" if ".lora_" in name else ("widened" if name.startswith(("x_embedder", "proj_out"))
                                                        else "base")
                seen.setdefault(kind, set()).add(p.dtype)
            seen["vae"] = {p.dtype for p in model.vae.parameters()}

    model = build_enhancer(EnhancerConfig.tiny(), seed=0)
    blobs: dict[int, bytes] = {}
    run = train_enhancer(model, pairs, cfg, progress=watch, checkpoint=lambda b, s: blobs.__setitem__(s, b))
    assert seen == {"lora": {torch.float32}, "widened": {torch.float32}, "base": {torch.bfloat16},
                    "vae": {torch.bfloat16}}
    assert all(torch.isfinite(torch.tensor(run.losses)))
    assert sum(run.losses[-10:]) < 0.8 * sum(run.losses[:10])
    assert {p.dtype for p in run.model.parameters()} == {torch.bfloat16}  # merged, one dtype
    resumed = train_enhancer(build_enhancer(EnhancerConfig.tiny(), seed=0), pairs, cfg, resume_from=blobs[20])
    assert resumed.losses == run.losses
    for (k, a), (_, b) in zip(_final_state(run).items(), _final_state(resumed).items()):
        assert torch.equal(a, b), k
    out = enhance_frame(run.model, pairs[0].lq[0], steps=2)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()


def test_training_attention_keeps_cudnn_off_while_any_training_runs():
    """cuDNN's attention failed in bf16 training on an H200 (training.training_attention): it is
    off while any training runs, for the whole process (the flag is global, not per thread), so
    one training ending while another still runs must not turn it back on; the last to end
    restores the setting. On the CPU nothing changes."""
    from contextlib import ExitStack

    from volcap_core.enhance.training import training_attention

    assert torch.backends.cuda.cudnn_sdp_enabled()
    with training_attention("cpu"):
        assert torch.backends.cuda.cudnn_sdp_enabled()
    a, b = ExitStack(), ExitStack()
    a.enter_context(training_attention("cuda"))
    assert not torch.backends.cuda.cudnn_sdp_enabled()
    b.enter_context(training_attention(torch.device("cuda", 0)))
    a.close()                                                    # the first ends, the second runs on
    assert not torch.backends.cuda.cudnn_sdp_enabled()
    b.close()
    assert torch.backends.cuda.cudnn_sdp_enabled()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_bfloat16_lora_training_runs_on_cuda():
    """The failure ``training_attention`` exists for: bf16 LoRA training on CUDA (PyTorch's
    default attention there is cuDNN's, whose backward failed on an H200 and turned the small
    model's loss NaN by the third step). With the switch, every loss is finite, the loss falls,
    cuDNN's attention is off while training runs and restored after, and the merged model
    enhances a frame on the GPU."""
    from volcap_core.enhance.inference import enhance_frame

    pairs = [_pairs(3, seed=0)]
    cfg = EnhancerTrainConfig(steps=60, batch=2, crop=48, lr=2e-3, finetune="lora", lora_rank=4,
                              checkpoint_every=0, seed=3, frozen_dtype="bfloat16")
    during = []
    before = torch.backends.cuda.cudnn_sdp_enabled()
    run = train_enhancer(build_enhancer(EnhancerConfig.small(), seed=0), pairs, cfg, device="cuda",
                         progress=lambda k, n, i: during.append(torch.backends.cuda.cudnn_sdp_enabled()))
    assert during and not any(during)
    assert torch.backends.cuda.cudnn_sdp_enabled() == before
    assert all(torch.isfinite(torch.tensor(run.losses))), run.losses[:5]
    assert sum(run.losses[-15:]) < 0.8 * sum(run.losses[:15])
    out = enhance_frame(run.model, pairs[0].lq[0].cuda(), steps=2)
    assert out.is_cuda and torch.isfinite(out).all()
