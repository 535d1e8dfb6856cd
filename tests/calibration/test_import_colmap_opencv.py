"""COLMAP and OpenCV calibrations in as Calibration records: a COLMAP model written by
colmap_export (text and binary) comes back with the same K, pose and lens; OpenCV YAML written by
cv2.FileStorage and JSON written here; errors name the file and the camera."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from volcap_core.calibration.colmap_export import export_colmap
from volcap_core.calibration.distortion import Distortion
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.geometry import look_at_rotation
from volcap_core.calibration.importers import calibration_from_colmap, calibration_from_opencv


def _rig():
    """Three cameras around the origin: (K, world_to_camera, w, h, lens or None)."""
    out = {}
    lenses = {"camA": None, "camB": Distortion.from_opencv([-0.12, 0.05, 0.001, -0.0005, 0.0]),
              "camC": Distortion.from_opencv([-0.1, 0.02, 0.0003, 0.0002, 0.01, 0.001, 0.0, 0.0])}
    for i, cid in enumerate(sorted(lenses)):
        a = 2 * np.pi * i / 3
        pos = np.array([3 * np.cos(a), 3 * np.sin(a), 1.5 + 0.1 * i])
        R = look_at_rotation(pos, (0, 0, 1.0))
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = R, -R @ pos
        K = np.array([[900.0 + 10 * i, 0, 639.3 - i], [0, 905.0 + 10 * i, 359.6 + i], [0, 0, 1]])
        out[cid] = (K, m, 1280, 720, lenses[cid]) if lenses[cid] is not None else (K, m, 1280, 720)
    return out


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_round_trip(tmp_path, binary):
    cams = _rig()
    export_colmap(tmp_path / "model", cams, binary=binary)
    rec = calibration_from_colmap(tmp_path / "model", "roundtrip", 12, 30.0)
    assert [c.id for c in rec.cameras] == sorted(cams)
    assert (rec.capture, rec.frame_count, rec.fps) == ("roundtrip", 12, 30.0)
    for cam in rec.cameras:
        K, m, w, h, *lens = cams[cam.id]
        assert (cam.width, cam.height) == (w, h)
        assert cam.intrinsics == pytest.approx((K[0, 0], K[1, 1], K[0, 2], K[1, 2]), abs=1e-9)
        assert np.asarray(cam.world_to_camera) == pytest.approx(m, abs=1e-9)
        want = lens[0].opencv() if lens else np.zeros(5)
        assert np.asarray(cam.distortion) == pytest.approx(want, abs=1e-12)


def test_colmap_scale_and_errors(tmp_path):
    cams = _rig()
    export_colmap(tmp_path / "m", cams)
    rec = calibration_from_colmap(tmp_path / "m", "mm", 1, 1.0, metres_per_unit=0.5)
    m = np.asarray(rec.camera("camA").world_to_camera)
    assert m[:3, 3] == pytest.approx(0.5 * cams["camA"][1][:3, 3])
    with pytest.raises(CalibrationInputError, match=r"empty: no cameras\.txt/\.bin"):
        (tmp_path / "empty").mkdir()
        calibration_from_colmap(tmp_path / "empty", "x", 1, 1.0)
    # a model COLMAP knows but the record cannot hold: named with its image
    text = (tmp_path / "m" / "cameras.txt").read_text().splitlines()
    i = next(k for k, line in enumerate(text) if line.startswith("1 "))
    parts = text[i].split()
    text[i] = " ".join([parts[0], "SIMPLE_RADIAL_FISHEYE", parts[2], parts[3], "900", "640", "360", "0.01"])
    (tmp_path / "m" / "cameras.txt").write_text("\n".join(text) + "\n")
    with pytest.raises(CalibrationInputError, match=r"image camA\.png \(camera camA\): COLMAP camera model SIMPLE_RADIAL_FISHEYE is not supported: a fisheye"):
        calibration_from_colmap(tmp_path / "m", "x", 1, 1.0)


def _write_yaml(path, cams, rodrigues=False, mm=False):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for cid, (K, m, w, h, *lens) in cams.items():
        fs.startWriteStruct(cid, cv2.FileNode_MAP)
        fs.write("camera_matrix", K)
        fs.write("distortion_coefficients", (lens[0].opencv() if lens else np.zeros(5)).reshape(1, -1))
        fs.write("R", cv2.Rodrigues(m[:3, :3])[0] if rodrigues else m[:3, :3])
        fs.write("t", m[:3, 3].reshape(3, 1) * (1000 if mm else 1))
        fs.write("image_width", w)
        fs.write("image_height", h)
        fs.endWriteStruct()
    fs.release()


@pytest.mark.parametrize("rodrigues", [False, True])
def test_opencv_yaml(tmp_path, rodrigues):
    cams = _rig()
    _write_yaml(tmp_path / "calib.yml", cams, rodrigues=rodrigues, mm=True)
    assert (tmp_path / "calib.yml").read_text().startswith("%YAML")   # "%YAML:1.0" from OpenCV 3, "%YAML 1.2" now
    rec = calibration_from_opencv((tmp_path / "calib.yml").read_bytes(), "yaml", 5, 25.0,
                                  source="calib.yml", metres_per_unit=0.001)
    for cam in rec.cameras:
        K, m, w, h, *lens = cams[cam.id]
        assert cam.intrinsics == pytest.approx((K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        assert np.asarray(cam.world_to_camera) == pytest.approx(m, abs=1e-9)
        assert np.asarray(cam.distortion) == pytest.approx(lens[0].opencv() if lens else np.zeros(5))
        assert (cam.width, cam.height) == (w, h)


def test_opencv_json_and_errors(tmp_path):
    cams = _rig()
    doc = {"cameras": {cid: {"K": K.tolist(), "dist": (list(lens[0].opencv()) if lens else [0, 0, 0, 0]),
                             "R": m[:3, :3].tolist(), "t": m[:3, 3].tolist(), "size": [w, h]}
                       for cid, (K, m, w, h, *lens) in cams.items()}}
    rec = calibration_from_opencv(json.dumps(doc).encode(), "json", 3, 24.0, source="calib.json")
    assert [c.id for c in rec.cameras] == sorted(cams)
    assert np.asarray(rec.camera("camC").distortion) == pytest.approx(cams["camC"][4].opencv())
    assert len(rec.camera("camC").distortion) == 8
    # one camera's file, named by its stem
    one = calibration_from_opencv(json.dumps(doc["cameras"]["camB"]).encode(), "one", 1, 1.0, source="/x/cam07.json")
    assert [c.id for c in one.cameras] == ["cam07"]

    bad = json.loads(json.dumps(doc))
    del bad["cameras"]["camB"]["t"]
    with pytest.raises(CalibrationInputError, match=r"calib\.json: camera camB: no t \(one of t, T"):
        calibration_from_opencv(json.dumps(bad).encode(), "j", 1, 1.0, source="calib.json")
    bad = json.loads(json.dumps(doc))
    bad["cameras"]["camA"]["dist"] = [0.1] * 6
    with pytest.raises(CalibrationInputError, match=r"calib\.json: camera camA: distortion: OpenCV distortion has 4, 5, 8, 12 or 14 coefficients .*got 6"):
        calibration_from_opencv(json.dumps(bad).encode(), "j", 1, 1.0, source="calib.json")
    bad = json.loads(json.dumps(doc))
    bad["cameras"]["camA"]["R"] = (2 * np.eye(3)).tolist()
    with pytest.raises(CalibrationInputError, match=r"calib\.json: camera camA: the rotation is not a proper rotation"):
        calibration_from_opencv(json.dumps(bad).encode(), "j", 1, 1.0, source="calib.json")
    with pytest.raises(CalibrationInputError, match=r"calib\.json: not JSON"):
        calibration_from_opencv(b"{oops", "j", 1, 1.0, source="calib.json")
    with pytest.raises(CalibrationInputError, match=r"calib\.json: frame_count and fps must be positive"):
        calibration_from_opencv(json.dumps(doc).encode(), "j", 0, 1.0, source="calib.json")
