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
from typing import Mapping

from hardware.rig import Rig
from volcap_core.calibration.assemble import build_record, tracking_blob
from volcap_core.calibration.inputs import EncoderReadings, FrameSource, split_cameras
from volcap_core.calibration.lidar import LidarScan
from volcap_core.calibration.record import Calibration
from volcap_core.calibration.scale import KnownPoints
from volcap_core.calibration.static import StaticCalibration, StaticCalibrationOptions
from volcap_core.calibration.static_step import calibrate_static_step
from volcap_core.calibration.tracking.observe import StaticReference
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.calibration.tracking.solve import TrackingSolution
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

