"""A resampled capture keeps its calibration (issue 31): a calibration of a synthetic capture,
applied to the same cameras' frames downsampled (2x, and 3x to sizes that do not divide), puts
every ground-truth point where the downsampled frame shows it; through ``volcap
import-calibration REF --format record`` onto a capture stored at the lower resolution.

The ground-truth points are the full-size pixels lifted by the true depth: an area downsampling
by n averages n x n pixels into one, so full-size pixel (x, y) lies in the low-resolution pixel
(x // n, y // n), at ``s (x + 0.5) - 0.5`` with ``s`` = the low size over the full one per axis.
The capture: 3 static cameras of the demo rig, 1 frame with depth (~3 s to render); the tests
~1 s after it.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.geometry import intrinsic_matrix, project
from volcap_core.calibration.importers import fit_calibration, fit_to_frames
from volcap_core.synth import ground_truth

synth = pytest.importorskip("volcap_core.synth.synthesize", reason="the synthetic capture renderer is absent")

CAMERAS = ["S000", "S003", "S006"]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """(the true calibration as a record, camera id -> (full-size pixels [N, 2], world points [N, 3]))."""
    from volcap_core.synth import read_exr

    root = tmp_path_factory.mktemp("resampled") / "cap"
    synth.synthesize_capture(root, rig="demo_scene", frames=1, cameras=CAMERAS, write_depth=True, supersample=1,
                             actors=1)
    cams_json = json.loads((root / "ground_truth/cameras.json").read_text())
    record, _ = ground_truth.calibration(cams_json, "full", CAMERAS, (8.0, 8.0, 4.0))
    points = {}
    for c in CAMERAS:
        d = np.asarray(read_exr(root / f"ground_truth/depth/{c}/000000.exr"), np.float64)
        d = d[..., 0] if d.ndim == 3 else d
        cam = record.camera(c)
        fx, fy, cx, cy = cam.intrinsics
        w2c = np.asarray(cam.world_to_camera)
        v, u = np.mgrid[0:d.shape[0]:7, 0:d.shape[1]:5]          # every 7th row, 5th column
        u, v, z = u.ravel().astype(float), v.ravel().astype(float), d[v, u].ravel()
        keep = np.isfinite(z) & (z > 0) & (z < 1e3)
        u, v, z = u[keep], v[keep], z[keep]
        xc = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1)
        points[c] = (np.stack([u, v], -1), (xc - w2c[:3, 3]) @ w2c[:3, :3])
    return record, points


@pytest.mark.parametrize("n", [2, 3])
def test_downsampled_frames_see_the_ground_truth_points_where_the_calibration_puts_them(calibrated, n):
    record, points = calibrated
    W, H = record.camera(CAMERAS[0]).width, record.camera(CAMERAS[0]).height
    w, h = round(W / n), round(H / n)            # 320x180 -> 160x90 and 107x60 (cv2.resize's rounding)
    fitted = fit_calibration(record, {c: (w, h) for c in CAMERAS}, capture="low")
    assert fitted.capture == "low"
    for c in CAMERAS:
        cam = fitted.camera(c)
        assert (cam.width, cam.height) == (w, h) and cam.world_to_camera == record.camera(c).world_to_camera
        uv_full, X = points[c]
        uv, _ = project(intrinsic_matrix(*cam.intrinsics), np.asarray(cam.world_to_camera), X)
        # where the area-downsampled frame shows each full-size pixel's point
        want = np.stack([w / W * (uv_full[:, 0] + 0.5) - 0.5, h / H * (uv_full[:, 1] + 0.5) - 0.5], -1)
        err = np.abs(uv - want).max()
        assert err < 1e-6, (c, n, err)
        if n == 2:   # and inside the low-resolution pixel that averages it
            assert np.array_equal(np.floor(uv + 0.5), uv_full // 2)
        # the naive reading (K times the scale) is off by a quarter (n=2) to a third (n=3) of a pixel
        naive = intrinsic_matrix(*record.camera(c).intrinsics) * np.array([[w / W], [h / H], [1.0]])
        err_naive = np.abs(project(naive, np.asarray(cam.world_to_camera), X)[0] - want).max()
        assert err_naive > 0.2, err_naive


def test_a_letterboxed_reencode_is_fitted_not_stretched(calibrated):
    # Pose2Sim's case: 1088x1920 -> 1080x1920 is a uniform scale with 7 px bars, not a stretch
    record, _ = calibrated
    cam = record.camera(CAMERAS[0]).model_copy(update={"width": 1088, "height": 1920})
    fit = fit_to_frames(cam, 1080, 1920)
    s = 1080 / 1088
    assert fit.quality["resample_scale"] == fit.quality["resample_scale_y"] == pytest.approx(s)
    assert fit.quality["resample_pad_y_px"] == pytest.approx((1920 - s * 1920) / 2)
    assert fit.intrinsics[3] == pytest.approx(s * (cam.intrinsics[3] + 0.5) - 0.5 + (1920 - s * 1920) / 2)


def test_a_tracking_camera_is_refused_at_another_size(calibrated):
    record, _ = calibrated
    tracking = record.camera(CAMERAS[0]).model_copy(update={"static": False, "role": "tracking-landscape",
                                                            "intrinsics": None, "world_to_camera": None})
    rec = record.model_copy(update={"cameras": (tracking,)})
    with pytest.raises(CalibrationInputError, match=r"calib: camera S000: a tracking camera .* cannot be fitted "
                                                    r"to frames of 160x90 \(it was calibrated at 320x180\)"):
        fit_calibration(rec, {"S000": (160, 90)}, source="calib")
    assert fit_calibration(rec, {"S000": (320, 180)}).cameras == (tracking,)   # the same size: as it is
    with pytest.raises(CalibrationInputError, match=r"calib: frame sizes given for camera\(s\) S009"):
        fit_calibration(record, {"S009": (160, 90)}, source="calib")


def test_cli_applies_a_stored_calibration_to_a_resampled_capture(calibrated, tmp_path):
    """``volcap import-calibration calibrations/full --format record --capture low``: the stored
    (solved) record, fitted to the low-resolution capture's frames, named imported-calibrations/low."""
    from typer.testing import CliRunner

    import flows.cli as cli
    from hardware.rig import load_rig
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture, CaptureCamera
    from volcap_core.store import ArtifactStore

    record, _ = calibrated
    s = ArtifactStore(str(tmp_path / "store"))
    s.set_ref("calibrations/full", s.put_record(record))
    cams = tuple(CaptureCamera(id=c, width=160, height=90, channels=("R", "G", "B"), source_encoding="linear",
                               frames=()) for c in CAMERAS)
    s.set_ref("captures/low", s.put_record(Capture(name="low", rig=load_rig("demo_scene"), fps=24.0,
                                                   start_timecode="00:00:00:00", frame_count=1, cameras=cams)))
    res = CliRunner().invoke(cli.app, ["import-calibration", "calibrations/full", "--format", "record",
                                       "--capture", "low", "--store", s.url, "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output.strip().splitlines()[-1])
    rec = s.get_record(s.get_ref("imported-calibrations/low"), Calibration)
    assert out["name"] == "imported-calibrations/low" and out["cameras"] == CAMERAS
    assert rec == fit_calibration(record, {c: (160, 90) for c in CAMERAS}, capture="low", frame_count=1, fps=24.0)
    res = CliRunner().invoke(cli.app, ["import-calibration", "calibrations/none", "--format", "record",
                                       "--capture", "low", "--store", s.url])
    assert isinstance(res.exception, cli.CommandError)
    assert "calibrations/none: no such calibration in the store" in str(res.exception)
