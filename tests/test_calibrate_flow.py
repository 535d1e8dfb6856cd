"""The calibrate flow and commands on a small synthetic capture: refs, the error table, caching,
a capture without tracking cameras, COLMAP export, bad inputs, reconstruct on the estimated calibration.

The capture is the 6-frame, 8-camera subset of the demo rig that tests/calibration uses (6 static +
2 tracking cameras), with dense points for two frames: ~30 s for the first calibration on 2 cores.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2  # noqa: F401  (before pycolmap)
import numpy as np
import pycolmap
import pytest

from flows.calibrate import calibrate_flow
from flows.ingest import ingest_flow
from flows.runtime import run_flow
from tasks.calibrate import calibrate_static, calibrate_tracking_camera
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.static_step import StaticCalibrationRecord
from tasks.contract import cached_output
from volcap_core.calibration.record import Calibration, camera_at, decode_tracking_frames
from volcap_core.capture import Capture, IngestError
from volcap_core.pointcloud import PointCloudSequence, decode_points
from volcap_core.records import ArtifactRef
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture

REPO = Path(__file__).resolve().parents[1]
FRAMES = 6
CAMERAS = ["S001", "S002", "S003", "S004", "S005", "S006", "S008", "S010"]
STATIC = [c for c in CAMERAS if c < "S008"]
NAME = "calib-flow"


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("calflow") / "cap"
    synthesize_capture(root, rig="demo_scene", frames=FRAMES, cameras=CAMERAS, name=NAME)
    return root


@pytest.fixture(scope="module")
def calibrated(prefect_api, capture_dir, tmp_path_factory):
    store = ArtifactStore(str(tmp_path_factory.mktemp("calstore") / "store")).url
    capture = run_flow(ingest_flow, store=store, capture_dir=str(capture_dir)).result
    first = run_flow(calibrate_flow, store=store, capture=f"captures/{NAME}", frames=(2, 4))
    return store, capture, first


def test_the_lidar_scan_is_a_stored_capture_input(calibrated, capture_dir):
    store, capture, _ = calibrated
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    assert cap.lidar is not None and cap.lidar.media_type == "application/x-ply"
    assert s.get_bytes(cap.lidar) == (capture_dir / "lidar.ply").read_bytes()


def test_calibrate_flow_refs_error_table_and_cached_rerun(calibrated):
    store, capture, first = calibrated
    # static, 2 tracking cameras, assemble, 2 dense frames, sequence, errors
    assert (first.tasks_run, first.tasks_cached, first.tasks_failed) == (8, 0, 0)
    out = first.result
    s = ArtifactStore(store)
    calib = s.get_record(out["calibration"]["digest"], Calibration)
    assert calib.capture == NAME and calib.frame_count == FRAMES and calib.reference_frame == FRAMES // 2
    assert sorted(calib.static_ids) == STATIC and sorted(calib.tracking_ids) == ["S008", "S010"]
    tf = decode_tracking_frames(s.get_bytes(calib.tracking_frames))
    for t in range(FRAMES):
        K, W, w, h = camera_at(calib, "S010", t, tf)
        assert K[0, 0] > 100 and np.allclose(W[:3, :3] @ W[:3, :3].T, np.eye(3), atol=1e-9)
    seq = s.get_record(out["points"]["digest"], PointCloudSequence)
    assert [f.frame for f in seq.frames] == [2, 3]
    assert s.resolve(f"calibrations/{NAME}").digest == out["calibration"]["digest"]
    assert seq.calibration.digest == out["calibration"]["digest"]
    for f in seq.frames:
        xyz, rgb = decode_points(s.get_bytes(f.points))
        assert len(xyz) == f.count > 2000 and rgb.shape == xyz.shape and f.time == pytest.approx(f.frame / 24)

    e = out["errors"]
    print(json.dumps({k: v for k, v in e["static"].items() if k != "per_camera"}))
    # measured here: rotation ~0.3-0.45°, centre < 1 % of the stage, tracking focal ~1 %, jitter
    # ~0.3 px, points ~18 mm from the true surface; the bounds are regression guards
    assert e["static"]["cameras"] == len(STATIC)
    assert e["static"]["rotation_deg_max"] < 0.8 and e["static"]["centre_frac_max"] < 0.025
    tr = e["tracking"]["priors"]
    assert set(tr["per_camera"]) == {"S008", "S010"}
    assert tr["focal_pct_max_abs"] < 2.0 and tr["pose_jitter_px_mean"] < 2.0
    # each tracker's record says how well its solve determines it (the covariance's sigma), and its
    # error is within what it says (3 sigma)
    for cam in ("S008", "S010"):
        q = calib.camera(cam).quality
        assert q["focal_sigma_pct"] > 0 and 0 < q["rotation_sigma_deg"] < 2.0 and q["centre_sigma_m"] > 0, q
        assert tr["per_camera"][cam]["focal_pct_mean_abs"] < 3 * q["focal_sigma_pct"], (cam, q)
    assert set(e["points"]["per_frame"]) == {"2", "3"} and e["points"]["median_distance_m"] < 0.06
    assert set(e["targets"]) >= {"static_rotation", "static_centre", "tracking_focal", "tracking_jitter"}

    again = run_flow(calibrate_flow, store=store, capture=capture.digest, frames=(2, 4))
    assert (again.tasks_run, again.tasks_cached) == (0, 8)
    assert {k: v for k, v in again.result.items() if k != "capture"} == {k: v for k, v in out.items() if k != "capture"}


def test_a_capture_without_tracking_cameras_runs_no_tracking_task(calibrated, capture_dir, tmp_path):
    store, _, _ = calibrated
    # the same frames (linked) described as a capture of the static cameras only
    root = tmp_path / "static-only"
    root.mkdir()
    (root / "frames").symlink_to(capture_dir / "frames")
    shutil.copyfile(capture_dir / "lidar.ply", root / "lidar.ply")
    (root / "ground_truth").symlink_to(capture_dir / "ground_truth")
    desc = json.loads((capture_dir / "capture.json").read_text())
    desc["name"] = "static-only"
    desc["cameras"] = [c for c in desc["cameras"] if c["id"] in STATIC]
    (root / "capture.json").write_text(json.dumps(desc))
    run_flow(ingest_flow, store=store, capture_dir=str(root))
    res = run_flow(calibrate_flow, store=store, capture="captures/static-only", frames=(3, 4))
    # static, assemble, one dense frame, sequence, errors: no tracking task
    assert (res.tasks_run, res.tasks_failed) == (5, 0)
    calib = ArtifactStore(store).get_record(res.result["calibration"]["digest"], Calibration)
    assert calib.tracking_ids == [] and calib.tracking_frames is None
    assert res.result["errors"]["tracking"] == {} and res.result["tracking_cameras"] == []
    static = ArtifactStore(store).get_record(_cached_ref(store, calibrate_static, capture=_capture_ref(res)),
                                             StaticCalibrationRecord)
    assert static.capture == "static-only" and static.reference is None  # nothing to register against is built


def _capture_ref(summary) -> ArtifactRef:
    return ArtifactRef.model_validate(summary.result["capture"])


def _cached_ref(store: str, task, **inputs) -> ArtifactRef:
    """The ref a task returned for these inputs, read from its cache record in the store."""
    _, result = cached_output(task, store, **inputs)
    assert result is not None, f"{task.name} has no cached result for {inputs}"
    return result if isinstance(result, ArtifactRef) else ArtifactRef.model_validate(result)


def test_bad_inputs_name_the_capture_and_camera(calibrated, capture_dir, tmp_path):
    store, capture, _ = calibrated
    static = _cached_ref(store, calibrate_static, capture=capture)
    with pytest.raises(CalibrationInputError, match=f"capture {NAME} has no camera 'S099'"):
        calibrate_tracking_camera.fn(store, capture, static, "S099")
    with pytest.raises(CalibrationInputError, match=f"capture {NAME}: camera S002 is a static camera"):
        calibrate_tracking_camera.fn(store, capture, static, "S002")

    # tracking cameras but no lidar scan: refused before any work (they register against the scan)
    root = tmp_path / "no-lidar"
    root.mkdir()
    (root / "frames").symlink_to(capture_dir / "frames")
    desc = json.loads((capture_dir / "capture.json").read_text())
    desc.pop("lidar")
    desc.pop("ground_truth")
    desc["name"] = "no-lidar"
    (root / "capture.json").write_text(json.dumps(desc))
    no_lidar = ingest_flow(store=store, capture_dir=str(root))
    assert ArtifactStore(store).get_record(no_lidar, Capture).lidar is None
    with pytest.raises(CalibrationInputError, match="capture no-lidar has tracking cameras .*S008, S010.* no lidar scan"):
        calibrate_static.fn(store, no_lidar)

    from tests.test_ingest import make_capture

    cap = make_capture(tmp_path / "tiny")
    desc = json.loads((cap / "capture.json").read_text())
    desc["lidar"] = "scan.ply"
    (cap / "capture.json").write_text(json.dumps(desc))
    (cap / "scan.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 500\n"
                                   b"property float x\nproperty float y\nproperty float z\nend_header\n" + b"\0" * 64)
    with pytest.raises(IngestError, match=r"lidar scan .*scan\.ply: not a readable PLY"):
        ingest_flow(store=store, capture_dir=str(cap))
    desc["lidar"] = "../outside.ply"
    (cap / "capture.json").write_text(json.dumps(desc))
    with pytest.raises(IngestError, match="must stay inside the capture folder"):
        ingest_flow(store=store, capture_dir=str(cap))


@pytest.fixture
def api_env(prefect_api):
    from prefect.settings import PREFECT_API_URL

    return {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value()}


def _volcap(*args: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flows.cli", *args], capture_output=True, text=True, env=env,
                          cwd=REPO, timeout=600)


def test_calibrate_and_export_colmap_commands(calibrated, api_env, tmp_path):
    store, _, first = calibrated
    res = _volcap("calibrate", f"captures/{NAME}", "--frames", "2:3", "--store", store, "--json", env=api_env)
    assert res.returncode == 0, res.stderr[-2000:]
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    # everything but the new frame range's sequence and error table is cached
    assert (doc["tasks_run"], doc["tasks_cached"], doc["tasks_failed"]) == (2, 5, 0)
    assert doc["calibration"] == first.result["calibration"]
    assert doc["errors"]["static"]["cameras"] == len(STATIC) and "priors" in doc["errors"]["tracking"]
    assert f"calibration: {doc['calibration']['digest']}" in res.stdout and "static cameras (6)" in res.stdout

    s = ArtifactStore(store)
    calib = s.get_record(doc["calibration"]["digest"], Calibration)
    tf = decode_tracking_frames(s.get_bytes(calib.tracking_frames))
    xyz, _ = decode_points(s.get_bytes(s.get_record(doc["points"]["digest"], PointCloudSequence).at(2).points))
    for binary in (False, True):
        out = tmp_path / f"colmap{int(binary)}"
        args = ["export-colmap", f"calibrations/{NAME}", "--frame", "2", "--out", str(out),
                "--points", doc["points"]["digest"], "--store", store, "--json"] + (["--binary"] if binary else [])
        r = _volcap(*args, env=api_env)
        assert r.returncode == 0, r.stderr[-2000:]
        assert (out / ("cameras.bin" if binary else "cameras.txt")).is_file()
        rec = pycolmap.Reconstruction(str(out))
        assert rec.num_images() == len(CAMERAS) and rec.num_points3D() == len(xyz)
        im = rec.find_image_with_name("S008.png")
        np.testing.assert_allclose(im.cam_from_world().matrix(), camera_at(calib, "S008", 2, tf)[1][:3], atol=1e-9)
    again = _volcap("export-colmap", doc["calibration"]["digest"], "--frame", "2", "--out", str(tmp_path / "colmap0"),
                    "--store", store, env=api_env)
    assert again.returncode == 0 and pycolmap.Reconstruction(str(tmp_path / "colmap0")).num_points3D() == 0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left

    bad = _volcap("export-colmap", doc["calibration"]["digest"], "--frame", "5", "--out", str(tmp_path / "x"),
                  "--points", doc["points"]["digest"], "--store", store, env=api_env)
    assert bad.returncode == 1 and "points" in bad.stderr and "no frame 5" in bad.stderr
    missing = _volcap("calibrate", "captures/nope", "--store", store, env=api_env)
    assert missing.returncode == 1 and "captures/nope" in missing.stderr


@pytest.mark.slow
def test_reconstruct_trains_on_the_estimated_calibration(calibrated):
    from flows.reconstruct import reconstruct_flow
    from volcap_core.reconstruction import SegmentModel

    store, capture, first = calibrated
    res = run_flow(reconstruct_flow, store=store, capture=capture.digest, frames=(2, 4), preset="test",
                   points_per_frame=2000, held_out=["S003"], steps=80, max_gaussians=30_000)
    out = res.result
    # the calibration comes from the cache; the dense frames run again without the held-out camera
    # (its footage must not reach the model it tests), then a new budgeted sequence and the training
    assert out["calibration"] == first.result["calibration"] and res.tasks_run == 4
    s = ArtifactStore(store)
    seq = s.get_record(out["points"]["digest"], PointCloudSequence)
    assert [f.count for f in seq.frames] == [2000, 2000]
    seg = out["segments"][0]
    print("estimated-calibration reconstruct", {k: seg[k] for k in ("held_out_psnr", "floor_initial_psnr",
                                                                   "floor_empty_psnr", "training_psnr", "gaussians")})
    rec = s.get_record(seg["model"]["digest"], SegmentModel)
    assert rec.calibration.digest == out["calibration"]["digest"]
    # on the estimated calibration too the model beats the floors of the same views. Measured
    # (2026-11-26; 80 steps of the test preset on 2 frames of 2000 estimated points matched at the
    # preset's dense_scale 0.5, a budget of 30 000 Gaussians, the scan's points among them): held-out
    # 16.71 dB, untrained 14.88, empty 14.88; training views 20.47; 46 s. Without the budget (the
    # scan's 104 000 points kept): 17.87 dB in 111 s; 40 steps and 30 000: 15.22 dB. Before the
    # dense points followed the preset's scale (full resolution, no budget), 20 steps gave 15.84 dB
    # on 2026-11-23 and 14.52 in a venv of 2026-11-26. The demo (550 steps) is where
    # the quality is measured; here a model that does not train, or renders nothing, fails. Bounds:
    # half the margins
    assert seg["held_out_psnr"] >= seg["floor_initial_psnr"] + 0.9
    assert seg["held_out_psnr"] >= seg["floor_empty_psnr"] + 0.9
