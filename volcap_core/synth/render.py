"""Ray casting of the set plus actors into linear radiance, with ss x ss supersampling.

Actors are drawn with a per-primitive z-buffer: each part is intersected only with the rays of
its conservative screen rectangle, so cost scales with the parts' image area.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from volcap_core.synth.actors import Actor, Prim
from volcap_core.synth.geometry import PinholeCamera, intersect_capsule, intersect_ellipsoid
from volcap_core.synth.stage import StaticScene


@dataclass
class World:
    stage: StaticScene
    actors: list[Actor]

    def prims(self, t: float) -> list[Prim]:
        out: list[Prim] = []
        for a in self.actors:
            out.extend(a.pose(t))
        return out

    def shadow_centres(self, t: float) -> np.ndarray:
        return np.array([a.root(t)[0][:2] for a in self.actors]).reshape(-1, 2)


@dataclass
class BackgroundCache:
    """A camera's set render (at ``bg_ss`` samples per pixel side), reused for every frame of a
    static camera."""

    dirs: np.ndarray           # (H*ss, W*ss, 3) unit directions for the actors
    bg_ss: int
    rad: np.ndarray            # (H*bg_ss, W*bg_ss, 3)
    t: np.ndarray              # (H*bg_ss, W*bg_ss)
    floor_idx: np.ndarray      # flat indices of floor samples
    floor_xy: np.ndarray       # their floor coordinates


def background(world: World, cam: PinholeCamera, ss: int, bg_ss: int | None = None) -> BackgroundCache:
    """Render the set. ``bg_ss`` < ``ss`` renders the set at fewer samples (its textures are
    mip-filtered to the footprint anyway) and repeats them onto the actor sample grid."""
    bg_ss = ss if bg_ss is None else bg_ss
    if ss % bg_ss:
        raise ValueError("bg_ss must divide ss")
    dirs = cam.ray_directions(ss)
    dirs_bg = dirs if bg_ss == ss else cam.ray_directions(bg_ss)
    rad, t, sid = world.stage.render(cam, dirs_bg, bg_ss)
    floor = np.flatnonzero(sid.reshape(-1) == world.stage.background.FLOOR)
    p = cam.centre[None, :2] + t.reshape(-1)[floor, None] * dirs_bg.reshape(-1, 3)[floor, :2]
    return BackgroundCache(dirs, bg_ss, rad, t, floor, p.astype(np.float32))


def render(world: World, cam: PinholeCamera, t_sec: float, ss: int,
           cache: BackgroundCache | None = None, prims: list[Prim] | None = None, bg_ss: int | None = None,
           want_depth: bool = False, want_mask: bool = False
           ) -> tuple[np.ndarray, np.ndarray | None] | tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """``(radiance, depth)``: radiance (H, W, 3) float32 and, if asked, depth along the optical axis
    (H, W float32; nearest sub-sample), else None.

    ``want_mask=True`` returns ``(radiance, depth, mask)`` instead: the performer coverage (H, W)
    float32 in [0, 1], the fraction of each pixel's ss x ss sub-samples whose visible surface is an
    actor part (0 where only the set, props, targets or chart are seen)."""
    if cache is None:
        cache = background(world, cam, ss, bg_ss)
    dirs = cache.dirs
    rad = cache.rad.copy()
    # soft contact shadows under each actor on the floor
    centres = world.shadow_centres(t_sec)
    if len(centres) and cache.floor_idx.size:
        shade = np.ones(cache.floor_idx.size, np.float32)
        for c in centres:
            d2 = ((cache.floor_xy - c.astype(np.float32)) ** 2).sum(1)
            near = d2 < (4 * 0.28) ** 2
            shade[near] *= 1 - 0.45 * np.exp(-d2[near] / (2 * 0.28 ** 2))
        rad.reshape(-1, 3)[cache.floor_idx] *= shade[:, None]
    f = ss // cache.bg_ss
    if f > 1:
        rad = np.repeat(np.repeat(rad, f, axis=0), f, axis=1)
        tbuf = np.repeat(np.repeat(cache.t, f, axis=0), f, axis=1)
    else:
        tbuf = cache.t.copy()
    world.stage.draw_timed(cam, dirs, ss, t_sec, tbuf, rad)
    if prims is None:
        prims = world.prims(t_sec)
    idx = draw_prims(world, cam, dirs, ss, tbuf, rad, prims)
    H, W = cam.height, cam.width
    out = rad if ss == 1 else cv2.resize(rad, (W, H), interpolation=cv2.INTER_AREA)
    depth = None
    if want_depth:
        zfac = dirs @ cam.R[2].astype(np.float32)
        depth = (tbuf * zfac).reshape(H, ss, W, ss).min(axis=(1, 3)).astype(np.float32)
    if want_mask:
        return out.astype(np.float32), depth, performer_coverage(idx, ss)
    return out.astype(np.float32), depth


def performer_coverage(idx: np.ndarray, ss: int) -> np.ndarray:
    """:func:`draw_prims`'s per-sub-sample part index (H*ss, W*ss) → the fraction of each pixel's
    ss x ss sub-samples where an actor part is visible, (H, W) float32 in [0, 1]."""
    h, w = idx.shape[0] // ss, idx.shape[1] // ss
    hits = (idx >= 0).reshape(h, ss, w, ss).sum(axis=(1, 3), dtype=np.int32)
    return (hits / np.float32(ss * ss)).astype(np.float32)


def draw_prims(world: World, cam: PinholeCamera, dirs, ss, tbuf, rad, prims: list[Prim]) -> np.ndarray:
    """Z-buffer the actor parts into ``tbuf``/``rad`` (in place); return, per sub-sample, the index
    into ``prims`` of the part that is the visible surface there, -1 where no part is."""
    o = cam.centre
    idx = np.full(tbuf.shape, -1, np.int16)
    rects = []
    for k, p in enumerate(prims):
        rect = cam.sphere_rect(p.centre, p.bound_radius, ss)
        rects.append(rect)
        if rect is None:
            continue
        y0, y1, x0, x1 = rect
        d = dirs[y0:y1, x0:x1]
        if p.kind == "ellipsoid":
            t = intersect_ellipsoid(o, d, p.centre, p.R, p.semi)
        else:
            t = intersect_capsule(o, d, p.a, p.b, p.radius)
        sub = tbuf[y0:y1, x0:x1]
        m = t < sub
        if m.any():
            sub[m] = t[m]
            idx[y0:y1, x0:x1][m] = k
    pix_angle = 1.0 / (cam.fx * ss)
    lighting = world.stage.lighting
    for k, p in enumerate(prims):
        rect = rects[k]
        if rect is None:
            continue
        y0, y1, x0, x1 = rect
        m = idx[y0:y1, x0:x1] == k
        if not m.any():
            continue
        d = dirs[y0:y1, x0:x1][m]
        t = tbuf[y0:y1, x0:x1][m]
        pw = o.astype(np.float32) + t[:, None] * d
        R = p.R.astype(np.float32)
        local = (pw - p.centre.astype(np.float32)) @ R          # world -> part-local
        if p.kind == "ellipsoid":
            nl = local / (p.semi.astype(np.float32) ** 2)
        else:
            half = float(np.linalg.norm(p.b - p.a) / 2)
            nl = local.copy()
            nl[:, 2] -= np.clip(local[:, 2], -half, half)
        n = nl @ R.T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
        cos = np.abs(np.einsum("ij,ij->i", n, d))
        fp = t * pix_angle / np.maximum(cos, 0.2)
        albedo = world.actors[p.actor].albedo(p, local, fp)
        rad[y0:y1, x0:x1][m] = albedo * lighting.irradiance(n)[:, None]
    return idx
