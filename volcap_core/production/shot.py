"""Shots: virtual camera paths over a performance, and the frames they render.

A shot is a JSON file (format in ``docs/shots.md``): resolution, sensor, frame range and rate, and
keyframes (frame, position, orientation quaternion *or* look-at point, focal length in mm,
optional roll). :func:`camera_at` interpolates them into a
:class:`~volcap_core.splat.camera.Camera`; :func:`render_shot_frame` renders the performance
through it and returns a linear, premultiplied RGBA half-float EXR cropped to the actors, with
the camera in its header and, from the second frame on, the exact backward flow to the previous
frame in two extra channels ``flow.x``, ``flow.y`` (:func:`render_performance_flow`; none across a
segment boundary).

Conventions:

- World: the capture's stage frame, metres, z up (``up`` is configurable per shot).
- Orientation quaternions are ``[w, x, y, z]``, the **camera-to-world** rotation of the camera's
  axes; ``axes: "opencv"`` (default; x right, y down, z forward, as every volcap camera) or
  ``"opengl"`` (x right, y up, looking down −z: USD, Maya, Blender).
- Roll (degrees) turns the camera about its viewing axis after aiming: ``R ← R · Rz(roll)`` in
  OpenCV axes, i.e. positive roll turns the camera clockwise as seen from behind it, so the scene
  turns counter-clockwise in the image.
- Time: shot frame ``f`` shows the performance at ``t = time_offset_s + f / fps`` seconds on the
  take's clock (``time_offset_s`` lets editorial frame numbers such as 1001 map to the take).
- Intrinsics: ``fx = focal_mm · W / sensor_w``, ``fy = focal_mm · H / sensor_h``, principal point
  at the image centre; a sensor whose aspect differs from the resolution's by more than 0.5% is
  refused (non-square pixels are not a thing a shot should do by accident).

Interpolation between keyframes ``i`` and ``i+1`` (``u`` = fraction of the way, in frames):

- position: ``catmull-rom`` (default; non-uniform Catmull-Rom through the keyframes, tangents
  ``(p_{i+1} − p_{i−1}) / (f_{i+1} − f_{i−1})``, one-sided at the ends: C¹) or ``linear``;
- orientation: ``slerp`` of the two keyframes' rotations (shortest arc). When **both** keyframes
  aim at a ``look_at`` point, the point itself is interpolated (like the position) and the camera
  re-aimed at every frame, so a subject framed at both keyframes stays framed in between;
- focal: ``log`` (default; geometric, a constant zoom ratio per frame) or ``linear``;
- roll: linear.

Before the first and after the last keyframe the camera holds.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from hardware.validation_errors import format_validation_error
from volcap_core.calibration.geometry import look_at_rotation
from volcap_core.chromaticities import WORKING_CHROMATICITIES
from volcap_core.imageio.write import HALF_MAX, to_half
from volcap_core.production.performance import Performance, gaussians_in_volume, render_performance, segments_at
from volcap_core.records import ArtifactRef
from volcap_core.splat.camera import Camera
from volcap_core.splat.model import Poly4DGS, evaluate
from volcap_core.splat.render import FLOW_MIN_ALPHA, Backend, gaussians_at, render_flow
from volcap_core.stage import Box

__all__ = [
    "FLOW_CHANNELS",
    "SHOT_FORMAT",
    "CropSettings",
    "Interpolation",
    "Keyframe",
    "Shot",
    "ShotError",
    "alpha_crop_window",
    "camera_at",
    "encode_shot_exr",
    "load_shot",
    "opengl_world_to_camera_row_major",
    "render_performance_flow",
    "render_shot_frame",
    "render_shot_frames",
]

SHOT_FORMAT = "volcap-shot/1"
#: the EXR channels of a shot frame's exact backward flow to the previous shot frame (half, px,
#: x right / y down; ``docs/shots.md``)
FLOW_CHANNELS = ("flow.x", "flow.y")
Vec3 = tuple[float, float, float]


class ShotError(ValueError):
    """An invalid shot file; the message names the shot, the file and each problem."""


class Keyframe(BaseModel):
    """A camera key. Give exactly one of ``orientation`` (quaternion wxyz, camera-to-world) and
    ``look_at`` (a world point the optical axis goes through)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    frame: float
    position: Vec3
    orientation: tuple[float, float, float, float] | None = None
    look_at: Vec3 | None = None
    focal_mm: float = Field(gt=0, allow_inf_nan=False)
    roll_deg: float = Field(0.0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _one_orientation(self) -> "Keyframe":
        if (self.orientation is None) == (self.look_at is None):
            both = "both" if self.orientation is not None else "neither"
            raise ValueError(f"give exactly one of 'orientation' and 'look_at' ({both} given)")
        values = [*self.position, *(self.orientation or ()), *(self.look_at or ())]
        if not all(math.isfinite(v) for v in values):
            raise ValueError("position, orientation and look_at must be finite numbers")
        if self.orientation is not None and math.sqrt(sum(q * q for q in self.orientation)) < 1e-9:
            raise ValueError(f"orientation quaternion {list(self.orientation)} has zero length")
        if self.look_at is not None and math.dist(self.look_at, self.position) < 1e-9:
            raise ValueError(f"look_at {list(self.look_at)} is the camera position itself")
        return self


class Interpolation(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    position: Literal["catmull-rom", "linear"] = "catmull-rom"
    orientation: Literal["slerp"] = "slerp"
    focal: Literal["log", "linear"] = "log"


class CropSettings(BaseModel):
    """Frames are cropped to the pixels with ``alpha > alpha_threshold``, grown by ``margin_px``."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    alpha_threshold: float = Field(1.0 / 255.0, ge=0.0, lt=1.0)
    margin_px: int = Field(16, ge=0)
    enabled: bool = True


class Shot(BaseModel):
    """A shot: a camera path over one performance (see module doc and ``docs/shots.md``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    format: Literal["volcap-shot/1"] = SHOT_FORMAT
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    performance: str = Field(min_length=1,
                             description="the capture (performance) it shows, by spec name")
    actors: tuple[str, ...] = Field((), description="actors in frame (enhancement is per actor); "
                                                    "empty: every actor of the capture")
    frames: tuple[int, int] = Field(description="shot frames [start, end), end exclusive")
    fps: float = Field(gt=0, allow_inf_nan=False)
    time_offset_s: float = Field(0.0, allow_inf_nan=False,
                                 description="t = time_offset_s + frame / fps on the take clock")
    resolution: tuple[int, int] = Field(description="width, height in pixels")
    sensor_mm: float | tuple[float, float] = Field(description="sensor width, or (width, height)")
    axes: Literal["opencv", "opengl"] = "opencv"
    up: Vec3 = (0.0, 0.0, 1.0)
    near: float = Field(0.05, gt=0)
    far: float = Field(1000.0, gt=0)
    interpolation: Interpolation = Field(default_factory=Interpolation)
    enhance: bool = Field(False, description="close-up: run the detail enhancer on this shot")
    content: Literal["stage", "all"] = Field(
        "stage", description="stage: only what is inside the capture's stage volume (the performers, "
                             "without the set), so alpha and the crop follow the actors; all: everything")
    crop: CropSettings = Field(default_factory=CropSettings)
    keyframes: tuple[Keyframe, ...] = Field(min_length=1)

    @field_validator("resolution")
    @classmethod
    def _positive_resolution(cls, v: tuple[int, int]) -> tuple[int, int]:
        if v[0] <= 0 or v[1] <= 0:
            raise ValueError(f"width and height must be positive, got {v[0]}x{v[1]}")
        return v

    @field_validator("sensor_mm")
    @classmethod
    def _positive_sensor(cls, v):
        sizes = v if isinstance(v, tuple) else (v,)
        if not all(math.isfinite(s) and s > 0 for s in sizes):
            raise ValueError(f"sensor size must be positive millimetres, got {v}")
        return v

    @model_validator(mode="after")
    def _check(self) -> "Shot":
        a, b = self.frames
        if b <= a:
            raise ValueError(f"frames [{a}, {b}) is empty (end is exclusive)")
        if self.far <= self.near:
            raise ValueError(f"far ({self.far}) must exceed near ({self.near})")
        if math.hypot(*self.up) < 1e-9:
            raise ValueError("up must be a non-zero vector")
        sw, sh = self.sensor_size_mm
        w, h = self.resolution
        if abs((sw / sh) / (w / h) - 1.0) > 5e-3:
            raise ValueError(f"sensor {sw:g}x{sh:g} mm (aspect {sw / sh:.4f}) does not match the "
                             f"resolution {w}x{h} (aspect {w / h:.4f}): give a sensor height of "
                             f"{sw * h / w:.3f} mm, or only the width")
        for i in range(1, len(self.keyframes)):
            prev, cur = self.keyframes[i - 1], self.keyframes[i]
            if cur.frame <= prev.frame:
                raise ValueError(f"keyframes must be sorted by frame with no repeats: keyframe {i} "
                                 f"(frame {cur.frame:g}) follows keyframe {i - 1} (frame "
                                 f"{prev.frame:g})")
        up = np.asarray(self.up, dtype=np.float64)
        for i, k in enumerate(self.keyframes):
            if k.look_at is not None:
                d = np.subtract(k.look_at, k.position)
                if np.linalg.norm(np.cross(d / np.linalg.norm(d), up / np.linalg.norm(up))) < 1e-6:
                    raise ValueError(f"keyframe {i} (frame {k.frame:g}): looks along 'up' "
                                     f"{list(self.up)}; the roll is undefined")
        return self

    @property
    def sensor_size_mm(self) -> tuple[float, float]:
        if isinstance(self.sensor_mm, tuple):
            return self.sensor_mm
        w, h = self.resolution
        return self.sensor_mm, self.sensor_mm * h / w

    def time_at(self, frame: float) -> float:
        """Seconds on the take's clock shown at shot frame ``frame``."""
        return self.time_offset_s + frame / self.fps

    def frame_numbers(self) -> range:
        return range(*self.frames)


def load_shot(source: str | Path | Mapping[str, Any], *, where: str | None = None) -> Shot:
    """A :class:`Shot` from a JSON file path or an already parsed mapping.

    Raises :class:`ShotError` naming the shot, the file (or ``where``) and, for each problem, the
    keyframe (index and frame) or field with the offending value."""
    if isinstance(source, Mapping):
        data, origin = dict(source), where or "<inline shot>"
    else:
        origin = where or str(source)
        try:
            data = json.loads(Path(source).read_text())
        except FileNotFoundError:
            raise ShotError(f"{origin}: shot file not found") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ShotError(f"{origin}: not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ShotError(f"{origin}: a shot is a JSON object, got {type(data).__name__}")
    name = data.get("name")
    label = f"shot {name!r}" if isinstance(name, str) else "shot (unnamed)"
    try:
        return Shot.model_validate(data)
    except ValidationError as exc:
        keyframes = data.get("keyframes") if isinstance(data.get("keyframes"), list) else []

        def describe(loc: tuple) -> str:
            if len(loc) >= 2 and loc[0] == "keyframes" and isinstance(loc[1], int):
                k = keyframes[loc[1]] if loc[1] < len(keyframes) else None
                frame = k.get("frame") if isinstance(k, dict) else None
                head = f"keyframe {loc[1]}" + (f" (frame {frame})" if frame is not None else "")
                rest = ".".join(str(p) for p in loc[2:])
                return f"{head}{': ' + rest if rest else ''}"
            return ".".join(str(p) for p in loc) or "shot"

        problems = format_validation_error(exc, describe_loc=describe)
        raise ShotError(f"{label} ({origin}): " + "; ".join(problems)) from None


# ------------------------------------------------------------------------------------------------
# Rotations (numpy float64; quaternions wxyz)


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Shepperd's method: the largest diagonal term picks a stable branch."""
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:  # shortest arc
        q1, d = -q1, -d
    if d > 0.9995:  # nearly parallel: normalised lerp is exact enough and stable
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(1.0, d))
    s = math.sin(theta)
    return (math.sin((1 - u) * theta) * q0 + math.sin(u * theta) * q1) / s


def _aim(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation (OpenCV axes as columns) of a camera at ``eye`` aimed at
    ``target``: the library's one look-at (:func:`~volcap_core.calibration.geometry.look_at_rotation`),
    transposed."""
    return look_at_rotation(eye, target, up=up).T


_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def _roll(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ------------------------------------------------------------------------------------------------
# Interpolation


def _segment(frames: Sequence[float], f: float) -> tuple[int, float]:
    """Keyframe interval ``i`` holding ``f`` and the fraction ``u`` in it (clamped: hold)."""
    n = len(frames)
    if n == 1 or f <= frames[0]:
        return 0, 0.0
    if f >= frames[-1]:
        return n - 2, 1.0
    i = int(np.searchsorted(frames, f, side="right")) - 1
    return i, (f - frames[i]) / (frames[i + 1] - frames[i])


def _hermite(frames: Sequence[float], points: Sequence[np.ndarray], i: int, u: float,
             mode: str) -> np.ndarray:
    """Position-like interpolation between points ``i`` and ``i+1`` (see module doc)."""
    p0, p1 = points[i], points[i + 1]
    if mode == "linear":
        return p0 + u * (p1 - p0)

    def tangent(k: int) -> np.ndarray:
        lo, hi = max(k - 1, 0), min(k + 1, len(points) - 1)
        return (points[hi] - points[lo]) / (frames[hi] - frames[lo])

    dt = frames[i + 1] - frames[i]
    u2, u3 = u * u, u * u * u
    return ((2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + u) * dt * tangent(i)
            + (-2 * u3 + 3 * u2) * p1 + (u3 - u2) * dt * tangent(i + 1))


def _keyframe_rotation(shot: Shot, k: Keyframe) -> np.ndarray:
    """Camera-to-world rotation (OpenCV axes) of a keyframe, without roll."""
    if k.look_at is not None:
        return _aim(np.asarray(k.position, float), np.asarray(k.look_at, float),
                    np.asarray(shot.up, float))
    R = _quat_to_matrix(np.asarray(k.orientation, float))
    return R @ _GL_TO_CV if shot.axes == "opengl" else R


def camera_pose_at(shot: Shot, frame: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``(position [3], camera-to-world rotation [3,3] in OpenCV axes, focal_mm)`` at ``frame``."""
    keys = shot.keyframes
    if len(keys) == 1:
        k = keys[0]
        return (np.asarray(k.position, float), _keyframe_rotation(shot, k) @ _roll(k.roll_deg),
                k.focal_mm)
    frames = [k.frame for k in keys]
    i, u = _segment(frames, frame)
    k0, k1 = keys[i], keys[i + 1]
    mode = shot.interpolation.position
    positions = [np.asarray(k.position, float) for k in keys]
    pos = _hermite(frames, positions, i, u, mode)
    if k0.look_at is not None and k1.look_at is not None:
        # re-aim at the interpolated target; neighbours that are not look-at keys do not bend it
        lo, hi = i, i + 1
        while lo > 0 and keys[lo - 1].look_at is not None:
            lo -= 1
        while hi + 1 < len(keys) and keys[hi + 1].look_at is not None:
            hi += 1
        sub_frames = frames[lo:hi + 1]
        targets = [np.asarray(keys[j].look_at, float) for j in range(lo, hi + 1)]
        target = _hermite(sub_frames, targets, i - lo, u, mode)
        R = _aim(pos, target, np.asarray(shot.up, float))
    else:
        q0 = _matrix_to_quat(_keyframe_rotation(shot, k0))
        q1 = _matrix_to_quat(_keyframe_rotation(shot, k1))
        R = _quat_to_matrix(_slerp(q0, q1, u))
    roll = k0.roll_deg + u * (k1.roll_deg - k0.roll_deg)
    if shot.interpolation.focal == "log":
        focal = math.exp(math.log(k0.focal_mm) + u * (math.log(k1.focal_mm) - math.log(k0.focal_mm)))
    else:
        focal = k0.focal_mm + u * (k1.focal_mm - k0.focal_mm)
    return pos, R @ _roll(roll), focal


def camera_at(shot: Shot, frame: float) -> Camera:
    """The :class:`~volcap_core.splat.camera.Camera` of ``shot`` at ``frame`` (fractional allowed)."""
    pos, R, focal = camera_pose_at(shot, frame)
    w, h = shot.resolution
    sw, sh = shot.sensor_size_mm
    K = np.array([[focal * w / sw, 0.0, w / 2.0], [0.0, focal * h / sh, h / 2.0], [0.0, 0.0, 1.0]])
    w2c = np.eye(4)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ pos
    return Camera(K=K, world_to_camera=w2c, width=w, height=h, near=shot.near, far=shot.far)


# ------------------------------------------------------------------------------------------------
# Frames: crop and EXR


def alpha_crop_window(alpha: np.ndarray, threshold: float,
                      margin: int) -> tuple[int, int, int, int] | None:
    """``(x_min, y_min, x_max, y_max)`` (inclusive, EXR data-window style) of the pixels with
    ``alpha > threshold``, grown by ``margin`` pixels and clipped to the image; None if none."""
    a = np.asarray(alpha)
    if a.ndim == 3:
        a = a[..., 0]
    mask = a > threshold
    if not mask.any():
        return None
    ys = np.flatnonzero(mask.any(axis=1))
    xs = np.flatnonzero(mask.any(axis=0))
    h, w = mask.shape
    return (max(0, int(xs[0]) - margin), max(0, int(ys[0]) - margin),
            min(w - 1, int(xs[-1]) + margin), min(h - 1, int(ys[-1]) + margin))


def opengl_world_to_camera_row_major(world_to_camera_cv: np.ndarray) -> np.ndarray:
    """OpenEXR's standard ``worldToCamera`` attribute from an OpenCV world-to-camera matrix.

    The standard attribute uses Imath's row-vector convention (``p_cam = p_world · M``) and a
    left-handed camera space with x right, **y up**, z forward (RenderMan's): flip y, transpose."""
    flip = np.diag([1.0, -1.0, 1.0, 1.0])
    # C order: the OpenEXR bindings copy the raw buffer, a transposed view would be written as is
    return np.ascontiguousarray((flip @ np.asarray(world_to_camera_cv, dtype=np.float64)).T)


def encode_shot_exr(rgba: np.ndarray, camera: Camera, shot: Shot, frame: int, *,
                    extra: Mapping[str, str | int | float] | None = None,
                    flow: np.ndarray | None = None) -> bytes:
    """Half-float RGBA EXR of one shot frame, cropped to the actors, camera in the header.

    ``rgba``: ``[H, W, 4]`` linear, premultiplied (a render over nothing). The display window is
    the full frame; the data window is :func:`alpha_crop_window` of the alpha (``shot.crop``), so
    compositing software places the crop where it belongs. An empty frame keeps a 1×1 data window
    at the origin and sets ``volcap.empty = 1``. Header attributes (``docs/shots.md``):
    ``volcap.shot``, ``volcap.performance``, ``volcap.frame``, ``volcap.time`` (s),
    ``volcap.fps``, ``volcap.K`` (m33d, pixels), ``volcap.worldToCamera`` (m44d, OpenCV axes,
    ``x_cam = M · x_world``), ``volcap.focalMm``, ``volcap.sensorMm`` (v2d),
    ``volcap.alphaThreshold``, ``volcap.cropMarginPx``, ``volcap.empty``, and the standard
    ``worldToCamera`` (m44f, OpenEXR's convention, see :func:`opengl_world_to_camera_row_major`).

    ``flow``: ``[H, W, 2]`` the frame's exact backward flow to the previous shot frame (px, x then
    y; :func:`render_performance_flow`), written as two more half channels :data:`FLOW_CHANNELS`
    over the same data window (not for an empty frame). None: RGBA only.
    """
    import OpenEXR

    px = np.asarray(rgba, dtype=np.float32)
    h, w = px.shape[:2]
    if px.ndim != 3 or px.shape[2] != 4:
        raise ValueError(f"rgba must be [H, W, 4], got {px.shape}")
    if flow is not None and np.shape(flow) != (h, w, 2):
        raise ValueError(f"flow must be [H, W, 2] = {(h, w, 2)}, got {np.shape(flow)}")
    if (w, h) != (camera.width, camera.height):
        raise ValueError(f"image {w}x{h} does not match the camera's {camera.width}x{camera.height}")
    crop = shot.crop
    window = (alpha_crop_window(px[..., 3], crop.alpha_threshold, crop.margin_px)
              if crop.enabled else (0, 0, w - 1, h - 1))
    empty = window is None
    if empty:
        window = (0, 0, 0, 0)
    x0, y0, x1, y1 = window
    half = to_half(px)
    cropped = half[y0:y1 + 1, x0:x1 + 1]
    focal = float(camera.K[0, 0]) * shot.sensor_size_mm[0] / w  # back from pixels to mm
    K = np.ascontiguousarray(camera.K.detach().cpu().double().numpy())
    w2c = np.ascontiguousarray(camera.world_to_camera.detach().cpu().double().numpy())
    header: dict[str, Any] = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "chromaticities": tuple(WORKING_CHROMATICITIES),  # renders are in the working space
        "dataWindow": (np.array([x0, y0], dtype=np.int32), np.array([x1, y1], dtype=np.int32)),
        "displayWindow": (np.array([0, 0], dtype=np.int32),
                          np.array([w - 1, h - 1], dtype=np.int32)),
        "volcap.shot": shot.name,
        "volcap.performance": shot.performance,
        "volcap.frame": int(frame),
        "volcap.time": np.array([shot.time_at(frame)], dtype=np.float64),
        "volcap.fps": np.array([shot.fps], dtype=np.float64),
        "volcap.K": K,
        "volcap.worldToCamera": w2c,
        "volcap.focalMm": np.array([focal], dtype=np.float64),
        "volcap.sensorMm": np.asarray(shot.sensor_size_mm, dtype=np.float64),
        "volcap.alphaThreshold": np.array([crop.alpha_threshold], dtype=np.float64),
        "volcap.cropMarginPx": int(crop.margin_px),
        "volcap.empty": int(empty),
        "worldToCamera": opengl_world_to_camera_row_major(w2c).astype(np.float32),
    }
    for key, value in (extra or {}).items():
        header[f"volcap.{key}"] = (np.array([value], dtype=np.float64)
                                   if isinstance(value, float) else value)
    planes = {c: np.ascontiguousarray(cropped[..., i]) for i, c in enumerate("RGBA")}
    if flow is not None and not empty:
        f16 = np.clip(np.nan_to_num(np.asarray(flow, np.float32), nan=0.0), -HALF_MAX, HALF_MAX).astype(np.float16)
        for i, c in enumerate(FLOW_CHANNELS):
            planes[c] = np.ascontiguousarray(f16[y0:y1 + 1, x0:x1 + 1, i])
    out = io.BytesIO()
    OpenEXR.File(header, planes).write(out)
    return out.getvalue()


def _segment_key(seg) -> tuple:
    return seg.frames, seg.model.digest


def render_performance_flow(performance: Performance, load_model: Callable[[ArtifactRef], Poly4DGS],
                            camera: Camera, t: float, prev_camera: Camera, prev_t: float,
                            backend: Backend = "auto", *, volume: Box | None = None) -> torch.Tensor | None:
    """The exact backward flow ``[H, W, 2]`` (px, x then y) of :func:`render_performance` at ``t``
    through ``camera`` to its render at ``prev_t`` through ``prev_camera``, or **None** where there
    is none: when the two frames are not rendered by the same segments (a segment boundary, or
    entering or leaving an overlap) or ``prev_t`` is outside the performance. A Gaussian exists in
    one segment's model only, so flow across models has no correspondence; the enhancer falls back
    to DIS for that pair.

    Per segment: :func:`~volcap_core.splat.render.render_flow` of the Gaussians the colour render
    draws at ``t`` (evaluated at ``t``, the same ``volume`` selection by their centre at ``t``)
    and the same Gaussians at ``prev_t`` (:func:`~volcap_core.splat.render.gaussians_at`: defined
    even for a Gaussian invisible then). Inside an overlap (both frames blend the same two
    segments) each segment's exact flow is combined like the image blend: ``Σ w_s α_s f_s /
    Σ w_s α_s`` with the weights at ``t``. Pixels whose alpha is below
    :data:`~volcap_core.splat.render.FLOW_MIN_ALPHA` get 0.
    """
    parts = segments_at(performance, t)
    try:
        prev_parts = segments_at(performance, prev_t)
    except ValueError:  # the previous frame is outside the performance: nothing to flow to
        return None
    if sorted(_segment_key(s) for s, _ in parts) != sorted(_segment_key(s) for s, _ in prev_parts):
        return None
    num = den = None
    with torch.no_grad():
        for seg, w in parts:
            model = load_model(seg.model)
            gaussians = gaussians_in_volume(evaluate(model, t), volume)
            out = render_flow(gaussians, gaussians_at(model, prev_t, gaussians.ids), camera, prev_camera,
                              backend=backend, min_alpha=0.0)
            wa = w * out["alpha"]
            num = wa * out["flow"] if num is None else num + wa * out["flow"]
            den = wa if den is None else den + wa
        return torch.where(den >= FLOW_MIN_ALPHA, num / den.clamp(min=1e-10), torch.zeros_like(num))


def render_shot_frame(shot: Shot, performance: Performance,
                      load_model: Callable[[ArtifactRef], Poly4DGS], frame: int, *,
                      backend: Backend = "auto", device: torch.device | str | None = None,
                      stage: Box | None = None, flow: bool = True) -> bytes:
    """Render shot frame ``frame`` of ``performance`` and encode it (:func:`encode_shot_exr`):
    linear premultiplied RGBA, half float, cropped to the actors, camera in the header.

    With ``flow`` (default), every frame but the shot's first also carries the exact backward flow
    to frame ``frame - 1`` (:func:`render_performance_flow`, channels :data:`FLOW_CHANNELS`),
    unless the two frames are rendered by different segments (then no flow channels).

    ``load_model`` maps a segment's model ref to the model on the rendering device (cache it);
    ``device`` moves the camera there."""
    a, b = shot.frames
    if not a <= frame < b:
        raise ValueError(f"shot {shot.name}: frame {frame} is outside its frames [{a}, {b})")
    camera = camera_at(shot, frame)
    if device is not None:
        camera = camera.to(device)
    if shot.content == "stage" and stage is None:
        raise ValueError(f"shot {shot.name}: content 'stage' needs the capture's stage volume")
    volume = stage if shot.content == "stage" else None
    out = render_performance(performance, load_model, camera, shot.time_at(frame), backend, volume=volume)
    rgba = torch.cat([out["rgb"], out["alpha"]], dim=-1).float().cpu().numpy()
    motion = None
    if flow and frame > a:
        prev_camera = camera_at(shot, frame - 1)
        if device is not None:
            prev_camera = prev_camera.to(device)
        motion = render_performance_flow(performance, load_model, camera, shot.time_at(frame), prev_camera,
                                         shot.time_at(frame - 1), backend, volume=volume)
        motion = None if motion is None else motion.float().cpu().numpy()
    return encode_shot_exr(rgba, camera, shot, frame, extra={"content": shot.content}, flow=motion)


def render_shot_frames(shot: Shot, performance: Performance, model_bytes: Callable[[ArtifactRef], bytes], *,
                       device: torch.device | str | None = None, stage: Box | None = None):
    """Every frame of ``shot`` in order: yields (``<frame:06d>.exr``, EXR bytes of
    :func:`render_shot_frame`, with the exact flow to the previous frame). ``model_bytes(ref)``
    reads a segment model's stored bytes; the last few models stay loaded on ``device`` (a
    boundary needs two; frames walk forward)."""
    import functools

    from volcap_core.splat import load_model

    device = device or ("cuda" if torch.cuda.is_available() else "cpu")

    @functools.lru_cache(maxsize=4)
    def model_of(ref: ArtifactRef) -> Poly4DGS:
        return load_model(model_bytes(ref), device)

    for f in shot.frame_numbers():
        yield f"{f:06d}.exr", render_shot_frame(shot, performance, model_of, f, device=device, stage=stage)
