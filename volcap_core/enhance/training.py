"""Train the Detail Enhancer: rectified-flow (flow-matching) fine-tuning of the widened Flux model.

    model = build_enhancer(EnhancerConfig.tiny(), seed=0)      # or Enhancer.from_pretrained(dir)
    result = train_enhancer(model, pair_sets, EnhancerTrainConfig(steps=200, crop=64),
                            checkpoint=lambda blob, step: put_bytes(blob, MEDIA_BYTES))
    put_bytes(enhancer_to_bytes(result.model), ...)

One step (Flux's training objective, as SD3/Flux are trained): draw ``batch`` samples, each a random
pair sequence, frame ``t`` and ``crop x crop`` window; VAE-encode the HQ frame into the clean latents
``x0 = [RGB latent, alpha latent]`` and the conditions (LQ RGB, LQ alpha, warped previous output,
validity mask; :func:`~volcap_core.enhance.model.encode_conditions`); draw a noise level ``sigma``
and noise ``eps ~ N(0, I)``; ``x_sigma = (1 - sigma) x0 + sigma eps``; the model predicts the velocity
``eps - x0`` (MSE, uniform weighting). Adam (bias-corrected, eps 1e-8), constant learning rate after
a linear warm-up, global gradient-norm clipping.

Noise levels: SD3's logit-normal sampling (``sigma = sigmoid(n)``, ``n ~ N(logit_mean, logit_std)``,
default N(0, 1)) followed by Flux's resolution-dependent exponential shift
(:func:`~volcap_core.enhance.model.shift_sigma` with ``mu`` = :func:`~volcap_core.enhance.model.crop_mu`
of the training crop, 1.15 at 1024 px), i.e. the same distribution of noise levels the sampler visits
at this resolution. (BFL has not published FLUX.1's training schedule; this is the SD3 recipe with
Flux's shift, which diffusers' Flux fine-tuning scripts also offer.)

What stands for the previous output during training (the paper: "conditioning it on the previous
output frame", "for the first frame, both conditions are replaced with zeros, and the network is
trained with 50% dropout on these inputs"): **the previous HQ frame**, warped into frame ``t`` exactly
as inference warps the previous output (:func:`~volcap_core.enhance.temporal.temporal_condition` with
the flow between the LQ frames ``t-1`` and ``t``; the validity mask compares the warped previous LQ
with the current LQ). The previous HQ is what a perfect enhancer would have produced for ``t-1``, so
training sees the previous *output* the way the method defines it, not the previous LQ (which the
current LQ already stands for). Optionally (``prev_output_noise`` > 0) Gaussian noise of that standard
deviation (linear RGB) is added to the warped HQ, so the model does not learn to trust it blindly;
default 0. Frame 0 of a sequence, and any other sample with probability ``drop_temporal`` (0.5), gets
zero condition latents (the first-frame case).

Flow during training (``flow``): ``"auto"`` uses a pair set's exact flow when it has one, else OpenCV
DIS (:class:`~volcap_core.enhance.temporal.DisFlow`) on the LQ frames (computed once per frame pair
and cached); ``"dis"`` always DIS; ``"zero"`` no motion compensation (an ablation).

Fine-tuning (``finetune``): ``"full"`` trains every transformer weight; ``"lora"`` freezes them and
trains low-rank adapters (:mod:`volcap_core.enhance.lora`: zero at the start, so training starts
from the widened model exactly) on the attention and feed-forward linears of every block, plus, in
full, the widened ``x_embedder`` and ``proj_out`` (their new columns / rows start at zero or as
copies and must be learnt). The VAE is frozen while the transformer trains;
with ``vae_steps`` > 0 it is first pre-trained on its own (:func:`train_vae`: L1 + L2 reconstruction
of the pair sets' HQ and LQ frames, RGB and alpha-as-gray, through the enhancer's own encode/decode
mapping), which a tiny enhancer with random weights needs and FLUX.1's trained VAE does not. After
training the adapters are merged into the weights (:func:`~volcap_core.enhance.lora.merge_lora`), so
the result saves as a plain enhancer.

Checkpoints are safetensors bytes (trainable tensors, Adam moments, the RNG state, the step, the loss
history; configs in the metadata; :mod:`volcap_core.checkpoint`). ``resume_from`` continues exactly:
on CPU a resumed run ends bit-identical to an uninterrupted one (tested). With LoRA, the checkpoint
holds only what is trained: resume on the same base model.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_serializer, model_validator
from torch import nn

from hardware.serialization import omit_unset
from volcap_core.checkpoint import (
    AdamState,
    adam_step,
    deterministic_torch,
    safetensors_bytes,
    safetensors_metadata,
)
from volcap_core.enhance.model import (
    DEFAULT_GROUP,
    Enhancer,
    crop_mu,
    decode,
    encode,
    encode_conditions,
    encode_target,
    gray_to_vae,
    image_ids,
    pack,
    predict_velocity,
    rgb_to_vae,
    shift_sigma,
)
from volcap_core.enhance.lora import add_lora, merge_lora

__all__ = [
    "EnhancerTrainConfig",
    "EnhancerTrainResult",
    "flow_matching_loss",
    "sample_sigmas",
    "train_enhancer",
    "train_vae",
    "trainable_parameters",
    "vae_loss",
]

CHECKPOINT_FORMAT = "volcap-enhancer-train/1"

class EnhancerTrainConfig(BaseModel):
    """Everything that shapes an enhancer training run (JSON; a task's cache key).

    Attributes:
        steps: optimiser steps.
        lr: Adam learning rate (constant after ``warmup_steps`` of linear warm-up).
        lr_decay: ``(step, factor)`` pairs: from optimiser step ``step`` on, the rate is ``lr`` times
            ``factor`` (the last pair reached applies). Default none (left out of the JSON, so
            configs written before the field existed keep their cache keys). At a constant rate the
            small model's loss swings widely and its output shows 16-px token blotches; a drop for
            the last third removes them (``docs/enhancer.md``, "Training").
        batch: samples per step (one crop of one frame each).
        crop: crop side in pixels (multiple of 16; lowered to the smallest frame, floored to 16).
        finetune: ``"lora"`` (adapters + widened layers) or ``"full"`` (every transformer weight).
        lora_rank, lora_alpha: adapter rank and scale numerator (scale = alpha / rank; default
            alpha = rank).
        drop_temporal: probability of zeroing both temporal conditions of a sample (paper: 0.5).
        prev_output_noise: std of Gaussian noise added to the warped previous HQ (see module doc).
        flow: ``"auto"`` | ``"dis"`` | ``"zero"`` (see module doc).
        logit_mean, logit_std: logit-normal noise-level sampling; ``resolution_shift``: apply
            Flux's shift for the crop size.
        max_grad_norm: global gradient-norm clip (0: none).
        train_prompts: also learn the groups' prompt embeddings.
        checkpoint_every: steps between checkpoints (and one after the last step; 0: last only).
        seed: seeds the one ``torch.Generator`` behind every random choice.
        vae_steps: steps of VAE pre-training (:func:`train_vae`) before the transformer's, on the
            pair sets' HQ and LQ frames; 0 (default): the VAE is used as given (FLUX.1's trained
            VAE). A tiny enhancer built with random weights needs it: its random VAE destroys
            every image it decodes.
        vae_lr, vae_batch, vae_crop: the VAE pre-training's Adam rate, crops per step and crop
            side (None: ``crop``; lowered to the frames, floored to a multiple of 8).
        vae_latent_weight: weight of the latent-statistics term of :func:`vae_loss`.
        vae_stages: further VAE pre-training after the first ``vae_steps``, as ``(steps, rate)``
            stages run in order, each a fresh :func:`train_vae` (new Adam moments) whose crops come
            from the stream of ``seed + k`` for stage ``k`` = 1, 2, ...: continuing at lower rates.
            Default none (left out of the JSON, so configs written before the field existed keep
            their cache keys). A random VAE pre-trained at one rate keeps wrong colours and blurred
            features that lower-rate stages restore (``docs/enhancer.md``, "The model").
        frozen_dtype: ``"float32"`` or ``"bfloat16"``: the dtype of every weight that is *not*
            trained (the VAE, and with LoRA the transformer's base weights); trained tensors
            (adapters, the widened layers, everything in full fine-tuning) stay float32 master
            weights with float32 Adam moments, and the forward pass runs under bfloat16 autocast.
            FLUX.1-dev's 12 B transformer is 48 GB in float32, 24 GB in bfloat16: what makes LoRA
            training fit one 80 GB GPU with room for 1024-px activations (diffusers' Flux LoRA
            scripts train the same way). A LoRA run's merged model is then stored in bfloat16.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    steps: int = Field(1000, ge=0)
    lr: float = Field(1e-4, gt=0)
    warmup_steps: int = Field(0, ge=0)
    lr_decay: tuple[tuple[int, float], ...] = ()
    batch: int = Field(1, ge=1)
    crop: int = Field(512, ge=16)
    finetune: Literal["lora", "full"] = "lora"
    lora_rank: int = Field(16, ge=1)
    lora_alpha: float | None = Field(None, gt=0)
    drop_temporal: float = Field(0.5, ge=0, le=1)
    prev_output_noise: float = Field(0.0, ge=0)
    flow: Literal["auto", "dis", "zero"] = "auto"
    logit_mean: float = 0.0
    logit_std: float = Field(1.0, gt=0)
    resolution_shift: bool = True
    max_grad_norm: float = Field(1.0, ge=0)
    train_prompts: bool = False
    checkpoint_every: int = Field(100, ge=0)
    seed: int = 0
    vae_steps: int = Field(0, ge=0)
    vae_lr: float = Field(1e-3, gt=0)
    vae_batch: int = Field(4, ge=1)
    vae_crop: int | None = Field(None, ge=8)
    vae_latent_weight: float = Field(0.01, ge=0)
    vae_stages: tuple[tuple[int, float], ...] = ()
    frozen_dtype: Literal["float32", "bfloat16"] = "float32"

    @field_validator("lr_decay", "vae_stages")
    @classmethod
    def _positive_schedule(cls, v: tuple[tuple[int, float], ...], info) -> tuple[tuple[int, float], ...]:
        count_name, value_name = {"lr_decay": ("step", "factor"), "vae_stages": ("steps", "rate")}[info.field_name]
        for count, value in v:
            if count < 1 or not value > 0:
                raise ValueError(f"each {info.field_name} pair needs {count_name} >= 1 and a {value_name} > 0, "
                                 f"got ({count}, {value})")
        return v

    @model_validator(mode="after")
    def _stages_follow_pretraining(self) -> "EnhancerTrainConfig":
        if self.vae_stages and self.vae_steps == 0:
            raise ValueError("vae_stages continue the VAE pre-training: they need vae_steps > 0")
        return self

    @model_serializer(mode="wrap")
    def _omit_empty_schedules(self, handler):
        # no lr_decay / no vae_stages (the defaults) are left out of the JSON: a task's cache key and
        # the checkpoints of configs written before the fields existed stay byte-identical
        return omit_unset(handler(self), ("lr_decay", "vae_stages"))

    def rate(self, step: int) -> float:
        """The transformer's learning rate at optimiser step ``step`` (1-based): the linear
        warm-up, then ``lr`` times the factor of the last :attr:`lr_decay` pair reached."""
        lr = self.lr * min(1.0, step / self.warmup_steps) if self.warmup_steps else self.lr
        factor = 1.0
        for at, f in sorted(self.lr_decay):
            if step >= at:
                factor = f
        return lr * factor


@dataclass
class EnhancerTrainResult:
    """The trained model (adapters merged), the loss after every step, steps and training seconds;
    ``vae_losses``: the VAE pre-training's loss per step (empty when ``vae_steps`` is 0)."""

    model: Enhancer
    losses: list[float] = field(default_factory=list)
    steps: int = 0
    wall_s: float = 0.0
    vae_losses: list[float] = field(default_factory=list)


def _cast_frozen(model: Enhancer, trained: dict[str, nn.Parameter], dtype: torch.dtype) -> None:
    """Every parameter not in ``trained`` to ``dtype``, every trained one to float32 (in place)."""
    keep = {id(p) for p in trained.values()}
    with torch.no_grad():
        for p in model.parameters():
            p.data = p.data.float() if id(p) in keep else p.data.to(dtype)


def trainable_parameters(model: Enhancer, config: EnhancerTrainConfig) -> dict[str, nn.Parameter]:
    """Name -> parameter of what ``config`` trains (sorted by name), with ``requires_grad`` set on
    them and cleared everywhere else. LoRA: the adapters, ``x_embedder`` and ``proj_out``; full:
    the whole transformer; plus the prompt embeddings when ``train_prompts``."""
    model.requires_grad_(False)
    out: dict[str, nn.Parameter] = {}
    for name, p in model.named_parameters():
        if name.startswith("transformer."):
            sub = name[len("transformer."):]
            take = (config.finetune == "full" or ".lora_A" in sub or ".lora_B" in sub
                    or sub.startswith("x_embedder.") or sub.startswith("proj_out."))
        else:
            take = config.train_prompts and name.startswith("prompt_")
        if take:
            out[name] = p
    for p in out.values():
        p.requires_grad_(True)
    return dict(sorted(out.items()))


# ---------------------------------------------------------------------------------- objective

_CUDNN_ATTENTION_LOCK = threading.Lock()
_cudnn_attention_off = 0          # trainings running with cuDNN's attention off (this process)
_cudnn_attention_before = True    # its setting before the first of them


@contextlib.contextmanager
def training_attention(device: torch.device | str) -> Iterator[None]:
    """While training on CUDA, PyTorch's scaled-dot-product attention uses flash, memory-efficient
    or math kernels, never cuDNN's; elsewhere nothing changes.

    Why: with cuDNN's attention chosen (PyTorch's default for bf16 on recent GPUs), the backward
    pass of the transformer under bf16 autocast fails or goes NaN, where flash and memory-efficient
    attention train it (what was seen on which GPU and software: ``docs/enhancer.md``, "Attention
    kernels in training"; ``bench/bench_enhance_gpu.py``). Inference keeps the default choice: only
    the backward failed.

    The switch (``torch.backends.cuda.enable_cudnn_sdp``) is one flag for the whole process, not
    per thread, so trainings that overlap in one process (mapped tasks) share it: the first to
    start turns cuDNN's attention off, the last to end restores what was set before.
    """
    global _cudnn_attention_off, _cudnn_attention_before
    if torch.device(device).type != "cuda":
        yield
        return
    with _CUDNN_ATTENTION_LOCK:
        if _cudnn_attention_off == 0:
            _cudnn_attention_before = torch.backends.cuda.cudnn_sdp_enabled()
            torch.backends.cuda.enable_cudnn_sdp(False)
        _cudnn_attention_off += 1
    try:
        yield
    finally:
        with _CUDNN_ATTENTION_LOCK:
            _cudnn_attention_off -= 1
            if _cudnn_attention_off == 0:
                torch.backends.cuda.enable_cudnn_sdp(_cudnn_attention_before)


def sample_sigmas(n: int, config: EnhancerTrainConfig, mu: float, generator: torch.Generator) -> torch.Tensor:
    """``[n]`` training noise levels: ``sigmoid(N(logit_mean, logit_std))``, then Flux's shift by
    ``mu`` when ``config.resolution_shift``. Float32, CPU."""
    s = torch.sigmoid(torch.randn(n, generator=generator) * config.logit_std + config.logit_mean)
    return shift_sigma(s, mu) if config.resolution_shift else s


def flow_matching_loss(model: Enhancer, x0: torch.Tensor, cond: torch.Tensor, sigma: torch.Tensor,
                       noise: torch.Tensor, prompt: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Rectified-flow loss: ``x_sigma = (1 - sigma) x0 + sigma eps``, MSE of the predicted velocity
    against ``eps - x0``. ``x0``, ``noise``: ``[B, 2C, h, w]``; ``cond``: ``[B, 4C, h, w]``;
    ``sigma``: ``[B]``; ``prompt``: pooled ``[B, P]``, sequence ``[B, S, D]``."""
    s = sigma.view(-1, 1, 1, 1).to(x0)
    xt = (1.0 - s) * x0 + s * noise
    target = pack(noise - x0)
    h, w = x0.shape[-2:]
    pred = predict_velocity(model, pack(xt), pack(cond), sigma.to(x0), image_ids(h, w, x0.device), prompt)
    return F.mse_loss(pred.float(), target.float())


# ------------------------------------------------------------------------------------- data

def _group(seq) -> str:
    return getattr(seq, "group", None) or DEFAULT_GROUP


def _crop_size(pairs: Sequence, crop: int) -> int:
    h = min(int(p.lq.shape[-2]) for p in pairs)
    w = min(int(p.lq.shape[-1]) for p in pairs)
    c = min(crop, h, w) // 16 * 16
    if c < 16:
        raise ValueError(f"frames of {h}x{w} px are too small for a 16-px crop")
    return c


class _Flows:
    """Backward flow of frame ``t`` (to ``t - 1``) per pair set, exact or DIS (cached), or None (zero)."""

    def __init__(self, pairs: Sequence, mode: str):
        self.pairs, self.mode, self.cache = pairs, mode, {}
        self._dis = None

    def __call__(self, i: int, t: int) -> torch.Tensor | None:
        if self.mode == "zero":
            return None
        seq = self.pairs[i]
        exact = getattr(seq, "flow", None)
        if self.mode == "auto" and exact is not None:
            return exact[t - 1]
        if (i, t) not in self.cache:
            from volcap_core.enhance.temporal import DisFlow

            self._dis = self._dis or DisFlow()
            self.cache[(i, t)] = self._dis(seq.lq[t - 1, :3], seq.lq[t, :3])
        return self.cache[(i, t)]


def _sample(pairs: Sequence, flows: _Flows, config: EnhancerTrainConfig, crop: int,
            gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, bool, str]:
    """One training sample: (lq, hq, warped previous HQ, mask) crops ``[4|1, crop, crop]``, whether
    the temporal conditions are kept, the group. Draws from ``gen`` in a fixed order."""
    from volcap_core.enhance.temporal import temporal_condition

    i = int(torch.randint(len(pairs), (1,), generator=gen))
    seq = pairs[i]
    n_frames, _, h, w = seq.lq.shape
    t = int(torch.randint(n_frames, (1,), generator=gen))
    drop = float(torch.rand(1, generator=gen)) < config.drop_temporal
    y0 = int(torch.randint(h - crop + 1, (1,), generator=gen))
    x0 = int(torch.randint(w - crop + 1, (1,), generator=gen))
    noise = (torch.randn(3, crop, crop, generator=gen) * config.prev_output_noise
             if config.prev_output_noise > 0 else None)
    win = (slice(None), slice(y0, y0 + crop), slice(x0, x0 + crop))
    lq, hq = seq.lq[t].float(), seq.hq[t].float()
    keep = t > 0 and not drop
    if keep:
        warped, mask = temporal_condition(seq.hq[t - 1].float(), seq.lq[t - 1].float(), lq, flows(i, t))
        warped = warped[win].clone()
        if noise is not None:
            warped[:3] += noise
    else:
        warped, mask = lq.new_zeros((4, h, w)), lq.new_zeros((1, h, w))
        warped = warped[win]
    return lq[win], hq[win], warped, mask[win], keep, _group(seq)


# ------------------------------------------------------------------------------ VAE pre-training

def vae_loss(model: Enhancer, rgba: torch.Tensor, latent_weight: float = 0.01) -> torch.Tensor:
    """Reconstruction loss of the VAE on RGBA crops ``[B, 4, H, W]`` (H, W multiples of 8), through
    exactly the mapping the enhancer uses: RGB by :func:`~volcap_core.enhance.model.rgb_to_vae`, alpha
    by :func:`~volcap_core.enhance.model.gray_to_vae` (alpha as a gray image), each through
    :func:`~volcap_core.enhance.model.encode` (posterior mode, Flux scaling and shift) and
    :func:`~volcap_core.enhance.model.decode`. Loss = L1 + L2 of the decoded minus the input (both in
    the VAE's [-1, 1] space, RGB and alpha images weighted alike) + ``latent_weight`` ·
    ``(mean(z)² + (var(z) - 1)²)`` of the scaled latents ``z``: keeps the latents near zero mean and
    unit variance, the scale the diffusion noise ``N(0, I)`` assumes (the Flux scaling and shift
    factors are kept, so the VAE learns latents they fit)."""
    x = torch.cat([rgb_to_vae(rgba[:, :3]), gray_to_vae(rgba[:, 3:4])])
    z = encode(model.vae, x)
    err = decode(model.vae, z).float() - x.float()
    loss = err.abs().mean() + (err * err).mean()
    if latent_weight > 0:
        zf = z.float()
        loss = loss + latent_weight * (zf.mean() ** 2 + (zf.var() - 1.0) ** 2)
    return loss


def _vae_generator(seed: int) -> torch.Generator:
    """The VAE pre-training's own generator (the transformer's stream is left untouched)."""
    import zlib

    return torch.Generator().manual_seed(zlib.crc32(f"vae/{int(seed)}".encode()))


def train_vae(model: Enhancer, frames: torch.Tensor, config: EnhancerTrainConfig, *,
              device: torch.device | str | None = None,
              progress: Callable[[int, int, dict], None] | None = None) -> list[float]:
    """Train ``model.vae`` (in place) to reconstruct RGBA ``frames [N, 4, H, W]`` (linear RGB,
    alpha in [0, 1]) for ``config.vae_steps`` Adam steps (rate ``vae_lr``, bias-corrected, eps 1e-8,
    gradient-norm clip ``max_grad_norm``) of :func:`vae_loss` on ``vae_batch`` random crops of side
    ``vae_crop`` (default ``crop``, lowered to the frames, floored to a multiple of 8) each. The crops
    come from a generator seeded by ``config.seed`` (its own stream, not the transformer's); on CPU
    with one thread (as training runs) the same inputs give the same weights bit for bit. Every VAE
    weight is trained; the VAE is left frozen (``requires_grad`` off) and in eval mode.
    Returns the loss of every step."""
    if frames.ndim != 4 or frames.shape[1] != 4:
        raise ValueError(f"frames must be [N, 4, H, W], got {tuple(frames.shape)}")
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    vae = model.vae
    vae.to(device)
    n, _, h, w = frames.shape
    crop = min(config.vae_crop or config.crop, h, w) // 8 * 8
    if crop < 8:
        raise ValueError(f"frames of {h}x{w} px are too small for an 8-px crop")
    gen = _vae_generator(config.seed)
    params = dict(sorted((k, p) for k, p in vae.named_parameters()))
    for p in params.values():
        p.requires_grad_(True)
    adam = AdamState.zeros_like({k: p.detach() for k, p in params.items()})
    losses: list[float] = []
    vae.train()
    t0 = time.perf_counter()
    try:
        with deterministic_torch(device.type), training_attention(device):
            for step in range(1, config.vae_steps + 1):
                crops = []
                for _ in range(config.vae_batch):
                    i = int(torch.randint(n, (1,), generator=gen))
                    y0 = int(torch.randint(h - crop + 1, (1,), generator=gen))
                    x0 = int(torch.randint(w - crop + 1, (1,), generator=gen))
                    crops.append(frames[i, :, y0:y0 + crop, x0:x0 + crop].float())
                batch = torch.stack(crops).to(device)
                for p in params.values():
                    p.grad = None
                loss = vae_loss(model, batch, config.vae_latent_weight)
                if not torch.isfinite(loss.detach()):
                    raise FloatingPointError(f"VAE step {step}: loss is {float(loss.detach())}")
                loss.backward()
                if config.max_grad_norm > 0:
                    torch.nn.utils.clip_grad_norm_(list(params.values()), config.max_grad_norm)
                adam_step(params, {k: config.vae_lr for k in params}, adam, eps=1e-8)
                losses.append(float(loss.detach()))
                if progress is not None:
                    progress(step, config.vae_steps, {"loss": losses[-1], "lr": config.vae_lr,
                                                      "wall_s": time.perf_counter() - t0})
    finally:
        for p in params.values():
            p.grad = None
            p.requires_grad_(False)
        vae.eval()
    return losses


# ---------------------------------------------------------------------------------- checkpoints

@dataclass
class _State:
    params: dict[str, nn.Parameter]
    adam: AdamState
    generator: torch.Generator
    step: int
    wall_s: float
    losses: list[float]
    vae_losses: list[float] = field(default_factory=list)


def _serialise(state: _State, model: Enhancer, config: EnhancerTrainConfig) -> bytes:
    tensors: dict[str, torch.Tensor] = {}
    for k, p in state.params.items():
        tensors[f"param/{k}"] = p.detach()
    tensors.update(state.adam.to_tensors("adam"))
    tensors["rng"] = state.generator.get_state()
    tensors["losses"] = torch.tensor(state.losses, dtype=torch.float64)
    if config.vae_steps > 0:  # the pre-trained VAE (frozen from here on): resumption skips pre-training
        for k, v in model.vae.state_dict().items():
            tensors[f"vae/{k}"] = v
        tensors["vae_losses"] = torch.tensor(state.vae_losses, dtype=torch.float64)
    tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    meta = {"format": CHECKPOINT_FORMAT, "train_config": config.model_dump_json(),
            "enhancer_config": model.config.model_dump_json(),
            "state": json.dumps({"step": state.step, "adam_step": state.adam.step, "wall_s": state.wall_s,
                                 "groups": model.groups})}
    return safetensors_bytes(tensors, meta)


def _restore(data: bytes, model: Enhancer, config: EnhancerTrainConfig, params: dict[str, nn.Parameter],
             state: _State) -> None:
    from safetensors.torch import load as st_load

    meta = safetensors_metadata(data)
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"not an enhancer training checkpoint (format {meta.get('format')!r})")
    if meta["enhancer_config"] != model.config.model_dump_json():
        raise ValueError("checkpoint was trained on another enhancer architecture")
    old = json.loads(meta["train_config"])
    for key in ("finetune", "lora_rank", "lora_alpha", "train_prompts", "vae_steps", "vae_stages"):
        if key not in old:  # written before the field existed (or left out): its default
            old[key] = EnhancerTrainConfig.model_fields[key].default
        if json.dumps(old[key]) != json.dumps(getattr(config, key)):
            raise ValueError(f"checkpoint has {key}={old[key]!r}, config {getattr(config, key)!r}")
    info = json.loads(meta["state"])
    t = st_load(data)
    stored = sorted(k[len("param/"):] for k in t if k.startswith("param/"))
    if stored != list(params):
        raise ValueError("checkpoint holds other trainable tensors than this configuration trains")
    with torch.no_grad():
        for k, p in params.items():
            p.copy_(t[f"param/{k}"])
    state.adam = AdamState.from_tensors(t, "adam", int(info["adam_step"]), like=params)
    state.generator.set_state(t["rng"].clone())
    state.step, state.wall_s = int(info["step"]), float(info["wall_s"])
    state.losses = [float(x) for x in t["losses"].tolist()]
    if config.vae_steps > 0:
        vae_state = {k[len("vae/"):]: v for k, v in t.items() if k.startswith("vae/")}
        model.vae.load_state_dict({k: v.to(model.vae.dtype) for k, v in vae_state.items()}, strict=True)
        state.vae_losses = [float(x) for x in t["vae_losses"].tolist()]


# ------------------------------------------------------------------------------------- training

def train_enhancer(model: Enhancer, pairs: Sequence, config: EnhancerTrainConfig, *,
                   checkpoint: Callable[[bytes, int], None] | None = None, resume_from: bytes | None = None,
                   progress: Callable[[int, int, dict], None] | None = None,
                   device: torch.device | str | None = None, merge: bool = True) -> EnhancerTrainResult:
    """Fine-tune ``model`` (in place) on LQ/HQ pair sequences.

    Args:
        model: a widened enhancer (:func:`~volcap_core.enhance.model.build_enhancer`,
            :meth:`~volcap_core.enhance.model.Enhancer.from_pretrained`). With LoRA and
            ``resume_from``, the same base model the checkpoint was trained from.
        pairs: sequences with ``lq``, ``hq`` ``[T, 4, H, W]`` linear RGBA, optional exact backward
            ``flow [T-1, 2, H, W]`` (``flow[t-1]`` takes frame ``t`` to ``t-1``) and optional
            ``group`` (prompt group; default ``"default"``) —
            :class:`~volcap_core.enhance.pairs.PairSet` fits. Groups without an embedding get zeros.
        config: :class:`EnhancerTrainConfig`.
        checkpoint: ``checkpoint(bytes, step)`` every ``config.checkpoint_every`` steps and after
            the last; the bytes resume the run exactly (wrap a ``put_bytes`` to store them).
        resume_from: checkpoint bytes to continue from (``steps`` may be larger than theirs).
        progress: ``progress(step, steps, {"loss", "sigma", "lr", "wall_s"})`` after every step.
        device: default CUDA when available, else CPU (CPU runs with one intra-op thread, so the
            run is reproducible and resumable bit for bit).
        merge: fold LoRA adapters into the weights at the end (the model then saves as a plain
            enhancer); False leaves them in place.
    With ``config.vae_steps`` > 0 the VAE is first pre-trained (:func:`train_vae`) on every pair
    set's HQ and LQ frames (then through ``config.vae_stages``), then frozen; checkpoints then hold
    the VAE weights, and a resumed run loads them instead of pre-training again (a run interrupted during VAE pre-training, which
    writes no checkpoint, starts over).
    The crop actually used becomes ``model.config.train_crop`` at the end (inference takes its
    timestep shift from it).
    Returns:
        :class:`EnhancerTrainResult`.
    """
    if not pairs:
        raise ValueError("no training pairs")
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    low = config.frozen_dtype == "bfloat16"
    # with frozen_dtype bfloat16 the transformer reaches the device only once its frozen weights
    # are halved (a float32 FLUX.1 transformer alone is 48 GB)
    (model.vae if low else model).to(device)
    model.vae.eval()
    model.transformer.train()
    crop = _crop_size(pairs, config.crop)
    mu = crop_mu(crop, model.config)
    for seq in pairs:
        model.ensure_prompt(_group(seq))
    vae_losses: list[float] = []
    if config.vae_steps > 0 and resume_from is None:
        frames = torch.cat([p.hq.float() for p in pairs] + [p.lq.float() for p in pairs])
        vae_losses = train_vae(model, frames, config, device=device)
        for k, (n, rate) in enumerate(config.vae_stages, start=1):
            stage = config.model_copy(update={"vae_steps": n, "vae_lr": rate, "seed": config.seed + k})
            vae_losses += train_vae(model, frames, stage, device=device)
        del frames
    model.vae.eval()
    model.vae.requires_grad_(False)
    gen = torch.Generator().manual_seed(config.seed)
    if config.finetune == "lora":
        add_lora(model, config.lora_rank, config.lora_alpha, generator=gen)
    params = trainable_parameters(model, config)
    if low:
        _cast_frozen(model, params, torch.bfloat16)
        model.to(device)
    state = _State(params, AdamState.zeros_like({k: p.detach() for k, p in params.items()}), gen, 0, 0.0, [],
                   vae_losses)
    if resume_from is not None:
        _restore(resume_from, model, config, params, state)
    flows = _Flows(pairs, config.flow)

    with deterministic_torch(device.type), training_attention(device):
        while state.step < config.steps:
            t_start = time.perf_counter()
            step = state.step + 1
            samples = [_sample(pairs, flows, config, crop, state.generator) for _ in range(config.batch)]
            lq, hq, warped, mask = (torch.stack([s[j] for s in samples]).to(device) for j in range(4))
            keep = torch.tensor([s[4] for s in samples], device=device)
            prompts = [model.prompt(s[5]) for s in samples]
            prompt = (torch.stack([p[0] for p in prompts]), torch.stack([p[1] for p in prompts]))
            sigma = sample_sigmas(config.batch, config, mu, state.generator).to(device)
            with torch.no_grad(), torch.autocast(device.type, torch.bfloat16, enabled=low):
                x0 = encode_target(model, hq).float()
                cond = encode_conditions(model, lq, warped, mask, keep).float()
            noise = torch.randn(x0.shape, generator=state.generator).to(device, x0.dtype)
            for p in params.values():
                p.grad = None
            with torch.autocast(device.type, torch.bfloat16, enabled=low):
                loss = flow_matching_loss(model, x0, cond, sigma, noise, prompt)
            if not torch.isfinite(loss.detach()):
                raise FloatingPointError(f"step {step}: loss is {float(loss.detach())}")
            loss.backward()
            if config.max_grad_norm > 0:
                torch.nn.utils.clip_grad_norm_(list(params.values()), config.max_grad_norm)
            lr = config.rate(step)
            adam_step(params, {k: lr for k in params}, state.adam, eps=1e-8)
            state.step = step
            state.losses.append(float(loss.detach()))
            state.wall_s += time.perf_counter() - t_start
            if progress is not None:
                progress(step, config.steps, {"loss": state.losses[-1], "sigma": float(sigma.mean()),
                                              "lr": lr, "wall_s": state.wall_s})
            if checkpoint is not None and ((config.checkpoint_every and step % config.checkpoint_every == 0)
                                           or step == config.steps):
                checkpoint(_serialise(state, model, config), step)
    model.requires_grad_(False)
    model.transformer.eval()
    if merge:
        merge_lora(model)
        if low and config.finetune == "lora":  # one dtype for inference: the base weights'
            model.to(torch.bfloat16)
    # inference fixes its timestep shift to the training crop's (model.crop_mu): record the crop used
    model.config = model.config.model_copy(update={"train_crop": crop})
    return EnhancerTrainResult(model, list(state.losses), state.step, state.wall_s, list(state.vae_losses))
