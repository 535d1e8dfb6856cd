"""A tracking camera's zoom lens: the focal its encoder reads, smoothed into the solve's prior,
and its distortion at each frame's focal, for undistorting the frame's keypoints.

A tracking camera whose rig carries a zoom lens table (``Rig.zoom_intrinsics``: its own or its lens
group's; distortion, optionally principal point, over the focal) has each frame's keypoints
undistorted, right after SIFT and before any matching, with the lens at that frame's focal as the
smoothed encoder gives it (the prior ``s(t)``, known before the solve), into the pinhole of
``K_t = (s(t), s(t), c_t)``; everything after (2D-3D and 2D-2D matching, the background
homographies, the solve) works on pinholes, and the solution's ``K`` is the pinhole of that frame's
rectified image (the same fx, fy, cx, cy as the raw frame, no distortion).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from volcap_core.calibration.distortion import Distortion

#: ``undistort(take index, raw pixels [N, 2]) -> (pinhole pixels [N, 2], converged [N] bool)``
Undistorter = Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]

#: a zoom lens: ``lens(focal_mm [T]) -> (distCoeffs [T, 5 or 8] OpenCV, principal [T, 2] px or None)``
ZoomLens = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]]


def smooth_encoder_focal(frames: np.ndarray, focal: np.ndarray, frame_count: int,
                         lam: float = 4.0, iterations: int = 5) -> np.ndarray:
    """Robust smooth curve through lens-encoder focal readings.

    ``frames`` [S] take indices of the readings, ``focal`` [S] readings (any unit); returns [T]
    (T = ``frame_count``, same unit): a Whittaker smoother (second differences, weight ``lam``) with
    Cauchy re-weighting (scale = 1.4826 MAD of the residuals), so a glitching reading does not bend
    it. Frames without a reading are interpolated by the smoother.
    """
    frames = np.asarray(frames, np.int64)
    y = np.zeros(frame_count)
    w0 = np.zeros(frame_count)
    ok = (frames >= 0) & (frames < frame_count)
    y[frames[ok]] = np.asarray(focal, np.float64)[ok]
    w0[frames[ok]] = 1.0
    if w0.sum() == 0:
        raise ValueError("no encoder reading inside the take")
    if frame_count < 3:
        return np.full(frame_count, y[w0 > 0].mean())
    D = np.diff(np.eye(frame_count), 2, axis=0)
    P = lam * D.T @ D
    w = w0.copy()
    z = y.copy()
    for _ in range(iterations):
        z = np.linalg.solve(np.diag(w) + P + 1e-12 * np.eye(frame_count), w * y)
        r = (y - z)[w0 > 0]
        s = max(1.4826 * np.median(np.abs(r)), 1e-9 * max(1.0, np.abs(y).max()))
        w = w0 / (1 + ((y - z) / (3 * s)) ** 2)
    return z


def zoom_lens(table) -> ZoomLens | None:
    """A rig's zoom lens table (``hardware.rig.ZoomIntrinsics``: ``model``, ``at_each(focals_mm)``
    -> samples with ``params``, ``cx``, ``cy``; None -> None) as a :data:`ZoomLens`: OpenCV's
    coefficients at each focal (5, or 8 when the table has a rational term), and the principal point
    when the table has one."""
    if table is None:
        return None

    def lens(focal_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        smp = table.at_each(np.asarray(focal_mm, np.float64).reshape(-1))
        coeffs = np.array([Distortion(table.model, s.params).opencv_full() for s in smp], np.float64).reshape(-1, 8)
        n = 8 if np.any(coeffs[:, 5:]) else 5
        pp = None
        if smp and smp[0].cx is not None:
            pp = np.array([[s.cx, s.cy] for s in smp], np.float64)
        return coeffs[:, :n], pp

    return lens


def frame_undistorter(focal_px: np.ndarray, principal: np.ndarray, coeffs: np.ndarray) -> Undistorter:
    """An :data:`Undistorter` for a camera whose frame t has the lens ``coeffs[t]`` (OpenCV) with
    focal ``focal_px[t]`` and principal point ``principal[t]``: raw pixels -> the pinhole with the
    same focal and principal point."""
    focal_px = np.asarray(focal_px, np.float64)
    principal = np.asarray(principal, np.float64)
    lenses = [Distortion.from_opencv(c) for c in np.asarray(coeffs, np.float64)]

    def undistort(t: int, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f, c = focal_px[t], principal[t]
        xy, ok = lenses[t].undistort_converged((np.asarray(uv, np.float64) - c) / f)
        return xy * f + c, ok

    return undistort


def lens_corner_shift_px(focal_px: np.ndarray, principal: np.ndarray, coeffs: np.ndarray, width: int,
                         height: int) -> np.ndarray:
    """[T]: how far each frame's lens moves the image corners (px, the largest of the four): the
    size of what undistortion corrects."""
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]])
    und = frame_undistorter(focal_px, principal, coeffs)
    return np.array([np.linalg.norm(und(t, corners)[0] - corners, axis=1).max() for t in range(len(focal_px))])
