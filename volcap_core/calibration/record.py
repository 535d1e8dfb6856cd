"""The ``Calibration`` record: every camera's intrinsics and pose at every take index.

Conventions: world = the stage frame (metres, z up, origin at the stage centre on the floor);
``world_to_camera`` is 4x4 with OpenCV camera axes (x right, y down, z forward), ``x_cam = R x + t``;
intrinsics in OpenCV pixels (centre of the top-left pixel at (0, 0)); distortion in OpenCV's order
``(k1, k2, p1, p2, k3)``, or ``(k1, k2, p1, p2, k3, k4, k5, k6)`` for a rational (FULL_OPENCV) lens
(all zero for pinhole cameras).

Size: static cameras carry one pose in the JSON record. Tracking cameras change every frame; their
per-frame arrays live in one safetensors blob referenced by ``Calibration.tracking_frames``:
``<camera id>/intrinsics`` float64 [T, 4] (fx, fy, cx, cy) and ``<camera id>/world_to_camera``
float64 [T, 4, 4], T = ``frame_count``; for a camera with a zoom lens table also
``<camera id>/distortion`` float64 [T, 5] or [T, 8]: OpenCV's distCoeffs of each frame's lens (the
lens at that frame's focal), so frame t of that camera is rectified with
``intrinsics[t]`` and ``distortion[t]`` (:func:`frame_camera`), and its ``intrinsics[t]`` is the
pinhole of the rectified frame. The blob's format is in its metadata: ``volcap-tracking-frames/1``
(no distortion: the bytes are those written before distortion existed) or ``/2`` (some camera has
per-frame distortion); :func:`decode_tracking_frames` reads both and refuses anything else.
:func:`encode_tracking_frames` / :func:`decode_tracking_frames` turn them into / from bytes; the
task layer stores the bytes and puts the ref in the record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Mapping

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, SerializerFunctionWrapHandler, field_validator, model_serializer
from safetensors.numpy import load as st_load
from safetensors.numpy import save as st_save

from hardware.serialization import omit_unset
from volcap_core.records import MEDIA_SAFETENSORS, ArtifactRef, Record

Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
Matrix4 = tuple[tuple[float, float, float, float], ...]


class CameraCalibration(BaseModel):
    """One camera. ``static`` cameras have ``intrinsics`` and ``world_to_camera`` here; tracking
    cameras have them per frame in the tracking blob (and None here)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str
    role: str = Field(description="rig role: static, tracking-landscape or tracking-portrait")
    static: bool
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    intrinsics: tuple[float, float, float, float] | None = Field(
        default=None, description="fx, fy, cx, cy in OpenCV pixels (static cameras)")
    distortion: tuple[float, ...] = Field(
        default=(0.0, 0.0, 0.0, 0.0, 0.0),
        description="OpenCV distCoeffs of the camera's own frames: 5 (k1 k2 p1 p2 k3) or 8 (… k4 k5 k6)")
    world_to_camera: Matrix4 | None = Field(default=None, description="4x4, OpenCV axes (static cameras)")
    quality: dict[str, float] = Field(default_factory=dict,
                                      description="per-camera fit statistics (reprojection px, inliers...)")
    scene_depth_m: tuple[float, float, float] | None = Field(
        default=None, description="a static camera's view of the static scene: the 1st percentile, median "
                                  "and 99th percentile depth (metres along its axis) of the calibration's sparse "
                                  "points it observes; where dense points sweep (dense_points_step). "
                                  "None: not measured (a calibration made before it was, or too few points)")

    @model_serializer(mode="wrap")
    def _omit_unmeasured(self, handler: SerializerFunctionWrapHandler):
        # records of calibrations without scene depths serialise (and digest) as before it existed
        return omit_unset(handler(self), ("scene_depth_m",))

    @field_validator("scene_depth_m")
    @classmethod
    def _ordered_depths(cls, v):
        if v is not None and not 0 < v[0] <= v[1] <= v[2]:
            raise ValueError(f"scene_depth_m must be positive depths (p1 <= median <= p99), got {v}")
        return v

    @field_validator("distortion")
    @classmethod
    def _opencv_length(cls, v):
        if len(v) not in (5, 8):
            raise ValueError(f"distortion holds OpenCV's 5 or 8 coefficients, got {len(v)}")
        return v

    @field_validator("world_to_camera")
    @classmethod
    def _is_rigid(cls, v):
        if v is None:
            return v
        m = np.asarray(v, np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"world_to_camera must be 4x4, got {m.shape}")
        R = m[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("world_to_camera rotation is not a proper rotation")
        if not np.allclose(m[3], [0, 0, 0, 1]):
            raise ValueError("world_to_camera last row must be 0 0 0 1")
        return v


class Calibration(Record):
    """A capture's calibration (consumed by Poly4DGS training through :func:`camera_at`)."""

    kind: ClassVar[str] = "calibration"
    capture: str = Field(description="name of the calibrated capture")
    frame_count: int = Field(gt=0)
    fps: float = Field(gt=0)
    reference_frame: int = Field(ge=0, description="take index the static cameras were calibrated on")
    stage_size_m: tuple[float, float, float]
    cameras: tuple[CameraCalibration, ...]
    tracking_frames: ArtifactRef | None = Field(
        default=None, description="safetensors blob of the tracking cameras' per-frame arrays")
    stats: dict[str, float] = Field(default_factory=dict)
    unregistered: dict[str, str] = Field(
        default_factory=dict, description="capture cameras left out of the calibration (the user allowed it), "
        "with the reason; training leaves them out")
    warnings: tuple[str, ...] = Field(
        default=(), description="what a user of the calibration must know, one line each: a step that did not "
        "run and why (a setting turned it off, or it had nothing to work on), a camera whose stated sigma "
        "cannot be trusted and why")

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler: SerializerFunctionWrapHandler):
        # a calibration without warnings serialises (and digests) as before they existed
        return omit_unset(handler(self), ("warnings",))

    def camera(self, camera_id: str) -> CameraCalibration:
        for c in self.cameras:
            if c.id == camera_id:
                return c
        raise KeyError(f"calibration of {self.capture} has no camera {camera_id!r}")

    @property
    def static_ids(self) -> list[str]:
        return [c.id for c in self.cameras if c.static]

    @property
    def tracking_ids(self) -> list[str]:
        return [c.id for c in self.cameras if not c.static]


@dataclass(frozen=True)
class TrackingFrames:
    """Per-frame arrays of one tracking camera: ``intrinsics`` [T, 4] (fx, fy, cx, cy) and
    ``world_to_camera`` [T, 4, 4], float64; ``distortion`` [T, 5] or [T, 8] (OpenCV's distCoeffs of
    each frame's lens) or None (pinhole frames)."""

    intrinsics: np.ndarray
    world_to_camera: np.ndarray
    distortion: np.ndarray | None = None


#: the tracking-frames blob's formats: 1 without distortion, 2 with per-frame distortion
TRACKING_FRAMES_FORMATS = ("volcap-tracking-frames/1", "volcap-tracking-frames/2")


def encode_tracking_frames(frames: Mapping[str, TrackingFrames]) -> bytes:
    """Tracking cameras' per-frame arrays -> safetensors bytes (deterministic: sorted keys). Format
    ``/1`` when no camera has distortion (the bytes written before it existed), else ``/2``."""
    tensors: dict[str, np.ndarray] = {}
    for cid in sorted(frames):
        f = frames[cid]
        intr = np.ascontiguousarray(np.asarray(f.intrinsics, np.float64))
        w2c = np.ascontiguousarray(np.asarray(f.world_to_camera, np.float64))
        if intr.ndim != 2 or intr.shape[1] != 4 or w2c.shape != (len(intr), 4, 4):
            raise ValueError(f"camera {cid}: intrinsics must be [T, 4] and world_to_camera [T, 4, 4], "
                             f"got {intr.shape} and {w2c.shape}")
        if not (np.isfinite(intr).all() and np.isfinite(w2c).all()):
            raise ValueError(f"camera {cid}: non-finite values")
        tensors[f"{cid}/intrinsics"] = intr
        tensors[f"{cid}/world_to_camera"] = w2c
        if f.distortion is not None:
            tensors[f"{cid}/distortion"] = _checked_distortion(cid, f.distortion, len(intr))
    fmt = TRACKING_FRAMES_FORMATS[1 if any(k.endswith("/distortion") for k in tensors) else 0]
    return st_save(tensors, metadata={"format": fmt})


def _checked_distortion(cid: str, d, T: int) -> np.ndarray:
    d = np.ascontiguousarray(np.asarray(d, np.float64))
    if d.ndim != 2 or d.shape[0] != T or d.shape[1] not in (5, 8):
        raise ValueError(f"camera {cid}: distortion must be [T, 5] or [T, 8] (OpenCV's distCoeffs per frame, "
                         f"T = {T}), got {d.shape}")
    if not np.isfinite(d).all():
        raise ValueError(f"camera {cid}: non-finite distortion")
    return d


def _blob_format(data: bytes) -> str | None:
    import json

    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + n])
    return (header.get("__metadata__") or {}).get("format")


def decode_tracking_frames(data: bytes) -> dict[str, TrackingFrames]:
    """Inverse of :func:`encode_tracking_frames`; refuses a blob of another format or with arrays
    that do not fit (a camera without its world_to_camera, a distortion of another length)."""
    try:
        fmt = _blob_format(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"not a tracking-frames blob: {exc}") from exc
    if fmt not in TRACKING_FRAMES_FORMATS:
        raise ValueError(f"tracking-frames blob of format {fmt!r}: this version reads "
                         f"{', '.join(TRACKING_FRAMES_FORMATS)}")
    t = st_load(data)
    out: dict[str, TrackingFrames] = {}
    for key in t:
        cid, name = key.rsplit("/", 1)
        if name == "intrinsics":
            if f"{cid}/world_to_camera" not in t:
                raise ValueError(f"tracking-frames blob: camera {cid} has no world_to_camera")
            dist = t.get(f"{cid}/distortion")
            if dist is not None:
                dist = _checked_distortion(cid, dist, len(t[key]))
            out[cid] = TrackingFrames(t[key], t[f"{cid}/world_to_camera"], dist)
    return out


def tracking_frames_ref(data: bytes) -> ArtifactRef:
    """The ref the store will give ``data`` (for records built before or without a store)."""
    from volcap_core.digest import digest_bytes

    return ArtifactRef(digest=digest_bytes(data), size=len(data), media_type=MEDIA_SAFETENSORS)


def camera_at(calibration: Calibration, camera_id: str, frame: int,
              tracking: Mapping[str, TrackingFrames] | None = None) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Camera ``camera_id`` at take index ``frame``: (K [3, 3], world_to_camera [4, 4], width, height).

    Static cameras are answered from the record alone; tracking cameras need ``tracking`` (the decoded
    blob of ``calibration.tracking_frames``). Raises ``KeyError`` for an unknown camera and
    ``IndexError`` for a frame outside ``[0, frame_count)``.
    """
    if not 0 <= frame < calibration.frame_count:
        raise IndexError(f"frame {frame} outside [0, {calibration.frame_count}) of {calibration.capture}")
    cam = calibration.camera(camera_id)
    if cam.static:
        fx, fy, cx, cy = cam.intrinsics
        w2c = np.asarray(cam.world_to_camera, np.float64)
    else:
        if tracking is None:
            raise ValueError(f"camera {camera_id} is a tracking camera: pass the decoded tracking frames "
                             f"(decode_tracking_frames of the blob {calibration.tracking_frames})")
        tf = tracking[camera_id]
        fx, fy, cx, cy = (float(v) for v in tf.intrinsics[frame])
        w2c = np.asarray(tf.world_to_camera[frame], np.float64)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return K, w2c.copy(), cam.width, cam.height


def frame_camera(calibration: Calibration, camera_id: str, frame: int,
                 tracking: Mapping[str, TrackingFrames] | None = None) -> CameraCalibration:
    """Camera ``camera_id`` at take index ``frame`` as a record camera with that frame's
    ``intrinsics``, ``distortion`` and ``world_to_camera``: what
    :func:`~volcap_core.calibration.distortion.rectify_frame` and ``rectified_valid`` take to
    rectify that frame. A static camera is returned as it is; a tracking camera needs ``tracking``
    (its distortion is that frame's lens, zeros for pinhole frames)."""
    cam = calibration.camera(camera_id)
    if cam.static:
        return cam
    K, w2c, _, _ = camera_at(calibration, camera_id, frame, tracking)
    d = tracking[camera_id].distortion
    dist = tuple(float(v) for v in d[frame]) if d is not None else cam.distortion
    return cam.model_copy(update={"intrinsics": (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])),
                                  "distortion": dist, "world_to_camera": matrix4(w2c)})


def matrix4(m: np.ndarray) -> Matrix4:
    """A 4x4 array as the record's nested tuple (floats rounded to 1e-12, re-orthonormalised)."""
    m = np.asarray(m, np.float64).copy()
    U, _, Vt = np.linalg.svd(m[:3, :3])
    m[:3, :3] = U @ Vt
    m[3] = (0.0, 0.0, 0.0, 1.0)
    return tuple(tuple(float(round(v, 12)) for v in row) for row in m)


def float_matrix(m: np.ndarray) -> tuple:
    """An array's rows as nested tuples of floats, as they are: a record field (the intermediate
    records', :mod:`~volcap_core.calibration.static_step`; unlike :func:`matrix4`, not re-orthonormalised)."""
    return tuple(tuple(float(v) for v in row) for row in np.asarray(m, np.float64))


def finite_figures(stats: Mapping, prefix: str = "") -> dict[str, float]:
    """The finite numbers of a nested stats dict, flattened to ``a.b`` keys: a record's ``stats``."""
    out: dict[str, float] = {}
    for k, v in stats.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(finite_figures(v, key + "."))
        elif isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(float(v)):
            out[key] = float(v)
    return out
