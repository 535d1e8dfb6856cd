"""The calibrate flow: an ingested capture in, a Calibration and per-frame dense points out.

DAG: ``calibrate-static`` once -> ``calibrate-tracking-camera`` per tracking camera (mapped; none for
a capture without tracking cameras) -> ``assemble-calibration`` -> ``dense-points-frame`` per frame
(mapped) -> ``point-cloud-sequence``; for a synthetic capture also ``calibration-errors``.

:func:`calibrate_capture` and :func:`point_cloud_for_frames` are plain functions, not flows: they
submit their tasks into whatever flow run calls them (this one, reconstruct, production), so their
task runs count, cache and retry as that run's own.
"""

from __future__ import annotations

from prefect import flow, get_run_logger, unmapped

from tasks.calibrate import (assemble_calibration, calibrate_static, calibrate_tracking_camera, calibration_errors,
                             dense_points_frame, point_cloud_sequence, tracking_camera_ids)
from volcap_core.capture import Capture
from volcap_core.records import ArtifactRef
from volcap_core.store import ArtifactStore


def calibrate_capture(store: str, capture: ArtifactRef) -> ArtifactRef:
    """The capture's Calibration ref: static cameras once, each tracking camera in its own task,
    then the record. Call it inside a flow run (any). Every step is cached by its inputs' digests."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    trackers = tracking_camera_ids(cap)
    static = calibrate_static(store, capture)
    tracking: list[ArtifactRef] = []
    if trackers:
        futures = calibrate_tracking_camera.map(unmapped(store), unmapped(capture), unmapped(static), trackers)
        tracking = [f.result() for f in futures]
    return assemble_calibration(store, capture, static, tracking)


def point_cloud_for_frames(store: str, capture: ArtifactRef, calibration: ArtifactRef, frames: list[int],
                           max_points_per_frame: int | None = None, seed: int = 0, scale: float = 1.0,
                           exclude_cameras: list[str] | None = None) -> ArtifactRef:
    """The PointCloudSequence ref of ``frames`` (take indices): one dense-points task per frame
    (mapped), then the sequence record (``max_points_per_frame``: a training budget, see
    :func:`tasks.calibrate.point_cloud_sequence`); ``exclude_cameras``: held-out cameras, which
    take no part. Call it inside a flow run (any)."""
    frames = sorted({int(f) for f in frames})
    dense = []
    if frames:
        futures = dense_points_frame.map(unmapped(store), unmapped(capture), unmapped(calibration), frames,
                                         unmapped(scale), unmapped(sorted(exclude_cameras or [])))
        dense = [f.result() for f in futures]
    return point_cloud_sequence(store, calibration, dense, max_points_per_frame, seed)


@flow(name="calibrate", persist_result=False)
def calibrate_flow(store: str, capture: str, frames: tuple[int, int] | None = None) -> dict:
    """Calibrate ``capture`` (a ref name such as ``captures/demo`` or a digest) and compute dense
    points for ``frames`` [a, b) (all frames when None).

    Returns JSON: ``calibration`` and ``points`` (ref dumps), ``errors`` (the error table of
    ``volcap_core.calibration.metrics`` when the capture carries ground truth, else None). Also names
    the results ``calibrations/<capture name>`` and ``points/<capture name>`` in the store.
    """
    log = get_run_logger()
    s = ArtifactStore(store)
    capture_ref = s.resolve(capture)
    cap = s.get_record(capture_ref, Capture)
    a, b = cap.take_range(frames)
    trackers = tracking_camera_ids(cap)
    log.info("capture %s: %d static + %d tracking cameras, dense points for frames %d:%d", cap.name,
             len(cap.cameras) - len(trackers), len(trackers), a, b)
    calib_ref = calibrate_capture(store, capture_ref)
    points_ref = point_cloud_for_frames(store, capture_ref, calib_ref, list(range(a, b)))
    errors = None
    if cap.ground_truth is not None:
        errors = s.get_json(calibration_errors(store, capture_ref, calib_ref, points_ref))
    s.set_ref(f"calibrations/{cap.name}", calib_ref)
    s.set_ref(f"points/{cap.name}", points_ref)
    return {"capture": capture_ref.model_dump(mode="json"), "calibration": calib_ref.model_dump(mode="json"),
            "points": points_ref.model_dump(mode="json"), "frames": [a, b], "tracking_cameras": trackers,
            "errors": errors}
