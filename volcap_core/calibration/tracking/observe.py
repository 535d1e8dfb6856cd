"""What a tracking camera sees of the static model: its 2D-3D and 2D-2D matches.

- 2D-3D: SIFT of each frame matched to the static reference (:func:`build_static_reference`: SIFT of
  the static cameras' background plates lifted onto the lidar scan, plus the sparse SfM points);
- 2D-2D: SIFT matches between frames t and t+k of the same camera (k in ``pair_offsets``), kept when
  they follow the dominant homography; for a camera that only rotates and zooms, background points
  map between its frames by ``K_j R_j R_i^T K_i^-1`` whatever their depth, so these constrain
  relative rotations and focal ratios very precisely.

After a first solve, the 2D-3D matches are found again guided by it (:func:`guided_observations`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import cv2
import numpy as np
from scipy.spatial import cKDTree

from volcap_core.calibration.features import SiftOptions, extract_sift, match_descriptors
from volcap_core.calibration.geometry import project
from volcap_core.calibration.images import to_uint8_gray
from volcap_core.calibration.lidar import LidarScan, lift_to_lidar
from volcap_core.calibration.tracking.lens import Undistorter
from volcap_core.calibration.tracking.options import TrackingOptions


@dataclass
class StaticReference:
    """3D points [N, 3] (stage frame) with SIFT descriptors [N, 128] uint8, from the static cameras."""

    points: np.ndarray
    descriptors: np.ndarray


def build_static_reference(images: Mapping[str, np.ndarray], K: Mapping[str, np.ndarray],
                           world_to_camera: Mapping[str, np.ndarray], scan: LidarScan | None,
                           *, sparse_points: np.ndarray | None = None,
                           sparse_descriptors: np.ndarray | None = None,
                           sift: SiftOptions = SiftOptions()) -> StaticReference:
    """SIFT of calibrated static views (background plates preferably), lifted onto the lidar scan.

    ``images``: id -> linear RGB [H, W, 3]. ``sparse_points`` [P, 3] with ``sparse_descriptors``
    [P, 128] (e.g. the SfM points and one descriptor of each) are appended. Without a scan only the
    sparse points are used.
    """
    pts, descs = [], []
    if scan is not None:
        for cid in sorted(images):
            img = images[cid]
            kp, de = extract_sift(to_uint8_gray(img), sift)
            X, ok = lift_to_lidar(K[cid], world_to_camera[cid], kp[:, :2], scan, img.shape[1], img.shape[0])
            pts.append(X[ok])
            descs.append(de[ok])
    if sparse_points is not None and sparse_descriptors is not None:
        good = np.isfinite(sparse_points).all(1)
        pts.append(np.asarray(sparse_points)[good])
        descs.append(np.asarray(sparse_descriptors)[good])
    if not pts:
        raise ValueError("a static reference needs a lidar scan or sparse points")
    return StaticReference(np.concatenate(pts).astype(np.float64), np.concatenate(descs).astype(np.uint8))


# --------------------------------------------------------------------------- observations

@dataclass
class TrackingObservations:
    """What one tracking camera saw. 2D-3D: ``m3_frame`` [A], ``m3_uv`` [A, 2], ``m3_X`` [A, 3].
    2D-2D: ``m2_i`` [B], ``m2_j`` [B] frames, ``m2_ui`` [B, 2], ``m2_uj`` [B, 2]. Homographies
    ``H[(i, j)]`` mapping frame i pixels to frame j pixels (consecutive pairs)."""

    frame_count: int
    width: int
    height: int
    m3_frame: np.ndarray
    m3_uv: np.ndarray
    m3_X: np.ndarray
    m2_i: np.ndarray
    m2_j: np.ndarray
    m2_ui: np.ndarray
    m2_uj: np.ndarray
    H: dict = field(default_factory=dict)
    seconds: float = 0.0
    #: each frame's SIFT keypoints [K_t, 2] (in the frame's pinhole when undistorted) and
    #: descriptors [K_t, 128] uint8, for the guided 2D-3D matching after the first solve
    keypoints: list = field(default_factory=list)
    descriptors: list = field(default_factory=list)


def observe_tracking_camera(frames: Sequence[np.ndarray], reference: StaticReference,
                            options: TrackingOptions = TrackingOptions(),
                            undistort: Undistorter | None = None) -> TrackingObservations:
    """Features and matches of one tracking camera. ``frames``: linear RGB [H, W, 3] per take index.
    ``undistort`` (:func:`~volcap_core.calibration.tracking.lens.frame_undistorter`): each frame's
    keypoints are moved into that frame's pinhole before any matching (a keypoint beyond the lens's
    fold is dropped)."""
    t0 = time.perf_counter()
    T = len(frames)
    h, w = frames[0].shape[:2]
    feats = []
    for t, f in enumerate(frames):
        kp, de = extract_sift(to_uint8_gray(f), options.sift)
        if undistort is not None and len(kp):
            kp = np.array(kp, dtype=np.float64, copy=True)
            uv, ok = undistort(t, kp[:, :2].astype(np.float64))
            kp[:, :2] = uv
            kp, de = kp[ok], de[ok]
        feats.append((kp, de))
    f3, uv3, X3 = [], [], []
    for t, (kp, de) in enumerate(feats):
        m = match_descriptors(de, reference.descriptors, ratio=options.ratio_3d)
        if len(m):
            f3.append(np.full(len(m), t))
            uv3.append(kp[m[:, 0], :2])
            X3.append(reference.points[m[:, 1]])
    i2, j2, ui2, uj2 = [], [], [], []
    Hs = {}
    for k in options.pair_offsets:
        for i in range(T - k):
            j = i + k
            kpi, dei = feats[i]
            kpj, dej = feats[j]
            m = match_descriptors(dei, dej, ratio=options.ratio_2d, mutual=True)
            if len(m) < options.min_pair_matches:
                continue
            a = kpi[m[:, 0], :2].astype(np.float64)
            b = kpj[m[:, 1], :2].astype(np.float64)
            H, mask = _background_homography(a, b, options)
            if H is None:
                continue
            if k == 1:
                Hs[(i, j)] = H
            i2.append(np.full(mask.sum(), i))
            j2.append(np.full(mask.sum(), j))
            ui2.append(a[mask])
            uj2.append(b[mask])

    def cat(x, shape):
        return np.concatenate(x) if x else np.zeros(shape)

    return TrackingObservations(T, w, h, cat(f3, (0,)).astype(np.int64), cat(uv3, (0, 2)), cat(X3, (0, 3)),
                                cat(i2, (0,)).astype(np.int64), cat(j2, (0,)).astype(np.int64),
                                cat(ui2, (0, 2)), cat(uj2, (0, 2)), Hs, time.perf_counter() - t0,
                                [np.asarray(kp[:, :2], np.float64) for kp, _ in feats], [de for _, de in feats])


def _background_homography(a: np.ndarray, b: np.ndarray, o: "TrackingOptions"):
    """The homography of the background between two frames of a tracking camera, and its inlier mask.

    A tracking camera follows an actor, so two motions compete: the background's (the camera's pan
    and zoom) and the actor's, which stays nearly still in the image. The dominant RANSAC model is
    sometimes the actor's; so a second model is fitted to the rest, and of the two (each with enough
    inliers) the one that moves more in the image is taken as the background.
    """
    H1, m1 = cv2.findHomography(a, b, cv2.RANSAC, o.homography_px, maxIters=2000, confidence=0.999)
    if H1 is None:
        return None, None
    m1 = m1.ravel().astype(bool)
    if m1.sum() < o.min_pair_matches:
        return None, None
    rest = ~m1
    if rest.sum() >= o.min_pair_matches:
        H2, m2 = cv2.findHomography(a[rest], b[rest], cv2.RANSAC, o.homography_px, maxIters=2000, confidence=0.999)
        if H2 is not None:
            m2r = m2.ravel().astype(bool)
            mask2 = np.zeros(len(a), bool)
            mask2[np.flatnonzero(rest)[m2r]] = True
            if mask2.sum() >= max(o.min_pair_matches, 0.3 * m1.sum()):
                move1 = np.median(np.linalg.norm(b[m1] - a[m1], axis=1))
                move2 = np.median(np.linalg.norm(b[mask2] - a[mask2], axis=1))
                if move2 > move1 + 2 * o.homography_px:
                    return H2, mask2
    return H1, m1


def undistort_observations(obs: TrackingObservations, undistort: Undistorter) -> TrackingObservations:
    """Matched observations of raw frames (already matched, e.g. a synthetic test's) moved into each
    frame's pinhole by ``undistort`` (:func:`~volcap_core.calibration.tracking.lens.frame_undistorter`);
    a match with a point beyond the lens's fold is dropped. :func:`observe_tracking_camera` does the
    same to keypoints before matching."""
    def move(frames: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out, ok = np.array(uv, np.float64, copy=True), np.ones(len(uv), bool)
        for t in np.unique(frames):
            sel = frames == t
            out[sel], ok[sel] = undistort(int(t), uv[sel])
        return out, ok

    uv3, ok3 = move(obs.m3_frame, obs.m3_uv)
    ui, oki = move(obs.m2_i, obs.m2_ui)
    uj, okj = move(obs.m2_j, obs.m2_uj)
    ok2 = oki & okj
    return TrackingObservations(obs.frame_count, obs.width, obs.height, obs.m3_frame[ok3], uv3[ok3], obs.m3_X[ok3],
                                obs.m2_i[ok2], obs.m2_j[ok2], ui[ok2], uj[ok2], dict(obs.H), obs.seconds)


def guided_observations(obs: TrackingObservations, reference: StaticReference, K: np.ndarray,
                        world_to_camera: np.ndarray, options: TrackingOptions = TrackingOptions()
                        ) -> TrackingObservations:
    """``obs`` with its 2D-3D matches found again, guided by a solution (``K`` [T, 3, 3],
    ``world_to_camera`` [T, 4, 4]): each frame's keypoints (``obs.keypoints``) against only the
    reference points that frame's camera projects within ``options.guided_radius_px`` of them,
    the nearest descriptor kept when it passes the ratio test among those candidates and is within
    ``options.guided_max_distance``. Matching the whole reference (the first solve) has to pass a
    ratio test against every point of the stage, which a zoomed view's few background features
    mostly fail; near its projection a point has few rivals."""
    f3, uv3, X3 = [], [], []
    r = float(options.guided_radius_px)
    for t, (kp, de) in enumerate(zip(obs.keypoints, obs.descriptors)):
        if len(kp) == 0:
            continue
        p, z = project(K[t], world_to_camera[t], reference.points)
        near = (z > 1e-3) & (p[:, 0] > -r) & (p[:, 0] < obs.width + r) & (p[:, 1] > -r) & (p[:, 1] < obs.height + r)
        if not near.any():
            continue
        idx = np.flatnonzero(near)
        tree = cKDTree(p[near])
        des = reference.descriptors[idx].astype(np.float32)
        for k, cand in enumerate(tree.query_ball_point(kp, r)):
            if not cand:
                continue
            d = np.linalg.norm(des[cand] - de[k].astype(np.float32), axis=1)
            order = np.argsort(d)
            if d[order[0]] > options.guided_max_distance or (
                    len(cand) > 1 and d[order[0]] > options.guided_ratio * d[order[1]]):
                continue
            f3.append(t)
            uv3.append(kp[k])
            X3.append(reference.points[idx[cand[order[0]]]])
    if not f3:
        return replace(obs, m3_frame=np.zeros(0, np.int64), m3_uv=np.zeros((0, 2)), m3_X=np.zeros((0, 3)))
    return replace(obs, m3_frame=np.asarray(f3, np.int64), m3_uv=np.asarray(uv3, np.float64),
                   m3_X=np.asarray(X3, np.float64))
