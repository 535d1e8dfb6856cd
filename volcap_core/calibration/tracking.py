"""Tracking (pan/tilt/zoom) cameras: a pose and a focal length at every frame.

Every tracking camera is registered at every frame against the *fixed* static model, then its whole
sequence is refined jointly with priors, because per-frame focal and depth trade off (a zoom-in looks
like a dolly-in) and per-frame estimates drift and stutter.

Observations (:func:`observe_tracking_camera`):

- 2D-3D: SIFT of each frame matched to the static reference (:func:`build_static_reference`: SIFT of
  the static cameras' background plates lifted onto the lidar scan, plus the sparse SfM points);
- 2D-2D: SIFT matches between frames t and t+k of the same camera (k in ``pair_offsets``), kept when
  they follow the dominant homography; for a camera that only rotates and zooms, background points
  map between its frames by ``K_j R_j R_i^T K_i^-1`` whatever their depth, so these constrain
  relative rotations and focal ratios very precisely.

Initialisation (:func:`initialise_tracking`): focal from the smoothed lens encoder, centre at the
rig's mount, relative rotations from the frame-to-frame homographies, absolute orientation by a
two-point RANSAC over the 2D-3D matches of all frames pooled (few per frame at high zoom, hundreds
together).

Refinement (:func:`refine_tracking`, torch, batched over cameras): Levenberg-Marquardt over, per frame,
rotation (3), centre (3) and log focal (1), and per camera a mean centre (3), a focal gain (log) and
an offset, minimising (Cauchy-robust) 2D-3D and 2D-2D reprojection errors plus

- a focal prior: ``log f_t = log(exp(a) * s(t) + b) ± focal_sigma_rel``, ``s`` the encoder focal
  (px) smoothed robustly over time (:func:`smooth_encoder_focal`), ``a, b`` the per-camera gain and
  offset (the encoder's calibration error);
- a centre prior: ``C_t = C_mean ± centre_sigma_m`` (the head barely translates).

The refinement can run from several starts along the zoom/dolly valley (:func:`dolly_zoom_start`,
``focal_scale_starts``; one by default), each camera keeping its lowest-cost result
(:func:`solve_tracking`); then the 2D-3D matches are found again guided by that solution
(:func:`guided_observations`) and the solve is refined once more on them. The solution's stats
carry its covariance's spread (``focal_sigma_pct``, ``rotation_sigma_deg``, ``centre_sigma_m``) and
:func:`tracking_support` says whether it can be returned as calibrated.

``mode="free"`` drops both priors (per-frame focal and centre free, still joint); ``"independent"``
also drops the 2D-2D terms: every frame alone, the classic per-frame registration.

Zoom lenses (:func:`zoom_lens`, ``lenses`` of :func:`prepare_tracking`): a tracking camera whose rig
carries a zoom lens table (``Rig.zoom_intrinsics``: its own or its lens group's; distortion,
optionally principal point, over the focal) has each frame's keypoints undistorted, right after
SIFT and before any matching, with the lens at that frame's focal as the smoothed encoder gives it
(the prior ``s(t)``, known before the solve), into the pinhole of ``K_t = (s(t), s(t), c_t)``;
everything after (2D-3D and 2D-2D matching, the background homographies, the solve) works on
pinholes, and the solution's ``K`` is the pinhole of that frame's rectified image (the same fx,
fy, cx, cy as the raw frame, no distortion). The lens each frame was undistorted with is :attr:`TrackingSolution.distortion`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

import cv2
import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from scipy.spatial import cKDTree

from volcap_core.calibration.distortion import Distortion
from volcap_core.calibration.features import SiftOptions, extract_sift, match_descriptors
from volcap_core.calibration.geometry import camera_centre, project
from volcap_core.calibration.images import to_uint8_gray
from volcap_core.calibration.lidar import LidarScan, lift_to_lidar

NF = 7   # per-frame parameters: rotation (3), centre (3), log focal (1)
NG = 5   # per-camera parameters: mean centre (3), focal gain (log), focal offset (px)


@dataclass(frozen=True)
class TrackingOptions:
    #: SIFT for the zoomed frames: more octaves (their background is many times larger)
    sift: SiftOptions = SiftOptions(num_octaves=6)
    ratio_3d: float = 0.85
    ratio_2d: float = 0.8
    pair_offsets: tuple[int, ...] = (1, 2, 4)
    #: RANSAC threshold of the frame-to-frame background homography. Between neighbouring frames
    #: the background of a tracker that follows an actor moves 3-6 px at 320x180, about what the
    #: actor moves: at 3 px the background's model took in half the actor's matches and seed 3's
    #: S011 (upper body, 15 2D-3D inliers) ended 2° off; at 1.5 px (SIFT's error is ~0.3-0.5 px)
    #: 0.3° (0.19° with the guided matching), the other trackers of four renders unchanged
    #: (docs/calibration.md)
    homography_px: float = 1.5
    min_pair_matches: int = 12
    pixel_sigma_3d: float = 2.0
    pixel_sigma_2d: float = 1.0
    focal_sigma_rel: float = 0.003
    centre_sigma_m: float = 0.005
    #: prior of the mean centre around the rig's mount (a zoomed view barely tells a sideways
    #: shift from a pan: without it the centre slides tens of cm)
    mount_sigma_m: float = 0.05
    smooth_lambda: float = 4.0
    iterations: int = 30
    #: starts along the zoom/dolly valley: the refinement is run from the initial focal scaled by
    #: each factor (and the centre moved along the view axis so the scene keeps its image size)
    #: and each camera keeps its lowest-cost solution. One start (the encoder's focal) is enough:
    #: LM slides along the valley to its lowest point from starts 3 % either side (the seven starts
    #: 0.97 ... 1.03 once looked needed because a 2D-3D match behind the camera froze the focal
    #: where it started: docs/calibration.md, "Tracking (zoom) cameras"). More starts are for a
    #: take whose cost along the valley has more than one dip
    focal_scale_starts: tuple[float, ...] = (1.0,)
    #: guided 2D-3D matching after the first solve (:func:`guided_observations`): each frame's
    #: keypoints matched only to the reference points its solved camera projects within this radius
    #: (None: off), ratio test among those candidates, and a ceiling on the SIFT distance; then the
    #: solve is refined from its solution. On four distorted demo renders the trackers' 2D-3D
    #: inliers rose 1.2-2.7x and the worst focal error fell from 1.32 % to 0.52 %
    guided_radius_px: float | None = 6.0
    guided_ratio: float = 0.9
    guided_max_distance: float = 250.0
    mode: str = "priors"            # priors | free | independent
    #: undistort each frame with its zoom lens at its focal (the ``lenses`` given to
    #: :func:`prepare_tracking`, from the rig's ``zoom_intrinsics``); False reads the raw frames as
    #: pinholes with the principal point at the image centre (what was done before the rigs held
    #: zoom lens tables; kept to measure what the lens is worth)
    zoom_distortion: bool = True
    ransac_iterations: int = 2000
    ransac_px: float = 12.0
    #: support a camera needs to be returned as calibrated (:func:`tracking_support`): 2D-3D inliers
    #: over the take (the trackers of the demo renders have 30-1270) and the covariance's bound on
    #: any frame's orientation (0.06-0.50° on them; None: no bound)
    min_inliers_3d: int = 8
    max_rotation_sigma_deg: float | None = 2.0
    #: an unsupported camera is left out of the calibration (listed with the reason) instead of an
    #: error (``volcap calibrate --allow-unregistered``)
    allow_unsupported: bool = False
    device: str = "cpu"
    seed: int = 0


# --------------------------------------------------------------------------- the encoder prior

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


# --------------------------------------------------------------------------- the static reference

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


#: ``undistort(take index, raw pixels [N, 2]) -> (pinhole pixels [N, 2], converged [N] bool)``
Undistorter = Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]


def observe_tracking_camera(frames: Sequence[np.ndarray], reference: StaticReference,
                            options: TrackingOptions = TrackingOptions(),
                            undistort: Undistorter | None = None) -> TrackingObservations:
    """Features and matches of one tracking camera. ``frames``: linear RGB [H, W, 3] per take index.
    ``undistort`` (:func:`frame_undistorter`): each frame's keypoints are moved into that frame's
    pinhole before any matching (a keypoint beyond the lens's fold is dropped)."""
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


# --------------------------------------------------------------------------- initialisation

def _principal_per_frame(principal, T: int) -> np.ndarray:
    """(cx, cy) or [T', 2] -> [T, 2] float64 (one principal point per frame; rows past T' repeat
    the last)."""
    pp = np.asarray(principal, np.float64)
    if pp.ndim == 1:
        return np.broadcast_to(pp.reshape(1, 2), (T, 2)).copy()
    if len(pp) < T:
        pp = np.concatenate([pp, np.repeat(pp[-1:], T - len(pp), 0)])
    return pp[:T].reshape(T, 2).copy()


def _orthonormal(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1, 1, -1]) @ Vt
    return R


def _bearings(uv: np.ndarray, f: float, cx: float, cy: float) -> np.ndarray:
    b = np.stack([(uv[:, 0] - cx) / f, (uv[:, 1] - cy) / f, np.ones(len(uv))], 1)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _ransac_rotation(a: np.ndarray, b: np.ndarray, thr: float, rng: np.random.Generator,
                     iterations: int) -> np.ndarray:
    """Rotation R with R a_i ≈ b_i (unit vectors [N, 3]) from 2-point samples; refit on the inliers
    (|R a - b| < thr) a few times."""
    n = len(a)
    if n < 2:
        return np.eye(3)
    best, best_n = np.ones(n, bool), -1
    for _ in range(iterations):
        i, j = rng.choice(n, 2, replace=False)
        if abs(a[i] @ a[j]) > 0.9999995:
            continue
        R = _kabsch(a[[i, j]], b[[i, j]])
        inl = np.linalg.norm(a @ R.T - b, axis=1) < thr
        cnt = int(inl.sum())
        if cnt > best_n:
            best, best_n = inl, cnt
    R = _kabsch(a[best], b[best]) if best.sum() >= 2 else np.eye(3)
    for _ in range(3):
        inl = np.linalg.norm(a @ R.T - b, axis=1) < thr
        if inl.sum() >= 3:
            R = _kabsch(a[inl], b[inl])
    return R


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |R a_i - b_i|^2 (unit vectors [N, 3])."""
    U, _, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def initialise_tracking(obs: TrackingObservations, focal_px: np.ndarray, centre: np.ndarray,
                        principal, options: TrackingOptions = TrackingOptions()
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Initial rotations [T, 3, 3], centres [T, 3] and focal lengths [T] of one tracking camera.

    ``focal_px`` [T]: the smoothed encoder focal; ``centre`` [3]: the mount position (metres);
    ``principal``: (cx, cy), or [T, 2] one per frame (a zoom lens whose axis moves with the zoom).
    """
    T = obs.frame_count
    pp = _principal_per_frame(principal, T)
    # relative rotations R_t R_{t-1}^T: robust Kabsch on the bearings of the matches of (t-1, t)
    rng = np.random.default_rng(options.seed)
    rel = [np.eye(3)]
    cons = (obs.m2_j - obs.m2_i) == 1
    for t in range(1, T):
        sel = cons & (obs.m2_i == t - 1)
        if sel.sum() < 3:
            rel.append(rel[-1])
            continue
        bi = _bearings(obs.m2_ui[sel], focal_px[t - 1], *pp[t - 1])
        bj = _bearings(obs.m2_uj[sel], focal_px[t], *pp[t])
        rel.append(_ransac_rotation(bi, bj, 2.0 / focal_px[t], rng, 200) @ rel[-1])
    rel = np.asarray(rel)
    # pooled bearings in the frame-0 orientation
    t3 = obs.m3_frame
    uv = obs.m3_uv
    if len(t3) < 3:
        raise RuntimeError("tracking camera: fewer than 3 2D-3D matches over the whole take")
    rays = np.stack([(uv[:, 0] - pp[t3, 0]) / focal_px[t3], (uv[:, 1] - pp[t3, 1]) / focal_px[t3],
                     np.ones(len(t3))], 1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    b = np.einsum("nji,nj->ni", rel[t3], rays)                    # R_rel^T ray
    d = obs.m3_X - centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    thr = options.ransac_px / np.median(focal_px)
    n = len(b)
    R0 = _ransac_rotation(d, b, thr, rng, options.ransac_iterations)
    inl = np.linalg.norm(d @ R0.T - b, axis=1) < thr
    R = rel @ R0
    C = np.repeat(np.asarray(centre, np.float64)[None], T, 0)
    return R, C, np.asarray(focal_px, np.float64).copy(), {"ransac_inliers": int(inl.sum()), "matches_3d": n,
                                                           "homographies": len(obs.H)}


# --------------------------------------------------------------------------- refinement

@dataclass
class TrackingSolution:
    """Per frame: ``K`` [T, 3, 3], ``world_to_camera`` [T, 4, 4]; per camera: focal ``gain``
    (multiplier on the smoothed encoder focal) and ``offset`` (px), mean ``centre`` [3].
    ``distortion`` [T, 5 or 8]: OpenCV's distCoeffs of each frame's lens (a zoom lens: the lens at
    that frame's focal) that the frame's observations were undistorted with, so ``K[t]`` is the
    pinhole of frame t rectified with it; None: the raw frames are pinholes."""

    K: np.ndarray
    world_to_camera: np.ndarray
    gain: float
    offset: float
    centre: np.ndarray
    stats: dict
    distortion: np.ndarray | None = None
    #: why the camera is left out of the calibration (:func:`tracking_support`), None when supported
    unsupported: str | None = None


def _skew(v: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(v[..., 0])
    return torch.stack([torch.stack([z, -v[..., 2], v[..., 1]], -1),
                        torch.stack([v[..., 2], z, -v[..., 0]], -1),
                        torch.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _dpi(w: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """d pi / d w [Q, 2, 3] for pi = f * w_xy / w_z."""
    z = w[:, 2]
    d = torch.zeros(len(w), 2, 3, dtype=w.dtype, device=w.device)
    d[:, 0, 0] = f / z
    d[:, 1, 1] = f / z
    d[:, 0, 2] = -f * w[:, 0] / z ** 2
    d[:, 1, 2] = -f * w[:, 1] / z ** 2
    return d


class _Batch:
    """All cameras' observations concatenated, with the camera index of each."""

    def __init__(self, obs: list[TrackingObservations], principal: np.ndarray, prior_px: list[np.ndarray],
                 mounts: list[np.ndarray], o: TrackingOptions, dev):
        f64 = dict(dtype=torch.float64, device=dev)
        self.B = len(obs)
        self.T = max(ob.frame_count for ob in obs)
        self.n = NF * self.T + NG
        c3, t3, uv3, X3 = [], [], [], []
        c2, i2, j2, ui2, uj2 = [], [], [], [], []
        for b, ob in enumerate(obs):
            c3.append(np.full(len(ob.m3_frame), b))
            t3.append(ob.m3_frame)
            uv3.append(ob.m3_uv)
            X3.append(ob.m3_X)
            if o.mode != "independent":
                c2.append(np.full(len(ob.m2_i), b))
                i2.append(ob.m2_i)
                j2.append(ob.m2_j)
                ui2.append(ob.m2_ui)
                uj2.append(ob.m2_uj)
        L = lambda xs, s: torch.as_tensor(np.concatenate(xs) if xs else np.zeros(s), device=dev)  # noqa: E731
        self.c3 = L(c3, (0,)).long()
        self.t3 = L(t3, (0,)).long()
        self.uv3 = L(uv3, (0, 2)).to(torch.float64)
        self.X3 = L(X3, (0, 3)).to(torch.float64)
        self.c2 = L(c2, (0,)).long()
        self.i2 = L(i2, (0,)).long()
        self.j2 = L(j2, (0,)).long()
        self.ui2 = L(ui2, (0, 2)).to(torch.float64)
        self.uj2 = L(uj2, (0, 2)).to(torch.float64)
        self.pp = torch.as_tensor(principal, **f64)                                   # [B, T, 2]
        self.s = torch.stack([torch.as_tensor(p, **f64) for p in prior_px])            # [B, T]
        self.mount = torch.as_tensor(np.stack([ob_mount for ob_mount in mounts]), **f64)  # [B, 3]
        self.valid_frame = torch.zeros(self.B, self.T, dtype=torch.bool, device=dev)
        for b, ob in enumerate(obs):
            self.valid_frame[b, :ob.frame_count] = True


class _State:
    def __init__(self, R, C, logf, Cm, a, off):
        self.R, self.C, self.logf, self.Cm, self.a, self.off = R, C, logf, Cm, a, off

    def step(self, d: torch.Tensor, T: int) -> "_State":
        B = d.shape[0]
        fr = d[:, :NF * T].view(B, T, NF)
        g = d[:, NF * T:]
        dR = axis_angle_to_rotation_matrix(fr[..., :3].reshape(-1, 3)).view(B, T, 3, 3)
        return _State(dR @ self.R, self.C + fr[..., 3:6], self.logf + fr[..., 6], self.Cm + g[:, :3],
                      self.a + g[:, 3], self.off + g[:, 4])


def _terms(st: _State, bt: _Batch, o: TrackingOptions, jac: bool):
    """Residual blocks: list of (camera [Q], residual [Q, k], J [Q, k, m], index [Q, m], weight sigma)."""
    out = []
    f = torch.exp(st.logf)
    # 2D-3D
    if len(bt.c3):
        b, t = bt.c3, bt.t3
        R = st.R[b, t]
        w = (R @ (bt.X3 - st.C[b, t])[..., None])[..., 0]
        ft = f[b, t]
        z = w[:, 2].clamp(min=1e-6)
        pred = ft[:, None] * w[:, :2] / z[:, None] + bt.pp[b, t]
        r = (pred - bt.uv3) / o.pixel_sigma_3d
        behind = w[:, 2] <= 1e-6
        r = torch.where(behind[:, None], torch.full_like(r, 1e3), r)
        J = idx = None
        if jac:
            d = _dpi(w, ft)
            Jw = d @ (-_skew(w))
            JC = d @ (-R)
            Jf = (ft[:, None] * w[:, :2] / z[:, None])[..., None]
            # a point behind the camera has the constant residual above: no slope (its 1/z Jacobian
            # at the clamped depth would be ~1e6 x f, freezing its frame and the focal of the take)
            J = torch.cat([Jw, JC, Jf], 2) / o.pixel_sigma_3d * (~behind).to(w.dtype)[:, None, None]
            idx = (NF * t)[:, None] + torch.arange(NF, device=t.device)[None]
        out.append((b, r, J, idx))
    # 2D-2D (frame i -> frame j, same camera)
    if len(bt.c2):
        b, i, j = bt.c2, bt.i2, bt.j2
        fi, fj = f[b, i], f[b, j]
        ppi, pp = bt.pp[b, i], bt.pp[b, j]
        ray = torch.cat([(bt.ui2 - ppi) / fi[:, None], torch.ones_like(fi)[:, None]], 1)
        Ri, Rj = st.R[b, i], st.R[b, j]
        v = (Ri.transpose(1, 2) @ ray[..., None])[..., 0]
        w = (Rj @ v[..., None])[..., 0]
        z = w[:, 2].clamp(min=1e-6)
        pred = fj[:, None] * w[:, :2] / z[:, None] + pp
        r = (pred - bt.uj2) / o.pixel_sigma_2d
        J = idx = None
        if jac:
            d = _dpi(w, fj)
            Jwj = d @ (-_skew(w))
            RjRiT = Rj @ Ri.transpose(1, 2)
            Jwi = d @ RjRiT @ _skew(ray)
            dray = torch.zeros_like(ray)
            dray[:, :2] = -(bt.ui2 - ppi) / fi[:, None]
            Jfi = d @ (RjRiT @ dray[..., None])
            Jfj = (fj[:, None] * w[:, :2] / z[:, None])[..., None]
            zero3 = torch.zeros(len(b), 2, 3, dtype=w.dtype, device=w.device)
            J = torch.cat([Jwi, zero3, Jfi, Jwj, zero3, Jfj], 2) / o.pixel_sigma_2d
            ar = torch.arange(NF, device=b.device)[None]
            idx = torch.cat([(NF * i)[:, None] + ar, (NF * j)[:, None] + ar], 1)
        out.append((b, r, J, idx))
    return out


def _prior_terms(st: _State, bt: _Batch, o: TrackingOptions, jac: bool):
    """Quadratic priors: focal curve, centre, weak gauge terms. Same format as _terms."""
    out = []
    B, T = bt.B, bt.T
    dev = st.C.device
    bb, tt = torch.meshgrid(torch.arange(B, device=dev), torch.arange(T, device=dev), indexing="ij")
    vf = bt.valid_frame
    bb, tt = bb[vf], tt[vf]
    ar3 = torch.arange(3, device=dev)
    if o.mode == "priors":
        g = torch.exp(st.a)[bb] * bt.s[bb, tt]
        model = g + st.off[bb]
        r = ((st.logf[bb, tt] - torch.log(model)) / o.focal_sigma_rel)[:, None]
        J = idx = None
        if jac:
            J = torch.stack([torch.ones_like(g), -g / model, -1.0 / model], 1)[:, None, :] / o.focal_sigma_rel
            idx = torch.stack([NF * tt + 6, torch.full_like(tt, NF * T + 3), torch.full_like(tt, NF * T + 4)], 1)
        out.append((bb, r, J, idx))
        rc = (st.C[bb, tt] - st.Cm[bb]) / o.centre_sigma_m
        J = idx = None
        if jac:
            eye = torch.eye(3, dtype=rc.dtype, device=dev).expand(len(bb), 3, 3)
            J = torch.cat([eye, -eye], 2) / o.centre_sigma_m
            idx = torch.cat([(NF * tt + 3)[:, None] + ar3, (NF * T + ar3).expand(len(bb), 3)], 1)
        out.append((bb, rc, J, idx))
        bcam = torch.arange(B, device=dev)
        rm = (st.Cm - bt.mount) / o.mount_sigma_m
        J = idx = None
        if jac:
            J = torch.eye(3, dtype=rm.dtype, device=dev).expand(B, 3, 3) / o.mount_sigma_m
            idx = (NF * T + ar3).expand(B, 3)
        out.append((bcam, rm, J, idx))
        # weak priors on the encoder calibration (1 % gain, 1 % offset) keep the system regular
        scale = bt.s.mean(1)
        r = torch.stack([st.a / 0.01, st.off / (0.01 * scale)], 1)
        J = idx = None
        if jac:
            J = torch.zeros(B, 2, 2, dtype=r.dtype, device=dev)
            J[:, 0, 0] = 1 / 0.01
            J[:, 1, 1] = 1 / (0.01 * scale)
            idx = torch.tensor([NF * T + 3, NF * T + 4], device=dev).expand(B, 2)
        out.append((bcam, r, J, idx))
    else:
        # without priors: only a weak regulariser (1 m around the mount) so every frame stays solvable
        rc = (st.C[bb, tt] - bt.mount[bb]) / 1.0
        J = idx = None
        if jac:
            J = torch.eye(3, dtype=rc.dtype, device=dev).expand(len(bb), 3, 3).clone()
            idx = (NF * tt + 3)[:, None] + ar3
        out.append((bb, rc, J, idx))
    return out


def _cost(st: _State, bt: _Batch, o: TrackingOptions) -> torch.Tensor:
    """Per-camera cost [B]: Cauchy on data terms, squares on priors."""
    c = torch.zeros(bt.B, dtype=torch.float64, device=st.C.device)
    for b, r, _, _ in _terms(st, bt, o, False):
        c.index_add_(0, b, torch.log1p((r ** 2).sum(1)))
    for b, r, _, _ in _prior_terms(st, bt, o, False):
        c.index_add_(0, b, (r ** 2).sum(1))
    return c


def _normal_equations(st: _State, bt: _Batch, o: TrackingOptions):
    B, n = bt.B, bt.n
    dev = st.C.device
    H = torch.zeros(B * n * n, dtype=torch.float64, device=dev)
    g = torch.zeros(B * n, dtype=torch.float64, device=dev)
    for robust, terms in ((True, _terms(st, bt, o, True)), (False, _prior_terms(st, bt, o, True))):
        for b, r, J, idx in terms:
            if len(b) == 0:
                continue
            w = 1.0 / (1.0 + (r ** 2).sum(1)) if robust else torch.ones(len(b), dtype=r.dtype, device=dev)
            Jw = J * w[:, None, None]
            JtJ = Jw.transpose(1, 2) @ J                                        # [Q, m, m]
            Jtr = (Jw.transpose(1, 2) @ r[..., None])[..., 0]                   # [Q, m]
            m = idx.shape[1]
            flat = (b[:, None, None] * n * n + idx[:, :, None] * n + idx[:, None, :]).reshape(-1)
            H.index_add_(0, flat, JtJ.reshape(-1))
            g.index_add_(0, (b[:, None] * n + idx).reshape(-1), Jtr.reshape(-1))
    H = H.view(B, n, n)
    g = g.view(B, n)
    # frames a camera does not have, and the unused globals without priors, get unit diagonals
    diag = H.diagonal(dim1=1, dim2=2)
    diag += (diag == 0).to(H.dtype)
    return H, g


def refine_tracking(obs: list[TrackingObservations], init: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                    prior_px: list[np.ndarray], principal: np.ndarray, mounts: list[np.ndarray],
                    options: TrackingOptions = TrackingOptions()) -> list[TrackingSolution]:
    """Jointly refine every tracking camera's sequence (batched over cameras).

    ``init[b]`` = (R [T, 3, 3], C [T, 3], f [T]) from :func:`initialise_tracking`; ``prior_px[b]`` [T]
    the smoothed encoder focal in px; ``principal`` [B, 2], or per camera [T, 2] (a principal point
    per frame), held fixed; ``mounts[b]`` [3] the nominal centre (prior of the mean centre).
    """
    t0 = time.perf_counter()
    dev = torch.device(options.device)
    f64 = dict(dtype=torch.float64, device=dev)
    T_max = max(ob.frame_count for ob in obs)
    pp = np.stack([_principal_per_frame(principal[b], T_max) for b in range(len(obs))])       # [B, T, 2]
    bt = _Batch(obs, pp, prior_px, mounts, options, dev)
    B, T = bt.B, bt.T

    def pad(a, shape_tail, fill):
        out = np.broadcast_to(np.asarray(fill, np.float64), (B, T) + shape_tail).copy()
        for b, x in enumerate(a):
            out[b, :len(x)] = x
        return torch.as_tensor(out, **f64)

    R = pad([i[0] for i in init], (3, 3), np.eye(3))
    C = pad([i[1] for i in init], (3,), 0.0)
    logf = torch.log(pad([i[2] for i in init], (), 1.0))
    Cm = torch.stack([C[b, :obs[b].frame_count].mean(0) for b in range(B)])
    # start gain/offset at the least-squares fit of the initial focal to the prior curve
    a = torch.zeros(B, **f64)
    off = torch.zeros(B, **f64)
    st = _State(R, C, logf, Cm, a, off)
    lam = torch.full((B,), 1e-3, **f64)
    cost = _cost(st, bt, options)
    it = 0
    for it in range(options.iterations):
        H, g = _normal_equations(st, bt, options)
        D = torch.diag_embed(H.diagonal(dim1=1, dim2=2))
        d = torch.linalg.solve(H + lam[:, None, None] * D, -g[..., None])[..., 0]
        new = st.step(d, T)
        new_cost = _cost(new, bt, options)
        better = new_cost < cost
        sel = better.to(torch.float64)
        st = _State(*[torch.where(_bc(better, x), y, x) for x, y in
                      ((st.R, new.R), (st.C, new.C), (st.logf, new.logf), (st.Cm, new.Cm), (st.a, new.a),
                       (st.off, new.off))])
        rel = (cost - new_cost) / cost.clamp(min=1e-12)
        cost = torch.where(better, new_cost, cost)
        lam = torch.where(better, (lam / 3).clamp(min=1e-9), lam * 5)
        if bool(((rel.abs() < 1e-7) & better | (lam > 1e7)).all()) and it > 2:
            break
        del sel
    sols = []
    f = torch.exp(st.logf)
    spread = _spread(st, bt, options)
    for b in range(B):
        Tb = obs[b].frame_count
        K = np.zeros((Tb, 3, 3))
        K[:, 0, 0] = f[b, :Tb].cpu().numpy()
        K[:, 1, 1] = K[:, 0, 0]
        K[:, 0, 2], K[:, 1, 2] = pp[b, :Tb, 0], pp[b, :Tb, 1]
        K[:, 2, 2] = 1
        Rb = st.R[b, :Tb].cpu().numpy()
        Cb = st.C[b, :Tb].cpu().numpy()
        W = np.tile(np.eye(4), (Tb, 1, 1))
        W[:, :3, :3] = Rb
        W[:, :3, 3] = -np.einsum("tij,tj->ti", Rb, Cb)
        res = _per_frame_residuals(st, bt, options, b, Tb)
        sols.append(TrackingSolution(K, W, float(torch.exp(st.a[b])), float(st.off[b]),
                                     st.Cm[b].cpu().numpy(),
                                     {"cost": float(cost[b]), "iterations": it + 1, **res,
                                      **{k: float(v[b]) for k, v in spread.items()}}))
    for s in sols:
        s.stats["seconds"] = time.perf_counter() - t0
    return sols


def _spread(st: _State, bt: _Batch, o: TrackingOptions) -> dict[str, torch.Tensor]:
    """How well each camera's solution is determined, from the Gauss-Newton covariance ``H^-1`` at
    the solution (the residuals are in units of their sigma, so ``H^-1`` is a covariance; the
    Cauchy weights of the last step count the outliers out). Per camera [B]:

    - ``focal_sigma_pct``: standard deviation of the take's mean focal, % (along the zoom/dolly
      valley the data barely tell a zoom from a dolly, so this is what the mount and encoder priors
      leave open where the 2D-3D matches are few);
    - ``rotation_sigma_deg``: the largest standard deviation of a frame's orientation (degrees);
    - ``centre_sigma_m``: the largest standard deviation of a frame's centre (metres).

    A lower bound on the true spread: where the robust term's inliers would change, no quadratic
    model sees it.
    """
    H, _ = _normal_equations(st, bt, o)
    cov = torch.linalg.inv(H)                                                  # [B, n, n]
    B, T = bt.B, bt.T
    blocks = cov[:, :NF * T, :NF * T].reshape(B, T, NF, T, NF)
    per_frame = torch.diagonal(blocks, dim1=1, dim2=3).permute(0, 3, 1, 2)     # [B, T, NF, NF]
    valid = bt.valid_frame
    n_valid = valid.sum(1).to(cov.dtype)
    # mean log focal over a camera's frames: v = 1/T_b on its frames' log-focal entries
    v = torch.zeros(B, bt.n, dtype=cov.dtype, device=cov.device)
    v[:, 6:NF * T:NF] = valid.to(cov.dtype) / n_valid[:, None]
    var_f = torch.einsum("bi,bij,bj->b", v, cov, v)
    rot = torch.linalg.eigvalsh(per_frame[..., :3, :3]).amax(-1).clamp(min=0)  # [B, T]
    cen = torch.linalg.eigvalsh(per_frame[..., 3:6, 3:6]).amax(-1).clamp(min=0)
    zero = torch.zeros_like(rot)
    return {"focal_sigma_pct": 100 * var_f.clamp(min=0).sqrt(),
            "rotation_sigma_deg": torch.rad2deg(torch.where(valid, rot, zero).amax(1).sqrt()),
            "centre_sigma_m": torch.where(valid, cen, zero).amax(1).sqrt()}


def tracking_support(sol: TrackingSolution, options: TrackingOptions = TrackingOptions()) -> str | None:
    """Why a solved tracking camera cannot be returned as calibrated, or None: fewer 2D-3D inliers
    over the take than ``options.min_inliers_3d`` (the priors alone would place it), or a frame's
    orientation determined to worse than ``options.max_rotation_sigma_deg`` (``stats``'
    ``rotation_sigma_deg``, from the solve's covariance)."""
    inliers = int(sol.stats.get("reprojection_3d_px_inliers", 0))
    if inliers < options.min_inliers_3d:
        return (f"{inliers} 2D-3D inliers against the static reference over the take (needs at least "
                f"{options.min_inliers_3d})")
    sigma = float(sol.stats.get("rotation_sigma_deg", float("inf")))
    if options.max_rotation_sigma_deg is not None and not sigma <= options.max_rotation_sigma_deg:
        return (f"its orientation is determined to {sigma:.3g}° only (bound {options.max_rotation_sigma_deg}°, "
                f"from {inliers} 2D-3D inliers)")
    return None


def _bc(mask: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return mask.view(-1, *([1] * (x.dim() - 1)))


def _per_frame_residuals(st, bt, o, b, Tb) -> dict:
    out = {}
    terms = _terms(st, bt, o, False)
    names = ["reprojection_3d_px", "reprojection_2d_px"] if len(bt.c3) else ["reprojection_2d_px"]
    sig = [o.pixel_sigma_3d, o.pixel_sigma_2d]
    for name, s, (cam, r, _, _) in zip(names, sig, terms):
        sel = cam == b
        e = (r[sel].norm(dim=1) * s).cpu().numpy()
        inl = e[e < 3 * s]
        out[name + "_median"] = float(np.median(inl)) if len(inl) else float("nan")   # over the inliers
        out[name + "_inliers"] = int(len(inl))
        out[name + "_matches"] = int(len(e))
    return out


# --------------------------------------------------------------------------- the whole stage

#: a zoom lens: ``lens(focal_mm [T]) -> (distCoeffs [T, 5 or 8] OpenCV, principal [T, 2] px or None)``
ZoomLens = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]]


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


def undistort_observations(obs: TrackingObservations, undistort: Undistorter) -> TrackingObservations:
    """Matched observations of raw frames (already matched, e.g. a synthetic test's) moved into each
    frame's pinhole by ``undistort`` (:func:`frame_undistorter`); a match with a point beyond the
    lens's fold is dropped. :func:`observe_tracking_camera` does the same to keypoints before
    matching."""
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


def lens_corner_shift_px(focal_px: np.ndarray, principal: np.ndarray, coeffs: np.ndarray, width: int,
                         height: int) -> np.ndarray:
    """[T]: how far each frame's lens moves the image corners (px, the largest of the four): the
    size of what undistortion corrects."""
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]])
    und = frame_undistorter(focal_px, principal, coeffs)
    return np.array([np.linalg.norm(und(t, corners)[0] - corners, axis=1).max() for t in range(len(focal_px))])


@dataclass
class TrackingProblem:
    """Observations and initial values of every tracking camera (see :func:`prepare_tracking`).
    ``principal``: [B, 2] or per camera [T, 2]; ``distortion``: per camera the lens [T, 5|8] its
    observations were undistorted with (None: none)."""

    ids: list[str]
    obs: list[TrackingObservations]
    inits: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    priors_px: list[np.ndarray]
    principal: np.ndarray | list[np.ndarray]
    mounts: list[np.ndarray]
    info: dict
    distortion: list[np.ndarray | None] | None = None
    #: the static model the observations were matched to (for the guided matching; None: none)
    reference: StaticReference | None = None


def prepare_tracking(frames: Mapping[str, Sequence[np.ndarray]],
                     encoder: Mapping[str, tuple[np.ndarray, np.ndarray]],
                     focal_px_per_mm: Mapping[str, float], mounts: Mapping[str, np.ndarray],
                     reference: StaticReference, options: TrackingOptions = TrackingOptions(),
                     lenses: Mapping[str, ZoomLens | None] | None = None) -> TrackingProblem:
    """Features, matches, the encoder prior and the initial values of every tracking camera.

    ``frames``: id -> T linear RGB images [H, W, 3] (take indices 0..T-1); ``encoder``: id ->
    (take indices [S], focal mm [S]) lens-encoder readings; ``focal_px_per_mm``: id -> sensor
    pixels per mm; ``mounts``: id -> nominal centre [3] (metres); ``reference``: the static model;
    ``lenses``: id -> its zoom lens (:func:`zoom_lens`; absent or None: a pinhole with its principal
    point at the image centre). With ``options.zoom_distortion`` a camera's frame t is undistorted
    with its lens at the smoothed encoder focal of frame t (the prior, known before the solve): a
    focal ε off moves an undistorted point by ~3 ε k1 r² of its radius (0.12 px at the corners for
    a 2.4 % corner distortion and ε = 1.2 %), which left the solve's focal and rotation unchanged
    to 0.01 % and 0.01° (docs/calibration.md, "Lens distortion").
    """
    ids = sorted(frames)
    obs, inits, priors, pps, dists, info = [], [], [], [], [], {}
    for cid in ids:
        seq = frames[cid]
        idx, mm = encoder[cid]
        prior = smooth_encoder_focal(idx, mm, len(seq), options.smooth_lambda) * focal_px_per_mm[cid]
        h, w = seq[0].shape[:2]
        pp = np.tile([(w - 1) / 2.0, (h - 1) / 2.0], (len(seq), 1))
        lens = (lenses or {}).get(cid) if options.zoom_distortion else None
        coeffs, undistort, extra = None, None, {}
        if lens is not None:
            coeffs, lens_pp = lens(prior / focal_px_per_mm[cid])
            if lens_pp is not None:
                pp = np.asarray(lens_pp, np.float64).reshape(len(seq), 2)
            undistort = frame_undistorter(prior, pp, coeffs)
            shift = lens_corner_shift_px(prior, pp, coeffs, w, h)
            extra = {"zoom_lens": 1.0, "lens_corner_shift_px_mean": float(shift.mean()),
                     "lens_corner_shift_px_max": float(shift.max())}
        ob = observe_tracking_camera(seq, reference, options, undistort)
        R, C, f, st = initialise_tracking(ob, prior, np.asarray(mounts[cid], np.float64), pp, options)
        obs.append(ob)
        inits.append((R, C, f))
        priors.append(prior)
        pps.append(pp)
        dists.append(coeffs)
        info[cid] = {**st, "observe_s": ob.seconds, **extra}
    return TrackingProblem(ids, obs, inits, priors, pps, [np.asarray(mounts[c], np.float64) for c in ids], info,
                           dists, reference)


def dolly_zoom_start(init: tuple[np.ndarray, np.ndarray, np.ndarray], obs: TrackingObservations,
                     scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An initial sequence (R [T, 3, 3], C [T, 3], f [T]) with every focal scaled by ``scale`` and the
    centre moved back along the mean view axis by ``(scale - 1)`` x the median distance of the
    2D-3D points, so the scene keeps its size in the image (a zoom-in looks like a dolly-in)."""
    R, C, f = init
    axis = R[:, 2, :].mean(0)
    axis /= np.linalg.norm(axis)
    dist = float(np.median(np.linalg.norm(obs.m3_X - C.mean(0), axis=1))) if len(obs.m3_X) else 0.0
    return R, C - (scale - 1.0) * dist * axis, f * scale


def solve_tracking(problem: TrackingProblem, options: TrackingOptions = TrackingOptions()
                   ) -> dict[str, TrackingSolution]:
    """Refine a prepared problem (``options.mode`` picks priors / free / independent): once from
    each of ``options.focal_scale_starts`` along the zoom/dolly valley, keeping each camera's
    lowest-cost solution (``stats["focal_scale_start"]`` says which)."""
    if not problem.ids:
        return {}
    best: list[TrackingSolution | None] = [None] * len(problem.ids)
    for scale in options.focal_scale_starts:
        inits = [dolly_zoom_start(i, ob, scale) for i, ob in zip(problem.inits, problem.obs)]
        sols = refine_tracking(problem.obs, inits, problem.priors_px, problem.principal, problem.mounts, options)
        for k, s in enumerate(sols):
            s.stats["focal_scale_start"] = scale
            if best[k] is None or s.stats["cost"] < best[k].stats["cost"]:
                best[k] = s
    if options.guided_radius_px is not None and problem.reference is not None:
        best = _guided_round(problem, best, options)
    out = {}
    for k, (cid, s) in enumerate(zip(problem.ids, best)):
        s.stats.update(problem.info[cid])
        if problem.distortion is not None and problem.distortion[k] is not None:
            s.distortion = np.asarray(problem.distortion[k], np.float64).copy()
        out[cid] = s
    return out


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


def _guided_round(problem: TrackingProblem, best: list[TrackingSolution], options: TrackingOptions
                  ) -> list[TrackingSolution]:
    """Each camera's solution refined once more on its guided 2D-3D matches, kept where they are at
    least as many as the first solve's inliers (a solve too far off finds fewer)."""
    guided = [guided_observations(ob, problem.reference, s.K, s.world_to_camera, options)
              for ob, s in zip(problem.obs, best)]
    inits = [(s.world_to_camera[:, :3, :3], camera_centre(s.world_to_camera), s.K[:, 0, 0]) for s in best]
    sols = refine_tracking(guided, inits, problem.priors_px, problem.principal, problem.mounts, options)
    out = []
    for s0, s1, g in zip(best, sols, guided):
        if len(g.m3_frame) >= s0.stats["reprojection_3d_px_inliers"]:
            s1.stats["focal_scale_start"] = s0.stats.get("focal_scale_start", 1.0)
            s1.stats["guided_matches_3d"] = len(g.m3_frame)
            s1.stats["first_solve_inliers_3d"] = s0.stats["reprojection_3d_px_inliers"]
            out.append(s1)
        else:
            s0.stats["guided_matches_3d"] = len(g.m3_frame)
            out.append(s0)
    return out


def calibrate_tracking_cameras(frames: Mapping[str, Sequence[np.ndarray]],
                               encoder: Mapping[str, tuple[np.ndarray, np.ndarray]],
                               focal_px_per_mm: Mapping[str, float], mounts: Mapping[str, np.ndarray],
                               reference: StaticReference, options: TrackingOptions = TrackingOptions(),
                               lenses: Mapping[str, ZoomLens | None] | None = None
                               ) -> dict[str, TrackingSolution]:
    """Register and refine every tracking camera at every frame: :func:`prepare_tracking` then
    :func:`solve_tracking`. Returns id -> :class:`TrackingSolution`; {} for no tracking camera.
    ``lenses``: id -> zoom lens (:func:`zoom_lens`), see :func:`prepare_tracking`."""
    if not frames:
        return {}
    return solve_tracking(prepare_tracking(frames, encoder, focal_px_per_mm, mounts, reference, options, lenses),
                          options)
