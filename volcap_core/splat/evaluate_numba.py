"""Compiled CPU slicing of a Poly4DGS model at time t (numba): the forward and backward of
:func:`~volcap_core.splat.model.evaluate` in a few loops over the Gaussians.

:func:`slice_poly4dgs_numba` takes a model's parameter tensors (``Poly4DGS.params``, the names and
shapes of :mod:`volcap_core.splat.model`'s module doc) and gives what ``evaluate`` gives, under the
same rules: ``dt = t - t0`` clamped to ``±max_abs_dt`` (t rounded to float32 first, as torch
subtracts a Python float from a float32 tensor); the opacity ``o_t = exp(logsigmoid(o) - ½ Σ_i
exp(min(log λ_i + 2i log max(|dt|, 1e-30), log_term_cap)))``; the Gaussians with ``o_t`` below
``min_opacity`` dropped (a NaN opacity too), ascending ``ids``; for the live ones the polynomials
``μ_0 + Σ_i μ_i dt^i`` (and the quaternion's and log-scale's), the quaternion normalised with eps
1e-8, the log-scale clamped to ``[log_scale_min, log_scale_max]`` and exponentiated, and the SH
rows ``sh0 | shN``. A model without ``t0`` (all degrees 0) has ``dt = 0``.

Why it exists: the PyTorch ``evaluate`` gathers ~10 tensors at the live ids (72 floats a Gaussian
at SH degree 3), evaluates each polynomial and the envelope in many small N-long ops, and autograd
scatters it all back (``index_put``): the largest items of a CPU training step's profile after the
compiled projection, on the one thread a reproducible training gives torch. Here one parallel loop
computes every Gaussian's opacity and the keep mask, a second gathers and evaluates the live ones,
and the backward is one loop writing each live Gaussian's rows of the parameters' full-size
gradients; it recomputes the polynomials and takes the exponentials' factors from the forward
(the transcendental functions, one call each per Gaussian, are most of the kernels' time).
Figures: ``docs/benchmarks.md``, "Rasterizer".

Gradients, from the outputs ``(means, quats, scales, opacities, sh)`` of each live Gaussian back to
its parameters (the chain of the forward in reverse, as autograd differentiates the PyTorch ops,
so the two paths agree to float32 rounding):

* polynomial ``v = v_0 + Σ_i v_i dt^i``: ``∂v_0 = ∂v``, ``∂v_i = ∂v dt^i``,
  ``∂dt += Σ_i ⟨∂v, v_i⟩ i dt^(i-1)``;
* quaternion ``q = p / max(|p|, 1e-8)``: ``∂p = (∂q - q ⟨q, ∂q⟩) / |p|``, or ``∂q / 1e-8`` below
  the eps; log-scale: ``∂s_log = ∂s · s`` inside the clamp (bounds inclusive, torch.clamp's rule),
  else 0;
* opacity ``o = exp(a)``, ``a = logsigmoid(x) - ½ Σ_i e_i``: ``∂a = ∂o · o``; ``∂x = ∂a ·
  sigmoid(-x)`` (torch's log_sigmoid_backward); each term ``e_i = exp(min(l_i, cap))`` with
  ``l_i = log λ_i + 2i log max(|dt|, 1e-30)`` gives ``∂log λ_i = -½ ∂a e_i`` where ``l_i <= cap``
  and ``∂dt += 2i (-½ ∂a e_i) sign(dt) / |dt|`` where also ``|dt| >= 1e-30``;
* ``dt = clamp(t - t0)``: ``∂t0 = -∂dt`` inside the clamp (inclusive), else 0;
* SH rows: copied to ``sh0`` and ``shN``.

Parallel over Gaussians (``numba.prange``) on :func:`~volcap_core.kernel_threads.kernel_threads`
threads; each Gaussian's values and gradient rows are computed and written by one thread, every sum
in a fixed order, so results do not depend on the thread count. float32 CPU tensors only;
``cache=True`` as the compiled projection (:mod:`volcap_core.splat.project_numba`). The numerical
guards are the model's constants, passed in by :func:`~volcap_core.splat.model.evaluate` (this
module is imported by the model, so it does not import it back).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from volcap_core.kernel_threads import kernel_threads_scope
from volcap_core.splat.kernel_tensors import require_float32_cpu

__all__ = ["slice_poly4dgs_numba"]

#: The parameter tensors the kernels take, in their argument order (absent ones are empty).
_PARAM_NAMES = ("means", "means_t", "quats", "quats_t", "scales", "scales_t", "opacities",
               "log_lambdas", "t0", "sh0", "shN")

# float32 constants (numba freezes globals with their types: a float64 literal would promote the
# arithmetic and the values would differ from the PyTorch path's float32 ops)
_ZERO = np.float32(0.0)
_HALF = np.float32(0.5)
_ONE = np.float32(1.0)
_QUAT_EPS = np.float32(1e-8)
_DT_FLOOR = np.float32(1e-30)


_JIT = dict(cache=True, error_model="numpy")      # IEEE division (x/0 = inf), as torch: no raise


@numba.njit(**_JIT)
def _dt(t, t0, temporal, i, max_abs_dt):
    """``clamp(t - t0[i], ±max_abs_dt)`` (0 without ``t0``) and whether the clamp passed it."""
    if not temporal:
        return _ZERO, False
    raw = t - t0[i]
    return min(max(raw, -max_abs_dt), max_abs_dt), (raw >= -max_abs_dt and raw <= max_abs_dt)


@numba.njit(**_JIT)
def _poly(base, coeffs, i, c, dt):
    """``base[i, c] + Σ_j coeffs[i, j, c] dt^(j+1)``, the powers by repeated product (torch's
    cumprod) and the sum in order of degree."""
    if coeffs.shape[1] == 0:
        return base[i, c]
    acc = _ZERO
    pw = _ONE
    for j in range(coeffs.shape[1]):
        pw = pw * dt
        acc += coeffs[i, j, c] * pw
    return base[i, c] + acc


@numba.njit(parallel=True, **_JIT)
def _live(t, t0, temporal, logits, log_lambdas, max_abs_dt, log_term_cap, min_opacity, opac,
          keep, d_logit, d_terms):
    """Every Gaussian's opacity at ``t`` (``opac [N]``) and whether it is kept (``keep [N]``:
    ``opac >= min_opacity``, False for NaN); for the backward, ``d_logit [N]`` = ∂logsigmoid/∂x
    and ``d_terms [N, n_o]`` = each envelope term ``exp(l_j)`` where ``l_j <= cap`` (else 0: the
    cap passes no gradient), so the backward evaluates no transcendental function."""
    n_o = log_lambdas.shape[1]
    for i in numba.prange(logits.shape[0]):
        dt, _ = _dt(t, t0, temporal, i, max_abs_dt)
        x = logits[i]
        # logsigmoid(x) = min(x, 0) - log1p(exp(-|x|)), torch's CPU formula, and its derivative
        z = np.float32(math.exp(-abs(x)))
        a = min(x, _ZERO) - np.float32(math.log1p(z))
        r = z / (_ONE + z)
        d_logit[i] = _ONE - r if x < _ZERO else r
        if n_o:
            log_abs_dt = np.float32(math.log(max(abs(dt), _DT_FLOOR)))
            acc = _ZERO
            for j in range(n_o):
                raw = log_lambdas[i, j] + np.float32(2 * (j + 1)) * log_abs_dt
                e = np.float32(math.exp(min(raw, log_term_cap)))
                acc += e
                d_terms[i, j] = e if raw <= log_term_cap else _ZERO
            a = a - _HALF * acc
        o = np.float32(math.exp(a))
        opac[i] = o
        keep[i] = o >= min_opacity


@numba.njit(parallel=True, **_JIT)
def _slice(ids, t, t0, temporal, max_abs_dt, log_scale_min, log_scale_max, means, means_t, quats,
           quats_t, scales, scales_t, opac, sh0, shN, o_means, o_quats, o_scales, o_opac, o_sh):
    """The live Gaussians ``ids [M]`` at ``t``: ``o_means [M, 3]``, ``o_quats [M, 4]`` (unit),
    ``o_scales [M, 3]`` (metres), ``o_opac [M]`` (from ``opac [N]``), ``o_sh [M, 3K]`` (the rows
    of ``sh0 [N, 3]`` then ``shN [N, 3(K-1)]``, flattened)."""
    L = shN.shape[1]
    for k in numba.prange(ids.shape[0]):
        i = ids[k]
        dt, _ = _dt(t, t0, temporal, i, max_abs_dt)
        for c in range(3):
            o_means[k, c] = _poly(means, means_t, i, c, dt)
            o_scales[k, c] = np.float32(math.exp(min(max(_poly(scales, scales_t, i, c, dt),
                                                         log_scale_min), log_scale_max)))
        q0 = _poly(quats, quats_t, i, 0, dt)
        q1 = _poly(quats, quats_t, i, 1, dt)
        q2 = _poly(quats, quats_t, i, 2, dt)
        q3 = _poly(quats, quats_t, i, 3, dt)
        n = max(np.float32(math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)), _QUAT_EPS)
        o_quats[k, 0], o_quats[k, 1], o_quats[k, 2], o_quats[k, 3] = q0 / n, q1 / n, q2 / n, q3 / n
        o_opac[k] = opac[i]
        o_sh[k, 0], o_sh[k, 1], o_sh[k, 2] = sh0[i, 0], sh0[i, 1], sh0[i, 2]
        for j in range(L):
            o_sh[k, 3 + j] = shN[i, j]


@numba.njit(**_JIT)
def _poly_backward(g, coeffs, i, c, dt, g_base, g_coeffs):
    """Writes ``∂base[i, c] = g`` and ``∂coeffs[i, j, c] = g dt^(j+1)``; returns ``∂dt``."""
    g_base[i, c] = g
    g_dt = _ZERO
    pw = _ONE                                           # dt^j
    for j in range(coeffs.shape[1]):
        g_dt += g * coeffs[i, j, c] * np.float32(j + 1) * pw
        pw = pw * dt
        g_coeffs[i, j, c] = g * pw
    return g_dt


@numba.njit(parallel=True, **_JIT)
def _backward(ids, t, t0, temporal, max_abs_dt, log_scale_min, log_scale_max, quats, quats_t,
              scales, scales_t, means_t, d_logit, d_terms, o_scales, o_opac,
              g_o_means, g_o_quats, g_o_scales, g_o_opac, g_o_sh,
              g_means, g_means_t, g_quats, g_quats_t, g_scales, g_scales_t, g_logits,
              g_log_lambdas, g_t0, g_sh0, g_shN):
    """Gradients of the live Gaussians ``ids [M]`` (their output gradients ``g_o_* [M, ...]``) to
    their parameters, written to rows ``ids[k]`` of the zero-filled full-size ``g_*`` (dropped
    Gaussians keep zero). Recomputes the polynomials; takes the transcendental factors from the
    forward (``d_logit``, ``d_terms``, the outputs ``o_scales``, ``o_opac``)."""
    L = g_shN.shape[1]
    n_o = d_terms.shape[1]
    for k in numba.prange(ids.shape[0]):
        i = ids[k]
        dt, inside = _dt(t, t0, temporal, i, max_abs_dt)
        g_dt = _ZERO
        for c in range(3):
            g_dt += _poly_backward(g_o_means[k, c], means_t, i, c, dt, g_means, g_means_t)
            v = _poly(scales, scales_t, i, c, dt)
            g_v = _ZERO
            if v >= log_scale_min and v <= log_scale_max:
                g_v = g_o_scales[k, c] * o_scales[k, c]
            g_dt += _poly_backward(g_v, scales_t, i, c, dt, g_scales, g_scales_t)

        # ---- quaternion normalisation
        q0 = _poly(quats, quats_t, i, 0, dt)
        q1 = _poly(quats, quats_t, i, 1, dt)
        q2 = _poly(quats, quats_t, i, 2, dt)
        q3 = _poly(quats, quats_t, i, 3, dt)
        norm = np.float32(math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3))
        n = max(norm, _QUAT_EPS)
        gq0, gq1, gq2, gq3 = g_o_quats[k, 0], g_o_quats[k, 1], g_o_quats[k, 2], g_o_quats[k, 3]
        if norm >= _QUAT_EPS:
            u0, u1, u2, u3 = q0 / n, q1 / n, q2 / n, q3 / n
            dot = u0 * gq0 + u1 * gq1 + u2 * gq2 + u3 * gq3
            gq0, gq1, gq2, gq3 = gq0 - u0 * dot, gq1 - u1 * dot, gq2 - u2 * dot, gq3 - u3 * dot
        g_dt += _poly_backward(gq0 / n, quats_t, i, 0, dt, g_quats, g_quats_t)
        g_dt += _poly_backward(gq1 / n, quats_t, i, 1, dt, g_quats, g_quats_t)
        g_dt += _poly_backward(gq2 / n, quats_t, i, 2, dt, g_quats, g_quats_t)
        g_dt += _poly_backward(gq3 / n, quats_t, i, 3, dt, g_quats, g_quats_t)

        # ---- opacity: o = exp(a), a = logsigmoid(x) - ½ Σ exp(min(l_j, cap))
        g_a = g_o_opac[k] * o_opac[k]
        g_logits[i] = g_a * d_logit[i]
        if n_o:
            g_log_abs_dt = _ZERO
            for j in range(n_o):
                g_l = -_HALF * g_a * d_terms[i, j]
                g_log_lambdas[i, j] = g_l
                g_log_abs_dt += np.float32(2 * (j + 1)) * g_l
            abs_dt = abs(dt)
            if abs_dt >= _DT_FLOOR:
                g_abs = g_log_abs_dt / abs_dt
                g_dt += g_abs if dt > _ZERO else -g_abs

        if temporal:
            g_t0[i] = -g_dt if inside else _ZERO
        g_sh0[i, 0], g_sh0[i, 1], g_sh0[i, 2] = g_o_sh[k, 0], g_o_sh[k, 1], g_o_sh[k, 2]
        for j in range(L):
            g_shN[i, j] = g_o_sh[k, 3 + j]


def _placeholder(n: int, name: str) -> np.ndarray:
    """The empty array standing for an absent parameter (a degree-0 property has none)."""
    shape = {"means_t": (n, 0, 3), "quats_t": (n, 0, 4), "scales_t": (n, 0, 3),
             "log_lambdas": (n, 0), "t0": (0,), "shN": (n, 0, 3)}[name]
    return np.zeros(shape, np.float32)


class _SliceNumba(torch.autograd.Function):
    """The compiled slice as an autograd node: ``(means [M, 3], quats [M, 4], scales [M, 3],
    opacities [M], sh [M, K, 3], ids [M])`` from the parameter tensors in ``_PARAM_NAMES``
    order (absent ones as ``None``); ids not differentiable. Keeps numpy views of the parameters
    and the forward's factors (the backward recomputes the polynomials per live Gaussian)."""

    @staticmethod
    def forward(ctx, t: float, min_opacity: float, guards: tuple, *params):
        n = params[0].shape[0]
        a = [_placeholder(n, name) if p is None else p.detach().contiguous().numpy()
             for name, p in zip(_PARAM_NAMES, params)]
        means, means_t, quats, quats_t, scales, scales_t, logits, log_lambdas, t0, sh0, shN = a
        sh0, shN = sh0.reshape(n, 3), shN.reshape(n, 3 * shN.shape[1])   # flat rows
        temporal = params[_PARAM_NAMES.index("t0")] is not None
        t32 = np.float32(t)
        max_abs_dt, log_term_cap, log_scale_min, log_scale_max = (np.float32(g) for g in guards)
        opac, keep = np.empty(n, np.float32), np.empty(n, np.bool_)
        d_logit = np.empty(n, np.float32)
        d_terms = np.empty((n, log_lambdas.shape[1]), np.float32)
        with kernel_threads_scope():
            _live(t32, t0, temporal, logits, log_lambdas, max_abs_dt, log_term_cap,
                  np.float32(min_opacity), opac, keep, d_logit, d_terms)
            ids = np.flatnonzero(keep).astype(np.int64)
            M, F = ids.shape[0], 3 + shN.shape[1]
            out = (np.empty((M, 3), np.float32), np.empty((M, 4), np.float32),
                   np.empty((M, 3), np.float32), np.empty(M, np.float32),
                   np.empty((M, F), np.float32))
            _slice(ids, t32, t0, temporal, max_abs_dt, log_scale_min, log_scale_max, means,
                   means_t, quats, quats_t, scales, scales_t, opac, sh0, shN, *out)
        ctx.arrays = (ids, t32, temporal, max_abs_dt, log_scale_min, log_scale_max, a, d_logit,
                      d_terms, out[2], out[3])
        ids_t = torch.from_numpy(ids)
        ctx.mark_non_differentiable(ids_t)
        o_means, o_quats, o_scales, o_opac, o_sh = (torch.from_numpy(o) for o in out)
        return o_means, o_quats, o_scales, o_opac, o_sh.view(M, F // 3, 3), ids_t

    @staticmethod
    def backward(ctx, *grads):
        (ids, t32, temporal, max_abs_dt, log_scale_min, log_scale_max, a, d_logit, d_terms,
         o_scales, o_opac) = ctx.arrays
        means, means_t, quats, quats_t, scales, scales_t, logits, log_lambdas, t0, sh0, shN = a
        n, M, F = means.shape[0], ids.shape[0], 3 + 3 * shN.shape[1]

        def grad(g, shape):                                 # None (output unused) is zero
            if g is None:
                return np.zeros(shape, np.float32)
            return g.detach().to(torch.float32).contiguous().numpy().reshape(shape)

        g_out = [grad(g, s) for g, s in zip(grads[:5], ((M, 3), (M, 4), (M, 3), (M,), (M, F)))]
        g_params = [np.zeros_like(p) for p in a]
        with kernel_threads_scope():
            _backward(ids, t32, t0, temporal, max_abs_dt, log_scale_min, log_scale_max, quats,
                      quats_t, scales, scales_t, means_t, d_logit, d_terms, o_scales, o_opac,
                      *g_out, *g_params[:9], g_params[9].reshape(n, 3),
                      g_params[10].reshape(n, 3 * shN.shape[1]))
        needs = ctx.needs_input_grad[3:]
        return (None, None, None, *(torch.from_numpy(g) if need else None
                                    for g, need in zip(g_params, needs)))


def slice_poly4dgs_numba(params: dict[str, torch.Tensor], t: float, min_opacity: float, *,
                         max_abs_dt: float, log_term_cap: float, log_scale_min: float,
                         log_scale_max: float):
    """A Poly4DGS model's live Gaussians at time ``t``, with the compiled kernels: the values and
    gradients of :func:`volcap_core.splat.model.evaluate`'s PyTorch path.

    Args:
        params: ``Poly4DGS.params`` (float32 CPU tensors; absent degrees absent, as the config
            makes them); gradients flow to those that require them.
        t: seconds on the take's clock. min_opacity: drop threshold.
        max_abs_dt, log_term_cap, log_scale_min, log_scale_max: the model's numerical guards
            (``MAX_ABS_DT``, ``_LOG_TERM_CAP``, ``LOG_SCALE_MIN``, ``LOG_SCALE_MAX``).
    Returns:
        ``(means [M, 3], quats [M, 4], scales [M, 3], opacities [M], sh [M, K, 3], ids [M])``,
        the M live Gaussians in ascending ``ids`` (int64); a dropped Gaussian gets exactly zero
        gradient.
    Raises:
        ValueError: a tensor not float32 or not on the CPU.
    """
    require_float32_cpu("slice", params)
    guards = (max_abs_dt, log_term_cap, log_scale_min, log_scale_max)
    return _SliceNumba.apply(t, min_opacity, guards, *(params.get(k) for k in _PARAM_NAMES))
