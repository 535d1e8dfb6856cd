"""Calibration error measures against ground truth (synthetic captures), as one table (a dict).

Measures (per camera, then mean / max over cameras):

- ``rotation_deg``: angle of ``R_est R_true^T``;
- ``centre_frac``: camera-centre error divided by the stage size (max of the stage's x and y extent),
  so 0.005 = 0.5 % of the stage (2 cm on the 4 m demo stage);
- ``focal_pct``: ``100 (f_est / f_true - 1)``;
- tracking cameras, frame to frame (t -> t+1), in pixels:
  ``pose_jitter_px`` = | (p_est(t+1) - p_est(t)) - (p_true(t+1) - p_true(t)) | for a point on the
  tracked actor (its head centre at t, held fixed): the motion the estimate invents or misses;
  ``focal_jitter_px`` = | dln f_est - dln f_true | x half the image diagonal: the spurious zoom
  motion at the image corner;
- ``projection_px``: mean distance between the projections by the estimated and the true camera of
  points where actors are (a grid over the stage, 0-2 m high; tracking cameras: the tracked actor's
  head): what the error does to a render. A principal-point error that a rotation compensates shows
  in ``rotation_deg`` but not here;
- ``reprojection_px``: median reprojection error of the fit (from the calibration stats);
- ``actor_points_3view``: 3D points triangulated in >= 3 views that lie on an actor
  (:func:`count_multiview_points`).

Targets on the demo capture (issue): static within 0.1° and 0.5 % of the stage; tracking focal within
1 % and jitter under 1 px.

Real footage has no ground truth: :func:`errors_against` measures a solve against a calibration the
studio trusts (``volcap calibrate --against``), beside the σ the solve states.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from volcap_core.calibration.features import SiftOptions, extract_sift, match_descriptors
from volcap_core.calibration.geometry import rotation_angle_deg, triangulate_points
from volcap_core.calibration.images import to_uint8_gray

TARGETS = {"static_rotation_deg": 0.1, "static_centre_frac": 0.005, "tracking_focal_pct": 1.0,
           "tracking_jitter_px": 1.0}


@dataclass
class GroundTruth:
    """Ground truth of a synthetic capture: per camera per take index (K [3, 3], world_to_camera
    [4, 4]); per actor per take index the head centre [3] and body parts (dicts of scene.json)."""

    cameras: dict[str, list[tuple[np.ndarray, np.ndarray]]]
    roles: dict[str, str]
    tracked_actor: dict[str, int]
    heads: list[np.ndarray]                  # per actor [T, 3]
    parts: list[list[list[dict]]]            # per actor, per frame, parts
    stage_size_m: tuple[float, float, float]
    sizes: dict[str, tuple[int, int]]

    @property
    def stage_scale_m(self) -> float:
        return float(max(self.stage_size_m[0], self.stage_size_m[1]))


def load_ground_truth(folder: str | Path) -> GroundTruth:
    """Read ``ground_truth/cameras.json`` and ``scene.json`` of a synthetic capture."""
    folder = Path(folder)
    return ground_truth_from_json(json.loads((folder / "cameras.json").read_text()),
                                  json.loads((folder / "scene.json").read_text()))


def ground_truth_from_json(cams: dict, scene: dict) -> GroundTruth:
    """The ground truth from the parsed ``cameras.json`` and ``scene.json`` of a synthetic capture."""
    out, roles, tracked, sizes = {}, {}, {}, {}
    for cid, c in cams["cameras"].items():
        frames = []
        for f in c["frames"]:
            K = np.array([[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1.0]])
            frames.append((K, np.asarray(f["world_to_camera"], np.float64)))
        out[cid] = frames
        roles[cid] = c["role"]
        sizes[cid] = (int(c["width"]), int(c["height"]))
        if c.get("tracking"):
            tracked[cid] = int(c["tracking"]["actor"])
    heads = [np.array([f["head_centre_m"] for f in a["frames"]]) for a in scene["actors"]]
    parts = [[f["parts"] for f in a["frames"]] for a in scene["actors"]]
    return GroundTruth(out, roles, tracked, heads, parts, tuple(scene["stage"]["size_m"]), sizes)


def _centre(w2c: np.ndarray) -> np.ndarray:
    return -w2c[..., :3, :3].swapaxes(-1, -2) @ w2c[..., :3, 3:4]


def stage_samples(stage_size_m, n: int = 9, height_m: float = 2.0) -> np.ndarray:
    """A grid of points [n*n*5, 3] over the stage floor area, 0..``height_m`` high (where actors are)."""
    sx, sy = stage_size_m[0], stage_size_m[1]
    x, y, z = np.meshgrid(np.linspace(-sx / 2, sx / 2, n), np.linspace(-sy / 2, sy / 2, n),
                          np.linspace(0.0, height_m, 5), indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], 1)


def projection_error_px(K, W, Kg, Wg, points: np.ndarray, size: tuple[int, int]) -> float:
    """Mean distance (px) between the projections of ``points`` [N, 3] by the estimated and the true
    camera, over the points inside the true image: what a wrong calibration does to a render. A
    principal-point error compensated by a rotation costs nothing here (it does in ``rotation_deg``)."""
    P = np.asarray(points, np.float64)
    pg = P @ Wg[:3, :3].T + Wg[:3, 3]
    pe = P @ W[:3, :3].T + W[:3, 3]
    ok = (pg[:, 2] > 0.1) & (pe[:, 2] > 0.1)
    ug = pg[ok, :2] / pg[ok, 2:] @ Kg[:2, :2].T + Kg[:2, 2]
    ue = pe[ok, :2] / pe[ok, 2:] @ K[:2, :2].T + K[:2, 2]
    inside = (ug[:, 0] >= 0) & (ug[:, 0] < size[0]) & (ug[:, 1] >= 0) & (ug[:, 1] < size[1])
    return float(np.linalg.norm(ue[inside] - ug[inside], axis=1).mean()) if inside.any() else float("nan")


def static_errors(K: Mapping[str, np.ndarray], world_to_camera: Mapping[str, np.ndarray], gt: GroundTruth,
                  frame: int) -> dict[str, dict[str, float]]:
    """Per static camera: rotation_deg, centre_m, centre_frac, focal_pct, projection_px (stage volume)."""
    out = {}
    samples = stage_samples(gt.stage_size_m)
    for cid in sorted(K):
        Kg, Wg = gt.cameras[cid][frame]
        ce = float(np.linalg.norm(_centre(world_to_camera[cid]) - _centre(Wg)))
        out[cid] = {"rotation_deg": float(rotation_angle_deg(world_to_camera[cid][:3, :3], Wg[:3, :3])),
                    "centre_m": ce, "centre_frac": ce / gt.stage_scale_m,
                    "focal_pct": float(100 * (K[cid][0, 0] / Kg[0, 0] - 1)),
                    "projection_px": projection_error_px(K[cid], world_to_camera[cid], Kg, Wg, samples,
                                                         gt.sizes[cid])}
    return out


def _project(K, W, X):
    p = W[:3, :3] @ X + W[:3, 3]
    return (K[:2, :2] @ (p[:2] / p[2])) + K[:2, 2]


def tracking_errors(K: np.ndarray, world_to_camera: np.ndarray, gt: GroundTruth, camera_id: str) -> dict:
    """One tracking camera over the take: ``K`` [T, 3, 3], ``world_to_camera`` [T, 4, 4]."""
    T = len(K)
    gts = gt.cameras[camera_id][:T]
    w, h = gt.sizes[camera_id]
    half_diag = 0.5 * float(np.hypot(w, h))
    actor = gt.tracked_actor.get(camera_id, 0)
    head = gt.heads[actor] if gt.heads else np.zeros((T, 3))
    fe = np.array([100 * (K[t, 0, 0] / gts[t][0][0, 0] - 1) for t in range(T)])
    re = np.array([rotation_angle_deg(world_to_camera[t, :3, :3], gts[t][1][:3, :3]) for t in range(T)])
    ce = np.array([np.linalg.norm(_centre(world_to_camera[t]) - _centre(gts[t][1])) for t in range(T)])
    pj, fj, pe = [], [], []
    for t in range(T):
        pe.append(float(np.linalg.norm(_project(K[t], world_to_camera[t], head[t])
                                       - _project(gts[t][0], gts[t][1], head[t]))))
    for t in range(T - 1):
        P = head[t]
        de = _project(K[t + 1], world_to_camera[t + 1], P) - _project(K[t], world_to_camera[t], P)
        dg = _project(gts[t + 1][0], gts[t + 1][1], P) - _project(gts[t][0], gts[t][1], P)
        pj.append(float(np.linalg.norm(de - dg)))
        dle = np.log(K[t + 1, 0, 0] / K[t, 0, 0])
        dlg = np.log(gts[t + 1][0][0, 0] / gts[t][0][0, 0])
        fj.append(abs(dle - dlg) * half_diag)
    pj = np.array(pj) if pj else np.zeros(1)
    fj = np.array(fj) if fj else np.zeros(1)
    return {"focal_pct_mean_abs": float(np.abs(fe).mean()), "focal_pct_max_abs": float(np.abs(fe).max()),
            "rotation_deg_mean": float(re.mean()), "rotation_deg_max": float(re.max()),
            "centre_frac_mean": float(ce.mean() / gt.stage_scale_m), "centre_m_mean": float(ce.mean()),
            "pose_jitter_px_mean": float(pj.mean()), "pose_jitter_px_max": float(pj.max()),
            "projection_px_mean": float(np.mean(pe)),
            "focal_jitter_px_mean": float(fj.mean()), "focal_jitter_px_max": float(fj.max())}


def calibration_table(static: Mapping[str, dict], tracking: Mapping[str, Mapping[str, dict]] | None = None,
                      extra: Mapping[str, float] | None = None) -> dict:
    """Summarise per-camera errors into the report table.

    ``static``: :func:`static_errors` output; ``tracking``: variant name (e.g. "priors", "free") ->
    camera id -> :func:`tracking_errors` output. Returns a nested dict with means / maxima and a
    ``targets`` section saying which targets are met.
    """
    table: dict = {"static": {}, "tracking": {}, "targets": {}}
    if static:
        r = np.array([v["rotation_deg"] for v in static.values()])
        c = np.array([v["centre_frac"] for v in static.values()])
        f = np.array([abs(v["focal_pct"]) for v in static.values()])
        pr = np.array([v.get("projection_px", np.nan) for v in static.values()])
        table["static"] = {"cameras": len(r), "rotation_deg_mean": float(r.mean()), "rotation_deg_max": float(r.max()),
                           "projection_px_mean": float(np.nanmean(pr)), "projection_px_max": float(np.nanmax(pr)),
                           "centre_frac_mean": float(c.mean()), "centre_frac_max": float(c.max()),
                           "focal_pct_mean_abs": float(f.mean()), "focal_pct_max_abs": float(f.max()),
                           "per_camera": {k: dict(v) for k, v in static.items()}}
        table["targets"]["static_rotation"] = bool(r.max() <= TARGETS["static_rotation_deg"])
        table["targets"]["static_centre"] = bool(c.max() <= TARGETS["static_centre_frac"])
    for variant, cams in (tracking or {}).items():
        if not cams:
            continue
        agg = {}
        for key in next(iter(cams.values())):
            vals = np.array([v[key] for v in cams.values()])
            agg[key] = float(vals.max() if key.endswith("_max") or key.endswith("max_abs") else vals.mean())
        agg["per_camera"] = {k: dict(v) for k, v in cams.items()}
        table["tracking"][variant] = agg
        if variant == "priors":
            table["targets"]["tracking_focal"] = bool(agg["focal_pct_max_abs"] <= TARGETS["tracking_focal_pct"])
            table["targets"]["tracking_jitter"] = bool(
                max(agg["pose_jitter_px_mean"], agg["focal_jitter_px_mean"]) <= TARGETS["tracking_jitter_px"])
    if extra:
        table.update({k: v for k, v in extra.items()})
    return table


# --------------------------------------------------------------------------- actor points

def distance_to_parts(points: np.ndarray, parts: list[dict]) -> np.ndarray:
    """Approximate distance (m) of points [N, 3] to an actor's parts (ellipsoids, capsules) [N]."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    best = np.full(len(P), np.inf)
    for p in parts:
        if p["kind"] == "capsule":
            a, b = np.asarray(p["a_m"]), np.asarray(p["b_m"])
            ab = b - a
            s = np.clip(((P - a) @ ab) / max(ab @ ab, 1e-12), 0, 1)
            d = np.linalg.norm(P - (a + s[:, None] * ab), axis=1) - p["radius_m"]
        else:
            R = np.asarray(p["rotation"])
            semi = np.asarray(p["semi_axes_m"])
            q = (P - np.asarray(p["centre_m"])) @ R / semi
            n = np.linalg.norm(q, axis=1)
            d = (n - 1) * semi.min()
        best = np.minimum(best, np.abs(d))
    return best


def count_multiview_points(images: Mapping[str, np.ndarray], cameras: Mapping[str, tuple[np.ndarray, np.ndarray]],
                           *, ratio: float = 0.8, epipolar_px: float = 2.0, reproj_px: float = 2.0,
                           min_views: int = 3, sift: SiftOptions = SiftOptions(num_octaves=6),
                           keep: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Multi-view points of one instant from calibrated cameras.

    SIFT in every view, ratio-test matches between every pair kept when within ``epipolar_px`` of
    the epipolar line the calibration predicts, tracks by union-find, DLT triangulation, then points
    whose every observation reprojects within ``reproj_px`` and that have >= ``min_views`` views.
    ``cameras``: id -> (K [3, 3], world_to_camera [4, 4]). ``keep``: optional filter on points
    (e.g. "on an actor"). Returns points [N, 3] and their view counts [N]. A better calibration
    finds more: wrong geometry rejects true matches.
    """
    ids = sorted(set(images) & set(cameras))
    feats = {c: extract_sift(to_uint8_gray(images[c]), sift) for c in ids}
    offs = {}
    n = 0
    for c in ids:
        offs[c] = n
        n += len(feats[c][0])
    parent = np.arange(n)

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    Ps = {c: cameras[c][0] @ cameras[c][1][:3] for c in ids}
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            m = match_descriptors(feats[a][1], feats[b][1], ratio=ratio, mutual=True)
            if len(m) == 0:
                continue
            ua = feats[a][0][m[:, 0], :2].astype(np.float64)
            ub = feats[b][0][m[:, 1], :2].astype(np.float64)
            Fm = _fundamental(cameras[a], cameras[b])
            d = _epipolar_distance(Fm, ua, ub)
            for qa, qb in m[d < epipolar_px]:
                ra, rb = find(offs[a] + qa), find(offs[b] + qb)
                if ra != rb:
                    parent[ra] = rb
    roots = np.array([find(x) for x in range(n)])
    cam_of = np.concatenate([np.full(len(feats[c][0]), k) for k, c in enumerate(ids)])
    xy = np.concatenate([feats[c][0][:, :2] for c in ids]).astype(np.float64)
    uniq, inv, counts = np.unique(roots, return_inverse=True, return_counts=True)
    multi = counts[inv] >= min_views
    # one observation per camera per track: drop tracks that hit a camera twice
    obs_p, obs_c, obs_xy = inv[multi], cam_of[multi], xy[multi]
    key = obs_p * len(ids) + obs_c
    _, kc = np.unique(key, return_counts=True)
    dup = np.unique(key[np.isin(key, np.unique(key)[kc > 1])] // len(ids))
    ok = ~np.isin(obs_p, dup)
    obs_p, obs_c, obs_xy = obs_p[ok], obs_c[ok], obs_xy[ok]
    if len(obs_p) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    pts_ids, obs_p = np.unique(obs_p, return_inverse=True)
    P = np.stack([Ps[c] for c in ids])
    X = triangulate_points(P, obs_p, obs_c, obs_xy, len(pts_ids))
    xh = np.einsum("mij,mj->mi", P[obs_c], np.c_[X[obs_p], np.ones(len(obs_p))])
    err = np.linalg.norm(xh[:, :2] / xh[:, 2:3] - obs_xy, axis=1)
    bad = np.zeros(len(pts_ids), bool)
    np.logical_or.at(bad, obs_p, ~(err < reproj_px) | (xh[:, 2] <= 0))
    views = np.bincount(obs_p, minlength=len(pts_ids))
    good = ~bad & (views >= min_views) & np.isfinite(X).all(1)
    X, views = X[good], views[good]
    if keep is not None and len(X):
        sel = keep(X)
        X, views = X[sel], views[sel]
    return X, views


def _fundamental(ca, cb) -> np.ndarray:
    Ka, Wa = ca
    Kb, Wb = cb
    Rab = Wb[:3, :3] @ Wa[:3, :3].T
    tab = Wb[:3, 3] - Rab @ Wa[:3, 3]
    tx = np.array([[0, -tab[2], tab[1]], [tab[2], 0, -tab[0]], [-tab[1], tab[0], 0]])
    return np.linalg.inv(Kb).T @ tx @ Rab @ np.linalg.inv(Ka)


def _epipolar_distance(F, ua, ub) -> np.ndarray:
    ha = np.c_[ua, np.ones(len(ua))]
    hb = np.c_[ub, np.ones(len(ub))]
    la = ha @ F.T                      # lines in b
    lb = hb @ F                        # lines in a
    num = np.abs(np.einsum("ij,ij->i", hb, la))
    return np.maximum(num / np.hypot(la[:, 0], la[:, 1]), num / np.hypot(lb[:, 0], lb[:, 1]))


# --------------------------------------------------------------------------- the calibration report


def calibration_report(calib, gt: GroundTruth, tracking: Mapping | None = None, scan=None,
                       points: Sequence[tuple[int, np.ndarray]] | None = None) -> dict:
    """The error table of a stored calibration against a synthetic capture's ground truth (JSON-ready:
    NaN/Inf become None).

    ``calib``: a :class:`~volcap_core.calibration.record.Calibration`; ``tracking``: its decoded
    tracking frames (``record.decode_tracking_frames``), needed when it has tracking cameras;
    ``scan``: the ground truth's lidar (:class:`~volcap_core.calibration.lidar.LidarScan`, the true
    static surface) and ``points``: (frame, xyz [N, 3]) of dense points, to score their distance to
    the true surfaces per frame.
    """
    from volcap_core.calibration.record import camera_at

    f0 = calib.reference_frame
    K, W = {}, {}
    for c in calib.static_ids:
        K[c], W[c], _, _ = camera_at(calib, c, f0)
    st_err = static_errors(K, W, gt, f0)
    tr_err = {}
    for c in calib.tracking_ids:
        Ks = np.zeros((calib.frame_count, 3, 3))
        fx, fy, cx, cy = tracking[c].intrinsics.T
        Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2], Ks[:, 2, 2] = fx, fy, cx, cy, 1.0
        tr_err[c] = tracking_errors(Ks, tracking[c].world_to_camera, gt, c)
    extra: dict = {"static_median_reprojection_px": calib.stats.get("static_median_reprojection_px"),
                   "frames": calib.frame_count, "reference_frame": f0,
                   "static_cameras": len(calib.static_ids), "tracking_cameras": len(calib.tracking_ids)}
    if points is not None:
        extra["points"] = (point_errors(points, gt, scan) if scan is not None
                           else {"per_frame": {}, "note": "ground truth has no lidar.ply"})
    return _finite_json(calibration_table(st_err, {"priors": tr_err} if tr_err else None, extra))


def errors_against(calib, reference) -> dict[str, dict[str, float | None]]:
    """Each static camera of ``calib`` that ``reference`` also has, against it: how far the solve
    moved from a calibration the studio trusts (an imported Qualisys/COLMAP/OpenCV record, or an
    earlier solve), beside what the solve says of itself. Both
    :class:`~volcap_core.calibration.record.Calibration` records, in one world (a capture without a
    scan whose mounts are the reference's poses; any other world needs aligning first).

    Per camera (JSON-ready): ``rotation_deg`` (angle of ``R R_ref^T``), ``rotation_sigma_deg`` (the
    stated σ, the camera's ``quality``; None when the solve states none), ``rotation_sigmas`` (error
    over σ), ``centre_m`` and ``centre_sigma_m``, ``focal_pct`` (``100 (fx / fx_ref - 1)``) and
    ``focal_sigma_pct`` (the stated focal σ, None when held or not stated),
    ``principal_px`` (distance between the principal points). The reference's frames must be the
    calibrated frames' size (``importers.fit_calibration`` makes them so)."""
    out: dict[str, dict[str, float | None]] = {}
    ref_ids = set(reference.static_ids)
    for cid in calib.static_ids:
        if cid not in ref_ids:
            continue
        c, r = calib.camera(cid), reference.camera(cid)
        if (c.width, c.height) != (r.width, r.height):
            raise ValueError(f"camera {cid}: calibrated at {c.width}x{c.height}, the reference describes "
                             f"{r.width}x{r.height} frames (fit it to the capture first)")
        W, Wr = np.asarray(c.world_to_camera, np.float64), np.asarray(r.world_to_camera, np.float64)
        rot = float(rotation_angle_deg(W[:3, :3], Wr[:3, :3]))
        sigma = c.quality.get("rotation_sigma_deg")
        out[cid] = {"rotation_deg": rot, "rotation_sigma_deg": sigma,
                    "rotation_sigmas": rot / sigma if sigma else None,
                    "centre_m": float(np.linalg.norm(_centre(W) - _centre(Wr))),
                    "centre_sigma_m": c.quality.get("centre_sigma_m"),
                    "focal_pct": 100.0 * (c.intrinsics[0] / r.intrinsics[0] - 1.0),
                    "focal_sigma_pct": c.quality.get("focal_sigma_pct"),
                    "principal_px": float(np.hypot(c.intrinsics[2] - r.intrinsics[2],
                                                   c.intrinsics[3] - r.intrinsics[3]))}
    return out


def point_errors(points: Sequence[tuple[int, np.ndarray]], gt: GroundTruth, scan) -> dict:
    """Per frame: points, median / 90th-percentile distance (m) to the true surface (the scan or an
    actor), points within 3 cm of an actor."""
    per = {}
    for frame, xyz in points:
        if not len(xyz):
            per[str(frame)] = {"points": 0}
            continue
        parts = [p for a in gt.parts for p in a[frame]] if gt.parts else []
        actor = distance_to_parts(xyz, parts) if parts else np.full(len(xyz), np.inf)
        d = np.minimum(scan.surface_distance(xyz, 0.3), actor)
        d = d[np.isfinite(d)]
        per[str(frame)] = {"points": int(len(xyz)),
                           "median_distance_m": float(np.median(d)) if len(d) else None,
                           "p90_distance_m": float(np.percentile(d, 90)) if len(d) else None,
                           "actor_points_3cm": int((actor < 0.03).sum())}
    vals = [v for v in per.values() if v.get("median_distance_m") is not None]
    return {"per_frame": per,
            "points_mean": float(np.mean([v["points"] for v in per.values()])) if per else 0.0,
            "median_distance_m": float(np.median([v["median_distance_m"] for v in vals])) if vals else None}


def _finite_json(x):
    """NaN/Inf (no JSON form) become None; numpy scalars plain numbers."""
    if isinstance(x, dict):
        return {str(k): _finite_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_json(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(float(x)) else None
    return x
