"""The metric scale of a capture without a lidar scan from distances a studio measured between
named scene points: two marks on the floor, the ends of a scale bar, two corners of a set piece.

A studio gives each point by its pixel position in two or more static cameras (any frame: the
cameras do not move) and the tape distance between two of them (:class:`KnownPoints`, the JSON of
``volcap calibrate --known-points``)::

    {"points": {"A": {"S001": [412.3, 608.0], "S004": [1210.7, 655.2]},
                "B": {"S001": [980.1, 611.4], "S004": [1688.0, 590.9], "S005": [300.2, 700.0]}},
     "distance_m": 1.5}

Each point is triangulated with the calibrated cameras (:func:`triangulate_marks`: the pixels
undistorted through a camera's lens, a linear triangulation refined by Gauss-Newton, its
covariance for a mark error of ``pixel_sigma_px``), then the calibration is scaled about the
mounts' centroid so the triangulated distance comes out as measured
(:func:`scale_to_known_points`; several distances: the least-squares scale, each one's residual
reported). With a lidar scan the scan gives the scale and the distances are only checked.

Refused, naming the point and the camera: a point marked in fewer than two calibrated static cameras
(a camera left out of the calibration does not count), a camera that is not a static camera of the
capture, a pixel outside the image, a point behind a camera, marks that disagree (a reprojection
above ``max_reprojection_px``), rays that meet at less than ``min_angle_deg``, and a distance the
marks determine to worse than ``max_distance_sigma`` (relative, at ``pixel_sigma_px``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Any, Mapping, Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from volcap_core.calibration.errors import CalibrationInputError, KnownPointsError
from volcap_core.calibration.geometry import Similarity, camera_centre

log = logging.getLogger("volcap.calibrate")


class KnownPoints(BaseModel):
    """Named scene points marked in static cameras and measured distances between them.

    ``points``: name -> {static camera id: [u, v]} in OpenCV pixels of the camera's own footage (the
    centre of the top-left pixel is (0, 0); a distorted camera's raw frames as ingested), at least two
    cameras per point. Either ``distance_m`` (exactly two points) or ``distances``
    ([[point, point, metres], ...]; the scale is their least-squares fit).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    points: dict[str, dict[str, tuple[float, float]]]
    distance_m: float | None = Field(default=None, gt=0)
    distances: tuple[tuple[str, str, float], ...] = ()
    #: how well a mark is placed (px, 1σ): the distance's uncertainty is computed for it
    pixel_sigma_px: float = Field(default=1.0, gt=0)
    #: a point whose marks reproject further than this from the triangulated point is refused (px)
    max_reprojection_px: float = Field(default=5.0, gt=0)
    #: a point whose widest pair of rays meets at less than this is refused (degrees)
    min_angle_deg: float = Field(default=2.0, ge=0)
    #: a distance the marks determine to worse than this fraction (1σ at ``pixel_sigma_px``) is refused
    max_distance_sigma: float = Field(default=0.05, gt=0)

    @model_validator(mode="after")
    def _check(self) -> "KnownPoints":
        if not self.points:
            raise ValueError("no points given")
        for name, marks in self.points.items():
            if len(marks) < 2:
                raise ValueError(f"point {name} is marked in {len(marks)} camera(s) "
                                 f"({', '.join(marks) or 'none'}); it needs at least two")
            for cam, (u, v) in marks.items():
                if not (math.isfinite(u) and math.isfinite(v)):
                    raise ValueError(f"point {name} in camera {cam}: pixel ({u}, {v}) is not finite")
        if (self.distance_m is None) == (not self.distances):
            raise ValueError("give either distance_m (between exactly two points) or distances "
                             "([[point, point, metres], ...]), not both or neither")
        if self.distance_m is not None and len(self.points) != 2:
            raise ValueError(f"distance_m is the distance between exactly two points, got {len(self.points)} "
                             f"({', '.join(self.points)}): give distances [[point, point, metres], ...] instead")
        for a, b, d in self.distances:
            unknown = [p for p in (a, b) if p not in self.points]
            if unknown:
                raise ValueError(f"distance {a}-{b} names point(s) {', '.join(unknown)} that are not in points "
                                 f"({', '.join(self.points)})")
            if a == b or not d > 0:
                raise ValueError(f"distance {a}-{b}: needs two different points and a positive distance, got {d}")
        return self

    def pairs(self) -> list[tuple[str, str, float]]:
        """The measured distances as (point, point, metres)."""
        if self.distance_m is not None:
            a, b = self.points
            return [(a, b, float(self.distance_m))]
        return [(a, b, float(d)) for a, b, d in self.distances]

    def cameras(self) -> list[str]:
        return sorted({c for marks in self.points.values() for c in marks})

    @classmethod
    def parse(cls, doc: Any, source: str = "known points") -> "KnownPoints":
        """A :class:`KnownPoints` from its JSON (a dict, or an instance), a :class:`KnownPointsError`
        naming ``source`` and the field otherwise."""
        if isinstance(doc, cls):
            return doc
        try:
            return cls.model_validate(doc)
        except ValidationError as exc:
            err = exc.errors()[0]
            loc = ".".join(str(x) for x in err["loc"])
            msg = err["msg"].removeprefix("Value error, ")
            raise KnownPointsError(f"{source}: {loc + ': ' if loc else ''}{msg}") from None


@dataclass
class Mark:
    """A triangulated known point."""

    name: str
    position: np.ndarray                 # [3] stage frame, metres
    cameras: list[str]
    reprojection_px: dict[str, float]    # per camera
    covariance: np.ndarray               # [3, 3] m², for a mark error of ``pixel_sigma_px``
    angle_deg: float                     # the widest angle between two of its rays
    depth_m: dict[str, float]            # along each camera's axis


def check_known_points(known: KnownPoints, static_ids: Sequence[str], tracking_ids: Sequence[str] = ()) -> None:
    """Refuse marks in cameras that are not static cameras of the capture (before calibrating)."""
    for name, marks in known.points.items():
        for cam in marks:
            if cam in tracking_ids:
                raise KnownPointsError(f"point {name} is marked in camera {cam}, a tracking camera: mark known "
                                       "points in static cameras (they do not move)")
            if cam not in static_ids:
                raise KnownPointsError(f"point {name} is marked in camera {cam}, not a static camera of the "
                                       f"capture ({', '.join(static_ids)})")


def _rectified_pixels(xy: np.ndarray, K: np.ndarray, raw) -> np.ndarray:
    """Pixels of a camera's own footage -> pixels of the pinhole ``K`` it was calibrated as (the
    same pixels when it has no distortion)."""
    if raw is None:
        return xy
    n = np.c_[(xy[:, 0] - raw.cx) / raw.fx, (xy[:, 1] - raw.cy) / raw.fy]
    if not raw.distortion.is_none:
        n = raw.distortion.undistort(n)
    return n @ np.asarray(K, np.float64)[:2, :2].T + np.asarray(K, np.float64)[:2, 2]


def _project(K: np.ndarray, W: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Pixel [2], depth and d(pixel)/dX [2, 3] of world point X."""
    Xc = W[:3, :3] @ X + W[:3, 3]
    z = Xc[2]
    fx, fy = K[0, 0], K[1, 1]
    uv = np.array([fx * Xc[0] / z + K[0, 2], fy * Xc[1] / z + K[1, 2]])
    d = np.array([[fx / z, 0, -fx * Xc[0] / z ** 2], [0, fy / z, -fy * Xc[1] / z ** 2]])
    return uv, float(z), d @ W[:3, :3]


def triangulate_marks(known: KnownPoints, K: Mapping[str, np.ndarray], world_to_camera: Mapping[str, np.ndarray],
                      size: Mapping[str, tuple[int, int]], raw_intrinsics: Mapping[str, Any] | None = None,
                      left_out: Mapping[str, str] | None = None) -> dict[str, Mark]:
    """Each known point triangulated from its marks in the calibrated cameras (``K`` the pinhole
    each was calibrated as, ``raw_intrinsics`` the own-footage intrinsics and distortion of a
    distorted camera). ``left_out``: cameras of the capture left out of the calibration (id ->
    why): their marks do not count. Raises :class:`KnownPointsError` naming the point and camera."""
    raw_intrinsics = raw_intrinsics or {}
    left_out = left_out or {}
    out: dict[str, Mark] = {}
    for name, marks in known.points.items():
        cams = [c for c in marks if c in world_to_camera]
        dropped = [c for c in marks if c not in world_to_camera]
        for c in dropped:
            if c not in left_out:
                raise KnownPointsError(f"point {name} is marked in camera {c}, which is not a calibrated static "
                                       f"camera ({', '.join(sorted(world_to_camera))})")
        if len(cams) < 2:
            why = "; ".join(f"{c} was left out of the calibration ({left_out[c]})" for c in dropped)
            raise KnownPointsError(f"point {name} is seen in {len(cams)} calibrated camera(s) "
                                   f"({', '.join(cams) or 'none'}): it needs at least two; {why}")
        pix = {}
        for c in cams:
            u, v = marks[c]
            w, h = size[c]
            if not (-0.5 <= u <= w - 0.5 and -0.5 <= v <= h - 0.5):
                raise KnownPointsError(f"point {name} in camera {c}: pixel ({u:g}, {v:g}) is outside its {w}x{h} "
                                       "image (OpenCV pixels: the top-left pixel's centre is (0, 0))")
            pix[c] = _rectified_pixels(np.array([[u, v]], np.float64), K[c], raw_intrinsics.get(c))[0]
        Ks = {c: np.asarray(K[c], np.float64) for c in cams}
        Ws = {c: np.asarray(world_to_camera[c], np.float64) for c in cams}
        # linear (DLT) start, then Gauss-Newton on the reprojection error
        A = []
        for c in cams:
            P = Ks[c] @ Ws[c][:3]
            A += [pix[c][0] * P[2] - P[0], pix[c][1] * P[2] - P[1]]
        A = np.array(A)
        A /= np.linalg.norm(A, axis=1, keepdims=True)
        h = np.linalg.svd(A)[2][-1]
        if abs(h[3]) < 1e-12:
            raise KnownPointsError(f"point {name}: its rays from {', '.join(cams)} do not meet (parallel): the "
                                   "marks do not show one point, or the cameras see it from the same direction")
        X = h[:3] / h[3]
        for _ in range(10):
            J, r = [], []
            for c in cams:
                uv, z, d = _project(Ks[c], Ws[c], X)
                J.append(d)
                r.append(pix[c] - uv)
            J, r = np.concatenate(J), np.concatenate(r)
            step = np.linalg.lstsq(J, r, rcond=None)[0]
            X = X + step
            if np.linalg.norm(step) < 1e-10:
                break
        depth = {c: _project(Ks[c], Ws[c], X)[1] for c in cams}
        behind = [c for c in cams if not depth[c] > 0]
        if behind:
            raise KnownPointsError(f"point {name} triangulates behind camera(s) {', '.join(behind)} (depth "
                                   f"{', '.join(f'{depth[c]:.2f} m' for c in behind)}): its marks in "
                                   f"{', '.join(cams)} do not show one point; check the pixels")
        reproj = {c: float(np.linalg.norm(_project(Ks[c], Ws[c], X)[0] - pix[c])) for c in cams}
        worst = max(reproj, key=reproj.get)
        if reproj[worst] > known.max_reprojection_px:
            where = (f"camera {worst}" if len(cams) > 2 else f"cameras {' and '.join(cams)}")
            raise KnownPointsError(f"point {name}: its marks disagree: the triangulated point reprojects "
                                   f"{reproj[worst]:.1f} px from its mark in {worst} (at most "
                                   f"{known.max_reprojection_px:g} px): check its pixels in {where}")
        rays = [(X - camera_centre(Ws[c])) / np.linalg.norm(X - camera_centre(Ws[c])) for c in cams]
        angle = max(math.degrees(math.acos(float(np.clip(rays[i] @ rays[j], -1, 1))))
                    for i in range(len(cams)) for j in range(i + 1, len(cams)))
        if angle < known.min_angle_deg:
            raise KnownPointsError(f"point {name} is ill-conditioned: its rays from {', '.join(cams)} meet at "
                                   f"{angle:.2f}° (needs at least {known.min_angle_deg:g}°): mark it in cameras "
                                   "that see it from further apart")
        J = np.concatenate([_project(Ks[c], Ws[c], X)[2] for c in cams])
        H = J.T @ J
        cov = (known.pixel_sigma_px ** 2 * np.linalg.inv(H) if np.linalg.cond(H) < 1e14
               else np.full((3, 3), np.inf))
        out[name] = Mark(name, X, cams, reproj, cov, angle, depth)
    return out


def measure_distances(known: KnownPoints, marks: Mapping[str, Mark]) -> list[dict]:
    """Each measured distance beside the triangulated one and its 1σ (metres, at ``pixel_sigma_px``);
    refuses a distance determined to worse than ``known.max_distance_sigma``."""
    rows = []
    for a, b, d in known.pairs():
        v = marks[b].position - marks[a].position
        now = float(np.linalg.norm(v))
        if not now > 1e-9:
            raise KnownPointsError(f"points {a} and {b} triangulate to the same place: check their marks")
        u = v / now
        sigma = float(math.sqrt(max(u @ (marks[a].covariance + marks[b].covariance) @ u, 0.0)))
        if not sigma <= known.max_distance_sigma * now:
            raise KnownPointsError(
                f"distance {a}-{b} is ill-conditioned: the marks give {now:.3f} m ± {sigma:.3f} m "
                f"({100 * sigma / now:.1f} %, for marks placed to {known.pixel_sigma_px:g} px; at most "
                f"{100 * known.max_distance_sigma:g} %): mark the points in cameras that see them from further "
                "apart, or measure a longer distance")
        rows.append({"a": a, "b": b, "measured_m": d, "triangulated_m": now, "sigma_m": sigma})
    return rows


def scale_to_known_points(static, known: KnownPoints, mounts: Mapping[str, np.ndarray], *, has_scan: bool,
                          left_out: Mapping[str, str] | None = None, mount_tolerance_m: float = 0.10):
    """``static`` (a :class:`~volcap_core.calibration.static.StaticCalibration` in the stage frame)
    scaled so the known distances come out as measured: a scaling by the least-squares factor about
    the mounts' centroid (the mounts still orient and place the stage, as with a known distance
    between cameras). With a scan (``has_scan``) nothing moves: the distances are only checked.

    Returns a new StaticCalibration whose ``stats["frame"]`` holds ``scale_source`` 2 (known points),
    ``known_points_scale``, ``known_points_distance_m`` / ``_triangulated_m`` / ``_sigma_m`` (the
    first distance), ``known_points_residual_max_m`` (after scaling, over all distances; with a
    scan: the error) and, without a scan, the mounts' residual recomputed (``mount_residual_*``);
    ``stats["known_points"]`` the per-point and per-distance details."""
    left = dict(left_out if left_out is not None else getattr(static, "reasons", {}) or {})
    marks = triangulate_marks(known, static.K, static.world_to_camera, static.size,
                              getattr(static, "raw_intrinsics", None), left)
    rows = measure_distances(known, marks)
    D = np.array([r["triangulated_m"] for r in rows])
    d = np.array([r["measured_m"] for r in rows])
    k = float(d @ D / (D @ D))
    ids = list(static.camera_ids)
    stats = dict(static.stats)
    frame = dict(stats.get("frame", {}))
    details: dict = {"points": {m.name: {"cameras": len(m.cameras), "angle_deg": m.angle_deg,
                                         "reprojection_max_px": max(m.reprojection_px.values()),
                                         "sigma_m": float(math.sqrt(max(np.trace(m.covariance), 0.0)))}
                                for m in marks.values()},
                     "distances": {f"{r['a']}-{r['b']}": dict(r) for r in rows}}
    for r in details["distances"].values():
        r.pop("a"), r.pop("b")
    first = rows[0]
    common = {"known_points_distance_m": first["measured_m"], "known_points_triangulated_m": first["triangulated_m"],
              "known_points_sigma_m": first["sigma_m"], "known_points_distances": float(len(rows)),
              "known_points_reprojection_max_px": max(max(m.reprojection_px.values()) for m in marks.values())}
    if has_scan:
        frame.update(common)
        frame["known_points_residual_max_m"] = float(np.max(np.abs(D - d)))
        stats["frame"], stats["known_points"] = frame, details
        return replace(static, stats=stats)
    c0 = np.mean([np.asarray(mounts[c], np.float64) for c in ids], axis=0)
    T = Similarity(k, np.eye(3), c0 - k * c0)
    w2c = {c: T.apply_pose(static.world_to_camera[c]) for c in ids}
    model = static.model
    if model is not None:
        model = replace(model, points=T.apply(model.points),
                        world_to_camera={c: T.apply_pose(v) for c, v in model.world_to_camera.items()})
    r = np.array([float(np.linalg.norm(camera_centre(w2c[c]) - np.asarray(mounts[c], np.float64))) for c in ids])
    for row in details["distances"].values():
        row["after_m"] = k * row["triangulated_m"]
    frame.update(common)
    frame.update({"scale_source": 2.0, "known_points_scale": k, "scale": float(frame.get("scale", 1.0)) * k,
                  "known_points_residual_max_m": float(np.max(np.abs(k * D - d))),
                  "mount_residual_rms_m": float(np.sqrt(np.mean(r ** 2))),
                  "mount_residual_median_m": float(np.median(r)), "mount_residual_max_m": float(r.max()),
                  "mount_residual": {c: float(v) for c, v in zip(ids, r)}})
    far = [f"{c} {v:.3f} m" for c, v in zip(ids, r) if v > mount_tolerance_m]
    frame["mount_outliers"] = len(far)
    if far:
        log.warning("no lidar scan: static camera(s) end further than %.2f m from their mounts after scaling to the "
                    "known points: %s (check the rig's mount positions and the measured distance)",
                    mount_tolerance_m, ", ".join(far))
    stats["frame"], stats["known_points"] = frame, details
    # scene depths are metres too: calibrate_static_step measures them after this scaling, but a
    # calibration read back from its record (static_from_record) carries them
    return replace(static, world_to_camera=w2c, model=model, stats=stats,
                   scene_depth={c: tuple(k * v for v in d) for c, d in static.scene_depth.items()})


def check_for_capture(cap_name: str, known: KnownPoints, static_ids: Sequence[str], tracking_ids: Sequence[str],
                      known_distance: tuple | None = None) -> None:
    """Before calibrating a capture: :func:`check_known_points`, and not both known points and a
    known distance between cameras; a
    :class:`~volcap_core.calibration.errors.CalibrationInputError` naming the capture otherwise."""
    if known_distance is not None:
        raise CalibrationInputError(f"capture {cap_name}: give either a known distance between two cameras or "
                                    "known points, not both")
    try:
        check_known_points(known, static_ids, tracking_ids)
    except KnownPointsError as exc:
        raise CalibrationInputError(f"capture {cap_name}: known points: {exc}") from exc


def apply_to_static_step(cap_name: str, rig, static, known: KnownPoints, *, has_scan: bool,
                         mount_tolerance_m: float = 0.10):
    """:func:`scale_to_known_points` for a capture's static step: the mounts from the rig, a
    :class:`~volcap_core.calibration.errors.CalibrationInputError` naming the capture on bad input."""
    mounts = {c: np.asarray(rig.camera(c).mount.position_m, np.float64) for c in static.camera_ids}
    try:
        return scale_to_known_points(static, known, mounts, has_scan=has_scan, mount_tolerance_m=mount_tolerance_m)
    except KnownPointsError as exc:
        raise CalibrationInputError(f"capture {cap_name}: known points: {exc}") from exc
