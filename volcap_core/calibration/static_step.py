"""The static cameras of a capture: the ``calibrate-static`` task's step and its record.

:func:`calibrate_static_step` calibrates the static cameras on :func:`reference_frame` with
background plates of :func:`plate_frames` (the policy: which frames, how many cameras must
register, what a capture with tracking cameras must provide), applies known points, and builds the
static reference the tracking cameras register against. :func:`static_record` /
:func:`static_calibration` carry its result between tasks as a :class:`StaticCalibrationRecord`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, SerializerFunctionWrapHandler, model_serializer
from safetensors.numpy import load as st_load
from safetensors.numpy import save as st_save

from hardware.serialization import omit_unset
from volcap_core.calibration import scale
from volcap_core.calibration.errors import CalibrationInputError, KnownDistanceError, UnsupportedCameraError
from volcap_core.calibration.inputs import FrameSource
from volcap_core.calibration.lidar import LidarScan
from volcap_core.calibration.photometric import background_plate
from volcap_core.calibration.record import Matrix3, Matrix4, finite_figures, float_matrix
from volcap_core.calibration.static import (StaticCalibration, StaticCalibrationOptions, calibrate_static_cameras,
                                            instant_frames, scene_depths)
from volcap_core.calibration.tracking.observe import StaticReference, build_static_reference
from volcap_core.records import ArtifactRef, Record

log = logging.getLogger("volcap.calibrate")


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
    #: what the user must know of it (:attr:`StaticCalibration.warnings`: a step that did not run
    #: and why, a camera's sigma that cannot be trusted); left out of the JSON when there is none
    warnings: tuple[str, ...] = ()

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler: SerializerFunctionWrapHandler):
        # a record without warnings serialises (and digests) as before they existed
        return omit_unset(handler(self), ("warnings",))


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
        # against the SfM points alone the tracking cameras' absolute orientation comes out wrong by
        # tens of degrees (docs/calibration.md): refuse rather than hand out such a calibration
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
            f"cannot be calibrated: {why}; check {'their' if many else 'its'} footage and mount, or {hint}"
            f"{_sparse_stage_hint(options)}") from exc
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


def _sparse_stage_hint(options: StaticCalibrationOptions) -> str:
    """The settings to try when static cameras are refused for what their views give (too few
    observations, too uncertain a pose): on a bare or repetitive stage, more instants pooled and a
    relaxed pair threshold (issue 31: a dome's repetitive panels calibrated at 640x360 with
    ``--min-pair-inliers 20``, a swept dark stage with ``--instants 4``); those already set are not
    named again. '' when both are."""
    tries = []
    if options.instants < 4 and options.instant_frames is None:
        tries.append("--instants 4 (instants pooled: texture moving through the stage)")
    if options.sfm.min_pair_inliers > 20:
        tries.append(f"--min-pair-inliers 20 (a camera pair needs {options.sfm.min_pair_inliers} verified matches "
                     "by default: too many for bare or repetitive views and wide baselines)")
    return "; on a bare or repetitive stage try " + " or ".join(tries) if tries else ""


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
    # that are no part of the scene, and can flip a tracking camera's solution (docs/calibration.md,
    # "Through the flow")
    return cv2.remap(np.ascontiguousarray(plate, np.float32), mx, my, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def encode_reference(ref: StaticReference) -> bytes:
    """The static reference as the record's blob: safetensors ``points`` [N, 3] float64 (stage
    frame, metres) and ``descriptors`` [N, 128] uint8."""
    return st_save({"points": np.ascontiguousarray(ref.points, np.float64),
                    "descriptors": np.ascontiguousarray(ref.descriptors, np.uint8)},
                   metadata={"format": "volcap-static-reference/1"})


def decode_reference(data: bytes) -> StaticReference:
    """Inverse of :func:`encode_reference`."""
    t = st_load(data)
    return StaticReference(t["points"], t["descriptors"])


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

    cams = tuple(StaticCamera(id=c, K=float_matrix(static.K[c]),
                              world_to_camera=float_matrix(static.world_to_camera[c]),
                              width=static.size[c][0], height=static.size[c][1],
                              scene_depth_m=static.scene_depth.get(c),
                              **raw_fields(c))
                 for c in static.camera_ids)
    stats = finite_figures(static.stats)
    stats["sparse_points"] = float(len(static.model.points))
    return StaticCalibrationRecord(capture=cap_name, reference_frame=step.reference_frame,
                                   plate_frames=tuple(step.plate_frames), cameras=cams,
                                   unregistered=tuple(static.unregistered),
                                   unregistered_reasons={c: static.reasons.get(c, "not registered")
                                                         for c in static.unregistered},
                                   reference=reference, stats=stats, warnings=tuple(static.warnings))


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
                             support={c: v for c, v in support.items() if v}, warnings=list(rec.warnings))
