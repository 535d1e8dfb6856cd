"""The Detail Enhancer's network: a widened Flux transformer, the Flux VAE and stored prompt embeddings.

The paper's "Detail Enhancement Model" (``paper.tex``, "Image-Conditioning", "Alpha Channel
Enhancement"): Flux's diffusion transformer whose first linear layer (``x_embedder``) takes six
VAE latents instead of one, and whose output layer (``proj_out``) predicts two.

Latents. The Flux VAE maps an image ``[B, 3, H, W]`` in [-1, 1] to ``[B, 16, H/8, W/8]``
(``L_ch`` = 16 channels; stored scaled as ``(z - 0.1159) * 0.3611``). The transformer sees latents
packed in 2x2 patches: ``[B, (H/16)(W/16), 64]`` (channel-major: feature ``c*4 + 2*dy + dx``), so
concatenating packed tensors on the last axis equals concatenating latents on channels. With
``L = 64`` the packed width of one latent, the widened transformer takes ``6 L = 384`` features per
token, in this order::

    [ noise RGB | noise alpha | LQ RGB | LQ alpha | warped previous output | validity mask ]
      slot 0      slot 1        slot 2   slot 3     slot 4                   slot 5

and predicts ``2 L = 128``: ``[ velocity RGB | velocity alpha ]``.

How each image becomes a VAE input (``[-1, 1]``, 3 channels; :func:`rgb_to_vae`, :func:`gray_to_vae`):

- RGB (LQ, HQ, the warped previous output): linear light -> unbounded sRGB (no clamp: HDR values
  above 1 stay above 1) -> ``2 x - 1``. Decoding inverts it exactly.
- alpha and the validity mask (1 channel in [0, 1]): replicated to 3 channels, then ``2 x - 1``.
  Decoding an alpha latent averages the 3 decoded channels and clamps to [0, 1].
- the warped previous output is encoded by its RGB only (premultiplied, as the renderer writes
  it); its alpha is not a condition (the paper's six slots have one for the previous output).

Widening keeps pretrained behaviour: the new ``x_embedder`` columns (slots 1-5) are zero, slot 0
keeps the pretrained weights, and the alpha head of ``proj_out`` starts as a copy of the RGB head,
so at initialisation the widened model's RGB (and alpha) velocity equals the pretrained model's
prediction from the noise RGB latent, whatever the conditions hold (tested).

Prompts. Flux is conditioned on a T5 sequence embedding ``[S, joint_attention_dim]`` and a CLIP
pooled embedding ``[pooled_projection_dim]``. The enhancer keeps one such pair per actor group
(:class:`PromptEmbedding`), computed once (:func:`encode_prompt`, which needs ``transformers`` and
the FLUX.1 text encoders on disk) and stored with the model; the text encoders are never needed at
run time. A group without a computed embedding gets a zero embedding of the right shape
(``prompt_tokens`` tokens), which training may learn (``EnhancerTrainConfig.train_prompts``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from volcap_core.checkpoint import safetensors_bytes, safetensors_metadata
from volcap_core.enhance.lora import LoRALinear

__all__ = [
    "CONDITION_SLOTS",
    "FLUX_SCALING_FACTOR",
    "FLUX_SHIFT_FACTOR",
    "Enhancer",
    "EnhancerConfig",
    "PromptEmbedding",
    "build_enhancer",
    "crop_mu",
    "decode",
    "decode_rgba",
    "encode",
    "encode_conditions",
    "encode_target",
    "encode_prompt",
    "enhancer_from_bytes",
    "enhancer_to_bytes",
    "flux_mu",
    "flux_sigmas",
    "gray_to_vae",
    "image_ids",
    "pack",
    "predict_velocity",
    "rgb_to_vae",
    "shift_sigma",
    "unpack",
    "vae_to_gray",
    "vae_to_rgb",
    "widen_transformer",
]

FLUX_SCALING_FACTOR = 0.3611
FLUX_SHIFT_FACTOR = 0.1159
#: input slots of the widened ``x_embedder``, in order (each one packed latent wide)
CONDITION_SLOTS = ("noise_rgb", "noise_alpha", "lq_rgb", "lq_alpha", "warped_prev", "validity")
N_INPUT_SLOTS = len(CONDITION_SLOTS)
N_OUTPUT_SLOTS = 2
ENHANCER_FORMAT = "volcap-enhancer/1"
DEFAULT_GROUP = "default"


# ------------------------------------------------------------------------------------- config

def _flux_dev_transformer() -> dict[str, Any]:
    return {"patch_size": 1, "in_channels": 64, "out_channels": None, "num_layers": 19,
            "num_single_layers": 38, "attention_head_dim": 128, "num_attention_heads": 24,
            "joint_attention_dim": 4096, "pooled_projection_dim": 768, "guidance_embeds": True,
            "axes_dims_rope": [16, 56, 56]}


def _flux_vae() -> dict[str, Any]:
    return {"in_channels": 3, "out_channels": 3, "latent_channels": 16,
            "down_block_types": ["DownEncoderBlock2D"] * 4, "up_block_types": ["UpDecoderBlock2D"] * 4,
            "block_out_channels": [128, 256, 512, 512], "layers_per_block": 2, "norm_num_groups": 32,
            "act_fn": "silu", "sample_size": 1024, "scaling_factor": FLUX_SCALING_FACTOR,
            "shift_factor": FLUX_SHIFT_FACTOR, "use_quant_conv": False, "use_post_quant_conv": False,
            "mid_block_add_attention": True, "force_upcast": True}


class EnhancerConfig(BaseModel):
    """What builds an :class:`Enhancer` (JSON; part of a training task's key).

    Attributes:
        transformer: ``FluxTransformer2DModel`` constructor arguments of the *base* (un-widened)
            model: ``in_channels`` = 4 x the VAE's latent channels (packed 2x2), ``out_channels``
            None. :func:`build_enhancer` widens it to 6x in and 2x out.
        vae: ``AutoencoderKL`` constructor arguments (16 latent channels, Flux's scaling 0.3611 and
            shift 0.1159).
        prompt_tokens: tokens of a zero prompt embedding (Flux-dev's T5 length: 512).
        guidance: the distilled-guidance value fed to models with ``guidance_embeds`` (FLUX.1-dev;
            3.5 is its pipeline's default); ignored otherwise.
        train_crop: training crop side (px). Inference fixes the timestep shift to this size's
            value (:func:`flux_mu`) whatever the frame or tile size: at full-frame 4K the automatic
            shift would be far outside its calibrated range.
        base_seq_len, max_seq_len, base_shift, max_shift: Flux's resolution-dependent shift
            (``FlowMatchEulerDiscreteScheduler`` of FLUX.1: 256, 4096, 0.5, 1.15).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    transformer: dict[str, Any] = Field(default_factory=_flux_dev_transformer)
    vae: dict[str, Any] = Field(default_factory=_flux_vae)
    prompt_tokens: int = Field(512, ge=1)
    guidance: float = 3.5
    train_crop: int = Field(1024, ge=16)
    base_seq_len: int = 256
    max_seq_len: int = 4096
    base_shift: float = 0.5
    max_shift: float = 1.15

    @classmethod
    def flux_dev(cls) -> "EnhancerConfig":
        """FLUX.1-dev's architecture (11.9 B parameters); random weights unless loaded."""
        return cls()

    @classmethod
    def tiny(cls) -> "EnhancerConfig":
        """A CPU-sized model with random weights: 1 double + 1 single block, 2 heads x 16, rope
        axes (4, 6, 6), joint_attention_dim 32; a 4-level VAE (x8) of 16-channel blocks with the
        Flux latent format (16 channels, same scaling/shift). Training crop 64 px."""
        transformer = {"patch_size": 1, "in_channels": 64, "out_channels": None, "num_layers": 1,
                       "num_single_layers": 1, "attention_head_dim": 16, "num_attention_heads": 2,
                       "joint_attention_dim": 32, "pooled_projection_dim": 32, "guidance_embeds": False,
                       "axes_dims_rope": [4, 6, 6]}
        vae = {**_flux_vae(), "block_out_channels": [16, 16, 16, 16], "layers_per_block": 1,
               "norm_num_groups": 4, "sample_size": 64, "force_upcast": False}
        return cls(transformer=transformer, vae=vae, prompt_tokens=8, guidance=0.0, train_crop=64)

    @classmethod
    def small(cls) -> "EnhancerConfig":
        """The CPU model that learns (``bench/bench_enhance.py``): :meth:`tiny` with a 256-wide
        transformer (8 heads x 32, rope axes (8, 12, 12); 3.8 M parameters) and VAE tiling only
        above 256 px (``sample_size`` 256). Each token must carry six packed latents in (6 x 64
        features) and two out (2 x 64): the tiny transformer's 32 features cannot even carry one,
        and trained it stays below the LQ input; 256 features learn more than 128 for a longer
        step, and tiling a 128-px frame into the tiny VAE's 64-px tiles costs detail (figures in
        ``docs/enhancer.md``, "The model")."""
        tiny = cls.tiny()
        transformer = {**tiny.transformer, "attention_head_dim": 32, "num_attention_heads": 8,
                       "axes_dims_rope": [8, 12, 12]}
        vae = {**tiny.vae, "sample_size": 256}
        return tiny.model_copy(update={"transformer": transformer, "vae": vae})

    @property
    def latent_channels(self) -> int:
        return int(self.vae.get("latent_channels", 16))

    @property
    def packed_channels(self) -> int:
        """``L``: one latent's width once packed in 2x2 patches (64 for Flux)."""
        return 4 * self.latent_channels


# ------------------------------------------------------------------------ latents and packing

def rgb_to_vae(rgb: torch.Tensor) -> torch.Tensor:
    """Linear RGB ``[..., 3, H, W]`` -> VAE input: unbounded sRGB (no clamp) mapped by ``2x - 1``."""
    from volcap_core.colour import srgb_encode_unbounded

    return 2.0 * srgb_encode_unbounded(rgb) - 1.0


def vae_to_rgb(x: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_vae`: VAE output ``[..., 3, H, W]`` -> linear RGB (unclamped)."""
    from volcap_core.colour import srgb_decode_unbounded

    return srgb_decode_unbounded((x + 1.0) * 0.5)


def gray_to_vae(a: torch.Tensor) -> torch.Tensor:
    """A 1-channel map in [0, 1] (alpha, validity mask) ``[..., 1, H, W]`` -> VAE input
    ``[..., 3, H, W]``: replicated to three channels, ``2x - 1``."""
    if a.shape[-3] != 1:
        raise ValueError(f"expected one channel, got {tuple(a.shape)}")
    return (2.0 * a - 1.0).expand(*a.shape[:-3], 3, *a.shape[-2:])


def vae_to_gray(x: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`gray_to_vae`: mean of the 3 decoded channels, ``(x + 1) / 2``, clamped to
    [0, 1]. ``[..., 3, H, W]`` -> ``[..., 1, H, W]``."""
    return ((x.mean(dim=-3, keepdim=True) + 1.0) * 0.5).clamp(0.0, 1.0)


def encode(vae, image: torch.Tensor) -> torch.Tensor:
    """VAE-encode ``image [B, 3, H, W]`` (in [-1, 1], H and W multiples of 8) to scaled latents
    ``[B, C, H/8, W/8]``: the posterior's mode (deterministic), then ``(z - shift) * scale``
    (Flux: 0.1159, 0.3611). Uses the VAE's own tiling when ``vae.enable_tiling()`` is on."""
    cfg = vae.config
    z = vae.encode(image.to(vae.dtype)).latent_dist.mode()
    return (z - (cfg.shift_factor or 0.0)) * cfg.scaling_factor


def decode(vae, latents: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`encode`'s scaling, then the VAE decoder: ``[B, C, h, w]`` ->
    ``[B, 3, 8h, 8w]`` in (about) [-1, 1]."""
    cfg = vae.config
    z = latents.to(vae.dtype) / cfg.scaling_factor + (cfg.shift_factor or 0.0)
    return vae.decode(z).sample


def pack(latents: torch.Tensor) -> torch.Tensor:
    """``[B, C, h, w]`` (h, w even) -> tokens ``[B, (h/2)(w/2), 4C]`` (Flux's 2x2 patches, row-major
    tokens, feature ``c*4 + 2*dy + dx``)."""
    b, c, h, w = latents.shape
    if h % 2 or w % 2:
        raise ValueError(f"latent size {h}x{w} must be even to pack 2x2 patches")
    x = latents.view(b, c, h // 2, 2, w // 2, 2).permute(0, 2, 4, 1, 3, 5)
    return x.reshape(b, (h // 2) * (w // 2), c * 4)


def unpack(tokens: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Inverse of :func:`pack`: ``[B, (h/2)(w/2), 4C]`` -> ``[B, C, h, w]`` (h, w in latent px)."""
    b, n, f = tokens.shape
    if n != (h // 2) * (w // 2):
        raise ValueError(f"{n} tokens do not tile a {h}x{w} latent")
    x = tokens.view(b, h // 2, w // 2, f // 4, 2, 2).permute(0, 3, 1, 4, 2, 5)
    return x.reshape(b, f // 4, h, w)


def image_ids(h: int, w: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Flux's rotary position ids of the packed tokens of an ``h x w`` latent: ``[(h/2)(w/2), 3]``
    rows ``(0, row, col)`` in token units, counted from the tile's own corner (every tile is seen
    as a training crop is)."""
    ids = torch.zeros(h // 2, w // 2, 3)
    ids[..., 1] = torch.arange(h // 2)[:, None]
    ids[..., 2] = torch.arange(w // 2)[None, :]
    return ids.reshape(-1, 3).to(device=device, dtype=dtype)


# --------------------------------------------------------------------------- timestep schedule

def flux_mu(image_seq_len: int, config: EnhancerConfig) -> float:
    """Flux's resolution-dependent shift ``mu``: linear in the packed token count, 0.5 at 256
    tokens (256 px) and 1.15 at 4096 (1024 px) (diffusers' ``calculate_shift``)."""
    m = (config.max_shift - config.base_shift) / (config.max_seq_len - config.base_seq_len)
    return image_seq_len * m + config.base_shift - m * config.base_seq_len


def crop_mu(crop_px: int, config: EnhancerConfig) -> float:
    """:func:`flux_mu` of a square ``crop_px`` image (``(crop/16)^2`` tokens)."""
    return flux_mu((crop_px // 16) ** 2, config)


def shift_sigma(sigma: torch.Tensor, mu: float) -> torch.Tensor:
    """Flux's exponential time shift: ``e^mu s / (e^mu s + 1 - s)`` (``s`` in [0, 1]; identity at
    mu = 0, pushes noise levels up for mu > 0)."""
    e = math.exp(mu)
    return e * sigma / (e * sigma + (1.0 - sigma))


def flux_sigmas(steps: int, mu: float) -> torch.Tensor:
    """The noise levels of an Euler sampler of ``steps`` steps: ``linspace(1, 1/steps, steps)``
    shifted by ``mu``, then 0 appended -> ``[steps + 1]`` float64, decreasing from 1 to 0
    (what FLUX.1's pipeline gives ``FlowMatchEulerDiscreteScheduler.set_timesteps``)."""
    if steps < 1:
        raise ValueError("steps must be >= 1")
    s = torch.linspace(1.0, 1.0 / steps, steps, dtype=torch.float64)
    return torch.cat([shift_sigma(s, mu), torch.zeros(1, dtype=torch.float64)])


# ------------------------------------------------------------------------------------- prompts

@dataclass(frozen=True)
class PromptEmbedding:
    """One actor group's text conditioning: ``pooled [P]`` (CLIP pooled; P =
    ``pooled_projection_dim``) and ``sequence [S, D]`` (T5 tokens; D = ``joint_attention_dim``)."""

    pooled: torch.Tensor
    sequence: torch.Tensor

    @classmethod
    def zeros(cls, config: EnhancerConfig) -> "PromptEmbedding":
        t = config.transformer
        return cls(torch.zeros(int(t["pooled_projection_dim"])),
                   torch.zeros(config.prompt_tokens, int(t["joint_attention_dim"])))

    def to_bytes(self) -> bytes:
        """Safetensors bytes (the stored artifact of a group's prompt)."""
        return safetensors_bytes({"pooled": self.pooled.detach().float().contiguous().cpu(),
                                  "sequence": self.sequence.detach().float().contiguous().cpu()},
                                 {"format": "volcap-prompt-embedding/1"})

    @classmethod
    def from_bytes(cls, data: bytes) -> "PromptEmbedding":
        from safetensors.torch import load as st_load

        t = st_load(data)
        return cls(t["pooled"].clone(), t["sequence"].clone())


def encode_prompt(text: str, encoders_dir: str | Path, *, max_sequence_length: int = 512,
                  device: str | torch.device = "cpu") -> PromptEmbedding:
    """Embed ``text`` with FLUX.1's text encoders (CLIP-L pooled + T5-XXL sequence) from a local
    FLUX.1 directory (``tokenizer``, ``text_encoder``, ``tokenizer_2``, ``text_encoder_2``
    subfolders), exactly as ``FluxPipeline.encode_prompt`` does. Needs ``transformers``; reads
    local files only. Run once per actor group and store the result (:meth:`PromptEmbedding.to_bytes`).
    """
    try:
        import transformers  # noqa: F401
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("encode_prompt needs the 'transformers' package and the FLUX.1 text "
                          "encoders; without them use PromptEmbedding.zeros") from e
    from diffusers import FluxPipeline

    pipe = FluxPipeline.from_pretrained(str(encoders_dir), transformer=None, vae=None,
                                        local_files_only=True)
    pipe.text_encoder.to(device)
    pipe.text_encoder_2.to(device)
    with torch.no_grad():
        seq, pooled, _ = pipe.encode_prompt(prompt=text, prompt_2=None, device=torch.device(device),
                                            max_sequence_length=max_sequence_length)
    return PromptEmbedding(pooled[0].float().cpu(), seq[0].float().cpu())


def _group_key(group: str) -> str:
    """ParameterDict keys may not contain '.'; group names are otherwise free."""
    return "g_" + group.encode().hex()


# ------------------------------------------------------------------------------------- the model

class Enhancer(nn.Module):
    """The widened Flux transformer, the VAE and the per-group prompt embeddings.

    ``transformer``: a ``FluxTransformer2DModel`` with ``in_channels = 6 L``, ``out_channels = 2 L``
    (:func:`widen_transformer`); ``vae``: an ``AutoencoderKL``; ``prompt_pooled`` /
    ``prompt_sequence``: one parameter per group (see :meth:`prompt`). Build with
    :func:`build_enhancer`, :meth:`from_pretrained` or :func:`enhancer_from_bytes`.
    """

    def __init__(self, transformer, vae, config: EnhancerConfig,
                 prompts: Mapping[str, PromptEmbedding] | None = None):
        super().__init__()
        L = config.packed_channels
        tc = transformer.config
        if tc.in_channels != N_INPUT_SLOTS * L or tc.out_channels != N_OUTPUT_SLOTS * L:
            raise ValueError(f"transformer takes {tc.in_channels} -> {tc.out_channels} features; the "
                             f"enhancer needs {N_INPUT_SLOTS * L} -> {N_OUTPUT_SLOTS * L} (widen it)")
        if vae.config.latent_channels != config.latent_channels:
            raise ValueError("VAE latent channels differ from the config")
        self.transformer = transformer
        self.vae = vae
        self.config = config
        self.prompt_pooled = nn.ParameterDict()
        self.prompt_sequence = nn.ParameterDict()
        self.vae.requires_grad_(False)
        for g, p in (prompts or {}).items():
            self.set_prompt(g, p)

    @property
    def groups(self) -> list[str]:
        return sorted(bytes.fromhex(k[2:]).decode() for k in self.prompt_pooled.keys())

    def set_prompt(self, group: str, prompt: PromptEmbedding) -> None:
        """Store (replace) ``group``'s embedding (frozen unless training learns prompts)."""
        t = self.config.transformer
        if tuple(prompt.pooled.shape) != (int(t["pooled_projection_dim"]),) or (
                prompt.sequence.ndim != 2 or prompt.sequence.shape[1] != int(t["joint_attention_dim"])):
            raise ValueError(f"prompt shapes {tuple(prompt.pooled.shape)}, {tuple(prompt.sequence.shape)} "
                             "do not fit the transformer")
        dev, dt = self.transformer.x_embedder.weight.device, self.transformer.dtype
        k = _group_key(group)
        self.prompt_pooled[k] = nn.Parameter(prompt.pooled.detach().to(dev, dt).clone(), requires_grad=False)
        self.prompt_sequence[k] = nn.Parameter(prompt.sequence.detach().to(dev, dt).clone(), requires_grad=False)

    def ensure_prompt(self, group: str) -> None:
        """Give ``group`` a zero embedding if it has none (see the module docstring)."""
        if _group_key(group) not in self.prompt_pooled:
            self.set_prompt(group, PromptEmbedding.zeros(self.config))

    def prompt(self, group: str = DEFAULT_GROUP) -> tuple[torch.Tensor, torch.Tensor]:
        """``(pooled [P], sequence [S, D])`` of ``group``; a group never given one reads zeros."""
        k = _group_key(group)
        if k not in self.prompt_pooled:
            z = PromptEmbedding.zeros(self.config)
            dev, dt = self.transformer.x_embedder.weight.device, self.transformer.dtype
            return z.pooled.to(dev, dt), z.sequence.to(dev, dt)
        return self.prompt_pooled[k], self.prompt_sequence[k]

    # -- persistence -------------------------------------------------------------------------

    def save_pretrained(self, path: str | Path) -> None:
        """A diffusers-style directory: ``transformer/`` and ``vae/`` (``save_pretrained``; the
        transformer config holds the widened ``in_channels``/``out_channels``),
        ``prompts.safetensors`` and ``enhancer.json`` (the whole :class:`EnhancerConfig`)."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        self.transformer.save_pretrained(path / "transformer")
        self.vae.save_pretrained(path / "vae")
        tensors = {}
        for g in self.groups:
            pooled, seq = self.prompt(g)
            tensors[f"{g}/pooled"] = pooled.detach().float().contiguous().cpu()
            tensors[f"{g}/sequence"] = seq.detach().float().contiguous().cpu()
        (path / "prompts.safetensors").write_bytes(safetensors_bytes(tensors, {"format": "volcap-prompts/1"}))
        (path / "enhancer.json").write_text(json.dumps(self.config.model_dump(mode="json"), indent=1,
                                                       sort_keys=True))

    @classmethod
    def from_pretrained(cls, path: str | Path, *, torch_dtype: torch.dtype | None = None,
                        device: str | torch.device | None = None) -> "Enhancer":
        """Load from a local directory only (never downloads): either a FLUX.1 checkpoint
        directory (``transformer/`` with ``in_channels`` 64, ``vae/``; widened here, see
        :func:`widen_transformer`) or one written by :meth:`save_pretrained` (already widened;
        ``prompts.safetensors`` and ``enhancer.json`` read when present)."""
        from diffusers import AutoencoderKL, FluxTransformer2DModel
        from safetensors.torch import load as st_load

        path = Path(path)
        if not (path / "transformer").is_dir() or not (path / "vae").is_dir():
            raise FileNotFoundError(f"{path}: expected transformer/ and vae/ subfolders")
        kw = {"local_files_only": True, **_load_kwargs()}
        if torch_dtype is not None:
            kw["torch_dtype"] = torch_dtype
        transformer = FluxTransformer2DModel.from_pretrained(str(path), subfolder="transformer", **kw)
        vae = AutoencoderKL.from_pretrained(str(path), subfolder="vae", **kw)
        L = 4 * int(vae.config.latent_channels)
        if transformer.config.in_channels == L:
            widen_transformer(transformer, L)
        base = _constructor_args(FluxTransformer2DModel, transformer.config)
        base.update(in_channels=L, out_channels=None)
        derived = EnhancerConfig(transformer=base, vae=_constructor_args(AutoencoderKL, vae.config))
        config = derived
        if (path / "enhancer.json").exists():
            config = EnhancerConfig.model_validate_json((path / "enhancer.json").read_text())
            for part in ("transformer", "vae"):
                ours, theirs = getattr(config, part), getattr(derived, part)
                bad = sorted(k for k in ours if _json_clean({"v": ours[k]}) != _json_clean({"v": theirs.get(k)}))
                if bad:
                    raise ValueError(f"{path}: enhancer.json's {part} config disagrees with {part}/ on {bad}")
        model = cls(transformer, vae, config)
        if (path / "prompts.safetensors").exists():
            t = st_load((path / "prompts.safetensors").read_bytes())
            for g in sorted({k.rsplit("/", 1)[0] for k in t}):
                model.set_prompt(g, PromptEmbedding(t[f"{g}/pooled"], t[f"{g}/sequence"]))
        if device is not None:
            model.to(device)
        return model


def _json_clean(d: dict) -> dict:
    """A config dict made JSON-plain (tuples -> lists)."""
    return json.loads(json.dumps(d, default=list))


def _constructor_args(cls, config) -> dict:
    """The constructor arguments of a diffusers model class found in its loaded ``config``."""
    import inspect

    names = [n for n in inspect.signature(cls.__init__).parameters if n != "self"]
    return _json_clean({n: config[n] for n in names if n in config})


def _load_kwargs() -> dict:
    """``low_cpu_mem_usage`` needs ``accelerate`` (recommended for FLUX.1: without it diffusers
    first initialises 12 B random weights); say so explicitly either way (no warning)."""
    import importlib.util

    return {"low_cpu_mem_usage": importlib.util.find_spec("accelerate") is not None}


def widen_transformer(transformer, packed_channels: int = 64) -> None:
    """Widen a Flux transformer in place for the enhancer.

    ``x_embedder``: ``Linear(L, D)`` -> ``Linear(6L, D)``: columns ``[0, L)`` (noise RGB) keep the
    pretrained weights, columns ``[L, 6L)`` (noise alpha, LQ RGB, LQ alpha, warped previous
    output, validity mask) are zero, the bias is kept. ``proj_out``: ``Linear(D, L)`` ->
    ``Linear(D, 2L)``: rows ``[0, L)`` (RGB velocity) keep the pretrained weights, rows
    ``[L, 2L)`` (alpha velocity) are a copy of them. ``register_to_config`` records the new
    widths, so ``save_pretrained``/``from_pretrained`` round-trips the widened model.
    """
    L = packed_channels
    old_in, old_out = transformer.x_embedder, transformer.proj_out
    p2 = transformer.config.patch_size ** 2
    if old_in.in_features != L or old_out.out_features != p2 * L:
        raise ValueError(f"transformer is not a base Flux model of {L} packed channels "
                         f"(x_embedder {old_in.in_features}, proj_out {old_out.out_features})")
    kw = {"device": old_in.weight.device, "dtype": old_in.weight.dtype}
    new_in = nn.Linear(N_INPUT_SLOTS * L, old_in.out_features, bias=old_in.bias is not None, **kw)
    new_out = nn.Linear(old_out.in_features, N_OUTPUT_SLOTS * p2 * L, bias=old_out.bias is not None, **kw)
    with torch.no_grad():
        new_in.weight.zero_()
        new_in.weight[:, :L] = old_in.weight
        if old_in.bias is not None:
            new_in.bias.copy_(old_in.bias)
        new_out.weight.copy_(old_out.weight.repeat(N_OUTPUT_SLOTS, 1))
        if old_out.bias is not None:
            new_out.bias.copy_(old_out.bias.repeat(N_OUTPUT_SLOTS))
    transformer.x_embedder = new_in
    transformer.proj_out = new_out
    transformer.out_channels = N_OUTPUT_SLOTS * L
    transformer.register_to_config(in_channels=N_INPUT_SLOTS * L, out_channels=N_OUTPUT_SLOTS * L)


def _base_transformer(config: EnhancerConfig):
    from diffusers import FluxTransformer2DModel

    cfg = dict(config.transformer)
    cfg["axes_dims_rope"] = tuple(cfg["axes_dims_rope"])
    return FluxTransformer2DModel(**cfg)


def _vae(config: EnhancerConfig):
    from diffusers import AutoencoderKL

    cfg = {k: (tuple(v) if isinstance(v, list) else v) for k, v in config.vae.items()}
    return AutoencoderKL(**cfg)


def build_enhancer(config: EnhancerConfig, *, seed: int = 0,
                   prompts: Mapping[str, PromptEmbedding] | None = None) -> Enhancer:
    """An enhancer with random weights (diffusers' initialisation under ``seed``; the global RNG is
    left as it was), widened as :func:`widen_transformer` does: what tests, the CPU demo and GPU
    timings use. Real weights come from :meth:`Enhancer.from_pretrained`."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        transformer = _base_transformer(config)
        vae = _vae(config)
    widen_transformer(transformer, config.packed_channels)
    return Enhancer(transformer, vae, config, prompts)


# ----------------------------------------------------------------------------- bytes (the store)

def enhancer_to_bytes(model: Enhancer) -> bytes:
    """The whole enhancer as safetensors bytes (the stored artifact): every weight (float32 unless
    the model is in another dtype) plus :class:`EnhancerConfig` and the group names in the
    metadata. Same model, same bytes."""
    _reject_lora(model)
    tensors = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
    meta = {"format": ENHANCER_FORMAT, "config": model.config.model_dump_json(),
            "groups": json.dumps(model.groups)}
    return safetensors_bytes(tensors, meta)


def enhancer_from_bytes(data: bytes, *, device: str | torch.device = "cpu") -> Enhancer:
    """Inverse of :func:`enhancer_to_bytes`. The modules are built on the meta device and the stored
    tensors assigned, so no random initialisation of a large model is paid."""
    from safetensors.torch import load as st_load

    meta = safetensors_metadata(data)
    if meta.get("format") != ENHANCER_FORMAT:
        raise ValueError(f"not an enhancer (format {meta.get('format')!r})")
    config = EnhancerConfig.model_validate_json(meta["config"])
    tensors = st_load(data)
    with torch.device("meta"):
        transformer = _base_transformer(config)
        vae = _vae(config)
        widen_transformer(transformer, config.packed_channels)
        model = Enhancer(transformer, vae, config)
        for g in json.loads(meta["groups"]):
            model.set_prompt(g, PromptEmbedding.zeros(config))
    model.load_state_dict({k: v.to(device) for k, v in tensors.items()}, strict=True, assign=True)
    for name, p in model.named_parameters():
        p.requires_grad_(False)
    for name, b in model.named_buffers():
        if b.is_meta:  # pragma: no cover - no such buffer in diffusers 0.42's Flux/VAE
            raise ValueError(f"buffer {name} was not stored")
    return model


def _reject_lora(model: Enhancer) -> None:
    if any(isinstance(m, LoRALinear) for m in model.modules()):
        raise ValueError("the model still holds LoRA adapters: merge them first (lora.merge_lora)")


# ------------------------------------------------------------------------- conditions, targets

def encode_conditions(model: Enhancer, lq: torch.Tensor, warped_prev: torch.Tensor | None,
                      mask: torch.Tensor | None, keep: torch.Tensor | None = None) -> torch.Tensor:
    """The four condition latents (slots 2-5), concatenated on channels.

    Args:
        lq: ``[B, 4, H, W]`` LQ RGBA (linear RGB, alpha in [0, 1]); H, W multiples of 16.
        warped_prev: ``[B, 4, H, W]`` warped previous output (only its RGB is encoded), or None.
        mask: ``[B, 1, H, W]`` validity in [0, 1], or None.
        keep: ``[B]`` bool, which samples have temporal conditions (training's dropout); None = all
            when ``warped_prev`` is given.
    Returns:
        ``[B, 4C, H/8, W/8]`` (C = 16): LQ RGB, LQ alpha, warped previous output, validity mask.
        The last two are **zero latents** (not the latents of black images) where absent: the
        first frame, or a dropped sample, so their ``x_embedder`` columns contribute nothing.
    """
    vae = model.vae
    parts = [encode(vae, rgb_to_vae(lq[:, :3])), encode(vae, gray_to_vae(lq[:, 3:4]))]
    if warped_prev is None:
        z = torch.zeros_like(parts[0])
        parts += [z, z]
    else:
        if mask is None:
            raise ValueError("warped_prev needs its validity mask")
        w = encode(vae, rgb_to_vae(warped_prev[:, :3]))
        m = encode(vae, gray_to_vae(mask))
        if keep is not None:
            k = keep.to(w.device, w.dtype).view(-1, 1, 1, 1)
            w, m = w * k, m * k
        parts += [w, m]
    return torch.cat(parts, dim=1)


def encode_target(model: Enhancer, hq: torch.Tensor) -> torch.Tensor:
    """Clean latents ``x0`` of HQ RGBA ``[B, 4, H, W]``: ``[B, 2C, H/8, W/8]`` (RGB latent, then the
    alpha latent)."""
    vae = model.vae
    return torch.cat([encode(vae, rgb_to_vae(hq[:, :3])), encode(vae, gray_to_vae(hq[:, 3:4]))], dim=1)


def decode_rgba(model: Enhancer, latents: torch.Tensor) -> torch.Tensor:
    """``[B, 2C, h, w]`` (RGB latent, alpha latent) -> RGBA ``[B, 4, 8h, 8w]``: linear RGB
    (unclamped) and alpha in [0, 1], the two latents decoded independently."""
    c = model.config.latent_channels
    rgb = vae_to_rgb(decode(model.vae, latents[:, :c]))
    alpha = vae_to_gray(decode(model.vae, latents[:, c:]))
    return torch.cat([rgb, alpha], dim=1)


# ------------------------------------------------------------------------------------ forward

def predict_velocity(model: Enhancer, noisy: torch.Tensor, conditions: torch.Tensor,
                     sigma: torch.Tensor, ids: torch.Tensor,
                     prompt: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """The transformer's rectified-flow velocity (``noise - clean``) for packed tokens.

    Args:
        noisy: ``[B, N, 2L]`` packed noisy latents (slots 0-1: RGB, alpha).
        conditions: ``[B, N, 4L]`` packed condition latents (slots 2-5: LQ RGB, LQ alpha, warped
            previous output, validity mask; zeros where absent).
        sigma: ``[B]`` noise levels in [0, 1] (the transformer scales them by 1000).
        ids: ``[N, 3]`` :func:`image_ids` of the tokens.
        prompt: ``(pooled [P] or [B, P], sequence [S, D] or [B, S, D])``.
    Returns:
        ``[B, N, 2L]``: velocity of the RGB latent then of the alpha latent.
    """
    tr = model.transformer
    dt = tr.dtype
    b = noisy.shape[0]
    pooled, seq = prompt
    if pooled.ndim == 1:
        pooled = pooled.unsqueeze(0).expand(b, -1)
    if seq.ndim == 2:
        seq = seq.unsqueeze(0).expand(b, -1, -1)
    hidden = torch.cat([noisy, conditions], dim=-1).to(dt)
    txt_ids = torch.zeros(seq.shape[1], 3, device=hidden.device, dtype=dt)
    guidance = None
    if tr.config.guidance_embeds:
        guidance = torch.full((b,), float(model.config.guidance), device=hidden.device, dtype=dt)
    out = tr(hidden_states=hidden, encoder_hidden_states=seq.to(dt), pooled_projections=pooled.to(dt),
             timestep=sigma.to(device=hidden.device, dtype=dt), img_ids=ids.to(hidden.device, dt),
             txt_ids=txt_ids, guidance=guidance, return_dict=False)[0]
    return out
