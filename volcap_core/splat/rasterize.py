"""Pure-PyTorch Gaussian splatting (projection + tiled alpha compositing), differentiable through
autograd. The CPU back-end of :func:`volcap_core.splat.render.render`.

It reproduces gsplat's ``rasterization(..., rasterize_mode="antialiased")`` conventions, so the two
back-ends agree on the same inputs:

* EWA projection with gsplat's clamp of the Jacobian to 1.3× the field of view; pixel centres at
  ``+0.5``; 2D covariance dilated by ``eps2d = 0.3`` px² and the opacity multiplied by the
  Mip-Splatting compensation ``sqrt(det Σ / det(Σ + 0.3 I))``;
* culling: depth outside ``(near, far)``, compensated opacity below 1/255, footprint off-image;
* footprint ``radius = ceil(min(3.33, sqrt(2 ln(255 o))) · σ_axis)`` per axis (the box that holds
  every fragment with α >= 1/255, so tiling never changes the image); not clamped to the image
  (only capped at 2^30 px for int32): the tile range is clipped to the tile grid instead, so a
  large Gaussian centred off-image or near an edge keeps every fragment that lands on the image;
* per pixel, front to back by camera depth: ``α = min(0.999, o · exp(-σ))``, fragments with
  α < 1/255 skipped, compositing stops before the fragment that would bring the transmittance to
  ``<= 1e-4``; gradients do not flow through these selections (as in gsplat).

How it is fast enough on a CPU: Gaussians are binned into small square tiles (default 8 px), each
tile's Gaussians sorted by depth and padded to a common length within a chunk of tiles of similar
load, and the Mahalanobis term of every (pixel, Gaussian) pair is a single batched matmul: in
tile-local coordinates ``σ - ln o`` is a quadratic form in the pixel position, i.e.
``[x², y², xy, x, y, 1] · coefficients(Gaussian)``. Transmittance is a cumulative sum of
``log(1 - α)``. The compositing has a hand-written backward (:class:`_Composite`) that recomputes
the per-pair terms instead of storing them, so memory is bounded by the chunk size
(``chunk_pairs`` pairs at a time) in forward and backward alike, whatever the image or the number
of Gaussians: autograd keeps only O(tiles × Gaussians per tile) between the passes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from volcap_core.splat.camera import Camera

__all__ = ["Projected", "TileBins", "TileStats", "bin_tiles", "project_gaussians",
           "quat_scale_to_covar", "rasterize_tiles"]

ALPHA_THRESHOLD = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
EPS2D = 0.3
EXTEND_MAX = 3.33
#: cap on the int32 footprint radii (px): far above any image, far below int32 overflow
RADIUS_MAX = 1 << 30
#: ln of the opacity given to padding slots: exp(-1e4) == 0 exactly, so they never contribute.
_DUMMY_LOG_OPACITY = -1e4


def quat_scale_to_covar(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """``Σ = R diag(s)² Rᵀ``.

    Args:
        quats: ``[N, 4]`` wxyz (normalised here; a zero quaternion gives R = I, not NaN).
        scales: ``[N, 3]`` standard deviations (metres).
    Returns:
        ``[N, 3, 3]`` covariances (metres²).
    """
    q = torch.nn.functional.normalize(quats, dim=-1, eps=1e-8)
    w, x, y, z = q.unbind(-1)
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)
    M = R * scales[:, None, :]
    return M @ M.transpose(1, 2)


@dataclass
class Projected:
    """Screen-space Gaussians that survived culling (M of the N given).

    Attributes:
        ids: ``[M]`` int64 indices into the input Gaussians.
        means2d: ``[M, 2]`` pixel coordinates (x right, y down; pixel (u, v) centre at u+.5, v+.5).
        conics: ``[M, 3]`` inverse of the dilated 2D covariance, ``(a, b, c)`` of
            ``[[a, b], [b, c]]`` in 1/px².
        opacities: ``[M]`` opacity times the antialiasing compensation.
        depths: ``[M]`` camera-space z (metres).
        radii: ``[M, 2]`` int32 footprint half-extents (px), not differentiable; not clamped to
            the image (capped at :data:`RADIUS_MAX`).
    """

    ids: torch.Tensor
    means2d: torch.Tensor
    conics: torch.Tensor
    opacities: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor


def _project(means, covars, opacities, camera: Camera, eps2d: float, antialiased: bool):
    """Per-Gaussian screen-space quantities (gsplat's ``persp_proj`` + ``add_blur``)."""
    W = camera.world_to_camera.to(means)
    K = camera.K.to(means)
    R, t = W[:3, :3], W[:3, 3]
    mc = means @ R.T + t                                   # [N, 3]
    cc = R @ covars @ R.T                                  # [N, 3, 3]
    x, y, z = mc.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w, h = camera.width, camera.height
    # gsplat clamps the point used in the Jacobian to 1.3x the field of view: a Gaussian far off
    # screen must not get a huge, badly conditioned footprint from the perspective derivative
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    lim_xp, lim_xn = (w - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (h - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    tx = z * torch.clamp(x / z, min=-lim_xn, max=lim_xp)
    ty = z * torch.clamp(y / z, min=-lim_yn, max=lim_yp)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / (z * z),
                     zero, fy / z, -fy * ty / (z * z)], dim=-1).reshape(-1, 2, 3)
    cov2d = J @ cc @ J.transpose(1, 2)                     # [N, 2, 2]
    a0, b0, c0 = cov2d[:, 0, 0], 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0]), cov2d[:, 1, 1]
    det0 = a0 * c0 - b0 * b0
    a, c = a0 + eps2d, c0 + eps2d
    det = a * c - b0 * b0
    if antialiased:
        comp = torch.sqrt(torch.clamp(det0 / det, min=0.0))
        opac = opacities * comp
    else:
        opac = opacities
    conics = torch.stack([c / det, -b0 / det, a / det], dim=-1)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)
    return means2d, a, c, det, conics, opac, z


def project_gaussians(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                      opacities: torch.Tensor, camera: Camera, *, eps2d: float = EPS2D,
                      antialiased: bool = True) -> Projected:
    """Project 3D Gaussians into ``camera`` and cull, gsplat-style.

    Culling is decided without gradient on all Gaussians; the differentiable quantities are then
    recomputed for the survivors only. So a culled Gaussian (behind the camera, at the camera plane,
    degenerate, any non-finite projected quantity) contributes exactly zero gradient instead of
    ``0 · inf = NaN``.

    Args:
        means: ``[N, 3]`` world positions. quats: ``[N, 4]`` wxyz. scales: ``[N, 3]`` (metres).
        opacities: ``[N]`` in [0, 1].
        camera: the view.
        eps2d: 2D dilation (px²). antialiased: apply the Mip-Splatting opacity compensation.
    Returns:
        :class:`Projected` for the M surviving Gaussians.
    """
    with torch.no_grad():
        z_all = means @ camera.world_to_camera[2, :3].to(means) + camera.world_to_camera[2, 3]
        ok = (z_all > camera.near) & (z_all < camera.far)
        # culled Gaussians get a stand-in 1 m in front of the camera so nothing below divides by
        # z <= 0 (their results are discarded)
        ahead = camera.centre.to(means) + camera.world_to_camera[2, :3].to(means)
        safe_means = torch.where(ok[:, None], means, ahead)
        covars = quat_scale_to_covar(quats, scales)
        m2d, a, c, det, conics, opac, z = _project(safe_means, covars, opacities, camera, eps2d,
                                                   antialiased)
        ok &= (det > 0) & torch.isfinite(det) & torch.isfinite(m2d).all(-1) & torch.isfinite(opac)
        ok &= torch.isfinite(conics).all(-1) & torch.isfinite(z)
        ok &= opac >= ALPHA_THRESHOLD
        extend = torch.clamp(torch.sqrt(2.0 * torch.log(opac.clamp(min=ALPHA_THRESHOLD)
                                                        / ALPHA_THRESHOLD)), max=EXTEND_MAX)
        rx = torch.ceil(extend * torch.sqrt(a.clamp(min=0)))
        ry = torch.ceil(extend * torch.sqrt(c.clamp(min=0)))
        ok &= (rx > 0) | (ry > 0)
        ok &= ~((m2d[:, 0] + rx <= 0) | (m2d[:, 0] - rx >= camera.width)
                | (m2d[:, 1] + ry <= 0) | (m2d[:, 1] - ry >= camera.height))
        ids = torch.nonzero(ok).squeeze(1)
        # NOT clamped to the image: a large Gaussian centred off-image or near an edge needs its
        # whole footprint for its tile range (rasterize_tiles clips the range to the tile grid, as
        # gsplat does). Clamping it to the image size cut such Gaussians along tile lines or
        # dropped them. Only capped so the int32 cannot overflow (a footprint of 2^30 px).
        radii = torch.stack([rx[ids], ry[ids]], dim=-1).clamp(max=RADIUS_MAX).to(torch.int32)
    covars = quat_scale_to_covar(quats[ids], scales[ids])
    m2d, _, _, _, conics, opac, z = _project(means[ids], covars, opacities[ids], camera, eps2d,
                                             antialiased)
    return Projected(ids=ids, means2d=m2d, conics=conics, opacities=opac, depths=z, radii=radii)


@dataclass
class TileStats:
    """What a rasterization cost: ``pairs`` (pixel, Gaussian) pairs inside the tile footprints
    (tile pixels × Gaussians binned to the tile), ``padded_pairs`` as evaluated after padding,
    ``intersections`` (tile, Gaussian) entries, ``chunks``."""

    pairs: int = 0
    padded_pairs: int = 0
    intersections: int = 0
    chunks: int = 0


def _pixel_monomials(tile_size: int, device, dtype) -> torch.Tensor:
    """``[P, 6]`` monomials (x², y², xy, x, y, 1) of the pixel centres relative to the tile centre,
    row-major within the tile."""
    r = torch.arange(tile_size, device=device, dtype=dtype) + 0.5 - tile_size / 2
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    x, y = xx.reshape(-1), yy.reshape(-1)
    return torch.stack([x * x, y * y, x * y, x, y, torch.ones_like(x)], dim=-1)


def _forward_terms(coef: torch.Tensor, monomials: torch.Tensor):
    """Per-pair compositing terms of one chunk (no autograd; shared by forward and backward).

    Returns ``alpha [T,P,K]`` (after the 0.999 clamp, the 1/255 threshold and the early stop; 0
    where unused), ``one_minus [T,P,K]`` (1 - alpha) and ``trans [T,P,K]`` (T_i, the transmittance
    in front of each fragment). In-place ops throughout: each pass over the pairs costs ~1 ns each.
    """
    # clamp before exp: far pixels have ln o - σ of -100s, whose exp is a float32 denormal, and
    # denormal arithmetic is ~10x slower on x86 (below e^-20 it is skipped as α < 1/255 anyway)
    alpha = torch.matmul(monomials, coef).clamp_(min=-20.0).exp_()  # o·exp(-σ), [T, P, K]
    alpha.clamp_(max=ALPHA_MAX)
    F.threshold_(alpha, ALPHA_THRESHOLD - 1e-12, 0.0)         # skip α < 1/255
    one_minus = torch.rsub(alpha, 1.0)
    # log(1 - α) rather than log1p(-α): α is 0 or >= 1/255 here, so nothing cancels, and log is
    # vectorised on CPU where log1p is not (2-3x faster)
    log_t = torch.log(one_minus)
    log_incl = torch.cumsum(log_t, dim=-1)
    # stop before the fragment that would take transmittance to <= 1e-4; log_incl only decreases
    # along K, so this drops a suffix of each pixel's list
    stop = log_incl <= math.log(TRANSMITTANCE_MIN)
    alpha.masked_fill_(stop, 0.0)
    one_minus.masked_fill_(stop, 1.0)
    # exclusive: T_i = Π_{j<i}(1 - α_j); clamped for the same denormal reason (T < 1e-4 is unused)
    trans = log_incl.sub_(log_t).clamp_(min=-20.0).exp_()
    return alpha, one_minus, trans


class _Composite(torch.autograd.Function):
    """Front-to-back compositing of one chunk of tiles with an analytic backward.

    ``values`` carries a last column of ones, so the accumulated last channel is ``Σ_i α_i T_i``,
    i.e. the pixel's alpha (1 - final transmittance) for free in the same matmul.

    Nothing per (pixel, Gaussian) pair is kept between forward and backward: the backward
    recomputes the terms from ``coef`` (one small matmul), so memory is O(tiles × Gaussians per
    tile), not O(pairs). With ``acc = Σ_i w_i v_i``, ``w_i = α_i T_i``, ``c_i = ⟨∂L/∂acc, v_i⟩`` and
    ``S_i = Σ_{j>i} w_j c_j``: ``∂L/∂α_i = T_i c_i - S_i / (1 - α_i)``; no gradient flows through
    the clamp, the threshold or the early stop (gsplat does the same).
    """

    @staticmethod
    def forward(ctx, coef, values, monomials):
        alpha, _, trans = _forward_terms(coef, monomials)
        ctx.save_for_backward(coef, values, monomials)
        return torch.matmul(alpha.mul_(trans), values)        # weights α_i T_i, [T, P, D]

    @staticmethod
    def backward(ctx, g_acc):
        coef, values, monomials = ctx.saved_tensors
        alpha, one_minus, trans = _forward_terms(coef, monomials)
        slope = alpha.masked_fill(alpha >= ALPHA_MAX, 0.0)     # dα/d(ln o - σ) = α if unclamped
        weights = alpha.mul_(trans)
        g_values = torch.matmul(weights.transpose(1, 2), g_acc)  # [T, K, D]
        c = torch.matmul(g_acc, values.transpose(1, 2))          # [T, P, K]
        wc = weights.mul_(c)
        incl = torch.cumsum(wc, dim=-1)
        suffix = torch.sub(incl[..., -1:], incl, out=incl)       # Σ_{j>i} w_j c_j
        g_alpha = trans.mul_(c).sub_(suffix.div_(one_minus))
        g_coef = torch.matmul(monomials.T, g_alpha.mul_(slope))  # [T, 6, K]
        return g_coef, g_values, None


def _composite_chunk(table: torch.Tensor, values: torch.Tensor, idx: torch.Tensor,
                     centres: torch.Tensor, monomials: torch.Tensor) -> torch.Tensor:
    """Composite one chunk of tiles.

    Args:
        table: ``[M+1, 6]`` per Gaussian (x, y, a, b, c, ln o); last row is the padding dummy.
        values: ``[M+1, D]`` per-Gaussian values to accumulate (colour channels, depth).
        idx: ``[T, K]`` Gaussian index per tile slot, front to back, padded with M.
        centres: ``[T, 2]`` tile centres (px).
        monomials: ``[P, 6]`` from :func:`_pixel_monomials`.
    Returns:
        ``[T, P, D]``: accumulated values (the last column of ``values`` being ones, the last
        channel is the alpha).
    """
    g = table[idx]                                            # [T, K, 6]
    mx = g[..., 0] - centres[:, None, 0]
    my = g[..., 1] - centres[:, None, 1]
    a, b, c, log_o = g[..., 2], g[..., 3], g[..., 4], g[..., 5]
    # ln o - σ = ln o - ½a(x-mx)² - ½c(y-my)² - b(x-mx)(y-my), expanded in the pixel monomials;
    # tile-local coordinates keep the expansion's cancellation small (|x|, |y| <= tile / 2)
    coef = torch.stack([-0.5 * a, -0.5 * c, -b, a * mx + b * my, c * my + b * mx,
                        log_o - 0.5 * a * mx * mx - 0.5 * c * my * my - b * mx * my], dim=1)
    return _Composite.apply(coef, values[idx], monomials)


def _zero_link(*tensors: torch.Tensor) -> torch.Tensor | None:
    """A scalar exactly 0 in the autograd graph of those ``tensors`` that require grad (0, not
    NaN, even for non-finite inputs; zero gradient to each); None when none requires grad."""
    out = None
    for t in tensors:
        if t.requires_grad:
            z = torch.where(torch.zeros_like(t, dtype=torch.bool), t, 0.0).sum()
            out = z if out is None else out + z
    return out


def _tile_range(lo: torch.Tensor, hi: torch.Tensor, ts: int, n: int):
    """Half-open tile index range ``[first, last)`` covering pixel interval ``[lo, hi]``, clipped
    to ``[0, n]`` (empty when the interval misses the grid or is NaN). Float64 in, int64 out: the
    division, rounding and clipping happen before the cast, so nothing can overflow."""
    first = torch.nan_to_num(torch.floor(lo / ts), nan=float(n)).clamp(0, n).long()
    last = torch.nan_to_num(torch.ceil(hi / ts), nan=0.0).clamp(0, n).long()
    return first, torch.maximum(last, first)


@dataclass
class TileBins:
    """Projected Gaussians binned to square tiles, front to back within each tile: what every
    compositor reads (:func:`rasterize_tiles`, :func:`volcap_core.splat.composite_numba
    .rasterize_tiles_numba`).

    Tiles are numbered row-major, ``tile = ty * tiles_x + tx``, tile ``(tx, ty)`` covering pixels
    ``[tx·s, (tx+1)·s) × [ty·s, (ty+1)·s)`` (``s = tile_size``; the last row and column may reach
    past the image).

    Attributes:
        tile_size: tile edge (px). tiles_x, tiles_y: the tile grid.
        ids: ``[I]`` int64 Gaussian index of each (tile, Gaussian) intersection, grouped by tile in
            tile order, front to back (ascending depth, ties in input order) within a tile.
        starts: ``[tiles]`` int64 offset of each tile's run in ``ids``.
        counts: ``[tiles]`` int64 length of each tile's run (0 for an empty tile).
    """

    tile_size: int
    tiles_x: int
    tiles_y: int
    ids: torch.Tensor
    starts: torch.Tensor
    counts: torch.Tensor


def bin_tiles(means2d: torch.Tensor, depths: torch.Tensor, radii: torch.Tensor, width: int,
              height: int, tile_size: int = 8) -> TileBins:
    """Bin each Gaussian to every tile its footprint box touches and sort each tile by depth.

    Args:
        means2d: ``[M, 2]`` px. depths: ``[M]`` sort key, front = smaller. radii: ``[M, 2]`` int
            footprint half-extents (px), not clamped to the image: the tile range is clipped to
            the grid instead, and a NaN centre bins nowhere.
        width, height: image size (px). tile_size: tile edge (px).
    Returns:
        :class:`TileBins` (no gradient: binning only selects).
    """
    ts = tile_size
    tw, th = -(-width // ts), -(-height // ts)
    with torch.no_grad():
        # tile ranges in float64 (exact for int32 radii and float32 means, no overflow whatever
        # the footprint), clipped to the tile grid before the cast (a NaN gives an empty range)
        r = radii.to(torch.float64)
        m = means2d.detach().to(torch.float64)
        x0, x1 = _tile_range(m[:, 0] - r[:, 0], m[:, 0] + r[:, 0], ts, tw)
        y0, y1 = _tile_range(m[:, 1] - r[:, 1], m[:, 1] + r[:, 1], ts, th)
        nx = x1 - x0
        count = nx * (y1 - y0)
        order = torch.argsort(depths.detach(), stable=True)   # front to back
        cnt_o = count[order]
        n_isect = int(cnt_o.sum())
        gid = torch.repeat_interleave(order, cnt_o)
        start = torch.repeat_interleave(torch.cumsum(cnt_o, 0) - cnt_o, cnt_o)
        local = torch.arange(n_isect, device=means2d.device) - start
        tile = (y0[gid] + local // nx[gid]) * tw + x0[gid] + local % nx[gid]
        tile, perm = torch.sort(tile, stable=True)            # stable: keeps depth order per tile
        gid = gid[perm]
        counts = torch.bincount(tile, minlength=tw * th)
        starts = torch.cumsum(counts, 0) - counts
    return TileBins(ts, tw, th, gid, starts, counts)


def rasterize_tiles(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                    depths: torch.Tensor, radii: torch.Tensor, values: torch.Tensor,
                    width: int, height: int, *, tile_size: int = 8,
                    chunk_pairs: int = 1 << 21, pad_ratio: float = 0.7,
                    stats: TileStats | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Alpha-composite projected Gaussians front to back (see module doc for the rules).

    Args:
        means2d: ``[M, 2]`` px. conics: ``[M, 3]`` (a, b, c), 1/px². opacities: ``[M]`` (already
            compensated). depths: ``[M]`` sort key, front = smaller. radii: ``[M, 2]`` int px.
        values: ``[M, D]`` accumulated per pixel as ``Σ_i α_i T_i v_i`` (colours, depth...).
        width, height: image size (px).
        tile_size: square tile edge (px); 8 wastes fewer pairs on small splats than gsplat's 16.
        chunk_pairs: target padded (pixel, Gaussian) pairs per chunk: bounds the temporaries
            (~6 float tensors of that many elements, ~50 MB at the default 2M) in forward and
            backward alike; nothing per pair is kept between them.
        pad_ratio: a chunk only holds tiles with at least this fraction of its largest tile's
            Gaussian count (padding waste <= 1 / pad_ratio).
        stats: filled with the work done, if given.
    Returns:
        ``(accumulated [H, W, D], transmittance [H, W])``.
    """
    device, dtype = means2d.device, means2d.dtype
    D = values.shape[1]
    ts = tile_size
    bins = bin_tiles(means2d, depths, radii, width, height, ts)
    tw, th = bins.tiles_x, bins.tiles_y
    n_tiles = tw * th
    P = ts * ts
    M = means2d.shape[0]
    gid, tile_start, counts = bins.ids, bins.starts, bins.counts
    n_isect = gid.shape[0]
    with torch.no_grad():
        busy = torch.nonzero(counts).squeeze(1)
        busy = busy[torch.argsort(counts[busy], descending=True, stable=True)]
        busy_counts = counts[busy].cpu().numpy()
    total_pairs = n_isect * P
    table = torch.cat([torch.stack([means2d[:, 0], means2d[:, 1], conics[:, 0], conics[:, 1],
                                    conics[:, 2], torch.log(opacities.clamp(min=1e-30))], -1),
                       torch.tensor([[0, 0, 0, 0, 0, _DUMMY_LOG_OPACITY]], device=device,
                                    dtype=dtype)])
    # a column of ones accumulates the alpha; the padding dummy (last row) is all zeros
    vals = torch.cat([torch.cat([values, values.new_ones(M, 1)], 1), values.new_zeros(1, D + 1)])
    monomials = _pixel_monomials(ts, device, dtype)
    outs, out_tiles = [], []
    i, n_busy, padded = 0, len(busy_counts), 0
    while i < n_busy:
        k = int(busy_counts[i])                                # largest count in this chunk
        n = int(np.clip(chunk_pairs // max(k * P, 1), 1, n_busy - i))
        # only tiles with at least `pad_ratio` of this load share a chunk: bounds padding waste
        n = max(1, int(np.searchsorted(-busy_counts[i:i + n], -pad_ratio * k, side="right")))
        tids = busy[i:i + n]
        slots = torch.arange(k, device=device)
        pos = tile_start[tids][:, None] + slots
        idx = torch.where(slots < counts[tids][:, None], gid[pos.clamp(max=n_isect - 1)], M)
        centres = torch.stack([(tids % tw) * ts + ts / 2, (tids // tw) * ts + ts / 2],
                              -1).to(dtype)
        outs.append(_composite_chunk(table, vals, idx, centres, monomials))
        out_tiles.append(tids)
        padded += n * k * P
        i += n
    base = torch.zeros(n_tiles, P, D + 1, device=device, dtype=dtype)
    if outs:
        base = base.index_copy(0, torch.cat(out_tiles), torch.cat(outs))
    elif (link := _zero_link(means2d, conics, opacities, values)) is not None:
        # nothing drawn (no Gaussians, or none reaches a tile): an exact-zero term that links the
        # image to the inputs, so backward works and gives them zero gradient
        base = base + link
    img = base.reshape(th, tw, ts, ts, D + 1).permute(0, 2, 1, 3, 4)
    img = img.reshape(th * ts, tw * ts, D + 1)
    img = img[:height, :width]
    if stats is not None:
        stats.pairs += total_pairs
        stats.padded_pairs += padded
        stats.intersections += n_isect
        stats.chunks += len(outs)
    return img[..., :D], 1.0 - img[..., D]
