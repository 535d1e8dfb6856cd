"""Static-camera structure from motion with pycolmap (CPU): SIFT, exhaustive matching, then
triangulation from the rig's nominal poses (seeded) or incremental mapping, the focal lengths held
at the rig's, and a robust global bundle adjustment; distorted cameras' inputs rectified into
square pinholes for the steps after (:func:`rectify_static_inputs`).

Traps handled here (pycolmap 4.2.1, see NOTES):

- ``cv2`` is imported before ``pycolmap`` (zlib clash on PNG writes otherwise);
- ``Database.write_camera`` creates a rig implicitly, and images written by hand get no frame: the
  images are created by feature extraction with ``ImageReaderOptions.existing_camera_id`` so each
  image is tied to its own, known camera (and frame);
- matching small views 30° apart gives few verified matches a pair: the mapper's initial-pair
  and registration thresholds are lowered accordingly, and affine-adapted SIFT is used;
- no dense MVS (``patch_match_stereo`` needs CUDA).

Everything returned is in OpenCV conventions (see :mod:`volcap_core.calibration.geometry`), in the
arbitrary frame and scale of the reconstruction until :meth:`SparseModel.transformed` is applied.
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Mapping, Sequence

import cv2
import numpy as np
import pycolmap

from hardware.lens_models import COLMAP_PIXEL_OFFSET
from volcap_core.calibration.distortion import Distortion, colmap_camera, from_colmap_camera
from volcap_core.calibration.features import SiftOptions
from volcap_core.calibration.geometry import Similarity, pose_matrix
from volcap_core.calibration.images import to_uint8_gray

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsics in OpenCV pixels (centre of the top-left pixel at (0, 0)) and the lens
    distortion (:class:`~volcap_core.calibration.distortion.Distortion`, none by default: a
    pinhole). A world point projects to ``K distortion.distort(x / z, y / z)``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: Distortion = Distortion.none()

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def pinhole(self) -> "Intrinsics":
        """The same fx, fy, cx, cy and size without the distortion."""
        return replace(self, distortion=Distortion.none())

    @staticmethod
    def nominal(focal_px: float, width: int, height: int) -> "Intrinsics":
        """Square pixels, principal point at the image centre ((W-1)/2, (H-1)/2), no distortion."""
        return Intrinsics(float(focal_px), float(focal_px), (width - 1) / 2.0, (height - 1) / 2.0,
                          int(width), int(height))

    @staticmethod
    def measured(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                 distortion: Distortion | None = None) -> "Intrinsics":
        """Intrinsics from a lens calibration (OpenCV pixels at ``width`` x ``height``)."""
        intr = Intrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height),
                          distortion if distortion is not None else Distortion.none())
        if not (intr.fx > 0 and intr.fy > 0 and np.isfinite([intr.cx, intr.cy]).all()):
            raise ValueError(f"measured intrinsics need positive focals and finite centres, got "
                             f"fx={fx} fy={fy} cx={cx} cy={cy}")
        return intr

    @staticmethod
    def from_rig(rig, camera_id: str) -> "Intrinsics":
        """A rig camera's intrinsics: its measured ones (its own or its lens group's, see
        ``hardware.rig.Rig.measured_intrinsics``) when the rig has them, else the nominal ones (the
        nominal focal in pixels, square pixels, centred principal point, no distortion)."""
        cam = rig.camera(camera_id)
        s = cam.sensor
        m = rig.measured_intrinsics(camera_id)
        if m is None:
            return Intrinsics.nominal(s.focal_px(cam.nominal_focal_mm), s.width_px, s.height_px)
        return Intrinsics.measured(m.fx, m.fy, m.cx, m.cy, s.width_px, s.height_px,
                                   Distortion(m.model, tuple(m.params)))

    def project(self, xyz_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points [N, 3] -> pixels [N, 2] (with the distortion)."""
        p = np.asarray(xyz_cam, np.float64)
        xy = self.distortion.distort(p[:, :2] / p[:, 2:3])
        return xy * [self.fx, self.fy] + [self.cx, self.cy]

    def undistort_pixels(self, uv: np.ndarray, out: "Intrinsics | None" = None) -> np.ndarray:
        """Pixels of this (distorted) camera [N, 2] -> pixels of the pinhole ``out`` (default:
        this camera's K without the distortion)."""
        return self.distortion.undistort_pixels(self.K, uv, None if out is None else out.K)


@dataclass(frozen=True)
class StaticSfmOptions:
    sift: SiftOptions = SiftOptions(num_threads=1)
    match_max_ratio: float = 0.8
    #: verified inliers a pair needs: at 320x180, true neighbours give 50-95, spurious pairs
    #: (repeated texture, markers) 15-30
    min_pair_inliers: int = 36
    #: COLMAP's guided matching (re-match under the verified two-view geometry)
    guided_matching: bool = True
    init_min_num_inliers: int = 30
    abs_pose_min_num_inliers: int = 15
    #: seeded mode: rounds of triangulation from the current poses, with a COLMAP bundle
    #: adjustment between rounds (none after the last: the lidar-constrained one follows)
    seeded_rounds: int = 1
    triangulation_max_angle_deg: float = 4.0
    #: two-view tracks (a point matched in exactly two images) in the seeded triangulation. COLMAP
    #: ignores them by default, which leaves a rig whose cameras only overlap in pairs (Pose2Sim's
    #: four cameras: only cam01-cam02 share a view) with no points at all. None (default): ignored,
    #: unless that leaves a camera with fewer than ``two_view_min_observations`` observations; then
    #: the points are triangulated again with them (stats ``two_view_tracks`` 1, and a warning
    #: naming the cameras). True / False: always / never
    two_view_tracks: bool | None = None
    two_view_min_observations: int = 25
    triangulation_max_error_px: float = 8.0
    #: refine the focal lengths in the final bundle adjustment (the paper keeps them fixed)
    refine_focal: bool = False
    #: refine the cameras' lens distortion (COLMAP's extra parameters) in COLMAP's bundle
    #: adjustment; False (default) holds it at the rig's measured values (the lens calibration is
    #: more accurate than what a few hundred SfM points at 320x180 give). With True, the seeded path
    #: runs one COLMAP adjustment (poses and distortion) after triangulating. Cameras without
    #: distortion (PINHOLE) have nothing to refine.
    refine_distortion: bool = False
    #: Cauchy loss scale of the final bundle adjustment, pixels
    loss_scale_px: float = 1.0
    #: one thread: COLMAP's threaded matching is not deterministic (the same views gave a different
    #: calibration from run to run: docs/calibration.md); one thread is, at more time
    num_threads: int = 1
    seed: int = 0


@dataclass
class SparseModel:
    """A sparse reconstruction of the static cameras.

    Shapes: ``points`` [P, 3] float64, ``colours`` [P, 3] float32 (linear, mean over the track),
    ``track_length`` [P] int; observations ``obs_point`` [M] (row in ``points``), ``obs_camera``
    [M] (index in ``camera_ids``), ``obs_xy`` [M, 2] OpenCV px. Per camera: ``keypoints`` [K, 2]
    OpenCV px, ``descriptors`` [K, 128] uint8, ``point_of_keypoint`` [K] int (-1 = untriangulated).
    """

    camera_ids: list[str]
    intrinsics: dict[str, Intrinsics]
    world_to_camera: dict[str, np.ndarray]
    points: np.ndarray
    colours: np.ndarray
    track_length: np.ndarray
    obs_point: np.ndarray
    obs_camera: np.ndarray
    obs_xy: np.ndarray
    keypoints: dict[str, np.ndarray]
    descriptors: dict[str, np.ndarray]
    point_of_keypoint: dict[str, np.ndarray]
    unregistered: list[str] = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    #: per camera that :meth:`rectified` resampled: its own (distorted) intrinsics; empty while
    #: the model is in the cameras' own pixels
    raw_intrinsics: dict[str, Intrinsics] = field(default_factory=dict)

    def rectified(self) -> "SparseModel":
        """The same model seen by square pinhole cameras (:func:`rectified_intrinsics`): every
        distorted (or non-square) camera's observations and keypoints mapped into its rectified
        pinhole, its intrinsics replaced by that pinhole, its own kept in :attr:`raw_intrinsics`. A
        model of square pinholes comes back unchanged. Images: :func:`undistort_views`."""
        raw = {c: self.intrinsics[c] for c in self.camera_ids if needs_rectification(self.intrinsics[c])}
        if not raw:
            return self
        obs = self.obs_xy.copy()
        kps = dict(self.keypoints)
        for ci, cid in enumerate(self.camera_ids):
            if cid not in raw:
                continue
            intr, rect = raw[cid], rectified_intrinsics(raw[cid])
            sel = self.obs_camera == ci
            obs[sel] = intr.undistort_pixels(self.obs_xy[sel], rect)
            kps[cid] = intr.undistort_pixels(self.keypoints[cid], rect)
        return replace(self, obs_xy=obs, keypoints=kps,
                       intrinsics={c: rectified_intrinsics(i) if c in raw else i for c, i in self.intrinsics.items()},
                       raw_intrinsics={**self.raw_intrinsics, **raw})

    def transformed(self, sim: Similarity) -> "SparseModel":
        """The same model in the frame ``x_new = s R x + t``."""
        return replace(self, points=sim.apply(self.points),
                       world_to_camera={k: sim.apply_pose(v) for k, v in self.world_to_camera.items()})

    def centres(self) -> np.ndarray:
        """Camera centres [C, 3] in ``camera_ids`` order."""
        out = []
        for cid in self.camera_ids:
            m = self.world_to_camera[cid]
            out.append(-m[:3, :3].T @ m[:3, 3])
        return np.asarray(out)

    def reprojection_errors(self) -> np.ndarray:
        """Reprojection error (px) of every observation [M]."""
        err = np.zeros(len(self.obs_point))
        for ci, cid in enumerate(self.camera_ids):
            sel = self.obs_camera == ci
            m = self.world_to_camera[cid]
            p = self.points[self.obs_point[sel]] @ m[:3, :3].T + m[:3, 3]
            uv = self.intrinsics[cid].project(p)
            err[sel] = np.linalg.norm(uv - self.obs_xy[sel], axis=1)
        return err


def _colmap_camera(intr: Intrinsics) -> pycolmap.Camera:
    """SIMPLE_PINHOLE / PINHOLE without distortion (as before), else the distortion's COLMAP model
    (OPENCV when fx != fy for the radial ones), its parameters as the starting values."""
    model, params = colmap_camera(intr.fx, intr.fy, intr.cx, intr.cy, intr.distortion)
    cam = pycolmap.Camera(model=model, width=intr.width, height=intr.height, params=params)
    cam.has_prior_focal_length = True
    return cam


def _intrinsics_from_colmap(cam: pycolmap.Camera) -> Intrinsics:
    (fx, fy, cx, cy), dist = from_colmap_camera(cam.model_name, cam.params)
    return Intrinsics(fx, fy, cx, cy, int(cam.width), int(cam.height), dist)


def needs_rectification(intr: Intrinsics) -> bool:
    """A camera the pinhole, one-focal stages (torch bundle adjustment, guided matching, dense
    points) cannot take as it is: it has distortion or non-square pixels."""
    return not intr.distortion.is_none or abs(intr.fx - intr.fy) > 1e-9 * intr.fx


def rectified_intrinsics(intr: Intrinsics) -> Intrinsics:
    """The square pinhole a camera's images are resampled to: focal ``fx`` for both axes, the same
    principal point and size, no distortion (unchanged for a square pinhole)."""
    if not needs_rectification(intr):
        return intr
    return Intrinsics(intr.fx, intr.fx, intr.cx, intr.cy, intr.width, intr.height)


#: how far (px) inside the source frame a rectified pixel of :func:`undistort_views` must fall to
#: count as footage: the Lanczos kernel's main lobe. Its side lobes reach 4 px with weights of a few
#: percent; a 4 px margin dropped anchors at the image edges, where a principal point and a rotation
#: differ most, and left the static cameras worse (docs/calibration.md)
RECTIFY_MARGIN_PX = 1.0


def undistort_views(images: Mapping[str, np.ndarray], intrinsics: Mapping[str, Intrinsics]
                    ) -> dict[str, np.ndarray]:
    """Images of distorted (or non-square) cameras -> their :func:`rectified_intrinsics` pinhole
    images (black where the ray leaves the source image: the borders of a barrel-distorted view).
    Square pinholes' images are returned as they are (the same arrays).

    Resampled with Lanczos (``cv2.INTER_LANCZOS4``, negative ringing clipped to 0), not bilinear:
    the calibration measures sub-pixel positions in these views, and bilinear interpolation blurs
    each pixel by an amount that depends on its sub-pixel phase, which moves the guided matching's
    NCC peaks by hundredths of a pixel; along the direction where a principal point and a rotation
    trade that is tenths of a pixel of principal point (``docs/benchmarks.md``, "Rectified with
    Lanczos")."""
    import cv2

    from volcap_core.calibration.distortion import undistort_image

    out = {}
    for cid, img in images.items():
        intr = intrinsics.get(cid)
        if intr is None or not needs_rectification(intr):
            out[cid] = img
        else:
            rect = undistort_image(img, intr, intr.distortion, rectified_intrinsics(intr),
                                   interpolation=cv2.INTER_LANCZOS4)
            out[cid] = np.maximum(rect, 0) if np.issubdtype(rect.dtype, np.floating) else rect
    return out


def raw_from_rectified(K: np.ndarray, raw: Intrinsics) -> Intrinsics:
    """A camera calibrated as the pinhole ``K`` [3, 3] on images rectified from ``raw`` (by
    :func:`undistort_views`) -> its intrinsics on its own images: ``K_raw = K_meas K_rect⁻¹ K``,
    ``raw``'s distortion. Exact for focal and centre changes of the pinhole when the distortion is
    none; with distortion the distortion stays centred at the measured principal point, so the
    model is exact to first order (the error is d(distortion)/dx times the change, ~0.01 px for a
    0.2 % focal and 0.3 px centre change with k1 = 0.1 at the corners of a 75° view)."""
    rect = rectified_intrinsics(raw)
    Kr = raw.K @ np.linalg.inv(rect.K) @ np.asarray(K, np.float64)
    return Intrinsics(float(Kr[0, 0]), float(Kr[1, 1]), float(Kr[0, 2]), float(Kr[1, 2]), raw.width, raw.height,
                      raw.distortion)


def rectify_static_inputs(model: "SparseModel", intrinsics: Mapping[str, Intrinsics],
                          images: Mapping[str, np.ndarray], plates: Mapping[str, np.ndarray] | None):
    """After :func:`reconstruct_static` on the cameras' own images: ``(model, intrinsics, images,
    plates, raw)`` with the model's observations, the intrinsics and the images (and plates) in the
    rectified square pinholes (:func:`rectified_intrinsics`), and ``raw`` the intrinsics the images
    were rectified from (the SfM's, so a distortion it refined is the one taken out; empty when
    every camera is a square pinhole: everything then comes back unchanged)."""
    raw = {c: model.intrinsics.get(c, i) for c, i in intrinsics.items() if needs_rectification(i)}
    if not raw:
        return model, dict(intrinsics), images, plates, {}
    model = model.rectified()
    intr = {c: rectified_intrinsics(raw[c]) if c in raw else i for c, i in intrinsics.items()}
    images = undistort_views(images, raw)
    plates = undistort_views(plates, raw) if plates is not None else None
    return model, intr, images, plates, raw


def _quiet() -> None:
    try:  # glog is chatty at INFO; keep warnings
        pycolmap.logging.minloglevel = 1
    except Exception:  # pragma: no cover - older pycolmap
        pass


def reconstruct_static(images: Mapping[str, np.ndarray], intrinsics: Mapping[str, Intrinsics],
                       options: StaticSfmOptions = StaticSfmOptions(),
                       initial_poses: Mapping[str, np.ndarray] | None = None,
                       work_dir: str | Path | None = None,
                       more_instants: Sequence[Mapping[str, np.ndarray]] = (),
                       lens_groups: Mapping[str, str] | None = None) -> SparseModel:
    """Sparse SfM of static cameras seen at one instant (the middle frame), or pooled over several.

    ``images``: camera id -> scene-linear RGB(A) float [H, W, C] (or uint8 gray [H, W]).
    ``intrinsics``: camera id -> fixed :class:`Intrinsics` (focal from the lens metadata).
    ``initial_poses``: camera id -> world-to-camera [4, 4] seeds (the rig's nominal mounts). With
    seeds the points are triangulated from the seeded poses and the poses bundle-adjusted
    (COLMAP, focal lengths fixed); without, COLMAP's incremental mapper runs on its own (it failed
    on the demo rig's mostly planar 320x180 views, see ``docs/calibration.md``).
    ``work_dir``: where the COLMAP database and PNGs go (a temporary folder when None).
    ``more_instants``: the same static cameras at other instants of the take (camera id -> image,
    any subset of ``images``' cameras), pooled into the one reconstruction (seeded path only): each
    (camera, instant) is a COLMAP image of that camera's pycolmap camera, features are matched only
    between images of the same instant (a moving board or actor is only rigid within an instant),
    every image of a camera is placed at that camera's one seeded pose, and the points triangulated
    at every instant come back as observations of the camera: a camera has ONE pose in the returned
    model, its keypoints are those of all its instants concatenated (instant order). A COLMAP
    adjustment (``seeded_rounds`` > 1, ``refine_distortion``) would move each image on its own: the
    poses of a camera's images are then averaged back into one (:func:`_tie_instant_poses`).
    ``lens_groups``: camera id -> lens group (the rig's ``lens_group``); the cameras of a group
    share one COLMAP camera, so refined intrinsics are one set per group (their intrinsics must be
    equal: ``ValueError`` otherwise).

    Returns the largest reconstruction; cameras it could not register are in ``unregistered``.
    Raises ``RuntimeError`` when fewer than two cameras register.
    """
    _quiet()
    pycolmap.set_random_seed(options.seed)       # RANSAC in matching/verification: same input, same output
    ids = sorted(images)
    missing = [c for c in ids if c not in intrinsics]
    if missing:
        raise ValueError(f"no intrinsics for camera(s) {missing}")
    if len(ids) < 2:
        raise ValueError("static SfM needs at least two cameras")
    # instant 0 is ``images`` (image names "<id>.png", as with one instant); instant k "<id>@k.png"
    instants = [dict(images)] + [{c: v for c, v in inst.items()} for inst in more_instants]
    for k, inst in enumerate(instants[1:], 1):
        extra = sorted(set(inst) - set(ids))
        if extra:
            raise ValueError(f"instant {k}: camera(s) {extra} are not among the static cameras {ids}")
    pooled = len(instants) > 1
    if pooled and initial_poses is None:
        raise ValueError("pooling several instants needs the seeded SfM (initial_poses): the incremental "
                         "mapper would give every instant of a camera its own pose")
    with tempfile.TemporaryDirectory(prefix="volcap-sfm-") as tmp:
        work = Path(work_dir) if work_dir is not None else Path(tmp)
        t0 = time.perf_counter()
        db_path, img_dir = _build_database(instants, intrinsics, ids, options, work, lens_groups)
        t1 = time.perf_counter()
        _match(db_path, options, [[_image_stem(c, k) for c in sorted(inst)] for k, inst in enumerate(instants)]
               if pooled else None, work)
        t2 = time.perf_counter()
        if initial_poses is not None:
            seeds = {c: initial_poses[c] for c in ids if c in initial_poses}
            two_view = _two_view_tracks(db_path, img_dir, work, seeds, options)
            rec = _seeded(db_path, seeds)
            for i in range(options.seeded_rounds):
                rec = _triangulate(rec, db_path, img_dir, work, options, two_view)
                if i + 1 < options.seeded_rounds:
                    _final_bundle_adjustment(rec, options)
                    if pooled:
                        _tie_instant_poses(rec)
            if options.refine_distortion and any(not intrinsics[c].distortion.is_none for c in ids):
                _final_bundle_adjustment(rec, options)
                if pooled:
                    _tie_instant_poses(rec)
            n_models = 1
        else:
            rec, n_models = _incremental(db_path, img_dir, work, options)
            _final_bundle_adjustment(rec, options)
        t3 = time.perf_counter()
        kps, descs = _read_features(db_path)
    model = _model_from_reconstruction(rec, ids, instants, kps, descs)
    if initial_poses is not None:
        model.stats["two_view_tracks"] = float(two_view)
    model.stats.update({"time_features_s": t1 - t0, "time_matching_s": t2 - t1,
                        "time_reconstruction_s": t3 - t2, "num_models": n_models,
                        "method": "seeded" if initial_poses is not None else "incremental",
                        "instants": len(instants)})
    return model


def _image_stem(camera_id: str, instant: int) -> str:
    """The COLMAP image name (without ``.png``) of a camera at an instant: ``<id>`` for instant 0
    (as with one instant), ``<id>@<k>`` after."""
    return camera_id if instant == 0 else f"{camera_id}@{instant}"


def _split_stem(stem: str) -> tuple[str, int]:
    """``<id>`` or ``<id>@<k>`` -> (camera id, instant); camera ids never contain ``@``
    (``hardware.rig.RigCamera.id``)."""
    cid, _, k = stem.partition("@")
    return cid, int(k) if k else 0


def _tie_instant_poses(rec: pycolmap.Reconstruction) -> None:
    """After a COLMAP adjustment of a pooled reconstruction: every image of one camera (one per
    instant) set to the mean of their poses (rotations by the chordal mean, centres averaged),
    since a static camera has one pose."""
    groups: dict[str, list[int]] = {}
    for iid in rec.reg_image_ids():
        groups.setdefault(_split_stem(rec.images[iid].name[:-4])[0], []).append(iid)
    for iids in groups.values():
        if len(iids) < 2:
            continue
        mats = [rec.images[i].cam_from_world().matrix() for i in iids]
        U, _, Vt = np.linalg.svd(np.mean([m[:, :3] for m in mats], axis=0))
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        C = np.mean([-m[:, :3].T @ m[:, 3] for m in mats], axis=0)
        pose = pycolmap.Rigid3d(np.c_[R, -R @ C])
        for i in iids:
            rec.frames[rec.images[i].frame_id].rig_from_world = pose


def _build_database(instants: Sequence[Mapping[str, np.ndarray]], intrinsics, ids, options: StaticSfmOptions,
                    work: Path, lens_groups: Mapping[str, str] | None = None) -> tuple[Path, Path]:
    img_dir = work / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    db_path = work / "database.db"
    if db_path.exists():
        db_path.unlink()
    for k, inst in enumerate(instants):
        for cid in ids:
            if cid not in inst:
                continue
            img = inst[cid]
            gray = img if img.dtype == np.uint8 and img.ndim == 2 else to_uint8_gray(img)
            cv2.imwrite(str(img_dir / f"{_image_stem(cid, k)}.png"), gray)
    colmap_ids: dict[str, int] = {}
    # write_camera creates a trivial rig per camera; the images (and their frames) are created by
    # feature extraction, tied to the camera through existing_camera_id (every instant of a camera
    # is an image of the same COLMAP camera)
    # cameras of one lens group (one body and lens model) are images of ONE COLMAP camera, so an
    # adjustment that refines intrinsics (refine_focal, refine_distortion) fits one set per group
    first_of: dict[tuple[str, str], str] = {}
    with pycolmap.Database.open(str(db_path)) as db:
        for cid in ids:
            group = (lens_groups or {}).get(cid)
            key = ("group", group) if group else ("camera", cid)
            if key not in first_of:
                first_of[key] = cid
                colmap_ids[cid] = int(db.write_camera(_colmap_camera(intrinsics[cid])))
                continue
            other = first_of[key]
            if intrinsics[cid] != intrinsics[other]:
                raise ValueError(f"cameras {other} and {cid} share lens group {group!r} but not their "
                                 f"intrinsics ({intrinsics[other]} vs {intrinsics[cid]})")
            colmap_ids[cid] = colmap_ids[other]
    eo = options.sift.colmap()
    for k, inst in enumerate(instants):
        for cid in ids:
            if cid not in inst:
                continue
            ro = pycolmap.ImageReaderOptions()
            ro.existing_camera_id = colmap_ids[cid]
            pycolmap.extract_features(str(db_path), str(img_dir), image_names=[f"{_image_stem(cid, k)}.png"],
                                      reader_options=ro, extraction_options=eo, device=pycolmap.Device.cpu)
    return db_path, img_dir


def _match(db_path: Path, options: StaticSfmOptions, groups: Sequence[Sequence[str]] | None = None,
           work: Path | None = None) -> None:
    """Exhaustive matching (``groups`` None), or every pair within each group of image stems only
    (pooled instants: the images of one instant)."""
    mo = pycolmap.FeatureMatchingOptions()
    mo.sift.max_ratio = options.match_max_ratio
    mo.num_threads = options.num_threads
    mo.guided_matching = options.guided_matching
    vo = pycolmap.TwoViewGeometryOptions()
    vo.min_num_inliers = options.min_pair_inliers
    if groups is None:
        pycolmap.match_exhaustive(str(db_path), matching_options=mo, verification_options=vo,
                                  device=pycolmap.Device.cpu)
        return
    pairs = [f"{a}.png {b}.png" for g in groups for i, a in enumerate(g) for b in g[i + 1:]]
    path = Path(work if work is not None else db_path.parent) / "pairs.txt"
    path.write_text("\n".join(pairs) + "\n")
    po = pycolmap.ImportedPairingOptions()
    po.match_list_path = path
    pycolmap.match_image_pairs(str(db_path), matching_options=mo, pairing_options=po, verification_options=vo,
                               device=pycolmap.Device.cpu)


def _read_features(db_path: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Keypoints (OpenCV px) and descriptors per image stem (:func:`_image_stem`)."""
    kps, descs = {}, {}
    with pycolmap.Database.open(str(db_path)) as db:
        for im in db.read_all_images():
            stem = im.name[:-4]
            k = np.asarray(db.read_keypoints(im.image_id), np.float64)
            kps[stem] = k[:, :2] - COLMAP_PIXEL_OFFSET
            descs[stem] = np.asarray(db.read_descriptors(im.image_id).data, np.uint8)
    return kps, descs


def _incremental(db_path: Path, img_dir: Path, work: Path, options: StaticSfmOptions):
    po = pycolmap.IncrementalPipelineOptions()
    po.ba_refine_focal_length = False
    po.ba_refine_extra_params = options.refine_distortion
    po.ba_refine_principal_point = False
    po.mapper.abs_pose_refine_focal_length = False
    po.mapper.abs_pose_refine_extra_params = False
    po.mapper.init_min_num_inliers = options.init_min_num_inliers
    po.mapper.abs_pose_min_num_inliers = options.abs_pose_min_num_inliers
    po.num_threads = options.num_threads
    po.random_seed = options.seed
    po.multiple_models = True
    sparse = work / "sparse"
    sparse.mkdir(exist_ok=True)
    recs = pycolmap.incremental_mapping(str(db_path), str(img_dir), str(sparse), options=po)
    if not recs:
        raise RuntimeError("static SfM registered no cameras")
    rec = max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    if rec.num_reg_images() < 2:
        raise RuntimeError("static SfM registered fewer than two cameras")
    return rec, len(recs)


def _seeded(db_path: Path, poses: Mapping[str, np.ndarray]) -> pycolmap.Reconstruction:
    """A reconstruction with the database's cameras and images at the given poses, no points."""
    rec = pycolmap.Reconstruction()
    added: set[int] = set()     # COLMAP cameras (a lens group's cameras share one)
    seeded: set[str] = set()    # our cameras
    with pycolmap.Database.open(str(db_path)) as db:
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        for im in db.read_all_images():
            cid = _split_stem(im.name[:-4])[0]    # every instant of a camera at its one pose
            if cid not in poses:
                continue
            seeded.add(cid)
            if im.camera_id not in added:
                rec.add_camera_with_trivial_rig(cams[im.camera_id])
                added.add(im.camera_id)
            kp = np.asarray(db.read_keypoints(im.image_id), np.float64)[:, :2]
            img = pycolmap.Image(name=im.name, keypoints=kp, camera_id=im.camera_id, image_id=im.image_id)
            m = np.asarray(poses[cid], np.float64)
            rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(m[:3, :4]))
    if len(seeded) < 2:
        raise RuntimeError("seeded static SfM needs at least two seeded cameras")
    return rec


def _two_view_tracks(db_path: Path, img_dir: Path, work: Path, seeds: Mapping[str, np.ndarray],
                     options: StaticSfmOptions) -> bool:
    """Whether the seeded triangulation keeps two-view tracks (``options.two_view_tracks``; None:
    only when, without them, a camera is left with fewer than ``options.two_view_min_observations``
    observations: its overlap with the others is pairwise, say so in a warning)."""
    if options.two_view_tracks is not None:
        return options.two_view_tracks
    rec = _triangulate(_seeded(db_path, seeds), db_path, img_dir, work, options, False)
    counts = {c: 0 for c in seeds}
    for iid in rec.reg_image_ids():
        counts[_split_stem(rec.images[iid].name[:-4])[0]] += rec.images[iid].num_points3D
    few = {c: n for c, n in counts.items() if n < options.two_view_min_observations}
    if few:
        import logging

        logging.getLogger("volcap.calibrate").warning(
            "static SfM: with COLMAP's two-view tracks ignored, camera(s) %s have too few observations (%s; "
            "needs %d): their views overlap the others' in pairs only, so the points are triangulated again "
            "with two-view tracks (StaticSfmOptions.two_view_tracks)", ", ".join(sorted(few)),
            ", ".join(f"{c} {n}" for c, n in sorted(few.items())), options.two_view_min_observations)
    return bool(few)


def _triangulate(rec, db_path: Path, img_dir: Path, work: Path, options: StaticSfmOptions, two_view: bool):
    po = pycolmap.IncrementalPipelineOptions()
    po.num_threads = options.num_threads
    po.triangulation.ignore_two_view_tracks = not two_view
    po.triangulation.create_max_angle_error = options.triangulation_max_angle_deg
    po.mapper.filter_max_reproj_error = options.triangulation_max_error_px
    out = work / "triangulated"
    out.mkdir(exist_ok=True)
    return pycolmap.triangulate_points(rec, str(db_path), str(img_dir), str(out), clear_points=True,
                                       options=po, refine_intrinsics=False)


def _final_bundle_adjustment(rec: pycolmap.Reconstruction, options: StaticSfmOptions) -> None:
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = options.refine_focal
    ba.refine_principal_point = False
    ba.refine_extra_params = options.refine_distortion
    ba.print_summary = False
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.loss_function_scale = options.loss_scale_px
    pycolmap.bundle_adjustment(rec, ba)


def _model_from_reconstruction(rec, ids, instants, kps, descs) -> SparseModel:
    """The SparseModel of a reconstruction: one entry per camera, whatever its number of images
    (instants): the pose of its first registered image (all of a camera's images share it in the
    pooled path), its keypoints and descriptors those of its instants concatenated in instant order,
    observations indexed into that concatenation."""
    if isinstance(instants, Mapping):
        instants = [instants]
    reg: dict[str, dict[int, int]] = {}
    for iid in rec.reg_image_ids():
        cid, k = _split_stem(rec.images[iid].name[:-4])
        reg.setdefault(cid, {})[k] = iid
    cam_ids = [c for c in ids if c in reg]
    intr, poses = {}, {}
    for cid in cam_ids:
        im = rec.images[reg[cid][min(reg[cid])]]
        intr[cid] = _intrinsics_from_colmap(rec.cameras[im.camera_id])
        m = im.cam_from_world().matrix()
        poses[cid] = pose_matrix(m[:, :3], m[:, 3])
    # per image: (camera index, keypoint offset in the camera's concatenation, the instant's image)
    index_of_image, offsets = {}, {}
    cam_kps, cam_descs = {}, {}
    for i, cid in enumerate(cam_ids):
        stems = [_image_stem(cid, k) for k in range(len(instants)) if _image_stem(cid, k) in kps]
        off = 0
        for stem in stems:
            k = _split_stem(stem)[1]
            offsets[stem] = off
            off += len(kps[stem])
            if k in reg[cid]:
                index_of_image[reg[cid][k]] = (i, offsets[stem], instants[k][cid])
        cam_kps[cid] = np.concatenate([kps[s] for s in stems]) if stems else np.zeros((0, 2))
        cam_descs[cid] = np.concatenate([descs[s] for s in stems]) if stems else np.zeros((0, 128), np.uint8)
    kps, descs = cam_kps, cam_descs
    pid_rows = {}
    pts, cols, tl = [], [], []
    obs_p, obs_c, obs_xy = [], [], []
    pok = {c: np.full(len(kps[c]), -1, np.int64) for c in cam_ids}
    for pid, p in rec.points3D.items():
        row = len(pts)
        pid_rows[pid] = row
        pts.append(np.asarray(p.xyz, np.float64))
        rgb = []
        n = 0
        for el in p.track.elements:
            where = index_of_image.get(el.image_id)
            if where is None:
                continue
            ci, off, img = where
            cid = cam_ids[ci]
            xy = kps[cid][off + el.point2D_idx]
            obs_p.append(row)
            obs_c.append(ci)
            obs_xy.append(xy)
            pok[cid][off + el.point2D_idx] = row
            n += 1
            if img.ndim == 3:
                x = int(np.clip(round(xy[0]), 0, img.shape[1] - 1))
                y = int(np.clip(round(xy[1]), 0, img.shape[0] - 1))
                rgb.append(np.asarray(img[y, x, :3], np.float32))
        tl.append(n)
        cols.append(np.mean(rgb, axis=0) if rgb else np.zeros(3, np.float32))
    model = SparseModel(
        camera_ids=cam_ids, intrinsics=intr, world_to_camera=poses,
        points=np.asarray(pts, np.float64).reshape(-1, 3),
        colours=np.asarray(cols, np.float32).reshape(-1, 3),
        track_length=np.asarray(tl, np.int64),
        obs_point=np.asarray(obs_p, np.int64), obs_camera=np.asarray(obs_c, np.int64),
        obs_xy=np.asarray(obs_xy, np.float64).reshape(-1, 2),
        keypoints={c: kps[c] for c in cam_ids}, descriptors={c: descs[c] for c in cam_ids},
        point_of_keypoint=pok, unregistered=[c for c in ids if c not in reg])
    err = model.reprojection_errors()
    model.stats.update({"registered": len(cam_ids), "points": len(pts),
                        "mean_reprojection_error_px": float(err.mean()) if len(err) else float("nan"),
                        "mean_track_length": float(np.mean(tl)) if tl else 0.0})
    return model
