"""A capture with neither a lidar scan nor tracking cameras, end to end (issue 13): ingest ->
calibrate (the stage frame and metric scale from the rig's mounts) -> reconstruct on the estimated
calibration; and the stage frame's similarity and known-distance scale on their own.

The capture: tests/test_calibrate_flow.py's 6 static cameras of the demo rig (S001-S006), 6 frames,
rendered without a scan and without the tracking cameras (``synthesize_capture(lidar=False)``: no
``lidar`` in capture.json; ``ground_truth/lidar.ply`` is still written and the error table uses it).
~1 min for the calibration and two dense frames on 2 cores, then ~1 min of training (marked slow).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2  # noqa: F401  (before pycolmap)
import numpy as np
import pytest

from flows.calibrate import calibrate_flow
from flows.ingest import ingest_flow
from flows.runtime import run_flow
from volcap_core.calibration.geometry import look_at_rotation, pose_matrix
from volcap_core.calibration.record import Calibration
from volcap_core.calibration.static import StaticCalibrationOptions, frame_without_lidar
from volcap_core.capture import Capture
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture

FRAMES = 6
#: the static cameras of tests/test_calibrate_flow.py's capture (which has a scan and trackers)
STATIC = ["S001", "S002", "S003", "S004", "S005", "S006"]
NAME = "no-lidar"


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("nolidar") / "cap"
    synthesize_capture(root, rig="demo_scene", frames=FRAMES, cameras=STATIC, name=NAME, lidar=False)
    return root


@pytest.fixture(scope="module")
def calibrated(prefect_api, capture_dir, tmp_path_factory):
    store = ArtifactStore(str(tmp_path_factory.mktemp("nolidarstore") / "store")).url
    capture = run_flow(ingest_flow, store=store, capture_dir=str(capture_dir)).result
    res = run_flow(calibrate_flow, store=store, capture=f"captures/{NAME}", frames=(2, 4))
    return store, capture, res


def test_the_synthetic_capture_has_no_scan(capture_dir):
    desc = json.loads((capture_dir / "capture.json").read_text())
    assert "lidar" not in desc and not (capture_dir / "lidar.ply").exists()
    assert (capture_dir / "ground_truth" / "lidar.ply").exists()       # evaluation only
    assert {c["id"] for c in desc["cameras"]} == set(STATIC)


def test_calibrate_without_lidar_or_tracking_cameras(calibrated):
    store, capture, res = calibrated
    s = ArtifactStore(store)
    assert s.get_record(capture, Capture).lidar is None
    out = res.result
    # static, assemble, two dense frames, sequence, errors: no tracking task
    assert (res.tasks_run, res.tasks_failed) == (6, 0)
    calib = s.get_record(out["calibration"]["digest"], Calibration)
    assert calib.static_ids == STATIC and calib.tracking_ids == [] and calib.unregistered == {}
    # the stage frame came from the mounts: the similarity onto them and its residual are reported
    frame = out["stage_frame"]
    assert frame["scale_source"] == 0.0 and frame["mount_inliers"] == len(STATIC)
    # measured (2026-11-24): 1.8 cm rms, 2.4 cm max (the synthetic mounts are 1.5 cm off per axis)
    assert frame["mount_residual_rms_m"] < 0.05 and frame["mount_residual_max_m"] < 0.10, frame
    static = out["errors"]["static"]
    print("no lidar", {k: round(v, 4) for k, v in static.items() if k != "per_camera"}, frame)
    # measured: rotation 0.13° mean, 0.21° max; centres 0.70 % of the 4 m stage (2.8 cm) at most;
    # focal within 0.24 %; projection 0.88 px mean (step 5 through the plates' plane-sweep surface;
    # with the scan, on the same cameras: 0.15° mean, 0.17° max, 0.75 %). Bounds ~3x
    assert static["cameras"] == len(STATIC)
    assert static["rotation_deg_max"] < 0.6, static
    assert static["centre_frac_max"] < 0.02, static
    assert static["focal_pct_max_abs"] < 1.0, static
    pts = out["errors"]["points"]
    assert pts, out["errors"]


@pytest.mark.slow
def test_reconstruct_without_lidar_beats_the_empty_model(calibrated):
    from flows.reconstruct import reconstruct_flow

    store, capture, first = calibrated
    res = run_flow(reconstruct_flow, store=store, capture=capture.digest, frames=(2, 4), preset="test",
                   points_per_frame=2000, held_out=["S003"])
    out = res.result
    assert out["calibration"] == first.result["calibration"]     # the same (cached) calibration
    seg = out["segments"][0]
    print("no lidar reconstruct", {k: seg[k] for k in ("held_out_psnr", "floor_initial_psnr", "floor_empty_psnr")})
    # measured (2026-11-24; the test preset's 20 steps on 2 frames of 2000 estimated points, 5 static
    # training views): held-out 15.26 dB, untrained 15.12, empty 14.88. (tests/test_calibrate_flow.py's
    # capture with a scan also trains on two tracking cameras: 15.84 there.) A model that does not
    # train, or renders nothing, fails
    assert seg["held_out_psnr"] >= seg["floor_initial_psnr"] + 0.05
    assert seg["held_out_psnr"] >= seg["floor_empty_psnr"] + 0.2


def _rig_like(n: int = 8, radius: float = 5.0):
    """Camera poses on a circle looking at the centre (world-to-camera) and their mounts."""
    w2c, mounts = {}, {}
    for i in range(n):
        a = 2 * np.pi * i / n
        C = np.array([radius * np.cos(a), radius * np.sin(a), 2.5])
        R = look_at_rotation(C, np.array([0.0, 0.0, 1.0]))
        w2c[f"C{i}"], mounts[f"C{i}"] = pose_matrix(R, -R @ C), C
    return w2c, mounts


def test_frame_without_lidar_is_a_robust_similarity_onto_the_mounts():
    from volcap_core.calibration.geometry import Similarity, so3_exp

    w2c, mounts = _rig_like()
    rng = np.random.default_rng(0)
    noisy = {c: m + rng.normal(0, 0.02, 3) for c, m in mounts.items()}    # a survey good to 2 cm
    noisy["C3"] = mounts["C3"] + np.array([0.6, 0.0, 0.0])                # one mount 60 cm wrong
    # the reconstruction in another frame: scale 0.7, rotated and shifted
    T = Similarity(0.7, so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, -0.5]))
    moved = {c: T.apply_pose(v) for c, v in w2c.items()}
    S, stats = frame_without_lidar(moved, noisy)
    back = {c: S.apply_pose(v) for c, v in moved.items()}
    for c in w2c:
        assert np.allclose(back[c][:3, :3], w2c[c][:3, :3], atol=0.01)
    assert abs(S.s * 0.7 - 1) < 0.01 and stats["mount_inliers"] == 7 and stats["mount_outliers"] == 1
    assert stats["mount_residual"]["C3"] > 0.5 and stats["mount_residual_median_m"] < 0.04
    # a known distance sets the scale exactly, the mounts still orient and place
    d = float(np.linalg.norm(mounts["C0"] - mounts["C4"]))
    S2, st2 = frame_without_lidar(moved, noisy, StaticCalibrationOptions(known_distance=("C0", "C4", d)))
    c0, c4 = (-(S2.apply_pose(moved[c])[:3, :3].T @ S2.apply_pose(moved[c])[:3, 3]) for c in ("C0", "C4"))
    assert abs(np.linalg.norm(c0 - c4) - d) < 1e-9 and st2["scale_source"] == 1.0
    with pytest.raises(ValueError, match="C9"):
        frame_without_lidar(moved, noisy, StaticCalibrationOptions(known_distance=("C0", "C9", 1.0)))
