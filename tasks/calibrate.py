"""Calibration tasks: static cameras once, each tracking camera on its own, one task per frame of
dense points, and small assembling steps.

Each task loads the ingested capture's EXRs from the store lazily (one frame at a time), calls the
calibration library (``volcap_core.calibration``) and stores what it returns:

- :func:`calibrate_static` -> a :class:`StaticCalibrationRecord` (the static cameras at the middle
  frame, and, when the capture has tracking cameras, the static reference they register against);
- :func:`calibrate_tracking_camera` -> a :class:`TrackingCameraRecord` (one camera over the take);
- :func:`assemble_calibration` -> the :class:`~volcap_core.calibration.record.Calibration` record,
  built by the library's own ``pipeline.build_record`` (so the fanned-out tasks give the record
  ``pipeline.calibrate_capture`` gives in one call);
- :func:`dense_points_frame` -> a :class:`DensePointsFrame` (one frame's fused multi-view points);
- :func:`point_cloud_sequence` -> the :class:`~volcap_core.pointcloud.PointCloudSequence` record;
- :func:`calibration_errors` -> the error table against a synthetic capture's ground truth (JSON).

The calibration reads the capture's ``lidar`` scan (an input, like the frames), never its ground truth.
"""

from __future__ import annotations

import logging
from dataclasses import replace
import math
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from safetensors.numpy import load as st_load
from safetensors.numpy import save as st_save

from tasks.contract import volcap_task
from volcap_core import imageio
from volcap_core.calibration.dense import DenseOptions, dense_points
from volcap_core.calibration.lidar import LidarScan
from volcap_core.calibration.metrics import (calibration_table, distance_to_parts, load_ground_truth,
                                             static_errors, tracking_errors)
from volcap_core.calibration.photometric import background_plate
from volcap_core.calibration.pipeline import CalibrationOptions, build_record
from volcap_core.calibration.record import (Calibration, TrackingFrames, camera_at, decode_tracking_frames,
                                            encode_tracking_frames)
from volcap_core.calibration.static import StaticCalibration, calibrate_static_cameras
from volcap_core.calibration.tracking import (StaticReference, TrackingSolution, build_static_reference,
                                              calibrate_tracking_cameras)
from volcap_core.capture import Capture
from volcap_core.pointcloud import POINTS_MEDIA, PointCloudFrame, PointCloudSequence, decode_points, encode_points
from volcap_core.records import MEDIA_SAFETENSORS, ArtifactRef, Record
from volcap_core.store import ArtifactStore

log = logging.getLogger("volcap.calibrate")

Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
Matrix4 = tuple[tuple[float, float, float, float], ...]
ERRORS_MEDIA = "application/vnd.volcap.calibration-errors+json"
#: the static SfM must register at least this fraction of the static cameras (and two): fewer
#: means the views do not overlap enough (or the frame is wrong), and calibration stops there
MIN_REGISTERED_FRACTION = 0.5
#: the library's defaults, as measured in docs/calibration.md (a change here is a task version bump)
OPTIONS = CalibrationOptions()
DENSE_OPTIONS = DenseOptions()


class CalibrationInputError(ValueError):
    """Bad calibration input; the message names the capture, camera and frame concerned."""


# ---------------------------------------------------------------------------------------------
# Records of the intermediate results
# ---------------------------------------------------------------------------------------------


class StaticCamera(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str
    K: Matrix3
    world_to_camera: Matrix4
    width: int
    height: int


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


def frame_loader(s: ArtifactStore, cap: Capture):
    """``load(camera_id, take_index) -> float32 [H, W, 3]`` decoding the ingested EXR from the store."""

    def load(camera_id: str, take_index: int) -> np.ndarray:
        cam = cap.camera(camera_id)
        if not 0 <= take_index < len(cam.frames):
            raise CalibrationInputError(f"capture {cap.name}, camera {camera_id}: no frame {take_index} "
                                        f"(take has {len(cam.frames)})")
        ref = cam.frames[take_index]
        pixels, _ = imageio.decode_exr(s.get_bytes(ref), name=f"{cap.name}/{camera_id}/{take_index} ({ref.digest})")
        return np.ascontiguousarray(pixels[..., :3], dtype=np.float32)

    return load


class LazyFrames(Sequence):
    """A camera's frames over the take, decoded when read (the library iterates them once)."""

    def __init__(self, load, camera_id: str, count: int):
        self._load, self._id, self._n = load, camera_id, count

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(self._n))]
        if not -self._n <= i < self._n:
            raise IndexError(i)
        return self._load(self._id, i % self._n)


def load_lidar(s: ArtifactStore, cap: Capture) -> LidarScan | None:
    if cap.lidar is None:
        return None
    try:
        return LidarScan.from_ply_bytes(s.get_bytes(cap.lidar))
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


def _floats(stats: dict, prefix: str = "") -> dict[str, float]:
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


def encode_reference(ref: StaticReference) -> bytes:
    return st_save({"points": np.ascontiguousarray(ref.points, np.float64),
                    "descriptors": np.ascontiguousarray(ref.descriptors, np.uint8)},
                   metadata={"format": "volcap-static-reference/1"})


def decode_reference(data: bytes) -> StaticReference:
    t = st_load(data)
    return StaticReference(t["points"], t["descriptors"])


def static_calibration(rec: StaticCalibrationRecord) -> StaticCalibration:
    """The library's StaticCalibration from the stored record (without the sparse model)."""
    ids = [c.id for c in rec.cameras]
    stats: dict[str, Any] = {}
    if "bundle.median_reprojection_px" in rec.stats:
        stats["bundle"] = {"median_reprojection_px": rec.stats["bundle.median_reprojection_px"]}
    return StaticCalibration(camera_ids=ids, K={c.id: np.asarray(c.K, np.float64) for c in rec.cameras},
                             world_to_camera={c.id: np.asarray(c.world_to_camera, np.float64) for c in rec.cameras},
                             size={c.id: (c.width, c.height) for c in rec.cameras}, model=None,
                             unregistered=list(rec.unregistered), stats=stats)


# ---------------------------------------------------------------------------------------------
# Tasks
# ---------------------------------------------------------------------------------------------


@volcap_task(name="calibrate-static", version="2")
def calibrate_static(store: str, capture: ArtifactRef) -> ArtifactRef:
    """Static cameras on the middle frame (+ background plates), registered to the capture's lidar.

    With tracking cameras in the capture, also builds the static reference they register against
    (SIFT of the plates lifted onto the lidar, which such a capture must therefore have)."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    statics, trackers = split_cameras(cap)
    if len(statics) < 2:
        raise CalibrationInputError(f"capture {cap.name}: static calibration needs at least two static cameras, "
                                    f"it has {len(statics)} ({', '.join(statics) or 'none'})")
    scan = load_lidar(s, cap)
    if scan is None and trackers:
        # Measured: against the SfM points alone (no scan) the tracking cameras' absolute orientation
        # came out 70-145° wrong on the test capture. Refuse rather than hand out such a calibration.
        raise CalibrationInputError(
            f"capture {cap.name} has tracking cameras ({', '.join(trackers)}) but no lidar scan: they register "
            "against the static set lifted onto the scan; name the scan in capture.json's 'lidar'")
    if scan is None:
        log.warning("capture %s has no lidar scan: the static cameras are placed by the SfM and their mounts only",
                    cap.name)
    load = frame_loader(s, cap)
    T = cap.frame_count
    ref_frame = T // 2 if OPTIONS.reference_frame is None else OPTIONS.reference_frame
    plate_idx = [int(k) for k in np.unique(np.linspace(0, T - 1, max(1, min(OPTIONS.plate_frames, T)))
                                           .round().astype(int))]
    images = {c: load(c, ref_frame) for c in statics}
    plates = {c: background_plate([load(c, k) for k in plate_idx]) for c in statics}
    try:
        static = calibrate_static_cameras(images, cap.rig, scan, plates=plates, options=OPTIONS.static)
    except RuntimeError as exc:  # the SfM registered no / too few cameras
        raise CalibrationInputError(f"capture {cap.name}, frame {ref_frame}: static calibration of "
                                    f"{', '.join(statics)} failed: {exc}") from exc
    need = max(2, math.ceil(MIN_REGISTERED_FRACTION * len(statics)))
    if len(static.camera_ids) < need:
        raise CalibrationInputError(
            f"capture {cap.name}, frame {ref_frame}: the static SfM registered {len(static.camera_ids)} of "
            f"{len(statics)} static cameras (needs {need}); not registered: {', '.join(static.unregistered)}")
    if static.unregistered:
        log.warning("capture %s: static cameras %s did not register on frame %d and are left out of the calibration",
                    cap.name, ", ".join(static.unregistered), ref_frame)
    reference = None
    if trackers:
        ref = build_static_reference({c: plates[c] for c in static.camera_ids}, static.K, static.world_to_camera,
                                     scan)
        reference = s.put_bytes(encode_reference(ref), MEDIA_SAFETENSORS)
    cams = tuple(StaticCamera(id=c, K=_matrix(static.K[c]), world_to_camera=_matrix(static.world_to_camera[c]),
                              width=static.size[c][0], height=static.size[c][1]) for c in static.camera_ids)
    stats = _floats(static.stats)
    stats["sparse_points"] = float(len(static.model.points))
    return s.put_record(StaticCalibrationRecord(capture=cap.name, reference_frame=ref_frame,
                                                plate_frames=tuple(plate_idx), cameras=cams,
                                                unregistered=tuple(static.unregistered), reference=reference,
                                                stats=stats))


@volcap_task(name="calibrate-tracking-camera", version="2")
def calibrate_tracking_camera(store: str, capture: ArtifactRef, static: ArtifactRef, camera: str) -> ArtifactRef:
    """One tracking camera at every frame of the take, against the fixed static reference.

    The library refines each camera's sequence on its own (its normal equations are per camera), so
    one camera per task gives what the batched call gives (docs/calibration.md, "Tasks")."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
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
    st = s.get_record(static, StaticCalibrationRecord)
    if st.reference is None:
        raise CalibrationInputError(f"capture {cap.name}: the static calibration {static.digest} holds no static "
                                    "reference (it was made for a capture without tracking cameras)")
    reference = decode_reference(s.get_bytes(st.reference))
    encoder = (np.array([r.frame for r in lens], np.int64), np.array([r.focal_mm for r in lens], np.float64))
    frames = LazyFrames(frame_loader(s, cap), camera, cap.frame_count)
    ppm = rig_cam.sensor.width_px / rig_cam.sensor.width_mm
    try:
        sols = calibrate_tracking_cameras({camera: frames}, {camera: encoder}, {camera: ppm},
                                          {camera: np.asarray(rig_cam.mount.position_m, np.float64)}, reference,
                                          OPTIONS.tracking)
    except RuntimeError as exc:  # e.g. too few 2D-3D matches over the take
        raise CalibrationInputError(f"capture {cap.name}, tracking camera {camera}: {exc}") from exc
    sol = sols[camera]
    blob = st_save({"K": np.ascontiguousarray(sol.K, np.float64),
                    "world_to_camera": np.ascontiguousarray(sol.world_to_camera, np.float64)})
    return s.put_record(TrackingCameraRecord(
        capture=cap.name, camera=camera, frames=s.put_bytes(blob, MEDIA_SAFETENSORS), gain=float(sol.gain),
        offset=float(sol.offset), centre=tuple(float(v) for v in sol.centre), stats=_floats(sol.stats)))


@volcap_task(name="assemble-calibration", version="1")
def assemble_calibration(store: str, capture: ArtifactRef, static: ArtifactRef,
                         tracking: list[ArtifactRef]) -> ArtifactRef:
    """The Calibration record (and its tracking-frames blob) from the static and per-camera results,
    exactly as ``volcap_core.calibration.pipeline.build_record`` makes it."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    st = s.get_record(static, StaticCalibrationRecord)
    sols: dict[str, TrackingSolution] = {}
    for ref in tracking:
        tr = s.get_record(ref, TrackingCameraRecord)
        if tr.capture != cap.name or tr.camera in sols:
            raise CalibrationInputError(f"capture {cap.name}: tracking result {ref.digest} is for "
                                        f"{tr.capture}/{tr.camera} (duplicate or another capture)")
        arr = st_load(s.get_bytes(tr.frames))
        sols[tr.camera] = TrackingSolution(arr["K"], arr["world_to_camera"], tr.gain, tr.offset,
                                           np.asarray(tr.centre, np.float64), dict(tr.stats))
    missing = sorted(set(tracking_camera_ids(cap)) - set(sols))
    if missing:
        raise CalibrationInputError(f"capture {cap.name}: no tracking result for camera(s) {', '.join(missing)}")
    blob = None
    if sols:
        blob = encode_tracking_frames({c: TrackingFrames(np.stack([v.K[:, 0, 0], v.K[:, 1, 1], v.K[:, 0, 2],
                                                                   v.K[:, 1, 2]], 1), v.world_to_camera)
                                       for c, v in sols.items()})
    record = build_record(cap.name, cap.rig, static_calibration(st), sols, cap.frame_count, cap.fps,
                          st.reference_frame, blob)
    if blob is not None:
        stored = s.put_bytes(blob, MEDIA_SAFETENSORS)
        assert stored == record.tracking_frames, (stored, record.tracking_frames)
    return s.put_record(record)


@volcap_task(name="dense-points-frame", version="2")
def dense_points_frame(store: str, capture: ArtifactRef, calibration: ArtifactRef, frame: int,
                       scale: float = 1.0, exclude_cameras: list[str] | None = None) -> ArtifactRef:
    """One frame's dense points: a plane sweep per calibrated static camera, fused by cross-view
    consistency (``volcap_core.calibration.dense``), colours linear. ``exclude_cameras`` (a
    reconstruction's held-out cameras) take no part: points seen or coloured by a camera would
    leak its footage into the model it is meant to test."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    calib = s.get_record(calibration, Calibration)
    if not 0 <= frame < cap.frame_count:
        raise CalibrationInputError(f"capture {cap.name}: frame {frame} outside the take [0, {cap.frame_count})")
    if calib.capture != cap.name:
        raise CalibrationInputError(f"calibration {calibration.digest} is of capture {calib.capture}, not {cap.name}")
    # Static cameras only: the zoomed tracking views see the scene 5-7x larger, which the
    # fixed-size NCC windows of the sweep do not match across.
    ids = [c for c in calib.static_ids if c in {cc.id for cc in cap.cameras} and c not in set(exclude_cameras or ())]
    if len(ids) < 2:
        raise CalibrationInputError(f"capture {cap.name}, frame {frame}: dense points need two calibrated static "
                                    f"cameras, the calibration has {len(ids)}")
    load = frame_loader(s, cap)
    images = {c: load(c, frame) for c in ids}
    cams = {c: camera_at(calib, c, frame)[:2] for c in ids}
    if not 0 < scale <= 1:
        raise CalibrationInputError(f"dense points: scale must be in (0, 1], got {scale}")
    # scale < 1 matches downscaled images (a quarter of the work at 0.5): previews and tests.
    # DenseOptions.scale is the library's downscale *factor* (2 = half size), hence the division.
    out = dense_points(images, cams, options=replace(DENSE_OPTIONS, scale=DENSE_OPTIONS.scale / scale))
    pos, col = out["positions"], out["colours"]
    if len(pos) == 0:
        log.warning("capture %s, frame %d: no dense point passed the consistency check", cap.name, frame)
    ref = s.put_bytes(encode_points(pos, col), POINTS_MEDIA)
    return s.put_record(DensePointsFrame(calibration=calibration, frame=frame, time=cap.frame_time(frame),
                                         count=len(pos), points=ref, cameras=tuple(ids),
                                         seconds=round(float(out["seconds"]), 3)))


@volcap_task(name="point-cloud-sequence", version="1")
def point_cloud_sequence(store: str, calibration: ArtifactRef, frames: list[ArtifactRef],
                         max_points_per_frame: int | None = None, seed: int = 0) -> ArtifactRef:
    """The PointCloudSequence of the given dense frames, in frame order. ``max_points_per_frame``
    subsamples each frame (uniformly, seeded by ``seed`` and the frame) to a training budget; the
    dense frames themselves stay whole (a new budget does not redo the sweep)."""
    s = ArtifactStore(store)
    recs = sorted((s.get_record(r, DensePointsFrame) for r in frames), key=lambda r: r.frame)
    seen = [r.frame for r in recs]
    if len(set(seen)) != len(seen):
        raise CalibrationInputError(f"point-cloud sequence: frame(s) given twice: {sorted(seen)}")
    out, dense_counts = [], []
    for r in recs:
        if r.calibration.digest != calibration.digest:
            raise CalibrationInputError(f"dense points of frame {r.frame} were made with calibration "
                                        f"{r.calibration.digest}, not {calibration.digest}")
        ref, count = r.points, r.count
        dense_counts.append(r.count)
        if max_points_per_frame is not None and r.count > max_points_per_frame:
            xyz, rgb = decode_points(s.get_bytes(r.points))
            keep = np.sort(np.random.default_rng([seed, r.frame]).choice(r.count, max_points_per_frame,
                                                                        replace=False))
            ref, count = s.put_bytes(encode_points(xyz[keep], rgb[keep]), POINTS_MEDIA), max_points_per_frame
        out.append(PointCloudFrame(frame=r.frame, time=r.time, count=count, points=ref))
    method = "plane sweep over the calibrated static cameras, fused by cross-view depth consistency"
    if max_points_per_frame is not None:
        method += f"; at most {max_points_per_frame} per frame"
    stats = {"frames": float(len(out))}
    if out:
        stats.update(dense_points_mean=float(np.mean(dense_counts)), points_mean=float(np.mean([f.count for f in out])))
    return s.put_record(PointCloudSequence(calibration=calibration, frames=tuple(out), method=method, stats=stats))


def _finite_json(x: Any) -> Any:
    """NaN/Inf (no JSON form) become None; numpy scalars plain numbers."""
    if isinstance(x, dict):
        return {str(k): _finite_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_json(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    return x


@volcap_task(name="calibration-errors", version="1")
def calibration_errors(store: str, capture: ArtifactRef, calibration: ArtifactRef,
                       points: ArtifactRef | None = None) -> ArtifactRef:
    """The error table of ``volcap_core.calibration.metrics`` against the capture's ground truth
    (synthetic captures): static and tracking cameras, and per frame the dense points' count and
    distance to the true surfaces (the set's lidar or an actor). Stored as JSON."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    if cap.ground_truth is None:
        raise CalibrationInputError(f"capture {cap.name} carries no ground truth (only synthetic captures do)")
    calib = s.get_record(calibration, Calibration)
    tree = s.get_tree(cap.ground_truth)
    for name in ("cameras.json", "scene.json"):
        if name not in tree:
            raise CalibrationInputError(f"capture {cap.name}: ground truth has no {name}")
    with tempfile.TemporaryDirectory(prefix="volcap-gt-") as tmp:
        for name in ("cameras.json", "scene.json"):
            (Path(tmp) / name).write_bytes(s.get_bytes(tree[name].digest))
        gt = load_ground_truth(tmp)
    f0 = calib.reference_frame
    K, W = {}, {}
    for c in calib.static_ids:
        K[c], W[c], _, _ = camera_at(calib, c, f0)
    st_err = static_errors(K, W, gt, f0)
    tr_err = {}
    if calib.tracking_ids:
        tf = decode_tracking_frames(s.get_bytes(calib.tracking_frames))
        for c in calib.tracking_ids:
            Ks = np.zeros((calib.frame_count, 3, 3))
            fx, fy, cx, cy = tf[c].intrinsics.T
            Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2], Ks[:, 2, 2] = fx, fy, cx, cy, 1.0
            tr_err[c] = tracking_errors(Ks, tf[c].world_to_camera, gt, c)
    extra: dict[str, Any] = {"static_median_reprojection_px": calib.stats.get("static_median_reprojection_px"),
                             "frames": calib.frame_count, "reference_frame": f0,
                             "static_cameras": len(calib.static_ids), "tracking_cameras": len(calib.tracking_ids)}
    if points is not None:
        extra["points"] = _point_errors(s, cap, tree, s.get_record(points, PointCloudSequence), gt)
    table = calibration_table(st_err, {"priors": tr_err} if tr_err else None, extra)
    return s.put_json(_finite_json(table), ERRORS_MEDIA)


def _point_errors(s: ArtifactStore, cap: Capture, tree, seq: PointCloudSequence, gt) -> dict:
    """Per frame: points, median / 90th-percentile distance (m) to the true surface, points within
    3 cm of an actor. The true static surface is the ground truth's lidar (evaluation only)."""
    if "lidar.ply" not in tree:
        return {"per_frame": {}, "note": "ground truth has no lidar.ply"}
    scan = LidarScan.from_ply_bytes(s.get_bytes(tree["lidar.ply"].digest))
    per = {}
    for f in seq.frames:
        xyz, _ = decode_points(s.get_bytes(f.points))
        if not len(xyz):
            per[str(f.frame)] = {"points": 0}
            continue
        parts = [p for a in gt.parts for p in a[f.frame]] if gt.parts else []
        actor = distance_to_parts(xyz, parts) if parts else np.full(len(xyz), np.inf)
        d = np.minimum(scan.surface_distance(xyz, 0.3), actor)
        d = d[np.isfinite(d)]
        per[str(f.frame)] = {"points": int(len(xyz)),
                             "median_distance_m": float(np.median(d)) if len(d) else None,
                             "p90_distance_m": float(np.percentile(d, 90)) if len(d) else None,
                             "actor_points_3cm": int((actor < 0.03).sum())}
    vals = [v for v in per.values() if v.get("median_distance_m") is not None]
    return {"per_frame": per,
            "points_mean": float(np.mean([v["points"] for v in per.values()])) if per else 0.0,
            "median_distance_m": float(np.median([v["median_distance_m"] for v in vals])) if vals else None}


__all__ = ["calibrate_static", "calibrate_tracking_camera", "assemble_calibration", "dense_points_frame",
           "point_cloud_sequence", "calibration_errors", "StaticCalibrationRecord", "TrackingCameraRecord",
           "DensePointsFrame", "CalibrationInputError", "frame_loader", "tracking_camera_ids", "split_cameras"]
