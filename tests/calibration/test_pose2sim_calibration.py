"""Pose2Sim SinglePerson through the static calibration (issue 31; skipped without ../shared).

Four real portrait cameras filming a person on a treadmill, no lidar. The rig is written from the
imported Qualisys calibration (``calibration_from_qualisys``, fitted to the 1080-wide re-encodes of
cam01 and cam02; ``rig_from_calibration``): each camera's lens the imported one, its mount the
imported pose. Only cam01-cam02 share a
view (docs/benchmarks.md, "Real footage: Pose2Sim SinglePerson"), so every track is a two-view track.

- by default the calibration refuses cam03 and cam04, naming why and the flag to try;
- with ``allow_unregistered`` cam01 and cam02 calibrate (two-view tracks, said in the warnings), and
  each one's stated rotation sigma matches its rotation error against the imported calibration
  within a factor of 2 (before: 0.0022-0.0028° stated against 0.7-0.8°, 250-370x understated);
  the lens calibration's focal is held (the pair's footage shows no evidence against it), within
  0.5 % of the studio's (before calibrate-static 13: +2.4 % / +2.9 % at this frame).

Full resolution (at half, SIFT finds no verified pair). ~2.5 min on 2 cores for the two runs
(SIFT of 1080x1920 frames), marked slow.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2  # noqa: F401  (before pycolmap)
import numpy as np
import pytest

from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.geometry import rotation_angle_deg
from volcap_core.calibration.importers import calibration_from_qualisys
from volcap_core.calibration.rig_from_calibration import rig_from_calibration
from volcap_core.calibration.static import StaticCalibrationOptions, nominal_pose
from volcap_core.calibration.static_step import calibrate_static_step
from volcap_core.capture import CaptureFolder
from volcap_core.colour import bt709_oetf_inverse

SINGLE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "pose2sim" / "Demo_SinglePerson"
SIZES = {"cam01": (1080, 1920), "cam02": (1080, 1920), "cam03": (1088, 1920), "cam04": (1088, 1920)}
FRAMES = 3
#: the take starts at the videos' frame 48 (of 100): the person mid-stride, the middle frame 49
START = "01:00:00:48"


def _rig(imported) -> dict:
    """The capture's rig: written from the imported calibration (``rig_from_calibration``, what
    `volcap import-calibration --write-rig` writes), on the 4 x 4 x 2.5 m stage of the treadmill."""
    return rig_from_calibration(imported, stage_size_m=(4.0, 4.0, 2.5)).model_dump(mode="json")


@pytest.fixture(scope="module")
def pose2sim(tmp_path_factory):
    data = SINGLE
    if not data.is_dir():
        pytest.skip(f"needs {data} (absent without ../shared)")
    imported = calibration_from_qualisys((data / "calibration" / "Calib.qca.txt").read_bytes(), "pose2sim", 100,
                                         60.0, frame_sizes=SIZES)
    root = tmp_path_factory.mktemp("pose2sim") / "capture"
    (root / "videos").mkdir(parents=True)
    for cid in SIZES:
        (root / "videos" / f"{cid}.mp4").symlink_to(data / "videos" / f"{cid}.mp4")
    (root / "rig.json").write_text(json.dumps(_rig(imported)))
    (root / "capture.json").write_text(json.dumps({
        "format": "volcap-capture/1", "name": "pose2sim", "rig": "rig.json", "fps": 60,
        "take": {"start_timecode": START, "frame_count": FRAMES},
        "cameras": [{"id": c, "path": f"videos/{c}.mp4", "start_timecode": "01:00:00:00"} for c in SIZES]}))
    cap = CaptureFolder.open(root)
    for c in imported.cameras:   # the mounts are the imported poses
        assert rotation_angle_deg(nominal_pose(cap.rig.camera(c.id))[:3, :3],
                                  np.asarray(c.world_to_camera)[:3, :3]) < 1e-4
    frames: dict[tuple[str, int], np.ndarray] = {}

    def load(camera: str, k: int) -> np.ndarray:
        # as ingest decodes them: untagged HD video, BT.709 transfer undone to scene-linear
        if (camera, k) not in frames:
            frames[camera, k] = bt709_oetf_inverse(cap.load(camera, k)).astype(np.float32)
        return frames[camera, k]

    return cap, load, imported


@pytest.mark.slow
def test_cameras_without_a_partner_are_refused_naming_why_and_the_flag(pose2sim):
    cap, load, _ = pose2sim
    with pytest.raises(CalibrationInputError) as err:
        calibrate_static_step(cap.name, cap.rig, sorted(SIZES), [], FRAMES, load, None)
    msg = str(err.value)
    print(msg)
    assert "static cameras cam03, cam04 cannot be calibrated" in msg
    assert "cam03: 0 observations in the sparse SfM" in msg and "--allow-unregistered" in msg


@pytest.mark.slow
def test_the_pair_calibrates_and_states_its_error(pose2sim):
    cap, load, imported = pose2sim
    step = calibrate_static_step(cap.name, cap.rig, sorted(SIZES), [], FRAMES, load, None,
                                 StaticCalibrationOptions(allow_unregistered=True))
    static = step.calibration
    assert static.camera_ids == ["cam01", "cam02"] and static.unregistered == ["cam03", "cam04"]
    assert any("two-view tracks" in w for w in static.warnings), static.warnings
    for c in static.camera_ids:
        err = rotation_angle_deg(static.world_to_camera[c][:3, :3],
                                 np.asarray(imported.camera(c).world_to_camera)[:3, :3])
        sigma = static.support[c]["rotation_sigma_deg"]
        print(c, f"error {err:.3f}°, stated sigma {sigma:.3f}°", static.support[c])
        # one draw of the error: measured 0.20° / 0.77° against 0.86° / 0.88°; over reference frames 49-90
        # the pair's errors are 0.18-0.81° against 0.86-0.87° (docs/benchmarks.md). The stated
        # sigma is not understated (before: 0.0022-0.0028°, 250-370x), and within the 1° bound
        assert err < 2 * sigma and 0.1 < sigma < 1.0, (c, err, sigma)
        # the held lens calibration: no evidence against it (measured Δχ² 2.6 / 4.4 against 25), so
        # its focal stays within the tight prior (measured +0.20 % / -0.00 %; loose: +2.41 % / +2.88 %)
        s = static.support[c]
        focal = static.raw_intrinsics[c].fx / imported.camera(c).intrinsics[0] - 1
        assert s["focal_held"] == 1.0 and s["focal_evidence_chi2"] < s["focal_release_chi2"], s
        assert abs(focal) < 0.005, (c, focal)
