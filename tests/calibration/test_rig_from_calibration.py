"""A rig from an imported calibration (issue 31): a studio that trusts its calibration gets a rig
without typing one. Pose2Sim's Qualisys file (skipped without ../shared):

- ``rig_from_calibration``: every camera's mount gives back the imported pose, its measured
  intrinsics are the imported lens at the frames' size (cam01/cam02 re-encoded 1080 wide), the
  static step would hold them as a lens calibration (~1 s);
- a camera without a fixed pose (a tracking camera) is refused naming it;
- `volcap import-calibration --format qualisys --frame-size ... --write-rig` writes the rig, and
  `volcap ingest` of the capture folder that names it takes the videos (slow: ~30 s, one frame of
  four 1080x1920 videos).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from volcap_core.calibration.geometry import rotation_angle_deg
from volcap_core.calibration.importers import calibration_from_qualisys
from volcap_core.calibration.rig_from_calibration import rig_from_calibration
from volcap_core.calibration.sfm import Intrinsics
from volcap_core.calibration.static import nominal_pose

REPO = Path(__file__).resolve().parents[2]
SINGLE = REPO.parent / "shared" / "data" / "real" / "pose2sim" / "Demo_SinglePerson"
QUALISYS = SINGLE / "calibration" / "Calib.qca.txt"
SIZES = {"cam01": (1080, 1920), "cam02": (1080, 1920), "cam03": (1088, 1920), "cam04": (1088, 1920)}


@pytest.fixture(scope="module")
def imported():
    if not QUALISYS.is_file():
        pytest.skip(f"needs {QUALISYS} (absent without ../shared)")
    return calibration_from_qualisys(QUALISYS.read_bytes(), "pose2sim", 3, 60.0, frame_sizes=SIZES)


def test_the_rig_is_the_imported_calibration(imported):
    rig = rig_from_calibration(imported)
    assert rig.name == "pose2sim" and rig.fps == 60.0 and rig.stage_size_m == imported.stage_size_m
    for c in imported.cameras:
        cam = rig.camera(c.id)
        W = np.asarray(c.world_to_camera)
        seed = nominal_pose(cam)          # what the static step seeds the camera with
        assert rotation_angle_deg(seed[:3, :3], W[:3, :3]) < 1e-4, c.id
        assert np.allclose(seed[:3, 3], W[:3, 3], atol=1e-6), c.id
        assert (cam.sensor.width_px, cam.sensor.height_px) == SIZES[c.id] == (c.width, c.height)
        held = Intrinsics.from_rig(rig, c.id)       # the lens calibration the static step holds
        assert rig.measured_intrinsics(c.id) is not None
        assert (held.fx, held.fy, held.cx, held.cy) == pytest.approx(c.intrinsics, abs=1e-9)
        assert held.distortion.opencv()[:5] == pytest.approx(c.distortion[:5], abs=1e-12)
        assert cam.role.value == "static"


def test_a_camera_without_a_fixed_pose_is_refused_by_name(imported):
    cams = list(imported.cameras)
    cams[2] = cams[2].model_copy(update={"static": False, "role": "tracking-landscape", "intrinsics": None,
                                         "world_to_camera": None})
    with pytest.raises(ValueError, match="camera cam03 has no fixed pose and intrinsics"):
        rig_from_calibration(imported.model_copy(update={"cameras": tuple(cams)}))


@pytest.mark.slow
def test_import_writes_a_rig_that_ingest_takes(prefect_api, imported, tmp_path):
    from prefect.settings import PREFECT_API_URL

    env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "VOLCAP_STORE": str(tmp_path / "store")}
    root = tmp_path / "pose2sim"
    (root / "videos").mkdir(parents=True)
    for cid in SIZES:
        (root / "videos" / f"{cid}.mp4").symlink_to(SINGLE / "videos" / f"{cid}.mp4")
    sizes = [a for c in ("cam01", "cam02") for a in ("--frame-size", f"{c}={SIZES[c][0]}x{SIZES[c][1]}")]
    run = subprocess.run([sys.executable, "-m", "flows.cli", "import-calibration", str(QUALISYS), "--format",
                          "qualisys", "--capture", "pose2sim", "--frames", "1", "--fps", "60", *sizes,
                          "--write-rig", str(root / "rig.json"), "--json"],
                         capture_output=True, text=True, env=env, cwd=REPO, timeout=300)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout.strip().splitlines()[-1])["rig"] == str(root / "rig.json")
    rig = json.loads((root / "rig.json").read_text())
    assert {c["id"]: (c["sensor"]["width_px"], c["sensor"]["height_px"]) for c in rig["cameras"]} == SIZES
    (root / "capture.json").write_text(json.dumps({
        "format": "volcap-capture/1", "name": "pose2sim", "rig": "rig.json", "fps": 60,
        "take": {"start_timecode": "01:00:00:49", "frame_count": 1},
        "cameras": [{"id": c, "path": f"videos/{c}.mp4", "start_timecode": "01:00:00:00"} for c in SIZES]}))
    run = subprocess.run([sys.executable, "-m", "flows.cli", "ingest", str(root), "--json"], capture_output=True,
                         text=True, env=env, cwd=REPO, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    # a wrong size for a camera is refused on the one line before anything is written
    run = subprocess.run([sys.executable, "-m", "flows.cli", "import-calibration", str(QUALISYS), "--format",
                          "qualisys", "--capture", "pose2sim", "--frame-size", "cam09=1080x1920",
                          "--write-rig", str(tmp_path / "other.json")],
                         capture_output=True, text=True, env=env, cwd=REPO, timeout=300)
    assert run.returncode != 0 and "cam09 not in the calibration" in run.stderr, run.stderr
    assert not (tmp_path / "other.json").exists()
