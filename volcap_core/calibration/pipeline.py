"""The whole calibration of one capture in one call: the steps the calibration tasks run, composed.

For tests, benchmarks and notebooks that hold a capture's frames rather than a store. It runs the
very step functions of the ``calibrate-static``, ``calibrate-tracking-camera`` and
``assemble-calibration`` tasks (:mod:`~volcap_core.calibration.static_step`,
:mod:`~volcap_core.calibration.tracking_step`, :mod:`~volcap_core.calibration.assemble`), the
cameras' roles split by the same :func:`~volcap_core.calibration.inputs.split_cameras`, so it
gives what ``volcap calibrate`` gives; it only keeps the library's results in memory instead of
storing records between the steps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from hardware.rig import Rig
from volcap_core.calibration.assemble import build_record, tracking_blob
from volcap_core.calibration.inputs import EncoderReadings, FrameSource, split_cameras
from volcap_core.calibration.lidar import LidarScan
from volcap_core.calibration.record import Calibration
from volcap_core.calibration.scale import KnownPoints
from volcap_core.calibration.static import StaticCalibration, StaticCalibrationOptions
from volcap_core.calibration.static_step import calibrate_static_step
from volcap_core.calibration.tracking import StaticReference, TrackingOptions, TrackingSolution
from volcap_core.calibration.tracking_step import calibrate_tracking_step


@dataclass(frozen=True)
class CalibrationOptions:
    """Options of a whole calibration: the static step's (frames, SfM, adjustments) and the
    tracking step's."""

    static: StaticCalibrationOptions = StaticCalibrationOptions()
    tracking: TrackingOptions = TrackingOptions()


@dataclass
class CalibrationResult:
    """The Calibration ``record`` and its tracking-frames blob (``tracking_bytes``, None without
    tracking cameras), with the library's results it was built from (``static``: with its sparse
    model; ``tracking``: id -> solution; ``reference``: the static reference) and ``stats``
    (``time_static_s``, ``time_tracking_s``, ``time_total_s``; ``tracking``: why that step was
    skipped)."""

    record: Calibration
    tracking_bytes: bytes | None
    static: StaticCalibration
    tracking: dict[str, TrackingSolution]
    reference: StaticReference | None
    stats: dict = field(default_factory=dict)


def calibrate_capture(load: FrameSource, rig: Rig, camera_ids: list[str], frame_count: int, fps: float, *,
                      capture_name: str, encoder: Mapping[str, EncoderReadings],
                      scan: LidarScan | None, options: CalibrationOptions = CalibrationOptions(),
                      known_points: KnownPoints | None = None) -> CalibrationResult:
    """Calibrate every camera of a capture: the static step, then the tracking step of each tracking
    camera, then the record, as the calibrate flow's tasks run them.

    ``load(camera_id, take_index) -> float32 [H, W, 3]`` linear RGB; ``camera_ids``: the capture's
    cameras (their roles come from the rig); ``encoder``: tracking camera id -> (take indices [S],
    focal mm [S]); ``scan``: the capture's lidar scan or None. Tracking cameras are skipped (with a
    note in ``stats``) when the capture has none. ``known_points``: marked scene points and their
    measured distances (``volcap calibrate --known-points``), checked and applied by the static step.
    Raises :class:`~volcap_core.calibration.errors.CalibrationInputError` naming the capture (and
    the point and camera) on input that cannot be calibrated.
    """
    t0 = time.perf_counter()
    statics, trackers = split_cameras(capture_name, rig, camera_ids)
    step = calibrate_static_step(capture_name, rig, statics, trackers, frame_count, load, scan, options.static,
                                 known_points)
    t1 = time.perf_counter()
    stats: dict = {"time_static_s": t1 - t0}  # frames are loaded inside the static step
    tracking = {c: calibrate_tracking_step(capture_name, rig, c, encoder.get(c), frame_count, load, step.reference,
                                           options.tracking) for c in trackers}
    if not trackers:
        stats["tracking"] = "skipped: the capture has no tracking cameras"
    stats["time_tracking_s"] = time.perf_counter() - t1
    blob = tracking_blob(tracking)
    record = build_record(capture_name, rig, step.calibration, tracking, frame_count, fps, step.reference_frame, blob)
    stats["time_total_s"] = time.perf_counter() - t0
    return CalibrationResult(record, blob, step.calibration, tracking, step.reference, stats)


# --------------------------------------------------------------------------- capture folders

@dataclass
class FolderCapture:
    """A capture folder (``volcap_core.capture`` layout) read directly: for tests, benchmarks and
    the demo. ``load(camera_id, take_index)`` decodes one frame (linear RGB float32 [H, W, 3])."""

    root: Path
    rig: Rig
    name: str
    fps: float
    frame_count: int
    camera_ids: list[str]
    offsets: dict[str, int]
    paths: dict[str, str]
    encoder: dict[str, tuple[np.ndarray, np.ndarray]]
    lidar_path: str | None = None

    @staticmethod
    def open(root: str | Path) -> "FolderCapture":
        import json

        from hardware.rig import load_rig
        from volcap_core.capture import CaptureDescription

        root = Path(root)
        desc = CaptureDescription.model_validate(json.loads((root / "capture.json").read_text()))
        rig_path = root / desc.rig
        rig = load_rig(rig_path if rig_path.suffix == ".json" and rig_path.exists() else desc.rig)
        offsets = {c.id: desc.take_offset(c) for c in desc.cameras}
        enc = {}
        for c in desc.cameras:
            if c.lens_encoder:
                enc[c.id] = (np.array([s.frame + offsets[c.id] for s in c.lens_encoder], np.int64),
                             np.array([s.focal_mm for s in c.lens_encoder], np.float64))
        return FolderCapture(root, rig, desc.name, desc.fps, desc.take.frame_count, [c.id for c in desc.cameras],
                             offsets, {c.id: c.path for c in desc.cameras}, enc, desc.lidar)

    def load(self, camera_id: str, take_index: int) -> np.ndarray:
        from volcap_core.imageio import read_image

        folder = self.root / self.paths[camera_id]
        n = take_index - self.offsets[camera_id]
        for ext in ("exr", "png", "tif", "tiff", "dpx"):
            p = folder / f"{n:06d}.{ext}"
            if p.exists():
                img, _ = read_image(p)
                return np.asarray(img[..., :3], np.float32)
        raise FileNotFoundError(f"{folder}: no frame {n:06d} (take index {take_index})")

    def lidar(self) -> LidarScan | None:
        """The scan ``capture.json`` names (``lidar``): an input of the capture, not ground truth."""
        if self.lidar_path is None:
            return None
        return LidarScan.from_ply_bytes((self.root / self.lidar_path).read_bytes())
