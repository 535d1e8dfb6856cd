"""Compiled CPU colours of the projection's survivors (numba): SH at the view direction, linearised,
forward and backward in one loop each.

:func:`survivor_colours_numba` gives what
``gaussian_colours(gaussians.select(ids), camera)`` (:mod:`volcap_core.splat.render`) gives, under
the same rules: the direction camera centre -> Gaussian normalised with eps 1e-12
(:func:`~volcap_core.splat.sh.sh_to_colour`; a zero direction gives the DC colour), the real SH
basis of degrees 0..3 in the 3DGS / gsplat convention, ``+ 0.5``, then for
``colour_space="srgb_unbounded"`` the unbounded sRGB decode of :mod:`volcap_core.colour`
(``x / 12.92`` below 0.04045, ``((x + 0.055) / 1.055)^2.4`` from it on); ``"linear"`` colours as
they are. It reads the survivors' SH rows and means in place (``ids`` into the evaluated set)
instead of gathering them first.

Why it exists: on a CPU the PyTorch colours are a gather of the survivors' SH rows (48 floats a
Gaussian at degree 3) and means, ~40 small ops over the survivors for the basis, the contraction
and the decode, and autograd's scatter of it all back, on the one thread a reproducible training
gives torch. Figures: ``docs/benchmarks.md``, "Rasterizer".

Gradients, from each survivor's colour back to its SH rows and mean (what autograd does to the
PyTorch ops, so the two agree to float32 rounding):

* decode: ``∂x = ∂c / 12.92`` below the break, ``∂c · 2.4 b^1.4 / 1.055`` with
  ``b = (x + 0.055) / 1.055`` from it on;
* ``c = Σ_k Y_k(d) sh_k + 0.5``: ``∂sh_k = Y_k(d) ∂c``, ``∂Y_k = ⟨sh_k, ∂c⟩``, then ``∂d`` by the
  basis polynomials' partial derivatives (gsplat's ``sh_coeffs_to_color_fast_vjp``);
* ``d = v / max(|v|, 1e-12)``, ``v = μ - centre``: ``∂μ = (∂d - d ⟨d, ∂d⟩) / |v|``, or
  ``∂d / 1e-12`` below the eps. Degree 0 has no direction and gives the means no gradient.

Parallel over survivors (``numba.prange``) on :func:`~volcap_core.kernel_threads.kernel_threads`
threads; each survivor's colour and gradient rows are computed and written by one thread (the ids
are distinct), so results do not depend on the thread count. float32 CPU tensors only;
``cache=True`` as the compiled projection (:mod:`volcap_core.splat.project_numba`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from volcap_core.colour import _A, _GAMMA, _SLOPE, SRGB_DECODE_BREAK
from volcap_core.kernel_threads import kernel_threads_scope
from volcap_core.splat.kernel_tensors import require_float32_cpu
from volcap_core.splat.sh import _C1, _C2, _C3, SH_C0

__all__ = ["survivor_colours_numba"]

_f = np.float32
_ZERO, _HALF, _ONE, _TWO = _f(0.0), _f(0.5), _f(1.0), _f(2.0)
_DIR_EPS = _f(1e-12)
_Y0, _Y1 = _f(SH_C0), _f(_C1)
_Y2 = tuple(_f(c) for c in _C2)
_Y3 = tuple(_f(c) for c in _C3)
_BREAK, _OFFSET, _SCALE = _f(SRGB_DECODE_BREAK), _f(_A), _f(1.0 + _A)
_SLOPE32, _GAMMA32, _GAMMA_M1 = _f(_SLOPE), _f(_GAMMA), _f(_GAMMA - 1.0)
_INV_SLOPE = _ONE / _SLOPE32
_JIT = dict(cache=True, error_model="numpy")      # IEEE division (x/0 = inf), as torch: no raise


@numba.njit(**_JIT)
def _basis(x, y, z, K):
    """The K (1, 4, 9 or 16) SH basis values at unit direction ``(x, y, z)`` as a 16-tuple (the
    unused ones 0), in the PyTorch order of products."""
    b1 = b2 = b3 = b4 = b5 = b6 = b7 = b8 = _ZERO
    b9 = b10 = b11 = b12 = b13 = b14 = b15 = _ZERO
    if K > 1:
        b1, b2, b3 = -_Y1 * y, _Y1 * z, -_Y1 * x
    if K > 4:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        b4, b5 = _Y2[0] * xy, _Y2[1] * yz
        b6 = _Y2[2] * (_TWO * zz - xx - yy)
        b7, b8 = _Y2[3] * xz, _Y2[4] * (xx - yy)
        if K > 9:
            b9 = _Y3[0] * y * (_f(3.0) * xx - yy)
            b10 = _Y3[1] * xy * z
            b11 = _Y3[2] * y * (_f(4.0) * zz - xx - yy)
            b12 = _Y3[3] * z * (_TWO * zz - _f(3.0) * xx - _f(3.0) * yy)
            b13 = _Y3[4] * x * (_f(4.0) * zz - xx - yy)
            b14 = _Y3[5] * z * (xx - yy)
            b15 = _Y3[6] * x * (xx - _f(3.0) * yy)
    return (_Y0, b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11, b12, b13, b14, b15)


@numba.njit(**_JIT)
def _direction(means, i, centre):
    """The unit direction centre -> mean ``i`` (eps 1e-12), and the norm's divisor."""
    vx, vy, vz = means[i, 0] - centre[0], means[i, 1] - centre[1], means[i, 2] - centre[2]
    norm = np.float32(math.sqrt(vx * vx + vy * vy + vz * vz))
    n = max(norm, _DIR_EPS)
    return vx / n, vy / n, vz / n, norm, n


@numba.njit(**_JIT)
def _raw_colour(sh, i, c, B):
    """``Σ_k B_k sh[i, k, c] + 0.5``, the sum in order of k."""
    acc = _ZERO
    for k in range(sh.shape[1]):
        acc += B[k] * sh[i, k, c]
    return acc + _HALF


@numba.njit(**_JIT)
def _row_dot(sh, i, k, g0, g1, g2):
    """``⟨sh[i, k], (g0, g1, g2)⟩``."""
    return sh[i, k, 0] * g0 + sh[i, k, 1] * g1 + sh[i, k, 2] * g2


@numba.njit(parallel=True, **_JIT)
def _forward(ids, sh, means, centre, decode, out, d_out):
    """``out [S, 3]``: the colours of the Gaussians ``ids [S]`` of ``sh [M, K, 3]`` and
    ``means [M, 3]``; ``d_out [S, 3]`` the decode's derivative at each (1 without decode), so the
    backward evaluates no power."""
    K = sh.shape[1]
    for s in numba.prange(ids.shape[0]):
        i = ids[s]
        x = y = z = _ZERO
        if K > 1:
            x, y, z, _, _ = _direction(means, i, centre)
        B = _basis(x, y, z, K)
        for c in range(3):
            v = _raw_colour(sh, i, c, B)
            d = _ONE
            if decode:
                if v < _BREAK:
                    v, d = v / _SLOPE32, _INV_SLOPE
                else:
                    b = (max(v, _BREAK) + _OFFSET) / _SCALE
                    v = np.float32(b ** _GAMMA32)
                    d = _GAMMA32 * np.float32(b ** _GAMMA_M1) / _SCALE
            out[s, c] = v
            d_out[s, c] = d


@numba.njit(parallel=True, **_JIT)
def _backward(ids, sh, means, centre, d_out, g_out, g_sh, g_means):
    """Writes rows ``ids[s]`` of ``g_sh [M, K, 3]`` and ``g_means [M, 3]`` (zeros in) from the
    colours' gradient ``g_out [S, 3]`` and the decode's derivative ``d_out [S, 3]``. Recomputes
    the basis."""
    K = sh.shape[1]
    for s in numba.prange(ids.shape[0]):
        i = ids[s]
        x = y = z = norm = _ZERO
        n = _ONE
        if K > 1:
            x, y, z, norm, n = _direction(means, i, centre)
        B = _basis(x, y, z, K)
        g0, g1, g2 = g_out[s, 0] * d_out[s, 0], g_out[s, 1] * d_out[s, 1], g_out[s, 2] * d_out[s, 2]
        for k in range(K):
            g_sh[i, k, 0] = B[k] * g0
            g_sh[i, k, 1] = B[k] * g1
            g_sh[i, k, 2] = B[k] * g2
        if K == 1:
            continue
        # ∂Y_k = <sh_k, ∂c>, then through each basis polynomial's partial derivatives
        r1, r2, r3 = _row_dot(sh, i, 1, g0, g1, g2), _row_dot(sh, i, 2, g0, g1, g2), _row_dot(
            sh, i, 3, g0, g1, g2)
        gx, gy, gz = -_Y1 * r3, -_Y1 * r1, _Y1 * r2
        if K > 4:
            r4, r5, r6 = (_row_dot(sh, i, 4, g0, g1, g2), _row_dot(sh, i, 5, g0, g1, g2),
                          _row_dot(sh, i, 6, g0, g1, g2))
            r7, r8 = _row_dot(sh, i, 7, g0, g1, g2), _row_dot(sh, i, 8, g0, g1, g2)
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            gx += (_Y2[0] * y * r4 - _TWO * _Y2[2] * x * r6 + _Y2[3] * z * r7
                   + _TWO * _Y2[4] * x * r8)
            gy += (_Y2[0] * x * r4 + _Y2[1] * z * r5 - _TWO * _Y2[2] * y * r6
                   - _TWO * _Y2[4] * y * r8)
            gz += _Y2[1] * y * r5 + _f(4.0) * _Y2[2] * z * r6 + _Y2[3] * x * r7
            if K > 9:
                r9, r10, r11 = (_row_dot(sh, i, 9, g0, g1, g2), _row_dot(sh, i, 10, g0, g1, g2),
                                _row_dot(sh, i, 11, g0, g1, g2))
                r12, r13 = _row_dot(sh, i, 12, g0, g1, g2), _row_dot(sh, i, 13, g0, g1, g2)
                r14, r15 = _row_dot(sh, i, 14, g0, g1, g2), _row_dot(sh, i, 15, g0, g1, g2)
                gx += (_f(6.0) * _Y3[0] * xy * r9 + _Y3[1] * yz * r10
                       - _TWO * _Y3[2] * xy * r11 - _f(6.0) * _Y3[3] * xz * r12
                       + _Y3[4] * (_f(4.0) * zz - _f(3.0) * xx - yy) * r13
                       + _TWO * _Y3[5] * xz * r14 + _Y3[6] * _f(3.0) * (xx - yy) * r15)
                gy += (_Y3[0] * _f(3.0) * (xx - yy) * r9 + _Y3[1] * xz * r10
                       + _Y3[2] * (_f(4.0) * zz - xx - _f(3.0) * yy) * r11
                       - _f(6.0) * _Y3[3] * yz * r12 - _TWO * _Y3[4] * xy * r13
                       - _TWO * _Y3[5] * yz * r14 - _f(6.0) * _Y3[6] * xy * r15)
                gz += (_Y3[1] * xy * r10 + _f(8.0) * _Y3[2] * yz * r11
                       + _Y3[3] * (_f(6.0) * zz - _f(3.0) * xx - _f(3.0) * yy) * r12
                       + _f(8.0) * _Y3[4] * xz * r13 + _Y3[5] * (xx - yy) * r14)
        # d = v / max(|v|, eps)
        if norm >= _DIR_EPS:
            dot = x * gx + y * gy + z * gz
            gx, gy, gz = gx - x * dot, gy - y * dot, gz - z * dot
        g_means[i, 0], g_means[i, 1], g_means[i, 2] = gx / n, gy / n, gz / n


class _SurvivorColours(torch.autograd.Function):
    """The compiled colours as an autograd node: ``[S, 3]`` from ``sh [M, K, 3]`` and
    ``means [M, 3]`` at ``ids [S]``; keeps numpy views of the inputs and the decode's derivative
    (the backward recomputes the basis per survivor)."""

    @staticmethod
    def forward(ctx, sh, means, ids, centre: np.ndarray, decode: bool):
        a_sh, a_means = (t.detach().contiguous().numpy() for t in (sh, means))
        a_ids = ids.detach().contiguous().numpy()
        out, d_out = np.empty((a_ids.shape[0], 3), np.float32), np.empty((a_ids.shape[0], 3),
                                                                         np.float32)
        with kernel_threads_scope():
            _forward(a_ids, a_sh, a_means, centre, decode, out, d_out)
        ctx.arrays = (a_ids, a_sh, a_means, centre, d_out)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g_out):
        a_ids, a_sh, a_means, centre, d_out = ctx.arrays
        g = g_out.detach().to(torch.float32).contiguous().numpy()
        g_sh, g_means = np.zeros_like(a_sh), np.zeros_like(a_means)
        with kernel_threads_scope():
            _backward(a_ids, a_sh, a_means, centre, d_out, g, g_sh, g_means)
        directional = a_sh.shape[1] > 1                     # degree 0 does not see the means
        return (torch.from_numpy(g_sh) if ctx.needs_input_grad[0] else None,
                torch.from_numpy(g_means) if ctx.needs_input_grad[1] and directional else None,
                None, None, None)


def survivor_colours_numba(sh: torch.Tensor, means: torch.Tensor, ids: torch.Tensor,
                           centre: torch.Tensor, *, linearise: bool) -> torch.Tensor:
    """Linear colours ``[S, 3]`` of the Gaussians ``ids`` seen from ``centre``, with the compiled
    kernels: the values and gradients of ``gaussian_colours`` on those Gaussians.

    Args:
        sh: ``[M, K, 3]`` SH coefficients of the evaluated set, K in (1, 4, 9, 16).
        means: ``[M, 3]`` their world positions (metres).
        ids: ``[S]`` int64 distinct rows of ``sh`` / ``means`` (the projection's survivors).
        centre: ``[3]`` camera centre in world coordinates (cast to float32 as the PyTorch path
            casts it to the means').
        linearise: decode the SH colour from unbounded sRGB (``colour_space="srgb_unbounded"``);
            False returns it as is (``"linear"``).
    Returns:
        ``[S, 3]`` float32 colours, differentiable to ``sh`` and ``means`` (rows not in ``ids``
        get exactly zero gradient).
    Raises:
        ValueError: a tensor not float32 or not on the CPU, or an unsupported K.
    """
    require_float32_cpu("colour kernel", {"sh": sh, "means": means})
    if sh.shape[1] not in (1, 4, 9, 16):
        raise ValueError(f"unsupported number of SH coefficients {sh.shape[1]}")
    c = centre.detach().to(torch.float32).cpu().numpy()
    return _SurvivorColours.apply(sh, means, ids.to(torch.int64), c, bool(linearise))
