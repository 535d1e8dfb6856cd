"""Low-rank adapters (LoRA) for the Detail Enhancer's Flux transformer.

``LoRALinear`` wraps a frozen ``nn.Linear`` as ``W x + (alpha / r) B A x`` with ``A [r, in]``
Kaiming-uniform and ``B [out, r]`` zero, so a model with fresh adapters computes exactly what it
computed before. :func:`add_lora` puts adapters on the attention and feed-forward linears of every
block (:data:`LORA_TARGETS`, the target list of diffusers' Flux LoRA scripts); :func:`merge_lora`
folds them back into the weights. Training (which tensors learn, the optimiser, checkpoints) is
:mod:`volcap_core.enhance.training`'s.

Our own rather than peft: peft pulls ``transformers`` and ``accelerate`` in, and its adapters would
have to be serialised and re-created for bit-identical resumption anyway.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["LORA_TARGETS", "LoRALinear", "add_lora", "merge_lora"]

#: Linear layers (module-name suffixes inside ``transformer_blocks`` / ``single_transformer_blocks``)
#: that get LoRA adapters: attention q/k/v/out of both streams, the feed-forward layers, and the
#: single blocks' MLP in and joint out projections.
LORA_TARGETS = ("attn.to_q", "attn.to_k", "attn.to_v", "attn.to_out.0", "attn.add_q_proj",
                "attn.add_k_proj", "attn.add_v_proj", "attn.to_add_out", "ff.net.0.proj", "ff.net.2",
                "ff_context.net.0.proj", "ff_context.net.2", "proj_mlp", "proj_out")


class LoRALinear(nn.Module):
    """``base(x) + scale * B(A(x))`` with ``A [r, in]``, ``B [out, r]``, ``scale = alpha / r``.
    ``A`` starts Kaiming-uniform (bound ``1/sqrt(in)``, as ``nn.Linear`` and peft), ``B`` at zero."""

    def __init__(self, base: nn.Linear, rank: int, alpha: float, generator: torch.Generator):
        super().__init__()
        self.base = base
        self.base.requires_grad_(False)
        self.rank, self.scale = rank, alpha / rank
        bound = 1.0 / math.sqrt(base.in_features)
        a = (torch.rand(rank, base.in_features, generator=generator) * 2.0 - 1.0) * bound
        # float32 adapters on a bfloat16 base (frozen_dtype): low-precision master weights would
        # lose most small Adam updates
        kw = {"device": base.weight.device, "dtype": torch.promote_types(base.weight.dtype, torch.float32)}
        self.lora_A = nn.Parameter(a.to(**kw))
        self.lora_B = nn.Parameter(torch.zeros(base.out_features, rank, **kw))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.base(x) + F.linear(F.linear(x, self.lora_A), self.lora_B) * self.scale

    def merged(self) -> nn.Linear:
        """The base layer with the adapter folded in (``W + scale B A``)."""
        with torch.no_grad():
            self.base.weight.add_((self.lora_B @ self.lora_A) * self.scale)
        return self.base


def _lora_sites(transformer) -> list[tuple[nn.Module, str, nn.Linear]]:
    sites = []
    for blocks in (transformer.transformer_blocks, transformer.single_transformer_blocks):
        for block in blocks:
            for name, mod in block.named_modules():
                if isinstance(mod, nn.Linear) and name in LORA_TARGETS:
                    parent_name, _, attr = name.rpartition(".")
                    sites.append((block.get_submodule(parent_name) if parent_name else block, attr, mod))
    return sites


def add_lora(model: nn.Module, rank: int, alpha: float | None = None, *,
             generator: torch.Generator | None = None) -> int:
    """Wrap every :data:`LORA_TARGETS` linear of ``model.transformer``'s blocks (an
    :class:`~volcap_core.enhance.model.Enhancer`'s Flux transformer) in a :class:`LoRALinear`, each
    ``A`` drawn from ``generator`` in block order (in place; already wrapped layers are left alone).
    ``alpha`` None: the rank. Returns the number of adapters added."""
    gen = generator or torch.Generator().manual_seed(0)
    n = 0
    for parent, attr, mod in _lora_sites(model.transformer):
        setattr(parent, attr, LoRALinear(mod, rank, float(alpha or rank), gen))
        n += 1
    return n


def merge_lora(model: nn.Module) -> int:
    """Fold every adapter of ``model.transformer`` into its base weight and put the plain
    ``nn.Linear`` back (in place), so the model saves as a plain enhancer. Returns the number merged."""
    n = 0
    for name, mod in list(model.transformer.named_modules()):
        if isinstance(mod, LoRALinear):
            parent_name, _, attr = name.rpartition(".")
            setattr(model.transformer.get_submodule(parent_name), attr, mod.merged())
            n += 1
    return n
