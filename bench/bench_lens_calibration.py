"""Lens calibration on real photographs: OpenCV's stereo checkerboard samples -> measured
intrinsics and distortion in a rig -> our distortion model against OpenCV's.

    python bench/bench_lens_calibration.py --data DIR [--out DIR] [--json]

``DIR`` holds OpenCV's sample images ``left01.jpg`` ... ``left14.jpg`` and ``right01.jpg`` ...
``right14.jpg`` (640x480 JPEG, a 9x6-corner checkerboard seen by two cameras of a stereo pair; no
``*10.jpg`` in the set: 13 pairs). They are not in this repository and the bench downloads nothing.
They ship in Debian's ``opencv-doc`` package (OpenCV 4.6.0, Apache-2.0 AND BSD-3-Clause, see the
package's ``/usr/share/doc/opencv-doc/copyright``), in ``examples/data/``:

    apt-get download opencv-doc        # ~96 MB .deb
    dpkg-deb -x opencv-doc_*_all.deb /tmp/opencv-doc
    python bench/bench_lens_calibration.py --data /tmp/opencv-doc/usr/share/doc/opencv-doc/examples/data

(the same files are ``samples/data/left*.jpg`` / ``right*.jpg`` in OpenCV's source tree).

What it does, per camera (left, right):

1. chessboard corners (``cv2.findChessboardCorners`` + ``cornerSubPix``) of every view;
2. ``cv2.calibrateCamera`` in the rig's ``OPENCV`` model (k1, k2, p1, p2; ``CALIB_FIX_K3``) and in
   OpenCV's default 5-coefficient model (k3 too, which our rigs express as ``FULL_OPENCV``);
   reprojection RMS over all views, and a leave-one-view-out figure (each view's corners predicted
   by a calibration from the other views: the error a lens calibration makes on a new image);
3. the calibration written as ``MeasuredIntrinsics`` of a two-camera rig (``hardware.rig.Rig``,
   mounts from ``cv2.stereoCalibrate``'s baseline), loaded back through ``Intrinsics.from_rig``;
4. our model against OpenCV's on the real corners: ``Intrinsics.project`` vs ``cv2.projectPoints``
   (the board corners at the calibrated board poses), ``Distortion.undistort_pixels`` vs
   ``cv2.undistortPoints`` with a 100-iteration criteria (converged) and vs plain
   ``cv2.undistortPoints`` (5 iterations, its
   default), and the round trip distort(undistort(p)) - p;
5. straightness: each row and column of 9 / 6 corners is a straight line in the world; the RMS
   distance of the corners to their fitted line, on the raw images and after our undistortion
   (a measure of the lens model on real data that needs no ground truth).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hardware.rig import Rig  # noqa: E402
from volcap_core.calibration.distortion import Distortion  # noqa: E402
from volcap_core.calibration.sfm import Intrinsics  # noqa: E402

PATTERN = (9, 6)            # inner corners of OpenCV's sample board
SQUARE = 1.0                # board units (the samples' square size is not published; scale-free here)
SENSOR_WIDTH_MM = 4.8       # a nominal 1/3" sensor for the rig file: only the mm <-> px conversion uses it
CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-12)


def find_corners(data: Path, side: str) -> tuple[dict[int, np.ndarray], tuple[int, int]]:
    """View number -> corners [54, 2] (OpenCV px) of every ``<side>NN.jpg`` where the board is found."""
    out, size = {}, None
    for path in sorted(data.glob(f"{side}[0-9][0-9].jpg")):
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        size = (gray.shape[1], gray.shape[0])
        ok, c = cv2.findChessboardCorners(gray, PATTERN,
                                          flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            continue
        c = cv2.cornerSubPix(gray, c, (11, 11), (-1, -1), CRITERIA)
        out[int(path.stem[len(side):])] = c.reshape(-1, 2).astype(np.float64)
    if size is None:
        raise SystemExit(f"{data}: no {side}NN.jpg images (see this script's docstring for where to get them)")
    return out, size


def board() -> np.ndarray:
    g = np.zeros((PATTERN[0] * PATTERN[1], 3), np.float32)
    g[:, :2] = np.mgrid[0:PATTERN[0], 0:PATTERN[1]].T.reshape(-1, 2) * SQUARE
    return g


def calibrate(corners: dict[int, np.ndarray], size, flags: int):
    obj = [board()] * len(corners)
    img = [c.astype(np.float32).reshape(-1, 1, 2) for c in corners.values()]
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None, flags=flags, criteria=CRITERIA)
    return float(rms), K, dist.ravel(), rvecs, tvecs


def leave_one_out(corners: dict[int, np.ndarray], size, flags: int) -> float:
    """RMS over views of the corners of each view predicted by a calibration without it (the
    view's board pose from solvePnP with the held-out intrinsics: only the lens is tested)."""
    errs = []
    keys = list(corners)
    for k in keys:
        rest = {j: corners[j] for j in keys if j != k}
        _, K, dist, _, _ = calibrate(rest, size, flags)
        ok, rv, tv = cv2.solvePnP(board(), corners[k].astype(np.float32), K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
        proj, _ = cv2.projectPoints(board(), rv, tv, K, dist)
        errs.append(np.sum((proj.reshape(-1, 2) - corners[k]) ** 2, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(errs))))


def line_rms(points: np.ndarray) -> float:
    """RMS distance of 2D points to their total-least-squares line."""
    c = points - points.mean(0)
    return float(np.sqrt(np.linalg.svd(c, compute_uv=False)[-1] ** 2 / len(points)))


def straightness(corners: dict[int, np.ndarray]) -> float:
    """RMS over every board row (9 corners) and column (6) of every view of the distance to its line."""
    sq = []
    for c in corners.values():
        g = c.reshape(PATTERN[1], PATTERN[0], 2)
        for r in range(PATTERN[1]):
            sq.append(line_rms(g[r]) ** 2)
        for q in range(PATTERN[0]):
            sq.append(line_rms(g[:, q]) ** 2)
    return float(np.sqrt(np.mean(sq)))


def measure_side(data: Path, side: str) -> dict:
    corners, size = find_corners(data, side)
    rms5, K5, d5, _, _ = calibrate(corners, size, 0)
    flags = cv2.CALIB_FIX_K3
    rms4, K, dist, rvecs, tvecs = calibrate(corners, size, flags)
    loo4 = leave_one_out(corners, size, flags)
    loo5 = leave_one_out(corners, size, 0)
    dist4 = Distortion("OPENCV", tuple(float(v) for v in dist[:4]))
    intr = Intrinsics.measured(K[0, 0], K[1, 1], K[0, 2], K[1, 2], size[0], size[1], dist4)
    # 4. our model against OpenCV's on the real corners
    proj_diff, undist_iter, undist_plain, round_trip, reproj = [], [], [], [], []
    for (k, c), rv, tv in zip(corners.items(), rvecs, tvecs):
        R, _ = cv2.Rodrigues(rv)
        X = board().astype(np.float64) @ R.T + tv.ravel()
        ours = intr.project(X)
        cvp, _ = cv2.projectPoints(board().astype(np.float64), rv, tv, K, dist)
        proj_diff.append(np.abs(ours - cvp.reshape(-1, 2)).max())
        reproj.append(np.sum((ours - c) ** 2, axis=1))
        und = dist4.undistort_pixels(K, c)
        it = cv2.undistortPoints(c.reshape(-1, 1, 2), K, dist, None, None, K,
                                 (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)).reshape(-1, 2)
        plain = cv2.undistortPoints(c.reshape(-1, 1, 2), K, dist, None, K).reshape(-1, 2)
        undist_iter.append(np.abs(und - it).max())
        undist_plain.append(np.abs(und - plain).max())
        round_trip.append(np.abs(dist4.distort_pixels(K, und) - c).max())
    und_corners = {k: dist4.undistort_pixels(K, c) for k, c in corners.items()}
    # the pixel furthest from the centre moves by (the size of the distortion at the corners)
    far = np.array([[0.0, 0.0], [size[0] - 1.0, 0.0], [0.0, size[1] - 1.0], [size[0] - 1.0, size[1] - 1.0]])
    shift = float(np.linalg.norm(dist4.undistort_pixels(K, far) - far, axis=1).max())
    return {
        "views": len(corners), "size": list(size),
        "opencv4": {"rms_px": rms4, "leave_one_out_px": loo4, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2],
                    "cy": K[1, 2], "k1": dist[0], "k2": dist[1], "p1": dist[2], "p2": dist[3]},
        "opencv5": {"rms_px": rms5, "leave_one_out_px": loo5, "fx": K5[0, 0], "fy": K5[1, 1], "cx": K5[0, 2],
                    "cy": K5[1, 2], "k": [float(v) for v in d5]},
        "ours_vs_cv2_project_max_px": float(np.max(proj_diff)),
        "ours_reprojection_rms_px": float(np.sqrt(np.mean(np.concatenate(reproj)))),
        "ours_vs_cv2_undistortPoints_converged_max_px": float(np.max(undist_iter)),
        "ours_vs_cv2_undistortPoints_default_max_px": float(np.max(undist_plain)),
        "round_trip_max_px": float(np.max(round_trip)),
        "straightness_raw_px": straightness(corners), "straightness_undistorted_px": straightness(und_corners),
        "image_corner_shift_px": shift,
        "_intrinsics": intr, "_corners": corners, "_K": K, "_dist": dist,
    }


def rig_json(left: dict, right: dict, data: Path) -> dict:
    """A two-camera rig with the measured intrinsics, the right camera's mount from stereoCalibrate
    (board units: the samples' square size is unknown, so the baseline is in squares)."""
    both = sorted(set(left["_corners"]) & set(right["_corners"]))
    obj = [board()] * len(both)
    _, _, _, _, _, R, T, _, _ = cv2.stereoCalibrate(
        obj, [left["_corners"][k].astype(np.float32) for k in both],
        [right["_corners"][k].astype(np.float32) for k in both],
        left["_K"], left["_dist"], right["_K"], right["_dist"], tuple(left["size"]),
        flags=cv2.CALIB_FIX_INTRINSIC, criteria=CRITERIA)
    centre_r = (-R.T @ T).ravel()   # right camera centre in the left camera's frame (x right, y down, z fwd)

    def cam(cid: str, m: dict, pos, look) -> dict:
        intr: Intrinsics = m["_intrinsics"]
        w, h = m["size"]
        f_mm = intr.fx * SENSOR_WIDTH_MM / w
        return {"id": cid, "role": "static", "lens": {"focal_min_mm": round(f_mm, 3), "focal_max_mm": round(f_mm, 3)},
                "sensor": {"width_mm": SENSOR_WIDTH_MM, "height_mm": SENSOR_WIDTH_MM * h / w, "width_px": w,
                           "height_px": h},
                "mount": {"kind": "tripod", "position_m": pos, "look_at_m": look}, "nominal_focal_mm": round(f_mm, 3),
                "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
                               "model": intr.distortion.model,
                               "params": list(intr.distortion.params)}}

    # stage frame: z up; the left camera at 1.5 m height looking along +y; camera x -> stage x, z -> y, y -> -z
    to_stage = lambda p: [float(p[0]), float(p[2]), float(1.5 - p[1])]  # noqa: E731
    left_cam = cam("L", left, [0.0, 0.0, 1.5], [0.0, 10.0, 1.5])
    right_cam = cam("R", right, to_stage(centre_r), to_stage(centre_r + np.array([0.0, 0.0, 10.0])))
    return {"name": "opencv_stereo_samples", "kind": "scene", "fps": 25.0, "stage_size_m": [4.0, 4.0, 3.0],
            "cameras": [left_cam, right_cam],
            "lighting": {"description": f"OpenCV stereo samples ({data.name}); baseline in board squares"},
            "_baseline_squares": float(np.linalg.norm(T))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="folder with left01.jpg ... right14.jpg")
    ap.add_argument("--out", type=Path, help="write the rig JSON and the figures here")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    res = {side: measure_side(args.data, side) for side in ("left", "right")}
    rig = rig_json(res["left"], res["right"], args.data)
    baseline = rig.pop("_baseline_squares")
    loaded = Rig.model_validate(rig)             # the rig validates (focal in lens range, centre inside)
    for cid, side in (("L", "left"), ("R", "right")):
        back = Intrinsics.from_rig(loaded, cid)
        assert back == res[side]["_intrinsics"], (back, res[side]["_intrinsics"])
    figures = {side: {k: v for k, v in r.items() if not k.startswith("_")} for side, r in res.items()}
    figures["stereo_baseline_squares"] = baseline
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "opencv_stereo_samples_rig.json").write_text(json.dumps(rig, indent=2))
        (args.out / "lens_calibration.json").write_text(json.dumps(figures, indent=2, default=float))
    if args.json:
        print(json.dumps(figures, indent=2, default=float))
        return 0
    for side in ("left", "right"):
        f = figures[side]
        o4, o5 = f["opencv4"], f["opencv5"]
        print(f"{side}: {f['views']} views {f['size'][0]}x{f['size'][1]}; OPENCV (k1 k2 p1 p2): "
              f"rms {o4['rms_px']:.3f} px, "
              f"leave-one-out {o4['leave_one_out_px']:.3f} px; fx {o4['fx']:.1f} fy {o4['fy']:.1f} cx {o4['cx']:.1f} "
              f"cy {o4['cy']:.1f} k1 {o4['k1']:.4f} k2 {o4['k2']:.4f} p1 {o4['p1']:.5f} p2 {o4['p2']:.5f}")
        print(f"  5 coefficients (k3): rms {o5['rms_px']:.3f} px, leave-one-out {o5['leave_one_out_px']:.3f} px")
        print(f"  ours vs cv2.projectPoints {f['ours_vs_cv2_project_max_px']:.2e} px max; reprojection with ours "
              f"{f['ours_reprojection_rms_px']:.3f} px rms; undistort vs undistortPoints (converged) "
              f"{f['ours_vs_cv2_undistortPoints_converged_max_px']:.2e} px, vs undistortPoints (default) "
              f"{f['ours_vs_cv2_undistortPoints_default_max_px']:.2e} px; round trip {f['round_trip_max_px']:.2e} px")
        print(f"  straightness of the board lines: raw {f['straightness_raw_px']:.3f} px -> undistorted "
              f"{f['straightness_undistorted_px']:.3f} px; distortion at the image corners "
              f"{f['image_corner_shift_px']:.1f} px")
    print(f"stereo baseline {baseline:.2f} squares; rig validates and reads back through Intrinsics.from_rig")
    return 0


if __name__ == "__main__":
    sys.exit(main())
