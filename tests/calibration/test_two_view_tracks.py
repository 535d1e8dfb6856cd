"""Two-view tracks in the seeded triangulation (issue 31): COLMAP ignores a point seen by two images
only, so a rig whose cameras overlap in pairs (Pose2Sim's four cameras: only cam01-cam02 share a
view) got no points and every camera was refused with "0 observations". Here the smallest such rig:
two static cameras of the demo rig, whose every track is a two-view track. By default the points are
triangulated again with two-view tracks, said in the stats, the warnings and the log; forced off, the
camera pair is refused as before. ~25 s on 2 cores (steps 1-4 only).
"""

from __future__ import annotations

import logging

import cv2  # noqa: F401  (before pycolmap)
import pytest

from volcap_core.calibration.lidar import LidarScan
from volcap_core.calibration.metrics import load_ground_truth, static_errors
from volcap_core.calibration.static import StaticCalibrationOptions, calibrate_static_cameras
from volcap_core.capture import CaptureFolder
from volcap_core.synth import synthesize_capture

CAMERAS = ["S001", "S002"]
FRAMES = 3


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    root = tmp_path_factory.mktemp("twoview") / "cap"
    synthesize_capture(root, rig="demo_scene", frames=FRAMES, cameras=CAMERAS, actors=1, name="two-view")
    cap = CaptureFolder.open(root)
    images = {c: cap.load(c, FRAMES // 2) for c in CAMERAS}
    return cap, images, LidarScan.from_ply_bytes(cap.lidar_path.read_bytes())


def test_a_pair_of_cameras_calibrates_on_two_view_tracks_and_says_so(pair, caplog):
    cap, images, scan = pair
    with caplog.at_level(logging.WARNING, logger="volcap.calibrate"):
        static = calibrate_static_cameras(images, cap.rig, scan, options=StaticCalibrationOptions(guided=None))
    assert static.camera_ids == CAMERAS and not static.unregistered
    assert static.stats["sfm"]["two_view_tracks"] == 1.0
    assert any("two-view tracks" in w for w in static.warnings), static.warnings
    assert "triangulated again with two-view tracks" in caplog.text and "S001 0, S002 0" in caplog.text
    for c in CAMERAS:
        assert static.support[c]["observations"] >= 25, static.support[c]
    err = static_errors(static.K, static.world_to_camera, load_ground_truth(cap.root / "ground_truth"), FRAMES // 2)
    print({c: (round(e["rotation_deg"], 4), round(static.support[c]["rotation_sigma_deg"], 4)) for c, e in err.items()})
    # measured: 0.63° and 0.73° (two cameras, step 4 only: no third view or guided tracks to hold
    # them); a guard against the pair falling apart, not an accuracy figure
    assert max(e["rotation_deg"] for e in err.values()) < 2.0, err
    # each camera's stated sigma is step 4's covariance (step 5 is off), no longer the pose-only
    # bound of the points held fixed (0.0035° here, 180-210x below the error); measured 0.16-0.19°,
    # still 3.9x below the error with this scan (docs/calibration.md), so only a floor is asserted
    for c in CAMERAS:
        assert static.support[c]["rotation_sigma_deg"] > 0.05, static.support[c]
