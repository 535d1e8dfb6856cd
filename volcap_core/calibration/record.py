"""Calibration and point-cloud records: what calibration produces and Poly4DGS training consumes.

Conventions: OpenCV pinhole. Pixel coordinates have the centre of the top-left pixel at (0, 0)
(add 0.5 to cx, cy for COLMAP/gsplat's "+0.5" pixel centres), world-to-camera poses map stage
coordinates (metres, z up) to camera coordinates (x right, y down, z forward). Distortion is
OpenCV's (k1, k2, p1, p2).

Per-frame arrays are kept out of the JSON record (180 cameras × 1000s of frames) in one
safetensors blob: ``K`` [C, F, 3, 3], ``world_to_camera`` [C, F, 4, 4], ``distortion`` [C, F, 4],
float64, camera order as in the record. Static cameras repeat one value over F.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict

from volcap_core.records import ArtifactRef, Record

CALIBRATION_ARRAYS_MEDIA = "application/vnd.volcap.calibration-arrays+safetensors"
POINTS_MEDIA = "application/vnd.volcap.points+safetensors"


class CalibratedCamera(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str
    width: int
    height: int
    static: bool


class Calibration(Record):
    """Every camera of a capture at every take frame."""

    kind: ClassVar[str] = "calibration"
    capture: ArtifactRef
    frame_count: int
    cameras: tuple[CalibratedCamera, ...]
    arrays: ArtifactRef  # safetensors: K, world_to_camera, distortion (see module docstring)
    source: Literal["estimated", "ground_truth"] = "estimated"
    metrics: dict[str, float] | None = None

    def camera_index(self, camera_id: str) -> int:
        for i, c in enumerate(self.cameras):
            if c.id == camera_id:
                return i
        raise KeyError(f"calibration has no camera {camera_id!r}")


@dataclass(frozen=True)
class CalibrationArrays:
    """Decoded per-frame arrays; ``K`` [C, F, 3, 3], ``world_to_camera`` [C, F, 4, 4],
    ``distortion`` [C, F, 4] (float64)."""

    K: np.ndarray
    world_to_camera: np.ndarray
    distortion: np.ndarray

    def __post_init__(self) -> None:
        c, f = self.K.shape[:2]
        if self.K.shape != (c, f, 3, 3) or self.world_to_camera.shape != (c, f, 4, 4) \
                or self.distortion.shape != (c, f, 4):
            raise ValueError(f"inconsistent calibration arrays: K {self.K.shape}, "
                             f"world_to_camera {self.world_to_camera.shape}, distortion {self.distortion.shape}")


def encode_calibration_arrays(arrays: CalibrationArrays) -> bytes:
    from safetensors.numpy import save

    return save({"K": np.ascontiguousarray(arrays.K, np.float64),
                 "world_to_camera": np.ascontiguousarray(arrays.world_to_camera, np.float64),
                 "distortion": np.ascontiguousarray(arrays.distortion, np.float64)})


def decode_calibration_arrays(data: bytes) -> CalibrationArrays:
    from safetensors.numpy import load

    t = load(data)
    return CalibrationArrays(t["K"], t["world_to_camera"], t["distortion"])


def camera_at(calibration: Calibration, arrays: CalibrationArrays, camera_id: str,
              frame: int) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(K [3, 3], world_to_camera [4, 4], width, height) of a camera at a take index."""
    i = calibration.camera_index(camera_id)
    if not 0 <= frame < calibration.frame_count:
        raise IndexError(f"frame {frame} outside the calibration's [0, {calibration.frame_count})")
    cam = calibration.cameras[i]
    return arrays.K[i, frame], arrays.world_to_camera[i, frame], cam.width, cam.height


class PointCloudFrame(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    frame: int          # take index
    time: float         # seconds on the take's clock (frame / fps)
    count: int
    points: ArtifactRef  # safetensors: xyz [N, 3] float32 metres, rgb [N, 3] float32 linear


class PointCloudSequence(Record):
    """Dense per-frame points (Poly4DGS initialises one Gaussian per point)."""

    kind: ClassVar[str] = "point-cloud-sequence"
    calibration: ArtifactRef
    frames: tuple[PointCloudFrame, ...]
    method: str

    def at(self, frame: int) -> PointCloudFrame:
        for f in self.frames:
            if f.frame == frame:
                return f
        raise KeyError(f"no points for frame {frame}")


def encode_points(xyz: np.ndarray, rgb: np.ndarray) -> bytes:
    from safetensors.numpy import save

    if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
        raise ValueError(f"points must be xyz [N, 3] and rgb [N, 3], got {xyz.shape} and {rgb.shape}")
    return save({"xyz": np.ascontiguousarray(xyz, np.float32), "rgb": np.ascontiguousarray(rgb, np.float32)})


def decode_points(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    from safetensors.numpy import load

    t = load(data)
    return t["xyz"], t["rgb"]
