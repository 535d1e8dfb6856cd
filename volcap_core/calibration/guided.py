"""Lidar-guided patch matching between calibrated static cameras.

Descriptor matching of wide 320x180 views 30° apart triangulates a few hundred points, nearly all
on the far walls: a camera sees them as one plane, where a sideways shift, a rotation and a
principal-point shift look alike, which holds the static calibration back (docs/calibration.md,
step 5). Once the cameras are known to half a pixel, the lidar
says where every background pixel of one camera lands in another, including on the floor and the
props near the cameras, which descriptors cannot match at those grazing angles. So:

1. corners (Shi-Tomasi, sub-pixel) of each camera's background plate are the anchors;
2. each anchor's viewing ray is intersected with the scan (:func:`~volcap_core.calibration.lidar.lift_to_lidar`),
   giving a point and, from the scan's normal there, a local plane;
3. for every other camera that sees that point unoccluded (scan z-buffer) and not at a grazing
   angle, the anchor's template (a (2h+1)^2 patch) is warped through the plane into that camera,
   and the best shift within ``search_px`` of the prediction is found by normalised
   cross-correlation over log luminance (per-camera gain and black level cancel), refined to
   sub-pixel by a parabola through the peak;
4. an anchor and its matches form a track. The anchor's own position is exact by construction (the
   template is centred on it), a match's error is the NCC localisation.

The tracks carry no lidar positions into the adjustment: the bundle adjuster triangulates them
freely and uses the scan only as a point-to-plane prior, so scan noise does not bias the cameras
(unlike a photometric residual evaluated at scan points, :mod:`~volcap_core.calibration.photometric`).
This gives tens of times the descriptor matches' observations, over the whole image, and with them
the bundle adjuster can also refine principal points.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Mapping

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from volcap_core.calibration.geometry import camera_centre, project
from volcap_core.calibration.images import luminance
from volcap_core.calibration.lidar import LidarScan, depth_buffer, lift_to_lidar


@dataclass(frozen=True)
class GuidedMatchOptions:
    #: Shi-Tomasi corners per camera (``cv2.goodFeaturesToTrack``), their quality level and spacing:
    #: every textured pixel (the principal points are noise-limited: more corners, closer, place them
    #: better; docs/calibration.md)
    max_corners: int = 30000
    corner_quality: float = 0.001
    min_corner_distance_px: float = 1.0
    #: template half-size h (a (2h+1)^2 patch) and the search window around the prediction
    template_half_px: int = 4
    search_px: float = 3.0
    search_step_px: float = 0.5
    #: a match needs this NCC at its peak
    min_ncc: float = 0.85
    #: after the grid search, this many re-centred refinements: NCC at the current estimate and
    #: ``refine_step_px`` either side in x and y, a parabola through each triple. On a noise-free
    #: texture they bring a match closer than the grid's parabola, but the cameras did not improve
    #: on the distorted demo capture (docs/calibration.md), so 0 (the grid's parabola only) stays
    #: the default
    refine_iterations: int = 0
    refine_step_px: float = 0.25
    #: |cos| of the angle between the scan normal and each view ray must exceed this
    min_view_cos: float = 0.2
    #: the predicted point must be within this relative depth of the other camera's scan z-buffer
    occlusion_rel: float = 0.03
    #: anchors matched at once (bounds the memory of the NCC search)
    chunk_anchors: int = 512


@dataclass
class GuidedTracks:
    """Tracks over the cameras ``camera_ids``: observations ``obs_point`` [M] (track index),
    ``obs_camera`` [M] (index in ``camera_ids``), ``obs_xy`` [M, 2] OpenCV px; ``points`` [P, 3]
    the anchors' lidar lifts (a starting point, metres); every track has >= 2 observations."""

    camera_ids: list[str]
    points: np.ndarray
    obs_point: np.ndarray
    obs_camera: np.ndarray
    obs_xy: np.ndarray
    stats: dict = field(default_factory=dict)


def log_luminance(linear: np.ndarray) -> np.ndarray:
    """Linear RGB [H, W, 3] -> log luminance [H, W] float32 (a gain becomes an offset NCC ignores)."""
    return np.log(np.maximum(luminance(linear), 1e-4)).astype(np.float32)


def _eroded(valid: np.ndarray, radius: int) -> np.ndarray:
    """``valid`` [H, W] bool shrunk by ``radius`` pixels (a square neighbourhood), the image's own
    border not counting as invalid."""
    if radius <= 0:
        return valid.copy()
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return cv2.erode(valid.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=1).astype(bool)


def anchor_corners(linear: np.ndarray, options: GuidedMatchOptions = GuidedMatchOptions(),
                   valid: np.ndarray | None = None) -> np.ndarray:
    """Sub-pixel Shi-Tomasi corners [N, 2] (OpenCV px) of a linear RGB image [H, W, 3], found in log
    luminance so that the dark floor's texture counts as much as the lit walls' (the floor's points
    are the near ones that pin the camera centres).

    ``valid`` [H, W] bool: the pixels holding footage (a rectified view's black corners are not:
    :func:`~volcap_core.calibration.distortion.undistort_valid_mask`). The contrast stretch is taken
    over them and no corner is kept whose template (``options.template_half_px``) reaches outside
    them: the edge of a black corner is the strongest "corner" of the image but not in the scene,
    and it set the quality threshold (a fraction of the strongest response) that the scene's own
    corners were measured against."""
    L = log_luminance(linear)
    mask = None
    if valid is not None and not valid.all():
        lo, hi = np.percentile(L[valid], [0.5, 99.5]) if valid.any() else (0.0, 1.0)
        mask = _eroded(valid, options.template_half_px + 2).astype(np.uint8) * 255
    else:
        lo, hi = np.percentile(L, [0.5, 99.5])
    g = np.clip(np.round(255 * (L - lo) / max(hi - lo, 1e-6)), 0, 255).astype(np.uint8)
    c = cv2.goodFeaturesToTrack(g, options.max_corners, options.corner_quality, options.min_corner_distance_px,
                                mask=mask)
    if c is None:
        return np.zeros((0, 2))
    c = cv2.cornerSubPix(g, c.astype(np.float32).reshape(-1, 1, 2), (2, 2), (-1, -1),
                         (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 0.01))
    return c.reshape(-1, 2).astype(np.float64)


def _sample(img: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``img`` [H, W] at OpenCV pixel positions ``xy`` [..., 2] -> [...]."""
    H, W = img.shape
    g = torch.stack([(xy[..., 0] + 0.5) / W * 2 - 1, (xy[..., 1] + 0.5) / H * 2 - 1], -1)
    out = F.grid_sample(img[None, None], g.reshape(1, -1, 1, 2).to(img.dtype), mode="bilinear",
                        padding_mode="border", align_corners=False)
    return out.reshape(xy.shape[:-1])


def _ncc(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Normalised cross-correlation over the last dimension."""
    a = a - a.mean(-1, keepdim=True)
    b = b - b.mean(-1, keepdim=True)
    return (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1) + 1e-6)


def _compiled_scores():
    """:func:`~volcap_core.calibration.guided_numba.shifted_ncc`, imported on first use (numba's
    import costs ~0.5 s), or None where numba does not import: then the torch code scores."""
    try:
        from volcap_core.calibration.guided_numba import shifted_ncc
    except ImportError:
        return None
    return shifted_ncc


def _match_patches(image: torch.Tensor, template: torch.Tensor, warped: np.ndarray,
                   options: GuidedMatchOptions) -> tuple[np.ndarray, np.ndarray]:
    """Where each warped template sits in ``image``: the NCC peak over shifts within
    ``options.search_px`` (a grid of ``search_step_px``), refined by a parabola through the peak.

    ``image`` [H, W] float32 log luminance; ``template`` [n, Q] its values at the anchor camera;
    ``warped`` [n, Q, 2] the template's pixels mapped into this camera (OpenCV px, the centre pixel
    at ``Q // 2``). Returns the matches [n, 2] (OpenCV px) and which of them are good [n]: a peak
    above ``min_ncc``, inside the window, and sharp. Anchors go ``chunk_anchors`` at a time, so
    the memory is bounded whatever their number. The scores of float32 inputs come from the
    compiled kernel where numba imports (:mod:`~volcap_core.calibration.guided_numba`: the same
    NCC to float32 rounding; docs/benchmarks.md "Calibration's step 5, compiled"), else from
    ``_sample`` and ``_ncc``.
    """
    steps = torch.arange(-options.search_px, options.search_px + 1e-9, options.search_step_px)
    ns = len(steps)
    shifts = torch.stack(torch.meshgrid(steps, steps, indexing="xy"), -1).reshape(-1, 2)     # [S, 2]
    n, centre_q = len(warped), warped.shape[1] // 2
    compiled = _compiled_scores() if image.dtype == torch.float32 and template.dtype == torch.float32 else None
    matches, good = np.zeros((n, 2)), np.zeros(n, bool)
    for lo in range(0, n, options.chunk_anchors):
        hi = min(n, lo + options.chunk_anchors)
        w = torch.as_tensor(warped[lo:hi], dtype=torch.float32)
        if compiled is not None:
            score = torch.from_numpy(compiled(image.numpy(), template[lo:hi].numpy(), w.numpy(), steps.numpy()))
        else:
            values = _sample(image, w[:, None] + shifts[None, :, None, :])                    # [m, S, Q]
            score = _ncc(template[lo:hi, None], values).reshape(hi - lo, ns, ns)              # [m, y, x]
        peak, best = score.reshape(hi - lo, -1).max(1)
        by, bx = best // ns, best % ns
        ok = (peak > options.min_ncc) & (by > 0) & (by < ns - 1) & (bx > 0) & (bx < ns - 1)
        m = torch.arange(hi - lo)
        by, bx = by.clamp(1, ns - 2), bx.clamp(1, ns - 2)
        c0 = score[m, by, bx]
        left, right = score[m, by, bx - 1], score[m, by, bx + 1]
        up, down = score[m, by - 1, bx], score[m, by + 1, bx]
        dx = 0.5 * (left - right) / (left - 2 * c0 + right - 1e-9)
        dy = 0.5 * (up - down) / (up - 2 * c0 + down - 1e-9)
        ok &= (dx.abs() < 0.6) & (dy.abs() < 0.6)
        shift = torch.stack([steps[bx] + dx * options.search_step_px, steps[by] + dy * options.search_step_px], -1)
        if options.refine_iterations > 0:
            shift, ok = _refine_shift(image, template[lo:hi], w, shift, ok, options)
        matches[lo:hi] = warped[lo:hi, centre_q] + shift.double().numpy()
        good[lo:hi] = ok.numpy()
    return matches, good


def _refine_shift(image: torch.Tensor, template: torch.Tensor, warped: torch.Tensor, shift: torch.Tensor,
                  ok: torch.Tensor, options: GuidedMatchOptions) -> tuple[torch.Tensor, torch.Tensor]:
    """Re-centred sub-pixel refinement of the grid's peaks ``shift`` [m, 2]: NCC at the estimate and
    ``refine_step_px`` either side in x and in y, a parabola through each triple, repeated
    ``refine_iterations`` times. A match whose refinement leaves the search window, or whose NCC
    stops being a peak (a triple that is not concave), is dropped."""
    h = options.refine_step_px
    probe = torch.tensor([[0.0, 0.0], [-h, 0.0], [h, 0.0], [0.0, -h], [0.0, h]])
    for _ in range(options.refine_iterations):
        values = _sample(image, warped[:, None] + (shift[:, None, :] + probe[None])[:, :, None, :])   # [m, 5, Q]
        c0, left, right, up, down = _ncc(template[:, None], values).unbind(1)
        cx, cy = left - 2 * c0 + right, up - 2 * c0 + down
        ok = ok & (cx < 0) & (cy < 0)
        dx = (0.5 * (left - right) / (cx - 1e-9)).clamp(-1.0, 1.0)
        dy = (0.5 * (up - down) / (cy - 1e-9)).clamp(-1.0, 1.0)
        shift = shift + torch.stack([dx, dy], -1) * h
    ok = ok & (shift.abs() <= options.search_px).all(-1)
    return shift, ok


def guided_tracks(images: Mapping[str, np.ndarray], K: Mapping[str, np.ndarray],
                  world_to_camera: Mapping[str, np.ndarray], scan: LidarScan,
                  options: GuidedMatchOptions = GuidedMatchOptions(),
                  valid: Mapping[str, np.ndarray | None] | None = None) -> GuidedTracks:
    """Tracks between calibrated cameras, matched through the lidar scan (module docstring).

    ``images``: camera id -> linear RGB [H, W, 3] (background plates: actors are not in the scan),
    whose order is the tracks' camera order;
    ``K`` [3, 3] and ``world_to_camera`` [4, 4] per camera, good to a pixel or so (the search
    window is ``options.search_px``);
    ``valid``: camera id -> [H, W] bool, the pixels holding footage (None or absent: all), e.g. a
    rectified pincushion view's black corners are not: no anchor's template and no match's search
    window may reach outside them (NCC over a window with black in it is dominated by that edge).
    """
    t0 = time.perf_counter()
    ids = list(images)
    h = options.template_half_px
    size = {c: (images[c].shape[1], images[c].shape[0]) for c in ids}
    logl = {c: torch.as_tensor(log_luminance(images[c])) for c in ids}
    zbuf = {c: depth_buffer(K[c], world_to_camera[c], *size[c], scan.points) for c in ids}
    grid = torch.arange(-h, h + 1, dtype=torch.float64)
    offsets = torch.stack(torch.meshgrid(grid, grid, indexing="xy"), -1).reshape(-1, 2)     # [Q, 2]
    points, obs = [], []            # obs rows: (track, camera index, x, y)
    n_anchor = 0
    margin = h + options.search_px + 1
    valid = {c: v for c, v in (valid or {}).items() if v is not None and not np.all(v)}
    # a match's window: the template's pixels shifted by up to search_px, read bilinearly
    search_ok = {c: _eroded(v, int(np.ceil(options.search_px)) + 1) for c, v in valid.items()}
    dropped = 0
    for ia, a in enumerate(ids):
        W, H = size[a]
        uv = anchor_corners(images[a], options, valid.get(a))
        inside = (uv[:, 0] > h + 1) & (uv[:, 0] < W - h - 2) & (uv[:, 1] > h + 1) & (uv[:, 1] < H - h - 2)
        uv = uv[inside]
        X, ok = lift_to_lidar(K[a], world_to_camera[a], uv, scan, W, H)
        uv, X = uv[ok], X[ok]
        if not len(uv):
            continue
        normal = scan.normals[scan.nearest(X)[1]]
        Ca = camera_centre(world_to_camera[a])
        # the template's pixels, back-projected onto each anchor's local plane
        pix = uv[:, None, :] + offsets.numpy()[None]                                          # [N, Q, 2]
        rays = np.concatenate([pix, np.ones(pix.shape[:2] + (1,))], -1) @ np.linalg.inv(K[a]).T \
            @ world_to_camera[a][:3, :3]
        depth = np.einsum("nj,nj->n", normal, X - Ca)[:, None] / np.einsum("nj,nqj->nq", normal, rays)
        template_world = Ca + depth[..., None] * rays                                          # [N, Q, 3]
        template = _sample(logl[a], torch.as_tensor(pix))                                      # [N, Q]
        track = n_anchor + np.arange(len(uv))
        n_anchor += len(uv)
        points.append(X)
        obs.append(np.c_[track, np.full(len(uv), ia), uv])
        cos_a = np.abs(np.einsum("nj,nj->n", normal, Ca - X)) / np.linalg.norm(Ca - X, axis=1)
        for ib, b in enumerate(ids):
            if ib == ia:
                continue
            Wb, Hb = size[b]
            pred, z = project(K[b], world_to_camera[b], X)
            vis = (z > 0.1) & (pred[:, 0] > margin) & (pred[:, 0] < Wb - 1 - margin) \
                & (pred[:, 1] > margin) & (pred[:, 1] < Hb - 1 - margin) & (cos_a > options.min_view_cos)
            sel = np.flatnonzero(vis)
            ix = np.round(pred[sel]).astype(np.int64)
            sel = sel[z[sel] <= zbuf[b][ix[:, 1], ix[:, 0]] * (1 + options.occlusion_rel) + 0.02]
            Cb = camera_centre(world_to_camera[b])
            cos_b = np.abs(np.einsum("nj,nj->n", normal[sel], Cb - X[sel])) / np.linalg.norm(Cb - X[sel], axis=1)
            sel = sel[cos_b > options.min_view_cos]
            if not len(sel):
                continue
            warped, _ = project(K[b], world_to_camera[b], template_world[sel].reshape(-1, 3))
            warped = warped.reshape(len(sel), -1, 2)
            if b in search_ok:
                wi = np.clip(np.round(warped).astype(np.int64), 0, [Wb - 1, Hb - 1])
                inside = search_ok[b][wi[..., 1], wi[..., 0]].all(1)
                dropped += int((~inside).sum())
                sel, warped = sel[inside], warped[inside]
                if not len(sel):
                    continue
            match, good = _match_patches(logl[b], template[sel], warped, options)
            obs.append(np.c_[track[sel[good]], np.full(int(good.sum()), ib), match[good]])
    obs_all = np.concatenate(obs) if obs else np.zeros((0, 4))
    count = np.bincount(obs_all[:, 0].astype(np.int64), minlength=n_anchor)
    obs_all = obs_all[count[obs_all[:, 0].astype(np.int64)] >= 2]
    kept, obs_point = np.unique(obs_all[:, 0].astype(np.int64), return_inverse=True)
    pts = np.concatenate(points)[kept] if points else np.zeros((0, 3))
    return GuidedTracks(camera_ids=ids, points=pts, obs_point=obs_point.astype(np.int64),
                        obs_camera=obs_all[:, 1].astype(np.int64), obs_xy=obs_all[:, 2:4].astype(np.float64),
                        stats={"anchors": int(n_anchor), "tracks": int(len(kept)),
                               "observations": int(len(obs_all)), "outside_footage": dropped,
                               "seconds": time.perf_counter() - t0})
