"""Capture folders on disk (what ingest reads, what ``volcap synth`` writes) and the Capture record.

On-disk layout (documented for users in ``docs/capture-layout.md``)::

    CAPTURE_DIR/
      capture.json                  CaptureDescription (below)
      <camera path>/<NNNNNN>.<ext>  one image per frame; NNNNNN = the camera's own frame number,
                                    0 at the camera's start timecode. ext: exr, dpx, tif, tiff, png
      <camera path>.mp4|mov|m4v|mkv or a camera's video file instead: its frame number n is the n-th
                                    picture decoded, 0 at the camera's start timecode
      <lidar>.ply                   optional: the rig's lidar scan of the static stage (stage frame,
                                    metres), named by ``CaptureDescription.lidar``; calibration input
      ground_truth/                 optional (synthetic captures): cameras per frame, geometry,
                                    lidar scan, colour chart; stored with the capture, never used
                                    by reconstruction, only by evaluation
      <masks>/<camera id>/<NNNNNN>.<ext>
                                    optional: performer masks, one value per pixel in [0, 1] (the
                                    performers' coverage), numbered as the camera's frames; named
                                    by ``CaptureDescription.masks``. ext: exr, png, tif, tiff

A frame's *take index* is its position in the take: ``timecode(frame) - take.start_timecode`` in
frames. Every camera must provide each take index in ``[0, take.frame_count)`` exactly once.

:class:`CaptureFolder` is the one reader of this layout: ingest, productions (before ingest), the
Face Rig pairs, tests and benchmarks open a folder with it. A folder it cannot read raises
:class:`IngestError`, whose message names the file, camera and frame.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from enum import Enum
from functools import cached_property
from pathlib import Path
from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_serializer, model_validator

from hardware.rig import Rig, load_rig
from hardware.serialization import omit_unset
from volcap_core.imageio.errors import ImageReadError
from volcap_core.imageio.read import probe_image, read_exr_native, read_image
from volcap_core.imageio.video import (
    VIDEO_EXTENSIONS,
    Matrix,
    Primaries,
    SignalRange,
    Transfer,
    VideoInfo,
    is_video_path,
    iter_video_frames,
    probe_video,
)
from volcap_core.records import ArtifactRef, Record

CAPTURE_FORMAT = "volcap-capture/1"
IMAGE_EXTENSIONS = (".exr", ".dpx", ".tif", ".tiff", ".png")
FRAME_FILE_RE = re.compile(r"^(?P<number>\d+)\.(?P<ext>exr|dpx|tif|tiff|png)$", re.IGNORECASE)
MASK_FILE_RE = re.compile(r"^(?P<number>\d+)\.(?P<ext>exr|tif|tiff|png)$", re.IGNORECASE)
TIMECODE_RE = re.compile(r"^(\d{2}):(\d{2}):(\d{2})[:;](\d{2})$")


class IngestError(ValueError):
    """A capture folder problem; the message names file, camera and frame."""


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
    video = "video"     # a video file's Y'CbCr, decoded as its ``VideoEncoding`` says (the camera's ``video``)


#: what an untagged video stream is taken to be: HD consumer and broadcast video (H.264, HEVC, VP9
#: from cameras and phones) is ITU-R BT.709 (its OETF, its Y'CbCr matrix, its primaries) in limited
#: range (8-bit Y' 16-235, Cb/Cr 16-240), as BT.709 and FFmpeg's own HD convention have it
DEFAULT_VIDEO_TRANSFER: Transfer = "bt709"
DEFAULT_VIDEO_RANGE: SignalRange = "limited"
DEFAULT_VIDEO_MATRIX: Matrix = "bt709"
DEFAULT_VIDEO_PRIMARIES: Primaries = "bt709"


class VideoEncoding(BaseModel):
    """How a camera's video file encodes light; each field None = the stream's own tag, else the
    default above. In ``capture.json`` (a camera's ``video``) it overrides the stream; in the
    Capture record (``source_video``) every field is set to what ingest used.

    ``transfer``: ``bt709`` (the BT.709 OETF, undone to scene-linear; also what BT.601 and BT.2020
    specify), ``srgb`` (IEC 61966-2-1) or ``linear``. ``range``: ``limited`` (8-bit Y' 16-235) or
    ``full`` (0-255). ``matrix``: the Y'CbCr matrix. ``primaries``: converted to the working
    primaries (Rec.709/D65) when they differ."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    transfer: Transfer | None = None
    range: SignalRange | None = None
    matrix: Matrix | None = None
    primaries: Primaries | None = None


class LensSample(BaseModel):
    """A lens-encoder reading of a tracking camera at one of its frames (camera-local number)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    frame: int = Field(ge=0)
    focal_mm: float = Field(gt=0)
    focus_m: float | None = Field(default=None, gt=0)


class CameraSource(BaseModel):
    """One camera of ``capture.json``: where its footage is and how it encodes light.

    ``path`` is a folder of frame files, or a video file (ending ``.mp4``, ``.mov``, ``.m4v``,
    ``.mkv``): its encoding is then ``video`` (the default for a video path; any other is refused)
    and ``video`` may override the stream's colour tags (:class:`VideoEncoding`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str
    path: str = Field(description="folder of this camera's frames, or its video file, relative to the capture folder")
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
    video: VideoEncoding | None = Field(default=None, description="a video camera's transfer, range, matrix "
                                                                  "and primaries, overriding the stream's tags")

    @model_validator(mode="before")
    @classmethod
    def _video_path_is_video(cls, data):
        if isinstance(data, dict) and "encoding" not in data and is_video_path(str(data.get("path", ""))):
            data = {**data, "encoding": Encoding.video}
        return data

    @model_serializer(mode="wrap")
    def _without_absent_video(self, handler):
        # a camera without video settings serialises as it did before the field existed, so the
        # cache keys of image-sequence ingests stay what they were
        return omit_unset(handler(self), ("video",))

    @property
    def is_video(self) -> bool:
        return self.encoding is Encoding.video

    @model_validator(mode="after")
    def _check(self) -> "CameraSource":
        if self.encoding is Encoding.ocio and not self.ocio_colorspace:
            raise ValueError(f"camera {self.id}: encoding 'ocio' needs 'ocio_colorspace'")
        video_path = is_video_path(self.path)
        if video_path != (self.encoding is Encoding.video):
            raise ValueError(f"camera {self.id}: path {self.path!r} is "
                             + ("a video file, its encoding must be 'video' (or left out)" if video_path else
                                f"not a video file ({', '.join(VIDEO_EXTENSIONS)}); encoding 'video' needs one"))
        if self.video is not None and not video_path:
            raise ValueError(f"camera {self.id}: 'video' settings need a video file path")
        if video_path and (self.exr_part or self.exr_view):
            raise ValueError(f"camera {self.id}: exr_part/exr_view do not apply to a video file")
        if self.path.startswith("/") or ".." in self.path.split("/"):
            raise ValueError(f"camera {self.id}: path {self.path!r} must stay inside the capture folder")
        return self


def video_encoding(camera: CameraSource, info: VideoInfo) -> VideoEncoding:
    """How ``camera``'s video is decoded, every field set: its ``video`` override, else the stream's
    tag, else the default (:data:`DEFAULT_VIDEO_TRANSFER` …). FFmpeg's ``yuvj*`` formats are full
    range. :class:`IngestError` when the stream is tagged with something volcap does not decode
    and the capture does not override it."""
    override = camera.video or VideoEncoding()
    tag_range = "full" if info.full_range_format else info.tag_range
    chosen = {}
    for name, tag, default in (("transfer", info.tag_transfer, DEFAULT_VIDEO_TRANSFER),
                               ("range", tag_range, DEFAULT_VIDEO_RANGE),
                               ("matrix", info.tag_matrix, DEFAULT_VIDEO_MATRIX),
                               ("primaries", info.tag_primaries, DEFAULT_VIDEO_PRIMARIES)):
        value = getattr(override, name)
        if value is None and tag is not None and tag.startswith("unsupported:"):
            raise IngestError(f"camera {camera.id}: {info.path} is tagged with {tag.split(':', 1)[1]}, which "
                              f"volcap does not decode; set \"video\": {{\"{name}\": ...}} in its capture.json "
                              "entry if the footage is in fact one of the supported encodings")
        chosen[name] = value if value is not None else tag if tag is not None else default
    return VideoEncoding(**chosen)


class Take(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    start_timecode: str
    frame_count: int = Field(gt=0)


class Performer(BaseModel):
    """Whose actor a capture films: actor ``actor`` of the capture named ``capture``. A Face Rig
    capture of a Scene Rig performer says so, so a production can check that an actor's face
    capture is of that actor (``docs/production-spec.md``). ``actor`` is the actor's index in
    that capture's ground truth (``ground_truth/scene.json`` ``actors``) for synthetic captures,
    the capture's own numbering otherwise."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    capture: str = Field(pattern=r"^[A-Za-z0-9_.-]+$", description="the capture's name (its capture.json 'name')")
    actor: int = Field(ge=0, description="the actor's index in that capture")


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
    performer: Performer | None = Field(default=None, description="whose actor the capture films (a Face Rig "
                                                                   "capture of a Scene Rig capture's actor)")
    masks: str | None = Field(default=None, description="performer masks: a folder, relative path, holding "
                                                        "<camera id>/<frame number>.exr|png|tif|tiff")

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler):
        # a capture that names no performer or masks serialises as it did before the fields existed
        return omit_unset(handler(self), ("performer", "masks"))

    @model_validator(mode="after")
    def _check(self) -> "CaptureDescription":
        if self.format != CAPTURE_FORMAT:
            raise ValueError(f"unsupported capture format {self.format!r} (expected {CAPTURE_FORMAT})")
        for what, path in (("lidar", self.lidar), ("masks", self.masks)):
            if path is not None and (path.startswith("/") or ".." in path.split("/")):
                raise ValueError(f"{what} path {path!r} must stay inside the capture folder")
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
    #: a video camera's decoding as used (every field set); None for image files, and then left
    #: out of the record's JSON, so records of image-sequence captures keep their bytes
    source_video: VideoEncoding | None = None
    #: performer masks, ``masks[i]`` at take index ``i``: one-channel (``Y``) half EXRs of
    #: ``width``×``height``, coverage in [0, 1]; None when the capture has none for this camera
    #: (then left out of the record's JSON, so records of captures without masks keep their bytes)
    masks: tuple[ArtifactRef, ...] | None = None

    @model_serializer(mode="wrap")
    def _without_absent_video(self, handler):
        return omit_unset(handler(self), ("source_video", "masks"))


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
    #: whose actor the capture films, as capture.json says (None: it does not say; then left out
    #: of the record's JSON, so records of captures without it keep their bytes)
    performer: Performer | None = None

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler):
        return omit_unset(handler(self), ("performer",))

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


@dataclass(frozen=True)
class CaptureFolder:
    """A capture folder (the layout above) opened: its ``capture.json`` parsed and its rig loaded
    (:func:`hardware.rig.load_rig`, a rig file relative to the folder); each camera's frame files
    listed when first asked for. Nothing is decoded until :meth:`load`.
    """

    root: Path
    description: CaptureDescription
    rig: Rig
    _files: dict[str, dict[int, Path]] = field(default_factory=dict, repr=False, compare=False)
    _videos: dict[str, VideoInfo] = field(default_factory=dict, repr=False, compare=False)
    _masks: dict[str, dict[int, Path]] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def open(cls, root: str | Path) -> "CaptureFolder":
        """Read ``root/capture.json`` and its rig; :class:`IngestError` when either is missing or
        invalid."""
        root = Path(root)
        path = root / "capture.json"
        if not path.is_file():
            raise IngestError(f"{path}: no capture description (capture.json) in {root}")
        try:
            desc = CaptureDescription.model_validate_json(path.read_bytes())
        except ValueError as exc:
            raise IngestError(f"{path}: invalid capture description: {exc}") from exc
        try:
            rig = load_rig(desc.rig, root)
        except ValueError as exc:
            raise IngestError(f"{path}: {exc}") from exc
        return cls(root, desc, rig)

    @property
    def description_path(self) -> Path:
        return self.root / "capture.json"

    @property
    def name(self) -> str:
        return self.description.name

    @property
    def fps(self) -> float:
        return self.description.fps

    @property
    def frame_count(self) -> int:
        """Frames in the take."""
        return self.description.take.frame_count

    @property
    def camera_ids(self) -> list[str]:
        """The cameras ``capture.json`` lists, in its order (a subset of the rig's)."""
        return [c.id for c in self.description.cameras]

    def camera(self, camera_id: str) -> CameraSource:
        for cam in self.description.cameras:
            if cam.id == camera_id:
                return cam
        raise KeyError(f"capture {self.name} has no camera {camera_id!r} (it has {', '.join(self.camera_ids)})")

    @cached_property
    def offsets(self) -> dict[str, int]:
        """Camera id → take index of its frame number 0 (:meth:`CaptureDescription.take_offset`)."""
        return {c.id: self.description.take_offset(c) for c in self.description.cameras}

    @cached_property
    def encoder(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Lens-encoder readings of the cameras that have them: camera id → (take indices ``[S]``
        int64, focal ``[S]`` float64 mm), every reading as listed, re-indexed to take indices."""
        out = {}
        for c in self.description.cameras:
            if c.lens_encoder:
                out[c.id] = (np.array([s.frame + self.offsets[c.id] for s in c.lens_encoder], np.int64),
                             np.array([s.focal_mm for s in c.lens_encoder], np.float64))
        return out

    @property
    def lidar_path(self) -> Path | None:
        """The lidar scan file ``capture.json`` names (PLY bytes; not checked here), None without one."""
        return self.root / self.description.lidar if self.description.lidar is not None else None

    @property
    def ground_truth_path(self) -> Path | None:
        """The ground-truth folder ``capture.json`` names (synthetic captures), None without one."""
        gt = self.description.ground_truth
        return self.root / gt if gt else None

    @property
    def masks_path(self) -> Path | None:
        """The performer masks folder ``capture.json`` names, None without one."""
        m = self.description.masks
        return self.root / m if m else None

    @cached_property
    def mask_cameras(self) -> list[str]:
        """The cameras that have performer masks (a ``<masks>/<camera id>/`` folder), in
        ``capture.json``'s order; empty when the capture names no masks folder. Refuses a named
        folder that does not exist and a sub-folder (or file) that is no listed camera's: a
        misspelt camera id would otherwise drop its masks unnoticed."""
        folder = self.masks_path
        if folder is None:
            return []
        if not folder.is_dir():
            raise IngestError(f"{self.description_path}: masks folder {folder} does not exist")
        ids = set(self.camera_ids)
        found = set()
        for p in sorted(folder.iterdir()):
            if p.name.startswith("."):
                continue
            if not p.is_dir() or p.name not in ids:
                raise IngestError(f"masks: unexpected {'folder' if p.is_dir() else 'file'} {p} (the masks "
                                  f"folder holds one folder per camera, named by its id: {', '.join(self.camera_ids)})")
            found.add(p.name)
        return [c for c in self.camera_ids if c in found]

    def mask_files(self, camera_id: str) -> dict[int, Path] | None:
        """A camera's performer mask files by take index (numbered as its frames: the camera's own
        frame number, ``offsets`` apply), resolved; None when the camera has no masks. Refuses an
        empty folder, a file not named as a frame and two files of one frame number."""
        if camera_id in self._masks:
            return self._masks[camera_id]
        self.camera(camera_id)
        if camera_id not in self.mask_cameras:
            return None
        folder = self.masks_path / camera_id
        offset = self.offsets[camera_id]
        by_index: dict[int, Path] = {}
        for p in sorted(folder.iterdir()):
            if p.name.startswith("."):
                continue
            m = MASK_FILE_RE.match(p.name)
            if p.is_dir() or not m:
                raise IngestError(f"camera {camera_id}: unexpected file {p} (masks are named NNNNNN.exr|png|tif|tiff, "
                                  "the camera's frame number)")
            number = int(m["number"])
            if number + offset in by_index:
                raise IngestError(f"camera {camera_id}: mask of frame {number} is duplicated: "
                                  f"{by_index[number + offset]} and {p}")
            by_index[number + offset] = p.resolve()
        if not by_index:
            raise IngestError(f"camera {camera_id}: no masks in {folder}")
        self._masks[camera_id] = by_index
        return by_index

    def load_mask(self, camera_id: str, take_index: int) -> np.ndarray:
        """A camera's performer mask at ``take_index`` as stored: float32 ``[H, W]`` (an EXR's one
        channel as it is, a PNG's/TIFF's integer codes / (2^bits - 1): coverage, never
        linearised). :class:`IngestError` naming file, camera and frame when there is none, or the
        file is unreadable, has other than one channel, or (EXR) its data window is not its
        display window. Values are not checked here (:func:`volcap_core.ingest.check_masks`)."""
        files = self.mask_files(camera_id)
        number = take_index - self.offsets[camera_id]
        path = files.get(take_index) if files is not None else None
        if path is None:
            raise IngestError(f"camera {camera_id}, frame {number}: no mask in "
                              f"{self.masks_path / camera_id if self.masks_path else 'the capture (no masks folder)'}")
        where = f"camera {camera_id}, frame {number}: mask {path}"
        try:
            info = probe_image(path)
            if len(info.channels) != 1:
                raise IngestError(f"{where} has channels {', '.join(info.channels)}; a mask has one "
                                  "(greyscale), the performers' coverage")
            if info.format == "exr":
                if info.parts != 1 or info.data_window != info.display_window:
                    raise IngestError(f"{where}: a mask EXR has one part whose data window is its display "
                                      f"window (it has {info.parts} part(s), data window {info.data_window}, "
                                      f"display window {info.display_window})")
                pixels, _ = read_exr_native(path)
            elif info.format in ("png", "tiff"):
                pixels, _ = read_image(path)
            else:
                raise IngestError(f"{where} is a {info.format.upper()} file; masks are EXR, PNG or TIFF")
        except ImageReadError as exc:
            raise IngestError(f"camera {camera_id}, frame {number}: {exc}") from exc
        return np.asarray(pixels[..., 0], np.float32)

    def video_info(self, camera_id: str) -> VideoInfo:
        """A video camera's file probed (:func:`volcap_core.imageio.video.probe_video`: size, frame
        count, colour tags); :class:`IngestError` naming camera and file when it is missing or
        unreadable, ``ValueError`` for a camera whose path is not a video."""
        if camera_id in self._videos:
            return self._videos[camera_id]
        cam = self.camera(camera_id)
        if not cam.is_video:
            raise ValueError(f"camera {cam.id}: {cam.path} is not a video file")
        path = self.root / cam.path
        if not path.is_file():
            raise IngestError(f"camera {cam.id}: video file {path} does not exist")
        try:
            info = probe_video(path.resolve())
        except ImageReadError as exc:
            raise IngestError(f"camera {cam.id}: {exc}") from exc
        self._videos[camera_id] = info
        return info

    def frame_files(self, camera_id: str) -> dict[int, Path]:
        """Every frame file of a camera by take index (some may lie outside the take), resolved.
        A video camera's frames all map to its video file (its frame number ``n`` at take index
        ``n + offset``, for every frame the file holds).

        Refuses a missing or empty camera folder, a file not named as a frame and two files of one
        frame number (``000012.exr`` and ``12.exr``)."""
        if camera_id in self._files:
            return self._files[camera_id]
        cam = self.camera(camera_id)
        if cam.is_video:
            info = self.video_info(camera_id)
            offset = self.offsets[cam.id]
            self._files[camera_id] = {n + offset: info.path for n in range(info.frame_count)}
            return self._files[camera_id]
        folder = self.root / cam.path
        if not folder.is_dir():
            raise IngestError(f"camera {cam.id}: folder {folder} does not exist")
        offset = self.offsets[cam.id]
        by_index: dict[int, Path] = {}
        for p in sorted(folder.iterdir()):
            if p.name.startswith(".") or p.is_dir():
                continue
            m = FRAME_FILE_RE.match(p.name)
            if not m:
                raise IngestError(f"camera {cam.id}: unexpected file {p} (frames are named NNNNNN.exr|dpx|tif|tiff|png)")
            number = int(m["number"])
            take_index = number + offset
            if take_index in by_index:
                raise IngestError(f"camera {cam.id}: frame {number} is duplicated: {by_index[take_index]} and {p}")
            by_index[take_index] = p.resolve()
        if not by_index:
            raise IngestError(f"camera {cam.id}: no frames in {folder}")
        self._files[camera_id] = by_index
        return by_index

    def frame_path(self, camera_id: str, take_index: int) -> Path:
        """The file of a camera's frame at ``take_index``; ``FileNotFoundError`` when it has none."""
        path = self.frame_files(camera_id).get(take_index)
        if path is None:
            folder = self.root / self.camera(camera_id).path
            raise FileNotFoundError(f"{folder}: no frame {take_index - self.offsets[camera_id]:06d} "
                                    f"(take index {take_index})")
        return path

    def load(self, camera_id: str, take_index: int) -> np.ndarray:
        """A camera's frame at ``take_index`` as stored, not converted: float32 ``[H, W, 3]`` R,G,B
        of the file's first part (:func:`volcap_core.imageio.read_image`). Scene-linear for linear
        footage, as synthetic captures are; ingest converts every other encoding. A video camera's
        frame is decoded (from the start of the file) to non-linear R'G'B' with its range and matrix
        (:func:`video_encoding`), its transfer function not undone."""
        path = self.frame_path(camera_id, take_index)
        cam = self.camera(camera_id)
        if cam.is_video:
            info = self.video_info(camera_id)
            enc = video_encoding(cam, info)
            try:
                for _, rgb in iter_video_frames(info, take_index - self.offsets[camera_id], 1,
                                                signal_range=enc.range, matrix=enc.matrix):
                    return rgb
            except ImageReadError as exc:
                raise IngestError(f"camera {cam.id}: {exc}") from exc
        img, _ = read_image(path)
        return np.asarray(img[..., :3], np.float32)
