"""The whole calibration of one capture as one pure function (the task layer wraps it).

Inputs are plain values: a frame source ``load(camera_id, take_index) -> linear RGB [H, W, 3]``
(lazy, so a task can decode EXRs from the store one at a time), the rig, the lens-encoder readings
re-indexed to take indices, and the lidar scan. Outputs: the :class:`Calibration` record (with the
ref its tracking blob will have), the blob's bytes, and the intermediate results for reports.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from hardware.rig import Rig
from volcap_core.calibration.assemble import build_record, tracking_blob
from volcap_core.calibration.lidar import LidarScan
from volcap_core.calibration.record import Calibration
from volcap_core.calibration.scale import KnownPoints
from volcap_core.calibration.static import StaticCalibration, StaticCalibrationOptions
from volcap_core.calibration.static_step import calibrate_static_step
from volcap_core.calibration.tracking import (StaticReference, TrackingOptions, TrackingSolution,
                                              calibrate_tracking_cameras, zoom_lens)
from volcap_core.calibration.tracking_step import check_tracking_support

FrameSource = Callable[[str, int], np.ndarray]


@dataclass(frozen=True)
class CalibrationOptions:
    """Options of a whole calibration: the static step's (frames, SfM, adjustments) and the
    tracking step's."""

    static: StaticCalibrationOptions = StaticCalibrationOptions()
    tracking: TrackingOptions = TrackingOptions()


@dataclass
class CalibrationResult:
    record: Calibration
    tracking_bytes: bytes | None
    static: StaticCalibration
    tracking: dict[str, TrackingSolution]
    reference: StaticReference | None
    stats: dict = field(default_factory=dict)


def calibrate_capture(load: FrameSource, rig: Rig, camera_ids: list[str], frame_count: int, fps: float, *,
                      capture_name: str, encoder: Mapping[str, tuple[np.ndarray, np.ndarray]],
                      scan: LidarScan | None, options: CalibrationOptions = CalibrationOptions(),
                      known_points: KnownPoints | None = None) -> CalibrationResult:
    """Calibrate every camera of a capture.

    ``camera_ids``: the capture's cameras (their roles come from the rig); ``encoder``: tracking camera
    id -> (take indices [S], focal mm [S]). Tracking cameras are skipped (with a note in ``stats``)
    when the capture has none. ``known_points``: marked scene points and their measured distances
    (``volcap calibrate --known-points``): without a scan the static calibration is scaled to them,
    with one they are only checked; checked and applied by the static step exactly as the
    ``calibrate-static`` task does (:func:`~volcap_core.calibration.static_step.calibrate_static_step`).
    Raises :class:`~volcap_core.calibration.errors.CalibrationInputError` naming the capture (and the
    point and camera) on input that cannot be calibrated.
    """
    t0 = time.perf_counter()
    statics = [c for c in camera_ids if not rig.camera(c).role.tracks]
    trackers = [c for c in camera_ids if rig.camera(c).role.tracks]
    step = calibrate_static_step(capture_name, rig, statics, trackers, frame_count, load, scan, options.static,
                                 known_points)
    static, reference, ref_frame = step.calibration, step.reference, step.reference_frame
    t2 = time.perf_counter()
    stats: dict = {"time_static_s": t2 - t0}  # frames are loaded inside the static step
    tracking: dict[str, TrackingSolution] = {}
    blob = None
    if trackers:
        frames = {c: [load(c, t) for t in range(frame_count)] for c in trackers}
        ppm = {c: rig.camera(c).sensor.width_px / rig.camera(c).sensor.width_mm for c in trackers}
        mounts = {c: np.asarray(rig.camera(c).mount.position_m, np.float64) for c in trackers}
        lenses = {c: zoom_lens(rig.zoom_intrinsics(c)) for c in trackers}   # zoom lens tables (own or group's)
        tracking = calibrate_tracking_cameras(frames, encoder, ppm, mounts, reference, options.tracking, lenses)
        # the tasks' check: an unsupported camera is an error, or left out and listed
        tracking = {c: check_tracking_support(capture_name, c, v, options.tracking) for c, v in tracking.items()}
        blob = tracking_blob(tracking)
    else:
        stats["tracking"] = "skipped: the capture has no tracking cameras"
    stats["time_tracking_s"] = time.perf_counter() - t2
    record = build_record(capture_name, rig, static, tracking, frame_count, fps, ref_frame, blob)
    stats["time_total_s"] = time.perf_counter() - t0
    return CalibrationResult(record, blob, static, tracking, reference, stats)


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
