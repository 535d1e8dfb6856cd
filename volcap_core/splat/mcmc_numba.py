"""Compiled CPU step of 3DGS-MCMC's position noise (numba): the covariance ``Σ = R diag(s)² Rᵀ``
of each Gaussian, its product with the gated draw and the move of ``μ_0``, fused in one pass, bit
for bit what :func:`volcap_core.splat.mcmc.inject_noise`'s torch code computes.

Why it exists: the torch code builds the covariances of all N Gaussians through ~30 small tensor
operations (:func:`~volcap_core.splat.rasterize.quat_scale_to_covar`) and two batched 3×3
products, each a pass over memory on the one thread reproducible training gives torch. Here each
Gaussian is read and written once, parallel over the Gaussians on
:func:`~volcap_core.kernel_threads.kernel_threads` threads (all cores); each Gaussian's move depends
only on its own inputs, so the bits do not depend on the thread count (a model of fewer than
:data:`_PARALLEL_MIN` Gaussians moves on the calling thread). Figures:
``docs/benchmarks.md`` ("Rasterizer", "The compiled optimiser").

The same bits as torch: every float32 operation is the one torch performs, in its order, and
numba without ``fastmath`` contracts none of them into a fused multiply-add (torch's kernels for
these operations do not fuse either, measured against float64 references): the quaternion's norm
is a sequential sum of squares from 0 and a correctly rounded square root, clamped to 1e-8
(``torch.nn.functional.normalize``); each entry of ``R`` is rounded as the tensor expressions of
``quat_scale_to_covar`` round it; each batched 3×3 product (``bmm``, which torch computes by a
plain loop at this size) sums its three products in order from 0. What this kernel does not
compute stays in torch, for the same reason: the gate's sigmoids and the scales' ``exp`` (torch's
vectorised ``exp`` is not the correctly rounded one numba would call) and the draws ``η`` (the
generator's stream).

Imports numba: :mod:`volcap_core.splat.mcmc` imports this module only when it moves float32 CPU
Gaussians.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from volcap_core.kernel_threads import kernel_threads_scope

__all__ = ["add_position_noise", "takes"]

_ZERO = np.float32(0.0)
_ONE = np.float32(1.0)
_TWO = np.float32(2.0)
#: the fewest Gaussians moved on all the kernels' threads (fewer: on the calling thread; the bits are
#: the same either way): 512 k, whose serial pass (~8 ms) outlasts waking a thread whose core
#: another process holds (~6 ms measured on the shared 2-core machine); the demo's 80 000 take 1.3 ms
_PARALLEL_MIN = 1 << 19
#: ``quat_scale_to_covar``'s normalisation eps: a zero quaternion gives R = I
_QUAT_EPS = np.float32(1e-8)


@numba.njit(cache=True, inline="always")
def _dot3(a0, a1, a2, b0, b1, b2):
    """``a·b`` as torch's small ``bmm`` sums it: from 0, in order, each step rounded."""
    acc = _ZERO
    acc += a0 * b0
    acc += a1 * b1
    acc += a2 * b2
    return acc


@numba.njit(cache=True, parallel=True)
def _add_noise(means, quats, scales, eta, gated_step):
    """``means[i] += Σ_i (η_i · gated_step[i])`` with ``Σ_i = R(q_i) diag(s_i)² R(q_i)ᵀ``.

    means ``[N, 3]`` (updated in place), quats ``[N, 4]`` wxyz (normalised here), scales
    ``[N, 3]`` standard deviations, eta ``[N, 3]``, gated_step ``[N]``; all float32."""
    for i in numba.prange(means.shape[0]):
        w, x, y, z = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        norm = _ZERO
        norm += w * w
        norm += x * x
        norm += y * y
        norm += z * z
        norm = np.sqrt(norm)
        if norm < _QUAT_EPS:                         # clamp_min: NaN stays NaN
            norm = _QUAT_EPS
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        # R row by row, each entry rounded as quat_scale_to_covar's tensor expressions round it
        r00 = _ONE - _TWO * (y * y + z * z)
        r01 = _TWO * (x * y - w * z)
        r02 = _TWO * (x * z + w * y)
        r10 = _TWO * (x * y + w * z)
        r11 = _ONE - _TWO * (x * x + z * z)
        r12 = _TWO * (y * z - w * x)
        r20 = _TWO * (x * z - w * y)
        r21 = _TWO * (y * z + w * x)
        r22 = _ONE - _TWO * (x * x + y * y)
        s0, s1, s2 = scales[i, 0], scales[i, 1], scales[i, 2]
        # M = R diag(s), Σ = M Mᵀ
        m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
        m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
        m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
        c00 = _dot3(m00, m01, m02, m00, m01, m02)
        c01 = _dot3(m00, m01, m02, m10, m11, m12)
        c02 = _dot3(m00, m01, m02, m20, m21, m22)
        c10 = _dot3(m10, m11, m12, m00, m01, m02)
        c11 = _dot3(m10, m11, m12, m10, m11, m12)
        c12 = _dot3(m10, m11, m12, m20, m21, m22)
        c20 = _dot3(m20, m21, m22, m00, m01, m02)
        c21 = _dot3(m20, m21, m22, m10, m11, m12)
        c22 = _dot3(m20, m21, m22, m20, m21, m22)
        k = gated_step[i]
        e0, e1, e2 = eta[i, 0] * k, eta[i, 1] * k, eta[i, 2] * k
        means[i, 0] = means[i, 0] + _dot3(c00, c01, c02, e0, e1, e2)
        means[i, 1] = means[i, 1] + _dot3(c10, c11, c12, e0, e1, e2)
        means[i, 2] = means[i, 2] + _dot3(c20, c21, c22, e0, e1, e2)


def takes(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, eta: torch.Tensor,
          gated_step: torch.Tensor) -> bool:
    """True when :func:`add_position_noise` gives the torch code's bits for these tensors: all
    float32 on the CPU, ``means`` contiguous (it is updated in place)."""
    return (all(t.device.type == "cpu" and t.dtype == torch.float32
                for t in (means, quats, scales, eta, gated_step))
            and means.is_contiguous())


def add_position_noise(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                       eta: torch.Tensor, gated_step: torch.Tensor) -> None:
    """``means += Σ (η · gated_step)`` in place, ``Σ = R diag(scales)² Rᵀ`` per Gaussian: the move
    of :func:`volcap_core.splat.mcmc.inject_noise` for tensors :func:`takes` accepts.

    Args:
        means: ``[N, 3]`` μ_0 (metres), updated in place.
        quats: ``[N, 4]`` wxyz, any norm (normalised with eps 1e-8, as
            :func:`~volcap_core.splat.rasterize.quat_scale_to_covar` does).
        scales: ``[N, 3]`` standard deviations (metres).
        eta: ``[N, 3]`` the standard normal draws.
        gated_step: ``[N]`` each Gaussian's gate times the step (1/metres).
    """
    m = means.detach().numpy()
    q, s, e, k = (t.detach().contiguous().numpy() for t in (quats, scales, eta, gated_step))
    with kernel_threads_scope():
        if means.shape[0] < _PARALLEL_MIN:
            numba.set_num_threads(1)
        _add_noise(m, q, s, e, k)
    # the write went through numpy: tell autograd, as torch's in-place add_ does
    torch.autograd.graph.increment_version(means)
