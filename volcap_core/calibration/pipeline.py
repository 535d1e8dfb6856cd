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
from volcap_core.calibration.lidar import LidarScan
from volcap_core.calibration.record import Calibration, CameraCalibration, matrix4, tracking_frames_ref
from volcap_core.calibration.scale import KnownPoints
from volcap_core.calibration.static import StaticCalibration, StaticCalibrationOptions
from volcap_core.calibration.steps import calibrate_static_step, check_tracking_support, tracking_blob
from volcap_core.calibration.tracking.calibrate import calibrate_tracking_cameras
from volcap_core.calibration.tracking.lens import zoom_lens
from volcap_core.calibration.tracking.observe import StaticReference
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.calibration.tracking.solve import TrackingSolution

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
    ``calibrate-static`` task does (:func:`~volcap_core.calibration.steps.calibrate_static_step`).
    Raises :class:`~volcap_core.calibration.steps.CalibrationInputError` naming the capture (and the
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


def _quality(stats: Mapping) -> dict[str, float]:
    """A camera's fit statistics as its record's ``quality``: the finite numbers, as floats."""
    return {k: float(v) for k, v in stats.items() if isinstance(v, (int, float)) and np.isfinite(v)}


def build_record(capture_name: str, rig: Rig, static: StaticCalibration, tracking: Mapping[str, TrackingSolution],
                 frame_count: int, fps: float, reference_frame: int, blob: bytes | None) -> Calibration:
    """The JSON-small record; ``blob`` (from :func:`volcap_core.calibration.steps.tracking_blob` of the
    supported cameras) gives the tracking ref. A tracking camera marked ``unsupported`` is left out
    and listed in ``unregistered`` with its reason, as a static camera the adjustment left out."""
    cams = []
    for cid in static.camera_ids:
        K = static.K[cid]
        w, h = static.size[cid]
        extra = {"scene_depth_m": static.scene_depth.get(cid)}   # where its dense points sweep
        raw = getattr(static, "raw_intrinsics", {}).get(cid)
        if raw is not None:       # a distorted lens: its intrinsics on its own frames, and the distortion
            K = raw.K
            extra["distortion"] = tuple(float(v) for v in raw.distortion.opencv())  # 5, or 8 (rational)
        # how well the adjustment holds and knows it (static.camera_support): observations, residual,
        # rotation / centre / principal-point sigma
        q = _quality(static.support.get(cid, {}))
        cams.append(CameraCalibration(id=cid, role=rig.camera(cid).role.value, static=True, width=w, height=h,
                                      intrinsics=(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])),
                                      world_to_camera=matrix4(static.world_to_camera[cid]), quality=q, **extra))
    left_out = {c: f"tracking camera: {v.unsupported}" for c, v in tracking.items() if v.unsupported is not None}
    tracking = {c: v for c, v in tracking.items() if c not in left_out}
    for cid in sorted(tracking):
        s = rig.camera(cid).sensor
        q = _quality(tracking[cid].stats)
        q["focal_gain"] = tracking[cid].gain
        q["focal_offset_px"] = tracking[cid].offset
        cams.append(CameraCalibration(id=cid, role=rig.camera(cid).role.value, static=False,
                                      width=s.width_px, height=s.height_px, quality=q))
    bstats = static.stats.get("bundle", {})
    rec_stats = {"static_cameras": float(len(static.camera_ids)), "tracking_cameras": float(len(tracking))}
    if "median_reprojection_px" in bstats:
        rec_stats["static_median_reprojection_px"] = float(bstats["median_reprojection_px"])
    # a capture without a lidar scan: how the stage frame and scale were set and the mounts' residual
    # (static.frame_without_lidar); with a scan and a known distance, that distance's check
    for k, v in static.stats.get("frame", {}).items():
        if isinstance(v, (int, float)) and np.isfinite(v):
            rec_stats[f"static_frame_{k}"] = float(v)
    return Calibration(capture=capture_name, frame_count=frame_count, fps=fps, reference_frame=reference_frame,
                       stage_size_m=tuple(rig.stage_size_m), cameras=tuple(cams),
                       tracking_frames=tracking_frames_ref(blob) if blob is not None else None, stats=rec_stats,
                       unregistered={**{c: static.reasons.get(c, "not registered") for c in static.unregistered},
                                     **left_out})


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
