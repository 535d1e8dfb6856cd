"""Dense per-frame point clouds: the record calibration's dense stage produces and Poly4DGS
initialises from (one Gaussian per point, t0 at the point's frame time).

Per frame one safetensors blob: ``xyz`` [N, 3] float32 metres (stage frame), ``rgb`` [N, 3] float32
linear colour.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from volcap_core.records import ArtifactRef, Record

POINTS_MEDIA = "application/vnd.volcap.points+safetensors"


class PointCloudFrame(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    frame: int           # take index
    time: float          # seconds on the take's clock (frame / fps)
    count: int
    points: ArtifactRef  # safetensors: xyz, rgb


class PointCloudSequence(Record):
    kind: ClassVar[str] = "point-cloud-sequence"
    calibration: ArtifactRef
    frames: tuple[PointCloudFrame, ...]
    method: str
    stats: dict[str, float] = {}

    def at(self, frame: int) -> PointCloudFrame:
        for f in self.frames:
            if f.frame == frame:
                return f
        raise KeyError(f"point-cloud sequence has no frame {frame}")


def encode_points(xyz: np.ndarray, rgb: np.ndarray) -> bytes:
    from safetensors.numpy import save

    xyz, rgb = np.asarray(xyz), np.asarray(rgb)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
        raise ValueError(f"points must be xyz [N, 3] and rgb [N, 3], got {xyz.shape} and {rgb.shape}")
    return save({"xyz": np.ascontiguousarray(xyz, np.float32), "rgb": np.ascontiguousarray(rgb, np.float32)})


def decode_points(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    from safetensors.numpy import load

    t = load(data)
    return t["xyz"], t["rgb"]
