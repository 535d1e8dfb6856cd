"""The :class:`~volcap_core.calibration.record.Calibration` record built from the static and
tracking steps' results: the ``assemble-calibration`` task's step.

:func:`build_record` is the one builder of the record (the task's :func:`assemble_calibration_record`
and :func:`volcap_core.calibration.pipeline.calibrate_capture` both call it); :func:`tracking_blob`
its tracking-frames blob. It lives beside :mod:`~volcap_core.calibration.record`, not in it, because
it reads the library's static and tracking results, which the record's readers (training, export)
need not import.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from hardware.rig import Rig
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.inputs import GetBytes, tracking_camera_ids
from volcap_core.calibration.record import (Calibration, CameraCalibration, TrackingFrames, encode_tracking_frames,
                                            matrix4, tracking_frames_ref)
from volcap_core.calibration.static import StaticCalibration
from volcap_core.calibration.static_step import StaticCalibrationRecord, static_calibration
from volcap_core.calibration.tracking.solve import TrackingSolution
from volcap_core.calibration.tracking_step import TrackingCameraRecord, tracking_solution
from volcap_core.capture import Capture


def _quality(stats: Mapping) -> dict[str, float]:
    """A camera's fit statistics as its record's ``quality``: the finite numbers, as floats."""
    return {k: float(v) for k, v in stats.items() if isinstance(v, (int, float)) and np.isfinite(v)}


def build_record(capture_name: str, rig: Rig, static: StaticCalibration, tracking: Mapping[str, TrackingSolution],
                 frame_count: int, fps: float, reference_frame: int, blob: bytes | None) -> Calibration:
    """The Calibration record of a static calibration and its tracking cameras' solutions; ``blob``
    (:func:`tracking_blob` of ``tracking``) gives the tracking ref. A tracking camera marked
    ``unsupported`` is left out and listed in ``unregistered`` with its reason, as a static camera
    the adjustment left out."""
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
                                     **left_out},
                       warnings=tuple(static.warnings))


def tracking_blob(sols: Mapping[str, TrackingSolution]) -> bytes | None:
    """The Calibration record's tracking-frames blob: per camera fx, fy, cx, cy and world_to_camera,
    and each frame's lens (``distortion``) for a camera whose frames were undistorted. A camera
    marked ``unsupported`` is left out (the record lists it instead); None when none is left."""
    kept = {c: v for c, v in sols.items() if v.unsupported is None}
    if not kept:
        return None
    return encode_tracking_frames({c: TrackingFrames(np.stack([v.K[:, 0, 0], v.K[:, 1, 1], v.K[:, 0, 2],
                                                               v.K[:, 1, 2]], 1), v.world_to_camera, v.distortion)
                                   for c, v in kept.items()})


def assemble_calibration_record(cap: Capture, static: StaticCalibrationRecord,
                                tracking: Sequence[TrackingCameraRecord], get_bytes: GetBytes
                                ) -> tuple[Calibration, bytes | None]:
    """The Calibration record and its tracking-frames blob (None without tracking cameras) from the
    stored static and tracking results (:func:`build_record`, as
    :func:`~volcap_core.calibration.pipeline.calibrate_capture` makes them from the steps' results);
    refuses a missing, duplicate or foreign tracking result."""
    sols: dict[str, TrackingSolution] = {}
    for tr in tracking:
        if tr.capture != cap.name or tr.camera in sols:
            raise CalibrationInputError(f"capture {cap.name}: tracking result for {tr.capture}/{tr.camera} "
                                        "is a duplicate or of another capture")
        sols[tr.camera] = tracking_solution(tr, get_bytes(tr.frames))
    missing = sorted(set(tracking_camera_ids(cap)) - set(sols))
    if missing:
        raise CalibrationInputError(f"capture {cap.name}: no tracking result for camera(s) {', '.join(missing)}")
    blob = tracking_blob(sols)
    record = build_record(cap.name, cap.rig, static_calibration(static), sols, cap.frame_count, cap.fps,
                          static.reference_frame, blob)
    return record, blob
