"""Dense per-frame point clouds from calibrated cameras: a torch plane sweep per reference camera,
then fusion by cross-view depth consistency.

For each reference camera and its ``neighbours`` best-placed cameras:

1. sweep ``num_depths`` fronto-parallel planes, uniform in inverse depth over ``[depth_min,
   depth_max]``; each neighbour is warped onto the reference through the plane and compared with a
   windowed normalised cross-correlation (NCC, box filters); the cost of a depth is ``1 - NCC``
   averaged over the best ``neighbours - 1`` neighbours (one may be occluded);
   (at half the working resolution; above ``coarse_quarter_above_px`` wide at a quarter, half the
   planes on a sixteenth of the pixels, then refined per pixel at half: the planes grow with the
   width, so this level was most of the time at 640 px and above);
2. refine around the best plane with ``refine_steps`` finer hypotheses (per-pixel depths) and a
   parabola through the three best costs;
3. keep pixels with NCC above ``min_ncc`` and enough texture.

Fusion: a reference pixel's 3D point is kept when at least ``min_consistent`` other depth maps see
it at the same depth (relative ``depth_tol``) where it projects. Colour: the reference camera's
linear RGB. Everything in float32 torch (GPU when ``device="cuda"``).

Bounded memory: each level keeps a running best over its hypotheses, evaluated in batches of
planes and bands of rows within ``SWEEP_BUDGET_MB`` (:class:`_Sweep`), never the cost volume; a
frame's images are read when needed (the matching images of every camera are kept, 5.25 bytes a
working pixel, and its depth map, 4). The memory model and its measurement: docs/calibration.md,
"Dense points: memory and time".

OpenCV's ``stereoRectify`` failed on strongly converging cameras (NOTES); the plane sweep needs no
rectification at all.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from collections.abc import Callable, Mapping

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
    #: above this working width (px) the coarse planes are swept at a quarter of the resolution and
    #: refined at half (:func:`depth_map`), at or below it at half
    coarse_quarter_above_px: int = 320
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
    K: np.ndarray           # [3, 3] at the depth map's resolution
    world_to_camera: np.ndarray
    planes: int = 0         # the coarse sweep's planes


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


def _prep(img: np.ndarray, scales: tuple[float, ...]) -> list[np.ndarray]:
    """The matching image of a view [H, W(, C)] at each downscale factor of ``scales``: the square
    root of its exposure-normalised luminance (roughly perceptual, noise-flattened), float32."""
    import cv2

    g = luminance(exposure_normalise(np.asarray(img, np.float32)))
    g = np.sqrt(np.clip(g, 0, None)).astype(np.float32)
    return [g if s == 1.0 else cv2.resize(g, None, fx=1 / s, fy=1 / s, interpolation=cv2.INTER_AREA)
            for s in scales]


def _scaled_K(K: np.ndarray, scale: float) -> np.ndarray:
    """Intrinsics of an image downscaled by ``scale`` (OpenCV centres: (x + 0.5) / s - 0.5)."""
    S = np.array([[1 / scale, 0, 0.5 / scale - 0.5], [0, 1 / scale, 0.5 / scale - 0.5], [0, 0, 1]])
    return S @ K


def _box(x: torch.Tensor, w: int) -> torch.Tensor:
    """Mean over a ``w`` x ``w`` window of [B, 1, H, W] (the pixels inside the image only)."""
    return F.avg_pool2d(x, w, stride=1, padding=w // 2, count_include_pad=False)


#: bytes of the sweep's working set per hypothesis and reference pixel: the arrays alive at once in
#: :meth:`_Sweep.cost` (the grid, the sampled neighbour, the NCC's windowed sums, the sum and worst
#: over the neighbours), rounded up; the measured peaks agree (docs/calibration.md, "Dense points:
#: memory and time")
SWEEP_BYTES_PER_HYPOTHESIS_PIXEL = 96
#: the sweep's working-set budget (MiB): planes are evaluated in batches, and the reference in bands
#: of rows, so that a batch stays within it at any resolution
SWEEP_BUDGET_MB = 256


@dataclass
class _View:
    """A camera at one level of the sweep: its matching image [1, 1, h, w], K at that level and
    world_to_camera [4, 4]."""
    image: torch.Tensor
    K: np.ndarray
    world_to_camera: np.ndarray


class _Sweep:
    """The matching cost of a reference view against its neighbours for depth hypotheses, evaluated
    in batches of hypotheses and bands of rows within ``budget_bytes``; the caller keeps what it
    needs of each batch (a running minimum), never the whole cost volume.

    A reference pixel at depth d lands in a neighbour at ``(d P + q)`` (homogeneous pixel), with
    ``P = Kn Rn Rr^T K_r^-1 [u, v, 1]`` per pixel and ``q = Kn (Rn Cr + tn)``: three multiply-adds
    a pixel and hypothesis. The cost of a hypothesis is ``1 - NCC`` averaged over the best
    ``neighbours - 1`` neighbours (one may be occluded; all of them when there is one)."""

    def __init__(self, ref: _View, neighbours: list[_View], window: int, budget_bytes: int):
        self.ref, self.nbs, self.window = ref, neighbours, window
        _, _, self.H, self.W = ref.image.shape
        self.halo = window // 2
        self.budget = max(int(budget_bytes), 1)
        mr = _box(ref.image, window)
        self.ref_mean = mr
        self.ref_var = (_box(ref.image * ref.image, window) - mr * mr).clamp(min=1e-8)
        Wr = ref.world_to_camera
        Rr, Cr = Wr[:3, :3], -Wr[:3, :3].T @ Wr[:3, 3]
        self.maps = []
        for nb in neighbours:
            Wn = nb.world_to_camera
            A = nb.K @ Wn[:3, :3] @ Rr.T @ np.linalg.inv(ref.K)
            q = nb.K @ (Wn[:3, :3] @ Cr + Wn[:3, 3])
            self.maps.append((torch.as_tensor(A, dtype=torch.float32, device=ref.image.device),
                              torch.as_tensor(q, dtype=torch.float32, device=ref.image.device)))

    def batches(self, n: int) -> list[tuple[int, int, int, int]]:
        """``(h0, h1, r0, r1)``: hypotheses [h0, h1) on output rows [r0, r1), covering ``n``
        hypotheses and every row, each batch within the budget (halo rows included)."""
        per = SWEEP_BYTES_PER_HYPOTHESIS_PIXEL * self.W
        depth = max(1, min(n, 16))
        rows = self.budget // (per * depth) - 2 * self.halo
        if rows >= self.H:
            depth = max(1, min(n, self.budget // (per * self.H)))
            rows = self.H
        else:
            depth = max(1, min(depth, self.budget // (per * (1 + 2 * self.halo + 1))))
            rows = max(1, self.budget // (per * depth) - 2 * self.halo)
        return [(h0, min(h0 + depth, n), r0, min(r0 + rows, self.H))
                for r0 in range(0, self.H, rows) for h0 in range(0, n, depth)]

    def cost(self, inv_depth: Callable[[int, int], torch.Tensor], r0: int, r1: int) -> torch.Tensor:
        """The cost [D, r1 - r0, W] of the reference's rows [r0, r1) at inverse depths (1/m)
        ``inv_depth(a, b)`` [D, b - a, W] (or [D, 1, 1]: planes) of rows [a, b): those rows and the
        NCC window's halo."""
        a, b = max(0, r0 - self.halo), min(self.H, r1 + self.halo)
        lo, hi = r0 - a, r1 - a
        d = inv_depth(a, b).clamp(min=1e-6).reciprocal()
        D = d.shape[0]
        t32 = dict(dtype=torch.float32, device=self.ref.image.device)
        v, u = torch.meshgrid(torch.arange(a, b, **t32), torch.arange(self.W, **t32), indexing="ij")
        ref = self.ref.image[:, :, a:b]
        mr = self.ref_mean[:, :, a:b]
        inv_sr = self.ref_var[:, :, a:b].rsqrt()
        total = worst = None
        for nb, (A, q) in zip(self.nbs, self.maps):
            h, w = nb.image.shape[-2:]
            # grid_sample's coordinates of pixel (x/z, y/z): 2 (x/z + 0.5) / w - 1, folded into the rows
            # of the homography so that each is one division: gx = (d Px + qx) / (d Pz + qz)
            Pz = A[2, 0] * u + A[2, 1] * v + A[2, 2]
            grid = torch.empty((D, b - a, self.W, 2), **t32)
            z = torch.addcmul(q[2].expand(1), d, Pz)
            zc = z.clamp(min=1e-6)
            for k, size in ((0, w), (1, h)):
                c = 1 / size - 1
                Pk = (A[k, 0] * u + A[k, 1] * v + A[k, 2]) * (2 / size) + c * Pz
                torch.div(torch.addcmul((q[k] * (2 / size) + c * q[2]).expand(1), d, Pk), zc, out=grid[..., k])
            del zc
            valid = (grid.abs() < 1).all(-1) & (z > 0)
            del z
            warped = F.grid_sample(nb.image.expand(D, -1, -1, -1), grid, mode="bilinear", padding_mode="zeros",
                                   align_corners=False)
            del grid
            mw = _box(warped, self.window)
            cov = _box(ref * warped, self.window).sub_(mr * mw)
            warped.mul_(warped)
            vw = _box(warped, self.window).sub_(mw.mul_(mw)).clamp_(min=1e-8)
            del warped, mw
            ncc = cov.mul_(vw.rsqrt_()).mul_(inv_sr)[:, 0]
            del vw
            ncc = ncc.masked_fill_(~valid, -1.0)[:, lo:hi]
            total = ncc.clone() if total is None else total.add_(ncc)
            worst = ncc if worst is None else torch.minimum(worst, ncc)
        n = len(self.nbs)
        # the mean of the best n - 1: all but the worst
        best = total if n == 1 else total.sub_(worst).div_(n - 1)
        return best.neg_().add_(1)


def depth_map(images: Mapping[str, np.ndarray], cameras: Mapping[str, Camera], ref: str, neighbours: list[str],
              options: DenseOptions = DenseOptions(), *, budget_mb: float = SWEEP_BUDGET_MB,
              prepared: Mapping[str, tuple[np.ndarray, ...]] | None = None) -> DepthMap:
    """Plane-sweep depth of camera ``ref`` (at the working resolution: images / ``options.scale``).

    Two levels: a sweep at 1/2 of the working resolution with planes ~1 px of disparity apart, then
    per-pixel hypotheses at the working resolution, 0.5 px apart, over two coarse steps either side.
    Above ``options.coarse_quarter_above_px`` working pixels wide, three: the planes ~1 px apart at
    1/4 of the resolution (half as many, on a sixteenth of the pixels), per-pixel hypotheses ~1 px
    apart at 1/2 over two of those planes either side, then the working resolution as above.
    Each level keeps a running best over batches of hypotheses (:class:`_Sweep`, at most
    ``budget_mb`` MiB of working set a batch), never the whole cost volume. ``prepared``: id ->
    (working, half, quarter resolution) matching images of :func:`_prep` when the caller holds them
    (else made from ``images``).
    """
    dev = torch.device(options.device)
    t32 = dict(dtype=torch.float32, device=dev)
    s = options.scale
    budget = int(budget_mb * 2 ** 20)

    def views(level: int, scale: float) -> tuple[_View, list[_View]]:
        out = []
        for cid in [ref, *neighbours]:
            g = prepared[cid][level] if prepared is not None else _prep(images[cid], (scale,))[0]
            out.append(_View(torch.as_tensor(g, **t32)[None, None], _scaled_K(cameras[cid][0], scale),
                             np.asarray(cameras[cid][1], np.float64)))
        return out[0], out[1:]

    # disparity per unit of inverse depth for the widest neighbour (px at the working resolution)
    Cref = -cameras[ref][1][:3, :3].T @ cameras[ref][1][:3, 3]
    base = max(np.linalg.norm(-cameras[n][1][:3, :3].T @ cameras[n][1][:3, 3] - Cref) for n in neighbours)
    fpx = cameras[ref][0][0, 0] / s
    inv_lo, inv_hi = 1 / options.depth_max, 1 / options.depth_min
    # coarse level: planes uniform in inverse depth, ~1 px of disparity apart at its resolution, the
    # running best plane per pixel; at a quarter of the working resolution above
    # coarse_quarter_above_px wide (the planes grow with the width), then refined at half
    g = prepared[ref][0] if prepared is not None else _prep(images[ref], (s,))[0]
    cs = 4 if g.shape[1] > options.coarse_quarter_above_px else 2
    sweep = _Sweep(*views(cs.bit_length() - 1, s * cs), options.window, budget)
    n_planes = int(np.clip((inv_hi - inv_lo) * fpx / cs * base / 1.0, 8, options.num_depths * 8))
    inv = torch.linspace(inv_lo, inv_hi, n_planes, **t32)
    best_j = _best_hypothesis(sweep, n_planes, lambda h0, h1, a, b: inv[h0:h1, None, None])
    inv_c = inv[best_j]
    coarse_step = (inv[1] - inv[0]) if n_planes > 1 else torch.tensor(0.01, **t32)
    del sweep, best_j
    if cs == 4:
        # half-resolution level: per-pixel hypotheses ~1 px of disparity apart at half resolution
        # over two quarter-resolution planes either side of the coarse depth, the best kept. The
        # coarse depths are median-filtered first: a pixel's hypotheses warp its NCC window with its
        # neighbours' depths, and a lone wrong plane in a window spoils the window's match
        sweep = _Sweep(*views(1, s * 2), options.window, budget)
        inv_q = F.interpolate(_median3(inv_c)[None, None], size=(sweep.H, sweep.W), mode="nearest")[0, 0]
        coarse_step = coarse_step / 2
        km = torch.arange(-4, 5, **t32) * coarse_step
        best_j = _best_hypothesis(sweep, len(km), lambda h0, h1, a, b: (inv_q[None, a:b] + km[h0:h1, None, None]
                                                                       ).clamp(min=1e-4))
        inv_c = (inv_q + km[best_j]).clamp(min=1e-4)
        del sweep, best_j, inv_q
    # fine level: per-pixel hypotheses around the coarse depth; the running best keeps the costs
    # either side of it for the parabola
    sweep = _Sweep(*views(0, s), options.window, budget)
    H, W = sweep.H, sweep.W
    inv0 = F.interpolate(inv_c[None, None], size=(H, W), mode="nearest")[0, 0]
    fine_step = 0.5 / (fpx * base)
    nk = int(min(max(2 * float(coarse_step) / fine_step, 2), 4 * options.refine_steps))
    ks = torch.arange(-nk, nk + 1, **t32) * fine_step
    n = len(ks)
    inf = torch.full((H, W), float("inf"), **t32)
    best, before, after, last = inf.clone(), inf.clone(), inf.clone(), inf.clone()
    j = torch.zeros((H, W), dtype=torch.long, device=dev)
    for h0, h1, r0, r1 in sweep.batches(n):
        rows = slice(r0, r1)
        c = sweep.cost(lambda a, b: (inv0[None, a:b] + ks[h0:h1, None, None]).clamp(min=1e-4), r0, r1)
        # the cost after the best so far, when the best was the previous batch's last hypothesis
        after[rows] = torch.where(j[rows] == h0 - 1, c[0], after[rows])
        cmin, jmin = c.min(0)
        better = cmin < best[rows]
        prev = torch.where(jmin > 0, c.gather(0, (jmin - 1).clamp(min=0)[None])[0], last[rows])
        nxt = torch.where(jmin < h1 - h0 - 1, c.gather(0, (jmin + 1).clamp(max=h1 - h0 - 1)[None])[0], inf[rows])
        best[rows] = torch.where(better, cmin, best[rows])
        j[rows] = torch.where(better, jmin + h0, j[rows])
        before[rows] = torch.where(better, prev, before[rows])
        after[rows] = torch.where(better, nxt, after[rows])
        last[rows] = c[-1]
    del sweep, last
    cm, c0, cp = before, best, after
    den = cm - 2 * c0 + cp
    ok_den = torch.isfinite(den) & (den > 1e-6)
    off = torch.where(ok_den, 0.5 * (cm - cp) / torch.where(ok_den, den, torch.ones_like(den)),
                      torch.zeros_like(den)).clamp(-0.5, 0.5)
    inv_best = (inv0 + ks[j]).clamp(min=1e-4) + off * fine_step
    depth = 1 / inv_best.clamp(min=1e-6)
    ncc = 1 - best
    ref_t = torch.as_tensor(g, **t32)[None, None]
    tex = torch.sqrt((_box(ref_t * ref_t, options.window) - _box(ref_t, options.window) ** 2).clamp(min=0))[0, 0]
    ok = (ncc > options.min_ncc) & (tex > options.min_texture) & (j > 0) & (j < n - 1)
    ok &= (depth > options.depth_min) & (depth < options.depth_max)
    depth = torch.where(ok, depth, torch.zeros_like(depth))
    return DepthMap(depth.cpu().numpy(), _scaled_K(cameras[ref][0], s), np.asarray(cameras[ref][1]), n_planes)


def _median3(x: torch.Tensor) -> torch.Tensor:
    """The 3 x 3 median of [H, W] (edges replicated)."""
    padded = F.pad(x[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    return padded.unfold(0, 3, 1).unfold(1, 3, 1).reshape(*x.shape, 9).median(-1).values


def _best_hypothesis(sweep: _Sweep, n: int, inv_depth: Callable[[int, int, int, int], torch.Tensor]
                     ) -> torch.Tensor:
    """The index [H, W] (long) of the least-cost of ``n`` hypotheses per pixel of ``sweep``'s
    reference, kept as a running best over its batches: ``inv_depth(h0, h1, a, b)`` is the inverse
    depths (1/m) of hypotheses [h0, h1) on rows [a, b), [h1 - h0, b - a, W] or [h1 - h0, 1, 1]."""
    best = torch.full((sweep.H, sweep.W), float("inf"), dtype=torch.float32, device=sweep.ref.image.device)
    best_j = torch.zeros((sweep.H, sweep.W), dtype=torch.long, device=sweep.ref.image.device)
    for h0, h1, r0, r1 in sweep.batches(n):
        c = sweep.cost(lambda a, b: inv_depth(h0, h1, a, b), r0, r1)
        cmin, jmin = c.min(0)
        better = cmin < best[r0:r1]
        best[r0:r1] = torch.where(better, cmin, best[r0:r1])
        best_j[r0:r1] = torch.where(better, jmin + h0, best_j[r0:r1])
    return best_j


#: reference pixels fused at a time (the fusion's float64 working set is ~200 bytes a pixel)
FUSE_CHUNK = 1 << 19


def fuse_depth_maps(maps: Mapping[str, DepthMap], images: Mapping[str, np.ndarray], options: DenseOptions
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points [N, 3] float32, linear colours [N, 3] float32 and consistent-view counts [N]. Each
    reference's image is read once (for its colours), its pixels fused ``FUSE_CHUNK`` at a time."""
    import cv2

    pts, cols, cnts = [], [], []
    for rid, dm in maps.items():
        H, W = dm.depth.shape
        flat = np.flatnonzero(dm.depth > 0)
        if len(flat) == 0:
            continue
        img = np.asarray(images[rid], np.float32)[..., :3]
        if img.shape[:2] != (H, W):
            img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
        img = img.reshape(-1, 3)
        Kinv = np.linalg.inv(dm.K).T
        R, t = dm.world_to_camera[:3, :3], dm.world_to_camera[:3, 3]
        for i in range(0, len(flat), FUSE_CHUNK):
            idx = flat[i:i + FUSE_CHUNK]
            v, u = np.divmod(idx, W)
            z = dm.depth.reshape(-1)[idx].astype(np.float64)
            X = (np.stack([u, v, np.ones_like(u)], 1).astype(np.float64) @ Kinv * z[:, None] - t) @ R
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
            pts.append(X[keep].astype(np.float32))
            cols.append(img[idx[keep]].astype(np.float32))
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


#: ``progress(done, total, info)`` after each reference camera's depth map: ``info`` holds its
#: ``camera``, ``planes``, ``depth_m`` (the sweep's nearest and farthest), ``pixels`` with a depth
#: and ``seconds`` since the frame began
DenseProgress = Callable[[int, int, dict], None]


def dense_points(images: Mapping[str, np.ndarray], cameras: Mapping[str, Camera], *,
                 references: list[str] | None = None, options: DenseOptions = DenseOptions(),
                 valid: Mapping[str, np.ndarray | None] | None = None,
                 sweeps: Mapping[str, tuple[float, float, float]] | None = None,
                 progress: DenseProgress | None = None, budget_mb: float = SWEEP_BUDGET_MB) -> dict:
    """One frame's dense point cloud from calibrated views.

    ``images``: id -> linear RGB [H, W, 3], read twice (its matching images, then a reference's
    colours): a mapping that loads on access keeps one full image in memory at a time;
    ``cameras``: id -> (K [3, 3], world_to_camera [4, 4]);
    ``references``: cameras that get a depth map (default: all with enough neighbours);
    ``valid``: id -> [H, W] bool, the pixels that hold footage (a rectified distorted frame's
    :func:`~volcap_core.calibration.distortion.rectified_valid`; None or absent: all): a reference
    pixel whose NCC window reaches outside them gets no depth (the black border's edge is texture
    that matches nothing real);
    ``sweeps``: id -> the reference's ``(nearest, neighbours', farthest)`` depth in metres: it sweeps
    from the nearest to the farthest, its neighbours chosen for their triangulation angle at the
    middle one (:func:`sweep_range` of a calibration's ``CameraCalibration.scene_depth_m``); a
    reference without one sweeps ``options.depth_min``-``depth_max``, neighbours chosen at 5 m;
    ``progress``: :data:`DenseProgress`; ``budget_mb``: the sweep's working set (:class:`_Sweep`;
    the result does not depend on it).
    Memory: the matching images (5.25 bytes a working pixel: working, half and quarter resolution)
    and depth maps (4) of every camera, one full image, the sweep's budget and the points
    (docs/calibration.md, "Dense points: memory and time").
    Returns ``positions`` [N, 3] float32 (metres, stage frame), ``colours`` [N, 3] float32 (linear),
    ``views`` [N] consistent other views, ``depth_maps`` {id: DepthMap}, ``seconds``.
    """
    t0 = time.perf_counter()
    ids = sorted(set(images) & set(cameras))
    refs = references or ids
    s = options.scale
    prepared: dict[str, tuple[np.ndarray, ...]] = {}

    class _Prepared(Mapping):   # each camera's matching images, made on first use
        def __getitem__(self, cid):
            if cid not in prepared:
                prepared[cid] = tuple(_prep(images[cid], (s, 2.0 * s, 4.0 * s)))
            return prepared[cid]

        def __iter__(self):
            return iter(ids)

        def __len__(self):
            return len(ids)

    maps = {}
    for k, r in enumerate(refs):
        lo, middle, hi = (sweeps or {}).get(r, (options.depth_min, 5.0, options.depth_max))
        nbs = choose_neighbours({c: cameras[c] for c in ids}, r, options.neighbours, options.min_angle_deg,
                                options.max_angle_deg, scene_depth=float(middle))
        if not nbs:
            continue
        dm = depth_map(images, cameras, r, nbs, replace(options, depth_min=float(lo), depth_max=float(hi)),
                       budget_mb=budget_mb, prepared=_Prepared())
        if valid is not None and valid.get(r) is not None:
            dm.depth[~_valid_at(valid[r], dm.depth.shape, options.window)] = 0.0
        maps[r] = dm
        if progress is not None:
            progress(k + 1, len(refs), {"camera": r, "planes": dm.planes, "depth_m": (float(lo), float(hi)),
                                        "pixels": int(np.count_nonzero(dm.depth)),
                                        "seconds": time.perf_counter() - t0})
    prepared.clear()
    pos, col, cnt = fuse_depth_maps(maps, images, options)
    return {"positions": pos, "colours": col, "views": cnt, "depth_maps": maps, "seconds": time.perf_counter() - t0}
