"""Compiled CPU compositing of binned Gaussians (numba): the per-pixel loop of gsplat's kernels.

:func:`rasterize_tiles_numba` takes the inputs and gives the outputs of
:func:`volcap_core.splat.rasterize.rasterize_tiles`, under the same rules (the module doc of
:mod:`volcap_core.splat.rasterize`): pixel centres at ``+0.5``; ``α = min(0.999, o·exp(-σ))`` with
``σ = ½a dx² + ½c dy² + b dx dy``; fragments with ``α < 1/255`` skipped; front to back, a pixel stops
before the fragment that would bring its transmittance to ``<= 1e-4``; each pixel accumulates
``Σ_i α_i T_i v_i`` and its alpha ``Σ_i α_i T_i``; no gradient through the clamp, the threshold or
the stop. The tile binning is :func:`~volcap_core.splat.rasterize.bin_tiles`, the one both
compositors use.

Why it exists: the PyTorch compositor evaluates every padded (pixel, Gaussian) pair of a tile, also
behind opaque surfaces, in ~10 passes over memory. Here each pixel walks its tile's list once, front
to back, and stops where it is opaque; the backward walks the same fragments back to front from the
final transmittance (``T_i = T_{i+1} / (1 - α_i)``), so nothing per pair is stored between the
passes: per pixel only the final transmittance and the count of fragments walked. Within a tile,
the Gaussians whose ellipse misses every pixel centre are dropped first, and each pixel tests 32
Gaussians at a time without branches before it composites the ones that can reach 1/255
(figures: ``docs/benchmarks.md``, "Rasterizer").

Gradients (the maths of ``rasterize._Composite.backward``): with ``w_i = α_i T_i``,
``c_i = ⟨∂L/∂acc, v_i⟩`` and ``S_i = Σ_{j>i} w_j c_j``, ``∂L/∂v_i = w_i ∂L/∂acc`` and
``∂L/∂α_i = T_i c_i - S_i / (1 - α_i)``; through ``α = o·exp(-σ)`` (unclamped fragments only) to the
opacity, the conic ``(a, b, c)`` and the 2-D mean.

Parallel over tiles (``numba.prange``) on :func:`~volcap_core.kernel_threads.kernel_threads` threads: all cores unless
``NUMBA_NUM_THREADS`` says fewer, also while torch trains on one thread for reproducibility. Each tile is owned by one thread, which writes its
pixels and its intersections' gradients; the per-Gaussian sums are then made serially in
intersection order, so results do not depend on the thread count. float32 CPU tensors only.
``cache=True``: the kernels compile once per machine (into ``__pycache__`` beside this file, or
numba's user cache directory where that is read-only) and load in well under a second afterwards.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from volcap_core.kernel_threads import kernel_threads_scope
from volcap_core.splat.kernel_tensors import as_arrays, require_float32_cpu
from volcap_core.splat.rasterize import (
    ALPHA_MAX,
    ALPHA_THRESHOLD,
    TRANSMITTANCE_MIN,
    TileBins,
    TileStats,
    bin_tiles,
)

__all__ = ["rasterize_tiles_numba"]

# float32 constants: numba freezes globals at compile time with their types, so the kernels' float
# arithmetic stays in float32 like the PyTorch compositor's
_HALF = np.float32(0.5)
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)
_PIXEL_CENTRE = np.float32(0.5)
_ALPHA_MAX = np.float32(ALPHA_MAX)
_ALPHA_THRESHOLD = np.float32(ALPHA_THRESHOLD)
_T_MIN = np.float32(TRANSMITTANCE_MIN)
#: a pair with σ beyond ln(255 o) + this is below the 1/255 threshold whatever the rounding: skipped
#: without its exp. Pairs nearer the threshold are decided by the exact α.
_SIGMA_MARGIN = np.float32(1e-3)
_LN_255 = np.float32(math.log(255.0))


#: Gaussians whose σ at a pixel are computed together: a loop without branches, which the compiler
#: turns into SIMD instructions; the compositing then walks the block one fragment at a time
_BLOCK = 32


@numba.njit(cache=True, inline="always")
def _min_sigma(mx, my, a, b, c, xlo, xhi, ylo, yhi):
    """Smallest σ of the Gaussian (mean ``(mx, my)``, conic ``(a, b, c)``) over the rectangle
    ``[xlo, xhi] × [ylo, yhi]`` of a tile's pixel centres, in float64; -inf for a conic that is not
    positive definite (never culled). σ is convex: 0 inside, else its minimum lies on an edge, where
    it is a 1-D quadratic minimised in closed form and clamped to the edge."""
    if not (a > 0.0 and c > 0.0 and a * c - b * b > 0.0):
        return -np.inf
    if xlo <= mx <= xhi and ylo <= my <= yhi:
        return 0.0
    best = np.inf
    for xe in (xlo, xhi):
        dx = xe - mx
        dy = min(max(-b * dx / c, ylo - my), yhi - my)
        best = min(best, 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)
    for ye in (ylo, yhi):
        dy = ye - my
        dx = min(max(-b * dy / a, xlo - mx), xhi - mx)
        best = min(best, 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)
    return best


@numba.njit(cache=True, inline="always")
def _pack_tile(means2d, conics, opacities, values, ids, start, count, xlo, xhi, ylo, yhi, geom,
               vals, slot):
    """Copy the tile's Gaussians that reach ``α >= 1/255`` at one of its pixel centres
    (``[xlo, xhi] × [ylo, yhi]``), front to back, into the contiguous rows of ``geom [7, K]`` (mx,
    my, a, b, c, o, σ beyond which α < 1/255 for sure) and ``vals [K, C]``, with ``slot [K]`` their
    offsets in the tile's run of ``ids``; returns K. The binning's footprint box holds the whole
    ellipse, so a tile at a corner of the box is often missed entirely: dropped here, its pairs
    cost nothing (in both passes, which pack identically)."""
    C = values.shape[1]
    k = 0
    for j in range(count):
        i = ids[start + j]
        o = opacities[i]
        # o < 1/255 (or NaN) never reaches the threshold
        if not o >= _ALPHA_THRESHOLD:
            continue
        lim = np.float32(np.log(o)) + _LN_255 + _SIGMA_MARGIN
        # the margin (1e-3) dwarfs the float32 rounding of a pixel's σ, so culling on the exact
        # minimum drops no pair the per-pixel test would keep
        if _min_sigma(np.float64(means2d[i, 0]), np.float64(means2d[i, 1]), np.float64(conics[i, 0]),
                      np.float64(conics[i, 1]), np.float64(conics[i, 2]), xlo, xhi, ylo, yhi) > lim:
            continue
        geom[0, k] = means2d[i, 0]
        geom[1, k] = means2d[i, 1]
        geom[2, k] = conics[i, 0]
        geom[3, k] = conics[i, 1]
        geom[4, k] = conics[i, 2]
        geom[5, k] = o
        geom[6, k] = lim
        for ch in range(C):
            vals[k, ch] = values[i, ch]
        slot[k] = j
        k += 1
    return k


@numba.njit(cache=True, inline="always")
def _candidates(geom, j0, m, fx, fy, sigma, hits):
    """σ of Gaussians ``j0 .. j0 + m - 1`` at pixel centre ``(fx, fy)`` into ``sigma[:m]``, and the
    block offsets of those that may reach α >= 1/255 into ``hits``; returns how many. The same
    float32 expression in forward and backward, so both take the same decisions. Branch-free: most
    pairs of a tile are outside the Gaussian's ellipse, in no predictable pattern, and a branch per
    pair would cost a misprediction each time."""
    n = 0
    for jj in range(m):
        j = j0 + jj
        dx = fx - geom[0, j]
        dy = fy - geom[1, j]
        s = _HALF * (geom[2, j] * dx * dx + geom[4, j] * dy * dy) + geom[3, j] * dx * dy
        sigma[jj] = s
        hits[n] = jj
        n += np.int64(s <= geom[6, j])
    return n


@numba.njit(cache=True, inline="always")
def _tile_box(t, tiles_x, tile_size, width, height):
    """Tile ``t``'s pixels ``[x0, x1) × [y0, y1)`` (row-major tiles, clipped to the image)."""
    x0 = (t % tiles_x) * tile_size
    y0 = (t // tiles_x) * tile_size
    return x0, y0, min(x0 + tile_size, width), min(y0 + tile_size, height)


@numba.njit(cache=True, inline="always")
def _tile_buffers(k, C):
    """A tile's working arrays for ``k`` Gaussians of ``C`` values: packed geometry ``[7, k]``,
    values ``[k, C]``, their slots ``[k]``, and one block's σ and hit indices ``[_BLOCK]``."""
    return (np.empty((7, k), np.float32), np.empty((k, C), np.float32), np.empty(k, np.int64),
            np.empty(_BLOCK, np.float32), np.empty(_BLOCK, np.int64))


@numba.njit(cache=True, parallel=True)
def _forward(means2d, conics, opacities, values, ids, starts, counts, tiles_x, tile_size, width,
             height, out, trans, walked):
    """Composite every tile: ``out [H, W, C]`` (zeros in) gets ``Σ α_i T_i v_i``, ``trans [H, W]``
    (ones in) the final transmittance, ``walked [H, W]`` how many of its tile's fragments a pixel
    went through before it stopped (0 in)."""
    C = values.shape[1]
    for t in numba.prange(starts.shape[0]):
        k = counts[t]
        if k == 0:
            continue
        x0, y0, x1, y1 = _tile_box(t, tiles_x, tile_size, width, height)
        geom, vals, slot, sig, hits = _tile_buffers(k, C)
        k = _pack_tile(means2d, conics, opacities, values, ids, starts[t], k, x0 + 0.5, x1 - 0.5,
                       y0 + 0.5, y1 - 0.5, geom, vals, slot)
        for py in range(y0, y1):
            fy = np.float32(py) + _PIXEL_CENTRE
            for px in range(x0, x1):
                fx = np.float32(px) + _PIXEL_CENTRE
                T = _ONE
                n = 0
                j0 = 0
                while j0 < k:
                    m = min(_BLOCK, k - j0)
                    stop = False
                    for h in range(_candidates(geom, j0, m, fx, fy, sig, hits)):
                        j = j0 + hits[h]
                        sigma = sig[hits[h]]
                        alpha = min(_ALPHA_MAX, geom[5, j] * np.exp(-sigma))
                        if alpha < _ALPHA_THRESHOLD:
                            continue
                        next_T = T * (_ONE - alpha)
                        if next_T <= _T_MIN:
                            stop = True
                            break
                        w = alpha * T
                        for ch in range(C):
                            out[py, px, ch] += w * vals[j, ch]
                        T = next_T
                        n = j + 1
                    if stop:
                        break
                    j0 += m
                trans[py, px] = T
                walked[py, px] = n


@numba.njit(cache=True, parallel=True)
def _backward(means2d, conics, opacities, values, ids, starts, counts, tiles_x, tile_size, width,
              height, trans, walked, grad_out, grad_geom, grad_vals):
    """Per intersection ``e`` (of ``ids``), the gradient of its tile's pixels to its Gaussian:
    ``grad_geom [I, 6]`` (mx, my, a, b, c, o) and ``grad_vals [I, C]`` (zeros in). Each pixel
    walks its fragments back to front from its final transmittance."""
    C = values.shape[1]
    for t in numba.prange(starts.shape[0]):
        k = counts[t]
        if k == 0:
            continue
        s = starts[t]
        x0, y0, x1, y1 = _tile_box(t, tiles_x, tile_size, width, height)
        geom, vals, slot, sig, hits = _tile_buffers(k, C)
        k = _pack_tile(means2d, conics, opacities, values, ids, s, k, x0 + 0.5, x1 - 0.5,
                       y0 + 0.5, y1 - 0.5, geom, vals, slot)
        for py in range(y0, y1):
            fy = np.float32(py) + _PIXEL_CENTRE
            for px in range(x0, x1):
                fx = np.float32(px) + _PIXEL_CENTRE
                T = trans[py, px]
                suffix = _ZERO                                   # Σ_{j>i} w_j c_j
                j1 = walked[py, px]
                while j1 > 0:
                    j0 = max(0, j1 - _BLOCK)
                    m = j1 - j0
                    for h in range(_candidates(geom, j0, m, fx, fy, sig, hits) - 1, -1, -1):
                        j = j0 + hits[h]
                        sigma = sig[hits[h]]
                        ex = np.exp(-sigma)
                        raw = geom[5, j] * ex
                        alpha = min(_ALPHA_MAX, raw)
                        if alpha < _ALPHA_THRESHOLD:
                            continue
                        e = s + slot[j]                          # the intersection
                        one_minus = _ONE - alpha
                        T = T / one_minus                        # T_j, in front of fragment j
                        w = alpha * T
                        c = _ZERO
                        for ch in range(C):
                            g = grad_out[py, px, ch]
                            c += g * vals[j, ch]
                            grad_vals[e, ch] += w * g
                        g_alpha = T * c - suffix / one_minus
                        suffix += w * c
                        if raw < _ALPHA_MAX:                     # no gradient through the clamp
                            dx = fx - geom[0, j]
                            dy = fy - geom[1, j]
                            g_q = g_alpha * alpha                # ∂L/∂(ln o - σ)
                            grad_geom[e, 0] += g_q * (geom[2, j] * dx + geom[3, j] * dy)
                            grad_geom[e, 1] += g_q * (geom[3, j] * dx + geom[4, j] * dy)
                            grad_geom[e, 2] -= g_q * _HALF * dx * dx
                            grad_geom[e, 3] -= g_q * dx * dy
                            grad_geom[e, 4] -= g_q * _HALF * dy * dy
                            grad_geom[e, 5] += g_alpha * ex  # ∂α/∂o = exp(-σ)
                    j1 = j0


@numba.njit(cache=True)
def _sum_per_gaussian(ids, grad_geom, grad_vals, g_means, g_conics, g_opacities, g_values):
    """Sum the intersections' gradients into their Gaussians, serially in intersection order
    (deterministic whatever the thread count)."""
    C = grad_vals.shape[1]
    for e in range(ids.shape[0]):
        i = ids[e]
        g_means[i, 0] += grad_geom[e, 0]
        g_means[i, 1] += grad_geom[e, 1]
        g_conics[i, 0] += grad_geom[e, 2]
        g_conics[i, 1] += grad_geom[e, 3]
        g_conics[i, 2] += grad_geom[e, 4]
        g_opacities[i] += grad_geom[e, 5]
        for ch in range(C):
            g_values[i, ch] += grad_vals[e, ch]


class _CompositeNumba(torch.autograd.Function):
    """The compiled compositor as an autograd node: ``acc [H, W, C]`` from the Gaussians'
    ``means2d``, ``conics``, ``opacities`` and ``values [M, C]`` binned in ``bins``. Keeps per
    pixel the final transmittance and the fragments walked (nothing per pair)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, values, bins: TileBins, width: int, height: int):
        C = values.shape[1]
        m, q, o, v, ids, starts, counts = as_arrays(means2d, conics, opacities, values, bins.ids,
                                                  bins.starts, bins.counts)
        out = np.zeros((height, width, C), np.float32)
        trans = np.ones((height, width), np.float32)
        walked = np.zeros((height, width), np.int64)
        with kernel_threads_scope():
            _forward(m, q, o, v, ids, starts, counts, bins.tiles_x, bins.tile_size, width, height,
                     out, trans, walked)
        ctx.arrays = (m, q, o, v, ids, starts, counts, trans, walked)
        ctx.grid = (bins.tiles_x, bins.tile_size, width, height)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_acc):
        m, q, o, v, ids, starts, counts, trans, walked = ctx.arrays
        g = grad_acc.detach().to(torch.float32).contiguous().numpy()
        grad_geom = np.zeros((ids.shape[0], 6), np.float32)
        grad_vals = np.zeros((ids.shape[0], v.shape[1]), np.float32)
        with kernel_threads_scope():
            _backward(m, q, o, v, ids, starts, counts, *ctx.grid, trans, walked, g, grad_geom,
                      grad_vals)
        g_means, g_conics = np.zeros_like(m), np.zeros_like(q)
        g_opacities, g_values = np.zeros_like(o), np.zeros_like(v)
        _sum_per_gaussian(ids, grad_geom, grad_vals, g_means, g_conics, g_opacities, g_values)
        return (torch.from_numpy(g_means), torch.from_numpy(g_conics),
                torch.from_numpy(g_opacities), torch.from_numpy(g_values), None, None, None)


def rasterize_tiles_numba(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                          depths: torch.Tensor, radii: torch.Tensor, values: torch.Tensor,
                          width: int, height: int, *, tile_size: int = 8,
                          stats: TileStats | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Alpha-composite projected Gaussians front to back with the compiled kernels: the inputs,
    outputs and rules of :func:`volcap_core.splat.rasterize.rasterize_tiles`.

    Args:
        means2d: ``[M, 2]`` px. conics: ``[M, 3]`` (a, b, c), 1/px². opacities: ``[M]`` (already
            compensated). depths: ``[M]`` sort key, front = smaller. radii: ``[M, 2]`` int px.
        values: ``[M, D]`` accumulated per pixel as ``Σ_i α_i T_i v_i`` (colours, depth...).
            All float32 on the CPU.
        width, height: image size (px). tile_size: square tile edge (px).
        stats: filled with the work bound, if given: ``pairs`` (tile pixels × Gaussians binned to
            the tile, as the PyTorch compositor counts them) and ``intersections``;
            ``padded_pairs`` = ``pairs`` (no padding here; pixels stop early, so fewer are
            evaluated), ``chunks`` unchanged.
    Returns:
        ``(accumulated [H, W, D], transmittance [H, W])``, differentiable to ``means2d``,
        ``conics``, ``opacities`` and ``values``.
    Raises:
        ValueError: a tensor not float32 or not on the CPU.
    """
    require_float32_cpu("compositor", {"means2d": means2d, "conics": conics, "opacities": opacities,
                                       "values": values})
    bins = bin_tiles(means2d, depths, radii, width, height, tile_size)
    D = values.shape[1]
    # a column of ones accumulates the pixel alpha (Σ α_i T_i) in the same walk
    with_alpha = torch.cat([values, values.new_ones(values.shape[0], 1)], 1)
    acc = _CompositeNumba.apply(means2d, conics, opacities, with_alpha, bins, width, height)
    if stats is not None:
        pairs = int(bins.ids.shape[0]) * tile_size * tile_size
        stats.pairs += pairs
        stats.padded_pairs += pairs
        stats.intersections += int(bins.ids.shape[0])
    return acc[..., :D], 1.0 - acc[..., D]
