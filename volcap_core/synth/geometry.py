"""Pinhole cameras and exact ray/primitive intersections, vectorised over pixels (numpy, float32).

Conventions (the same as ``ground_truth/cameras.json``):

- world: metres, z up, origin at the stage centre on the floor;
- camera: OpenCV, x right, y down, z forward; ``x_cam = R @ x_world + t``;
- pixels: OpenCV, the centre of the top-left pixel is (0, 0), so an image of width W spans
  [-0.5, W - 0.5] and its middle is (W - 1) / 2 (COLMAP puts pixel centres at +0.5: add 0.5).

Every camera is a central camera (all rays share its centre), a pinhole unless it has a lens
``distortion`` (:class:`~volcap_core.calibration.distortion.Distortion`): then a pixel's ray is
found by undistorting its normalized coordinates, so the footage is rendered exactly through the
distorted lens (no resampling of a pinhole render; Newton's inverse is accurate to ~1e-13). The
intersection routines take one origin ``o`` (3,) and many unit directions ``d`` (..., 3).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from volcap_core.calibration.distortion import Distortion
from volcap_core.calibration.geometry import look_at_rotation

EPS = 1e-6


@dataclass(frozen=True)
class PinholeCamera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray      # (3, 3) world -> camera
    t: np.ndarray      # (3,)
    distortion: Distortion = Distortion.none()

    @staticmethod
    def looking_at(width, height, fx, fy, cx, cy, position, look_at, roll_deg=0.0,
                   distortion: Distortion = Distortion.none()) -> "PinholeCamera":
        R = look_at_rotation(position, look_at, roll_deg)
        return PinholeCamera(width, height, float(fx), float(fy), float(cx), float(cy), R,
                             -R @ np.asarray(position, np.float64), distortion)

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def world_to_camera(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> pixel coordinates (N, 2) and depths (N,) along the optical axis."""
        p = np.asarray(points, np.float64) @ self.R.T + self.t
        z = p[:, 2]
        if not self.distortion.is_none:
            xy = self.distortion.distort(p[:, :2] / z[:, None])
            return xy * [self.fx, self.fy] + [self.cx, self.cy], z
        uv = np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy], axis=1)
        return uv, z

    def ray_directions(self, ss: int = 1) -> np.ndarray:
        """Unit world directions (H*ss, W*ss, 3) through an ss x ss grid of samples in each pixel."""
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        u = (np.arange(self.width)[:, None] + offs[None, :]).reshape(-1)
        v = (np.arange(self.height)[:, None] + offs[None, :]).reshape(-1)
        d = np.empty((v.size, u.size, 3), np.float32)
        if self.distortion.is_none:
            xc = ((u - self.cx) / self.fx).astype(np.float32)
            yc = ((v - self.cy) / self.fy).astype(np.float32)
            d[..., 0] = xc[None, :]
            d[..., 1] = yc[:, None]
        else:
            xd = np.broadcast_to(((u - self.cx) / self.fx)[None, :], (v.size, u.size))
            yd = np.broadcast_to(((v - self.cy) / self.fy)[:, None], (v.size, u.size))
            xy = self.distortion.undistort(np.stack([xd, yd], axis=-1).reshape(-1, 2))
            d[..., :2] = xy.reshape(v.size, u.size, 2)
        d[..., 2] = 1.0
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return d @ self.R.astype(np.float32)   # camera -> world: R^T d, as row vectors d @ R

    def sphere_rect(self, centre, radius, ss: int = 1) -> tuple[int, int, int, int] | None:
        """Conservative sample-grid rectangle (y0, y1, x0, x1) covering a sphere, None when it is
        behind the camera or outside the image. The whole grid when the sphere reaches the camera."""
        Hs, Ws = self.height * ss, self.width * ss
        c = self.R @ np.asarray(centre, np.float64) + self.t
        r = float(radius)
        if c[2] + r <= EPS:
            return None
        if c[2] - r <= 0.05:
            return (0, Hs, 0, Ws)
        corners = c[None, :] + r * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1)
                                             for sz in (-1, 1)], np.float64)
        if not self.distortion.is_none:
            u, v = self._distorted_rect(corners[:, 0] / corners[:, 2], corners[:, 1] / corners[:, 2])
            if u is None:
                return None
        else:
            u = self.fx * corners[:, 0] / corners[:, 2] + self.cx
            v = self.fy * corners[:, 1] / corners[:, 2] + self.cy
        # sample s of pixel j sits at j + (s + 0.5)/ss - 0.5  ->  grid index = (u + 0.5) * ss - 0.5
        x0 = max(0, int(math.floor((u.min() + 0.5) * ss - 0.5)))
        x1 = min(Ws, int(math.ceil((u.max() + 0.5) * ss - 0.5)) + 1)
        y0 = max(0, int(math.floor((v.min() + 0.5) * ss - 0.5)))
        y1 = min(Hs, int(math.ceil((v.max() + 0.5) * ss - 0.5)) + 1)
        if x0 >= x1 or y0 >= y1:
            return None
        return (y0, y1, x0, x1)

    @functools.cached_property
    def _undistorted_extent(self) -> tuple[float, float, float, float]:
        """Normalized (undistorted) bounding box (x0, x1, y0, y1) of every ray of the image."""
        n = 64
        u = np.linspace(-0.5, self.width - 0.5, n)
        v = np.linspace(-0.5, self.height - 0.5, n)
        edge = np.concatenate([np.stack([u, np.full(n, v[0])], 1), np.stack([u, np.full(n, v[-1])], 1),
                               np.stack([np.full(n, u[0]), v], 1), np.stack([np.full(n, u[-1]), v], 1)])
        xy = self.distortion.undistort((edge - [self.cx, self.cy]) / [self.fx, self.fy])
        return float(xy[:, 0].min()), float(xy[:, 0].max()), float(xy[:, 1].min()), float(xy[:, 1].max())

    def _distorted_rect(self, x, y):
        """Pixel bounds (as two arrays of u and v samples) of the distorted image of the undistorted
        normalized box spanned by ``x``, ``y``: the box is clipped to the image's rays (beyond them
        the distortion may fold back) and its boundary sampled, distorted, and padded by 1 px."""
        ex0, ex1, ey0, ey1 = self._undistorted_extent
        x0, x1 = max(float(x.min()), ex0), min(float(x.max()), ex1)
        y0, y1 = max(float(y.min()), ey0), min(float(y.max()), ey1)
        if x0 > x1 or y0 > y1:
            return None, None
        n = 33
        xs, ys = np.linspace(x0, x1, n), np.linspace(y0, y1, n)
        edge = np.concatenate([np.stack([xs, np.full(n, y0)], 1), np.stack([xs, np.full(n, y1)], 1),
                               np.stack([np.full(n, x0), ys], 1), np.stack([np.full(n, x1), ys], 1)])
        uv = self.distortion.distort(edge) * [self.fx, self.fy] + [self.cx, self.cy]
        return np.array([uv[:, 0].min() - 1, uv[:, 0].max() + 1]), np.array([uv[:, 1].min() - 1, uv[:, 1].max() + 1])


# --------------------------------------------------------------------------- intersections
# Each returns t (...,) with np.inf for a miss; directions are unit vectors.

def intersect_box_inside(o, d, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Rays from inside an axis-aligned box: distance to the exit face and the face index
    (0: x-min, 1: x-max, 2: y-min, 3: y-max, 4: z-min (floor), 5: z-max (ceiling))."""
    ts = []
    faces = []
    for axis in range(3):
        da = d[..., axis]
        pos = da > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hi = (hi[axis] - o[axis]) / da
            t_lo = (lo[axis] - o[axis]) / da
        t_axis = np.where(pos, t_hi, t_lo)
        t_axis = np.where(np.abs(da) < 1e-12, np.inf, t_axis)
        ts.append(t_axis)
        faces.append(np.where(pos, 2 * axis + 1, 2 * axis))
    ts = np.stack(ts, -1)
    k = np.argmin(ts, axis=-1)
    t = np.take_along_axis(ts, k[..., None], -1)[..., 0]
    face = np.take_along_axis(np.stack(faces, -1), k[..., None], -1)[..., 0]
    return t.astype(np.float32), face.astype(np.int8)


def intersect_cylinder_inside(o, d, radius, z0, z1) -> tuple[np.ndarray, np.ndarray]:
    """Rays from inside a capped vertical cylinder about the z axis: exit distance and the surface
    (0: wall, 1: floor cap at z0, 2: ceiling cap at z1)."""
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = 2 * (o[0] * d[..., 0] + o[1] * d[..., 1])
    c = o[0] ** 2 + o[1] ** 2 - radius ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = (-b + np.sqrt(np.maximum(b * b - 4 * a * c, 0))) / (2 * a)
        t_wall = np.where(a < 1e-12, np.inf, t_wall)
        t_floor = np.where(d[..., 2] < -1e-12, (z0 - o[2]) / d[..., 2], np.inf)
        t_ceil = np.where(d[..., 2] > 1e-12, (z1 - o[2]) / d[..., 2], np.inf)
    ts = np.stack([t_wall, t_floor, t_ceil], -1)
    k = np.argmin(ts, -1)
    return np.take_along_axis(ts, k[..., None], -1)[..., 0].astype(np.float32), k.astype(np.int8)


def intersect_rect(o, d, origin, eu, ev, size_u, size_v):
    """A two-sided rectangle ``origin + a*eu + b*ev``, 0<=a<=size_u, 0<=b<=size_v
    (eu, ev orthonormal). Returns t (inf on a miss) and the plane coordinates (a, b)."""
    n = np.cross(eu, ev)
    denom = d @ n.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((np.asarray(origin) - o) @ n) / denom
    p = np.asarray(o, np.float32) + t[..., None] * d
    rel = p - np.asarray(origin, np.float32)
    a = rel @ np.asarray(eu, np.float32)
    b = rel @ np.asarray(ev, np.float32)
    ok = (t > EPS) & (a >= 0) & (a <= size_u) & (b >= 0) & (b <= size_v) & np.isfinite(t)
    return np.where(ok, t, np.inf).astype(np.float32), a, b


def intersect_ellipsoid(o, d, centre, R, semi):
    """Ellipsoid with semi-axes ``semi`` along the columns of ``R`` (local -> world rotation)."""
    Rt = np.asarray(R, np.float32).T
    s = np.asarray(semi, np.float32)
    ol = (Rt @ (np.asarray(o, np.float32) - np.asarray(centre, np.float32))) / s
    dl = (d @ Rt.T) / s
    a = np.einsum("...i,...i->...", dl, dl)
    b = 2 * (dl @ ol)
    c = float(ol @ ol) - 1.0
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)
    return np.where((disc >= 0) & (t > EPS), t, np.inf).astype(np.float32)


def intersect_capsule(o, d, pa, pb, r):
    """Capsule around segment pa-pb with radius r (unit directions)."""
    pa = np.asarray(pa, np.float32)
    ba = np.asarray(pb, np.float32) - pa
    oa = np.asarray(o, np.float32) - pa
    baba = float(ba @ ba)
    bard = d @ ba
    baoa = float(ba @ oa)
    rdoa = d @ oa
    oaoa = float(oa @ oa)
    a = baba - bard * bard
    b = baba * rdoa - baoa * bard
    c = baba * oaoa - baoa * baoa - r * r * baba
    h = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t_body = (-b - np.sqrt(h)) / a
    y = baoa + t_body * bard
    body_ok = (h >= 0) & (y > 0) & (y < baba) & (t_body > EPS)
    # caps: spheres at pa (y <= 0) or pb
    oc_a = oa
    oc_b = np.asarray(o, np.float32) - np.asarray(pb, np.float32)
    t_caps = []
    for oc in (oc_a, oc_b):
        bb = d @ oc
        cc = float(oc @ oc) - r * r
        hh = bb * bb - cc
        with np.errstate(invalid="ignore"):
            tc = -bb - np.sqrt(hh)
        t_caps.append(np.where((hh > 0) & (tc > EPS), tc, np.inf))
    t_cap = np.minimum(t_caps[0], t_caps[1])
    return np.where(body_ok, t_body, t_cap).astype(np.float32)
