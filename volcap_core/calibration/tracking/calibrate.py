"""The tracking-camera stage: every camera observed and initialised (:func:`prepare_tracking`),
then solved (:func:`solve_tracking`).

The refinement can run from several starts along the zoom/dolly valley (:func:`dolly_zoom_start`,
``focal_scale_starts``; one by default), each camera keeping its lowest-cost result; then the 2D-3D
matches are found again guided by that solution
(:func:`~volcap_core.calibration.tracking.observe.guided_observations`) and the solve is refined
once more on them. The lens each frame was undistorted with is
:attr:`~volcap_core.calibration.tracking.solve.TrackingSolution.distortion`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from volcap_core.calibration.geometry import camera_centre
from volcap_core.calibration.tracking.lens import (ZoomLens, frame_undistorter, lens_corner_shift_px,
                                                    smooth_encoder_focal)
from volcap_core.calibration.tracking.observe import (StaticReference, TrackingObservations, guided_observations,
                                                       observe_tracking_camera)
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.calibration.tracking.solve import TrackingSolution, initialise_tracking, refine_tracking


@dataclass
class TrackingProblem:
    """Observations and initial values of every tracking camera (see :func:`prepare_tracking`).
    ``principal``: [B, 2] or per camera [T, 2]; ``distortion``: per camera the lens [T, 5|8] its
    observations were undistorted with (None: none)."""

    ids: list[str]
    obs: list[TrackingObservations]
    inits: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    priors_px: list[np.ndarray]
    principal: np.ndarray | list[np.ndarray]
    mounts: list[np.ndarray]
    info: dict
    distortion: list[np.ndarray | None] | None = None
    #: the static model the observations were matched to (for the guided matching; None: none)
    reference: StaticReference | None = None


def prepare_tracking(frames: Mapping[str, Sequence[np.ndarray]],
                     encoder: Mapping[str, tuple[np.ndarray, np.ndarray]],
                     focal_px_per_mm: Mapping[str, float], mounts: Mapping[str, np.ndarray],
                     reference: StaticReference, options: TrackingOptions = TrackingOptions(),
                     lenses: Mapping[str, ZoomLens | None] | None = None) -> TrackingProblem:
    """Features, matches, the encoder prior and the initial values of every tracking camera.

    ``frames``: id -> T linear RGB images [H, W, 3] (take indices 0..T-1); ``encoder``: id ->
    (take indices [S], focal mm [S]) lens-encoder readings; ``focal_px_per_mm``: id -> sensor
    pixels per mm; ``mounts``: id -> nominal centre [3] (metres); ``reference``: the static model;
    ``lenses``: id -> its zoom lens (:func:`~volcap_core.calibration.tracking.lens.zoom_lens`;
    absent or None: a pinhole with its principal point at the image centre). With
    ``options.zoom_distortion`` a camera's frame t is undistorted with its lens at the smoothed
    encoder focal of frame t (the prior, known before the solve): a focal ε off moves an undistorted
    point by only ~3 ε k1 r² of its radius (docs/calibration.md, "Lens distortion").
    """
    ids = sorted(frames)
    obs, inits, priors, pps, dists, info = [], [], [], [], [], {}
    for cid in ids:
        seq = frames[cid]
        idx, mm = encoder[cid]
        prior = smooth_encoder_focal(idx, mm, len(seq), options.smooth_lambda) * focal_px_per_mm[cid]
        h, w = seq[0].shape[:2]
        pp = np.tile([(w - 1) / 2.0, (h - 1) / 2.0], (len(seq), 1))
        lens = (lenses or {}).get(cid) if options.zoom_distortion else None
        coeffs, undistort, extra = None, None, {}
        if lens is not None:
            coeffs, lens_pp = lens(prior / focal_px_per_mm[cid])
            if lens_pp is not None:
                pp = np.asarray(lens_pp, np.float64).reshape(len(seq), 2)
            undistort = frame_undistorter(prior, pp, coeffs)
            shift = lens_corner_shift_px(prior, pp, coeffs, w, h)
            extra = {"zoom_lens": 1.0, "lens_corner_shift_px_mean": float(shift.mean()),
                     "lens_corner_shift_px_max": float(shift.max())}
        ob = observe_tracking_camera(seq, reference, options, undistort)
        R, C, f, st = initialise_tracking(ob, prior, np.asarray(mounts[cid], np.float64), pp, options)
        obs.append(ob)
        inits.append((R, C, f))
        priors.append(prior)
        pps.append(pp)
        dists.append(coeffs)
        info[cid] = {**st, "observe_s": ob.seconds, **extra}
    return TrackingProblem(ids, obs, inits, priors, pps, [np.asarray(mounts[c], np.float64) for c in ids], info,
                           dists, reference)


def dolly_zoom_start(init: tuple[np.ndarray, np.ndarray, np.ndarray], obs: TrackingObservations,
                     scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An initial sequence (R [T, 3, 3], C [T, 3], f [T]) with every focal scaled by ``scale`` and the
    centre moved back along the mean view axis by ``(scale - 1)`` x the median distance of the
    2D-3D points, so the scene keeps its size in the image (a zoom-in looks like a dolly-in)."""
    R, C, f = init
    axis = R[:, 2, :].mean(0)
    axis /= np.linalg.norm(axis)
    dist = float(np.median(np.linalg.norm(obs.m3_X - C.mean(0), axis=1))) if len(obs.m3_X) else 0.0
    return R, C - (scale - 1.0) * dist * axis, f * scale


def solve_tracking(problem: TrackingProblem, options: TrackingOptions = TrackingOptions()
                   ) -> dict[str, TrackingSolution]:
    """Refine a prepared problem (``options.mode`` picks priors / free / independent): once from
    each of ``options.focal_scale_starts`` along the zoom/dolly valley, keeping each camera's
    lowest-cost solution (``stats["focal_scale_start"]`` says which)."""
    if not problem.ids:
        return {}
    best: list[TrackingSolution | None] = [None] * len(problem.ids)
    for scale in options.focal_scale_starts:
        inits = [dolly_zoom_start(i, ob, scale) for i, ob in zip(problem.inits, problem.obs)]
        sols = refine_tracking(problem.obs, inits, problem.priors_px, problem.principal, problem.mounts, options)
        for k, s in enumerate(sols):
            s.stats["focal_scale_start"] = scale
            if best[k] is None or s.stats["cost"] < best[k].stats["cost"]:
                best[k] = s
    if options.guided_radius_px is not None and problem.reference is not None:
        best = _guided_round(problem, best, options)
    out = {}
    for k, (cid, s) in enumerate(zip(problem.ids, best)):
        s.stats.update(problem.info[cid])
        if problem.distortion is not None and problem.distortion[k] is not None:
            s.distortion = np.asarray(problem.distortion[k], np.float64).copy()
        out[cid] = s
    return out


def _guided_round(problem: TrackingProblem, best: list[TrackingSolution], options: TrackingOptions
                  ) -> list[TrackingSolution]:
    """Each camera's solution refined once more on its guided 2D-3D matches, kept where they are at
    least as many as the first solve's inliers (a solve too far off finds fewer)."""
    guided = [guided_observations(ob, problem.reference, s.K, s.world_to_camera, options)
              for ob, s in zip(problem.obs, best)]
    inits = [(s.world_to_camera[:, :3, :3], camera_centre(s.world_to_camera), s.K[:, 0, 0]) for s in best]
    sols = refine_tracking(guided, inits, problem.priors_px, problem.principal, problem.mounts, options)
    out = []
    for s0, s1, g in zip(best, sols, guided):
        if len(g.m3_frame) >= s0.stats["reprojection_3d_px_inliers"]:
            s1.stats["focal_scale_start"] = s0.stats.get("focal_scale_start", 1.0)
            s1.stats["guided_matches_3d"] = len(g.m3_frame)
            s1.stats["first_solve_inliers_3d"] = s0.stats["reprojection_3d_px_inliers"]
            out.append(s1)
        else:
            s0.stats["guided_matches_3d"] = len(g.m3_frame)
            out.append(s0)
    return out


def calibrate_tracking_cameras(frames: Mapping[str, Sequence[np.ndarray]],
                               encoder: Mapping[str, tuple[np.ndarray, np.ndarray]],
                               focal_px_per_mm: Mapping[str, float], mounts: Mapping[str, np.ndarray],
                               reference: StaticReference, options: TrackingOptions = TrackingOptions(),
                               lenses: Mapping[str, ZoomLens | None] | None = None
                               ) -> dict[str, TrackingSolution]:
    """Register and refine every tracking camera at every frame: :func:`prepare_tracking` then
    :func:`solve_tracking`. Returns id -> :class:`~volcap_core.calibration.tracking.solve.TrackingSolution`;
    {} for no tracking camera. ``lenses``: id -> zoom lens
    (:func:`~volcap_core.calibration.tracking.lens.zoom_lens`), see :func:`prepare_tracking`."""
    if not frames:
        return {}
    return solve_tracking(prepare_tracking(frames, encoder, focal_px_per_mm, mounts, reference, options, lenses),
                          options)
