"""The calibration of a stored capture, step by step: what each fanned-out calibration task computes.

:func:`volcap_core.calibration.pipeline.calibrate_capture` calibrates a capture in one call; the
calibrate flow runs the same work as separate, cached tasks (static cameras once, each tracking
camera on its own, dense points per frame). This module holds those steps and the records that
carry their results between tasks, so a task only loads its inputs, calls one function here and
stores what it returns. Nothing here touches a store: bytes come through a ``get_bytes(ref)``
callable.

Policy lives here too, once: which frame the static cameras are calibrated on and which frames make
their background plates (:func:`reference_frame`, :func:`plate_frames`), how many static cameras
must register, what a capture with tracking cameras must provide.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from safetensors.numpy import load as st_load
from safetensors.numpy import save as st_save

from volcap_core import imageio
from volcap_core.calibration import scale
from volcap_core.calibration.colour import ColourCalibrationOptions
from volcap_core.calibration.dense import DenseOptions, dense_points, sweep_range
from volcap_core.calibration.distortion import rectified_valid, rectify_frame
from volcap_core.calibration.lidar import LidarScan
from volcap_core.calibration.photometric import background_plate
from volcap_core.calibration.record import (Calibration, TrackingFrames, camera_at, encode_tracking_frames,
                                            frame_camera)
from volcap_core.calibration.static import (StaticCalibration, StaticCalibrationOptions, UnsupportedCameraError,
                                            KnownDistanceError, calibrate_static_cameras, instant_frames,
                                            scene_depths)
from volcap_core.calibration.tracking.calibrate import calibrate_tracking_cameras
from volcap_core.calibration.tracking.lens import zoom_lens
from volcap_core.calibration.tracking.observe import StaticReference, build_static_reference
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.calibration.tracking.solve import TrackingSolution, tracking_support
from volcap_core.capture import Capture
from volcap_core.records import ArtifactRef, Record

log = logging.getLogger("volcap.calibrate")

Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
Matrix4 = tuple[tuple[float, float, float, float], ...]
GetBytes = Callable[[ArtifactRef], bytes]
#: ``load(camera_id, take_index) -> float32 [H, W, 3]`` scene-linear RGB
FrameSource = Callable[[str, int], np.ndarray]


class CalibrationInputError(ValueError):
    """Bad calibration input; the message names the capture, camera and frame concerned."""


# ---------------------------------------------------------------------------------------------
# Records of the intermediate results
# ---------------------------------------------------------------------------------------------


class StaticCamera(BaseModel):
    """One calibrated static camera: ``K`` the square pinhole it was calibrated as (on its
    rectified images when its lens is distorted); ``raw_intrinsics`` (fx, fy, cx, cy on its own
    images) and ``distortion`` (``Distortion.to_json``) for a camera with distortion or non-square
    pixels (:attr:`StaticCalibration.raw_intrinsics`), None for a square pinhole."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str
    K: Matrix3
    world_to_camera: Matrix4
    width: int
    height: int
    raw_intrinsics: tuple[float, float, float, float] | None = None
    distortion: dict[str, Any] | None = None
    #: its view of the static scene (:func:`~volcap_core.calibration.static.scene_depths`): 1st
    #: percentile, median, 99th percentile depth in metres; None: too few sparse points in front
    scene_depth_m: tuple[float, float, float] | None = None


class StaticCalibrationRecord(Record):
    """The static cameras calibrated on ``reference_frame`` (as the library returned them: not yet
    re-orthonormalised into the Calibration record) and, for a capture with tracking cameras, the
    static reference (``reference``: safetensors ``points`` [N, 3] float64, ``descriptors`` [N, 128]
    uint8) the tracking cameras register against."""

    kind: ClassVar[str] = "static-calibration"
    capture: str
    reference_frame: int
    plate_frames: tuple[int, ...]
    cameras: tuple[StaticCamera, ...]
    unregistered: tuple[str, ...] = ()
    #: why each unregistered camera is left out (allowed by ``allow_unregistered``)
    unregistered_reasons: dict[str, str] = Field(default_factory=dict)
    reference: ArtifactRef | None = None
    stats: dict[str, float] = Field(default_factory=dict)


class TrackingCameraRecord(Record):
    """One tracking camera over the take: ``frames`` is safetensors ``K`` [T, 3, 3] and
    ``world_to_camera`` [T, 4, 4] float64; ``gain`` / ``offset`` the fitted encoder correction."""

    kind: ClassVar[str] = "tracking-camera-calibration"
    capture: str
    camera: str
    frames: ArtifactRef
    gain: float
    offset: float
    centre: tuple[float, float, float]
    stats: dict[str, float] = Field(default_factory=dict)
    #: why the camera is left out of the calibration (``TrackingOptions.allow_unsupported``), None
    #: when it is calibrated
    unsupported: str | None = None


class DensePointsFrame(Record):
    """One frame's dense points (``points``: safetensors ``xyz``, ``rgb`` as in
    :mod:`volcap_core.pointcloud`), fused from the calibration's static cameras."""

    kind: ClassVar[str] = "dense-points-frame"
    calibration: ArtifactRef
    frame: int
    time: float
    count: int
    points: ArtifactRef
    cameras: tuple[str, ...]
    seconds: float


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------


def frame_loader(get_bytes: GetBytes, cap: Capture) -> FrameSource:
    """``load(camera_id, take_index) -> float32 [H, W, 3]`` decoding the capture's ingested EXRs."""

    def load(camera_id: str, take_index: int) -> np.ndarray:
        cam = cap.camera(camera_id)
        if not 0 <= take_index < len(cam.frames):
            raise CalibrationInputError(f"capture {cap.name}, camera {camera_id}: no frame {take_index} "
                                        f"(take has {len(cam.frames)})")
        ref = cam.frames[take_index]
        pixels, _ = imageio.decode_exr(get_bytes(ref), name=f"{cap.name}/{camera_id}/{take_index} ({ref.digest})")
        return np.ascontiguousarray(pixels[..., :3], dtype=np.float32)

    return load


class LazyFrames(Sequence):
    """A camera's frames over the take, decoded when read (the library iterates them once)."""

    def __init__(self, load: FrameSource, camera_id: str, count: int):
        self._load, self._id, self._n = load, camera_id, count

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(self._n))]
        if not -self._n <= i < self._n:
            raise IndexError(i)
        return self._load(self._id, i % self._n)


def load_lidar(get_bytes: GetBytes, cap: Capture) -> LidarScan | None:
    """The capture's lidar scan (an input, like the frames), None when it has none."""
    if cap.lidar is None:
        return None
    try:
        return LidarScan.from_ply_bytes(get_bytes(cap.lidar))
    except (ValueError, KeyError, IndexError) as exc:
        raise CalibrationInputError(f"capture {cap.name}: lidar scan {cap.lidar.digest} is not a readable PLY: "
                                    f"{exc}") from exc


def split_cameras(cap: Capture) -> tuple[list[str], list[str]]:
    """(static, tracking) camera ids of a capture, by the rig's roles."""
    statics, trackers = [], []
    for cam in cap.cameras:
        try:
            role = cap.rig.camera(cam.id).role
        except (KeyError, ValueError) as exc:
            raise CalibrationInputError(f"capture {cap.name}: camera {cam.id} is not in rig {cap.rig.name}") from exc
        (trackers if role.tracks else statics).append(cam.id)
    return statics, trackers


def tracking_camera_ids(cap: Capture) -> list[str]:
    return split_cameras(cap)[1]


# ---------------------------------------------------------------------------------------------
# Static cameras
# ---------------------------------------------------------------------------------------------


def reference_frame(frame_count: int, options: StaticCalibrationOptions) -> int:
    """The take index the static cameras are calibrated on: the middle frame (the paper) unless set."""
    return frame_count // 2 if options.reference_frame is None else options.reference_frame


def plate_frames(frame_count: int, options: StaticCalibrationOptions) -> list[int]:
    """Take indices, evenly spread, whose median is each static camera's background plate."""
    n = max(1, min(options.plate_frames, frame_count))
    return [int(k) for k in np.unique(np.linspace(0, frame_count - 1, n).round().astype(int))]


@dataclass
class StaticStep:
    """The static cameras of a capture and what the tracking cameras need of them."""

    calibration: StaticCalibration
    reference_frame: int
    plate_frames: list[int]
    plates: dict[str, np.ndarray]
    #: the static set lifted onto the scan (None for a capture without tracking cameras)
    reference: StaticReference | None


def calibrate_static_step(cap_name: str, rig, static_ids: Sequence[str], tracking_ids: Sequence[str],
                          frame_count: int, load: FrameSource, scan: LidarScan | None,
                          options: StaticCalibrationOptions = StaticCalibrationOptions(),
                          known_points: scale.KnownPoints | None = None) -> StaticStep:
    """Calibrate the static cameras on :func:`reference_frame` with background plates, register them
    to the scan and, when the capture has tracking cameras, build the reference they register against.

    ``known_points`` (:class:`~volcap_core.calibration.scale.KnownPoints`): marked scene points and
    their measured distances. Checked against the capture's cameras before anything is calibrated
    (:func:`scale.check_for_capture`), then applied to the static calibration
    (:func:`scale.apply_to_static_step`: without a scan it is scaled to them, with a scan they are only
    checked) *before* the static reference is built, so the reference's points are in the same
    (scaled) frame as the static cameras. The one implementation for the ``calibrate-static`` task
    and :func:`volcap_core.calibration.pipeline.calibrate_capture`.

    Refuses (:class:`CalibrationInputError`, naming the capture, frame and cameras) fewer than two
    static cameras, tracking cameras without a scan (with or without known points: the tracking
    cameras register against the static set lifted onto the scan), a camera the adjustment cannot
    support (too few observations or too uncertain a pose, ``options.min_observations`` etc.) unless
    ``options.allow_unregistered``, fewer than ``options.min_registered_fraction`` of the static
    cameras calibrated (a seeded camera without observations is not calibrated), and known points
    that cannot give a scale (the message names the point and camera) or come with
    ``options.known_distance``.
    """
    if known_points is not None:
        scale.check_for_capture(cap_name, known_points, static_ids, tracking_ids, options.known_distance)
    if len(static_ids) < 2:
        raise CalibrationInputError(f"capture {cap_name}: static calibration needs at least two static cameras, "
                                    f"it has {len(static_ids)} ({', '.join(static_ids) or 'none'})")
    if scan is None and tracking_ids:
        # Measured: against the SfM points alone (no scan) the tracking cameras' absolute orientation
        # came out 70-145° wrong on the test capture. Refuse rather than hand out such a calibration.
        raise CalibrationInputError(
            f"capture {cap_name} has tracking cameras ({', '.join(tracking_ids)}) but no lidar scan: they register "
            "against the static set lifted onto the scan; name the scan in capture.json's 'lidar'"
            + ("" if known_points is None else " (known points scale the static cameras only)"))
    if options.known_distance is not None:
        unknown = [c for c in options.known_distance[:2] if c not in static_ids]
        if unknown:
            raise CalibrationInputError(f"capture {cap_name}: the known distance names camera(s) {', '.join(unknown)}, "
                                        f"not static cameras of the capture ({', '.join(static_ids)})")
    if scan is None:
        log.warning("capture %s has no lidar scan: the static cameras are placed by the SfM and their mounts only%s",
                    cap_name, "" if options.known_distance is None else
                    f", scaled to the known distance {options.known_distance[2]} m between "
                    f"{options.known_distance[0]} and {options.known_distance[1]}")
    ref_frame = reference_frame(frame_count, options)
    plate_idx = plate_frames(frame_count, options)
    images = {c: load(c, ref_frame) for c in static_ids}
    plates = {c: background_plate([load(c, k) for k in plate_idx]) for c in static_ids}
    # more instants pooled into the SfM (options.instants / instant_frames; none by default)
    try:
        pooled = instant_frames(frame_count, ref_frame, options)
    except ValueError as exc:
        raise CalibrationInputError(f"capture {cap_name}: {exc}") from exc
    more = [{c: load(c, k) for c in static_ids} for k in pooled[1:]]
    need = max(2, math.ceil(options.min_registered_fraction * len(static_ids)))
    try:
        static = calibrate_static_cameras(images, rig, scan, plates=plates, options=options, more_instants=more)
        if len(pooled) > 1:
            static.stats["instants"] = {"count": len(pooled), **{f"frame_{i}": k for i, k in enumerate(pooled)}}
    except UnsupportedCameraError as exc:
        names = sorted(exc.reasons)
        many = len(names) > 1
        why = str(exc) if many else exc.reasons[names[0]]
        hint = (f"allow {'them' if many else 'it'} to be left out with --allow-unregistered "
                "(StaticCalibrationOptions.allow_unregistered)"
                if len(static_ids) - len(names) >= need else
                f"fewer than {need} of {len(static_ids)} static cameras would be left")
        raise CalibrationInputError(
            f"capture {cap_name}, frame {ref_frame}: static camera{'s' if many else ''} {', '.join(names)} "
            f"cannot be calibrated: {why}; check {'their' if many else 'its'} footage and mount, or {hint}") from exc
    except KnownDistanceError as exc:   # e.g. a camera of the known distance was left out
        raise CalibrationInputError(f"capture {cap_name}, frame {ref_frame}: {exc}") from exc
    except RuntimeError as exc:  # the SfM registered no / too few cameras
        raise CalibrationInputError(f"capture {cap_name}, frame {ref_frame}: static calibration of "
                                    f"{', '.join(static_ids)} failed: {exc}") from exc
    if len(static.camera_ids) < need:
        raise CalibrationInputError(
            f"capture {cap_name}, frame {ref_frame}: the static calibration supports {len(static.camera_ids)} of "
            f"{len(static_ids)} static cameras (needs {need}); not calibrated: "
            + "; ".join(f"{c}: {static.reasons.get(c, 'not registered')}" for c in static.unregistered))
    if static.unregistered:
        log.warning("capture %s, frame %d: static cameras left out of the calibration (allow_unregistered): %s",
                    cap_name, ref_frame,
                    "; ".join(f"{c}: {static.reasons.get(c, 'not registered')}" for c in static.unregistered))
    if known_points is not None:
        # before the reference: were the static cameras scaled (no scan), the reference lifted from
        # them is in the same frame (with a scan nothing moves; tracking without a scan is refused above)
        static = scale.apply_to_static_step(cap_name, rig, static, known_points, has_scan=scan is not None,
                                            mount_tolerance_m=options.mount_tolerance_m)
    # in the final frame: where each camera's dense points will sweep
    static = replace(static, scene_depth=scene_depths(static, rig.stage_size_m))
    reference = None
    if tracking_ids:
        # the plates are the cameras' own (distorted) images: resampled into the pinholes ``static.K``
        # the reference lifts their features with
        reference = build_static_reference({c: _plate_in_pinhole(plates[c], static, c) for c in static.camera_ids},
                                           static.K, static.world_to_camera, scan)
    return StaticStep(static, ref_frame, plate_idx, plates, reference)


def _plate_in_pinhole(plate: np.ndarray, static: StaticCalibration, camera: str) -> np.ndarray:
    """A static camera's plate (its own pixels) resampled into the pinhole ``static.K[camera]`` it
    was calibrated as; unchanged for a square pinhole."""
    raw = (getattr(static, "raw_intrinsics", {}) or {}).get(camera)
    if raw is None:
        return plate
    import cv2

    from volcap_core.calibration.distortion import undistort_maps
    from volcap_core.calibration.sfm import Intrinsics

    K = static.K[camera]
    out = Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), raw.width, raw.height)
    mx, my = undistort_maps(raw, raw.distortion, out)
    # the border is replicated, not black: a black corner's edge is a ring of strong SIFT features
    # that are no part of the scene. Measured on the distorted demo capture (6 frames), tracking
    # camera S011: black border 155° off (a flipped solution); replicated 0.18°, focal 0.36 %; the
    # raw plates read as pinholes (before) 0.51°, focal 1.24 %
    return cv2.remap(np.ascontiguousarray(plate, np.float32), mx, my, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def encode_reference(ref: StaticReference) -> bytes:
    return st_save({"points": np.ascontiguousarray(ref.points, np.float64),
                    "descriptors": np.ascontiguousarray(ref.descriptors, np.uint8)},
                   metadata={"format": "volcap-static-reference/1"})


def decode_reference(data: bytes) -> StaticReference:
    t = st_load(data)
    return StaticReference(t["points"], t["descriptors"])


def _floats(stats: Mapping, prefix: str = "") -> dict[str, float]:
    """Finite numbers of a nested stats dict, flattened to ``a.b`` keys."""
    out: dict[str, float] = {}
    for k, v in stats.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_floats(v, key + "."))
        elif isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(float(v)):
            out[key] = float(v)
    return out


def _matrix(m: np.ndarray) -> tuple:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(m, np.float64))


def static_record(cap_name: str, step: StaticStep, reference: ArtifactRef | None) -> StaticCalibrationRecord:
    """The record of a static step; ``reference``: the stored :func:`encode_reference` of its reference."""
    static = step.calibration
    raw = getattr(static, "raw_intrinsics", {}) or {}

    def raw_fields(c: str) -> dict:
        if c not in raw:
            return {}
        r = raw[c]
        return {"raw_intrinsics": (float(r.fx), float(r.fy), float(r.cx), float(r.cy)),
                "distortion": r.distortion.to_json()}

    cams = tuple(StaticCamera(id=c, K=_matrix(static.K[c]), world_to_camera=_matrix(static.world_to_camera[c]),
                              width=static.size[c][0], height=static.size[c][1],
                              scene_depth_m=static.scene_depth.get(c),
                              **raw_fields(c))
                 for c in static.camera_ids)
    stats = _floats(static.stats)
    stats["sparse_points"] = float(len(static.model.points))
    return StaticCalibrationRecord(capture=cap_name, reference_frame=step.reference_frame,
                                   plate_frames=tuple(step.plate_frames), cameras=cams,
                                   unregistered=tuple(static.unregistered),
                                   unregistered_reasons={c: static.reasons.get(c, "not registered")
                                                         for c in static.unregistered},
                                   reference=reference, stats=stats)


def static_calibration(rec: StaticCalibrationRecord) -> StaticCalibration:
    """The library's StaticCalibration from the stored record (without the sparse model)."""
    ids = [c.id for c in rec.cameras]
    stats: dict[str, Any] = {}
    if "bundle.median_reprojection_px" in rec.stats:
        stats["bundle"] = {"median_reprojection_px": rec.stats["bundle.median_reprojection_px"]}
    # the no-lidar stage frame's figures (static.frame_without_lidar), top level only
    frame = {k[6:]: v for k, v in rec.stats.items() if k.startswith("frame.") and "." not in k[6:]}
    if frame:
        stats["frame"] = frame
    # each camera's final support (static.camera_support), as calibrate_static_cameras returned it
    support: dict[str, dict[str, float]] = {c: {} for c in ids}
    for k, v in rec.stats.items():
        if k.startswith("support."):       # support.<camera id, which may hold dots>.<figure>
            cid, _, figure = k[len("support."):].rpartition(".")
            if cid in support:
                support[cid][figure] = v
    from volcap_core.calibration.distortion import Distortion
    from volcap_core.calibration.sfm import Intrinsics

    raw = {c.id: Intrinsics(*c.raw_intrinsics, c.width, c.height, Distortion.from_json(c.distortion))
           for c in rec.cameras if c.raw_intrinsics is not None}
    return StaticCalibration(camera_ids=ids, K={c.id: np.asarray(c.K, np.float64) for c in rec.cameras},
                             world_to_camera={c.id: np.asarray(c.world_to_camera, np.float64) for c in rec.cameras},
                             size={c.id: (c.width, c.height) for c in rec.cameras}, model=None,
                             unregistered=list(rec.unregistered), stats=stats,
                             reasons={c: rec.unregistered_reasons.get(c, "not registered") for c in rec.unregistered},
                             raw_intrinsics=raw,
                             scene_depth={c.id: c.scene_depth_m for c in rec.cameras if c.scene_depth_m is not None},
                             support={c: v for c, v in support.items() if v})


# ---------------------------------------------------------------------------------------------
# Tracking cameras
# ---------------------------------------------------------------------------------------------


def calibrate_tracking_step(cap: Capture, camera: str, reference: StaticReference | None, load: FrameSource,
                            options: TrackingOptions = TrackingOptions()) -> TrackingSolution:
    """One tracking camera at every frame of the take, against the fixed static reference.

    The library refines each camera's sequence on its own (its normal equations are per camera), so
    one camera per call gives what the batched call gives (docs/calibration.md, "Tasks")."""
    ids = [c.id for c in cap.cameras]
    if camera not in ids:
        raise CalibrationInputError(f"capture {cap.name} has no camera {camera!r} (it has {', '.join(ids)})")
    try:
        rig_cam = cap.rig.camera(camera)
    except (KeyError, ValueError) as exc:
        raise CalibrationInputError(f"capture {cap.name}: camera {camera} is not in rig {cap.rig.name}") from exc
    if not rig_cam.role.tracks:
        raise CalibrationInputError(f"capture {cap.name}: camera {camera} is a {rig_cam.role.value} camera, "
                                    "not a tracking camera")
    lens = cap.camera(camera).lens_encoder
    if not lens:
        raise CalibrationInputError(f"capture {cap.name}: tracking camera {camera} has no lens-encoder readings")
    if reference is None:
        raise CalibrationInputError(f"capture {cap.name}: the static calibration holds no static reference (it "
                                    "was made for a capture without tracking cameras)")
    encoder = (np.array([r.frame for r in lens], np.int64), np.array([r.focal_mm for r in lens], np.float64))
    frames = LazyFrames(load, camera, cap.frame_count)
    ppm = rig_cam.sensor.width_px / rig_cam.sensor.width_mm
    try:
        # a zoom lens table in the rig: each frame is undistorted with the lens at its focal
        sols = calibrate_tracking_cameras({camera: frames}, {camera: encoder}, {camera: ppm},
                                          {camera: np.asarray(rig_cam.mount.position_m, np.float64)}, reference,
                                          options, lenses={camera: zoom_lens(cap.rig.zoom_intrinsics(camera))})
    except RuntimeError as exc:  # e.g. too few 2D-3D matches over the take
        raise CalibrationInputError(f"capture {cap.name}, tracking camera {camera}: {exc}") from exc
    return check_tracking_support(cap.name, camera, sols[camera], options)


def check_tracking_support(capture_name: str, camera: str, sol: TrackingSolution,
                           options: TrackingOptions = TrackingOptions()) -> TrackingSolution:
    """``sol`` when the camera is supported (:func:`~volcap_core.calibration.tracking.tracking_support`);
    otherwise an error naming the capture, the camera and the reason, or, with
    ``options.allow_unsupported``, ``sol`` marked ``unsupported`` (the calibration leaves it out and
    lists it). The one check of the flow's tasks and of ``pipeline.calibrate_capture``."""
    why = tracking_support(sol, options)
    if why is None:
        return sol
    if not options.allow_unsupported:
        raise CalibrationInputError(
            f"capture {capture_name}: tracking camera {camera} cannot be calibrated: {why}; check its footage, "
            "encoder and mount, or allow it to be left out with --allow-unregistered "
            "(TrackingOptions.allow_unsupported)")
    sol.unsupported = why
    return sol


def encode_tracking_solution(sol: TrackingSolution) -> bytes:
    """Safetensors ``K`` [T, 3, 3] and ``world_to_camera`` [T, 4, 4] float64 of one camera, and its
    ``distortion`` [T, 5|8] (each frame's lens) when its frames were undistorted."""
    arrays = {"K": np.ascontiguousarray(sol.K, np.float64),
              "world_to_camera": np.ascontiguousarray(sol.world_to_camera, np.float64)}
    if sol.distortion is not None:
        arrays["distortion"] = np.ascontiguousarray(sol.distortion, np.float64)
    return st_save(arrays)


def tracking_record(cap_name: str, camera: str, sol: TrackingSolution, frames: ArtifactRef) -> TrackingCameraRecord:
    """The record of one tracking camera; ``frames``: the stored :func:`encode_tracking_solution`."""
    return TrackingCameraRecord(capture=cap_name, camera=camera, frames=frames, gain=float(sol.gain),
                                offset=float(sol.offset), centre=tuple(float(v) for v in sol.centre),
                                stats=_floats(sol.stats), unsupported=sol.unsupported)


def tracking_solution(rec: TrackingCameraRecord, frames: bytes) -> TrackingSolution:
    """The library's TrackingSolution from a stored record and its frames blob."""
    arr = st_load(frames)
    return TrackingSolution(arr["K"], arr["world_to_camera"], rec.gain, rec.offset,
                            np.asarray(rec.centre, np.float64), dict(rec.stats), arr.get("distortion"),
                            rec.unsupported)


def assemble_calibration_record(cap: Capture, static: StaticCalibrationRecord,
                                tracking: Sequence[TrackingCameraRecord], get_bytes: GetBytes
                                ) -> tuple[Calibration, bytes | None]:
    """The Calibration record and its tracking-frames blob (None without tracking cameras), exactly
    as ``pipeline.calibrate_capture`` makes them in one call (``pipeline.build_record``)."""
    from volcap_core.calibration.pipeline import build_record  # pipeline imports this module

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


# ---------------------------------------------------------------------------------------------
# Dense points
# ---------------------------------------------------------------------------------------------


@dataclass
class DenseFrame:
    positions: np.ndarray   # [N, 3] float32, metres, stage frame
    colours: np.ndarray     # [N, 3] float32, linear
    cameras: list[str]
    seconds: float


def dense_points_step(cap: Capture, calib: Calibration, frame: int, load: FrameSource,
                      options: DenseOptions = DenseOptions(), scale: float = 1.0,
                      exclude_cameras: Sequence[str] = ()) -> DenseFrame:
    """One frame's dense points: a plane sweep per calibrated static camera, fused by cross-view
    consistency (``volcap_core.calibration.dense``), colours linear. ``exclude_cameras`` (a
    reconstruction's held-out cameras) take no part: points seen or coloured by a camera would
    leak its footage into the model it is meant to test. ``scale`` < 1 matches downscaled images
    (a quarter of the work at 0.5): previews and tests. A distorted camera's frame is rectified
    first (:func:`~volcap_core.calibration.distortion.rectify_frame`: the pinhole of its record's
    K) and its pixels outside the source take no part."""
    if not 0 <= frame < cap.frame_count:
        raise CalibrationInputError(f"capture {cap.name}: frame {frame} outside the take [0, {cap.frame_count})")
    if calib.capture != cap.name:
        raise CalibrationInputError(f"calibration of capture {calib.capture} given for capture {cap.name}")
    if not 0 < scale <= 1:
        raise CalibrationInputError(f"dense points: scale must be in (0, 1], got {scale}")
    # Static cameras only: the zoomed tracking views see the scene 5-7x larger, which the
    # fixed-size NCC windows of the sweep do not match across.
    present, excluded = {c.id for c in cap.cameras}, set(exclude_cameras)
    ids = [c for c in calib.static_ids if c in present and c not in excluded]
    if len(ids) < 2:
        raise CalibrationInputError(f"capture {cap.name}, frame {frame}: dense points need two calibrated static "
                                    f"cameras, the calibration has {len(ids)}")
    # a distorted camera's frame is resampled into the pinhole of its record's K (rectify_frame)
    images = {c: rectify_frame(load(c, frame), calib.camera(c)) for c in ids}
    cams = {c: camera_at(calib, c, frame)[:2] for c in ids}
    # DenseOptions.scale is the library's downscale *factor* (2 = half size), hence the division.
    valid = {c: rectified_valid(calib.camera(c)) for c in ids}
    # each camera sweeps around the static scene it saw at calibration (a stage of any size); a
    # calibration recorded before scene depths were takes DenseOptions' fixed range
    sweeps = {c: sweep_range(calib.camera(c).scene_depth_m) for c in ids if calib.camera(c).scene_depth_m}
    out = dense_points(images, cams, options=replace(options, scale=options.scale / scale), valid=valid,
                       sweeps=sweeps)
    if len(out["positions"]) == 0:
        log.warning("capture %s, frame %d: no dense point passed the consistency check", cap.name, frame)
    return DenseFrame(out["positions"], out["colours"], ids, float(out["seconds"]))


def thin_points(xyz: np.ndarray, rgb: np.ndarray, budget: int, seed: int, frame: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """At most ``budget`` of a frame's points, uniformly (seeded by ``seed`` and the frame), in order."""
    if len(xyz) <= budget:
        return xyz, rgb
    keep = np.sort(np.random.default_rng([seed, frame]).choice(len(xyz), budget, replace=False))
    return xyz[keep], rgb[keep]


# ---------------------------------------------------------------------------------------------
# Colour between rigs (a chart seen by the Face Rig and by the Scene Rig)
# ---------------------------------------------------------------------------------------------

Point2 = tuple[float, float]


class ChartView(BaseModel):
    """Where a colour chart is seen in one rig: the image (a capture's frame: ``capture``,
    ``camera``, ``frame``; or a stored EXR: ``image``) and where its patches are, in exactly one of
    three ways:

    - ``patches_px``: every patch centre (OpenCV px), in the chart's patch order;
    - ``corners_px``: the centres of the four corner patches (first patch, end of the first row,
      last patch, start of the last row) of a ``rows`` x ``cols`` chart (a ColorChecker: 4 x 6);
      the others follow by the chart plane's projective map;
    - ``patches_m`` (stage frame, metres) and ``patch_size_m`` with a ``calibration`` of the capture:
      projected through that camera at that frame.

    ``patch_radius_px``: half the side of the averaged window (default: from the options'
    ``window_fraction`` and the patch spacing). Both rigs' views must list the same patches in the
    same order."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    rig: str = Field(description="which rig this is: 'face' or 'scene' (or any label)")
    capture: ArtifactRef | None = None
    camera: str | None = None
    frame: int = Field(default=0, ge=0, description="take index")
    image: ArtifactRef | None = Field(default=None, description="a stored EXR of the chart instead of a capture frame")
    patches_px: tuple[Point2, ...] | None = None
    corners_px: tuple[Point2, Point2, Point2, Point2] | None = None
    rows: int = Field(default=4, ge=2)
    cols: int = Field(default=6, ge=2)
    patch_radius_px: float | None = Field(default=None, gt=0)
    calibration: ArtifactRef | None = None
    patches_m: tuple[tuple[float, float, float], ...] | None = None
    patch_size_m: float | None = Field(default=None, gt=0)

    def label(self) -> str:
        if self.image is not None:
            return f"{self.rig} rig, image {self.image.digest}"
        return f"{self.rig} rig, camera {self.camera}, frame {self.frame}"


class ColourMatrixRecord(Record):
    """The colour calibration between two rigs: the source rig's linear RGB mapped onto the
    reference rig's, ``ref ≈ matrix @ src + offset`` (Rec.709 linear). ``before`` / ``after``: ΔE76
    and ΔE2000 over the chart patches seen in both views (mean, max), ``delta_e2000`` per patch used
    (after). Applied to an image by :func:`volcap_core.calibration.colour.apply_colour_matrix`."""

    kind: ClassVar[str] = "colour-matrix"
    source_rig: str
    reference_rig: str
    source: ChartView
    reference: ChartView
    matrix: Matrix3
    offset: tuple[float, float, float]
    patches_used: tuple[int, ...]
    before: dict[str, float]
    after: dict[str, float]
    delta_e2000: tuple[float, ...]


def _view_image(view: ChartView, get_bytes: GetBytes) -> np.ndarray:
    if (view.image is None) == (view.capture is None):
        raise CalibrationInputError(f"colour chart ({view.rig} rig): give either a capture (with camera and frame) "
                                    "or an image")
    if view.image is not None:
        try:
            pixels, _ = imageio.decode_exr(get_bytes(view.image), name=f"chart image {view.image.digest}")
        except ValueError as exc:
            raise CalibrationInputError(f"colour chart ({view.label()}): not a readable EXR: {exc}") from exc
        return np.ascontiguousarray(pixels[..., :3], np.float32)
    cap = Capture.from_json_bytes(get_bytes(view.capture))
    ids = [c.id for c in cap.cameras]
    if view.camera not in ids:
        raise CalibrationInputError(f"colour chart ({view.rig} rig): capture {cap.name} has no camera "
                                    f"{view.camera!r} (it has {', '.join(ids)})")
    return frame_loader(get_bytes, cap)(view.camera, view.frame)


def chart_view_colours(view: ChartView, get_bytes: GetBytes,
                       options: ColourCalibrationOptions = ColourCalibrationOptions()) -> tuple[np.ndarray, np.ndarray]:
    """The chart's patch colours [N, 3] (linear) in ``view`` and which were sampled [N] (window inside
    the image, ≥ 4 px)."""
    from volcap_core.calibration.colour import chart_grid_px, chart_patches_in_view, grid_spacing_px, sample_patches

    given = [k for k in ("patches_px", "corners_px", "patches_m") if getattr(view, k) is not None]
    if len(given) != 1:
        raise CalibrationInputError(f"colour chart ({view.label()}): give exactly one of patches_px, corners_px, "
                                    f"patches_m (got {', '.join(given) or 'none'})")
    image = _view_image(view, get_bytes)
    if view.patches_m is not None:
        if view.calibration is None or view.patch_size_m is None or view.capture is None:
            raise CalibrationInputError(f"colour chart ({view.label()}): patches_m needs the capture, its "
                                        "calibration and patch_size_m")
        calib = Calibration.from_json_bytes(get_bytes(view.calibration))
        tracking = None
        if calib.tracking_frames is not None and view.camera in calib.tracking_ids:
            from volcap_core.calibration.record import decode_tracking_frames
            tracking = decode_tracking_frames(get_bytes(calib.tracking_frames))
        try:
            K, w2c, _, _ = camera_at(calib, view.camera, view.frame, tracking)
        except (KeyError, IndexError) as exc:
            raise CalibrationInputError(f"colour chart ({view.label()}): {exc}") from exc
        # the record's K is the pinhole of the rectified frame (a tracking camera's: of that frame's lens)
        image = rectify_frame(image, frame_camera(calib, view.camera, view.frame, tracking))
        return chart_patches_in_view(image, K, w2c, np.asarray(view.patches_m, np.float64), view.patch_size_m,
                                     options.window_fraction)
    if view.corners_px is not None:
        try:
            centres = chart_grid_px(np.asarray(view.corners_px, np.float64), view.rows, view.cols)
        except ValueError as exc:
            raise CalibrationInputError(f"colour chart ({view.label()}): {exc}") from exc
        spacing = grid_spacing_px(centres, view.rows, view.cols)
    else:
        centres = np.asarray(view.patches_px, np.float64).reshape(-1, 2)
        if len(centres) < 2 and view.patch_radius_px is None:
            raise CalibrationInputError(f"colour chart ({view.label()}): one patch: give patch_radius_px")
        d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        spacing = d.min(1)
    radius = (np.full(len(centres), view.patch_radius_px) if view.patch_radius_px is not None
              else 0.5 * options.window_fraction * spacing)
    cols, ok = np.zeros((len(centres), 3)), np.zeros(len(centres), bool)
    for i, (c, r) in enumerate(zip(centres, radius)):
        v, m = sample_patches(image, c[None], float(r))
        cols[i], ok[i] = v[0], bool(m[0])
    return cols, ok


def colour_step(source: ChartView, reference: ChartView, get_bytes: GetBytes,
                options: ColourCalibrationOptions = ColourCalibrationOptions()) -> ColourMatrixRecord:
    """Fit the source rig's chart colours onto the reference rig's (:func:`colour.calibrate_colour`)
    over the patches sampled in both views; refuses views that disagree on the patch count or
    share fewer than ``options.min_patches`` patches."""
    from volcap_core.calibration.colour import calibrate_colour

    src, ok_s = chart_view_colours(source, get_bytes, options)
    ref, ok_r = chart_view_colours(reference, get_bytes, options)
    if len(src) != len(ref):
        raise CalibrationInputError(f"colour chart: {len(src)} patches in the {source.label()} but {len(ref)} in the "
                                    f"{reference.label()}: both views must list the same patches")
    both = ok_s & ok_r
    need = max(options.min_patches, 4 if options.offset else 3)
    if both.sum() < need:
        where = [f"{v.label()}: {int(ok.sum())} of {len(ok)}" for v, ok in ((source, ok_s), (reference, ok_r))]
        raise CalibrationInputError(f"colour chart: {int(both.sum())} patches sampled in both views, the fit needs "
                                    f"{need} (patches inside the image: {'; '.join(where)})")
    res = calibrate_colour(src[both], ref[both], offset=options.offset, robust_iterations=options.robust_iterations)
    summary = lambda r: {k: float(v) for k, v in r.items() if k != "delta_e2000"}  # noqa: E731
    return ColourMatrixRecord(source_rig=source.rig, reference_rig=reference.rig, source=source, reference=reference,
                              matrix=_matrix(res["matrix"]), offset=tuple(float(v) for v in res["offset"]),
                              patches_used=tuple(int(i) for i in np.flatnonzero(both)),
                              before=summary(res["before"]), after=summary(res["after"]),
                              delta_e2000=tuple(round(float(v), 6) for v in res["after"]["delta_e2000"]))


__all__ = ["CalibrationInputError", "StaticCamera", "StaticCalibrationRecord", "TrackingCameraRecord",
           "DensePointsFrame", "frame_loader", "LazyFrames", "load_lidar", "split_cameras", "tracking_camera_ids",
           "reference_frame", "plate_frames", "StaticStep", "calibrate_static_step", "encode_reference",
           "decode_reference", "static_record", "static_calibration", "calibrate_tracking_step",
           "check_tracking_support",
           "encode_tracking_solution", "tracking_record", "tracking_solution", "assemble_calibration_record",
           "tracking_blob", "DenseFrame", "dense_points_step", "thin_points", "ChartView", "ColourMatrixRecord",
           "chart_view_colours", "colour_step"]
