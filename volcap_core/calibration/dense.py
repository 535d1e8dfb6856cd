"""Dense per-frame point clouds from calibrated cameras: a torch plane sweep per reference camera,
then fusion by cross-view depth consistency.

For each reference camera and its ``neighbours`` best-placed cameras:

1. sweep ``num_depths`` fronto-parallel planes, uniform in inverse depth over ``[depth_min,
   depth_max]``; each neighbour is warped onto the reference through the plane and compared with a
   windowed normalised cross-correlation (NCC, box filters); the cost of a depth is ``1 - NCC``
   averaged over the best ``neighbours - 1`` neighbours (one may be occluded);
2. refine around the best plane with ``refine_steps`` finer hypotheses (per-pixel depths) and a
   parabola through the three best costs;
3. keep pixels with NCC above ``min_ncc`` and enough texture.

Fusion: a reference pixel's 3D point is kept when at least ``min_consistent`` other depth maps see
it at the same depth (relative ``depth_tol``) where it projects. Colour: the reference camera's
linear RGB. Everything in float32 torch (GPU when ``device="cuda"``).

OpenCV's ``stereoRectify`` failed on strongly converging cameras (NOTES); the plane sweep needs no
rectification at all.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Mapping

import numpy as np
import torch
import torch.nn.functional as F

from volcap_core.calibration.images import exposure_normalise, luminance

Camera = tuple[np.ndarray, np.ndarray]   # K [3, 3], world_to_camera [4, 4]


@dataclass(frozen=True)
class DenseOptions:
    depth_min: float = 1.0
    depth_max: float = 14.0
    #: cap on the coarse planes / 4 (planes are spaced ~1.5 px of disparity at 1/4 resolution)
    num_depths: int = 96
    #: cap on the fine hypotheses either side of the coarse depth / 4
    refine_steps: int = 8
    neighbours: int = 3
    #: preferred angle (deg) between a reference and a neighbour at the scene
    min_angle_deg: float = 8.0
    max_angle_deg: float = 50.0
    window: int = 5
    min_ncc: float = 0.6
    min_texture: float = 0.01
    depth_tol: float = 0.01
    min_consistent: int = 1
    #: downscale factor of the images before matching (1 = full resolution)
    scale: float = 1.0
    device: str = "cpu"


@dataclass
class DepthMap:
    depth: np.ndarray       # [H, W] float32, 0 = invalid
    ncc: np.ndarray         # [H, W]
    K: np.ndarray
    world_to_camera: np.ndarray


def choose_neighbours(cameras: Mapping[str, Camera], ref: str, n: int, min_angle_deg: float = 8.0,
                      max_angle_deg: float = 50.0, scene_depth: float = 5.0) -> list[str]:
    """The ``n`` cameras whose view of the reference's scene point (``scene_depth`` m along its axis)
    is closest to 20-25° of triangulation angle within [min, max], nearest first."""
    K, W = cameras[ref]
    C = -W[:3, :3].T @ W[:3, 3]
    P = C + scene_depth * W[2, :3]
    scored = []
    for cid, (_, Wc) in cameras.items():
        if cid == ref:
            continue
        Cc = -Wc[:3, :3].T @ Wc[:3, 3]
        a, b = C - P, Cc - P
        ang = math.degrees(math.acos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1)))
        facing = Wc[2, :3] @ W[2, :3]
        if min_angle_deg <= ang <= max_angle_deg and facing > 0.3:
            scored.append((abs(ang - 22.0), cid))
    return [c for _, c in sorted(scored)[:n]]


def _prep(img: np.ndarray, scale: float) -> np.ndarray:
    import cv2

    g = luminance(exposure_normalise(np.asarray(img, np.float32)))
    g = np.sqrt(np.clip(g, 0, None)).astype(np.float32)           # roughly perceptual, noise-flattened
    if scale != 1.0:
        g = cv2.resize(g, None, fx=1 / scale, fy=1 / scale, interpolation=cv2.INTER_AREA)
    return g


def _scaled_K(K: np.ndarray, scale: float) -> np.ndarray:
    """Intrinsics of an image downscaled by ``scale`` (OpenCV centres: (x + 0.5) / s - 0.5)."""
    S = np.array([[1 / scale, 0, 0.5 / scale - 0.5], [0, 1 / scale, 0.5 / scale - 0.5], [0, 0, 1]])
    return S @ K


def _box(x: torch.Tensor, w: int) -> torch.Tensor:
    return F.avg_pool2d(x, w, stride=1, padding=w // 2, count_include_pad=False)


def _ncc(ref: torch.Tensor, warped: torch.Tensor, valid: torch.Tensor, w: int) -> torch.Tensor:
    """Windowed NCC of ref [1, 1, H, W] with warped [D, 1, H, W] -> [D, H, W] (-1 where invalid)."""
    mr = _box(ref, w)
    vr = (_box(ref * ref, w) - mr * mr).clamp(min=1e-8)
    mw = _box(warped, w)
    vw = (_box(warped * warped, w) - mw * mw).clamp(min=1e-8)
    cov = _box(ref * warped, w) - mr * mw
    ncc = cov / torch.sqrt(vr * vw)
    return torch.where(valid > 0.5, ncc, torch.full_like(ncc, -1.0))[:, 0]


def _warp(nb: torch.Tensor, Kr_inv: torch.Tensor, Rr: torch.Tensor, Cr: torch.Tensor, Kn: torch.Tensor,
          Rn: torch.Tensor, tn: torch.Tensor, depth: torch.Tensor, rays: torch.Tensor):
    """Sample neighbour image nb [1, 1, h, w] at the projections of reference pixels at depths
    ``depth`` [D, H, W]; ``rays`` [H, W, 3] reference camera rays with z = 1."""
    D, H, W = depth.shape
    Xc = rays[None] * depth[..., None]                                     # [D, H, W, 3] ref camera
    Xw = (Xc - 0) @ Rr + Cr                                                # world: R^T x + C
    Xn = Xw @ Rn.T + tn
    z = Xn[..., 2:3]
    uv = Xn[..., :2] / z.clamp(min=1e-6) @ Kn[:2, :2].T + Kn[:2, 2]
    h, w = nb.shape[-2:]
    gx = 2 * (uv[..., 0] + 0.5) / w - 1
    gy = 2 * (uv[..., 1] + 0.5) / h - 1
    grid = torch.stack([gx, gy], -1)
    out = F.grid_sample(nb.expand(D, -1, -1, -1), grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    valid = ((gx.abs() < 1) & (gy.abs() < 1) & (z[..., 0] > 0)).to(out.dtype)[:, None]
    return out, valid


def _sweep_setup(images, cameras, ref, neighbours, scale, t32):
    gr = _prep(images[ref], scale)
    H, W = gr.shape
    Kr = _scaled_K(cameras[ref][0], scale)
    Wr = cameras[ref][1]
    Rr = torch.as_tensor(Wr[:3, :3], **t32)
    Cr = torch.as_tensor(-Wr[:3, :3].T @ Wr[:3, 3], **t32)
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    rays = torch.as_tensor(np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(Kr).T.astype(np.float32), **t32)
    nbs = []
    for nb in neighbours:
        gn = _prep(images[nb], scale)
        Kn = torch.as_tensor(_scaled_K(cameras[nb][0], scale), **t32)
        Wn = cameras[nb][1]
        nbs.append((torch.as_tensor(gn, **t32)[None, None], Kn, torch.as_tensor(Wn[:3, :3], **t32),
                    torch.as_tensor(Wn[:3, 3], **t32)))
    return torch.as_tensor(gr, **t32)[None, None], Kr, Wr, Rr, Cr, rays, nbs


def _cost_fn(ref_t, Rr, Cr, rays, nbs, window):
    def cost(depths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        nccs = []
        for img, Kn, Rn, tn in nbs:
            warped, valid = _warp(img, None, Rr, Cr, Kn, Rn, tn, depths, rays)
            nccs.append(_ncc(ref_t, warped, valid, window))
        ncc = torch.stack(nccs)                                            # [N, D, H, W]
        k = max(1, len(nbs) - 1)
        best = ncc.topk(k, dim=0).values.mean(0)
        return 1 - best, best
    return cost


def _chunked(cost, depths: torch.Tensor, chunk: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    cs, ns = [], []
    for i in range(0, len(depths), chunk):
        c, n = cost(depths[i:i + chunk])
        cs.append(c)
        ns.append(n)
    return torch.cat(cs), torch.cat(ns)


def depth_map(images: Mapping[str, np.ndarray], cameras: Mapping[str, Camera], ref: str, neighbours: list[str],
              options: DenseOptions = DenseOptions()) -> DepthMap:
    """Plane-sweep depth of camera ``ref`` (at the working resolution: images / ``options.scale``).

    Two levels: a sweep at 1/2 of the working resolution with planes ~1 px of disparity apart, then
    per-pixel hypotheses at the working resolution, 0.5 px apart, over two coarse steps either side.
    """
    dev = torch.device(options.device)
    t32 = dict(dtype=torch.float32, device=dev)
    s = options.scale
    # disparity per unit of inverse depth for the widest neighbour (px at the working resolution)
    Cref = -cameras[ref][1][:3, :3].T @ cameras[ref][1][:3, 3]
    base = max(np.linalg.norm(-cameras[n][1][:3, :3].T @ cameras[n][1][:3, 3] - Cref) for n in neighbours)
    fpx = cameras[ref][0][0, 0] / s
    inv_lo, inv_hi = 1 / options.depth_max, 1 / options.depth_min
    # coarse level
    cs = 2.0
    ref_c, _, _, Rr, Cr, rays_c, nbs_c = _sweep_setup(images, cameras, ref, neighbours, s * cs, t32)
    n_planes = int(np.clip((inv_hi - inv_lo) * fpx / cs * base / 1.0, 8, options.num_depths * 8))
    inv = torch.linspace(inv_lo, inv_hi, n_planes, **t32)
    Hc, Wc = ref_c.shape[-2:]
    cost_c = _cost_fn(ref_c, Rr, Cr, rays_c, nbs_c, options.window)
    c1, _ = _chunked(cost_c, (1 / inv)[:, None, None].expand(-1, Hc, Wc))
    inv_c = inv[c1.argmin(0)]
    # fine level
    ref_t, Kr, Wr, Rr, Cr, rays, nbs = _sweep_setup(images, cameras, ref, neighbours, s, t32)
    H, W = ref_t.shape[-2:]
    inv0 = F.interpolate(inv_c[None, None], size=(H, W), mode="nearest")[0, 0]
    coarse_step = (inv[1] - inv[0]) if n_planes > 1 else torch.tensor(0.01, **t32)
    fine_step = 0.5 / (fpx * base)
    nk = int(min(max(2 * float(coarse_step) / fine_step, 2), 4 * options.refine_steps))
    ks = torch.arange(-nk, nk + 1, **t32) * fine_step
    invs = (inv0[None] + ks[:, None, None]).clamp(min=1e-4)
    cost = _cost_fn(ref_t, Rr, Cr, rays, nbs, options.window)
    c2, n2 = _chunked(cost, 1 / invs)
    j = c2.argmin(0)
    jc = j.clamp(1, len(ks) - 2)
    cm = c2.gather(0, (jc - 1)[None])[0]
    c0 = c2.gather(0, jc[None])[0]
    cp = c2.gather(0, (jc + 1)[None])[0]
    den = cm - 2 * c0 + cp
    off = torch.where(den > 1e-6, 0.5 * (cm - cp) / den, torch.zeros_like(den)).clamp(-0.5, 0.5)
    inv_best = invs.gather(0, jc[None])[0] + off * fine_step
    depth = 1 / inv_best.clamp(min=1e-6)
    ncc = n2.gather(0, j[None])[0]
    tex = torch.sqrt((_box(ref_t * ref_t, options.window) - _box(ref_t, options.window) ** 2).clamp(min=0))[0, 0]
    ok = (ncc > options.min_ncc) & (tex > options.min_texture) & (j > 0) & (j < len(ks) - 1)
    ok &= (depth > options.depth_min) & (depth < options.depth_max)
    depth = torch.where(ok, depth, torch.zeros_like(depth))
    return DepthMap(depth.cpu().numpy(), ncc.cpu().numpy(), Kr, Wr)


def fuse_depth_maps(maps: Mapping[str, DepthMap], images: Mapping[str, np.ndarray], options: DenseOptions
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points [N, 3] float32, linear colours [N, 3] float32 and consistent-view counts [N]."""
    import cv2

    pts, cols, cnts = [], [], []
    for rid, dm in maps.items():
        H, W = dm.depth.shape
        v, u = np.nonzero(dm.depth > 0)
        if len(u) == 0:
            continue
        z = dm.depth[v, u].astype(np.float64)
        rays = np.stack([u, v, np.ones_like(u)], 1).astype(np.float64) @ np.linalg.inv(dm.K).T
        Xc = rays * z[:, None]
        R, t = dm.world_to_camera[:3, :3], dm.world_to_camera[:3, 3]
        X = (Xc - t) @ R
        count = np.zeros(len(X), np.int64)
        for oid, om in maps.items():
            if oid == rid:
                continue
            Ro, to = om.world_to_camera[:3, :3], om.world_to_camera[:3, 3]
            Xo = X @ Ro.T + to
            zo = Xo[:, 2]
            uo = Xo[:, :2] / np.maximum(zo, 1e-9)[:, None] @ om.K[:2, :2].T + om.K[:2, 2]
            ui = np.round(uo[:, 0]).astype(int)
            vi = np.round(uo[:, 1]).astype(int)
            inside = (zo > 0) & (ui >= 0) & (vi >= 0) & (ui < om.depth.shape[1]) & (vi < om.depth.shape[0])
            d = np.zeros(len(X))
            d[inside] = om.depth[vi[inside], ui[inside]]
            count += (inside & (d > 0) & (np.abs(d - zo) < options.depth_tol * zo)).astype(np.int64)
        keep = count >= options.min_consistent
        img = np.asarray(images[rid], np.float32)[..., :3]
        if options.scale != 1.0:
            img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
        pts.append(X[keep].astype(np.float32))
        cols.append(img[v[keep], u[keep]].astype(np.float32))
        cnts.append(count[keep])
    if not pts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
    return np.concatenate(pts), np.concatenate(cols), np.concatenate(cnts)


def _valid_at(valid: np.ndarray, shape: tuple[int, int], window: int) -> np.ndarray:
    """A full-resolution validity mask at a depth map's ``shape``: a pixel is kept when its whole
    NCC window (``window`` px at that resolution) lies in valid pixels."""
    import cv2

    v = np.asarray(valid, np.float32)
    if v.shape != shape:
        v = cv2.resize(v, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    ok = (v >= 0.999).astype(np.uint8)
    if window > 1:
        ok = cv2.erode(ok, np.ones((window, window), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=1)
    return ok.astype(bool)


#: a camera's sweep around the static scene it sees: from this fraction of its 1st-percentile depth
#: to this multiple of its 99th (:func:`sweep_range`): room for performers nearer than the set and
#: for what the percentiles cut
DEPTH_MARGIN = (0.7, 1.4)


def sweep_range(scene_depth_m: tuple[float, float, float]) -> tuple[float, float, float]:
    """A reference camera's sweep ``(nearest, neighbours', farthest)`` depth (metres; see
    :func:`dense_points`) from its view of the scene ``(1st percentile, median, 99th percentile)``
    depth: ``DEPTH_MARGIN`` times the outer two, its neighbours chosen at the median."""
    return (DEPTH_MARGIN[0] * float(scene_depth_m[0]), float(scene_depth_m[1]),
            DEPTH_MARGIN[1] * float(scene_depth_m[2]))


def dense_points(images: Mapping[str, np.ndarray], cameras: Mapping[str, Camera], *,
                 references: list[str] | None = None, options: DenseOptions = DenseOptions(),
                 valid: Mapping[str, np.ndarray | None] | None = None,
                 sweeps: Mapping[str, tuple[float, float, float]] | None = None) -> dict:
    """One frame's dense point cloud from calibrated views.

    ``images``: id -> linear RGB [H, W, 3]; ``cameras``: id -> (K [3, 3], world_to_camera [4, 4]);
    ``references``: cameras that get a depth map (default: all with enough neighbours);
    ``valid``: id -> [H, W] bool, the pixels that hold footage (a rectified distorted frame's
    :func:`~volcap_core.calibration.distortion.rectified_valid`; None or absent: all): a reference
    pixel whose NCC window reaches outside them gets no depth (the black border's edge is texture
    that matches nothing real);
    ``sweeps``: id -> the reference's ``(nearest, neighbours', farthest)`` depth in metres: it sweeps
    from the nearest to the farthest, its neighbours chosen for their triangulation angle at the
    middle one (:func:`sweep_range` of a calibration's ``CameraCalibration.scene_depth_m``); a
    reference without one sweeps ``options.depth_min``-``depth_max``, neighbours chosen at 5 m.
    Returns ``positions`` [N, 3] float32 (metres, stage frame), ``colours`` [N, 3] float32 (linear),
    ``views`` [N] consistent other views, ``depth_maps`` {id: DepthMap}, ``seconds``.
    """
    t0 = time.perf_counter()
    ids = sorted(set(images) & set(cameras))
    refs = references or ids
    maps = {}
    for r in refs:
        lo, middle, hi = (sweeps or {}).get(r, (options.depth_min, 5.0, options.depth_max))
        nbs = choose_neighbours({c: cameras[c] for c in ids}, r, options.neighbours, options.min_angle_deg,
                                options.max_angle_deg, scene_depth=float(middle))
        if not nbs:
            continue
        dm = depth_map(images, cameras, r, nbs, replace(options, depth_min=float(lo), depth_max=float(hi)))
        if valid is not None and valid.get(r) is not None:
            dm.depth[~_valid_at(valid[r], dm.depth.shape, options.window)] = 0.0
        maps[r] = dm
    pos, col, cnt = fuse_depth_maps(maps, images, options)
    return {"positions": pos, "colours": col, "views": cnt, "depth_maps": maps, "seconds": time.perf_counter() - t0}
