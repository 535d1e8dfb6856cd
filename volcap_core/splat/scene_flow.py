"""The performers' initial motion: each frame's moving points' velocity from the training views'
optical flow, triangulated (scene flow).

Why: a moving Gaussian starts centred on its frame's time with no motion, so it can only live
about one frame; a frame's performers then get ~1/n of the segment's moving Gaussians and of its
steps. Given its point's velocity (``means_t``'s first-order term), a Gaussian stays on the body
over several frames (``TrainConfig.init_lifespan_frames``), so every frame sees several frames'
Gaussians and every Gaussian trains on several frames' views. Measured on the demo segment:
``docs/poly4dgs.md``, "The performers' initial motion".

For a frame's moving points ``X`` and a neighbouring frame (one interval before or after):

1. :func:`optical_flow` in every training camera, both ways between the two frames;
2. each point's projection moved by the forward flow where the camera sees it (the frame's own
   z-buffer) and the backward flow brings it back within ``fb_px`` (occlusions and mismatches fail);
3. :func:`moved_points`: the point that projects to the moved pixels through the neighbouring
   frame's cameras (least squares, two cameras at least);
4. :func:`point_velocities`: displacement over time, averaged over both neighbours; points no two
   cameras agree on take the median of their nearest known neighbours', and every velocity is that
   median (a body part moves as one; one flow vector is noisy).

Cameras are OpenCV pinholes: ``K [3, 3]`` with pixel centres at integers, ``world_to_camera
[4, 4]``; positions in metres, times in seconds, velocities in m/s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["FlowPair", "moved_points", "optical_flow", "point_velocities", "smoothed_velocities"]


def optical_flow(a: np.ndarray, b: np.ndarray, *, upsample: int = 2) -> np.ndarray:
    """Dense flow ``[H, W, 2]`` (pixels, x then y) from grey image ``a`` to ``b`` (``[H, W]``
    uint8): OpenCV's DIS at its medium preset, down to the finest scale, on the images upsampled
    ``upsample`` times (cubic) and brought back by area.

    Why not DIS's default: it stops at half resolution, and at the demo's 320x180 a limb is a few
    pixels wide, so its flow is dragged toward the still background and the velocities come out
    too slow (``docs/poly4dgs.md``, "The performers' initial motion", measures both)."""
    import cv2

    h, w = a.shape
    if upsample > 1:
        a = cv2.resize(a, None, fx=upsample, fy=upsample, interpolation=cv2.INTER_CUBIC)
        b = cv2.resize(b, None, fx=upsample, fy=upsample, interpolation=cv2.INTER_CUBIC)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setFinestScale(0)
    flow = dis.calc(a, b, None)
    if upsample > 1:
        flow = cv2.resize(flow, (w, h), interpolation=cv2.INTER_AREA) / upsample
    return flow.astype(np.float32)


@dataclass(frozen=True)
class FlowPair:
    """One training camera between a frame (``a``) and its neighbour (``b``): its cameras at both
    (a tracking camera moves and zooms), image size, and the optical flow both ways."""

    K_a: np.ndarray            # [3, 3]
    world_to_camera_a: np.ndarray   # [4, 4]
    K_b: np.ndarray
    world_to_camera_b: np.ndarray
    width: int
    height: int
    forward: np.ndarray        # [H, W, 2] flow a -> b, pixels
    backward: np.ndarray       # [H, W, 2] flow b -> a


def _project(K: np.ndarray, W: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(uv [N, 2] pixels, camera-space points [N, 3])``. Not ``calibration.geometry.project``: the
    depth is floored here so a point behind a camera keeps finite pixels and Jacobian, which its
    zero weight then cancels (an infinite one times zero would poison the solve with NaN)."""
    pc = xyz @ W[:3, :3].T + W[:3, 3]
    z = np.maximum(pc[:, 2], 1e-6)
    return pc[:, :2] / z[:, None] @ K[:2, :2].T + K[:2, 2], pc


def _sample(field: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples ``[N, C]`` of ``field [H, W, C]`` at ``uv`` (edge values outside)."""
    import cv2

    # remap's maps as rows of 1024 (a map side must stay under 32767; a frame holds ~1e5 points)
    n = len(uv)
    rows = max(1, -(-n // 1024))
    maps = np.zeros((2, rows * 1024), np.float32)
    maps[:, :n] = uv.T
    x, y = maps.reshape(2, rows, 1024)
    return np.stack([cv2.remap(np.ascontiguousarray(field[..., c]), x, y, cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE).ravel()[:n] for c in range(field.shape[-1])], axis=1)


def moved_points(xyz: np.ndarray, observations: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                 *, iterations: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the points went: for each point the position whose projections through the
    observing cameras land on its observed pixels, by Gauss-Newton from ``xyz`` (a small move:
    three iterations converge).

    Args:
        xyz: ``[N, 3]`` the points before they moved (metres).
        observations: per camera ``(K [3, 3], world_to_camera [4, 4], uv [N, 2] pixels, ok [N] bool)``:
            where that camera sees each point after the move, for the points with ``ok``.
    Returns:
        ``(moved [N, 3], cameras [N] int, rms_px [N])``: the cameras that observed each point and
        the root-mean-square reprojection error of the moved point over them (points with fewer
        than two observations are underdetermined: read ``cameras``).
    """
    x = np.asarray(xyz, np.float64).reshape(-1, 3).copy()
    n = len(x)
    count = np.zeros(n, np.int64)
    for *_, ok in observations:
        count += ok
    for _ in range(iterations):
        A = np.zeros((n, 3, 3))
        g = np.zeros((n, 3))
        for K, W, uv, ok in observations:
            proj, pc = _project(K, W, x)
            z = np.maximum(pc[:, 2], 1e-6)
            J = np.zeros((n, 2, 3))   # d(pixel) / d(camera-space point)
            J[:, 0, 0] = K[0, 0] / z
            J[:, 0, 2] = -K[0, 0] * pc[:, 0] / z ** 2
            J[:, 1, 1] = K[1, 1] / z
            J[:, 1, 2] = -K[1, 1] * pc[:, 1] / z ** 2
            J = (J @ W[:3, :3]) * ok[:, None, None]
            A += np.einsum("nki,nkj->nij", J, J)
            g += np.einsum("nki,nk->ni", J, (proj - uv) * ok[:, None])
        # Levenberg damping: a point seen once (or never) stays put along the unobserved directions
        A += (1e-3 * np.trace(A, axis1=1, axis2=2) / 3 + 1e-9)[:, None, None] * np.eye(3)
        x -= np.linalg.solve(A, g[..., None])[..., 0]
    err = np.zeros(n)
    for K, W, uv, ok in observations:
        proj, _ = _project(K, W, x)
        err += ok * ((proj - uv) ** 2).sum(axis=1)
    return x, count, np.sqrt(err / np.maximum(count, 1))


def point_velocities(xyz: np.ndarray, neighbours: Sequence[tuple[float, Sequence[FlowPair]]], *,
                     fb_px: float = 1.0, max_rms_px: float = 1.0, max_move_m: float = 0.2) -> np.ndarray:
    """Each point's velocity ``[N, 3]`` (m/s; NaN rows where no neighbour gave one): the mean over
    ``neighbours`` of its displacement to that frame over the time between them.

    Args:
        xyz: ``[N, 3]`` a frame's moving points.
        neighbours: per neighbouring frame ``(dt_s, pairs)``: its time minus the frame's, and one
            :class:`FlowPair` per training camera seeing both.
        fb_px: a camera's flow at a point counts where the backward flow returns within this.
        max_rms_px: a moved point counts where its reprojection error is within this.
        max_move_m: and where it moved less than this (a limb moves ~5 cm a frame at 24 fps).
    """
    from volcap_core.calibration.lidar import depth_buffer

    x = np.asarray(xyz, np.float64).reshape(-1, 3)
    estimates = []
    for dt_s, pairs in neighbours:
        observations = []
        for p in pairs:
            uv, pc = _project(p.K_a, p.world_to_camera_a, x)
            w, h = p.width, p.height
            seen = (pc[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
            # hidden behind another performer: deeper than the frame's own z-buffer (3 cm slack)
            zbuf = depth_buffer(p.K_a, p.world_to_camera_a, w, h, x, splat_px=1)
            ix = np.clip(np.round(uv).astype(np.int64), 0, [w - 1, h - 1])
            seen &= pc[:, 2] <= zbuf[ix[:, 1], ix[:, 0]] + 0.03
            moved = uv + _sample(p.forward, uv)
            back = _sample(p.backward, moved)
            ok = seen & (np.linalg.norm(moved + back - uv, axis=1) < fb_px)
            observations.append((p.K_b, p.world_to_camera_b, moved, ok))
        if not observations:
            continue
        to, cams, rms = moved_points(x, observations)
        good = (cams >= 2) & (rms < max_rms_px) & (np.linalg.norm(to - x, axis=1) < max_move_m)
        v = np.full_like(x, np.nan)
        v[good] = (to[good] - x[good]) / dt_s
        estimates.append(v)
    if not estimates:
        return np.full_like(x, np.nan)
    stack = np.stack(estimates)
    known = np.isfinite(stack[..., 0])
    out = np.full_like(x, np.nan)
    some = known.any(axis=0)
    out[some] = np.nansum(np.where(known[..., None], stack, 0.0), axis=0)[some] / known.sum(axis=0)[some, None]
    return out


def smoothed_velocities(xyz: np.ndarray, velocity: np.ndarray, *, neighbours: int = 32) -> np.ndarray:
    """``[N, 3]``: each point's velocity as the per-axis median of its ``neighbours`` nearest points'
    known (finite) ones; zero everywhere when fewer than that many are known. A body part moves
    as one, and one point's flow is noisy (measured against the truth: ``docs/poly4dgs.md``,
    "The performers' initial motion")."""
    from scipy.spatial import cKDTree

    x = np.asarray(xyz, np.float64).reshape(-1, 3)
    known = np.isfinite(velocity).all(axis=1)
    if known.sum() < neighbours:
        return np.zeros_like(x)
    _, idx = cKDTree(x[known]).query(x, k=neighbours)
    return np.median(velocity[known][idx], axis=1)
