"""The facerig_pairs flow: an actor's ingested Face Rig capture in, its Gaussian-splat pair dataset out.

It reads like the paper's "Training Data Generation" (``docs/enhancer.md``, "Gaussian-splat pairs")::

    windows    the preset's sub-sequences, spread evenly over the take (face_windows)
    calibrate  the capture's calibration (the calibrate flow's tasks), or one given (a studio's
               target calibration), or a synthetic capture's ground truth; dense points of the
               windows' frames likewise
    models     per sub-sequence an HQ model (face_hq_gaussians_per_frame a frame) and an LQ model
               (a count a frame drawn from the LQ range, seeded per sub-sequence): train-segment
               runs with the preset's TrainConfig, every model at once, through the production's
               segment fan-out (flows/segment_runs.py: runs of the train-segment deployment on
               GPU workers, or task runs in this process, as ``segment_runs`` chooses)
    paths      per sub-sequence face_camera_paths camera paths around the head its HQ model holds
    render     both models along every path of their sub-sequence (one task per sub-sequence, each
               model loaded once): half RGBA EXR at pair_resolution, the Face Rig ->
               Scene Rig colour matrix applied, the LQ's exact flow per frame pair
    dataset    a PairDataset with the split by sub-sequence

Every step is a cached volcap task: a rerun recomputes nothing.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from prefect import flow, get_run_logger, unmapped

from flows.calibrate import calibrate_capture, point_cloud_for_frames
from flows.segment_runs import SegmentJob, SegmentRuns, segment_runs_mode, train_segments
from tasks.facerig import face_paths, pair_dataset, render_pairs
from tasks.reconstruct import ground_truth_calibration, ground_truth_points
from volcap_core import reconstruction
from volcap_core.calibration.record import Calibration
from volcap_core.capture import Capture
from volcap_core.enhance.production import face_windows
from volcap_core.production.presets import QualityPreset, named_preset
from volcap_core.records import ArtifactRef
from volcap_core.splat_pairs import lq_gaussians_per_frame
from volcap_core.store import ArtifactStore


def face_model_jobs(capture: ArtifactRef, calibration: ArtifactRef, points: ArtifactRef, windows: list[list[int]],
                    quality: QualityPreset, held_out: list[str], lq_counts: list[int], seed: int = 0
                    ) -> list[SegmentJob]:
    """The two segment trainings of each sub-sequence, HQ then LQ, in window order.

    ``windows``: each sub-sequence's consecutive capture frames; ``lq_counts``: its LQ Gaussians a
    frame. Both models train on the window's frames with the preset's TrainConfig (``held_out``
    cameras out of the loss), the HQ to ``face_hq_gaussians_per_frame`` × frames Gaussians, the LQ
    to its count × frames: the budgets are per frame, as the paper's counts are."""
    if len(lq_counts) != len(windows):
        raise ValueError(f"{len(lq_counts)} LQ count(s) for {len(windows)} sub-sequence(s)")
    return [SegmentJob(capture=capture, calibration=calibration, points=points, frames=(w[0], w[-1] + 1),
                       config=quality.train_config(held_out=held_out, max_gaussians=per_frame * len(w)), seed=seed)
            for w, lq in zip(windows, lq_counts) for per_frame in (quality.face_hq_gaussians_per_frame, lq)]


@flow(name="facerig-pairs", persist_result=False)
def facerig_pairs_flow(store: str, capture: str, actor: str, quality: str | QualityPreset = "preview",
                       calibration: str | None = None, points: str | None = None, ground_truth: bool = False,
                       colour: str | None = None, lq_range: tuple[int, int] | None = None,
                       lq_range_source: str = "measured", lq_measurement: str | None = None,
                       seed: int = 0, segment_runs: SegmentRuns = "auto", max_attempts: int = 3,
                       poll_interval_s: float = 5.0) -> dict[str, Any]:
    """The pair dataset of ``actor``'s Face Rig ``capture`` (a ref name or digest) at ``quality``
    (a preset name or a resolved preset: its ``face_*`` sizes, ``pair_resolution`` and the
    segment TrainConfig).

    ``calibration`` / ``points``: refs of the capture's Calibration and PointCloudSequence; when
    omitted, the calibrate flow's tasks calibrate the capture and match dense points of the
    windows' frames at the preset's ``dense_scale`` (``ground_truth=True``: a synthetic capture's
    true cameras and points from true depth instead, for benchmarks and tests). ``colour``: a
    ``calibrate-colour`` record (Face Rig -> Scene Rig) applied to every render; None: none.
    ``lq_range``: the LQ counts per frame to draw from, e.g. the measured range of the Scene Rig
    reconstruction (``volcap_core.production.lq_range``), recorded with ``lq_range_source``; None:
    the preset's ``face_lq_gaussians``, recorded as ``preset``. ``lq_measurement``: the digest of
    the ``lq-range`` artifact it was measured in, recorded in the dataset's parameters (None:
    nothing recorded). ``segment_runs`` / ``max_attempts`` / ``poll_interval_s``: how the models
    train, as the production's segments do (``auto`` | ``local`` | ``deployment``:
    ``flows.segment_runs.segment_runs_mode``; a production passes its own mode).

    Returns the dataset's ref and what it was made of (calibration, points, each sub-sequence's
    frames, models and LQ count, the number of sequences).
    """
    log = get_run_logger()
    mode = segment_runs_mode(segment_runs)   # before any work: a missing deployment is refused at once
    q = named_preset(quality) if isinstance(quality, str) else quality
    s = ArtifactStore(store)
    cap_ref = s.resolve(capture)
    cap = s.get_record(cap_ref, Capture)
    windows = face_windows(cap.frame_count, q.face_subsequences, q.face_subsequence_frames)
    if lq_range is None:
        lq_range, lq_range_source = tuple(q.face_lq_gaussians), "preset"

    if calibration:
        calib_ref = s.resolve(calibration)
    elif ground_truth:
        calib_ref = ground_truth_calibration(store, cap_ref)
    else:
        calib_ref = calibrate_capture(store, cap_ref)
    held = reconstruction.default_held_out(cap, calibration=s.get_record(calib_ref, Calibration),
                                           tracking=q.held_out_tracking)
    if points:
        points_ref = s.resolve(points)
    elif ground_truth:
        points_ref = ground_truth_points(store, cap_ref, calib_ref, q.face_hq_gaussians_per_frame, seed,
                                         exclude_cameras=held)
    else:
        points_ref = point_cloud_for_frames(store, cap_ref, calib_ref, sorted({f for w in windows for f in w}),
                                            scale=q.dense_scale, exclude_cameras=held)

    # two models per sub-sequence, budgets a frame times its frames: the preset's segment training
    lq_counts = [lq_gaussians_per_frame(lq_range, seed, i) for i in range(len(windows))]
    jobs = face_model_jobs(cap_ref, calib_ref, points_ref, windows, q, held, lq_counts, seed)
    log.info("Face Rig pairs of %s: %d sub-sequence(s) of %d frame(s) of capture %s, HQ %d Gaussians a frame, "
             "LQ %s a frame (range %s, %s), held out %s; models %s", actor, len(windows), len(windows[0]), cap.name,
             q.face_hq_gaussians_per_frame, lq_counts, list(lq_range), lq_range_source, ", ".join(held) or "none",
             mode)
    models = train_segments(store, jobs, mode, max_attempts, poll_interval_s)
    hq_models, lq_models = models[0::2], models[1::2]

    # camera paths around each sub-sequence's head, from its HQ model
    around = np.median([c.mount.look_at_m for c in cap.rig.cameras], axis=0).tolist()   # where the rig aims
    times = [[cap.frame_time(f) for f in w] for w in windows]
    futures = [face_paths.submit(store, hq_models[i], times[i], q.face_camera_paths, q.pair_resolution,
                                 q.pair_resolution, seed + i, around) for i in range(len(windows))]
    path_refs = [f.result() for f in futures]

    colour_ref = s.resolve(colour) if colour else None
    futures = render_pairs.map(unmapped(store), hq_models, lq_models, path_refs, list(range(len(windows))),
                               windows, lq_counts, unmapped(q.face_hq_gaussians_per_frame), unmapped(colour_ref))
    sequences = [ref for f in futures for ref in f.result()]
    dataset = pair_dataset(store, sequences, actor, cap_ref, calib_ref, len(windows), list(lq_range),
                           lq_range_source, q.pair_resolution,
                           {"subsequences": q.face_subsequences, "subsequence_frames": q.face_subsequence_frames,
                            "camera_paths": q.face_camera_paths,
                            "hq_gaussians_per_frame": q.face_hq_gaussians_per_frame, "windows": windows,
                            "held_out": held, **({"lq_measurement": lq_measurement} if lq_measurement else {})},
                           seed, colour=colour_ref)
    log.info("Face Rig pairs of %s: %d sequence(s) -> %s", actor, len(sequences), dataset.digest)
    return {"dataset": dataset, "capture": cap_ref, "calibration": calib_ref, "points": points_ref,
            "subsequences": [{"frames": w, "hq": hq, "lq": lq, "lq_gaussians": n}
                             for w, hq, lq, n in zip(windows, hq_models, lq_models, lq_counts)],
            "sequences": len(sequences)}


__all__ = ["face_model_jobs", "facerig_pairs_flow"]
