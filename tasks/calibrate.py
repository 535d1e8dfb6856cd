"""Calibration tasks: static cameras once, each tracking camera on its own, one task per frame of
dense points, and small assembling steps. Each loads its inputs from the store, calls one step
(``volcap_core.calibration.*_step``, :mod:`~volcap_core.calibration.assemble`, or the metrics) and
stores what it returns:

- :func:`calibrate_static` -> a :class:`~volcap_core.calibration.static_step.StaticCalibrationRecord`;
- :func:`calibrate_tracking_camera` -> a
  :class:`~volcap_core.calibration.tracking_step.TrackingCameraRecord` (one camera over the take);
- :func:`assemble_calibration` -> the :class:`~volcap_core.calibration.record.Calibration` record;
- :func:`dense_points_frame` -> a :class:`~volcap_core.calibration.dense_points_step.DensePointsFrame`
  (one frame's fused multi-view points);
- :func:`point_cloud_sequence` -> the :class:`~volcap_core.pointcloud.PointCloudSequence` record;
- :func:`calibration_errors` -> the error table against a synthetic capture's ground truth (JSON);
- :func:`calibrate_colour` -> a :class:`~volcap_core.calibration.colour_step.ColourMatrixRecord`: the
  colour matrix between two rigs from a chart seen by each.

Settings are parameters with the library's defaults (their every field is in the cache key);
the calibration reads the capture's ``lidar`` scan (an input, like the frames), never its ground truth.
What each task version changed: docs/calibration.md, "Task versions".
"""

from __future__ import annotations

import json

from prefect import get_run_logger

from tasks.contract import volcap_task
from volcap_core.calibration.assemble import assemble_calibration_record
from volcap_core.calibration.colour import ColourCalibrationOptions
from volcap_core.calibration.colour_step import ChartView, colour_step
from volcap_core.calibration.dense import DenseOptions
from volcap_core.calibration.dense_points_step import DensePointsFrame, dense_points_step, thin_points
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.inputs import capture_cameras, frame_loader, lens_encoder, load_lidar
from volcap_core.calibration.lidar import LidarScan
from volcap_core.calibration.metrics import calibration_report, ground_truth_from_json
from volcap_core.calibration.record import Calibration, decode_tracking_frames
from volcap_core.calibration.scale import KnownPoints
from volcap_core.calibration.static import StaticCalibrationOptions
from volcap_core.calibration.static_step import (StaticCalibrationRecord, calibrate_static_step, decode_reference,
                                                 encode_reference, static_record)
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.calibration.tracking_step import (TrackingCameraRecord, calibrate_tracking_step,
                                                   encode_tracking_solution, tracking_record)
from volcap_core.capture import Capture
from volcap_core.pointcloud import POINTS_MEDIA, PointCloudFrame, PointCloudSequence, decode_points, encode_points
from volcap_core.records import MEDIA_SAFETENSORS, ArtifactRef
from volcap_core.store import ArtifactStore

ERRORS_MEDIA = "application/vnd.volcap.calibration-errors+json"
#: what the calibration's numbers depend on besides the inputs: SIFT and the mapper (pycolmap),
#: image filtering (OpenCV, kornia), the adjustments and the plane sweep (torch, numpy, scipy)
CALIBRATION_LIBRARIES = ("pycolmap", "cv2", "kornia", "torch", "numpy", "scipy")


@volcap_task(name="calibrate-static", version="13", libraries=CALIBRATION_LIBRARIES)
def calibrate_static(store: str, capture: ArtifactRef,
                     options: StaticCalibrationOptions = StaticCalibrationOptions(),
                     known_points: KnownPoints | None = None) -> ArtifactRef:
    """Static cameras on the middle frame (+ background plates), registered to the capture's lidar;
    with tracking cameras, also the static reference they register against. A camera the adjustment
    cannot support is an error naming it, or (``options.allow_unregistered``) left out and listed.
    ``known_points`` (distances between marked scene points, ``volcap_core.calibration.scale``)
    scale a capture without a scan; the step checks and applies them."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    statics, trackers = capture_cameras(cap)
    step = calibrate_static_step(cap.name, cap.rig, statics, trackers, cap.frame_count,
                                 frame_loader(s.get_bytes, cap), load_lidar(s.get_bytes, cap), options, known_points)
    reference = (s.put_bytes(encode_reference(step.reference), MEDIA_SAFETENSORS)
                 if step.reference is not None else None)
    return s.put_record(static_record(cap.name, step, reference))


@volcap_task(name="calibrate-tracking-camera", version="4", libraries=CALIBRATION_LIBRARIES)
def calibrate_tracking_camera(store: str, capture: ArtifactRef, static: ArtifactRef, camera: str,
                              options: TrackingOptions = TrackingOptions()) -> ArtifactRef:
    """One tracking camera at every frame of the take, against the fixed static reference; a camera
    the solve cannot support is an error naming it, or (``options.allow_unsupported``) left out."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    encoder = lens_encoder(cap, camera)
    st = s.get_record(static, StaticCalibrationRecord)
    reference = decode_reference(s.get_bytes(st.reference)) if st.reference is not None else None
    sol = calibrate_tracking_step(cap.name, cap.rig, camera, encoder, cap.frame_count, frame_loader(s.get_bytes, cap),
                                  reference, options)
    frames = s.put_bytes(encode_tracking_solution(sol), MEDIA_SAFETENSORS)
    return s.put_record(tracking_record(cap.name, camera, sol, frames))


@volcap_task(name="assemble-calibration", version="7")
def assemble_calibration(store: str, capture: ArtifactRef, static: ArtifactRef,
                         tracking: list[ArtifactRef]) -> ArtifactRef:
    """The Calibration record (and its tracking-frames blob) from the static and per-camera results,
    built by :func:`~volcap_core.calibration.assemble.build_record`, as
    ``volcap_core.calibration.pipeline.calibrate_capture`` builds it."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    record, blob = assemble_calibration_record(
        cap, s.get_record(static, StaticCalibrationRecord),
        [s.get_record(ref, TrackingCameraRecord) for ref in tracking], s.get_bytes)
    if blob is not None:
        stored = s.put_bytes(blob, MEDIA_SAFETENSORS)
        assert stored == record.tracking_frames, (stored, record.tracking_frames)
    return s.put_record(record)


@volcap_task(name="dense-points-frame", version="5", libraries=CALIBRATION_LIBRARIES)
def dense_points_frame(store: str, capture: ArtifactRef, calibration: ArtifactRef, frame: int,
                       scale: float = 1.0, exclude_cameras: list[str] | None = None,
                       options: DenseOptions = DenseOptions()) -> ArtifactRef:
    """One frame's dense points from the calibrated static cameras but ``exclude_cameras`` (a
    reconstruction's held-out cameras); ``scale`` < 1 matches downscaled images (previews, tests).
    A distorted camera's frame is rectified into the pinhole of its record's K first; a calibration
    with scene depths is swept around each camera's scene, one without around the stage volume.
    Logs a line per camera swept (its planes, depth range, pixels with a depth, time so far) and
    one for the frame. Version 4: the sweep in bounded memory (batches of planes, bands of rows,
    frames loaded when read) with the warp as a per-pixel homography (the same depths to float
    rounding) and a calibration without scene depths swept over the stage volume in each
    camera's view (before: the fixed 1-14 m of ``DenseOptions``)."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    run_log = get_run_logger()

    def progress(done: int, total: int, info: dict) -> None:
        run_log.info("capture %s, frame %d: dense points of camera %s (%d/%d): %d planes over %.2f-%.2f m, "
                     "%d pixels with a depth, %.0f s so far", cap.name, frame, info["camera"], done, total,
                     info["planes"], *info["depth_m"], info["pixels"], info["seconds"])

    out = dense_points_step(cap, s.get_record(calibration, Calibration), frame, frame_loader(s.get_bytes, cap),
                            options, scale, exclude_cameras or (), progress=progress)
    run_log.info("capture %s, frame %d: %d dense points from %d cameras in %.0f s", cap.name, frame,
                 len(out.positions), len(out.cameras), out.seconds)
    ref = s.put_bytes(encode_points(out.positions, out.colours), POINTS_MEDIA)
    return s.put_record(DensePointsFrame(calibration=calibration, frame=frame, time=cap.frame_time(frame),
                                         count=len(out.positions), points=ref, cameras=tuple(out.cameras),
                                         seconds=round(out.seconds, 3)))


@volcap_task(name="point-cloud-sequence", version="1", libraries=("numpy",))
def point_cloud_sequence(store: str, calibration: ArtifactRef, frames: list[ArtifactRef],
                         max_points_per_frame: int | None = None, seed: int = 0) -> ArtifactRef:
    """The PointCloudSequence of the given dense frames, in frame order. ``max_points_per_frame``
    thins each frame (:func:`volcap_core.calibration.dense_points_step.thin_points`) to a budget; the dense
    frames themselves stay whole (a new budget does not redo the sweep)."""
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
            xyz, rgb = thin_points(*decode_points(s.get_bytes(r.points)), max_points_per_frame, seed, r.frame)
            ref, count = s.put_bytes(encode_points(xyz, rgb), POINTS_MEDIA), len(xyz)
        out.append(PointCloudFrame(frame=r.frame, time=r.time, count=count, points=ref))
    method = "plane sweep over the calibrated static cameras, fused by cross-view depth consistency"
    if max_points_per_frame is not None:
        method += f"; at most {max_points_per_frame} per frame"
    stats = {"frames": float(len(out))}
    if out:
        stats.update(dense_points_mean=sum(dense_counts) / len(dense_counts),
                     points_mean=sum(f.count for f in out) / len(out))
    return s.put_record(PointCloudSequence(calibration=calibration, frames=tuple(out), method=method, stats=stats))


@volcap_task(name="calibration-errors", version="1", libraries=("numpy", "scipy"))
def calibration_errors(store: str, capture: ArtifactRef, calibration: ArtifactRef,
                       points: ArtifactRef | None = None) -> ArtifactRef:
    """The error table of ``volcap_core.calibration.metrics.calibration_report`` against the
    capture's ground truth (synthetic captures): static and tracking cameras, and per frame the dense
    points' count and distance to the true surfaces (the set's lidar or an actor). Stored as JSON."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    if cap.ground_truth is None:
        raise CalibrationInputError(f"capture {cap.name} carries no ground truth (only synthetic captures do)")
    calib = s.get_record(calibration, Calibration)
    tree = s.get_tree(cap.ground_truth)
    for name in ("cameras.json", "scene.json"):
        if name not in tree:
            raise CalibrationInputError(f"capture {cap.name}: ground truth has no {name}")
    gt = ground_truth_from_json(*(json.loads(s.get_bytes(tree[n].digest)) for n in ("cameras.json", "scene.json")))
    tracking = decode_tracking_frames(s.get_bytes(calib.tracking_frames)) if calib.tracking_ids else None
    scan = LidarScan.from_ply_bytes(s.get_bytes(tree["lidar.ply"].digest)) if "lidar.ply" in tree else None
    frames = None
    if points is not None:
        frames = [(f.frame, decode_points(s.get_bytes(f.points))[0])
                  for f in s.get_record(points, PointCloudSequence).frames]
    return s.put_json(calibration_report(calib, gt, tracking, scan, frames), ERRORS_MEDIA)


@volcap_task(name="calibrate-colour", version="3", libraries=("numpy", "OpenImageIO", "cv2"))
def calibrate_colour(store: str, source: ChartView, reference: ChartView,
                     options: ColourCalibrationOptions = ColourCalibrationOptions()) -> ArtifactRef:
    """The colour matrix between two rigs from a chart seen by each (``source``: the rig mapped,
    usually the Face Rig; ``reference``: the rig it is mapped onto, usually the Scene Rig): a
    :class:`~volcap_core.calibration.colour_step.ColourMatrixRecord` with the fit's ΔE before and
    after. The views' refs (capture, image, calibration) are inputs: their digests are in the key."""
    s = ArtifactStore(store)
    return s.put_record(colour_step(source, reference, s.get_bytes, options))


__all__ = ["calibrate_static", "calibrate_tracking_camera", "assemble_calibration", "dense_points_frame",
           "point_cloud_sequence", "calibration_errors", "calibrate_colour"]
