"""Reconstruction tasks: ground-truth inputs for synthetic captures, segment training, rendering.

Each loads its records from the store, calls :mod:`volcap_core.segment` (or the synthetic capture's
:mod:`volcap_core.synth.ground_truth`) and stores what comes back.
"""

from __future__ import annotations

import functools
import json

import numpy as np
from prefect import get_run_logger

from tasks.artifacts import ProgressArtifact, artifact_key, publish_image, publish_table
from tasks.contract import current_run_key, volcap_task
from volcap_core import reconstruction
from volcap_core.calibration.distortion import record_distortion
from volcap_core.calibration.record import Calibration, camera_at, frame_camera
from volcap_core.capture import Capture
from volcap_core.imageio.read import decode_exr
from volcap_core.pointcloud import POINTS_MEDIA, PointCloudFrame, PointCloudSequence, encode_points
from volcap_core.records import MEDIA_EXR, MEDIA_SAFETENSORS, ArtifactRef
from volcap_core.segment import fit_segment, render_segment_exr, tracking_frames
from volcap_core.view import ViewSpec
from volcap_core.splat.train import TrainConfig
from volcap_core.store import ArtifactStore, MissingRefError
from volcap_core.synth import ground_truth

#: training and rendering numerics: torch (the optimiser and the rasterizer's torch back-end),
#: numpy and scipy (initialisation, scoring), OpenCV (rectifying a distorted camera's frames).
#: The device and the back-end chosen by "auto" are not in the key: see docs/tasks.md, "What is
#: not in a key".
RECONSTRUCTION_LIBRARIES = ("torch", "numpy", "scipy", "cv2")


def _ground_truth(s: ArtifactStore, cap: Capture) -> ground_truth.GroundTruthFiles:
    if cap.ground_truth is None:
        raise ValueError(f"capture {cap.name} carries no ground truth (only synthetic captures do)")
    tree = s.get_tree(cap.ground_truth)
    return ground_truth.GroundTruthFiles(cap.name, {p: e.digest for p, e in tree.items()}, s.get_bytes)


@volcap_task(name="ground-truth-calibration", version="2")
def ground_truth_calibration(store: str, capture: ArtifactRef) -> ArtifactRef:
    """The synthetic capture's true cameras as a Calibration record (source ``ground_truth``)."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    cams_json = json.loads(_ground_truth(s, cap).read("cameras.json"))
    record, blob = ground_truth.calibration(cams_json, cap.name, [c.id for c in cap.cameras],
                                            cap.rig.stage_size_m)
    if blob is not None:
        record = record.model_copy(update={"tracking_frames": s.put_bytes(blob, MEDIA_SAFETENSORS)})
    return s.put_record(record)


@volcap_task(name="ground-truth-points", version="4", libraries=("numpy", "OpenImageIO"))
def ground_truth_points(store: str, capture: ArtifactRef, calibration: ArtifactRef, points_per_frame: int,
                        seed: int, exclude_cameras: list[str] | None = None) -> ArtifactRef:
    """Dense points per frame from the true depth maps of every camera but ``exclude_cameras``
    (held-out ones), coloured by its image. Version 3: a camera with lens distortion is
    back-projected through it (before: as the pinhole of its K)."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    calib = s.get_record(calibration, Calibration)
    files = _ground_truth(s, cap)
    tracking = tracking_frames(s.get_bytes, calib)
    ids = [c.id for c in cap.cameras if c.id not in set(exclude_cameras or ())]

    def load_image(cam: str, f: int) -> np.ndarray:
        return decode_exr(s.get_bytes(cap.camera(cam).frames[f]))[0]

    def camera_at_frame(cam: str, f: int):
        return camera_at(calib, cam, f, tracking)[:2]

    frames = []
    for f in range(cap.frame_count):
        xyz, rgb = ground_truth.depth_points(files, ids, f, load_image, camera_at_frame, points_per_frame, seed,
                                             distortion_of=lambda c, k: record_distortion(
                                                 frame_camera(calib, c, k, tracking)))
        frames.append(PointCloudFrame(frame=f, time=cap.frame_time(f), count=len(xyz),
                                      points=s.put_bytes(encode_points(xyz, rgb), POINTS_MEDIA)))
    return s.put_record(PointCloudSequence(calibration=calibration, frames=tuple(frames),
                                           method=f"ground-truth depth, {points_per_frame} per frame"))


@volcap_task(name="train-segment", version="13", retries=1, libraries=RECONSTRUCTION_LIBRARIES)
def train_segment_task(store: str, capture: ArtifactRef, calibration: ArtifactRef, points: ArtifactRef,
                       frames: list[int], config: TrainConfig, seed: int) -> ArtifactRef:
    """Train one Poly4DGS segment, score it against its floors and draw its contact sheet
    (:func:`volcap_core.segment.fit_segment`).

    Every ``config.checkpoint_every`` steps the training state is stored and named
    ``checkpoints/<this run's cache key>``; a killed or retried run of the same segment resumes from
    it, and ends with the same model as an uninterrupted run (on CPU, bit for bit). The Prefect UI
    shows the training progress, the score table and the contact sheet as artifacts of this run.
    Version 5: the record names the rasterizer back-end that trained it. Version 6: a camera
    calibrated with lens distortion trains on its frames rectified into the pinhole of its K, the
    pixels outside its source left out of the loss and the scores (before: raw frames as a pinhole).
    Version 8: the scores add ``regions``, the performer- and face-region PSNR, SSIM and detail per
    camera role beside the floors (a synthetic capture's; ``docs/poly4dgs.md``, "Evaluation").
    Version 9: the initial points may add the zoom cameras' own (``TrainConfig.init_zoom_stride_px``,
    the demo preset's; issue 28), and TrainConfig gained the fields of that route. Version 10: a
    capture without a lidar scan (real footage) starts from a room shell coloured by the static
    training cameras beside its dense points (``reconstruction.segment_init``; issue 30). Version 11:
    a capture with its own performer masks starts from the performers' visual hull. Version 12: the
    zoom cameras' points (``init_zoom_stride_px``, the demo preset's) take the depth the frame's
    other training cameras confirm by photo-consistency, the unconfirmed ones dropped
    (``splat.init.photo_depth``; issue 28). Version 13: the scores add ``alpha``, the performers'
    alpha on the held-out views against their masks, beside the floors (issue 30).
    """
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    a, b = frames
    ckpt_name = f"checkpoints/{current_run_key()}"
    run_log = get_run_logger()
    try:
        resume = s.get_bytes(s.get_ref(ckpt_name))
        run_log.warning("segment [%d, %d): resuming from %s", a, b, ckpt_name)
    except MissingRefError:
        resume = None

    key = f"segment-{a}-{b}"
    progress_artifact = ProgressArtifact(artifact_key(key, "training"),
                                         f"Training of segment [{a}, {b}) of {cap.name}: steps done")
    every = max(1, config.steps // 10)
    mcmc = {"relocated": 0, "grown": 0}

    def progress(step: int, total: int, info: dict) -> None:  # what a coordinator watches scroll by
        progress_artifact.update(step, total)
        mcmc["relocated"] += info["relocated"]
        mcmc["grown"] += info["grown"]
        if step % every == 0 or step == total:
            run_log.info("segment [%d, %d): step %d/%d, loss %.4f, %d Gaussians (MCMC so far: %d relocated, "
                         "%d grown), %.0f s", a, b, step, total, info["loss"], info["num_gaussians"],
                         mcmc["relocated"], mcmc["grown"], info["wall_s"])

    files = _ground_truth(s, cap) if cap.ground_truth is not None else None
    scene = json.loads(files.read("scene.json")) if files is not None and "scene.json" in files else None
    fitted = fit_segment(cap, capture, s.get_record(calibration, Calibration), calibration,
                         s.get_record(points, PointCloudSequence), (a, b), config, seed,
                         get_bytes=s.get_bytes, put_bytes=s.put_bytes,
                         load_mask=ground_truth.mask_loader(files) if files is not None else None,
                         checkpoint=lambda blob, step: s.set_ref(ckpt_name, s.put_bytes(blob)),
                         resume_from=resume, progress=progress,
                         head_region=None if scene is None else functools.partial(ground_truth.face_region, scene))
    progress_artifact.finish()
    rec = fitted.record
    run_log.info("segment [%d, %d): rasterizer %s (%s)", a, b, rec.backend, rec.backend_reason)
    ref = s.put_record(rec)
    publish_table(artifact_key(key, "scores"), fitted.report.table(),
                  f"Segment [{a}, {b}) of {cap.name}: held-out scores (per-camera gain/offset fitted on other "
                  f"frames) beside the empty and untrained floors, and the training views")
    publish_image(artifact_key(key, "contact-sheet"), fitted.sheet_ui_jpeg,
                  f"Segment [{a}, {b}) of {cap.name}: footage | render | error")
    try:  # the model is stored: its checkpoint has done its job (gc may take it)
        s.delete_ref(ckpt_name)
    except MissingRefError:
        pass
    return ref


@volcap_task(name="render-views", version="2", libraries=("torch", "OpenEXR"))
def render_views(store: str, segment: ArtifactRef, views: list[ViewSpec], grids_of: str | None = None) -> list[ArtifactRef]:
    """Render a segment model from any cameras at any times (novel views, camera paths): linear
    RGBA half-float EXRs. ``grids_of``: apply that training camera's exposure/black grids. A view's
    ``near_m`` clips what lies nearer (version 2: version 1 ignored it, so its renders of views with
    a near plane are not reused)."""
    s = ArtifactStore(store)
    seg = s.get_record(segment, reconstruction.SegmentModel)
    return [s.put_bytes(render_segment_exr(s.get_bytes, seg, np.asarray(v.K), np.asarray(v.world_to_camera),
                                           v.width, v.height, v.time_s, grids_of, near_m=v.near_m), MEDIA_EXR)
            for v in views]


__all__ = ["ground_truth_calibration", "ground_truth_points", "train_segment_task", "render_views", "ViewSpec"]
