"""Static wide cameras: one calibration from the middle frame, in metres and the stage frame.

Pipeline (each step a pure function of the previous one's output):

1. intrinsics from the lens metadata: the rig's nominal focal (mm) -> pixels, principal point at
   the image centre, no distortion;
2. sparse SfM with pycolmap (:func:`volcap_core.calibration.sfm.reconstruct_static`): SIFT,
   exhaustive matching, then triangulation from the rig's nominal mount poses (seeded, default) or
   COLMAP's incremental mapper followed by a robust similarity onto the nominal mount positions;
3. a robust point-to-plane ICP of the sparse points onto the lidar scan (incremental path only:
   seeded poses are already in the stage frame);
4. bundle adjustment in torch with the lidar as a prior on the points, a focal prior around the
   lens metadata and a centre prior around the mounts (:mod:`volcap_core.calibration.bundle`);
5. with a lidar scan: lidar-guided patch matching of the background plates between the cameras of
   step 4 (:mod:`volcap_core.calibration.guided`, ~30x the observations, over the whole image) and
   a second bundle adjustment on those tracks that also refines the principal points and leaves the
   centres to the data (the mounts only a weak prior);
6. optionally, direct photometric refinement against the lidar
   (:mod:`volcap_core.calibration.photometric`): every textured background pixel seen by two cameras
   votes (off by default: it did not improve the demo capture).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from hardware.rig import Rig, RigCamera
from volcap_core.calibration.bundle import BundleOptions, bundle_adjust
from volcap_core.calibration.geometry import (Similarity, look_at_rotation, pose_matrix, robust_umeyama,
                                              triangulate_points)
from volcap_core.calibration.guided import GuidedMatchOptions, guided_tracks
from volcap_core.calibration.lidar import LidarScan, align_to_lidar
from volcap_core.calibration.photometric import PhotometricOptions, refine_photometric
from volcap_core.calibration.sfm import Intrinsics, SparseModel, StaticSfmOptions, reconstruct_static


@dataclass(frozen=True)
class StaticCalibrationOptions:
    sfm: StaticSfmOptions = StaticSfmOptions()
    #: seed the SfM with the rig's nominal mount poses (False: COLMAP's incremental mapper alone)
    seeded: bool = True
    bundle: BundleOptions = BundleOptions(focal_sigma_rel=0.03, centre_sigma_m=0.03)
    #: lidar-guided patch matching after the first adjustment (None skips it and the second one)
    guided: GuidedMatchOptions | None = GuidedMatchOptions()
    #: the adjustment on the guided tracks: observations weighted as what they are (NCC matches
    #: reproject to ~0.05 px: at the first adjustment's 1 px the priors outweighed them along the
    #: principal-point/rotation valley), principal points refined (σ 2 px around the image centre),
    #: centres left to the data (σ 0.3 m around the mounts)
    guided_bundle: BundleOptions = BundleOptions(pixel_sigma=0.1, focal_sigma_rel=0.03, centre_sigma_m=0.3,
                                                 principal_sigma_px=2.0)
    #: None (default) skips the photometric refinement: on the demo capture it did not beat the
    #: lidar-constrained bundle adjustment (rotation 0.19° vs 0.17° mean, centres 0.8 % vs 0.5 % of
    #: the stage) at ten times the cost; ``PhotometricOptions(max_points=20000, centre_sigma_m=0.03)``
    #: turns it on
    photometric: PhotometricOptions | None = None
    #: frames (evenly spread over the take) whose median is each static camera's background plate
    plate_frames: int = 8
    #: the take index calibrated on; None: the middle frame (the paper)
    reference_frame: int | None = None
    #: the SfM must register at least this fraction of the static cameras (and two): fewer means
    #: the views do not overlap enough (or the frame is wrong), and calibration stops there
    min_registered_fraction: float = 0.5


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


def nominal_intrinsics(cam: RigCamera) -> Intrinsics:
    """Lens metadata -> pinhole intrinsics: nominal focal (mm) in pixels, centred principal point."""
    s = cam.sensor
    return Intrinsics.nominal(s.focal_px(cam.nominal_focal_mm), s.width_px, s.height_px)


def nominal_pose(cam: RigCamera) -> np.ndarray:
    """World-to-camera [4, 4] of a camera at its nominal mount, looking at its nominal target."""
    R = look_at_rotation(cam.mount.position_m, cam.mount.look_at_m, cam.mount.roll_deg)
    return pose_matrix(R, -R @ np.asarray(cam.mount.position_m, np.float64))


def calibrate_static_cameras(images: Mapping[str, np.ndarray], rig: Rig, scan: LidarScan | None,
                             *, plates: Mapping[str, np.ndarray] | None = None,
                             options: StaticCalibrationOptions = StaticCalibrationOptions()) -> StaticCalibration:
    """Calibrate the rig's static cameras from one instant.

    ``images``: static camera id -> scene-linear RGB [H, W, 3] float at the middle frame.
    ``plates``: optional background plates (:func:`~volcap_core.calibration.photometric.background_plate`)
    for the guided matching and the photometric step (default: ``images``; plates have no actors, whom
    the scan does not have). ``scan``: the lidar scan of the static stage in the stage frame (None:
    metric frame from the mounts only, no lidar terms, no guided matching, no photometric step).
    """
    t0 = time.perf_counter()
    ids = sorted(images)
    cams = {c: rig.camera(c) for c in ids}
    intr = {c: nominal_intrinsics(cams[c]) for c in ids}
    seeds = {c: nominal_pose(cams[c]) for c in ids}
    mounts = {c: np.asarray(cams[c].mount.position_m, np.float64) for c in ids}
    stats: dict = {}
    model = reconstruct_static(images, intr, options.sfm, initial_poses=seeds if options.seeded else None)
    stats["sfm"] = dict(model.stats)
    t1 = time.perf_counter()
    if not options.seeded:
        src = model.centres()
        dst = np.stack([mounts[c] for c in model.camera_ids])
        T, _ = robust_umeyama(src, dst, threshold=0.5)
        model = model.transformed(T)
        if scan is not None:
            T2, icp = align_to_lidar(model.points, scan)
            model = model.transformed(T2)
            stats["icp"] = icp
    reg = model.camera_ids
    res = bundle_adjust(np.stack([model.world_to_camera[c] for c in reg]),
                        np.array([model.intrinsics[c].fx for c in reg]),
                        np.array([[model.intrinsics[c].cx, model.intrinsics[c].cy] for c in reg]),
                        model.points, model.obs_camera, model.obs_point, model.obs_xy, scan=scan,
                        focal_prior=np.array([intr[c].fx for c in reg]),
                        centre_prior=np.stack([mounts[c] for c in reg]), options=options.bundle)
    K = {c: np.array([[res["focal"][i], 0, intr[c].cx], [0, res["focal"][i], intr[c].cy], [0, 0, 1.0]])
         for i, c in enumerate(reg)}
    w2c = {c: res["world_to_camera"][i] for i, c in enumerate(reg)}
    stats["bundle"] = dict(res["stats"])
    stats["bundle"]["median_reprojection_px"] = float(np.median(res["reprojection_px"][res["inlier"]]))
    t2 = time.perf_counter()
    background = plates if plates is not None else images
    if scan is not None and options.guided is not None:
        # the tracks' cameras come in ``reg`` order, the order of the dict passed
        tracks = guided_tracks({c: background[c] for c in reg}, K, w2c, scan, options.guided)
        P = np.stack([K[c] @ w2c[c][:3] for c in reg])
        start = triangulate_points(P, tracks.obs_point, tracks.obs_camera, tracks.obs_xy, len(tracks.points))
        start = np.where(np.isfinite(start), start, tracks.points)
        g = bundle_adjust(np.stack([w2c[c] for c in reg]), np.array([K[c][0, 0] for c in reg]),
                          np.array([[intr[c].cx, intr[c].cy] for c in reg]), start, tracks.obs_camera,
                          tracks.obs_point, tracks.obs_xy, scan=scan, focal_prior=np.array([intr[c].fx for c in reg]),
                          centre_prior=np.stack([mounts[c] for c in reg]), options=options.guided_bundle)
        K = {c: np.array([[g["focal"][i], 0, g["principal"][i, 0]], [0, g["focal"][i], g["principal"][i, 1]],
                          [0, 0, 1.0]]) for i, c in enumerate(reg)}
        w2c = {c: g["world_to_camera"][i] for i, c in enumerate(reg)}
        stats["guided"] = {**tracks.stats, "bundle": g["stats"], "inliers": int(g["inlier"].sum()),
                           "median_reprojection_px": float(np.median(g["reprojection_px"][g["inlier"]]))}
    t_guided = time.perf_counter()
    if scan is not None and options.photometric is not None:
        ph = refine_photometric({c: background[c] for c in reg}, K, w2c, scan, centre_prior=mounts,
                                focal_prior={c: intr[c].fx for c in reg}, options=options.photometric)
        K, w2c = ph["K"], ph["world_to_camera"]
        stats["photometric"] = {k: ph[k] for k in ("samples", "points", "rms_per_level", "seconds")}
    t3 = time.perf_counter()
    # the sparse points, re-triangulated from the final cameras (inlier observations only)
    inl = res["inlier"]
    P = np.stack([K[c] @ w2c[c][:3] for c in reg])
    pts = triangulate_points(P, model.obs_point[inl], model.obs_camera[inl], model.obs_xy[inl], len(model.points))
    good = np.isfinite(pts).all(1)
    pts[~good] = res["points"][~good]
    model.points = pts
    model.world_to_camera = dict(w2c)
    model.intrinsics = {c: Intrinsics(K[c][0, 0], K[c][1, 1], K[c][0, 2], K[c][1, 2], intr[c].width,
                                      intr[c].height) for c in reg}
    stats["time_s"] = {"sfm": t1 - t0, "bundle": t2 - t1, "guided": t_guided - t2, "photometric": t3 - t_guided,
                       "total": time.perf_counter() - t0}
    return StaticCalibration(camera_ids=reg, K=K, world_to_camera=w2c,
                             size={c: (intr[c].width, intr[c].height) for c in reg}, model=model,
                             unregistered=list(model.unregistered), stats=stats)


def similarity_to_mounts(model: SparseModel, rig: Rig) -> Similarity:
    """Robust similarity taking a reconstruction's camera centres onto the rig's nominal mounts."""
    src = model.centres()
    dst = np.stack([np.asarray(rig.camera(c).mount.position_m, np.float64) for c in model.camera_ids])
    return robust_umeyama(src, dst, threshold=0.5)[0]
