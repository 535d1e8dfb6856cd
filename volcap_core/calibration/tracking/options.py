"""The settings of the tracking-camera stage (:mod:`volcap_core.calibration.tracking`), one
frozen dataclass read by its observation, solve and lens parts (and keyed by the calibration
task)."""

from __future__ import annotations

from dataclasses import dataclass

from volcap_core.calibration.features import SiftOptions


@dataclass(frozen=True)
class TrackingOptions:
    #: SIFT for the zoomed frames: more octaves (their background is many times larger)
    sift: SiftOptions = SiftOptions(num_octaves=6)
    ratio_3d: float = 0.85
    ratio_2d: float = 0.8
    pair_offsets: tuple[int, ...] = (1, 2, 4)
    #: RANSAC threshold (px) of the frame-to-frame background homography: a few times SIFT's error,
    #: well below how far the background of a tracker that follows an actor moves between
    #: neighbouring frames, which is about what the actor moves (a wider threshold lets the
    #: background's model take in the actor's matches; docs/calibration.md)
    homography_px: float = 1.5
    min_pair_matches: int = 12
    pixel_sigma_3d: float = 2.0
    pixel_sigma_2d: float = 1.0
    focal_sigma_rel: float = 0.003
    centre_sigma_m: float = 0.005
    #: prior of the mean centre around the rig's mount (a zoomed view barely tells a sideways
    #: shift from a pan: without it the centre slides tens of cm)
    mount_sigma_m: float = 0.05
    smooth_lambda: float = 4.0
    iterations: int = 30
    #: starts along the zoom/dolly valley: the refinement is run from the initial focal scaled by
    #: each factor (and the centre moved along the view axis so the scene keeps its image size)
    #: and each camera keeps its lowest-cost solution. One start (the encoder's focal) is enough:
    #: LM slides along the valley to its lowest point (docs/calibration.md, "Tracking (zoom)
    #: cameras"). More starts are for a take whose cost along the valley has more than one dip
    focal_scale_starts: tuple[float, ...] = (1.0,)
    #: guided 2D-3D matching after the first solve
    #: (:func:`~volcap_core.calibration.tracking.observe.guided_observations`): each frame's
    #: keypoints matched only to the reference points its solved camera projects within this radius
    #: (px; None: off), ratio test among those candidates, and a ceiling on the SIFT distance; then
    #: the solve is refined from its solution (more 2D-3D inliers where a zoomed view's few
    #: background features fail the ratio test against the whole stage)
    guided_radius_px: float | None = 6.0
    guided_ratio: float = 0.9
    guided_max_distance: float = 250.0
    mode: str = "priors"            # priors | free | independent
    #: undistort each frame with its zoom lens at its focal (the ``lenses`` given to
    #: :func:`~volcap_core.calibration.tracking.calibrate.prepare_tracking`, from the rig's
    #: ``zoom_intrinsics``); False reads the raw frames as pinholes with the principal point at the
    #: image centre (to measure what the lens is worth)
    zoom_distortion: bool = True
    ransac_iterations: int = 2000
    ransac_px: float = 12.0
    #: support a camera needs to be returned as calibrated
    #: (:func:`~volcap_core.calibration.tracking.solve.tracking_support`): 2D-3D inliers over the
    #: take and the covariance's bound on any frame's orientation (degrees; None: no bound)
    min_inliers_3d: int = 8
    max_rotation_sigma_deg: float | None = 2.0
    #: an unsupported camera is left out of the calibration (listed with the reason) instead of an
    #: error (``volcap calibrate --allow-unregistered``)
    allow_unsupported: bool = False
    device: str = "cpu"
    seed: int = 0
