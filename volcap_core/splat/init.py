"""Initial Gaussians of a segment from its per-frame dense points (paper: "We initialize 4D
primitives from a sequence of dense point clouds reconstructed per frame").

What does not move is one Gaussian for the whole segment, not a copy per frame:

1. :func:`classify_static` marks a frame's point static when it lies on the lidar scan of the
   empty stage (when the capture has one) or when the other frames of the segment have a point
   within a few centimetres of it (props and sets the scan missed). Performers fail both tests.
2. :func:`drop_isolated` removes moving points far sparser than their frame's moving cloud: a
   plane sweep's floaters (mid-room triangulations of emissive strips, wrong matches) are sparse,
   performers are dense.
3. :func:`initial_gaussians` pools the static points of every frame, thins them on a voxel grid
   to the static budget and gives them an unbounded lifespan (λ = 0, centred mid-segment); each
   frame's moving points are thinned to the moving budget and live about one frame interval
   around their frame's time, or several where they carry their velocity
   (:mod:`volcap_core.splat.scene_flow`).

Initial scale: ``scale_factor`` × the RMS distance to the 3 nearest neighbours *within the pool the
Gaussian was drawn from after thinning*, at most ``max_scale_ratio`` × the pool's median — the
3DGS rule with a factor between 3DGS's 1 and gsplat's MCMC recipe's 0.1 (``docs/poly4dgs.md``
says which and why). With
1× on 2,500 points per frame a floor point near a camera covered the whole frame and half the
Gaussians never received a gradient.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["InitSplit", "classify_static", "colour_scan", "drop_isolated", "finest_footprint",
           "footprint_levels", "initial_gaussians", "neighbour_scale", "room_shell", "visual_hull", "voxel_thin",
           "Neighbour", "photo_depth", "zoom_points"]


def neighbour_scale(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """RMS distance ``[N]`` (metres) to the k nearest other points (3DGS's initial scale), floored
    at 1e-7; 0.01 m for a cloud of one point."""
    from scipy.spatial import cKDTree

    if len(xyz) < 2:
        return np.full(len(xyz), 0.01)
    kk = min(k, len(xyz) - 1)
    d, _ = cKDTree(xyz).query(xyz, k=kk + 1)
    d = d[:, 1:]
    return np.maximum(np.sqrt((d * d).mean(axis=1)), 1e-7)


def finest_footprint(xyz: np.ndarray, cameras: Sequence[tuple[np.ndarray, np.ndarray, int, int]]) -> np.ndarray:
    """``[N]`` metres: the smallest pixel footprint (depth / focal length) of a point over the
    cameras whose image it falls in; inf for a point no camera sees.

    ``cameras``: ``(K [3, 3] OpenCV, world_to_camera [4, 4], width, height)``. What a tracking
    camera framing a face resolves there: its footprint is 4-8× finer than a static camera's.
    """
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    out = np.full(len(xyz), np.inf)
    for K, W, w, h in cameras:
        pc = xyz @ np.asarray(W)[:3, :3].T + np.asarray(W)[:3, 3]
        z = pc[:, 2]
        ok = z > 0.1
        uv = np.zeros((len(xyz), 2))
        uv[ok] = pc[ok, :2] / z[ok, None] @ np.asarray(K)[:2, :2].T + np.asarray(K)[:2, 2]
        ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
        f = float(np.sqrt(K[0][0] * K[1][1]))
        out[ok] = np.minimum(out[ok], z[ok] / f)
    return out


def footprint_levels(footprint: np.ndarray, coarse: float, finest_level: int) -> np.ndarray:
    """``[N]`` int levels for :func:`voxel_thin`: ``floor(log2(footprint / coarse))`` clipped to
    ``[finest_level, 0]`` (0 where the footprint is inf or at least ``coarse``)."""
    f = np.asarray(footprint, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        lv = np.floor(np.log2(f / coarse))
    lv = np.where(np.isfinite(lv), lv, 0)
    return np.clip(lv, finest_level, 0).astype(np.int64)


#: how far (metres) a zoom pixel's photo-consistent depth may lie from the static cameras' cloud:
#: a few times how far that cloud lies off the performers (``docs/poly4dgs.md``, "The zoom points'
#: depth"); not tuned
ZOOM_DEPTH_BAND_M = 0.1


#: another camera at the same instant: ``(K [3, 3], world_to_camera [4, 4], width, height, load)``,
#: ``load() -> [height, width, 3]`` linear footage (called only for the neighbours chosen)
Neighbour = tuple[np.ndarray, np.ndarray, int, int, Callable[[], np.ndarray]]


def photo_depth(depth: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray, image: np.ndarray,
                neighbours: Sequence[Neighbour], *, band_m: float = ZOOM_DEPTH_BAND_M) -> np.ndarray:
    """A camera's depth ``[H, W]`` (metres along its axis) searched by photo-consistency within
    ``band_m`` of a prior ``depth`` (e.g. a coarse cloud's z-buffer; inf where it has none); NaN
    where the neighbours do not confirm one.

    The plane sweep of the dense points (:func:`volcap_core.calibration.dense.depth_map`: NCC over
    5-pixel windows, the best of all but one neighbour, a parabola through the best costs) with
    this camera as reference over the prior's depth range, at a scale both resolve: a zoom camera
    sees a face 3-8× finer than the static cameras around it, so its image is first averaged over
    ``2^k``-pixel blocks, the largest no coarser than the neighbours' median footprint there.
    Neighbours are those of ``neighbours`` whose image holds the prior's surface, up to three at
    the best triangulation angles
    (:func:`~volcap_core.calibration.dense.choose_neighbours`). A pixel keeps the sweep's depth
    where the sweep found one (NCC and texture high enough) within ``band_m`` of its prior.

    Args:
        depth: ``[H, W]`` prior depth. K: ``[3, 3]`` OpenCV intrinsics. world_to_camera: ``[4, 4]``.
        image: ``[H, W, 3]`` linear footage.
        neighbours: the other cameras at the same instant (:data:`Neighbour`).
    """
    from dataclasses import replace

    from scipy.ndimage import map_coordinates

    from volcap_core.calibration.dense import DenseOptions, choose_neighbours, depth_map

    h, w = depth.shape
    out = np.full((h, w), np.nan)
    prior = np.isfinite(depth)
    if prior.sum() < 16:
        return out
    W = np.asarray(world_to_camera, np.float64)
    K = np.asarray(K, np.float64)
    v, u = np.nonzero(prior)
    d = depth[v, u]
    surface = (np.linalg.solve(K, np.stack([u, v, np.ones_like(d)])) * d)
    surface = (W[:3, :3].T @ (surface - W[:3, 3:4])).T                   # [P, 3] world
    # the neighbours that hold (nearly all of) the prior's surface, and their footprint there
    seen, foot = {}, []
    for i, (Kn, Wn, wn, hn, load) in enumerate(neighbours):
        Kn, Wn = np.asarray(Kn, np.float64), np.asarray(Wn, np.float64)
        pc = surface @ Wn[:3, :3].T + Wn[:3, 3]
        front = pc[:, 2] > 0.1
        uv = pc[front, :2] / pc[front, 2:3] @ Kn[:2, :2].T + Kn[:2, 2]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= wn - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= hn - 1)
        if front.mean() > 0.95 and inside.mean() > 0.9:
            seen[f"n{i}"] = (Kn, Wn, load)
            foot.append(float(np.median(pc[front, 2])) / float(np.sqrt(Kn[0, 0] * Kn[1, 1])))
    if not seen:
        return out
    own = float(np.median(d)) / float(np.sqrt(K[0, 0] * K[1, 1]))
    k = int(np.clip(math.floor(math.log2(max(float(np.median(foot)) / own, 1.0))), 0, 3))
    r = 2 ** k
    hh, ww = h // r, w // r
    small = np.asarray(image[: hh * r, : ww * r, :3], np.float32).reshape(hh, r, ww, r, 3).mean(axis=(1, 3))
    Ks = np.array([[1 / r, 0, 0.5 / r - 0.5], [0, 1 / r, 0.5 / r - 0.5], [0, 0, 1]]) @ K   # block centres
    cameras = {"ref": (Ks, W), **{c: (Kn, Wn) for c, (Kn, Wn, _) in seen.items()}}
    nbs = choose_neighbours(cameras, "ref", 3, scene_depth=float(np.median(d)))
    if not nbs:
        return out
    images = {"ref": small, **{c: np.asarray(seen[c][2]())[..., :3] for c in nbs}}
    lo = max(0.2, float(np.percentile(d, 2)) - band_m)
    hi = float(np.percentile(d, 98)) + band_m
    dm = depth_map(images, cameras, "ref", nbs, replace(DenseOptions(), depth_min=lo, depth_max=hi))
    # back at full resolution: each pixel interpolates the depths found around it (none: NaN)
    found = (dm.depth > 0).astype(np.float64)
    coords = np.stack([(v + 0.5) / r - 0.5, (u + 0.5) / r - 0.5])
    weight = map_coordinates(found, coords, order=1, mode="nearest")
    sweep = map_coordinates(dm.depth.astype(np.float64), coords, order=1, mode="nearest") / np.maximum(weight, 1e-9)
    ok = (weight > 0.99) & (np.abs(sweep - d) <= band_m)
    out[v[ok], u[ok]] = sweep[ok]
    return out


def zoom_points(xyz: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray, image: np.ndarray, *,
                stride_px: int = 2, neighbours: Sequence[Neighbour] = (),
                band_m: float = ZOOM_DEPTH_BAND_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points at a camera's own resolution on the surface of a cloud: the camera's view of the
    cloud's surface, sampled every ``stride_px`` pixels and coloured by its footage.

    The cloud (``xyz [P, 3]`` metres, e.g. a frame's performers from the static cameras' sweep) is
    z-buffered into the camera, each point splatted over about half its neighbour spacing so the
    surface closes, the splat's growth at the silhouette eroded away again; each sampled pixel
    is lifted to the buffer's depth and takes the mean footage colour of its ``stride_px``²
    block. A tracking camera framing a face resolves it 4-8× finer than the sweep's spacing: its
    points carry what the dense points cannot (eyes, brows, hair pattern).

    With ``neighbours`` (the other training cameras at that frame) each pixel takes a depth of its
    own instead, searched by photo-consistency within ``band_m`` of the buffer's
    (:func:`photo_depth`), and pixels whose depth the neighbours do not confirm are dropped: the
    buffer of a 1-2 cm cloud lies centimetres off the surface a 3 mm zoom pixel sees, and points
    there, coloured from the zoom camera, smear what every other camera sees of them
    (``docs/poly4dgs.md``, "The zoom points' depth").

    Args:
        K: ``[3, 3]`` OpenCV intrinsics (top-left pixel centre at 0). world_to_camera: ``[4, 4]``.
        image: ``[H, W, 3]`` linear footage of that camera at the cloud's frame.
        neighbours: the other cameras at the same instant (:data:`Neighbour`).
        band_m: how far (metres) a pixel's depth may lie from the buffer's.
    Returns:
        ``(xyz [M, 3], rgb [M, 3] linear, footprint [M] metres per pixel)``.
    """
    from scipy.ndimage import binary_erosion

    from volcap_core.calibration.lidar import depth_buffer

    h, w = image.shape[:2]
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    W = np.asarray(world_to_camera, np.float64)
    K = np.asarray(K, np.float64)
    empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    if len(xyz) < 2:
        return empty
    z = xyz @ W[2, :3] + W[2, 3]
    front = z > 0.1
    if not front.any():
        return empty
    spacing_px = neighbour_scale(xyz)[front] * float(K[0, 0]) / z[front]
    splat = int(min(32, max(1, math.ceil(0.5 * float(np.median(spacing_px))))))
    zbuf = depth_buffer(K, W, w, h, xyz, splat_px=splat)
    inside = binary_erosion(np.isfinite(zbuf), structure=np.ones((2 * splat + 1, 2 * splat + 1), bool))
    if len(neighbours):
        zbuf = photo_depth(np.where(inside, zbuf, np.inf), K, W, image, neighbours, band_m=band_m)
        inside = np.isfinite(zbuf)
    s = max(1, int(stride_px))
    hh, ww = h // s, w // s
    blocks = np.asarray(image[: hh * s, : ww * s, :3], np.float64).reshape(hh, s, ww, s, 3).mean(axis=(1, 3))
    vv, uu = np.mgrid[0:hh, 0:ww]
    u = uu * s + 0.5 * (s - 1)     # the block's centre, OpenCV pixel coordinates
    v = vv * s + 0.5 * (s - 1)
    ci, cj = np.minimum(np.round(v).astype(np.int64), h - 1), np.minimum(np.round(u).astype(np.int64), w - 1)
    keep = inside[ci, cj]
    d = zbuf[ci, cj][keep]
    rays = np.linalg.solve(K, np.stack([u[keep], v[keep], np.ones_like(d)]))      # [3, M], z = 1
    cam = rays * d
    world = (W[:3, :3].T @ (cam - W[:3, 3:4])).T
    foot = d / float(np.sqrt(K[0, 0] * K[1, 1]))
    return world, blocks[keep], foot


def classify_static(frames: Sequence[np.ndarray], *,
                    scan_distance: Callable[[np.ndarray], np.ndarray] | None = None,
                    scan_tolerance_m: float = 0.05, persistence_radius_m: float = 0.03,
                    persistence: float = 0.5) -> list[np.ndarray]:
    """Which points of each frame belong to what does not move.

    Args:
        frames: per frame, ``[P_f, 3]`` points (metres).
        scan_distance: ``[N, 3] -> [N]`` distance to the empty stage's scanned surface (inf where
            the scan has nothing near), or None when there is no scan.
        scan_tolerance_m: a point this close to the scan is static.
        persistence_radius_m, persistence: a point is also static when at least this fraction of
            the *other* frames has a point within the radius of it (needs >= 2 frames).
    Returns:
        per frame, ``[P_f]`` bool.
    """
    from scipy.spatial import cKDTree

    out = []
    trees = [cKDTree(f) if len(f) else None for f in frames] if len(frames) > 1 else []
    for i, xyz in enumerate(frames):
        static = np.zeros(len(xyz), bool)
        if len(xyz) and scan_distance is not None:
            static |= np.asarray(scan_distance(xyz)) < scan_tolerance_m
        if trees and len(xyz):
            hits = np.zeros(len(xyz), np.int32)
            for j, tree in enumerate(trees):
                if j == i or tree is None:
                    continue
                d, _ = tree.query(xyz, k=1, distance_upper_bound=persistence_radius_m)
                hits += np.isfinite(d)
            static |= hits >= persistence * (len(frames) - 1)
        out.append(static)
    return out


def drop_isolated(xyz: np.ndarray, *, neighbours: int = 8, factor: float = 3.0,
                  groups: np.ndarray | None = None) -> np.ndarray:
    """``[N]`` bool: points whose distance to their ``neighbours``-th nearest neighbour is at most
    ``factor`` × the median of that distance over the cloud (scale-free: a cloud in millimetres or
    kilometres, sparse or dense, is judged against its own density). Clouds of at most
    ``neighbours`` points are kept whole.

    ``groups [N]`` (ints, or None): each point is judged against the median of its own group, so
    a dense part (a zoom camera's points, :func:`footprint_levels`) does not make the sweep's
    coarser points look isolated."""
    from scipy.spatial import cKDTree

    if len(xyz) <= neighbours:
        return np.ones(len(xyz), bool)
    d, _ = cKDTree(xyz).query(xyz, k=neighbours + 1)
    dk = d[:, -1]
    if groups is None:
        return dk <= factor * np.median(dk)
    limit = np.empty(len(xyz))
    for g in np.unique(groups):
        limit[groups == g] = factor * np.median(dk[groups == g])
    return dk <= limit


def voxel_thin(xyz: np.ndarray, budget: int, rng: np.random.Generator,
               level: np.ndarray | None = None) -> np.ndarray:
    """Indices of at most ``budget`` points spread evenly in space: one random point per cell of
    the coarsest-needed cubic grid (bisected on the cell size), topped up at random if the grid
    leaves room. Deterministic for a seeded ``rng``.

    ``level [N]`` (ints <= 0, or None: all 0): a point of level ``-k`` is thinned on a grid
    ``2^k`` times finer, so where a camera resolves finer (:func:`footprint_levels`) more points
    are kept."""
    n = len(xyz)
    if n <= budget:
        return np.arange(n)
    if budget <= 0:
        return np.zeros(0, np.int64)
    order = rng.permutation(n)
    pts = xyz[order]
    extent = float(np.max(pts.max(0) - pts.min(0))) or 1.0
    lo, hi = extent * 1e-4, extent
    lev = None if level is None or not np.any(level) else np.asarray(level, np.int64)[order]

    origin = pts.min(0)

    def pick(cell: float) -> np.ndarray:
        if lev is None:
            ijk = np.floor((pts - origin) / cell).astype(np.int64)
        else:
            ijk = np.floor((pts - origin) / (cell * np.exp2(lev))[:, None]).astype(np.int64)
        dims = ijk.max(0) + 1
        keys = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]   # one int64 per cell
        if lev is not None:
            _, keys = np.unique(np.stack([keys, lev], 1), axis=0, return_inverse=True)
        _, first = np.unique(keys, return_index=True)
        return np.sort(first)

    best = pick(hi)
    for _ in range(30):
        mid = math.sqrt(lo * hi)
        sel = pick(mid)
        if len(sel) > budget:
            lo = mid
        else:
            hi, best = mid, sel
        if hi / lo < 1.02:
            break
    if len(best) < budget:  # fill up with the points not yet taken, in the random order
        rest = np.setdiff1d(np.arange(n), best)[: budget - len(best)]
        best = np.sort(np.concatenate([best, rest]))
    return np.sort(order[best])


@dataclass
class InitSplit:
    """The initial Gaussians before they become a model (numpy, N rows).

    Attributes:
        xyz: ``[N, 3]`` metres. rgb: ``[N, 3]`` linear colour. scale: ``[N]`` metres.
        t0: ``[N]`` seconds. static: ``[N]`` bool (unbounded lifespan).
        velocity: ``[N, 3]`` m/s at ``t0`` (0 for the static ones), or None where no frame gave one.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    scale: np.ndarray
    t0: np.ndarray
    static: np.ndarray
    velocity: np.ndarray | None = None

    @property
    def counts(self) -> dict[str, int]:
        return {"static": int(self.static.sum()), "moving": int((~self.static).sum())}


def initial_gaussians(frames: Sequence[tuple], *,
                      budget: int, static_share: float = 0.6, scale_factor: float = 0.5,
                      max_scale_ratio: float = 4.0, seed: int = 0,
                      moving_scale_px: float | None = None, finest_level: int = 0) -> InitSplit:
    """Pool and thin a segment's points into at most ``budget`` initial Gaussians.

    Args:
        frames: per frame ``(time_s, xyz [P, 3], rgb [P, 3] linear, static [P] bool or None)``,
            optionally a fifth ``footprint [P]`` metres (:func:`finest_footprint`) or None and a
            sixth ``velocity [P, 3]`` m/s (:mod:`~volcap_core.splat.scene_flow`) or None, which
            the moving Gaussians drawn from those points keep; ``static=None`` treats the
            frame's points as moving.
        budget: most Gaussians in total.
        static_share: fraction of the budget the static pool may take (what it leaves unused
            goes to the moving points, and the reverse).
        scale_factor, max_scale_ratio: initial scale = factor × RMS distance to the 3 nearest
            neighbours in its pool, at most ``max_scale_ratio`` × that pool's median (a lone
            point of a sparse region must not cover a camera's frame).
        seed: thinning randomness.
        moving_scale_px: a moving Gaussian's initial scale is at most this × its point's
            footprint (where the frame gives footprints): the finest camera that sees it
            resolves detail that the sweep's spacing would blur.
        finest_level: moving points are thinned on grids up to ``2^-finest_level`` times finer
            where a camera resolves finer than the frame's 90th-percentile footprint
            (:func:`footprint_levels`); 0: one grid for all.
    Returns:
        :class:`InitSplit`.
    """
    rng = np.random.default_rng(seed)
    s_xyz, s_rgb, m_parts = [], [], []
    any_velocity = False
    for time_s, xyz, rgb, static, *more in frames:
        xyz, rgb = np.asarray(xyz, np.float64).reshape(-1, 3), np.asarray(rgb, np.float64).reshape(-1, 3)
        st = np.zeros(len(xyz), bool) if static is None else np.asarray(static, bool)
        foot = more[0] if more and more[0] is not None else np.full(len(xyz), np.inf)
        vel = more[1] if len(more) > 1 and more[1] is not None else None
        any_velocity |= vel is not None
        vel = np.zeros((len(xyz), 3)) if vel is None else np.asarray(vel, np.float64).reshape(-1, 3)
        s_xyz.append(xyz[st])
        s_rgb.append(rgb[st])
        moving, m_foot = xyz[~st], np.asarray(foot, np.float64)[~st]
        level = _levels(m_foot, finest_level)
        keep = drop_isolated(moving, groups=level)
        m_parts.append((float(time_s), moving[keep], rgb[~st][keep], m_foot[keep],
                        None if level is None else level[keep], vel[~st][keep]))
    s_xyz_all = np.concatenate(s_xyz) if s_xyz else np.zeros((0, 3))
    s_rgb_all = np.concatenate(s_rgb) if s_rgb else np.zeros((0, 3))
    # the same static point given by several frames is one point (a scan repeated per frame)
    _, first = np.unique(s_xyz_all, axis=0, return_index=True)
    first = np.sort(first)
    s_xyz_all, s_rgb_all = s_xyz_all[first], s_rgb_all[first]
    n_moving_avail = sum(len(p[1]) for p in m_parts)
    static_budget = min(len(s_xyz_all), max(int(static_share * budget), budget - n_moving_avail))
    idx = voxel_thin(s_xyz_all, static_budget, rng)
    parts_xyz = [s_xyz_all[idx]]
    parts_rgb = [s_rgb_all[idx]]
    parts_scale = [_capped(neighbour_scale(s_xyz_all[idx]), max_scale_ratio)]
    n_static = len(idx)
    times = [f[0] for f in frames]
    mid = 0.5 * (min(times) + max(times)) if times else 0.0
    parts_t0 = [np.full(n_static, mid)]
    parts_velocity = [np.zeros((n_static, 3))]
    shares = _fair_shares([len(p[1]) for p in m_parts], budget - n_static)
    for (time_s, xyz, rgb, foot, level, vel), share in zip(m_parts, shares):
        if share == 0:
            continue
        k = voxel_thin(xyz, share, rng, level)
        parts_xyz.append(xyz[k])
        parts_rgb.append(rgb[k])
        parts_velocity.append(vel[k])
        sc = scale_factor * _capped(neighbour_scale(xyz[k]), max_scale_ratio)
        if moving_scale_px is not None:
            sc = np.minimum(sc, moving_scale_px * foot[k])
        parts_scale.append(sc)
        parts_t0.append(np.full(len(k), time_s))
    parts_scale[0] = scale_factor * parts_scale[0]
    xyz = np.concatenate(parts_xyz)
    scale = np.concatenate(parts_scale)
    static = np.zeros(len(xyz), bool)
    static[:n_static] = True
    return InitSplit(xyz, np.concatenate(parts_rgb), scale, np.concatenate(parts_t0), static,
                     np.concatenate(parts_velocity) if any_velocity else None)


def _levels(footprint: np.ndarray, finest_level: int) -> np.ndarray | None:
    """A frame's moving points' :func:`footprint_levels` against its 90th-percentile footprint
    (the static cameras' resolution), or None when levels are off or no point has a footprint."""
    finite = np.isfinite(footprint)
    if finest_level >= 0 or not finite.any():
        return None
    return footprint_levels(footprint, float(np.percentile(footprint[finite], 90)), finest_level)


def _fair_shares(available: Sequence[int], budget: int) -> list[int]:
    """Split ``budget`` over clouds as evenly as possible, a cloud never getting more than it has
    (what a small cloud leaves goes to the others)."""
    shares = [0] * len(available)
    left = max(0, budget)
    order = sorted(range(len(available)), key=lambda i: available[i])
    for rank, i in enumerate(order):
        shares[i] = min(available[i], left // (len(order) - rank))
        left -= shares[i]
    return shares


def _capped(scale: np.ndarray, ratio: float) -> np.ndarray:
    return np.minimum(scale, ratio * np.median(scale)) if len(scale) else scale


def colour_scan(points: np.ndarray, views: Sequence, *, min_views: int = 1, splat_px: int = 2,
                depth_tolerance: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Colour a scan of the empty stage from calibrated views (the static cameras' background).

    Each scan point is projected into every view; it counts as seen where its depth is within
    ``depth_tolerance`` (relative, plus 2 cm) of the view's z-buffer of the scan itself (so walls
    hide what is behind them). Its colour is the per-channel median over the views that see it:
    a performer standing in front of the set in a few views does not colour it.

    Args:
        points: ``[N, 3]`` scan points (metres, the calibration's world frame).
        views: :class:`~volcap_core.splat.train.View` s (``camera``: pixel centres at +0.5;
            ``load()``: ``[H, W, 3|4]`` linear).
        min_views: a point seen by fewer views gets no colour.
    Returns:
        ``(rgb [N, 3] linear float32, seen [N] bool)``; rows of unseen points are 0.
    """
    from volcap_core.calibration.lidar import depth_buffer

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    samples = np.full((len(views), len(pts), 3), np.nan, np.float32)
    for k, v in enumerate(views):
        K = v.camera.opencv_K()
        W = v.camera.world_to_camera.double().numpy()
        w, h = v.camera.width, v.camera.height
        zbuf = depth_buffer(K, W, w, h, pts, splat_px=splat_px)
        pc = pts @ W[:3, :3].T + W[:3, 3]
        z = pc[:, 2]
        ok = z > 0.1
        uv = np.zeros((len(pts), 2))
        uv[ok] = pc[ok, :2] / z[ok, None] @ K[:2, :2].T + K[:2, 2]
        ix = np.round(uv).astype(np.int64)
        ok &= (ix[:, 0] >= 0) & (ix[:, 0] < w) & (ix[:, 1] >= 0) & (ix[:, 1] < h)
        ok[ok] &= z[ok] <= zbuf[ix[ok, 1], ix[ok, 0]] * (1 + depth_tolerance) + 0.02
        image = v.load()[..., :3].numpy()
        samples[k, ok] = image[ix[ok, 1], ix[ok, 0]]
    seen = np.isfinite(samples[..., 0]).sum(0) >= min_views
    rgb = np.zeros((len(pts), 3), np.float32)
    if seen.any():
        rgb[seen] = np.nanmedian(samples[:, seen], axis=0)
    return rgb, seen


def room_shell(camera_centres: np.ndarray, stage: tuple, *, margin_m: float = 1.0, spacing_m: float = 0.05
               ) -> np.ndarray:
    """Points on the floor, walls and ceiling of a box room around a rig: the stand-in for a lidar
    scan of the empty stage when a capture has none (real footage), coloured like a scan by
    :func:`colour_scan`.

    Without it the initial model of a real capture is the plane sweep's points alone, which cover
    5-8 % of a view's pixels (the room, the floor and the far walls find no match): the first
    renders are black where the footage is not, training fills the frame with a flat black-level
    veil and low-opacity Gaussians, and a held-out view renders as fog (``docs/poly4dgs.md``,
    "Real footage"). The floor is the stage frame's ``z = 0`` (exact for a calibration in the
    stage frame); the walls stand ``margin_m`` beyond both the stage volume and every camera, the
    ceiling ``margin_m`` above the highest of them: a guess training corrects, seen by the cameras
    where the real room is.

    Args:
        camera_centres: ``[C, 3]`` camera centres, metres, stage frame (z up, floor at 0).
        stage: the performance volume, a :data:`volcap_core.stage.Box`.
        margin_m: the walls' and ceiling's distance beyond the stage and the cameras.
        spacing_m: grid spacing of the points on each face.
    Returns:
        ``[N, 3]`` float64 points on the box's six faces (the floor at ``z = 0``).
    """
    c = np.asarray(camera_centres, np.float64).reshape(-1, 3)
    (x0, y0, _), (x1, y1, z1) = stage
    lo = np.minimum([x0, y0], c[:, :2].min(0)) - margin_m if len(c) else np.array([x0, y0]) - margin_m
    hi = np.maximum([x1, y1], c[:, :2].max(0)) + margin_m if len(c) else np.array([x1, y1]) + margin_m
    top = max(z1, float(c[:, 2].max()) if len(c) else z1) + margin_m
    lo3, hi3 = np.array([lo[0], lo[1], 0.0]), np.array([hi[0], hi[1], top])
    axes = [np.linspace(lo3[i], hi3[i], max(2, int(math.ceil((hi3[i] - lo3[i]) / spacing_m)) + 1)) for i in range(3)]
    faces = []
    for i in range(3):
        u, v = (axes[j] for j in range(3) if j != i)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        for side in (lo3[i], hi3[i]):
            f = np.empty((uu.size, 3))
            f[:, i] = side
            f[:, [j for j in range(3) if j != i]] = np.stack([uu.ravel(), vv.ravel()], 1)
            faces.append(f)
    return np.concatenate(faces)


def filled_silhouette(mask: np.ndarray, *, threshold: float = 0.5, close_px: int = 5) -> np.ndarray:
    """A performer mask with the holes in its silhouettes filled: the pixels at ``threshold`` or more,
    closed over ``close_px`` (a disc of that radius) and hole-filled, are set to 1; the soft edge
    outside them is kept.

    A median plate keeps a performer who stays in one place as a ghost (a torso over a
    treadmill): where the frame matches the ghost, the relative difference falls below
    :data:`volcap_core.masks.LOW` and the mask has holes inside an otherwise closed outline. Holes
    would carve a tunnel through :func:`visual_hull`, which is what this is for.

    Args:
        mask: ``[H, W]`` coverage in [0, 1] (a capture's performer mask, e.g.
            :func:`volcap_core.masks.plate_mask`'s).
    Returns:
        ``[H, W]`` float32 in [0, 1], never below ``mask``.
    """
    from scipy import ndimage

    m = np.asarray(mask, np.float32)
    r = int(close_px)
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    disc = xx * xx + yy * yy <= r * r
    solid = m >= threshold
    if r > 0:
        solid = ndimage.binary_closing(np.pad(solid, r), structure=disc)[r:-r, r:-r]
    solid = ndimage.binary_fill_holes(solid)
    return np.maximum(m, solid.astype(np.float32))


def visual_hull(cameras: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], volume: tuple, *,
                spacing_m: float = 0.025, threshold: float = 0.5, min_views: int = 2) -> np.ndarray:
    """The performers' visual hull from their masks: the surface voxels of the stage volume that
    every camera seeing them sees inside its mask.

    Without it the performers of a sparse real rig have points only where two cameras within the
    plane sweep's triangulation angle see them (Pose2Sim: the cam01-cam02 pair, the back from
    cam03-cam04), and a held-out view between them gets the performers painted on the room
    (``docs/poly4dgs.md``, "Real footage"). A voxel outside a camera's frame is not carved by it;
    one seen by fewer than ``min_views`` cameras is dropped (nothing pins its depth).

    Args:
        cameras: ``(K [3, 3] OpenCV pixel centres at integers, world_to_camera [4, 4], mask [H, W]
            coverage in [0, 1])`` per camera, all at one instant.
        volume: the stage volume (:data:`volcap_core.stage.Box`) the performers stand in.
        spacing_m: voxel size.
        threshold: coverage at which a pixel counts as the performers'.
    Returns:
        ``[N, 3]`` float64 centres of the hull's surface voxels (a voxel with a 6-neighbour outside).
    """
    (x0, y0, z0), (x1, y1, z1) = volume
    axes = [np.arange(lo + spacing_m / 2, hi, spacing_m) for lo, hi in ((x0, x1), (y0, y1), (z0, z1))]
    shape = tuple(len(a) for a in axes)
    xyz = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = np.ones(len(xyz), bool)
    seen = np.zeros(len(xyz), np.int32)
    for K, W, mask in cameras:
        # only voxels no camera has carved yet are projected: the rest stay carved whatever this
        # camera sees (the same hull as projecting all, a fraction of the work after the first)
        idx = np.flatnonzero(inside)
        m = np.asarray(mask, np.float32) >= threshold
        h, w = m.shape
        pc = xyz[idx] @ np.asarray(W, np.float64)[:3, :3].T + np.asarray(W, np.float64)[:3, 3]
        z = pc[:, 2]
        ok = z > 0.1
        uv = np.zeros((len(idx), 2))
        uv[ok] = pc[ok, :2] / z[ok, None] @ np.asarray(K, np.float64)[:2, :2].T + np.asarray(K, np.float64)[:2, 2]
        ix = np.round(uv).astype(np.int64)
        ok &= (ix[:, 0] >= 0) & (ix[:, 0] < w) & (ix[:, 1] >= 0) & (ix[:, 1] < h)
        seen[idx] += ok
        inside[idx[ok]] = m[ix[ok, 1], ix[ok, 0]]
    inside &= seen >= min_views
    grid = inside.reshape(shape)
    pad = np.pad(grid, 1)
    interior = grid.copy()
    for axis in range(3):
        for step in (-1, 1):
            interior &= np.roll(pad, step, axis=axis)[1:-1, 1:-1, 1:-1]
    return xyz[(grid & ~interior).reshape(-1)]
