"""Small geometry helpers shared by the calibration stages (numpy, float64). Its
:func:`look_at_rotation` is also the one the synthetic capture and the splat renderer's cameras use.

Conventions (everywhere in ``volcap_core.calibration``):

- world: the stage frame, metres, z up, origin at the stage centre on the floor;
- camera: OpenCV axes (x right, y down, z forward); ``x_cam = R @ x_world + t`` and the
  world-to-camera matrix is ``[[R, t], [0, 1]]``; the camera centre is ``C = -R^T t``;
- pixels: OpenCV, the centre of the top-left pixel is (0, 0). COLMAP puts it at (0.5, 0.5):
  :data:`hardware.lens_models.COLMAP_PIXEL_OFFSET` is added when going to COLMAP and subtracted
  when coming back.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


#: ``|cos|`` of the angle between the optical axis and ``up`` above which :func:`look_at_rotation`
#: takes image "up" from a fallback axis: within ~2.6 degrees of ``up`` the image's horizontal axis
#: would swing with the slightest change of aim (and is undefined when exactly parallel).
NEAR_PARALLEL_UP_COS = 0.999


def look_at_rotation(position, target, roll_deg: float = 0.0, *, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera rotation ``R`` (3, 3), OpenCV camera axes (x right, y down, z forward), of a
    camera at ``position`` (3,) whose optical axis passes through ``target`` (3,), world units.

    The rows of ``R`` are the camera axes in world coordinates: ``x_cam = R @ (x_world - position)``,
    i.e. ``t = -R @ position``; ``R.T`` is the camera-to-world rotation. The library's one look-at
    (rig mounts, synthetic cameras, splat render cameras).

    ``up`` (3,), any length: the world direction that appears upward in the image (image y points
    the other way); default world +z, the stage's up. When the optical axis is within ~2.6 degrees
    of ``up`` or ``-up`` (``|cos| > NEAR_PARALLEL_UP_COS``: a rig camera looking straight down),
    the world axis most perpendicular to ``up`` is used instead, the first on ties: world +x for
    the default, so such a camera has world +x at the top of its image. ``roll_deg`` then turns the
    image clockwise as seen by the camera (the x/y axes rotate about the optical axis; the rig
    ``Mount``'s ``roll_deg``).

    Raises ValueError naming the vectors when ``target`` is ``position`` (no optical axis), ``up``
    is zero, or any of them is not finite.
    """
    c = np.asarray(position, np.float64)
    f = np.asarray(target, np.float64) - c
    n = np.linalg.norm(f)
    if not (1e-9 < n < math.inf):  # also NaN
        raise ValueError(f"camera at {c.tolist()} looking at {np.asarray(target).tolist()}: "
                         "no optical axis (the target is the camera position, or not finite)")
    f = f / n
    u = np.asarray(up, np.float64)
    nu = np.linalg.norm(u)
    if not (0 < nu < math.inf):
        raise ValueError(f"up {u.tolist()} is not a direction")
    u = u / nu
    if abs(f @ u) > NEAR_PARALLEL_UP_COS:
        u = np.eye(3)[int(np.argmin(np.abs(u)))]
    x = np.cross(f, u)
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    if roll_deg:
        a = math.radians(roll_deg)
        x, y = math.cos(a) * x + math.sin(a) * y, -math.sin(a) * x + math.cos(a) * y
    return np.stack([x, y, f])


def pose_matrix(R, t) -> np.ndarray:
    """4x4 world-to-camera from R (3, 3) and t (3,)."""
    m = np.eye(4)
    m[:3, :3] = np.asarray(R, np.float64)
    m[:3, 3] = np.asarray(t, np.float64)
    return m


def camera_centre(world_to_camera) -> np.ndarray:
    """Camera centre (3,) in world coordinates of a 4x4 (or batch [..., 4, 4]) world-to-camera."""
    m = np.asarray(world_to_camera, np.float64)
    R, t = m[..., :3, :3], m[..., :3, 3]
    return -np.einsum("...ji,...j->...i", R, t)


def camera_gaps(world_to_camera: Sequence[np.ndarray]) -> tuple[np.ndarray, float]:
    """The distances between the cameras' centres, [N, N] metres (inf on the diagonal), and the
    rig's camera spacing: the median distance from a camera to its nearest neighbour (0 for one
    camera)."""
    centres = np.stack([camera_centre(np.asarray(W, np.float64)) for W in world_to_camera])
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1) + np.diag(np.full(len(centres), np.inf))
    return gaps, float(np.median(gaps.min(1))) if len(centres) > 1 else 0.0


def depths_in_view(points: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray,
                    size: tuple[int, int]) -> np.ndarray:
    """Depths of the points in front of a camera that project into its ``size`` = (W, H) image."""
    X = np.asarray(points, np.float64) @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = X[:, 2]
    front = z > 1e-9
    uv = X[front, :2] / z[front, None] @ K[:2, :2].T + K[:2, 2]
    w, h = size
    inside = (uv[:, 0] > -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < h - 0.5)
    return z[front][inside]


def intrinsic_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def project(K, world_to_camera, points) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> OpenCV pixels (N, 2) and depths (N,) along the optical axis."""
    m = np.asarray(world_to_camera, np.float64)
    p = np.asarray(points, np.float64) @ m[:3, :3].T + m[:3, 3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p[:, :2] / z[:, None]) @ np.asarray(K, np.float64)[:2, :2].T + np.asarray(K)[:2, 2]
    return uv, z


def rotation_angle_deg(Ra, Rb) -> np.ndarray:
    """Angle (degrees) of Ra Rb^T; batched over leading axes."""
    Ra, Rb = np.asarray(Ra, np.float64), np.asarray(Rb, np.float64)
    c = (np.einsum("...ij,...ij->...", Ra, Rb) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def so3_exp(w) -> np.ndarray:
    """Rodrigues: axis-angle (3,) -> rotation (3, 3)."""
    w = np.asarray(w, np.float64)
    th = np.linalg.norm(w)
    Kx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + Kx
    Kx /= th
    return np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * Kx @ Kx


class Similarity:
    """x_new = s * R @ x + t (world-from-model). ``apply`` maps points, ``apply_pose`` maps a
    world-to-camera matrix of the old frame to the new frame (the camera stays the same camera)."""

    def __init__(self, s: float = 1.0, R=None, t=None):
        self.s = float(s)
        self.R = np.eye(3) if R is None else np.asarray(R, np.float64)
        self.t = np.zeros(3) if t is None else np.asarray(t, np.float64)

    def apply(self, x) -> np.ndarray:
        return self.s * np.asarray(x, np.float64) @ self.R.T + self.t

    def apply_pose(self, world_to_camera) -> np.ndarray:
        m = np.asarray(world_to_camera, np.float64)
        Rc, tc = m[:3, :3], m[:3, 3]
        # x_cam = Rc x_old + tc, x_old = R^T (x_new - t) / s  ->  scale the camera frame by s
        Rn = Rc @ self.R.T
        tn = self.s * tc - Rn @ self.t
        return pose_matrix(Rn, tn)

    def compose(self, other: "Similarity") -> "Similarity":
        """self ∘ other (apply other first)."""
        return Similarity(self.s * other.s, self.R @ other.R, self.s * self.R @ other.t + self.t)

    def __repr__(self) -> str:
        return f"Similarity(s={self.s:.6g}, t={np.round(self.t, 4).tolist()})"


def umeyama(src, dst, weights=None, with_scale: bool = True) -> Similarity:
    """Least-squares similarity with ``dst ≈ s R src + t`` (Umeyama 1991). src, dst: (N, 3)."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    xs, xd = src - ms, dst - md
    cov = (xd * w[:, None]).T @ xs
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (w * (xs ** 2).sum(1)).sum()
    s = float(np.trace(np.diag(S) @ D) / var) if with_scale else 1.0
    t = md - s * R @ ms
    return Similarity(s, R, t)


def robust_umeyama(src, dst, threshold: float, iterations: int = 200, seed: int = 0,
                   min_inliers: int = 3) -> tuple[Similarity, np.ndarray]:
    """RANSAC over minimal 3-point sets, then a refit on the inliers (|residual| < threshold,
    in ``dst`` units). Returns the similarity and the boolean inlier mask."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    n = len(src)
    if n < 3:
        raise ValueError(f"a similarity needs >= 3 correspondences, got {n}")
    rng = np.random.default_rng(seed)
    best = None
    best_count = -1
    best_err = np.inf
    trials = [np.arange(3)] if n == 3 else [rng.choice(n, 3, replace=False) for _ in range(iterations)]
    for idx in trials:
        try:
            T = umeyama(src[idx], dst[idx])
        except np.linalg.LinAlgError:
            continue
        if not np.isfinite(T.s) or T.s <= 0:
            continue
        r = np.linalg.norm(T.apply(src) - dst, axis=1)
        inl = r < threshold
        cnt = int(inl.sum())
        err = float(np.minimum(r, threshold).sum())
        if cnt > best_count or (cnt == best_count and err < best_err):
            best, best_count, best_err = inl, cnt, err
    if best is None or best_count < min_inliers:
        T = umeyama(src, dst)
        return T, np.ones(n, bool)
    T = umeyama(src[best], dst[best])
    for _ in range(3):
        inl = np.linalg.norm(T.apply(src) - dst, axis=1) < threshold
        if inl.sum() < 3:
            break
        T = umeyama(src[inl], dst[inl])
    return T, inl


def triangulate_points(P: np.ndarray, obs_point: np.ndarray, obs_camera: np.ndarray, obs_xy: np.ndarray,
                       n_points: int) -> np.ndarray:
    """Linear (DLT) triangulation. ``P`` [C, 3, 4] projection matrices K [R|t]; observations
    ``obs_point`` [M], ``obs_camera`` [M], ``obs_xy`` [M, 2] OpenCV px. Returns [n_points, 3]
    (NaN for points with fewer than two observations)."""
    P = np.asarray(P, np.float64)
    rows = np.concatenate([obs_xy[:, 0:1] * P[obs_camera, 2] - P[obs_camera, 0],
                           obs_xy[:, 1:2] * P[obs_camera, 2] - P[obs_camera, 1]], 0)
    pid = np.concatenate([obs_point, obs_point])
    out = np.full((n_points, 3), np.nan)
    A = np.zeros((n_points, 4, 4))
    rows = rows / np.linalg.norm(rows, axis=1, keepdims=True)
    np.add.at(A, pid, rows[:, :, None] * rows[:, None, :])
    cnt = np.bincount(obs_point, minlength=n_points)
    ok = cnt >= 2
    if ok.any():
        _, vec = np.linalg.eigh(A[ok])
        h = vec[:, :, 0]
        out[ok] = h[:, :3] / h[:, 3:4]
    return out
