"""Reconstruction tasks: ground-truth inputs for synthetic captures, segment training, rendering."""

from __future__ import annotations

import json
import logging

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict

from prefect import get_run_logger

from tasks.artifacts import ProgressArtifact, artifact_key, publish_image, publish_table
from tasks.contract import current_run_key, volcap_task
from volcap_core.contact_sheet import contact_sheet, encode_jpeg, encode_png
from volcap_core import imageio, reconstruction
from volcap_core.calibration.record import Calibration, TrackingFrames, camera_at, decode_tracking_frames
from volcap_core.capture import Capture
from volcap_core.pointcloud import POINTS_MEDIA, PointCloudFrame, PointCloudSequence, decode_points, encode_points
from volcap_core.records import MEDIA_EXR, MEDIA_PNG, MEDIA_SAFETENSORS, ArtifactRef
from volcap_core.splat import evaluate, load_model, render, save_model, train_segment
from volcap_core.splat.report import score_segment
from volcap_core.splat.train import TrainConfig
from volcap_core.store import ArtifactStore, MissingRefError
from volcap_core.synth import ground_truth

log = logging.getLogger("volcap.reconstruct")


def _ground_truth_file(s: ArtifactStore, capture: Capture, path: str) -> bytes:
    if capture.ground_truth is None:
        raise ValueError(f"capture {capture.name} carries no ground truth (only synthetic captures do)")
    tree = s.get_tree(capture.ground_truth)
    if path not in tree:
        raise ValueError(f"capture {capture.name}: ground truth has no {path}"
                         + (" (synthesize with write_depth=True for depth maps)" if path.startswith("depth/") else ""))
    return s.get_bytes(tree[path].digest)


@volcap_task(name="ground-truth-calibration", version="1")
def ground_truth_calibration(store: str, capture: ArtifactRef) -> ArtifactRef:
    """The synthetic capture's true cameras as a Calibration record (source ``ground_truth``)."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    cams_json = json.loads(_ground_truth_file(s, cap, "cameras.json"))
    record, blob = ground_truth.calibration(cams_json, cap.name, [c.id for c in cap.cameras],
                                            cap.rig.stage_size_m)
    if blob is not None:
        record = record.model_copy(update={"tracking_frames": s.put_bytes(blob, MEDIA_SAFETENSORS)})
    return s.put_record(record)


def load_tracking(s: ArtifactStore, calib: Calibration) -> dict[str, TrackingFrames] | None:
    return decode_tracking_frames(s.get_bytes(calib.tracking_frames)) if calib.tracking_frames else None


@volcap_task(name="ground-truth-points", version="2")
def ground_truth_points(store: str, capture: ArtifactRef, calibration: ArtifactRef, points_per_frame: int,
                        seed: int, exclude_cameras: list[str] | None = None) -> ArtifactRef:
    """Dense points per frame from the true depth maps of every camera but ``exclude_cameras``
    (held-out ones), coloured by its image."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    calib = s.get_record(calibration, Calibration)
    tracking = load_tracking(s, calib)
    frames = []
    for f in range(cap.frame_count):
        xyz_all, rgb_all = [], []
        for cam in cap.cameras:
            if cam.id in set(exclude_cameras or ()):
                continue
            depth, _ = imageio.decode_exr_native(_ground_truth_file(s, cap, f"depth/{cam.id}/{f:06d}.exr"))
            image, _ = imageio.decode_exr(s.get_bytes(cam.frames[f]))
            K, w2c, _, _ = camera_at(calib, cam.id, f, tracking)
            xyz, rgb = ground_truth.backproject_depth(depth[..., 0].astype(np.float32), image, K, w2c)
            xyz_all.append(xyz)
            rgb_all.append(rgb)
        xyz, rgb = ground_truth.subsample(np.concatenate(xyz_all), np.concatenate(rgb_all),
                                          points_per_frame, seed + f)
        ref = s.put_bytes(encode_points(xyz, rgb), POINTS_MEDIA)
        frames.append(PointCloudFrame(frame=f, time=cap.frame_time(f), count=len(xyz), points=ref))
    return s.put_record(PointCloudSequence(calibration=calibration, frames=tuple(frames),
                                           method=f"ground-truth depth, {points_per_frame} per frame"))


@volcap_task(name="train-segment", version="4", retries=1)
def train_segment_task(store: str, capture: ArtifactRef, calibration: ArtifactRef, points: ArtifactRef,
                       frames: list[int], config: TrainConfig, seed: int) -> ArtifactRef:
    """Train one Poly4DGS segment, score it against its floors and draw its contact sheet.

    Every ``config.checkpoint_every`` steps the training state is stored and named
    ``checkpoints/<this run's cache key>``; a killed or retried run of the same segment resumes from
    it, and ends with the same model as an uninterrupted run (on CPU, bit for bit). The Prefect UI
    shows the training progress, the score table and the contact sheet as artifacts of this run.
    """
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    calib = s.get_record(calibration, Calibration)
    pts = s.get_record(points, PointCloudSequence)
    a, b = frames
    data = reconstruction.segment_data(cap, calib, load_tracking(s, calib), (a, b),
                                       reconstruction.FrameCache(s.get_bytes), scale=config.image_scale,
                                       load_mask=_mask_loader(s, cap))
    init = reconstruction.segment_init(s.get_bytes, cap, pts, data, config.held_out_cameras)

    ckpt_name = f"checkpoints/{current_run_key()}"
    try:
        resume = s.get_bytes(s.get_ref(ckpt_name))
        log.warning("segment [%d, %d): resuming from %s", a, b, ckpt_name)
    except MissingRefError:
        resume = None

    def checkpoint(blob: bytes, step: int) -> None:
        s.set_ref(ckpt_name, s.put_bytes(blob))

    device = "cuda" if torch.cuda.is_available() else "cpu"
    run_log = get_run_logger()
    every = max(1, config.steps // 10)
    key = f"segment-{a}-{b}"
    progress_artifact = ProgressArtifact(artifact_key(key, "training"),
                                         f"Training of segment [{a}, {b}) of {cap.name}: steps done")

    mcmc = {"relocated": 0, "grown": 0}

    def progress(step: int, total: int, info: dict) -> None:  # what a coordinator watches scroll by
        progress_artifact.update(step, total)
        mcmc["relocated"] += info["relocated"]
        mcmc["grown"] += info["grown"]
        if step % every == 0 or step == total:
            run_log.info("segment [%d, %d): step %d/%d, loss %.4f, %d Gaussians (MCMC so far: %d relocated, "
                         "%d grown), %.0f s", a, b, step, total, info["loss"], info["num_gaussians"],
                         mcmc["relocated"], mcmc["grown"], info["wall_s"])

    with reconstruction.deterministic_torch(device):
        result = train_segment(data, init, config, checkpoint=checkpoint if config.checkpoint_every else None,
                               resume_from=resume, seed=seed, device=device, progress=progress)
        report = score_segment(result.model, result.grids, data, init, config, seed=seed, device=device)
    progress_artifact.finish()
    title = f"{cap.name} frames {a}:{b}: footage | render | error"
    sheet = encode_png(contact_sheet(report.sheet_rows, title=title))
    # the UI copy is smaller: a full-width sheet of noisy footage is several MB of PNG, too much to
    # inline in an artifact
    sheet_ui = encode_jpeg(contact_sheet(report.sheet_rows, title=title, max_width=720))
    sheet_ref = s.put_bytes(sheet, MEDIA_PNG)
    model_ref = s.put_bytes(save_model(result.model), reconstruction.SEGMENT_MODEL_MEDIA)
    grids_ref = s.put_bytes(reconstruction.encode_grids(result.grids.camera_ids, result.grids.exposure,
                                                        result.grids.black))
    trained = report.held_out["trained"]
    record = reconstruction.SegmentModel(
        capture=capture, calibration=calibration, frames=(a, b), fps=cap.fps, model=model_ref, grids=grids_ref,
        grid_cameras=tuple(result.grids.camera_ids), held_out_cameras=tuple(config.held_out_cameras),
        gaussians=len(result.model), steps=result.steps, wall_s=result.wall_s,
        held_out_psnr=_finite(trained.psnr), held_out_ssim=_finite(trained.ssim),
        scores=report.to_json(), contact_sheet=sheet_ref,
        history=tuple(reconstruction.EvalSample(step=h.step, wall_s=h.wall_s, psnr=_finite(h.psnr),
                                                ssim=_finite(h.ssim)) for h in result.history),
        config=config.model_dump(mode="json"))
    ref = s.put_record(record)
    publish_table(artifact_key(key, "scores"), report.table(),
                  f"Segment [{a}, {b}) of {cap.name}: held-out scores (per-camera gain/offset fitted on other "
                  f"frames) beside the empty and untrained floors, and the training views")
    publish_image(artifact_key(key, "contact-sheet"), sheet_ui,
                  f"Segment [{a}, {b}) of {cap.name}: footage | render | error")
    try:  # the model is stored: its checkpoint has done its job (gc may take it)
        s.delete_ref(ckpt_name)
    except MissingRefError:
        pass
    return ref


def _mask_loader(s: ArtifactStore, cap: Capture):
    """Performer masks of a synthetic capture (``ground_truth/masks``), or None without them."""
    if cap.ground_truth is None:
        return None
    tree = s.get_tree(cap.ground_truth)
    if not any(p.startswith("masks/") for p in tree):
        return None

    def load(cam: str, frame: int):
        entry = tree.get(f"masks/{cam}/{frame:06d}.exr")
        return None if entry is None else ground_truth.performer_mask(s.get_bytes(entry.digest))

    return load


def _finite(x: float) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


class ViewSpec(BaseModel):
    """A camera at an instant: OpenCV intrinsics (top-left pixel centre at 0) and world-to-camera."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    K: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
    world_to_camera: tuple[tuple[float, float, float, float], ...]
    width: int
    height: int
    time_s: float


@volcap_task(name="render-views", version="1")
def render_views(store: str, segment: ArtifactRef, views: list[ViewSpec], grids_of: str | None = None) -> list[ArtifactRef]:
    """Render a segment model from any cameras at any times (novel views, camera paths): linear
    RGBA half-float EXRs. ``grids_of``: apply that training camera's exposure/black grids."""
    s = ArtifactStore(store)
    seg = s.get_record(segment, reconstruction.SegmentModel)
    return [s.put_bytes(render_segment_exr(s, seg, np.asarray(v.K), np.asarray(v.world_to_camera), v.width, v.height,
                                           v.time_s, grids_of), MEDIA_EXR) for v in views]


def render_segment_exr(s: ArtifactStore, seg: reconstruction.SegmentModel, K: np.ndarray, w2c: np.ndarray,
                       width: int, height: int, time_s: float, grids_of: str | None = None) -> bytes:
    lo, hi = seg.time_range
    if not lo - 0.5 / seg.fps <= time_s <= hi + 0.5 / seg.fps:
        log.warning("time %.3f s is outside the segment's %.3f-%.3f s", time_s, lo, hi)
    model = load_model(s.get_bytes(seg.model))
    camera = reconstruction.splat_camera(K, w2c, width, height)
    with torch.no_grad():
        out = render(evaluate(model, time_s), camera)
        rgb = out["rgb"]
        if grids_of is not None:
            if seg.grids is None or grids_of not in seg.grid_cameras:
                raise ValueError(f"segment has no exposure grids for camera {grids_of!r} "
                                 f"(it has {', '.join(seg.grid_cameras) or 'none'})")
            rgb = reconstruction.decode_grids(s.get_bytes(seg.grids)).apply(rgb, grids_of)
        rgba = torch.cat([rgb, out["alpha"]], dim=-1).cpu().numpy()
    attrs = {"volcap.time_s": float(time_s), "volcap.segment_frames": f"{seg.frames[0]}:{seg.frames[1]}",
             "volcap.K": json.dumps(np.asarray(K).tolist()),
             "volcap.world_to_camera": json.dumps(np.asarray(w2c).tolist())}
    return imageio.encode_exr(rgba, ("R", "G", "B", "A"), pixel_type="half", attributes=attrs)


__all__ = ["ground_truth_calibration", "ground_truth_points", "train_segment_task", "render_views", "ViewSpec",
           "render_segment_exr"]
