"""One segment of a capture: train it, score it against its floors, draw it, render it.

:func:`fit_segment` is what the ``train-segment`` task runs: from the stored records of a capture,
its calibration and its dense points to a :class:`~volcap_core.reconstruction.SegmentModel`
record (its blobs put through ``put_bytes``), the score report and the contact sheets.
:func:`render_segment_exr` renders a stored segment from any camera at any time (novel views, the
``render`` command). Bytes move through ``get_bytes(ref)`` / ``put_bytes(data, media)`` callables,
so nothing here touches a store or Prefect.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from volcap_core import reconstruction
from volcap_core.calibration.record import Calibration, TrackingFrames, decode_tracking_frames
from volcap_core.capture import Capture
from volcap_core.checkpoint import deterministic_torch
from volcap_core.contact_sheet import contact_sheet, encode_jpeg, encode_png
from volcap_core.imageio.write import encode_exr
from volcap_core.pointcloud import PointCloudSequence
from volcap_core.records import MEDIA_BYTES, MEDIA_PNG, ArtifactRef
from volcap_core.splat import evaluate, load_model, render, save_model, train_segment
from volcap_core.splat.report import SegmentScores, score_segment
from volcap_core.splat.train import TrainConfig, View

log = logging.getLogger("volcap.reconstruct")

GetBytes = Callable[[ArtifactRef], bytes]
PutBytes = Callable[[bytes, str], ArtifactRef]
#: ``(time_s, K [3, 3], world_to_camera [4, 4], width, height) -> [height, width] bool``: where
#: the performers' heads are in a camera at a take time
HeadRegion = Callable[[float, np.ndarray, np.ndarray, int, int], np.ndarray]
#: the UI copy of a contact sheet is this wide (px): a full-width sheet of noisy footage is several
#: MB of PNG, too much to inline in a Prefect artifact
UI_SHEET_WIDTH = 720


def tracking_frames(get_bytes: GetBytes, calib: Calibration) -> dict[str, TrackingFrames] | None:
    """The calibration's per-frame tracking cameras, None when it has none. A blob that does not
    decode is a ``ValueError`` naming the blob and the capture."""
    if not calib.tracking_frames:
        return None
    try:
        return decode_tracking_frames(get_bytes(calib.tracking_frames))
    except ValueError as exc:
        raise ValueError(f"calibration of capture {calib.capture!r}: tracking frames "
                         f"{calib.tracking_frames.digest}: {exc}") from exc


@dataclass
class FittedSegment:
    """A trained segment: its record (blobs already put), its scores and the UI contact sheet (JPEG)."""

    record: reconstruction.SegmentModel
    report: SegmentScores
    sheet_ui_jpeg: bytes


def fit_segment(cap: Capture, capture_ref: ArtifactRef, calib: Calibration, calibration_ref: ArtifactRef,
                points: PointCloudSequence, frames: tuple[int, int], config: TrainConfig, seed: int, *,
                get_bytes: GetBytes,
                put_bytes: PutBytes, load_mask: Callable[[str, int], np.ndarray | None] | None = None,
                checkpoint: Callable[[bytes, int], None] | None = None, resume_from: bytes | None = None,
                progress: Callable[[int, int, dict], None] | None = None,
                device: str | None = None, head_region: HeadRegion | None = None) -> FittedSegment:
    """Train take frames [a, b) of a capture (``cap``, stored as ``capture_ref``; likewise the
    calibration), score the result against its floors (empty and
    untrained models, on the held-out views) and draw its contact sheet (footage | render | error).

    ``checkpoint(blob, step)`` is called every ``config.checkpoint_every`` steps; ``resume_from``
    continues such a blob (on CPU the result is bit-identical to an uninterrupted run).
    ``load_mask(camera, take index)``: performer coverage for the performer-only scores (synthetic
    captures). ``device``: None picks CUDA when present. ``head_region(time_s, K, world_to_camera,
    width, height)``: where the performers' heads are in a view (a synthetic capture's
    :func:`~volcap_core.synth.ground_truth.face_region` without coverage), for the face figures of
    the scores' ``regions``; the camera roles come from the calibration.
    """
    a, b = frames
    data = reconstruction.segment_data(cap, calib, tracking_frames(get_bytes, calib), (a, b),
                                       reconstruction.FrameCache(get_bytes), scale=config.image_scale,
                                       load_mask=load_mask)
    init = reconstruction.segment_init(get_bytes, cap, points, data, config.held_out_cameras,
                                       zoom_stride_px=config.init_zoom_stride_px,
                                       scene_flow=config.init_scene_flow)
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    with deterministic_torch(device):
        result = train_segment(data, init, config, checkpoint=checkpoint if config.checkpoint_every else None,
                               resume_from=resume_from, seed=seed, device=device, progress=progress)
        report = score_segment(result.model, result.grids, data, init, config, seed=seed, device=device,
                               roles={c.id: "static" if c.static else "tracking" for c in calib.cameras},
                               head_region=None if head_region is None else _view_head_region(head_region))
    title = f"{cap.name} frames {a}:{b}: footage | render | error"
    sheet_ref = put_bytes(encode_png(contact_sheet(report.sheet_rows, title=title)), MEDIA_PNG)
    sheet_ui = encode_jpeg(contact_sheet(report.sheet_rows, title=title, max_width=UI_SHEET_WIDTH))
    model_ref = put_bytes(save_model(result.model), reconstruction.SEGMENT_MODEL_MEDIA)
    grids_ref = put_bytes(reconstruction.encode_grids(result.grids.camera_ids, result.grids.exposure,
                                                      result.grids.black), MEDIA_BYTES)
    trained = report.held_out["trained"]
    record = reconstruction.SegmentModel(
        capture=capture_ref, calibration=calibration_ref, frames=(a, b), fps=cap.fps, model=model_ref,
        grids=grids_ref, grid_cameras=tuple(result.grids.camera_ids), held_out_cameras=tuple(config.held_out_cameras),
        gaussians=len(result.model), steps=result.steps, wall_s=result.wall_s,
        held_out_psnr=_finite(trained.psnr), held_out_ssim=_finite(trained.ssim),
        scores=report.to_json(), contact_sheet=sheet_ref,
        history=tuple(reconstruction.EvalSample(step=h.step, wall_s=h.wall_s, psnr=_finite(h.psnr),
                                                ssim=_finite(h.ssim)) for h in result.history),
        config=config.model_dump(mode="json"),
        backend=result.backend.name if result.backend else None,
        backend_reason=result.backend.reason if result.backend else None)
    return FittedSegment(record, report, sheet_ui)


def _view_head_region(head_region: HeadRegion) -> Callable[[View], np.ndarray]:
    def of_view(v: View) -> np.ndarray:
        cam = v.camera
        return head_region(v.time, cam.K.detach().cpu().numpy(), cam.world_to_camera.detach().cpu().numpy(),
                           cam.width, cam.height)
    return of_view


def _finite(x: float | None) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def render_segment_exr(get_bytes: GetBytes, seg: reconstruction.SegmentModel, K: np.ndarray, w2c: np.ndarray,
                       width: int, height: int, time_s: float, grids_of: str | None = None,
                       near_m: float | None = None) -> bytes:
    """The segment from camera (K [3, 3] OpenCV, world-to-camera [4, 4]) at ``time_s`` seconds on
    the take's clock: linear RGBA half-float EXR bytes, the camera in the header. ``grids_of``:
    apply that training camera's exposure/black-level grids (what that camera would have recorded).
    ``near_m``: the near clipping plane (metres of camera depth; None: the renderer's default)."""
    lo, hi = seg.time_range
    if not lo - 0.5 / seg.fps <= time_s <= hi + 0.5 / seg.fps:
        log.warning("time %.3f s is outside the segment's %.3f-%.3f s", time_s, lo, hi)
    if grids_of is not None and (seg.grids is None or grids_of not in seg.grid_cameras):
        raise ValueError(f"segment has no exposure grids for camera {grids_of!r} "
                         f"(it has {', '.join(seg.grid_cameras) or 'none'})")
    model = load_model(get_bytes(seg.model))
    camera = reconstruction.splat_camera(K, w2c, width, height, near=near_m)
    with torch.no_grad():
        out = render(evaluate(model, time_s), camera)
        rgb = out["rgb"]
        if grids_of is not None:
            rgb = reconstruction.decode_grids(get_bytes(seg.grids)).apply(rgb, grids_of)
        rgba = torch.cat([rgb, out["alpha"]], dim=-1).cpu().numpy()
    attrs = {"volcap.time_s": float(time_s), "volcap.segment_frames": f"{seg.frames[0]}:{seg.frames[1]}",
             "volcap.K": json.dumps(np.asarray(K).tolist()),
             "volcap.world_to_camera": json.dumps(np.asarray(w2c).tolist())}
    return encode_exr(rgba, ("R", "G", "B", "A"), pixel_type="half", attributes=attrs)


__all__ = ["FittedSegment", "HeadRegion", "fit_segment", "render_segment_exr", "tracking_frames", "UI_SHEET_WIDTH"]
