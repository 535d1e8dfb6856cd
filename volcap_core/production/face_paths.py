"""Camera paths around a head: the moving cameras the Face Rig's LQ/HQ pairs are rendered along.

The paper renders each Face Rig sub-sequence's two Poly4DGS models along 60 camera paths of 8
frames, "a moving camera focusing on the face", over "a diverse range of camera motions and focal
lengths". :func:`face_camera_paths` draws such paths, seeded, around a head given by its centre
(one, or one per frame: the camera follows a moving head) and radius; :func:`head_from_model`
takes that head from the reconstruction (a Face Rig model's Gaussians at a time), not from any
synthetic truth.

A path keeps the face framed: every view aims at the head centre (plus a small drawn offset), and
its distance follows from its focal length so that the head sphere fills a drawn fraction of the
frame height. Across a path the focal length (zoom), the distance (dolly) and the direction
(azimuth around the head, elevation) change at constant rates per frame. The distribution is
:class:`FacePathDistribution`; docs/enhancer.md ("Camera paths") states it and why.

Each view carries a near clipping plane (``ViewSpec.near_m``) a few head radii nearer than the head
centre: the paths' distances come from the lens, not from the room, so a path camera may stand
beyond the room's walls (a zoomed-in camera far away), and then what lies between it and the head
(the wall's Gaussians) must not be drawn: the renders see the head and what is behind it.

Conventions: world metres, the stage frame (z up unless ``up`` says otherwise); cameras OpenCV
(x right, y down, z forward), ``K`` in pixels with the top-left pixel centre at 0 (as
:class:`~volcap_core.view.ViewSpec`); focal lengths in mm on a 36 mm-wide sensor (full-frame
equivalent), square pixels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from volcap_core.calibration.geometry import look_at_rotation
from volcap_core.view import ViewSpec

__all__ = ["NEAR_MIN_M", "SENSOR_WIDTH_MM", "CameraPath", "FacePathDistribution", "HeadEstimate", "face_camera_paths",
           "head_from_model"]

#: full-frame sensor width (mm): focal lengths are equivalents on it, ``fx = focal · W / 36``
SENSOR_WIDTH_MM = 36.0

#: the nearest a path view's near plane comes to its camera (metres; the splat camera's default)
NEAR_MIN_M = 0.01


@dataclass(frozen=True)
class FacePathDistribution:
    """What :func:`face_camera_paths` draws, per path (each range uniform unless said otherwise).

    Attributes:
        focal_mm: ``(lo, hi)`` start focal length, mm full-frame equivalent, log-uniform.
        zoom: the end focal is the start's times ``zoom ** U(-1, 1)`` (log-uniform), clipped to
            ``focal_mm``.
        head_fraction: ``(lo, hi)`` the head sphere's image diameter over the frame height, drawn
            at the start and at the end (the distance follows from it and the focal length).
        azimuth_deg: the start direction is within ± this of ``facing`` around ``up``.
        orbit_deg: the azimuth changes by ``U(-orbit, orbit)`` over the path.
        elevation_deg: ``(lo, hi)`` the band of the camera's elevation above the head centre's
            horizontal plane, start and end (end = start + ``U(-tilt, tilt)``, clipped to the band).
        tilt_deg: see ``elevation_deg``.
        aim_offset: the look-at target is the head centre plus a point drawn uniformly in a ball of
            this many head radii, at the start and at the end (the face is near, not exactly at,
            the image centre).
        roll_deg: the camera's roll about its optical axis, ``U(-roll, roll)`` at start and end.
        near_margin: not drawn: each view's near clipping plane (``ViewSpec.near_m``, metres of
            camera depth) is its distance to the head centre less this many head radii (at least
            :data:`NEAR_MIN_M`), so the head (within one radius of its centre, the aim offset
            within ``aim_offset`` radii) and what is behind it are drawn and nothing between the
            camera and the head is.
    """

    focal_mm: tuple[float, float] = (35.0, 200.0)
    zoom: float = 1.5
    head_fraction: tuple[float, float] = (0.3, 0.6)
    azimuth_deg: float = 75.0
    orbit_deg: float = 30.0
    elevation_deg: tuple[float, float] = (-15.0, 30.0)
    tilt_deg: float = 10.0
    aim_offset: float = 0.25
    roll_deg: float = 3.0
    near_margin: float = 3.0

    def __post_init__(self) -> None:
        lo, hi = self.focal_mm
        if not 0 < lo <= hi:
            raise ValueError(f"face path distribution: focal_mm {self.focal_mm} must be 0 < lo <= hi")
        if not self.zoom >= 1:
            raise ValueError(f"face path distribution: zoom {self.zoom} must be >= 1")
        lo, hi = self.head_fraction
        if not 0 < lo <= hi < 2:
            raise ValueError(f"face path distribution: head_fraction {self.head_fraction} must be 0 < lo <= hi < 2")
        lo, hi = self.elevation_deg
        if not -90 < lo <= hi < 90:
            raise ValueError(f"face path distribution: elevation_deg {self.elevation_deg} must be inside (-90, 90)")
        if not self.near_margin >= 1 + self.aim_offset:
            raise ValueError(f"face path distribution: near_margin {self.near_margin} must be >= 1 + aim_offset "
                             f"({1 + self.aim_offset:g} head radii): the near plane would cut the head")
        if min(self.azimuth_deg, self.orbit_deg, self.tilt_deg, self.aim_offset, self.roll_deg) < 0:
            raise ValueError("face path distribution: azimuth_deg, orbit_deg, tilt_deg, aim_offset and "
                             "roll_deg must be >= 0")


@dataclass(frozen=True)
class CameraPath:
    """One moving camera over a sub-sequence's frames.

    Attributes:
        views: one :class:`~volcap_core.view.ViewSpec` per frame time, in order (K px, OpenCV
            world-to-camera, width, height, ``time_s`` the frame's time, ``near_m`` the near
            clipping plane: see :attr:`FacePathDistribution.near_margin`).
        params: JSON-able, what was drawn: ``seed``, ``index``, ``frames``, ``sensor_width_mm``,
            ``focal_mm_start``/``_end`` (full-frame equivalent), ``distance_m_start``/``_end``
            (camera centre to head centre), ``near_m_start``/``_end`` (the views' near planes),
            ``azimuth_deg_start``/``_end`` (around ``up`` from
            ``facing``), ``elevation_deg_start``/``_end``, ``head_fraction_start``/``_end``,
            ``roll_deg_start``/``_end``, ``aim_offset_m_start``/``_end`` (3-vectors),
            ``zoom_rate`` and ``dolly_rate`` (natural log of the focal length's and the
            distance's ratio per frame: 0 on a one-frame path).
    """

    views: list[ViewSpec]
    params: dict = field(default_factory=dict)


def face_camera_paths(head_centre_m, head_radius_m: float, frame_times_s, count: int, *, width: int,
                      height: int, seed: int, facing=(1.0, 0.0, 0.0), up=(0.0, 0.0, 1.0),
                      distribution: FacePathDistribution | None = None) -> list[CameraPath]:
    """``count`` seeded camera paths around a head, one view per frame time.

    Path ``i`` draws from its own stream (``seed``, ``i``): the first ``k`` paths are the same
    whatever ``count`` is. At frame ``k`` of ``n`` (``u = k / (n − 1)``) the focal length, the head
    fraction (so the distance), the azimuth, the elevation, the aim offset and the roll run from
    their start to their end value: log-linearly for the focal length and the distance (constant
    zoom and dolly rates), linearly for the others. The camera sits at that distance from the head
    centre of that frame in that direction and aims at the centre plus the offset; with the head
    sphere of ``head_radius_m`` at distance ``d`` its image diameter is ``2 f r / √(d² − r²)``
    pixels (``f`` the focal in pixels), the drawn fraction of ``height``. Its near clipping plane
    is ``max(d − near_margin · r, NEAR_MIN_M)``: nothing between the camera and the head is drawn.

    Args:
        head_centre_m: ``[3]`` the head centre (metres, world), or ``[n, 3]`` one per frame time.
        head_radius_m: the head's radius (metres), e.g. :func:`head_from_model`'s.
        frame_times_s: ``[n]`` the frames' times (seconds on the take's clock), n >= 1.
        count: number of paths (>= 0).
        width, height: image size (pixels).
        seed: non-negative integer.
        facing: ``[3]`` the direction the face looks (world); only its part across ``up`` counts.
        up: ``[3]`` the world's up (image up; the elevation's axis): the stage's +z by default.
        distribution: what is drawn (default :class:`FacePathDistribution`).
    Returns:
        ``count`` :class:`CameraPath`.
    """
    dist = distribution or FacePathDistribution()
    times = np.asarray(frame_times_s, np.float64).reshape(-1)
    n = len(times)
    if n == 0 or not np.all(np.isfinite(times)):
        raise ValueError(f"face camera paths: frame_times_s must be a non-empty list of finite times, got {times.tolist()}")
    centres = np.asarray(head_centre_m, np.float64)
    if centres.shape == (3,):
        centres = np.broadcast_to(centres, (n, 3))
    if centres.shape != (n, 3) or not np.all(np.isfinite(centres)):
        raise ValueError(f"face camera paths: head_centre_m must be finite, [3] or [{n}, 3] (one per frame time), "
                         f"got shape {np.shape(head_centre_m)}")
    r = float(head_radius_m)
    if not 0 < r < math.inf:
        raise ValueError(f"face camera paths: head_radius_m must be a positive length, got {head_radius_m}")
    if int(count) != count or count < 0:
        raise ValueError(f"face camera paths: count must be a non-negative integer, got {count}")
    if int(width) != width or int(height) != height or width <= 0 or height <= 0:
        raise ValueError(f"face camera paths: width and height must be positive integers, got {width}x{height}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"face camera paths: seed must be a non-negative integer, got {seed}")
    U = _unit(up, "up")
    F = np.asarray(facing, np.float64) - np.dot(facing, U) * U
    if not np.linalg.norm(F) > 1e-6:
        raise ValueError(f"face camera paths: facing {list(facing)} is parallel to up {list(up)}")
    F = F / np.linalg.norm(F)
    S = np.cross(U, F)                      # the face's left, seen from the front: azimuth +90
    return [_path(i, int(seed), dist, centres, times, r, int(width), int(height), F, S, U) for i in range(int(count))]


def _path(i: int, seed: int, dist: FacePathDistribution, centres: np.ndarray, times: np.ndarray, r: float,
          width: int, height: int, F: np.ndarray, S: np.ndarray, U: np.ndarray) -> CameraPath:
    rng = np.random.default_rng([seed, i])
    lo, hi = np.log(dist.focal_mm)
    f0 = math.exp(rng.uniform(lo, hi))
    f1 = float(np.clip(f0 * dist.zoom ** rng.uniform(-1.0, 1.0), *dist.focal_mm))
    phi0, phi1 = rng.uniform(*dist.head_fraction, size=2)
    a0 = rng.uniform(-dist.azimuth_deg, dist.azimuth_deg)
    a1 = a0 + rng.uniform(-dist.orbit_deg, dist.orbit_deg)
    e0 = rng.uniform(*dist.elevation_deg)
    e1 = float(np.clip(e0 + rng.uniform(-dist.tilt_deg, dist.tilt_deg), *dist.elevation_deg))
    aim0, aim1 = (_in_ball(rng) * dist.aim_offset * r for _ in range(2))
    roll0, roll1 = rng.uniform(-dist.roll_deg, dist.roll_deg, size=2)

    n = len(times)
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    views, dists = [], []
    for k in range(n):
        u = k / (n - 1) if n > 1 else 0.0
        f_mm = math.exp((1 - u) * math.log(f0) + u * math.log(f1))
        phi = math.exp((1 - u) * math.log(phi0) + u * math.log(phi1))
        fpx = f_mm * width / SENSOR_WIDTH_MM
        d = _distance(fpx, r, phi * height)
        az, el = math.radians((1 - u) * a0 + u * a1), math.radians((1 - u) * e0 + u * e1)
        direction = math.cos(el) * (math.cos(az) * F + math.sin(az) * S) + math.sin(el) * U
        position = centres[k] + d * direction
        target = centres[k] + (1 - u) * aim0 + u * aim1
        R = look_at_rotation(position, target, (1 - u) * roll0 + u * roll1, up=U)
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ position
        K = ((fpx, 0.0, cx), (0.0, fpx, cy), (0.0, 0.0, 1.0))
        views.append(ViewSpec(K=K, world_to_camera=tuple(tuple(float(x) for x in row) for row in w2c),
                              width=width, height=height, time_s=float(times[k]),
                              near_m=max(d - dist.near_margin * r, NEAR_MIN_M)))
        dists.append(d)
    steps = max(n - 1, 1)
    params = {"seed": seed, "index": i, "frames": n, "sensor_width_mm": SENSOR_WIDTH_MM,
              "focal_mm_start": f0, "focal_mm_end": f1, "distance_m_start": dists[0], "distance_m_end": dists[-1],
              "near_m_start": views[0].near_m, "near_m_end": views[-1].near_m,
              "azimuth_deg_start": a0, "azimuth_deg_end": a1, "elevation_deg_start": e0, "elevation_deg_end": e1,
              "head_fraction_start": float(phi0), "head_fraction_end": float(phi1),
              "roll_deg_start": float(roll0), "roll_deg_end": float(roll1),
              "aim_offset_m_start": aim0.tolist(), "aim_offset_m_end": aim1.tolist(),
              "zoom_rate": math.log(f1 / f0) / steps if n > 1 else 0.0,
              "dolly_rate": math.log(dists[-1] / dists[0]) / steps if n > 1 else 0.0,
              "distribution": _jsonable(asdict(dist))}
    return CameraPath(views=views, params=params)


def _distance(fpx: float, r: float, diameter_px: float) -> float:
    """The distance (metres) at which a sphere of radius ``r`` seen on-axis by a pinhole of focal
    ``fpx`` pixels has an image diameter of ``diameter_px``: ``d = √(r² + (2 f r / D)²)``."""
    return math.sqrt(r * r + (2.0 * fpx * r / diameter_px) ** 2)


def _in_ball(rng: np.random.Generator) -> np.ndarray:
    """A point drawn uniformly in the unit ball."""
    v = rng.normal(size=3)
    return v / np.linalg.norm(v) * rng.uniform() ** (1.0 / 3.0)


def _unit(v, name: str) -> np.ndarray:
    a = np.asarray(v, np.float64)
    n = np.linalg.norm(a) if a.shape == (3,) else 0.0
    if not 1e-12 < n < math.inf:
        raise ValueError(f"face camera paths: {name} must be a finite non-zero 3-vector, got {np.asarray(v).tolist()}")
    return a / n


def _jsonable(d: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


@dataclass(frozen=True)
class HeadEstimate:
    """A head taken from a model: ``centre_m`` ``[3]`` (metres, world), ``radius_m`` (metres), the
    number of Gaussians the fit kept (``gaussians``) and the top of the head along ``up``
    (``top_m``, metres)."""

    centre_m: np.ndarray
    radius_m: float
    gaussians: int
    top_m: float


def head_from_model(means, opacities, *, up=(0.0, 0.0, 1.0), around_m=None, within_m: float = 0.5,
                    min_opacity: float = 0.5, crown_m: float = 0.22, top_quantile: float = 0.995,
                    radius_range_m: tuple[float, float] = (0.06, 0.16), tolerance: float = 0.15,
                    trials: int = 400, max_points: int = 5000) -> HeadEstimate:
    """The head of a Face Rig model (one actor's head and shoulders) from its Gaussians at a time.

    The head is the top of the performer: of the nearly opaque Gaussians (opacity at that time
    >= ``min_opacity``: the surfaces, not the haze) within ``within_m`` of ``around_m`` (where the
    rig's cameras aim: the walls and ceiling of the rig stay out), the top is the
    ``top_quantile`` of their heights along ``up`` (a few floaters above do not move it) and the
    crown the ones less than ``crown_m`` below it (the head down to about the chin, above the
    shoulders). A sphere is fitted to the crown's centres robustly (RANSAC): of ``trials`` spheres
    through 4 of them (seeded: the same Gaussians give the same head) with a radius in
    ``radius_range_m``, the one with the most centres within ``tolerance`` of a radius of its
    surface in the most directions from its centre (a head is seen from all around; a flat slate held
    in front of the face covers a few directions however many Gaussians it has), then the most
    such centres, wins and is refined by least squares on those; so what else is that high (the
    slate, a raised hand, the neck) does not pull it.

    Args:
        means: ``[N, 3]`` the Gaussians' centres at the time (metres, world;
            :func:`volcap_core.splat.model.evaluate`'s ``means``), numpy or torch.
        opacities: ``[N]`` their opacities at that time, in [0, 1] (``evaluate``'s ``opacities``).
        up: ``[3]`` the world's up.
        around_m: ``[3]`` where to look (e.g. the median of the Face Rig cameras' aim points);
            None: every Gaussian.
        within_m: radius (metres) of the ball around ``around_m`` that counts.
        max_points: the crown is subsampled (seeded) to this many centres for the fit.
    Returns:
        :class:`HeadEstimate`. ``ValueError`` when fewer than 10 Gaussians are left to fit or no
        sphere of a head's radius fits them.
    """
    P = _array(means).reshape(-1, 3)
    o = _array(opacities).reshape(-1)
    if len(P) != len(o):
        raise ValueError(f"head from model: {len(P)} means but {len(o)} opacities")
    U = np.asarray(up, np.float64)
    U = U / np.linalg.norm(U)
    keep = np.isfinite(P).all(axis=1) & (o >= min_opacity)
    if around_m is not None:
        keep &= np.linalg.norm(P - np.asarray(around_m, np.float64), axis=1) <= within_m
    P = P[keep]
    if len(P) < 10:
        raise ValueError(f"head from model: {len(P)} Gaussians with opacity >= {min_opacity:g}"
                         + ("" if around_m is None else f" within {within_m:g} m of {np.asarray(around_m).tolist()}")
                         + ": too few to find a head")
    h = P @ U
    top = float(np.quantile(h, top_quantile))
    crown = P[(h >= top - crown_m) & (h <= top)]
    if len(crown) < 10:
        raise ValueError(f"head from model: {len(crown)} Gaussians in the top {crown_m:g} m: too few to fit a head")
    rng = np.random.default_rng(0)
    if len(crown) > max_points:
        crown = crown[rng.choice(len(crown), max_points, replace=False)]
    r_lo, r_hi = radius_range_m
    best, best_score = None, (0, 0)
    for _ in range(trials):
        c, r = _fit_sphere(crown[rng.choice(len(crown), 4, replace=False)])
        if not r_lo <= r <= r_hi:
            continue
        offsets = crown - c
        on = np.abs(np.linalg.norm(offsets, axis=1) - r) < tolerance * r
        score = (_directions_covered(offsets[on], U), int(on.sum()))
        if score > best_score:
            best, best_score = (c, r), score
    if best is None:
        raise ValueError(f"head from model: no sphere of radius {r_lo:g}-{r_hi:g} m fits the top {crown_m:g} m "
                         f"of the Gaussians ({len(crown)} of them)")
    centre, radius = best
    inliers = crown
    for _ in range(3):
        near = crown[np.abs(np.linalg.norm(crown - centre, axis=1) - radius) < tolerance * radius]
        if len(near) < 10:
            break
        inliers = near
        centre, radius = _fit_sphere(near)
    return HeadEstimate(centre_m=centre, radius_m=radius, gaussians=len(inliers), top_m=top)


def _directions_covered(offsets: np.ndarray, up: np.ndarray, bins: tuple[int, int] = (12, 6), least: int = 3) -> int:
    """How many of ``bins`` (azimuth × elevation, equal steps) directions from a sphere's centre hold
    at least ``least`` of ``offsets`` ``[M, 3]``: a head seen from all around covers most, a flat
    patch (a slate, a wall) only the few it faces."""
    if len(offsets) == 0:
        return 0
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    az = np.arctan2(offsets @ e2, offsets @ e1)
    el = np.arcsin(np.clip(offsets @ up / np.linalg.norm(offsets, axis=1).clip(1e-12), -1.0, 1.0))
    i = np.minimum(((az + np.pi) / (2 * np.pi) * bins[0]).astype(int), bins[0] - 1)
    j = np.minimum(((el + np.pi / 2) / np.pi * bins[1]).astype(int), bins[1] - 1)
    return int((np.bincount(i * bins[1] + j, minlength=bins[0] * bins[1]) >= least).sum())


def _fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere through ``points`` ``[M, 3]``: ``|p|² = 2 c·p + (r² − |c|²)``."""
    A = np.concatenate([2.0 * points, np.ones((len(points), 1))], axis=1)
    b = (points ** 2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:3]
    return c, float(math.sqrt(max(sol[3] + c @ c, 0.0)))


def _array(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, np.float64)
