"""Compiled CPU projection of 3-D Gaussians (numba): gsplat's fused projection, forward and backward.

:func:`project_gaussians_numba` takes the inputs and gives the outputs of
:func:`volcap_core.splat.rasterize.project_gaussians`, under the same rules (its docstring and the
module doc of :mod:`volcap_core.splat.rasterize`): ``Σ = R diag(s)² Rᵀ`` from the quaternion
normalised with eps 1e-8 (a zero quaternion gives R = I); EWA projection with the Jacobian's point
clamped to 1.3× the field of view; the 2-D covariance symmetrised (``b = ½(Σ₀₁ + Σ₁₀)``) and dilated
by ``eps2d``; the conic its inverse; the opacity times the Mip-Splatting compensation
``sqrt(max(det₀ / det, 0))``; the same culling (depth outside ``(near, far)``, ``det <= 0``, any
non-finite result, compensated opacity below 1/255, zero footprint, footprint off-image), the same
ascending ``ids`` and the same int32 radii (capped at ``RADIUS_MAX``, not clamped to the image).

Why it exists: the PyTorch projection runs hundreds of small ops over N-long tensors, twice (a pass
without gradient over all N Gaussians to cull, a differentiable one over the survivors), plus their
autograd backward, on the one thread a reproducible training gives torch. Here one parallel loop
over the Gaussians computes everything for all N and the keep mask, and the backward is one more
loop with the gradient written out by hand (gsplat's ``fully_fused_projection`` does the same on a
GPU). Figures: ``docs/benchmarks.md``, "Rasterizer".

Gradients, from the outputs ``(means2d, conics, opacities, depths)`` of each survivor back to its
``(means, quats, scales, opacities)``, the chain of the forward in reverse (each step is what
autograd does to the PyTorch ops, so the two back-ends agree to float32 rounding):

* compensation ``r = det₀ / det``: ``∂o' = ∂L/∂o'·comp``, ``∂r = ∂L/∂o'·o / (2 comp)``,
  with ``det₀ = a₀c₀ - b²`` and ``det = (a₀+ε)(c₀+ε) - b²``;
* conic ``C = Σ₂⁻¹``: ``∂L/∂Σ₂ = -C G C`` with ``G`` the symmetric matrix of the conic's gradient
  (its off-diagonal entry being half ``∂L/∂b_conic``, the conic's ``b`` sitting at both places);
* ``Σ₂ = J Σc Jᵀ``: ``∂L/∂Σc = Jᵀ G₂ J``, ``∂L/∂J = 2 G₂ J Σc`` (both symmetric);
* ``J`` at ``t = z · clamp(x/z)``: through ``z`` directly and through ``t``, which passes the
  gradient to ``x`` only where ``x/z`` is within the clamp's bounds (torch.clamp's rule, inclusive)
  and to ``z`` as ``clamp(x/z) - [inside]·x/z``;
* ``Σc = Rw Σ Rwᵀ``: ``∂L/∂Σ = Rwᵀ ∂L/∂Σc Rw``; ``Σ = M Mᵀ``, ``M = R diag(s)``:
  ``∂L/∂M = 2 ∂L/∂Σ M``, ``∂s_k = Σ_r ∂M_rk R_rk``, ``∂R_rk = ∂M_rk s_k``, then through the
  quaternion's rotation matrix and the normalisation ``q = p / max(|p|, 1e-8)``
  (``∂p = (∂q - q ⟨q, ∂q⟩) / |p|``, or ``∂q / 1e-8`` below the eps);
* ``means2d = (fx x/z + cx, fy y/z + cy)``, ``depth = z``, camera point ``Rw μ + t``:
  ``∂μ = Rwᵀ ∂(x, y, z)``.

Parallel over Gaussians (``numba.prange``) on :func:`~volcap_core.kernel_threads.kernel_threads`
threads; each Gaussian is computed and written by one thread, so results do not depend on the
thread count. float32 CPU tensors only; ``cache=True`` as the compiled compositor
(:mod:`volcap_core.splat.composite_numba`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from volcap_core.kernel_threads import kernel_threads_scope
from volcap_core.splat.kernel_tensors import as_arrays, require_float32_cpu
from volcap_core.splat.camera import Camera
from volcap_core.splat.rasterize import ALPHA_THRESHOLD, EPS2D, EXTEND_MAX, RADIUS_MAX, Projected

__all__ = ["project_gaussians_numba"]

# float32 constants: numba freezes globals at compile time with their types, so the arithmetic
# stays in float32 like the PyTorch projection's (a float64 literal would promote it)
_ZERO = np.float32(0.0)
_HALF = np.float32(0.5)
_ONE = np.float32(1.0)
_TWO = np.float32(2.0)
_QUAT_EPS = np.float32(1e-8)
_ALPHA_THRESHOLD = np.float32(ALPHA_THRESHOLD)
_EXTEND_MAX = np.float32(EXTEND_MAX)
_RADIUS_MAX = np.float32(RADIUS_MAX)


@numba.njit(cache=True)
def _rotation(qw, qx, qy, qz):
    """Rotation matrix (row-major 9-tuple) of the quaternion ``(w, x, y, z)`` normalised with eps
    1e-8, and the normalised quaternion and the norm's divisor ``max(|q|, 1e-8)``."""
    n = max(np.float32(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)), _QUAT_EPS)
    w, x, y, z = qw / n, qx / n, qy / n, qz / n
    R = (_ONE - _TWO * (y * y + z * z), _TWO * (x * y - w * z), _TWO * (x * z + w * y),
         _TWO * (x * y + w * z), _ONE - _TWO * (x * x + z * z), _TWO * (y * z - w * x),
         _TWO * (x * z - w * y), _TWO * (y * z + w * x), _ONE - _TWO * (x * x + y * y))
    return R, w, x, y, z, n


@numba.njit(cache=True)
def _mm(A, B):
    """``A @ B`` of 3x3 matrices held as row-major 9-tuples (registers, not arrays: nothing is
    allocated per Gaussian)."""
    return (A[0] * B[0] + A[1] * B[3] + A[2] * B[6],
            A[0] * B[1] + A[1] * B[4] + A[2] * B[7],
            A[0] * B[2] + A[1] * B[5] + A[2] * B[8],
            A[3] * B[0] + A[4] * B[3] + A[5] * B[6],
            A[3] * B[1] + A[4] * B[4] + A[5] * B[7],
            A[3] * B[2] + A[4] * B[5] + A[5] * B[8],
            A[6] * B[0] + A[7] * B[3] + A[8] * B[6],
            A[6] * B[1] + A[7] * B[4] + A[8] * B[7],
            A[6] * B[2] + A[7] * B[5] + A[8] * B[8])


@numba.njit(cache=True)
def _t(A):
    """Transpose of a row-major 9-tuple."""
    return (A[0], A[3], A[6], A[1], A[4], A[7], A[2], A[5], A[8])


@numba.njit(cache=True)
def _camera_covariance(R, s0, s1, s2, Rw):
    """``Σc = Rw (R diag(s)² Rᵀ) Rwᵀ`` (9-tuples): returns ``(M, Σc)`` with ``M = R diag(s)``, in
    the PyTorch projection's order of products (``M Mᵀ``, then ``Rw Σ``, then ``· Rwᵀ``)."""
    M = (R[0] * s0, R[1] * s1, R[2] * s2, R[3] * s0, R[4] * s1, R[5] * s2,
         R[6] * s0, R[7] * s1, R[8] * s2)
    return M, _mm(_mm(Rw, _mm(M, _t(M))), _t(Rw))


@numba.njit(cache=True)
def _jacobian(x, y, z, fx, fy, lim):
    """The EWA Jacobian's non-zero entries ``(fx/z, -fx·tx/z², fy/z, -fy·ty/z²)`` at the point
    clamped to ``lim = (lim_xn, lim_xp, lim_yn, lim_yp)``, and the clamped ratios ``tx/z, ty/z``."""
    ux = min(max(x / z, -lim[0]), lim[1])
    uy = min(max(y / z, -lim[2]), lim[3])
    tx, ty = z * ux, z * uy
    return fx / z, -fx * tx / (z * z), fy / z, -fy * ty / (z * z), ux, uy


@numba.njit(cache=True)
def _cov2d(j00, j02, j11, j12, C):
    """``(a₀, b₀, c₀)`` of ``J Σc Jᵀ`` with ``J = [[j00, 0, j02], [0, j11, j12]]``, ``b₀`` the
    average of the two off-diagonal entries (as the PyTorch projection symmetrises)."""
    # rows of J Σc
    p0 = j00 * C[0] + j02 * C[6]
    p1 = j00 * C[1] + j02 * C[7]
    p2 = j00 * C[2] + j02 * C[8]
    q0 = j11 * C[3] + j12 * C[6]
    q1 = j11 * C[4] + j12 * C[7]
    q2 = j11 * C[5] + j12 * C[8]
    a0 = p0 * j00 + p2 * j02
    c0 = q1 * j11 + q2 * j12
    b0 = _HALF * ((p1 * j11 + p2 * j12) + (q0 * j00 + q2 * j02))
    return a0, b0, c0


@numba.njit(cache=True, parallel=True)
def _forward(means, quats, scales, opacities, Rw, tw, fx, fy, cx, cy, lim, width, height, near,
             far, eps2d, antialiased, means2d, conics, opac_out, depths, radii, keep):
    """Every Gaussian's screen-space quantities and whether it survives culling: ``means2d [N, 2]``,
    ``conics [N, 3]``, ``opac_out [N]``, ``depths [N]``, ``radii [N, 2]`` int32, ``keep [N]``
    (the culled ones' entries are undefined)."""
    for i in numba.prange(means.shape[0]):
        mx, my, mz = means[i, 0], means[i, 1], means[i, 2]
        z = Rw[6] * mx + Rw[7] * my + Rw[8] * mz + tw[2]
        keep[i] = False
        if not (z > near and z < far):                    # also NaN
            continue
        x = Rw[0] * mx + Rw[1] * my + Rw[2] * mz + tw[0]
        y = Rw[3] * mx + Rw[4] * my + Rw[5] * mz + tw[1]
        R, _, _, _, _, _ = _rotation(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3])
        _, C = _camera_covariance(R, scales[i, 0], scales[i, 1], scales[i, 2], Rw)
        j00, j02, j11, j12, _, _ = _jacobian(x, y, z, fx, fy, lim)
        a0, b0, c0 = _cov2d(j00, j02, j11, j12, C)
        det0 = a0 * c0 - b0 * b0
        a, c = a0 + eps2d, c0 + eps2d
        det = a * c - b0 * b0
        o = opacities[i]
        if antialiased:
            o = o * np.float32(math.sqrt(max(det0 / det, _ZERO)))
        u = fx * x / z + cx
        v = fy * y / z + cy
        qa, qb, qc = c / det, -b0 / det, a / det
        if not (det > _ZERO and np.isfinite(det) and np.isfinite(u) and np.isfinite(v)
                and np.isfinite(o) and np.isfinite(qa) and np.isfinite(qb) and np.isfinite(qc)
                and o >= _ALPHA_THRESHOLD):
            continue
        extend = min(np.float32(math.sqrt(_TWO * np.float32(math.log(o / _ALPHA_THRESHOLD)))),
                     _EXTEND_MAX)
        rx = np.ceil(extend * np.float32(math.sqrt(max(a, _ZERO))))
        ry = np.ceil(extend * np.float32(math.sqrt(max(c, _ZERO))))
        if not (rx > _ZERO or ry > _ZERO):
            continue
        if u + rx <= _ZERO or u - rx >= width or v + ry <= _ZERO or v - ry >= height:
            continue
        keep[i] = True
        means2d[i, 0], means2d[i, 1] = u, v
        conics[i, 0], conics[i, 1], conics[i, 2] = qa, qb, qc
        opac_out[i] = o
        depths[i] = z
        radii[i, 0] = np.int32(min(rx, _RADIUS_MAX))
        radii[i, 1] = np.int32(min(ry, _RADIUS_MAX))


@numba.njit(cache=True, parallel=True)
def _survivors(ids, means2d, conics, opac, depths, radii):
    """The rows ``ids [M]`` of the forward's per-Gaussian outputs, as new compact arrays (numpy's
    fancy indexing of five arrays cost half the kernel's time)."""
    M = ids.shape[0]
    m2, cn, op = np.empty((M, 2), np.float32), np.empty((M, 3), np.float32), np.empty(M, np.float32)
    dp, rd = np.empty(M, np.float32), np.empty((M, 2), np.int32)
    for k in numba.prange(M):
        i = ids[k]
        m2[k, 0], m2[k, 1] = means2d[i, 0], means2d[i, 1]
        cn[k, 0], cn[k, 1], cn[k, 2] = conics[i, 0], conics[i, 1], conics[i, 2]
        op[k] = opac[i]
        dp[k] = depths[i]
        rd[k, 0], rd[k, 1] = radii[i, 0], radii[i, 1]
    return m2, cn, op, dp, rd


@numba.njit(cache=True, parallel=True)
def _backward(ids, means, quats, scales, opacities, Rw, tw, fx, fy, lim, eps2d, antialiased,
              g_means2d, g_conics, g_opac, g_depths, g_means, g_quats, g_scales, g_opacities):
    """Gradients of the survivors ``ids [M]`` (their output gradients ``g_* [M, ...]``) to their
    inputs, written to row ``ids[k]`` of ``g_means [N, 3]``, ``g_quats [N, 4]``, ``g_scales [N, 3]``
    and ``g_opacities [N]`` (zeros in: culled Gaussians keep zero). Recomputes the forward."""
    for k in numba.prange(ids.shape[0]):
        i = ids[k]
        mx, my, mz = means[i, 0], means[i, 1], means[i, 2]
        x = Rw[0] * mx + Rw[1] * my + Rw[2] * mz + tw[0]
        y = Rw[3] * mx + Rw[4] * my + Rw[5] * mz + tw[1]
        z = Rw[6] * mx + Rw[7] * my + Rw[8] * mz + tw[2]
        R, w, qx, qy, qz, n = _rotation(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3])
        s0, s1, s2 = scales[i, 0], scales[i, 1], scales[i, 2]
        M, C = _camera_covariance(R, s0, s1, s2, Rw)
        j00, j02, j11, j12, ux, uy = _jacobian(x, y, z, fx, fy, lim)
        a0, b0, c0 = _cov2d(j00, j02, j11, j12, C)
        det0 = a0 * c0 - b0 * b0
        a, c = a0 + eps2d, c0 + eps2d
        det = a * c - b0 * b0
        o = opacities[i]

        # ---- opacity and its compensation -> (a0, b0, c0), o
        ga0 = gb0 = gc0 = _ZERO
        if antialiased:
            ratio = det0 / det
            comp = np.float32(math.sqrt(max(ratio, _ZERO)))
            g_opacities[i] = g_opac[k] * comp
            if ratio >= _ZERO and comp > _ZERO:           # clamp's and sqrt's gradient
                g_r = g_opac[k] * o * _HALF / comp
                g_det0, g_det = g_r / det, -g_r * ratio / det
                ga0 += g_det0 * c0 + g_det * c
                gc0 += g_det0 * a0 + g_det * a
                gb0 -= _TWO * b0 * (g_det0 + g_det)
        else:
            g_opacities[i] = g_opac[k]

        # ---- conic = inverse of [[a, b0], [b0, c]]: dL/dΣ2 = -C G C
        ca, cb, cc = c / det, -b0 / det, a / det
        ga_, gb_, gc_ = g_conics[k, 0], _HALF * g_conics[k, 1], g_conics[k, 2]
        # T = G C (G symmetric [[ga_, gb_], [gb_, gc_]], C symmetric [[ca, cb], [cb, cc]])
        t00, t01 = ga_ * ca + gb_ * cb, ga_ * cb + gb_ * cc
        t10, t11 = gb_ * ca + gc_ * cb, gb_ * cb + gc_ * cc
        ga0 -= ca * t00 + cb * t10
        gc0 -= cb * t01 + cc * t11
        gb0 -= (ca * t01 + cb * t11) + (cb * t00 + cc * t10)

        # ---- cov2d = J Σc Jᵀ: G2 = [[ga0, gb0/2], [gb0/2, gc0]]
        hb = _HALF * gb0
        # G2 J (2x3): rows (ga0·J0 + hb·J1, hb·J0 + gc0·J1), J0 = (j00, 0, j02), J1 = (0, j11, j12)
        e00, e01, e02 = ga0 * j00, hb * j11, ga0 * j02 + hb * j12
        e10, e11, e12 = hb * j00, gc0 * j11, hb * j02 + gc0 * j12
        # dL/dΣc = Jᵀ (G2 J): column-by-row
        gC = (j00 * e00, j00 * e01, j00 * e02,
              j11 * e10, j11 * e11, j11 * e12,
              j02 * e00 + j12 * e10, j02 * e01 + j12 * e11, j02 * e02 + j12 * e12)
        # dL/dJ = 2 (G2 J) Σc, only the non-zero entries of J
        gj00 = _TWO * (e00 * C[0] + e01 * C[3] + e02 * C[6])
        gj02 = _TWO * (e00 * C[2] + e01 * C[5] + e02 * C[8])
        gj11 = _TWO * (e10 * C[1] + e11 * C[4] + e12 * C[7])
        gj12 = _TWO * (e10 * C[2] + e11 * C[5] + e12 * C[8])

        # ---- J at the clamped point, and the projected mean and depth -> camera point
        z2 = z * z
        tx, ty = z * ux, z * uy
        in_x = ux == x / z                                # not clamped: gradient passes to x
        in_y = uy == y / z
        g_tx = -fx / z2 * gj02
        g_ty = -fy / z2 * gj12
        gx = g_means2d[k, 0] * fx / z
        gy = g_means2d[k, 1] * fy / z
        gz = (g_depths[k] - g_means2d[k, 0] * fx * x / z2 - g_means2d[k, 1] * fy * y / z2
              - fx / z2 * gj00 - fy / z2 * gj11
              + _TWO * fx * tx / (z2 * z) * gj02 + _TWO * fy * ty / (z2 * z) * gj12)
        if in_x:
            gx += g_tx
            gz += g_tx * (ux - x / z)
        else:
            gz += g_tx * ux
        if in_y:
            gy += g_ty
            gz += g_ty * (uy - y / z)
        else:
            gz += g_ty * uy
        for col in range(3):
            g_means[i, col] = Rw[col] * gx + Rw[3 + col] * gy + Rw[6 + col] * gz

        # ---- Σc = Rw Σ Rwᵀ -> Σ; Σ = M Mᵀ -> M -> (R, s)
        gS = _mm(_mm(_t(Rw), gC), Rw)
        gM = _mm((gS[0] + gS[0], gS[1] + gS[3], gS[2] + gS[6],
                  gS[3] + gS[1], gS[4] + gS[4], gS[5] + gS[7],
                  gS[6] + gS[2], gS[7] + gS[5], gS[8] + gS[8]), M)
        g_scales[i, 0] = gM[0] * R[0] + gM[3] * R[3] + gM[6] * R[6]
        g_scales[i, 1] = gM[1] * R[1] + gM[4] * R[4] + gM[7] * R[7]
        g_scales[i, 2] = gM[2] * R[2] + gM[5] * R[5] + gM[8] * R[8]
        G00, G01, G02 = gM[0] * s0, gM[1] * s1, gM[2] * s2
        G10, G11, G12 = gM[3] * s0, gM[4] * s1, gM[5] * s2
        G20, G21, G22 = gM[6] * s0, gM[7] * s1, gM[8] * s2

        # ---- R(q) -> normalised q -> raw quaternion
        gw = _TWO * (-qz * G01 + qy * G02 + qz * G10 - qx * G12 - qy * G20 + qx * G21)
        gx_ = _TWO * (qy * G01 + qz * G02 + qy * G10 - _TWO * qx * G11 - w * G12 + qz * G20
                      + w * G21 - _TWO * qx * G22)
        gy_ = _TWO * (-_TWO * qy * G00 + qx * G01 + w * G02 + qx * G10 + qz * G12 - w * G20
                      + qz * G21 - _TWO * qy * G22)
        gz_ = _TWO * (-_TWO * qz * G00 - w * G01 + qx * G02 + w * G10 - _TWO * qz * G11
                      + qy * G12 + qx * G20 + qy * G21)
        if n > _QUAT_EPS:
            dot = w * gw + qx * gx_ + qy * gy_ + qz * gz_
            gw, gx_, gy_, gz_ = gw - w * dot, gx_ - qx * dot, gy_ - qy * dot, gz_ - qz * dot
        g_quats[i, 0] = gw / n
        g_quats[i, 1] = gx_ / n
        g_quats[i, 2] = gy_ / n
        g_quats[i, 3] = gz_ / n


def _camera_arrays(camera: Camera):
    """The camera as the kernels take it, in float32 computed as the PyTorch projection computes
    it: ``Rw`` (row-major 9-tuple), ``t`` (3-tuple), ``fx, fy, cx, cy`` and the Jacobian clamp's
    bounds ``(lim_xn, lim_xp, lim_yn, lim_yp)``."""
    W = camera.world_to_camera.detach().to(torch.float32).cpu()
    K = camera.K.detach().to(torch.float32).cpu()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w, h = camera.width, camera.height
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    lim = torch.stack([cx / fx + 0.3 * tan_x, (w - cx) / fx + 0.3 * tan_x,
                       cy / fy + 0.3 * tan_y, (h - cy) / fy + 0.3 * tan_y])
    f32 = np.float32
    return (tuple(f32(v) for v in W[:3, :3].reshape(-1).tolist()),
            tuple(f32(v) for v in W[:3, 3].tolist()), f32(fx), f32(fy), f32(cx), f32(cy),
            tuple(f32(v) for v in lim.tolist()))


class _ProjectNumba(torch.autograd.Function):
    """The compiled projection as an autograd node: ``(means2d [M, 2], conics [M, 3],
    opacities [M], depths [M], ids [M], radii [M, 2])`` of the M survivors from ``means [N, 3]``,
    ``quats [N, 4]``, ``scales [N, 3]``, ``opacities [N]``; ids and radii not differentiable.
    Keeps the inputs (the backward recomputes the forward per survivor)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, camera: Camera, eps2d: float,
                antialiased: bool):
        m, q, s, o = as_arrays(means, quats, scales, opacities)
        N = m.shape[0]
        Rw, tw, fx, fy, cx, cy, lim = _camera_arrays(camera)
        means2d = np.empty((N, 2), np.float32)
        conics = np.empty((N, 3), np.float32)
        opac = np.empty(N, np.float32)
        depths = np.empty(N, np.float32)
        radii = np.empty((N, 2), np.int32)
        keep = np.empty(N, np.bool_)
        with kernel_threads_scope():
            _forward(m, q, s, o, Rw, tw, fx, fy, cx, cy, lim, np.float32(camera.width),
                     np.float32(camera.height), np.float32(camera.near), np.float32(camera.far),
                     np.float32(eps2d), bool(antialiased), means2d, conics, opac, depths, radii,
                     keep)
            ids = np.flatnonzero(keep).astype(np.int64)
            kept = _survivors(ids, means2d, conics, opac, depths, radii)
        ctx.arrays = (ids, m, q, s, o, Rw, tw, fx, fy, lim, np.float32(eps2d), bool(antialiased))
        means2d, conics, opac, depths, radii = (torch.from_numpy(a) for a in kept)
        ids_t = torch.from_numpy(ids)
        ctx.mark_non_differentiable(ids_t, radii)
        return means2d, conics, opac, depths, ids_t, radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_opac, g_depths, _g_ids, _g_radii):
        ids, m, q, s, o, Rw, tw, fx, fy, lim, eps2d, antialiased = ctx.arrays
        M = ids.shape[0]

        def grad(g, shape):                                 # None (output unused) is zero
            if g is None:
                return np.zeros(shape, np.float32)
            return g.detach().to(torch.float32).contiguous().numpy()

        gm2, gq, go, gd = (grad(g_means2d, (M, 2)), grad(g_conics, (M, 3)), grad(g_opac, M),
                           grad(g_depths, M))
        g_means, g_quats = np.zeros_like(m), np.zeros_like(q)
        g_scales, g_opacities = np.zeros_like(s), np.zeros_like(o)
        with kernel_threads_scope():
            _backward(ids, m, q, s, o, Rw, tw, fx, fy, lim, eps2d, antialiased, gm2, gq, go, gd,
                      g_means, g_quats, g_scales, g_opacities)
        return (torch.from_numpy(g_means), torch.from_numpy(g_quats), torch.from_numpy(g_scales),
                torch.from_numpy(g_opacities), None, None, None)


def project_gaussians_numba(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                            opacities: torch.Tensor, camera: Camera, *, eps2d: float = EPS2D,
                            antialiased: bool = True) -> Projected:
    """Project 3D Gaussians into ``camera`` and cull, with the compiled kernels: the inputs,
    outputs and rules of :func:`volcap_core.splat.rasterize.project_gaussians`.

    Args:
        means: ``[N, 3]`` world positions. quats: ``[N, 4]`` wxyz. scales: ``[N, 3]`` (metres).
        opacities: ``[N]`` in [0, 1]. All float32 on the CPU.
        camera: the view.
        eps2d: 2D dilation (px²). antialiased: apply the Mip-Splatting opacity compensation.
    Returns:
        :class:`~volcap_core.splat.rasterize.Projected` for the M surviving Gaussians, its
        ``means2d``, ``conics``, ``opacities`` and ``depths`` differentiable to ``means``,
        ``quats``, ``scales`` and ``opacities`` (a culled Gaussian gets exactly zero gradient).
    Raises:
        ValueError: a tensor not float32 or not on the CPU.
    """
    require_float32_cpu("projection", {"means": means, "quats": quats, "scales": scales,
                                       "opacities": opacities})
    means2d, conics, opac, depths, ids, radii = _ProjectNumba.apply(
        means, quats, scales, opacities, camera, eps2d, antialiased)
    return Projected(ids=ids, means2d=means2d, conics=conics, opacities=opac, depths=depths,
                     radii=radii)
