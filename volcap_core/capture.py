"""Capture folders on disk (what ingest reads, what ``volcap synth`` writes) and the Capture record.

On-disk layout (documented for users in ``docs/capture-layout.md``)::

    CAPTURE_DIR/
      capture.json                  CaptureDescription (below)
      <camera path>/<NNNNNN>.<ext>  one image per frame; NNNNNN = the camera's own frame number,
                                    0 at the camera's start timecode. ext: exr, dpx, tif, tiff, png
      <lidar>.ply                   optional: the rig's lidar scan of the static stage (stage frame,
                                    metres), named by ``CaptureDescription.lidar``; calibration input
      ground_truth/                 optional (synthetic captures): cameras per frame, geometry,
                                    lidar scan, colour chart; stored with the capture, never used
                                    by reconstruction, only by evaluation

A frame's *take index* is its position in the take: ``timecode(frame) - take.start_timecode`` in
frames. Every camera must provide each take index in ``[0, take.frame_count)`` exactly once.
"""

from __future__ import annotations

import re
from enum import Enum
from typing import ClassVar

from pydantic import BaseModel, ConfigDict, Field, model_validator

from hardware.rig import Rig
from volcap_core.records import ArtifactRef, Record

CAPTURE_FORMAT = "volcap-capture/1"
IMAGE_EXTENSIONS = (".exr", ".dpx", ".tif", ".tiff", ".png")
FRAME_FILE_RE = re.compile(r"^(?P<number>\d+)\.(?P<ext>exr|dpx|tif|tiff|png)$", re.IGNORECASE)
TIMECODE_RE = re.compile(r"^(\d{2}):(\d{2}):(\d{2})[:;](\d{2})$")


def timecode_to_frames(timecode: str, fps: float) -> int:
    """``HH:MM:SS:FF`` (non-drop-frame) at integer ``fps`` → frames since midnight."""
    m = TIMECODE_RE.match(timecode)
    if not m:
        raise ValueError(f"timecode {timecode!r} is not HH:MM:SS:FF")
    if abs(fps - round(fps)) > 1e-9:
        raise ValueError(f"timecodes need an integer frame rate, got {fps}")
    rate = int(round(fps))
    h, mi, s, f = (int(g) for g in m.groups())
    if mi >= 60 or s >= 60 or f >= rate:
        raise ValueError(f"timecode {timecode!r} is out of range at {rate} fps")
    return ((h * 60 + mi) * 60 + s) * rate + f


def frames_to_timecode(frames: int, fps: float) -> str:
    rate = int(round(fps))
    f = frames % rate
    s = frames // rate
    return f"{s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}:{f:02d}"


class Encoding(str, Enum):
    """How a camera's files encode light. Ingest converts all of them to scene-linear."""

    linear = "linear"   # scene-linear already (EXR from a debayer to linear)
    srgb = "srgb"       # IEC 61966-2-1 transfer function (8/16-bit PNG, TIFF)
    ocio = "ocio"       # a camera log curve, converted by an OpenColorIO config (``ocio_colorspace``)


class LensSample(BaseModel):
    """A lens-encoder reading of a tracking camera at one of its frames (camera-local number)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    frame: int = Field(ge=0)
    focal_mm: float = Field(gt=0)
    focus_m: float | None = Field(default=None, gt=0)


class CameraSource(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str
    path: str = Field(description="folder of this camera's frames, relative to the capture folder")
    start_timecode: str = Field(description="timecode of the camera's frame number 0")
    encoding: Encoding = Encoding.linear
    ocio_colorspace: str | None = None
    lens_encoder: list[LensSample] | None = None
    # Which picture of a multi-part / multi-view EXR is this camera's footage (by name: files are
    # refused rather than read as their first part or default view). Here, not on the rig camera:
    # how footage is packed is a property of the delivered files, like ``encoding``, and two
    # cameras of a stereo pair may share one folder of two-view files.
    exr_part: str | None = Field(default=None, min_length=1,
                                 description="EXR part name (the part's 'name' attribute) holding this camera")
    exr_view: str | None = Field(default=None, min_length=1,
                                 description="EXR view name ('multiView' / a part's 'view') holding this camera")

    @model_validator(mode="after")
    def _ocio_needs_colorspace(self) -> "CameraSource":
        if self.encoding is Encoding.ocio and not self.ocio_colorspace:
            raise ValueError(f"camera {self.id}: encoding 'ocio' needs 'ocio_colorspace'")
        if self.path.startswith("/") or ".." in self.path.split("/"):
            raise ValueError(f"camera {self.id}: path {self.path!r} must stay inside the capture folder")
        return self


class Take(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    start_timecode: str
    frame_count: int = Field(gt=0)


class CaptureDescription(BaseModel):
    """``capture.json``: what a capture folder holds."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    format: str = CAPTURE_FORMAT
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    rig: str = Field(description="built-in rig name, or a rig JSON file relative to the capture folder")
    fps: float = Field(gt=0)
    take: Take
    cameras: list[CameraSource]
    ocio_config: str | None = Field(default=None, description="OpenColorIO config, relative path")
    ground_truth: str | None = Field(default=None, description="ground-truth folder, relative path")
    lidar: str | None = Field(default=None, description="lidar scan of the static stage: a PLY file, relative "
                                                        "path (stage frame, metres); calibration input")

    @model_validator(mode="after")
    def _check(self) -> "CaptureDescription":
        if self.format != CAPTURE_FORMAT:
            raise ValueError(f"unsupported capture format {self.format!r} (expected {CAPTURE_FORMAT})")
        if self.lidar is not None and (self.lidar.startswith("/") or ".." in self.lidar.split("/")):
            raise ValueError(f"lidar path {self.lidar!r} must stay inside the capture folder")
        seen: set[str] = set()
        for cam in self.cameras:
            if cam.id in seen:
                raise ValueError(f"camera {cam.id} is listed twice")
            seen.add(cam.id)
            timecode_to_frames(cam.start_timecode, self.fps)
        timecode_to_frames(self.take.start_timecode, self.fps)
        return self

    def take_offset(self, camera: CameraSource) -> int:
        """Take index of the camera's frame number 0 (negative when it started before the take)."""
        return (timecode_to_frames(camera.start_timecode, self.fps)
                - timecode_to_frames(self.take.start_timecode, self.fps))


class CaptureCamera(BaseModel):
    """One camera of an ingested capture. ``frames[i]`` is take index ``i``: a half-float,
    scene-linear EXR in the working space (linear Rec.709/D65) with channels ``channels``
    (``R,G,B`` or ``R,G,B,A``), ``width``×``height`` = the source's display window.

    ``source_part``/``source_view``: the EXR part name and view the frames were taken from (None:
    the file had no part name / no views). ``source_chromaticities``: the primaries and white the
    files declared (None: none declared, i.e. Rec.709/D65), converted to the working space."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str
    width: int
    height: int
    channels: tuple[str, ...]
    source_encoding: Encoding
    frames: tuple[ArtifactRef, ...]
    lens_encoder: tuple[LensSample, ...] | None = Field(
        default=None, description="readings re-indexed to take indices")
    # defaults: records written before these fields existed load as "no part, no view, Rec.709"
    source_part: str | None = None
    source_view: str | None = None
    source_chromaticities: tuple[float, float, float, float, float, float, float, float] | None = None


class Capture(Record):
    """An ingested capture: every frame scene-linear in the store, plus what describes them."""

    kind: ClassVar[str] = "capture"
    name: str
    rig: Rig
    fps: float
    start_timecode: str
    frame_count: int
    cameras: tuple[CaptureCamera, ...]
    ground_truth: ArtifactRef | None = None
    #: the lidar scan of the static stage (PLY bytes as captured): what calibration registers to
    lidar: ArtifactRef | None = None

    def camera(self, camera_id: str) -> CaptureCamera:
        for cam in self.cameras:
            if cam.id == camera_id:
                return cam
        raise KeyError(f"capture {self.name} has no camera {camera_id!r}")

    def take_range(self, frames: tuple[int, int] | None = None) -> tuple[int, int]:
        """``frames`` as take indices ``[a, b)`` checked against the take (the whole take when None)."""
        a, b = frames if frames is not None else (0, self.frame_count)
        if not 0 <= a < b <= self.frame_count:
            raise ValueError(f"frames {a}:{b} outside capture {self.name}'s [0, {self.frame_count})")
        return a, b

    def frame_time(self, index: int) -> float:
        """Seconds since the take start for take index ``index``."""
        return index / self.fps
