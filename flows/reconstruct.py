"""The reconstruct flow: an ingested capture in, one trained Poly4DGS model per segment out.

Segments and training settings come from a named preset (:mod:`volcap_core.production.presets`), the same
table a production spec's ``quality:`` reads: the same capture, frames and preset give the same
segments here as in a production (overlapping neighbours included; each is trained on its own), and
each segment trains to the same Gaussian budget, the plan's (``--max-gaussians`` replaces it).
"""

from __future__ import annotations

from collections.abc import Sequence

from prefect import flow, get_run_logger

from flows.calibrate import (calibrate_capture, known_points_spec, point_cloud_for_frames, static_calibration_options,
                             tracking_calibration_options)
from flows.segment_runs import SegmentJob, train_segments
from tasks.reconstruct import ground_truth_calibration, ground_truth_points
from volcap_core import reconstruction
from volcap_core.calibration.record import Calibration
from volcap_core.capture import Capture
from volcap_core.production.presets import named_preset
from volcap_core.production.segments import SegmentPlan
from volcap_core.production.spec import CaptureInfo
from volcap_core.splat.train import TrainConfig
from volcap_core.store import ArtifactStore


def plan_reconstruction(info: CaptureInfo, frames: tuple[int, int], preset: str,
                        segment_frames: int | None = None) -> SegmentPlan:
    """The segments of take indices ``[frames[0], frames[1])``: the preset's plan (its budget at
    the capture's largest image, its overlap), at most ``segment_frames`` frames each when given
    (``--segment-frames``: the preset's ``max_segment_frames`` replaced, as a spec would)."""
    quality = named_preset(preset)
    if segment_frames is not None:
        quality = quality.with_overrides(max_segment_frames=segment_frames)
    return quality.plan_segments(frames, info.width, info.height)


def segment_configs(plan: SegmentPlan, preset: str, *, degrees: str = "poly4dgs", held_out: Sequence[str] = (),
                    steps: int | None = None, max_gaussians: int | None = None,
                    mask_alpha: tuple[float, int] | None = None,
                    set_frozen_from: float | None = None) -> list[TrainConfig]:
    """Each segment's TrainConfig: the preset's (its schedule stretched to ``steps`` when given),
    with the segment's Gaussian budget from the plan (``gaussians_per_frame`` a frame within the
    preset's cap), as a production's train-segment step trains it; ``max_gaussians`` replaces that
    budget for every segment. ``mask_alpha``: ``(weight, every)``, the preset's
    ``mask_alpha_weight`` and ``mask_alpha_every`` replaced (the alpha loss on the capture's masks).
    ``set_frozen_from``: the preset's replaced (0: the set trains to the end; None: the preset's)."""
    quality = named_preset(preset) if steps is None else named_preset(preset).with_steps(steps)
    if mask_alpha is not None:
        quality = quality.with_overrides(mask_alpha_weight=mask_alpha[0], mask_alpha_every=mask_alpha[1])
    if set_frozen_from is not None:
        quality = quality.with_overrides(set_frozen_from=set_frozen_from or None)
    return [quality.train_config(degrees=degrees, held_out=held_out, max_gaussians=max_gaussians or seg.gaussians)
            for seg in plan.segments]


def segment_summary(rec: reconstruction.SegmentModel, ref) -> dict:
    """What a coordinator reads of a trained segment: held-out PSNR/SSIM under the protocol, raw,
    on the performers, and the floors measured on the same views (empty and untrained models)."""
    held = rec.scores.get("held_out", {})
    trained, empty, initial = held.get("trained", {}), held.get("empty", {}), held.get("initial", {})
    training = rec.scores.get("training", {})
    return {"model": ref.model_dump(mode="json"), "frames": list(rec.frames), "gaussians": rec.gaussians,
            "held_out_psnr": rec.held_out_psnr, "held_out_ssim": rec.held_out_ssim,
            "held_out_psnr_raw": trained.get("psnr_raw"),
            "held_out_psnr_performers": trained.get("psnr_performers"),
            "held_out_ssim_performers": trained.get("ssim_performers"),
            "floor_empty_psnr": empty.get("psnr"), "floor_empty_ssim": empty.get("ssim"),
            "floor_initial_psnr": initial.get("psnr"), "floor_initial_ssim": initial.get("ssim"),
            "training_psnr": training.get("psnr"), "training_ssim": training.get("ssim"),
            "scores": rec.scores,
            "contact_sheet": rec.contact_sheet.model_dump(mode="json") if rec.contact_sheet else None,
            "train_wall_s": round(rec.wall_s, 3)}


@flow(name="reconstruct", persist_result=False)
def reconstruct_flow(store: str, capture: str, frames: tuple[int, int] | None = None, preset: str = "demo",
                     degrees: str = "poly4dgs", segment_frames: int | None = None,
                     calibration: str | None = None, points: str | None = None,
                     held_out: list[str] | None = None, points_per_frame: int | None = None,
                     max_gaussians: int | None = None, seed: int = 0, ground_truth: bool = False,
                     steps: int | None = None, allow_unregistered: bool = False,
                     known_distance: tuple[str, str, float] | None = None,
                     known_points: dict | None = None, min_pair_inliers: int | None = None,
                     mask_alpha: tuple[float, int] | None = None, set_frozen_from: float | None = None) -> dict:
    """Train the segments of ``capture`` (a ref name such as ``captures/demo`` or a digest).

    ``calibration`` / ``points``: refs of a Calibration and a PointCloudSequence. When omitted, the
    capture is calibrated here (the calibrate flow's tasks, cached) and dense points are computed
    for the frames trained, matched at the preset's ``dense_scale`` of the footage's resolution as a
    production matches them (at most ``points_per_frame`` each when given; training thins them to
    its own budget, so the default keeps every point for the static/moving split to see).
    ``ground_truth=True`` uses a synthetic
    capture's ground truth instead (true cameras, points from true depth): benchmarks, fast tests.
    ``allow_unregistered``, ``known_distance``, ``known_points``, ``min_pair_inliers``: the calibration run here, as
    ``calibrate_flow`` takes them (the same settings give the same cached calibration); refused
    with ``calibration`` or ``ground_truth``, which run none.

    Segments: :func:`plan_reconstruction` (``segment_frames`` caps their length). Training:
    :func:`segment_configs`, the preset's TrainConfig stretched to ``steps`` when given, each
    segment to its plan's Gaussian budget unless ``max_gaussians`` is given; ``mask_alpha``:
    ``(weight, every)``, the alpha loss on the capture's own masks (a capture without masks trains
    as without it); ``set_frozen_from``: the fraction of the steps after which the set stops
    training (0: never; None: the preset's).
    Returns the segment model refs and their held-out PSNR/SSIM and training wall time, each with
    its frames and its core (the frames no neighbour shares).
    """
    log = get_run_logger()
    calibrating = {k: v for k, v in (("allow_unregistered", allow_unregistered), ("known_distance", known_distance),
                                     ("known_points", known_points), ("min_pair_inliers", min_pair_inliers)) if v}
    if calibrating and (calibration or ground_truth):
        raise ValueError(f"{', '.join(calibrating)}: settings of the calibration reconstruct runs itself, which it "
                         f"does not run with {'a given calibration' if calibration else 'the ground truth'}")
    known = known_points_spec(known_points, known_distance)
    s = ArtifactStore(store)
    capture_ref = s.resolve(capture)
    cap = s.get_record(capture_ref, Capture)
    a, b = cap.take_range(frames)
    # planned before anything runs: a segment length the preset's overlap cannot take fails here
    plan = plan_reconstruction(CaptureInfo.from_capture(cap), (a, b), preset, segment_frames)

    if calibration:
        calib_ref = s.resolve(calibration)
    elif ground_truth:
        calib_ref = ground_truth_calibration(store, capture_ref)
    else:
        calib_ref = calibrate_capture(store, capture_ref,
                                      static_calibration_options(allow_unregistered, known_distance=known_distance,
                                                                 min_pair_inliers=min_pair_inliers),
                                      known, tracking_calibration_options(allow_unregistered))
    held = (held_out if held_out is not None
            else reconstruction.default_held_out(cap, calibration=s.get_record(calib_ref, Calibration),
                                                 tracking=named_preset(preset).held_out_tracking))
    # held-out cameras take no part in the initial points: their footage must not reach the model
    if points:
        points_ref = s.resolve(points)
    elif ground_truth:
        # true depth of every pixel of every camera is millions of points: a budget is needed here
        points_ref = ground_truth_points(store, capture_ref, calib_ref, points_per_frame or 150_000, seed,
                                         exclude_cameras=held)
    else:
        # matched at the preset's dense_scale, as a production's dense-points step matches them (the
        # same preset, the same cached frames)
        points_ref = point_cloud_for_frames(store, capture_ref, calib_ref, list(range(a, b)), points_per_frame, seed,
                                            scale=named_preset(preset).dense_scale, exclude_cameras=held)
    log.info("capture %s: %s calibration %s, points %s", cap.name,
             "given" if calibration else "ground-truth" if ground_truth else "estimated", calib_ref.digest,
             points_ref.digest)
    configs = segment_configs(plan, preset, degrees=degrees, held_out=held, steps=steps, max_gaussians=max_gaussians,
                              mask_alpha=mask_alpha, set_frozen_from=set_frozen_from)
    log.info("capture %s: %d segment(s) of frames %d:%d (%d shared by neighbours), preset %s, held out %s",
             cap.name, len(plan.segments), a, b, plan.overlap, preset, ", ".join(held) or "none")
    jobs = [SegmentJob(capture=capture_ref, calibration=calib_ref, points=points_ref, frames=seg.frames,
                       config=config, seed=seed)
            for seg, config in zip(plan.segments, configs)]
    # in this process, through the one segment fan-out a production uses (flows/segment_runs.py)
    models = train_segments(store, jobs, "local", max_attempts=1, poll_interval_s=0.0)
    report = [{**segment_summary(s.get_record(ref, reconstruction.SegmentModel), ref), "core": list(seg.core)}
              for seg, ref in zip(plan.segments, models)]
    return {"capture": capture_ref.model_dump(mode="json"), "calibration": calib_ref.model_dump(mode="json"),
            "points": points_ref.model_dump(mode="json"), "segments": report}
