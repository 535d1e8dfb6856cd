"""Calibration benchmark: error against ground truth and run time on a synthetic capture.

    python bench/bench_calibration.py [--capture DIR] [--frames 24] [--out table.json]

Without ``--capture`` it renders the demo capture (``synthesize_capture(rig="demo_scene")``) into a
temporary folder first. Prints the error table of ``volcap_core.calibration.metrics`` for the
static cameras and for the tracking cameras with the priors ("priors"), without them ("free":
joint, per-frame focal and centre free) and frame by frame ("independent"), the number of 3D points
triangulated in >= 3 views on the actors with each, and every stage's run time.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from volcap_core.calibration.lidar import LidarScan  # noqa: E402
from volcap_core.calibration.inputs import split_cameras  # noqa: E402
from volcap_core.calibration.metrics import (calibration_table, count_multiview_points, distance_to_parts,  # noqa: E402
                                             load_ground_truth, static_errors, tracking_errors)
from volcap_core.calibration.photometric import PhotometricOptions, background_plate  # noqa: E402
from volcap_core.calibration.static import StaticCalibrationOptions, calibrate_static_cameras  # noqa: E402
from volcap_core.calibration.static_step import plate_frames, reference_frame  # noqa: E402
from volcap_core.calibration.tracking.calibrate import prepare_tracking, solve_tracking
from volcap_core.calibration.tracking.observe import build_static_reference
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.capture import CaptureFolder  # noqa: E402


def run(capture_dir: Path, point_frames: int = 3, variants=("priors", "free", "independent")) -> dict:
    times: dict[str, float] = {}
    cap = CaptureFolder.open(capture_dir)
    gt = load_ground_truth(capture_dir / "ground_truth")
    scan = LidarScan.from_ply_bytes(cap.lidar_path.read_bytes())
    T = cap.frame_count
    # the calibrate-static step's policy: its roles, reference frame and plate frames
    mid = reference_frame(T, StaticCalibrationOptions())
    statics, trackers = split_cameras(cap.name, cap.rig, cap.camera_ids)
    t = time.perf_counter()
    images = {c: cap.load(c, mid) for c in statics}
    idx = plate_frames(T, StaticCalibrationOptions())
    plates = {c: background_plate([cap.load(c, int(k)) for k in idx]) for c in statics}
    times["load_static_s"] = time.perf_counter() - t

    t = time.perf_counter()
    static = calibrate_static_cameras(images, cap.rig, scan, plates=plates)
    times["static_total_s"] = time.perf_counter() - t
    for k, v in static.stats["time_s"].items():
        times[f"static_{k}_s"] = v
    st_err = static_errors(static.K, static.world_to_camera, gt, mid)
    # the same with the (optional) photometric step and without the lidar, for comparison
    variants_static = {}
    for name, opts, sc in (("+ photometric refinement", StaticCalibrationOptions(
                                photometric=PhotometricOptions(max_points=20000, centre_sigma_m=0.03)), scan),
                           ("sfm, mounts only (no lidar)", StaticCalibrationOptions(photometric=None), None)):
        t = time.perf_counter()
        s2 = calibrate_static_cameras(images, cap.rig, sc, plates=plates, options=opts)
        e2 = static_errors(s2.K, s2.world_to_camera, gt, mid)
        variants_static[name] = {"rotation_deg_max": max(v["rotation_deg"] for v in e2.values()),
                                 "projection_px_mean": float(np.mean([v["projection_px"] for v in e2.values()])),
                                 "rotation_deg_mean": float(np.mean([v["rotation_deg"] for v in e2.values()])),
                                 "centre_frac_max": max(v["centre_frac"] for v in e2.values()),
                                 "seconds": time.perf_counter() - t}

    tr_err: dict = {}
    points: dict = {}
    if trackers:
        t = time.perf_counter()
        ref = build_static_reference({c: plates[c] for c in static.camera_ids}, static.K, static.world_to_camera,
                                     scan)
        frames = {c: [cap.load(c, k) for k in range(T)] for c in trackers}
        ppm = {c: cap.rig.camera(c).sensor.width_px / cap.rig.camera(c).sensor.width_mm for c in trackers}
        mounts = {c: np.asarray(cap.rig.camera(c).mount.position_m) for c in trackers}
        problem = prepare_tracking(frames, cap.encoder, ppm, mounts, ref)
        times["tracking_prepare_s"] = time.perf_counter() - t
        sols_by_variant = {}
        for v in variants:
            t = time.perf_counter()
            sols = solve_tracking(problem, replace(TrackingOptions(), mode=v))
            times[f"tracking_solve_{v}_s"] = time.perf_counter() - t
            sols_by_variant[v] = sols
            tr_err[v] = {c: tracking_errors(s.K, s.world_to_camera, gt, c) for c, s in sols.items()}
            tr_err[v] = {c: {**e, "reprojection_3d_px_median": sols[c].stats.get("reprojection_3d_px_median", np.nan)}
                         for c, e in tr_err[v].items()}
        # points in >= 3 views on the actors, at a few frames
        pf = np.unique(np.linspace(1, T - 2, point_frames).round().astype(int)) if T > 2 else [0]
        for v in ("priors", "free"):
            if v not in sols_by_variant:
                continue
            t = time.perf_counter()
            n = 0
            for k in pf:
                cams = {c: (static.K[c], static.world_to_camera[c]) for c in static.camera_ids}
                cams.update({c: (s.K[k], s.world_to_camera[k]) for c, s in sols_by_variant[v].items()})
                imgs = {c: cap.load(c, int(k)) for c in cams}
                parts = [p for a in gt.parts for p in a[int(k)]]
                X, _ = count_multiview_points(imgs, cams, keep=lambda P: distance_to_parts(P, parts) < 0.05)
                n += len(X)
            points[v] = n / len(pf)
            times[f"points_{v}_s"] = time.perf_counter() - t
    table = calibration_table(st_err, tr_err, {
        "static_variants": variants_static,
        "actor_points_3view_per_frame": points,
        "static_median_reprojection_px": static.stats["bundle"]["median_reprojection_px"],
        "static_guided": {k: static.stats["guided"][k] for k in ("tracks", "observations", "median_reprojection_px")}
        if "guided" in static.stats else None,
        "times_s": times, "frames": T, "static_cameras": len(statics), "tracking_cameras": len(trackers)})
    return table


def _fmt(table: dict) -> str:
    lines = []
    s = table["static"]
    lines.append(f"static cameras ({s['cameras']}): rotation mean {s['rotation_deg_mean']:.3f}° max "
                 f"{s['rotation_deg_max']:.3f}°; centre mean {100 * s['centre_frac_mean']:.2f}% max "
                 f"{100 * s['centre_frac_max']:.2f}% of stage; |focal| mean {s['focal_pct_mean_abs']:.2f}% "
                 f"max {s['focal_pct_max_abs']:.2f}%; projection of the stage volume mean {s['projection_px_mean']:.2f} px "
                 f"max {s['projection_px_max']:.2f} px; reprojection {table['static_median_reprojection_px']:.2f} px "
                 f"(SIFT tracks)")
    if table.get("static_guided"):
        g = table["static_guided"]
        lines.append(f"  guided tracks: {g['tracks']} tracks, {g['observations']} observations, reprojection "
                     f"{g['median_reprojection_px']:.3f} px")
    for k, v in table["static_variants"].items():
        lines.append(f"  {k}: rotation mean {v['rotation_deg_mean']:.3f}° max {v['rotation_deg_max']:.3f}°, "
                     f"centre max {100 * v['centre_frac_max']:.2f}%, projection {v['projection_px_mean']:.2f} px  "
                     f"({v['seconds']:.1f} s)")
    for variant, t in table["tracking"].items():
        lines.append(f"tracking [{variant}]: |focal| mean {t['focal_pct_mean_abs']:.2f}% max {t['focal_pct_max_abs']:.2f}%; "
                     f"rotation mean {t['rotation_deg_mean']:.3f}°; centre {100 * t['centre_frac_mean']:.2f}% of stage; "
                     f"pose jitter mean {t['pose_jitter_px_mean']:.2f} px max {t['pose_jitter_px_max']:.2f}; "
                     f"focal jitter mean {t['focal_jitter_px_mean']:.2f} px max {t['focal_jitter_px_max']:.2f}; "
                     f"actor-head projection {t['projection_px_mean']:.1f} px; "
                     f"reprojection(2D-3D inliers) {t['reprojection_3d_px_median']:.1f} px")
    if table["actor_points_3view_per_frame"]:
        lines.append("actor points in >=3 views per frame: " + ", ".join(
            f"{k} {v:.1f}" for k, v in table["actor_points_3view_per_frame"].items()))
    lines.append("targets: " + ", ".join(f"{k} {'met' if v else 'NOT met'}" for k, v in table["targets"].items()))
    lines.append("times: " + ", ".join(f"{k} {v:.1f}" for k, v in table["times_s"].items()))
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="volcap-bench-calib-") as tmp:
        cap = args.capture
        if cap is None:
            from volcap_core.synth.synthesize import synthesize_capture

            t = time.perf_counter()
            cap = Path(tmp) / "demo"
            synthesize_capture(cap, rig="demo_scene", frames=args.frames)
            print(f"rendered the demo capture ({args.frames} frames) in {time.perf_counter() - t:.1f} s")
        table = run(cap)
    print(_fmt(table))
    if args.out:
        args.out.write_text(json.dumps(table, indent=1, default=float))


if __name__ == "__main__":
    main()
