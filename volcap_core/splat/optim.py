"""A functional Adam over a dict of named tensors.

Why not ``torch.optim.Adam``: MCMC relocation resets the moments of individual Gaussians and
growth appends rows, which with torch's optimizer means reaching into ``optimizer.state`` keyed by
tensor identity; checkpoints must be safetensors (no pickle); and learning rates are a pure function
of the step (no scheduler state). Here the state is two dicts of tensors and an int. The update is
exactly ``torch.optim.Adam``'s (bias-corrected, ``eps`` added to the corrected ``sqrt(v)``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["AdamState", "adam_step", "exponential_lr"]


@dataclass
class AdamState:
    """First and second moments per parameter name (same shapes as the parameters), and the
    number of steps taken (one count for all: every group steps together)."""

    exp_avg: dict[str, torch.Tensor] = field(default_factory=dict)
    exp_avg_sq: dict[str, torch.Tensor] = field(default_factory=dict)
    step: int = 0

    @classmethod
    def zeros_like(cls, params: dict[str, torch.Tensor]) -> "AdamState":
        return cls({k: torch.zeros_like(v) for k, v in params.items()},
                   {k: torch.zeros_like(v) for k, v in params.items()}, 0)


@torch.no_grad()
def adam_step(params: dict[str, torch.Tensor], lrs: dict[str, float | torch.Tensor],
              state: AdamState, *, betas: tuple[float, float] = (0.9, 0.999),
              eps: float = 1e-15) -> None:
    """One Adam update in place on every ``params[name]`` that has a ``.grad`` and a learning
    rate ``lrs[name]``: a float (0 or absent = frozen) or a tensor broadcastable to the parameter
    (e.g. ``[1, n, 1]``: one rate per polynomial order). ``eps = 1e-15`` as in 3DGS (Gaussian
    parameters have tiny gradients; a larger eps would silently lower their learning rate)."""
    state.step += 1
    b1, b2 = betas
    bc1 = 1.0 - b1 ** state.step
    bc2 = 1.0 - b2 ** state.step
    for name, p in params.items():
        lr = lrs.get(name, 0.0)
        if p.grad is None or (not isinstance(lr, torch.Tensor) and lr <= 0.0):
            continue
        g = p.grad
        m, v = state.exp_avg[name], state.exp_avg_sq[name]
        m.mul_(b1).add_(g, alpha=1.0 - b1)
        v.mul_(b2).addcmul_(g, g, value=1.0 - b2)
        denom = (v / bc2).sqrt_().add_(eps)
        if isinstance(lr, torch.Tensor):
            p.sub_(m / denom * (lr / bc1))
        else:
            p.addcdiv_(m, denom, value=-lr / bc1)


def exponential_lr(lr_init: float, lr_final: float, step: int, max_steps: int) -> float:
    """Log-linear decay from ``lr_init`` at step 0 to ``lr_final`` at ``max_steps`` (3DGS's position
    schedule: 1.6e-4 -> 1.6e-6 times the scene scale), constant after."""
    if max_steps <= 0 or lr_init == lr_final:
        return lr_init
    f = min(max(step / max_steps, 0.0), 1.0)
    return float(lr_init * (lr_final / lr_init) ** f)
