"""Compiled CPU Adam (numba): :func:`volcap_core.checkpoint.adam_step`'s update of one parameter,
bit for bit the update of its torch code, in two fused passes around torch's square root.

Why it exists: on a CPU, training runs torch on one thread (reproducibility), and the torch update
walks each parameter and its moments ~8 times (``mul_``, ``add_``, ``addcmul_``, a division,
``sqrt_``, ``add_``, ``addcdiv_`` or a product with the tensor rate). Here one pass updates the
moments and writes the corrected second moment, torch takes its square root, and a second pass
updates the parameter. Each element is computed from its own inputs only, so the bits do not
depend on the thread count: a parameter of at least :data:`_PARALLEL_MIN` elements is split over
:func:`~volcap_core.kernel_threads.kernel_threads` threads (all cores), a smaller one runs on the
calling thread (:func:`_threads_for`). Figures: ``docs/benchmarks.md`` ("Rasterizer", "The
compiled optimiser").

The same bits as torch: every operation is the float32 operation torch's CPU kernels perform, in
their order (measured against float64 references). Two of them are fused multiply-adds in torch:
``add_(g, alpha=a)`` is ``fma(g, a, m)`` in its vectorised kernel and ``addcmul_(g, g, value=c)``
rounds ``c·g`` and then adds ``(c·g)·g`` in one fma; they are written here as explicit fmas
(:func:`_fma`, LLVM's ``llvm.fma.f32``), while numba without ``fastmath`` contracts nothing else
(each ``a * b + c`` stays two roundings, as torch's separate kernels round them). Torch fuses so
only where its CPU kernels are built with FMA (capability AVX2 or AVX512): on any other CPU
:func:`takes` declines and the torch code runs. The square root stays torch's: its float32
``sqrt`` (MKL's) is not the correctly rounded one numba computes (1 ulp apart on ~0.7 % of
values), and its bits do not depend on the array's length, offset or thread count (checked).
Scalars are rounded to float32 first, as torch's kernels do with a Python scalar on a float32
tensor.

Imports numba: :mod:`volcap_core.checkpoint` imports this module only when it updates a CPU
parameter.
"""

from __future__ import annotations

import contextlib

import numba
import numpy as np
import torch
from numba.core import types
from numba.extending import intrinsic

from volcap_core.kernel_threads import kernel_threads_scope

__all__ = ["adam_update", "takes"]

#: the fewest elements a parameter has for its update to run on all the kernels' threads (fewer: on
#: the calling thread; the bits are the same either way): 8 M, whose serial pass (~5 ms) outlasts
#: waking a thread whose core another process holds. Every parameter of the demo's model (80 000
#: Gaussians, the largest its 3.6 M SH coefficients) runs on the calling thread.
_PARALLEL_MIN = 1 << 23

#: torch's CPU capabilities whose kernels are built with FMA, so ``add_(alpha)`` and ``addcmul_``
#: round once (the update written here); elsewhere the torch code runs
_FUSED_CAPABILITIES = frozenset({"AVX2", "AVX512"})


@intrinsic
def _fma(typingctx, a, b, c):
    """``a·b + c`` rounded once (float32), whatever the CPU: LLVM's ``llvm.fma.f32``, which is
    never split into a multiply and an add (a CPU without FMA computes it in software)."""
    if not all(t == types.float32 for t in (a, b, c)):
        return None

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return types.float32(types.float32, types.float32, types.float32), codegen


@numba.njit(cache=True, parallel=True)
def _moments(g, m, v, q, b1, a1, b2, a2, bc2):
    """The moments' update and the corrected second moment, on flat float32 arrays: torch's
    ``m.mul_(b1).add_(g, alpha=a1)``, ``v.mul_(b2).addcmul_(g, g, value=a2)`` and ``q = v / bc2``
    (whose square root torch then takes)."""
    for i in numba.prange(g.shape[0]):
        gi = g[i]
        mi = _fma(gi, a1, m[i] * b1)
        vi = _fma(a2 * gi, gi, v[i] * b2)
        m[i] = mi
        v[i] = vi
        q[i] = vi / bc2


@numba.njit(cache=True, parallel=True)
def _step_float_rate(p, m, root, eps, step_size):
    """``p += (step_size · m) / (root + eps)`` on flat float32 arrays: torch's ``add_(eps)`` and
    ``addcdiv_(m, denom, value=step_size)`` (``step_size = -lr / bc1``)."""
    for i in numba.prange(p.shape[0]):
        p[i] = p[i] + (step_size * m[i]) / (root[i] + eps)


@numba.njit(cache=True, parallel=True)
def _step_tensor_rate(p, m, root, eps, rate):
    """``p -= m / (root + eps) · rate`` on ``[rows, K]`` float32 arrays: torch's ``add_(eps)`` and
    ``p.sub_(m / denom * (lr / bc1))``; ``rate [R, K]`` is ``lr / bc1`` with R = 1 (the same rate
    for every row) or R = rows."""
    per_row = np.int64(rate.shape[0] > 1)
    for r in numba.prange(p.shape[0]):
        rr = r * per_row
        for k in range(p.shape[1]):
            p[r, k] = p[r, k] - m[r, k] / (root[r, k] + eps) * rate[rr, k]


def takes(p: torch.Tensor, g: torch.Tensor, m: torch.Tensor, v: torch.Tensor,
          lr: float | torch.Tensor) -> bool:
    """True when :func:`adam_update` gives the torch code's bits for this parameter: the
    parameter, its gradient and moments float32, contiguous, of one shape, on the CPU (and a tensor
    rate float32 on the CPU), and torch's CPU kernels fused as this module's are (capability AVX2
    or AVX512)."""
    tensors = (p, g, m, v)
    if not all(t.device.type == "cpu" and t.layout == torch.strided and t.dtype == torch.float32
               and t.is_contiguous() and t.shape == p.shape for t in tensors):
        return False
    if isinstance(lr, torch.Tensor) and not (lr.device.type == "cpu" and lr.dtype == torch.float32):
        return False
    return torch.backends.cpu.get_cpu_capability() in _FUSED_CAPABILITIES


def adam_update(p: torch.Tensor, g: torch.Tensor, m: torch.Tensor, v: torch.Tensor,
                lr: float | torch.Tensor, *, betas: tuple[float, float], bc1: float, bc2: float,
                eps: float) -> None:
    """One Adam update of ``p`` and its moments ``m``, ``v`` in place, the update of
    :func:`volcap_core.checkpoint.adam_step` for tensors :func:`takes` accepts.

    Args:
        p, g, m, v: the parameter, its gradient and moments (same shape, float32, contiguous, CPU).
        lr: a float, or a float32 tensor broadcastable to ``p`` (e.g. ``[1, n, 1]``).
        betas: Adam's ``(b1, b2)``. bc1, bc2: the bias corrections ``1 - b^step``. eps: added to
            the corrected ``sqrt(v)``.
    """
    if p.numel() == 0:
        return
    b1, b2 = betas
    f32 = np.float32
    # the corrected second moment, then its square root by torch (module doc)
    root = torch.empty_like(p)
    pa, ga, ma, va, ra = (t.detach().numpy().reshape(-1) for t in (p, g, m, v, root))
    with _threads_for(p):
        _moments(ga, ma, va, ra, f32(b1), f32(1.0 - b1), f32(b2), f32(1.0 - b2), f32(bc2))
    root.sqrt_()
    with _threads_for(p):
        if isinstance(lr, torch.Tensor):
            rows = p.shape[0] if p.ndim else 1
            # lr / bc1 in torch: the bits of the torch code's rate; then one row of it when it
            # is the same for every row of p (the trainer's [1, n, 1]: sliced before the reshape,
            # which copies), else a row per row of p
            rate = (lr / bc1).expand(p.shape)
            if p.ndim and _same_rows(lr, p):
                rate = rate[:1]
            rate = rate.reshape(rate.shape[0] if rate.ndim else 1, -1).contiguous().numpy()
            _step_tensor_rate(pa.reshape(rows, -1), ma.reshape(rows, -1), ra.reshape(rows, -1),
                              f32(eps), rate)
        else:
            _step_float_rate(pa, ma, ra, f32(eps), f32(-lr / bc1))
    # the writes went through numpy: tell autograd, as torch's in-place ops do
    torch.autograd.graph.increment_version([p, m, v])


@contextlib.contextmanager
def _threads_for(p: torch.Tensor):
    """:func:`~volcap_core.kernel_threads.kernel_threads_scope`, on one thread for a parameter of
    fewer than :data:`_PARALLEL_MIN` elements: its update is shorter than waking the other threads
    can be when another process holds their core (~6 ms a launch measured on the shared 2-core
    machine, microseconds on a quiet one), and a Poly4DGS model has a dozen parameters, each
    updated by two kernels (on all cores, the demo segment's 150 steps took 61 s instead of 43
    beside another training)."""
    with kernel_threads_scope():
        if p.numel() < _PARALLEL_MIN:
            numba.set_num_threads(1)
        yield


def _same_rows(lr: torch.Tensor, p: torch.Tensor) -> bool:
    """True when the rate ``lr`` broadcast to ``p`` (at least 1-D) is the same in every row of
    ``p`` (its first dimension is missing or 1)."""
    return lr.ndim < p.ndim or lr.shape[0] == 1
