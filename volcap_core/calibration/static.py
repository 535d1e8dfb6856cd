"""Static wide cameras: one calibration from the middle frame (or several instants pooled), in metres
and the stage frame.

:func:`calibrate_static_cameras` runs these stages in order, each a function of the previous ones'
output:

1. the rig's priors (:func:`_rig_priors`): each camera's intrinsics, measured when the rig carries
   a lens calibration (its own or its lens group's), else nominal (the nominal focal in pixels, a
   centred principal point, no distortion); its pose at its nominal mount; its mount's position;
2. sparse SfM with pycolmap (:func:`volcap_core.calibration.sfm.reconstruct_static`): SIFT,
   exhaustive matching, then triangulation from the nominal mount poses (seeded, default) or
   COLMAP's incremental mapper; a distorted (or non-square) camera is then rectified into a square
   pinhole (observations, images and plates resampled), and a camera with too few observations is
   left out (:func:`_sparse_model`);
3. incremental path only (seeded poses are in the stage frame already): a robust similarity of the
   camera centres onto the mounts, then a robust point-to-plane ICP of the sparse points onto the
   lidar scan (:func:`_into_stage_frame`);
4. bundle adjustment in torch with the lidar as a prior on the points, a focal prior around the
   rig's intrinsics and a centre prior around the mounts (:mod:`volcap_core.calibration.bundle`);
   a camera its inliers do not support is left out; without a scan, the stage frame and scale
   from the mounts or a known distance (:func:`frame_without_lidar`) (:func:`_first_adjustment`);
5. patch matching of the background plates between the cameras of step 4, guided through the
   lidar scan (:mod:`volcap_core.calibration.guided`, many times the observations, over the whole
   image), and a second bundle adjustment on those tracks that also refines the principal points
   and a rectified camera's radial k1, k2, and leaves the centres to the data (the mounts only a
   weak prior); without a scan the same matching runs through a plane-sweep surface of the plates
   (:func:`surface_from_plates`), the centres held by the mounts, and the stage frame taken again
   (:func:`_guided_adjustment`);
6. optionally, direct photometric refinement against the lidar
   (:mod:`volcap_core.calibration.photometric`): every textured background pixel seen by two cameras
   votes (off by default: it did not improve the demo capture) (:func:`_photometric_refinement`);
7. the sparse points re-triangulated from the final cameras (:func:`_final_model`), each
   camera's support measured under them (:func:`_final_support`), and a camera whose final sigma
   exceeds the bounds refused or left out (:func:`_refuse_uncertain`).

A step that did not run (step 5 turned off, or without a surface to guide it) is said in
:attr:`StaticCalibration.warnings` and logged.

Every camera's support is measured on the SfM's observations (step 2) and on the inliers of step 4's
adjustment (:func:`camera_support`: observation count, and the pose's standard deviation with the
points held fixed, a lower bound); after step 5 the standard deviations reported are step 5's
covariance, which counts what the principal point leaves open
(:attr:`~volcap_core.calibration.bundle.BundleResult.sigma`), or step 4's when step 5 did not run. A camera below
``options.min_observations`` or above the uncertainty bounds is unsupported: with
``options.allow_unregistered`` it is left out (listed in ``unregistered`` with the reason), otherwise
:class:`UnsupportedCameraError` names it. A seeded camera without observations is never returned as
calibrated (it would sit at its mount).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np

from hardware.rig import Rig, RigCamera
from volcap_core.calibration.bundle import BundleOptions, BundleResult, CameraSigma, bundle_adjust, camera_parameters
from volcap_core.calibration.dense import DenseOptions, dense_points, sweep_range
from volcap_core.calibration.distortion import Distortion, undistort_valid_mask
from volcap_core.calibration.errors import KnownDistanceError, UnsupportedCameraError
from volcap_core.calibration.focal_prior import (MEASURED_FOCAL_SIGMA_REL, RELEASE_CHI2, FocalDecision,
                                                 adjust_with_held_focals)
from volcap_core.calibration.geometry import (Similarity, camera_centre, camera_gaps, depths_in_view, look_at_rotation,
                                              pose_matrix, robust_umeyama, rotation_angle_deg,
                                              triangulate_points)
from volcap_core.calibration.guided import GuidedMatchOptions, guided_tracks
from volcap_core.calibration.lidar import LidarScan, align_to_lidar
from volcap_core.calibration.photometric import PhotometricOptions, refine_photometric
from volcap_core.calibration.sfm import (RECTIFY_MARGIN_PX, Intrinsics, SparseModel, StaticSfmOptions,
                                         raw_from_rectified, reconstruct_static, rectify_static_inputs)
from volcap_core.stage import stage_volume

#: calibration messages (warnings a user acts on, each focal decision)
log = logging.getLogger("volcap.calibrate")


#: the prior (1σ) of the step-5 adjustment's corrections to a lens calibration's radial k1 and k2
DISTORTION_SIGMA = 0.002
#: the prior (1σ, px) of the step-5 adjustment on a measured principal point
MEASURED_PRINCIPAL_SIGMA_PX = 0.5


@dataclass(frozen=True)
class StaticCalibrationOptions:
    sfm: StaticSfmOptions = StaticSfmOptions()
    #: seed the SfM with the rig's nominal mount poses (False: COLMAP's incremental mapper alone)
    seeded: bool = True
    #: step 4's adjustment; its covariance (the sigma stated when step 5 does not run) counts the
    #: observations at their residuals' spread, not at the 1 px weighting (``sigma_from_residuals``)
    bundle: BundleOptions = BundleOptions(focal_sigma_rel=0.03, centre_sigma_m=0.03, sigma_from_residuals=True)
    #: lidar-guided patch matching after the first adjustment (None skips it and the second one)
    guided: GuidedMatchOptions | None = GuidedMatchOptions()
    #: the adjustment on the guided tracks: observations weighted as what they are (NCC matches
    #: reproject to ~0.05 px: at the first adjustment's 1 px the priors outweighed them along the
    #: principal-point/rotation valley), principal points refined (σ 2 px around the image centre),
    #: centres left to the data (σ 0.3 m around the mounts)
    #: A rectified camera's (one with a lens calibration's distortion) radial k1, k2 are refined there
    #: too, with a prior of ``distortion_sigma`` around the rig's values (``bundle.py``): the guided
    #: tracks cover the whole image, where the few hundred SfM points did not
    guided_bundle: BundleOptions = BundleOptions(pixel_sigma=0.1, focal_sigma_rel=0.03, centre_sigma_m=0.3,
                                                 principal_sigma_px=2.0, distortion_sigma=DISTORTION_SIGMA)
    #: in that adjustment, the principal-point prior (px) of a camera whose rig carries measured
    #: intrinsics (a lens calibration, its own or its lens group's) around the measured principal
    #: point, in place of ``guided_bundle.principal_sigma_px`` (which is for nominal cameras: a centred
    #: principal point, a sensor's ~1 px tolerance). None: ``guided_bundle``'s for every camera
    measured_principal_sigma_px: float | None = MEASURED_PRINCIPAL_SIGMA_PX
    #: in steps 4 and 5, the focal prior (1σ, relative) of a camera whose rig carries measured
    #: intrinsics while the footage shows no evidence against its lens calibration; released to
    #: ``bundle.focal_sigma_rel`` / ``guided_bundle.focal_sigma_rel`` when its observations fit better
    #: by more than ``measured_focal_release_chi2`` with it free (:mod:`~volcap_core.calibration.focal_prior`).
    #: None: every focal under those loose priors (before calibrate-static 13)
    measured_focal_sigma_rel: float | None = MEASURED_FOCAL_SIGMA_REL
    measured_focal_release_chi2: float = RELEASE_CHI2
    #: None (default) skips the photometric refinement: on the demo capture it did not beat the
    #: bundle adjustments, at many times their cost (docs/calibration.md);
    #: ``PhotometricOptions(max_points=20000, centre_sigma_m=0.03)`` turns it on
    photometric: PhotometricOptions | None = None
    #: frames (evenly spread over the take) whose median is each static camera's background plate
    plate_frames: int = 8
    #: the take index calibrated on; None: the middle frame (the paper)
    reference_frame: int | None = None
    #: instants of the take pooled into the static SfM (:func:`instant_frames`): 1 (default, the
    #: paper) uses the reference frame alone; n > 1 adds n - 1 more spread evenly over the take, so a
    #: capture whose background alone is too sparse at one instant (a dark stage, a moving board or
    #: actor giving the texture) gathers observations from several. Features are matched between
    #: cameras within an instant only, and each static camera keeps ONE pose over all of them
    #: (:func:`~volcap_core.calibration.sfm.reconstruct_static`). Seeded SfM only.
    instants: int = 1
    #: the take indices to pool instead (the reference frame is always one of them); None: from
    #: ``instants``
    instant_frames: tuple[int, ...] | None = None
    #: without a lidar scan, the metric scale from a measured distance between two static cameras'
    #: optical centres: (camera id, camera id, metres). None: the scale (and the stage frame) come
    #: from the rig's mounts alone (a robust similarity of the adjusted camera centres onto them).
    #: With a scan the scan gives the scale; the distance is then only checked (stats
    #: ``frame.known_distance_error_m``)
    known_distance: tuple[str, str, float] | None = None
    #: without a lidar scan, step 5 (guided matching and the second adjustment) runs through a
    #: surface made by a plane sweep of the background plates with step 4's cameras
    #: (:func:`surface_from_plates`) instead of the scan, the centres held by the mounts (step 4's
    #: ``centre_sigma_m``) and no lidar prior; False: steps 1-4 only
    surface_without_scan: bool = True
    #: the stand-in surface (:func:`surface_from_plates`) needs at least this many fused points to
    #: guide step 5; fewer, and step 5 does not run (said in the calibration's ``warnings``)
    surface_min_points: int = 2000
    #: without a lidar scan: a camera whose adjusted centre is further than this from its mount
    #: after the similarity onto the mounts is named in a warning (the mounts are surveyed to a few
    #: cm; metres). The residual is in the stats (``frame.mount_residual_*``)
    mount_tolerance_m: float = 0.10
    #: the SfM must register at least this fraction of the static cameras (and two): fewer means
    #: the views do not overlap enough (or the frame is wrong), and calibration stops there
    min_registered_fraction: float = 0.5
    #: a camera needs at least this many observations (SfM keypoints of triangulated points) in the
    #: sparse reconstruction, before and after step 4's outlier rejection, to count as calibrated:
    #: well below what registered cameras of the demo capture have, well above what a camera whose
    #: view matches nothing has (docs/calibration.md)
    min_observations: int = 25
    #: a camera whose pose standard deviation after step 4 (its inlier observations, points and
    #: intrinsics held fixed: a lower bound that ignores the priors, see :func:`camera_support`)
    #: exceeds this rotation (degrees) or centre (metres) is unsupported too: bounds several times
    #: what the demo capture's cameras reach, about what a mount survey gives (docs/calibration.md;
    #: None: no bound)
    max_rotation_sigma_deg: float | None = 1.0
    max_centre_sigma_m: float | None = 0.3
    #: an unsupported camera (above) is an error naming it and the reason (False), or is left out
    #: of the calibration and listed in ``unregistered`` with the reason (True); training then
    #: leaves it out
    allow_unregistered: bool = False


@dataclass
class StaticCalibration:
    """Calibrated static cameras. ``K`` [3, 3] and ``world_to_camera`` [4, 4] per camera id (OpenCV,
    metres, stage frame); ``model`` the sparse reconstruction in the same frame (points refined);
    ``unregistered`` the static cameras that could not be calibrated."""

    camera_ids: list[str]
    K: dict[str, np.ndarray]
    world_to_camera: dict[str, np.ndarray]
    size: dict[str, tuple[int, int]]
    model: SparseModel
    unregistered: list[str] = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    #: cameras with distortion (or non-square pixels): their intrinsics on their own images
    #: (:func:`~volcap_core.calibration.sfm.raw_from_rectified`); their ``K`` is the square pinhole of
    #: their rectified images (:func:`~volcap_core.calibration.sfm.undistort_views`)
    raw_intrinsics: dict[str, Intrinsics] = field(default_factory=dict)
    #: why each camera of ``unregistered`` is not calibrated
    reasons: dict[str, str] = field(default_factory=dict)
    #: per calibrated camera: :func:`camera_support` of the final sparse reconstruction, and
    #: ``guided_observations`` (step 5's inliers) when step 5 ran
    support: dict[str, dict] = field(default_factory=dict)
    #: per calibrated camera, its view of the scene (:func:`scene_depths`): where its dense points
    #: sweep; kept by the records when ``model`` is not
    scene_depth: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    #: what the user must know of this calibration, one line each: a step that did not run (a
    #: setting turned it off, or it had nothing to work on) and what that leaves. Also logged as
    #: warnings, and carried into the records (``warnings``)
    warnings: list[str] = field(default_factory=list)



def nominal_pose(cam: RigCamera) -> np.ndarray:
    """World-to-camera [4, 4] of a camera at its nominal mount, looking at its nominal target."""
    R = look_at_rotation(cam.mount.position_m, cam.mount.look_at_m, cam.mount.roll_deg)
    return pose_matrix(R, -R @ np.asarray(cam.mount.position_m, np.float64))


def instant_frames(frame_count: int, reference: int, options: StaticCalibrationOptions) -> list[int]:
    """The take indices the static SfM pools, the reference frame first: ``options.instant_frames``
    when given, else the reference alone (``instants`` = 1) or ``instants`` frames spread evenly over
    the take (the evenly spaced one nearest the reference replaced by it)."""
    if options.instant_frames is not None:
        bad = [k for k in options.instant_frames if not 0 <= k < frame_count]
        if bad:
            raise ValueError(f"instant_frames {bad} outside the take [0, {frame_count})")
        rest = sorted(set(int(k) for k in options.instant_frames) - {reference})
        return [reference] + rest
    if options.instants < 1:
        raise ValueError(f"instants must be >= 1, got {options.instants}")
    n = min(options.instants, frame_count)
    if n <= 1:
        return [reference]
    spread = [int(k) for k in np.unique(np.linspace(0, frame_count - 1, n).round().astype(int))]
    spread[int(np.argmin([abs(k - reference) for k in spread]))] = reference
    return [reference] + sorted(set(spread) - {reference})


def calibrate_static_cameras(images: Mapping[str, np.ndarray], rig: Rig, scan: LidarScan | None,
                             *, plates: Mapping[str, np.ndarray] | None = None,
                             options: StaticCalibrationOptions = StaticCalibrationOptions(),
                             more_instants: Sequence[Mapping[str, np.ndarray]] = ()) -> StaticCalibration:
    """Calibrate the rig's static cameras from one instant, or several pooled: the stages of the
    module docstring, in order.

    ``images``: static camera id -> scene-linear RGB [H, W, 3] float at the middle frame.
    ``more_instants``: the same cameras at other instants (:func:`instant_frames`), pooled into the
    sparse SfM (features matched within an instant, one pose per camera); the later steps use
    ``images`` / ``plates``.
    ``plates``: optional background plates (:func:`~volcap_core.calibration.photometric.background_plate`)
    for the guided matching and the photometric step (default: ``images``; plates have no actors, whom
    the scan does not have). ``scan``: the lidar scan of the static stage in the stage frame (None:
    no lidar terms, no photometric step, step 5 through a plane-sweep surface of the plates; the
    stage frame and the metric scale from a robust similarity of the adjusted camera centres onto
    the rig's mounts, or the scale from ``options.known_distance``, see :func:`frame_without_lidar`).
    """
    t0 = time.perf_counter()
    stats: dict = {}
    warnings: list[str] = []
    priors = _rig_priors(rig, sorted(images))                                                               # 1
    model, views, reasons = _sparse_model(images, plates, priors, options, more_instants, stats)            # 2
    if stats["sfm"].get("two_view_tracks") and options.sfm.two_view_tracks is None:
        warnings.append("the sparse SfM kept two-view tracks (points seen by two cameras only): without them a "
                        "camera had too few observations, its view overlapping the others' in pairs only; each "
                        "pair's points then rest on that one pair's matches")
    t1 = time.perf_counter()
    model = _into_stage_frame(model, priors.mounts, scan, options, stats)                                   # 3
    model, first, cams = _first_adjustment(model, views, priors, scan, options, reasons, stats)             # 4
    t2 = time.perf_counter()
    cams = _guided_adjustment(cams, views, priors, rig, scan, options, stats, warnings)                     # 5
    t_guided = time.perf_counter()
    cams = _photometric_refinement(cams, views, priors, scan, options, stats)                               # 6
    t3 = time.perf_counter()
    model = _final_model(model, first, cams, views)                                                         # 7
    support = _final_support(model, first, cams)
    # each measured camera's final focal decision (step 5's when it ran) in its support, so the
    # Calibration record's quality says whether its lens calibration's focal was held and why
    decisions = stats.get("focal_prior", {}).get("step5" if cams.guided_observations is not None else "step4", {})
    for c in cams.ids:
        support[c].update(decisions.get(c, {}))
    stated = cams.guided_sigma if cams.guided_observations is not None else first.sigma
    if stated is not None and stated.undetermined:
        warnings.append(f"the final adjustment leaves {stated.undetermined} direction(s) of the cameras undetermined "
                        "by the footage and the priors (e.g. two cameras without a scan turning together about their "
                        "baseline): each camera's sigma leaves them out; along them the cameras are where their "
                        "mounts' aims put them")
        log.warning("%s", warnings[-1])
    model, cams, support = _refuse_uncertain(model, cams, support, options, reasons)
    stats["support"] = support
    stats["time_s"] = {"sfm": t1 - t0, "bundle": t2 - t1, "guided": t_guided - t2, "photometric": t3 - t_guided,
                       "total": time.perf_counter() - t0}
    reg, K = cams.ids, cams.K
    return StaticCalibration(camera_ids=reg, K=K, world_to_camera=cams.world_to_camera,
                             size={c: (views.intrinsics[c].width, views.intrinsics[c].height) for c in reg},
                             model=model, unregistered=sorted(reasons), stats=stats,
                             reasons=dict(sorted(reasons.items())), support=support, warnings=warnings,
                             raw_intrinsics={c: raw_from_rectified(K[c], cams.lenses[c]) for c in reg
                                             if c in cams.lenses})


@dataclass(frozen=True)
class _RigPriors:
    """Step 1: what the rig says of each static camera before any image is read (camera id -> ...)."""

    #: the measured intrinsics when the rig carries them (its own or its lens group's), else the
    #: nominal ones (:meth:`~volcap_core.calibration.sfm.Intrinsics.from_rig`)
    intrinsics: dict[str, Intrinsics]
    #: world-to-camera [4, 4] at the nominal mount (:func:`nominal_pose`), the seeded SfM's poses
    seeds: dict[str, np.ndarray]
    #: the mount's position [3] (metres, stage frame): the prior of the camera's centre
    mounts: dict[str, np.ndarray]
    #: the camera's lens group (None: its own)
    lens_groups: dict[str, str | None]
    #: whether the rig carries measured intrinsics for the camera (its own or its lens group's)
    measured: dict[str, bool]


@dataclass(frozen=True)
class _Views:
    """Step 2's views of the cameras, which the later steps work on: distorted (or non-square)
    cameras rectified into square pinholes, their images and plates resampled."""

    #: camera id -> the pinhole its observations, images and plates are in
    intrinsics: dict[str, Intrinsics]
    #: camera id -> scene-linear RGB [H, W, 3] at the reference instant
    images: Mapping[str, np.ndarray]
    #: camera id -> background plate [H, W, 3], or None (the images serve)
    plates: Mapping[str, np.ndarray] | None
    #: camera id -> the lens a rectified camera's views were resampled from (its raw intrinsics and
    #: distortion); cameras without distortion are absent
    lenses: dict[str, Intrinsics]

    @property
    def background(self) -> Mapping[str, np.ndarray]:
        """What the guided matching and the photometric step read: the plates, else the images."""
        return self.plates if self.plates is not None else self.images


@dataclass(frozen=True)
class _Cameras:
    """The calibrated cameras as a stage leaves them."""

    #: the calibrated camera ids, in the order of every per-camera array below
    ids: list[str]
    #: camera id -> K [3, 3] of its (rectified) pinhole
    K: dict[str, np.ndarray]
    #: camera id -> world-to-camera [4, 4] (OpenCV, metres, stage frame)
    world_to_camera: dict[str, np.ndarray]
    #: camera id -> a rectified camera's lens as calibrated: its views' lens, with step 5's
    #: corrections of its radial terms; cameras without distortion are absent
    lenses: dict[str, Intrinsics]
    #: step 5's inlier observations per camera [C] (None: step 5 did not run)
    guided_observations: np.ndarray | None = None
    #: step 5's standard deviations of each camera (None: step 5 did not run)
    guided_sigma: CameraSigma | None = None


def _rig_priors(rig: Rig, ids: Sequence[str]) -> _RigPriors:
    """1. Each camera's intrinsics, nominal pose, mount and lens group from the rig."""
    cams = {c: rig.camera(c) for c in ids}
    return _RigPriors(intrinsics={c: Intrinsics.from_rig(rig, c) for c in ids},
                      seeds={c: nominal_pose(cams[c]) for c in ids},
                      mounts={c: np.asarray(cams[c].mount.position_m, np.float64) for c in ids},
                      lens_groups={c: cams[c].lens_group for c in ids},
                      measured={c: rig.measured_intrinsics(c) is not None for c in ids})


def _sparse_model(images: Mapping[str, np.ndarray], plates: Mapping[str, np.ndarray] | None, priors: _RigPriors,
                  options: StaticCalibrationOptions, more_instants: Sequence[Mapping[str, np.ndarray]],
                  stats: dict) -> tuple[SparseModel, _Views, dict[str, str]]:
    """2. The sparse SfM (seeded with the nominal poses, or incremental), its distorted cameras
    rectified, and the cameras it does not hold left out. Returns the model, the views the later
    steps work on, and why each left-out camera is (camera id -> reason); raises
    :class:`UnsupportedCameraError` when fewer than two cameras are left."""
    model = reconstruct_static(images, priors.intrinsics, options.sfm,
                               initial_poses=priors.seeds if options.seeded else None, more_instants=more_instants,
                               lens_groups={c: g for c, g in priors.lens_groups.items() if g})
    stats["sfm"] = dict(model.stats)
    # distorted (or non-square) cameras: from here on everything works on their rectified square
    # pinholes (observations, images and plates resampled); ``lenses`` is what they came from
    model, intr, images, plates, lenses = rectify_static_inputs(model, priors.intrinsics, images, plates)
    reasons = {c: "the SfM did not register it (no view overlapping enough)" for c in model.unregistered}
    # a seeded camera is "registered" by construction: its observations say whether anything holds it
    counts = np.bincount(model.obs_camera, minlength=len(model.camera_ids))
    for i, c in enumerate(model.camera_ids):
        if counts[i] < options.min_observations:
            reasons[c] = (f"{counts[i]} observations in the sparse SfM (needs at least {options.min_observations}): "
                          "its view matches too few features of the other cameras")
    model = _without_cameras(model, [c for c in model.camera_ids if c in reasons])
    if len(model.camera_ids) < 2:
        raise UnsupportedCameraError(reasons)
    return model, _Views(intr, images, plates, lenses), reasons


def _into_stage_frame(model: SparseModel, mounts: Mapping[str, np.ndarray], scan: LidarScan | None,
                      options: StaticCalibrationOptions, stats: dict) -> SparseModel:
    """3. An incremental reconstruction into the stage frame: the robust similarity taking its
    camera centres onto the mounts, then a robust point-to-plane ICP of its points onto the scan.
    A seeded reconstruction is in the stage frame already: returned as it is."""
    if options.seeded:
        return model
    src = model.centres()
    dst = np.stack([mounts[c] for c in model.camera_ids])
    T, _ = robust_umeyama(src, dst, threshold=0.5)
    model = model.transformed(T)
    if scan is not None:
        T2, icp = align_to_lidar(model.points, scan)
        model = model.transformed(T2)
        stats["icp"] = icp
    return model


def _first_adjustment(model: SparseModel, views: _Views, priors: _RigPriors, scan: LidarScan | None,
                      options: StaticCalibrationOptions, reasons: dict[str, str], stats: dict
                      ) -> tuple[SparseModel, BundleResult, _Cameras]:
    """4. The bundle adjustment of the sparse model (lidar prior on the points, focal prior around
    the rig's intrinsics, centre prior around the mounts), then each camera's support on its inlier
    observations (:func:`camera_support`): an unsupported camera is added to ``reasons`` and left
    out (:class:`UnsupportedCameraError` unless ``options.allow_unregistered``). Without a scan the
    cameras and points are then taken into the stage frame (:func:`frame_without_lidar`); with one,
    a known distance is only checked. Returns the model without the cameras left out, the
    adjustment (its observations aligned with that model's) and the cameras."""
    intr, mounts = views.intrinsics, priors.mounts
    reg = model.camera_ids
    focal_prior = np.array([intr[c].fx for c in reg])

    def adjust(focal_sigma: np.ndarray) -> BundleResult:
        return bundle_adjust(np.stack([model.world_to_camera[c] for c in reg]),
                             np.array([model.intrinsics[c].fx for c in reg]),
                             np.array([[model.intrinsics[c].cx, model.intrinsics[c].cy] for c in reg]),
                             model.points, model.obs_camera, model.obs_point, model.obs_xy, scan=scan,
                             focal_prior=focal_prior, centre_prior=np.stack([mounts[c] for c in reg]),
                             lens_group=[priors.lens_groups[c] for c in reg], focal_sigma=focal_sigma,
                             options=options.bundle)

    res, decided = _held_focals(adjust, reg, priors, focal_prior, model.obs_camera, options.bundle, options)
    _record_focal_decisions(stats, "step4", reg, decided)
    K = {c: np.array([[res.focal[i], 0, intr[c].cx], [0, res.focal[i], intr[c].cy], [0, 0, 1.0]])
         for i, c in enumerate(reg)}
    w2c = {c: res.world_to_camera[i] for i, c in enumerate(reg)}
    stats["bundle"] = dict(res.stats)
    stats["bundle"]["median_reprojection_px"] = float(np.median(res.reprojection_px[res.inlier]))
    inl = res.inlier
    support = camera_support(K, w2c, reg, res.points, model.obs_camera[inl], model.obs_point[inl],
                             model.obs_xy[inl])
    for c in reg:
        why = _unsupported(support[c], options)
        if why:
            reasons[c] = why
    if reasons and not options.allow_unregistered:
        raise UnsupportedCameraError(reasons)
    if any(c in reasons for c in reg):
        # left out of everything that follows (their step-4 observations too)
        drop = [c for c in reg if c in reasons]
        kept = np.array([c not in reasons for c in reg])
        keep_obs = kept[model.obs_camera]
        sg = res.sigma
        res = replace(res, inlier=inl[keep_obs], world_to_camera=res.world_to_camera[kept], focal=res.focal[kept],
                      sigma=None if sg is None else CameraSigma(sg.rotation_deg[kept], sg.centre_m[kept],
                                                                sg.focal_rel[kept], sg.principal_px[kept],
                                                                sg.undetermined))
        model = _without_cameras(model, drop, min_views=0)  # observations stay aligned with keep_obs
        reg = model.camera_ids
        if len(reg) < 2:
            raise UnsupportedCameraError(reasons)
        K = {c: K[c] for c in reg}
        w2c = {c: w2c[c] for c in reg}
    if scan is None:
        # no lidar: the stage frame and the metric scale from the mounts (or a measured distance)
        T, stats["frame"] = frame_without_lidar({c: w2c[c] for c in reg}, mounts, options)
        w2c = {c: T.apply_pose(w2c[c]) for c in reg}
        res = replace(res, points=T.apply(res.points))
    elif options.known_distance is not None:
        stats["frame"] = _check_known_distance(w2c, options.known_distance)
    return model, res, _Cameras(reg, K, w2c, dict(views.lenses))


def _guided_adjustment(cams: _Cameras, views: _Views, priors: _RigPriors, rig: Rig, scan: LidarScan | None,
                       options: StaticCalibrationOptions, stats: dict, warnings: list[str]) -> _Cameras:
    """5. Patch matching of the background between the cameras of step 4, guided through the
    scan (without one, through a plane-sweep surface of the plates: :func:`surface_from_plates`),
    and a second adjustment on those tracks: principal points refined, a rectified camera's radial
    k1, k2 corrected, the centres left to the data (with no scan, held by the mounts as in step 4:
    they are the frame, taken again after it). The cameras unchanged when ``options.guided`` is
    None or there is nothing to guide the matching; then why is appended to ``warnings`` and logged
    (:func:`_skipped_step5`)."""
    reg, K, w2c = cams.ids, cams.K, cams.world_to_camera
    intr, mounts, background = views.intrinsics, priors.mounts, views.background
    guide, guided_bundle = scan, options.guided_bundle
    if scan is None and options.guided is not None and options.surface_without_scan:
        # no scan: step 5 warps its templates through a plane-sweep surface of the plates instead,
        # with no lidar prior and the centres held by the mounts as in step 4 (they are the frame)
        guide, stats["surface"] = surface_from_plates({c: background[c] for c in reg}, K, w2c,
                                                      min_points=options.surface_min_points)
        guided_bundle = replace(guided_bundle, centre_sigma_m=options.bundle.centre_sigma_m)
    if options.guided is None:
        return _skipped_step5(cams, "turned off (StaticCalibrationOptions.guided is None)", warnings, stats)
    if guide is None and not options.surface_without_scan:
        return _skipped_step5(cams, "no lidar scan, and the stand-in surface is turned off "
                              "(StaticCalibrationOptions.surface_without_scan=False)", warnings, stats)
    if guide is None:
        got = int(stats["surface"].get("points", 0))
        return _skipped_step5(cams, f"no lidar scan, and the stand-in surface of the background plates got {got} "
                              f"points (needs {options.surface_min_points}): the plates are too bare, or too alike "
                              "between the cameras, for the plane sweep", warnings, stats)
    # the tracks' cameras come in ``reg`` order, the order of the dict passed; a rectified view's
    # pixels without footage (a pincushion lens's black corners) take no part in the matching
    lenses = views.lenses
    valid = {c: undistort_valid_mask(lenses[c], lenses[c].distortion, intr[c], margin_px=RECTIFY_MARGIN_PX)
             for c in reg if c in lenses}
    tracks = guided_tracks({c: background[c] for c in reg}, K, w2c, guide, options.guided, valid=valid)
    P = np.stack([K[c] @ w2c[c][:3] for c in reg])
    start = triangulate_points(P, tracks.obs_point, tracks.obs_camera, tracks.obs_xy, len(tracks.points))
    start = np.where(np.isfinite(start), start, tracks.points)
    focal_prior = np.array([intr[c].fx for c in reg])

    def adjust(focal_sigma: np.ndarray) -> BundleResult:
        return bundle_adjust(np.stack([w2c[c] for c in reg]), np.array([K[c][0, 0] for c in reg]),
                             np.array([[intr[c].cx, intr[c].cy] for c in reg]), start, tracks.obs_camera,
                             tracks.obs_point, tracks.obs_xy, scan=scan, focal_prior=focal_prior,
                             centre_prior=np.stack([mounts[c] for c in reg]),
                             lens_group=[priors.lens_groups[c] for c in reg],
                             lens=[_radial_lens(intr[c], lenses.get(c)) for c in reg],
                             principal_sigma=_principal_sigmas(reg, rig, guided_bundle, options),
                             focal_sigma=focal_sigma, options=guided_bundle)

    g, decided = _held_focals(adjust, reg, priors, focal_prior, tracks.obs_camera, guided_bundle, options)
    _record_focal_decisions(stats, "step5", reg, decided)
    K = {c: np.array([[g.focal[i], 0, g.principal[i, 0]], [0, g.focal[i], g.principal[i, 1]],
                      [0, 0, 1.0]]) for i, c in enumerate(reg)}
    w2c = {c: g.world_to_camera[i] for i, c in enumerate(reg)}
    stats["guided"] = {"ran": 1, **tracks.stats, "bundle": g.stats, "inliers": int(g.inlier.sum()),
                       "median_reprojection_px": float(np.median(g.reprojection_px[g.inlier])),
                       "through": "lidar scan" if scan is not None else "plane-sweep surface"}
    calibrated = dict(cams.lenses)
    if g.distortion is not None:   # the lens as refined: what the record and the frames rectified after use
        for i, c in enumerate(reg):
            if _radial_lens(intr[c], lenses.get(c)) is not None:
                calibrated[c] = replace(calibrated[c], distortion=_with_radial(calibrated[c].distortion,
                                                                               g.distortion[i]))
                stats["guided"].setdefault("distortion_correction", {})[c] = {
                    "dk1": float(g.distortion[i][0]), "dk2": float(g.distortion[i][1])}
    if scan is None:   # the adjusted cameras onto the mounts again (or the known distance)
        T, stats["frame"] = frame_without_lidar(w2c, mounts, options)
        w2c = {c: T.apply_pose(w2c[c]) for c in reg}
    return _Cameras(reg, K, w2c, calibrated, guided_observations=np.bincount(tracks.obs_camera[g.inlier],
                                                                             minlength=len(reg)),
                    guided_sigma=g.sigma)


def _held_focals(adjust, reg: Sequence[str], priors: _RigPriors, focal_prior: np.ndarray, obs_camera: np.ndarray,
                 bundle: BundleOptions, options: StaticCalibrationOptions
                 ) -> tuple[BundleResult, dict[int, FocalDecision]]:
    """An adjustment (``adjust(focal_sigma)``) whose measured focals need evidence to move
    (:func:`~volcap_core.calibration.focal_prior.adjust_with_held_focals`); with focals held by
    ``bundle`` (no focal prior) the one adjustment."""
    if bundle.focal_sigma_rel is None:
        return adjust(None), {}
    focal_of = camera_parameters([priors.lens_groups[c] for c in reg], len(reg),
                                 share_focal=bundle.share_group_focal).focal_of
    return adjust_with_held_focals(adjust, [priors.measured[c] for c in reg], focal_prior, obs_camera,
                                   loose_sigma_rel=bundle.focal_sigma_rel,
                                   tight_sigma_rel=options.measured_focal_sigma_rel,
                                   release_chi2=options.measured_focal_release_chi2, focal_of=focal_of)


def _record_focal_decisions(stats: dict, step: str, reg: Sequence[str], decided: Mapping[int, FocalDecision]) -> None:
    """Each measured camera's focal decision of ``step`` into ``stats["focal_prior"][step][id]``
    (held or released, its evidence, the focal's move either way), and logged."""
    if not decided:
        return
    out = stats.setdefault("focal_prior", {}).setdefault(step, {})
    for i, d in decided.items():
        out[reg[i]] = d.as_stats()
        log.info("%s %s: measured focal %s (evidence Δχ² %.1f against %.0f; free it moves %+.2f %%, here %+.2f %%)",
                 step, reg[i], "held" if d.held else "released", d.evidence_chi2, d.release_chi2,
                 100 * d.free_shift_rel, 100 * d.shift_rel)


def _skipped_step5(cams: _Cameras, why: str, warnings: list[str], stats: dict) -> _Cameras:
    """Step 5 did not run: ``why`` (and what it leaves) appended to ``warnings`` and logged, and
    ``stats["guided"]["ran"] = 0`` (1 when it ran). Returns ``cams`` unchanged."""
    msg = (f"step 5 (the guided matching and the final adjustment) did not run: {why}; the cameras are "
           "step 4's, from the sparse SfM alone, and each camera's sigma is step 4's adjustment covariance")
    warnings.append(msg)
    stats["guided"] = {"ran": 0}
    log.warning("%s", msg)
    return cams


def _photometric_refinement(cams: _Cameras, views: _Views, priors: _RigPriors, scan: LidarScan | None,
                            options: StaticCalibrationOptions, stats: dict) -> _Cameras:
    """6. With a scan and ``options.photometric``: every textured background pixel seen by two
    cameras votes on their poses and focals (:func:`~volcap_core.calibration.photometric.refine_photometric`).
    Otherwise the cameras unchanged."""
    if scan is None or options.photometric is None:
        return cams
    ph = refine_photometric({c: views.background[c] for c in cams.ids}, cams.K, cams.world_to_camera, scan,
                            centre_prior=priors.mounts, focal_prior={c: views.intrinsics[c].fx for c in cams.ids},
                            options=options.photometric)
    stats["photometric"] = {k: ph[k] for k in ("samples", "points", "rms_per_level", "seconds")}
    return replace(cams, K=ph["K"], world_to_camera=ph["world_to_camera"])


def _final_model(model: SparseModel, first: BundleResult, cams: _Cameras, views: _Views) -> SparseModel:
    """7. The sparse model under the final cameras: its points re-triangulated from them (inlier
    observations of step 4 only; a point that does not triangulate keeps step 4's position)."""
    reg, K, w2c = cams.ids, cams.K, cams.world_to_camera
    inl = first.inlier
    P = np.stack([K[c] @ w2c[c][:3] for c in reg])
    pts = triangulate_points(P, model.obs_point[inl], model.obs_camera[inl], model.obs_xy[inl], len(model.points))
    good = np.isfinite(pts).all(1)
    pts[~good] = first.points[~good]
    intr = views.intrinsics
    return replace(model, points=pts, world_to_camera=dict(w2c),
                   intrinsics={c: Intrinsics(K[c][0, 0], K[c][1, 1], K[c][0, 2], K[c][1, 2], intr[c].width,
                                             intr[c].height) for c in reg})


def _final_support(model: SparseModel, first: BundleResult, cams: _Cameras) -> dict[str, dict]:
    """7. Each camera's support (:func:`camera_support`): the sparse model's observations (step 4's
    inliers) under the final cameras; its standard deviations are step 5's covariance, or step 4's
    when step 5 did not run (``guided_ran`` 0)."""
    reg, inlier = cams.ids, first.inlier
    support = camera_support(cams.K, cams.world_to_camera, reg, model.points, model.obs_camera[inlier],
                             model.obs_point[inlier], model.obs_xy[inlier])
    for c in reg:   # whether step 5 refined it (0: see the calibration's warnings for why not)
        support[c]["guided_ran"] = float(cams.guided_observations is not None)
    if cams.guided_observations is None and first.sigma is not None:
        # step 4's adjustment covariance (points eliminated, the mount and focal priors in), not the
        # pose-only bound with the points held: that bound misses the cameras and points turning
        # together, which only the priors hold when few cameras share the points (two cameras of
        # the demo rig: 0.0035° stated, 0.63-0.73° off; step 4's covariance 0.46-0.48°)
        for i, c in enumerate(reg):
            support[c].update(rotation_sigma_deg=float(first.sigma.rotation_deg[i]),
                              centre_sigma_m=float(first.sigma.centre_m[i]),
                              # how far the footage may move a held lens calibration's focal
                              # (docs/calibration.md, "Focal drift from a held lens calibration")
                              focal_sigma_pct=100 * float(first.sigma.focal_rel[i]))
    if cams.guided_observations is not None:
        # how well step 5 knows each camera: its adjustment's covariance, the points eliminated and
        # the principal point, focal and lens corrections unknown under their priors (a
        # principal-point error is a rotation, bundle._camera_sigma), in place of the pose-only
        # bound on the SfM's observations
        counts, sigma = cams.guided_observations, cams.guided_sigma
        for i, c in enumerate(reg):
            # a camera step 5 matched nothing for: its covariance is its priors and a regulariser
            known = 1.0 if counts[i] > 0 else float("inf")
            support[c].update(guided_observations=int(counts[i]),
                              rotation_sigma_deg=known * float(sigma.rotation_deg[i]),
                              centre_sigma_m=known * float(sigma.centre_m[i]),
                              principal_sigma_px=known * float(sigma.principal_px[i]),
                              focal_sigma_pct=known * 100 * float(sigma.focal_rel[i]))
    return support


def _refuse_uncertain(model: SparseModel, cams: _Cameras, support: dict[str, dict], options: StaticCalibrationOptions,
                      reasons: dict[str, str]) -> tuple[SparseModel, _Cameras, dict[str, dict]]:
    """7. The final support held to the same bounds as step 4's (``options.max_rotation_sigma_deg``,
    ``max_centre_sigma_m``), now on the final sigma (step 5's covariance when it ran): a camera above
    them is unsupported, added to ``reasons``, and left out (:class:`UnsupportedCameraError` unless
    ``options.allow_unregistered``). Never kept with a sigma above the bound (the webcams of issue 31:
    4.6° against the 1° bound, all returned as calibrated)."""
    bad = {}
    for c in cams.ids:
        why = _unsupported(support[c], options)
        if why:
            bad[c] = "after the final adjustment, " + why + (
                " (step 5's guided matching found none of its background plate in the other cameras' views)"
                if support[c].get("guided_observations", 1) == 0 else "")
    if not bad:
        return model, cams, support
    reasons.update(bad)
    keep = [c for c in cams.ids if c not in bad]
    if not options.allow_unregistered or len(keep) < 2:
        raise UnsupportedCameraError(reasons)
    kept = np.array([c in keep for c in cams.ids])
    cams = _Cameras(keep, {c: cams.K[c] for c in keep}, {c: cams.world_to_camera[c] for c in keep},
                    {c: v for c, v in cams.lenses.items() if c in keep},
                    None if cams.guided_observations is None else cams.guided_observations[kept],
                    None if cams.guided_sigma is None else CameraSigma(*(a[kept] for a in (
                        cams.guided_sigma.rotation_deg, cams.guided_sigma.centre_m, cams.guided_sigma.focal_rel,
                        cams.guided_sigma.principal_px)), undetermined=cams.guided_sigma.undetermined))
    return _without_cameras(model, list(bad)), cams, {c: support[c] for c in keep}


def _radial_lens(rect: Intrinsics, raw: Intrinsics | None) -> tuple[float, ...] | None:
    """``bundle_adjust``'s ``lens`` of a camera: the square pinhole ``rect`` its views and
    observations were rectified into and the radial k1, k2, k3 of its lens ``raw`` (k3 enters the
    correction's radial slope); None when it was not rectified, or its lens has no k1 and k2 to
    correct (PINHOLE with non-square pixels), or is a rational FULL_OPENCV (k4-k6: the correction's
    radial slope assumes a polynomial): held."""
    if raw is None or raw.distortion.model not in ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"):
        return None
    full = [float(v) for v in raw.distortion.opencv_full()]
    if any(full[5:]):
        return None
    return (rect.fx, rect.cx, rect.cy, full[0], full[1], full[4])


def _with_radial(d: Distortion, correction) -> Distortion:
    """``d`` with ``correction`` (dk1, dk2) added to its k1 and k2 (a SIMPLE_RADIAL lens becomes the
    RADIAL one it then is)."""
    if d.model == "SIMPLE_RADIAL":
        d = Distortion("RADIAL", (d.params[0], 0.0))
    params = list(d.params)
    params[0] += float(correction[0])
    params[1] += float(correction[1])
    return Distortion(d.model, tuple(params))


def _principal_sigmas(reg: Sequence[str], rig: Rig, bundle: BundleOptions,
                      options: StaticCalibrationOptions) -> list[float] | None:
    """The step-5 principal-point prior of each camera: ``options.measured_principal_sigma_px`` for a
    camera with measured intrinsics in the rig, ``bundle.principal_sigma_px`` for the others."""
    if bundle.principal_sigma_px is None or options.measured_principal_sigma_px is None:
        return None
    return [options.measured_principal_sigma_px if rig.measured_intrinsics(c) is not None
            else bundle.principal_sigma_px for c in reg]


def surface_from_plates(plates: Mapping[str, np.ndarray], K: Mapping[str, np.ndarray],
                        world_to_camera: Mapping[str, np.ndarray], min_points: int = 2000,
                        scale: float = 2.0) -> tuple[LidarScan | None, dict]:
    """A stand-in for the lidar scan when a capture has none: the plane-sweep points of the
    background plates (:func:`~volcap_core.calibration.dense.depth_map`, fused by cross-view
    consistency) seen by the cameras of step 4, normals from their neighbours. Step 4's cameras are
    consistent with each other (0.1-0.2 px) even where they are off in the stage frame, so the
    surface is the set as they see it, which is all the guided matching needs to predict where a
    pixel of one camera lands in another. None (and the count in the stats) when fewer than
    ``min_points`` points pass.

    The sweep's depths come from the scene, per camera (:func:`_surface_depth_ranges`): a probe
    sweep at half the working resolution over everything from a quarter of the rig's camera spacing
    (the median distance from a camera to its nearest neighbour) to a thousand times it, then each
    camera's 1st-99th percentile of the probe's fused points in its view, widened to 0.7x and 1.4x;
    its neighbours are chosen at its median probe depth (the triangulation angle they see its scene
    at). A camera whose probe saw almost nothing takes the widest range of the others, and a
    background reaching the probe's nearest depth is named in a warning; both are counted in the
    stats (``depth_fallback_cameras``, ``near_limit_cameras``), as is every range
    (``depth_range.<id>.min_m`` / ``.max_m``, ``depth_min_m`` / ``depth_max_m``). Nothing is swept
    over a fixed range: a scene of any size gives the same surface (scaled)."""
    t0 = time.perf_counter()
    ids = sorted(plates)
    cameras = {c: (np.asarray(K[c], np.float64), np.asarray(world_to_camera[c], np.float64)) for c in ids}
    ranges, middle, stats = _surface_depth_ranges(plates, cameras, scale)
    # the working resolution is half the plates': a quarter of the sweep's cost; the guided
    # matching searches ±3 px around what the surface predicts and refines by NCC on the full images
    pos, _ = _sweep_and_fuse(plates, cameras, scale, ranges, middle)
    stats.update({"points": len(pos), "seconds": time.perf_counter() - t0})
    if len(pos) < min_points:
        return None, stats
    return LidarScan(np.asarray(pos, np.float64), None), stats


#: the stand-in surface's probe: from this fraction of the median distance between neighbouring
#: cameras (a surface nearer than ~0.8 of it is seen by a neighbour at more than the sweep's 50°
#: anyway) to ``_PROBE_FAR`` times it; each camera's range is its ``_DEPTH_PERCENTILES`` of the
#: probe's points, widened by ``dense.sweep_range``; fewer than ``_MIN_PROBE_POINTS`` in view: the
#: fallback
_PROBE_NEAR, _PROBE_FAR = 0.25, 1000.0
_DEPTH_PERCENTILES = (1.0, 99.0)
_MIN_PROBE_POINTS = 100


def _sweep_and_fuse(images: Mapping[str, np.ndarray], cameras: Mapping[str, tuple[np.ndarray, np.ndarray]],
                    scale: float, ranges: Mapping[str, tuple[float, float]], scene_depth: Mapping[str, float],
                    depth_tol: float | None = None) -> tuple[np.ndarray, dict]:
    """:func:`~volcap_core.calibration.dense.dense_points` with a depth range per reference camera
    (``ranges``: id -> (min, max) metres) and its neighbours chosen for their angle at the scene
    ``scene_depth`` metres along its axis (not at a fixed 5 m). Returns the fused points [N, 3] and
    the depth maps."""
    base = DenseOptions(scale=scale)
    if depth_tol is not None:
        base = replace(base, depth_tol=depth_tol)
    out = dense_points(images, cameras, options=base,
                       sweeps={c: (ranges[c][0], scene_depth[c], ranges[c][1]) for c in cameras})
    return out["positions"], out["depth_maps"]


def scene_depths(static: StaticCalibration, stage_size_m: Sequence[float],
                 min_points: int = 20) -> dict[str, tuple[float, float, float]]:
    """Each static camera's view of the scene, ``(nearest, middle, farthest)`` depth in metres
    along its axis: where its dense points sweep (:func:`~volcap_core.calibration.dense.sweep_range`),
    so a stage of any size, or a miniature, is swept where its scene is.

    Two parts make the scene: the set, as the sparse points the camera observes (``static.model``
    under its final pose; their 1st and 99th percentile: SIFT finds the textured walls, rarely the
    floor at the camera's feet), and the performance volume (``stage_volume(stage_size_m)``, sampled
    on a grid: the points that project into its image), where the performers the dense points are
    for stand (the part of it at least the rig's camera spacing away: nearer, no neighbour sees a
    point within the sweep's angle). Nearest and farthest span both; the middle, where its
    neighbours are chosen for their triangulation angle, is the volume's median depth (the sparse
    points' without the volume in view). Cameras with fewer than ``min_points`` sparse points in
    front are left out (they sweep the fixed range); none without a model. Kept in ``StaticCalibration.scene_depth``
    (:func:`~volcap_core.calibration.static_step.calibrate_static_step`) and the records after it."""
    model = static.model
    if model is None:
        return {}
    (x0, y0, z0), (x1, y1, z1) = stage_volume(stage_size_m, floor_clearance_m=0.0)
    grid = np.stack(np.meshgrid(np.linspace(x0, x1, 25), np.linspace(y0, y1, 25), np.linspace(z0, z1, 11),
                                indexing="ij"), -1).reshape(-1, 3)
    # nearer than the rig's camera spacing no neighbour sees a point within the sweep's 50° of
    # triangulation angle (2 atan(1/2) = 53°): a camera inside the stage volume (a dome) would
    # otherwise sweep from a few cm, eight times the planes for nothing
    _, spacing = camera_gaps([static.world_to_camera[c] for c in sorted(static.world_to_camera)])
    out = {}
    for i, c in enumerate(model.camera_ids):
        if c not in static.world_to_camera:
            continue
        pts = model.points[np.unique(model.obs_point[model.obs_camera == i])]
        pts = pts[np.isfinite(pts).all(1)]
        W = np.asarray(static.world_to_camera[c], np.float64)
        z = pts @ W[2, :3] + W[2, 3]
        z = z[z > 1e-6]
        if len(z) < min_points:
            continue
        lo, mid, hi = np.percentile(z, (_DEPTH_PERCENTILES[0], 50.0, _DEPTH_PERCENTILES[1]))
        stage = depths_in_view(grid, static.K[c], W, static.size[c])
        stage = stage[stage >= spacing]
        if len(stage):
            lo, mid, hi = min(lo, stage.min()), np.median(stage), max(hi, stage.max())
        out[c] = (float(lo), float(mid), float(hi))
    return out


def _surface_depth_ranges(plates: Mapping[str, np.ndarray], cameras: Mapping[str, tuple[np.ndarray, np.ndarray]],
                          scale: float) -> tuple[dict[str, tuple[float, float]], dict[str, float], dict]:
    """Each camera's sweep depth range for :func:`surface_from_plates`, from a probe sweep of the
    plates, its median depth (where its neighbours are chosen) and the stats saying how they were
    found. The probe chooses neighbours at the median distance to the other cameras (a rig looks
    across its stage)."""
    t0 = time.perf_counter()
    ids = sorted(cameras)
    gaps, spacing = camera_gaps([cameras[c][1] for c in ids])
    spacing = max(spacing, 1e-6)
    near, far = _PROBE_NEAR * spacing, _PROBE_FAR * spacing
    across = {c: float(np.median(gaps[i][np.isfinite(gaps[i])])) for i, c in enumerate(ids)}
    probe, _ = _sweep_and_fuse(plates, cameras, 2 * scale, {c: (near, far) for c in ids}, across, depth_tol=0.02)
    stats: dict = {"probe_points": len(probe), "camera_spacing_m": spacing, "probe_near_m": near, "probe_far_m": far,
                   "depth_range": {}}
    found: dict[str, tuple[float, float]] = {}
    middle = dict(across)
    close: list[str] = []
    for c in ids:
        h, w = np.asarray(plates[c]).shape[:2]
        z = depths_in_view(probe, cameras[c][0], cameras[c][1], (w, h))
        stats["depth_range"][c] = {"probe_points": len(z)}
        if len(z) < _MIN_PROBE_POINTS:
            continue
        lo, hi = np.percentile(z, _DEPTH_PERCENTILES)
        middle[c] = float(np.median(z))
        lo_m, _, hi_m = sweep_range((float(lo), middle[c], float(hi)))
        found[c] = (max(near, lo_m), min(far, hi_m))
        if lo < 2 * near:
            close.append(f"{c} ({lo:.2f} m)")
    if found:
        widest = (min(v[0] for v in found.values()), max(v[1] for v in found.values()))
    else:   # the probe saw (almost) nothing: the whole probe range, slow but nothing left out
        widest = (near, far)
    ranges = {c: found.get(c, widest) for c in ids}
    fallback = [c for c in ids if c not in found]
    if fallback:
        log.warning("no lidar scan: the stand-in surface's probe saw fewer than %d points in camera(s) %s; they "
                    "sweep %.2f-%.1f m (%s)", _MIN_PROBE_POINTS, ", ".join(fallback), *widest,
                    "the other cameras' widest range" if found else "the whole probe range")
    if close:
        log.warning("no lidar scan: the background of camera(s) %s reaches the stand-in surface's nearest probe "
                    "depth (%.2f m): anything nearer is left out of it", ", ".join(close), near)
    for c in ids:
        stats["depth_range"][c].update({"min_m": ranges[c][0], "max_m": ranges[c][1]})
    stats.update({"depth_min_m": min(v[0] for v in ranges.values()), "depth_max_m": max(v[1] for v in ranges.values()),
                  "depth_fallback_cameras": len(fallback), "near_limit_cameras": len(close),
                  "probe_seconds": time.perf_counter() - t0})
    return ranges, middle, stats


def _known_distance_of(ids: Sequence[str], known: tuple[str, str, float]) -> tuple[str, str, float]:
    """``known`` (camera id, camera id, metres) when both cameras are among the calibrated ``ids``
    and the distance is positive; :class:`KnownDistanceError` otherwise."""
    a, b, d = known
    missing = [c for c in (a, b) if c not in ids]
    if missing:
        raise KnownDistanceError(f"known_distance names camera(s) {missing} that are not calibrated static cameras "
                                 f"({', '.join(sorted(ids))})")
    if not d > 0:
        raise KnownDistanceError(f"known_distance between {a} and {b} must be positive, got {d}")
    return a, b, d


def _check_known_distance(world_to_camera: Mapping[str, np.ndarray], known: tuple[str, str, float]) -> dict:
    """With a scan (which gives the scale): how far the calibrated cameras' centres are from the
    known distance (metres)."""
    a, b, d = _known_distance_of(list(world_to_camera), known)
    measured = float(np.linalg.norm(camera_centre(world_to_camera[a]) - camera_centre(world_to_camera[b])))
    return {"known_distance_m": float(d), "known_distance_measured_m": measured,
            "known_distance_error_m": measured - float(d)}


def frame_without_lidar(world_to_camera: Mapping[str, np.ndarray], mounts: Mapping[str, np.ndarray],
                        options: StaticCalibrationOptions = StaticCalibrationOptions()) -> tuple[Similarity, dict]:
    """The stage frame and metric scale of cameras calibrated without a lidar scan: the robust
    similarity (:func:`~volcap_core.calibration.geometry.robust_umeyama`, inliers within 0.25 m)
    taking the adjusted camera centres onto the rig's mount positions; with
    ``options.known_distance`` (two cameras' centre distance in metres) the scale is then set so
    that distance comes out exact (a scaling about the mounts' centroid: the mounts still give the
    orientation and position).

    Returns the similarity (``x_stage = s R x + t``) and stats: ``scale`` (of the whole
    transform), ``rotation_deg``, ``translation_m``, ``mount_inliers``, ``mount_residual_rms_m`` /
    ``_median_m`` / ``_max_m`` (distance of each camera centre from its mount afterwards: with
    mounts surveyed to a few cm and a good SfM, a few cm) and ``mount_residual.<id>``, and with a
    known distance ``known_distance_*``. A camera further than ``options.mount_tolerance_m`` from its
    mount is logged as a warning (``mount_outliers``: how many)."""
    ids = sorted(world_to_camera)
    src = np.stack([camera_centre(world_to_camera[c]) for c in ids])
    dst = np.stack([np.asarray(mounts[c], np.float64) for c in ids])
    if len(ids) >= 3:
        T, inl = robust_umeyama(src, dst, threshold=0.25)
    else:   # two cameras do not fix a rotation: left where the mounts' prior put them
        T, inl = Similarity(), np.ones(len(ids), bool)
    stats: dict = {"scale_source": 0.0, "mount_inliers": int(inl.sum())}
    if options.known_distance is not None:
        a, b, d = _known_distance_of(ids, options.known_distance)
        moved = T.apply(src)
        now = float(np.linalg.norm(moved[ids.index(a)] - moved[ids.index(b)]))
        k = float(d) / now
        c0 = dst.mean(0)
        T = Similarity(k, np.eye(3), c0 - k * c0).compose(T)
        stats.update({"scale_source": 1.0, "known_distance_m": float(d), "known_distance_scale": k,
                      "known_distance_from_mounts_m": now})
    r = np.linalg.norm(T.apply(src) - dst, axis=1)
    stats.update({"scale": float(T.s), "rotation_deg": float(rotation_angle_deg(T.R, np.eye(3))),
                  "translation_m": float(np.linalg.norm(T.t)), "mount_residual_rms_m": float(np.sqrt(np.mean(r ** 2))),
                  "mount_residual_median_m": float(np.median(r)), "mount_residual_max_m": float(r.max()),
                  "mount_residual": {c: float(v) for c, v in zip(ids, r)}})
    far = [f"{c} {v:.3f} m" for c, v in zip(ids, r) if v > options.mount_tolerance_m]
    stats["mount_outliers"] = len(far)
    if far:
        log.warning(
            "no lidar scan: static camera(s) end further than %.2f m from their mounts after the similarity onto "
            "the mounts: %s (check the rig's mount positions)", options.mount_tolerance_m, ", ".join(far))
    return T, stats


def camera_support(K: Mapping[str, np.ndarray], world_to_camera: Mapping[str, np.ndarray], camera_ids: list[str],
                   points: np.ndarray, obs_camera: np.ndarray, obs_point: np.ndarray, obs_xy: np.ndarray,
                   *, min_sigma_px: float = 0.05) -> dict[str, dict]:
    """How well the observations hold each camera: per camera id, ``observations`` (count),
    ``residual_px`` (robust σ of the reprojection residual, 1.4826 MAD per coordinate, at least
    ``min_sigma_px``), and ``rotation_sigma_deg`` / ``centre_sigma_m``: the largest standard
    deviation of the camera's rotation and centre from the Gauss-Newton covariance
    ``σ² (JᵀJ)⁻¹`` of its 6 pose parameters with the points and intrinsics held fixed. Holding the
    points fixed makes it a lower bound (optimistic), and it ignores the mount and lidar priors:
    it measures what the camera's own observations pin down (inf when they cannot: fewer than 3, or
    degenerate). Costs a 6x6 system per camera.

    ``obs_camera`` indexes ``camera_ids``; observations in OpenCV pixels."""
    out: dict[str, dict] = {}
    P = np.asarray(points, np.float64)
    for i, c in enumerate(camera_ids):
        sel = np.asarray(obs_camera) == i
        n = int(sel.sum())
        entry = {"observations": n, "residual_px": float("inf"), "rotation_sigma_deg": float("inf"),
                 "centre_sigma_m": float("inf")}
        out[c] = entry
        if n < 3:
            continue
        W = np.asarray(world_to_camera[c], np.float64)
        Kc = np.asarray(K[c], np.float64)
        R = W[:3, :3]
        X = P[np.asarray(obs_point)[sel]] @ R.T + W[:3, 3]
        z = X[:, 2]
        front = z > 1e-9
        if front.sum() < 3:
            continue
        X, z, xy = X[front], z[front], np.asarray(obs_xy, np.float64)[sel][front]
        fx, fy = Kc[0, 0], Kc[1, 1]
        uv = np.c_[fx * X[:, 0] / z + Kc[0, 2], fy * X[:, 1] / z + Kc[1, 2]]
        r = (uv - xy).ravel()
        sigma = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), min_sigma_px)
        # d(u, v)/d X_cam, and X_cam = exp([w]) R (X - C - dC): dX_cam = -[X_cam]x w - R dC
        du = np.zeros((len(X), 2, 3))
        du[:, 0, 0] = fx / z
        du[:, 0, 2] = -fx * X[:, 0] / z ** 2
        du[:, 1, 1] = fy / z
        du[:, 1, 2] = -fy * X[:, 1] / z ** 2
        skew = np.zeros((len(X), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -X[:, 2], X[:, 1], -X[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = X[:, 2], -X[:, 1], X[:, 0]
        J = np.concatenate([du @ -skew, du @ -R], axis=2).reshape(-1, 6)
        H = J.T @ J
        entry["residual_px"] = sigma
        if np.linalg.cond(H) > 1e14:
            continue
        cov = sigma ** 2 * np.linalg.inv(H)
        entry["rotation_sigma_deg"] = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0))))
        entry["centre_sigma_m"] = float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0)))
    return out


def _unsupported(s: Mapping, options: StaticCalibrationOptions) -> str:
    """Why a camera's support (:func:`camera_support`) is not enough under ``options`` ('' if it is)."""
    if s["observations"] < options.min_observations:
        return (f"{s['observations']} observations left after the bundle adjustment's outlier rejection "
                f"(needs at least {options.min_observations})")
    if options.max_rotation_sigma_deg is not None and not s["rotation_sigma_deg"] <= options.max_rotation_sigma_deg:
        return (f"its rotation is determined to {s['rotation_sigma_deg']:.3g}° only (bound "
                f"{options.max_rotation_sigma_deg}°, from {s['observations']} observations)")
    if options.max_centre_sigma_m is not None and not s["centre_sigma_m"] <= options.max_centre_sigma_m:
        return (f"its position is determined to {s['centre_sigma_m']:.3g} m only (bound "
                f"{options.max_centre_sigma_m} m, from {s['observations']} observations)")
    return ""


def _without_cameras(model: SparseModel, drop: list[str], min_views: int = 2) -> SparseModel:
    """``model`` without the cameras ``drop`` (moved to ``unregistered``) and their observations;
    observations of points left with fewer than ``min_views`` views go too."""
    if not drop:
        return model
    keep_ids = [c for c in model.camera_ids if c not in drop]
    new_index = np.full(len(model.camera_ids), -1, np.int64)
    for j, c in enumerate(keep_ids):
        new_index[model.camera_ids.index(c)] = j
    oc = new_index[model.obs_camera] if len(model.obs_camera) else model.obs_camera
    keep = oc >= 0
    views = np.bincount(model.obs_point[keep], minlength=len(model.points))
    keep &= views[model.obs_point] >= min_views
    pok = {c: np.where((v >= 0) & (views[np.maximum(v, 0)] >= min_views), v, -1)
           for c, v in model.point_of_keypoint.items() if c not in drop}
    return replace(model, camera_ids=keep_ids,
                   intrinsics={c: model.intrinsics[c] for c in keep_ids},
                   world_to_camera={c: model.world_to_camera[c] for c in keep_ids},
                   obs_point=model.obs_point[keep], obs_camera=oc[keep], obs_xy=model.obs_xy[keep],
                   keypoints={c: v for c, v in model.keypoints.items() if c not in drop},
                   descriptors={c: v for c, v in model.descriptors.items() if c not in drop},
                   point_of_keypoint=pok, unregistered=sorted(set(model.unregistered) | set(drop)))
