"""An imported (trusted) calibration refined against the capture's own footage.

A studio's calibration (:mod:`~volcap_core.calibration.importers`) is made before the take: a
camera knocked since, or a survey good to a few centimetres, is off by pixels in the footage
(Pose2Sim's four cameras: 10-26 px, docs/calibration.md). Refining it keeps what the studio trusts
(its world frame, scale and, unless asked, its lenses) and moves each pose only as far as the
footage says:

1. every static camera's frame at one instant (or several, pooled) is rectified into the pinhole
   of its record's K (:func:`~volcap_core.calibration.distortion.rectify_frame`) and its SIFT
   features extracted;
2. every pair of cameras is matched (ratio test, mutual) and the matches verified by a RANSAC
   fundamental matrix of the images themselves, not by the imported poses (which may be those
   pixels off); pairs with fewer than ``min_pair_matches`` inliers are dropped;
3. verified matches become tracks (union-find; a track that meets a camera twice is dropped) and
   are triangulated through the imported cameras;
4. :func:`~volcap_core.calibration.bundle.bundle_adjust` refines poses and points, each camera
   centre held around its imported one (``centre_sigma_m``: the gauge and scale stay the
   file's), focal lengths and principal points held unless ``intrinsics`` (then with priors of
   ``focal_sigma_rel`` and ``principal_sigma_px`` around the imported values; fx / fy and the lens
   are kept: the adjustment has one focal per camera, so observations are scaled to square pixels
   and back);
5. a camera with fewer than ``min_observations`` observations (it shares nothing with the others)
   keeps its imported values.

Each camera's ``quality`` says what happened: ``refine_observations``, ``refine_rotation_moved_deg``,
``refine_centre_moved_m``, ``refine_rotation_sigma_deg``, ``refine_centre_sigma_m``,
``refine_reprojection_px`` (median, inliers) and, for intrinsics, ``refine_focal_moved_rel``; a camera
left as imported (no frames, or too few observations) has ``refine_kept_imported`` = 1 and its
observation count. The record's ``stats`` gain ``refine.*`` totals. The σ are the adjustment's
(``bundle.CameraSigma``, observations at ``pixel_sigma``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from volcap_core.calibration.bundle import BundleOptions, bundle_adjust
from volcap_core.calibration.distortion import rectify_frame
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.features import SiftOptions, extract_sift, match_descriptors
from volcap_core.calibration.geometry import camera_centre, intrinsic_matrix, rotation_angle_deg, triangulate_points
from volcap_core.calibration.images import to_uint8_gray
from volcap_core.calibration.record import Calibration, CameraCalibration, matrix4


@dataclass(frozen=True)
class RefineOptions:
    #: refine focal lengths and principal points too (around the imported ones); poses only by default
    intrinsics: bool = False
    #: prior of a refined focal around the imported one (relative) and of a principal point (px)
    focal_sigma_rel: float = 0.02
    principal_sigma_px: float = 5.0
    #: prior of each camera centre around the imported one (m): how far the footage may move it
    centre_sigma_m: float = 0.05
    #: Lowe's ratio, the fundamental matrix's RANSAC threshold (px), inliers a pair needs
    ratio: float = 0.8
    ransac_px: float = 2.0
    min_pair_matches: int = 15
    #: the adjustment's pixel sigma (its Cauchy scale) and outlier rounds (px): SIFT on verified
    #: tracks is good to ~0.1 px, and the bundle's defaults (1 px; 8, 4, 3, 2 px) let its 0.5-2 px
    #: mislocalised matches pull the rotations (docs/calibration.md, "Refining an imported calibration")
    pixel_sigma: float = 0.25
    outlier_px: tuple[float, ...] = (4.0, 2.0, 1.0, 0.7)
    #: observations a camera needs to be refined; fewer: it keeps its imported values
    min_observations: int = 20
    sift: SiftOptions = field(default_factory=lambda: SiftOptions(num_octaves=6))


@dataclass(frozen=True)
class RefineReport:
    """Per camera id: ``observations`` (inliers of the adjustment), ``rotation_moved_deg``,
    ``centre_moved_m``, ``rotation_sigma_deg``, ``centre_sigma_m``, ``reprojection_px`` (median)
    and, with intrinsics, ``focal_moved_rel``; ``kept`` the cameras left as imported, with why."""

    cameras: dict[str, dict[str, float]]
    kept: dict[str, str]


def refine_imported(calibration: Calibration, frames: Sequence[Mapping[str, np.ndarray]],
                    options: RefineOptions = RefineOptions()) -> tuple[Calibration, RefineReport]:
    """``calibration`` (static cameras) refined against ``frames``: one or more instants, each camera
    id -> its frame, linear RGB float32 [H, W, 3] at the record camera's size (module docstring).
    Returns the refined record (same world frame, capture and cameras) and the per-camera report.
    A frame of another size than its camera's is an error naming the camera; tracking cameras
    and cameras without frames are kept as they are."""
    ids = [c.id for c in calibration.cameras if c.static and frames and all(c.id in f for f in frames)]
    no_footage = {c.id: "no frames of it to refine against" for c in calibration.cameras
                  if c.static and c.id not in ids}
    if len(ids) < 2:
        raise CalibrationInputError(f"calibration of {calibration.capture}: refining needs frames of at least two "
                                    f"static cameras, got {len(ids)}")
    cams = {c: calibration.camera(c) for c in ids}
    for k, instant in enumerate(frames):
        for c in ids:
            h, w = np.asarray(instant[c]).shape[:2]
            if (w, h) != (cams[c].width, cams[c].height):
                raise CalibrationInputError(f"calibration of {calibration.capture}, camera {c}: frame {k} is {w}x{h}, "
                                            f"the calibration's camera {cams[c].width}x{cams[c].height} (fit it to the "
                                            "frames first: importers.fit_calibration)")
    obs_c, obs_p, obs_xy = _tracks(ids, cams, frames, options)
    counts = np.bincount(obs_c, minlength=len(ids))
    kept = {ids[i]: f"{counts[i]} observations shared with the other cameras (needs {options.min_observations})"
            for i in range(len(ids)) if counts[i] < options.min_observations}
    kept.update(no_footage)
    report: dict[str, dict[str, float]] = {}
    updated: dict[str, CameraCalibration] = {}
    active = [i for i in range(len(ids)) if ids[i] not in kept]
    if len(active) >= 2:
        updated, report, more_kept = _adjust([ids[i] for i in active], cams, obs_c, obs_p, obs_xy, active, options)
        kept.update(more_kept)
    else:   # one camera cannot be adjusted alone: every camera keeps the file's values, and says so
        kept.update({ids[i]: "no other camera left to refine it against" for i in active})
    out = []
    for cam in calibration.cameras:
        if cam.id in updated and cam.id not in kept:
            out.append(updated[cam.id])
        elif cam.id in kept:
            obs = report.get(cam.id, {}).get("observations", float(counts[ids.index(cam.id)]) if cam.id in ids else 0.0)
            out.append(cam.model_copy(update={"quality": {**cam.quality, "refine_kept_imported": 1.0,
                                                          "refine_observations": float(obs)}}))
        else:
            out.append(cam)
    for c in kept:
        report.pop(c, None)
    moved = [r["rotation_moved_deg"] for r in report.values()]
    stats = {**calibration.stats, "refine.cameras": float(len(report)), "refine.kept_imported": float(len(kept)),
             "refine.instants": float(len(frames))}
    if moved:
        stats["refine.rotation_moved_deg_max"] = float(max(moved))
        stats["refine.centre_moved_m_max"] = float(max(r["centre_moved_m"] for r in report.values()))
    record = calibration.model_copy(update={"cameras": tuple(out), "stats": stats})
    return record, RefineReport(cameras=report, kept=kept)


def _pinhole_gray(frame: np.ndarray, cam: CameraCalibration) -> np.ndarray:
    return to_uint8_gray(np.asarray(rectify_frame(np.asarray(frame, np.float32), cam)))


def _tracks(ids: list[str], cams: Mapping[str, CameraCalibration], frames: Sequence[Mapping[str, np.ndarray]],
            options: RefineOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations (camera index [M], point index [M], pinhole px [M, 2]) of the verified tracks of
    every instant (an instant's tracks are its own points: the scene may move between instants)."""
    oc, op, oxy = [], [], []
    npts = 0
    for instant in frames:
        feats = [extract_sift(_pinhole_gray(instant[c], cams[c]), options.sift) for c in ids]
        offs = np.cumsum([0] + [len(f[0]) for f in feats])
        parent = np.arange(offs[-1])

        def find(x: int) -> int:
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        for a in range(len(ids)):
            for b in range(a + 1, len(ids)):
                m = match_descriptors(feats[a][1], feats[b][1], ratio=options.ratio, mutual=True)
                if len(m) < max(options.min_pair_matches, 8):
                    continue
                ua, ub = feats[a][0][m[:, 0], :2], feats[b][0][m[:, 1], :2]
                _, inl = cv2.findFundamentalMat(ua, ub, cv2.FM_RANSAC, options.ransac_px, 0.999)
                if inl is None or int(inl.sum()) < options.min_pair_matches:
                    continue
                for qa, qb in m[inl.ravel().astype(bool)]:
                    ra, rb = find(offs[a] + qa), find(offs[b] + qb)
                    if ra != rb:
                        parent[ra] = rb
        roots = np.array([find(x) for x in range(offs[-1])], np.int64)
        cam_of = np.concatenate([np.full(len(f[0]), k) for k, f in enumerate(feats)])
        xy = np.concatenate([f[0][:, :2] for f in feats]).astype(np.float64)
        _, inv, counts = np.unique(roots, return_inverse=True, return_counts=True)
        multi = counts[inv] >= 2
        p, c, uv = inv[multi], cam_of[multi], xy[multi]
        key = p * len(ids) + c                          # a track that meets a camera twice is dropped
        uk, kc = np.unique(key, return_counts=True)
        ok = ~np.isin(p, np.unique(uk[kc > 1] // len(ids)))
        p, c, uv = p[ok], c[ok], uv[ok]
        _, p = np.unique(p, return_inverse=True)
        oc.append(c)
        op.append(p + npts)
        oxy.append(uv)
        npts += int(p.max()) + 1 if len(p) else 0
    return (np.concatenate(oc).astype(np.int64), np.concatenate(op).astype(np.int64),
            np.concatenate(oxy).reshape(-1, 2))


def _adjust(ids: list[str], cams: Mapping[str, CameraCalibration], obs_c, obs_p, obs_xy, active: list[int],
            options: RefineOptions):
    """Bundle adjustment of the cameras ``ids`` (indices ``active`` of the observations' cameras)."""
    remap = np.full(max(active) + 1 if active else 0, -1, np.int64)
    remap[active] = np.arange(len(active))
    sel = np.isin(obs_c, active)
    oc, op, uv = remap[obs_c[sel]], obs_p[sel], obs_xy[sel].copy()
    pts, op = np.unique(op, return_inverse=True)
    intr = np.array([cams[c].intrinsics for c in ids], np.float64)          # fx, fy, cx, cy
    aspect = intr[:, 0] / intr[:, 1]
    uv[:, 1] = intr[oc, 3] + (uv[:, 1] - intr[oc, 3]) * aspect[oc]         # square pixels of focal fx
    w2c = np.stack([np.asarray(cams[c].world_to_camera, np.float64) for c in ids])
    K = np.stack([intrinsic_matrix(f, f, cx, cy) for f, _, cx, cy in intr])
    X = triangulate_points(K @ w2c[:, :3], op, oc, uv, len(pts))
    # points that did not triangulate in front of their cameras are left out
    depth = np.einsum("mij,mj->mi", w2c[oc, :3], np.c_[X[op], np.ones(len(op))])[:, 2]
    bad = np.zeros(len(pts), bool)
    np.logical_or.at(bad, op, ~(depth > 0) | ~np.isfinite(depth))
    keep = ~bad[op]
    oc, op, uv = oc[keep], op[keep], uv[keep]
    good, op = np.unique(op, return_inverse=True)
    X = X[good]
    bundle = BundleOptions(focal_sigma_rel=options.focal_sigma_rel if options.intrinsics else None,
                           principal_sigma_px=options.principal_sigma_px if options.intrinsics else None,
                           centre_sigma_m=options.centre_sigma_m, pixel_sigma=options.pixel_sigma,
                           outlier_px=options.outlier_px)
    centres = np.stack([camera_centre(m) for m in w2c])
    res = bundle_adjust(w2c, intr[:, 0], intr[:, 2:4], X, oc, op, uv, centre_prior=centres, options=bundle)
    inl = np.bincount(oc[res.inlier], minlength=len(ids))
    updated, report, kept = {}, {}, {}
    for i, c in enumerate(ids):
        cam = cams[c]
        if inl[i] < options.min_observations:
            kept[c] = f"{inl[i]} observations left after the adjustment's outliers (needs {options.min_observations})"
            report[c] = {"observations": float(inl[i])}
            continue
        m = res.world_to_camera[i]
        mine = oc[res.inlier] == i
        q = {"refine_observations": float(inl[i]),
             "refine_rotation_moved_deg": float(rotation_angle_deg(m[:3, :3], w2c[i, :3, :3])),
             "refine_centre_moved_m": float(np.linalg.norm(camera_centre(m) - centres[i])),
             "refine_rotation_sigma_deg": float(res.sigma.rotation_deg[i]),
             "refine_centre_sigma_m": float(res.sigma.centre_m[i]),
             "refine_reprojection_px": float(np.median(res.reprojection_px[res.inlier][mine]))}
        update = {"world_to_camera": matrix4(m)}
        if options.intrinsics:
            f = float(res.focal[i])
            q["refine_focal_moved_rel"] = float(f / intr[i, 0] - 1.0)
            # the principal point back from square pixels (cy is the fixed point of that scaling)
            cy = intr[i, 3] + (float(res.principal[i, 1]) - intr[i, 3]) / aspect[i]
            update["intrinsics"] = (f, f / aspect[i], float(res.principal[i, 0]), cy)
        q = {k: v for k, v in q.items() if math.isfinite(v)}
        updated[c] = cam.model_copy(update={**update, "quality": {**cam.quality, **q}})
        report[c] = {k.removeprefix("refine_"): v for k, v in q.items()}
    return updated, report, kept
