"""Lenses as studios write them: OpenCV's distCoeffs vectors (4, 5, 8, 12, 14 values) and COLMAP's
camera models enter a rig as they are, and project and undistort exactly as OpenCV and COLMAP do;
what volcap cannot apply is refused by name; an invalid rig is one line naming the file, the
camera and the reason, through the `volcap` command too."""

from __future__ import annotations

import json

import cv2  # before pycolmap (docs: a zlib clash the other way round)
import numpy as np
import pytest
from pydantic import ValidationError

from hardware.lens_models import COLMAP_MODELS, COLMAP_PIXEL_OFFSET, COLMAP_REFUSED
from hardware.rig import Rig, load_rig
from volcap_core.calibration.distortion import Distortion, from_colmap_camera
from volcap_core.calibration.sfm import Intrinsics

W, H = 1280, 720
K = np.array([[905.3, 0.0, 647.2], [0.0, 903.9, 356.8], [0.0, 0.0, 1.0]])
#: a webcam's lens (the issue's 4 webcams at 1280x720: barrel, a little decentring)
WEBCAM = [-0.31, 0.12, 0.0007, -0.0005, -0.021]
#: OpenCV's vectors of each length, as calibrateCamera writes them (8: CALIB_RATIONAL_MODEL;
#: 12 / 14: CALIB_THIN_PRISM_MODEL / CALIB_TILTED_MODEL with those terms fixed at 0)
VECTORS = {
    4: WEBCAM[:4],
    5: WEBCAM,
    8: [0.42, -0.11, 0.0007, -0.0005, 0.013, 0.71, -0.05, 0.021],
    12: [0.42, -0.11, 0.0007, -0.0005, 0.013, 0.71, -0.05, 0.021, 0.0, 0.0, 0.0, 0.0],
    14: WEBCAM + [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
}


def _camera(cam_id: str = "C0", **intrinsics) -> dict:
    cam = {"id": cam_id, "role": "static", "lens": {"focal_min_mm": 3.0, "focal_max_mm": 6.0},
           "sensor": {"width_mm": 6.4, "height_mm": 3.6, "width_px": W, "height_px": H},
           "mount": {"kind": "tripod", "position_m": [3.0, 0.0, 1.5], "look_at_m": [0.0, 0.0, 1.0]},
           "nominal_focal_mm": 4.5}
    if intrinsics:
        cam["intrinsics"] = intrinsics
    return cam


def _rig(*cameras: dict, **extra) -> dict:
    return {"name": "webcams", "kind": "scene", "fps": 30.0, "stage_size_m": [4.0, 4.0, 2.5],
            "lighting": {"description": "office"}, "cameras": list(cameras), **extra}


def _opencv_intrinsics(coeffs) -> dict:
    return {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "opencv": list(coeffs)}


#: cv2.undistortPoints iterated to convergence (its default stops after 5 iterations)
_TIGHT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


def _pixels_across_the_image(n: int = 15) -> np.ndarray:
    """[n², 2] pixels on a grid from corner to corner of the image (float64)."""
    u, v = np.meshgrid(np.linspace(0, W - 1, n), np.linspace(0, H - 1, n))
    return np.stack([u.ravel(), v.ravel()], -1)


def _rays(dist: np.ndarray) -> np.ndarray:
    """[N, 3] camera-frame points (depths 1.5-6 m) whose OpenCV projection covers the image."""
    xy = cv2.undistortPoints(_pixels_across_the_image()[:, None], K, dist, None, None, criteria=_TIGHT)[:, 0]
    z = np.linspace(1.5, 6.0, len(xy))
    return np.concatenate([xy * z[:, None], z[:, None]], axis=1)


def test_no_colmap_model_is_both_accepted_and_refused():
    assert not set(COLMAP_MODELS) & set(COLMAP_REFUSED)


@pytest.mark.parametrize("length", sorted(VECTORS))
def test_opencv_vector_projects_and_undistorts_as_opencv(length):
    coeffs = VECTORS[length]
    rig = Rig.model_validate(_rig(_camera(**_opencv_intrinsics(coeffs))))
    intr = Intrinsics.from_rig(rig, "C0")
    dist = np.asarray(coeffs, np.float64)
    # OpenCV's projection of points across the whole image
    X = _rays(dist)
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, dist)
    assert np.abs(intr.project(X) - ref[:, 0]).max() < 1e-6
    # and its inverse: pixels across the image -> the pinhole's pixels
    uv = _pixels_across_the_image()
    ref_u = cv2.undistortPoints(uv[:, None], K, dist, None, K, criteria=_TIGHT)[:, 0]
    assert np.abs(intr.undistort_pixels(uv) - ref_u).max() < 1e-6
    # what a calibration record stores (Distortion.opencv) applies the same lens in OpenCV
    again, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, intr.distortion.opencv())
    assert np.abs(again - ref).max() < 1e-9


def test_opencv_vector_maps_onto_the_smallest_exact_model():
    def model(coeffs):
        return Rig.model_validate(_rig(_camera(**_opencv_intrinsics(coeffs)))).cameras[0].intrinsics

    m = model(WEBCAM)
    assert (m.model, m.params) == ("FULL_OPENCV", tuple(WEBCAM) + (0.0, 0.0, 0.0))
    m = model(WEBCAM[:4] + [0.0])            # k3 fixed at 0 (CALIB_FIX_K3): OpenCV's 4 parameters
    assert (m.model, m.params) == ("OPENCV", tuple(WEBCAM[:4]))
    assert model([-0.2, 0.03, 0.0, 0.0]).model == "RADIAL"
    assert model([]).model == "PINHOLE"
    assert Distortion.from_opencv(VECTORS[12]) == Distortion("FULL_OPENCV", tuple(VECTORS[8]))


def test_rig_with_an_opencv_lens_serialises_as_model_and_params():
    rig = Rig.model_validate(_rig(_camera(**_opencv_intrinsics(WEBCAM))))
    dumped = rig.model_dump(mode="json")
    assert "opencv" not in dumped["cameras"][0]["intrinsics"]
    assert dumped["cameras"][0]["intrinsics"]["model"] == "FULL_OPENCV"
    assert Rig.model_validate(dumped) == rig
    # a lens group takes the same form
    group = _rig(_camera("C0"), _camera("C1"), lens_groups={"webcam": _opencv_intrinsics(WEBCAM)})
    for cam in group["cameras"]:
        cam["lens_group"] = "webcam"
    assert Rig.model_validate(group).measured_intrinsics("C1") == rig.cameras[0].intrinsics


@pytest.mark.parametrize("coeffs, message", [
    (VECTORS[8] + [0.0012, 0.0, 0.0, 0.0], r"camera C0: intrinsics: OpenCV distortion term s1 = 0\.0012 \(thin prism\) "
                                           r"is not applied"),
    (VECTORS[8] + [0.0, 0.0, 0.0, -3e-4], r"term s4 = -0\.0003 \(thin prism\)"),
    (VECTORS[14][:13] + [0.002], r"camera C0: intrinsics: OpenCV distortion term tauY = 0\.002 \(sensor tilt\)"),
    (WEBCAM + [0.1], r"camera C0: intrinsics: OpenCV distortion has 4, 5, 8, 12 or 14 coefficients .*got 6"),
    ([0.1, float("nan"), 0, 0], r"camera C0: intrinsics: OpenCV distortion coefficients: non-finite"),
])
def test_opencv_terms_volcap_cannot_apply_are_refused_by_name(coeffs, message):
    with pytest.raises(ValidationError, match=message):
        Rig.model_validate(_rig(_camera(**_opencv_intrinsics(coeffs))))
    with pytest.raises(ValueError, match=message.split("intrinsics: ")[-1]):
        Distortion.from_opencv(coeffs)


def test_opencv_form_refuses_a_second_distortion():
    both = {**_opencv_intrinsics(WEBCAM), "model": "OPENCV", "params": WEBCAM[:4]}
    with pytest.raises(ValidationError, match="camera C0: intrinsics: give the distortion as opencv or as model"):
        Rig.model_validate(_rig(_camera(**both)))
    with pytest.raises(ValidationError, match="camera C0: intrinsics: OpenCV distortion coefficients: expected a list "
                                              "of numbers, got 3.0"):
        Rig.model_validate(_rig(_camera(**{**_opencv_intrinsics([]), "opencv": 3.0})))


def _zoom_rig(table: dict) -> dict:
    cam = _camera("Z0")
    cam.update(role="tracking-landscape", lens={"focal_min_mm": 4.0, "focal_max_mm": 12.0}, nominal_focal_mm=6.0,
               zoom_intrinsics=table)
    return _rig(cam)


def test_zoom_lens_table_takes_opencv_vectors_in_one_model():
    wide, tele = [-0.31, 0.12, 0.0007, -0.0005, -0.021], [0.05, 0.0, 0.0004, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    table = {"samples": [{"focal_mm": 4.0, "opencv": wide, "cx": 641.0, "cy": 359.0},
                         {"focal_mm": 12.0, "opencv": tele, "cx": 640.0, "cy": 360.0}]}
    z = Rig.model_validate(_zoom_rig(table)).camera("Z0").zoom_intrinsics
    # the wide end needs k3: the whole table is FULL_OPENCV, each sample the same lens as its vector
    assert z.model == "FULL_OPENCV"
    assert Distortion(z.model, z.samples[0].params).opencv_full() == Distortion.from_opencv(wide).opencv_full()
    assert Distortion(z.model, z.samples[1].params).opencv_full() == Distortion.from_opencv(tele).opencv_full()
    assert z.samples[1].cx == 640.0
    # a table's own model holds them when it can, and is refused by name when it cannot
    assert Rig.model_validate(_zoom_rig({**table, "model": "FULL_OPENCV"})).camera("Z0").zoom_intrinsics == z
    with pytest.raises(ValidationError, match=r"camera Z0: zoom_intrinsics: the sample at 4.0 mm: distortion model "
                                              r"OPENCV has no k3: these OpenCV coefficients need FULL_OPENCV"):
        Rig.model_validate(_zoom_rig({**table, "model": "OPENCV"}))
    prism = {"samples": [{"focal_mm": 4.0, "opencv": wide}, {"focal_mm": 12.0, "opencv": tele[:8] + [0.0, 0.0, 2e-3, 0.0]}]}
    with pytest.raises(ValidationError, match=r"camera Z0: zoom_intrinsics: the sample at 12.0 mm: OpenCV distortion "
                                              r"term s3 = 0.002 \(thin prism\)"):
        Rig.model_validate(_zoom_rig(prism))
    mixed = {"samples": [{"focal_mm": 4.0, "opencv": wide}, {"focal_mm": 12.0, "params": [0.05, 0.0, 0.0004, 0.0]}]}
    with pytest.raises(ValidationError, match="camera Z0: zoom_intrinsics: give every sample's distortion as opencv"):
        Rig.model_validate(_zoom_rig(mixed))


#: COLMAP cameras (cameras.txt's model and params, COLMAP pixels) of the webcam's lens
COLMAP_CAMERAS = {
    "SIMPLE_PINHOLE": [905.3, 647.7, 357.3],
    "PINHOLE": [905.3, 903.9, 647.7, 357.3],
    "SIMPLE_RADIAL": [905.3, 647.7, 357.3, -0.21],
    "RADIAL": [905.3, 647.7, 357.3, -0.31, 0.12],
    "OPENCV": [905.3, 903.9, 647.7, 357.3, -0.31, 0.12, 0.0007, -0.0005],
    "FULL_OPENCV": [905.3, 903.9, 647.7, 357.3, 0.42, -0.11, 0.0007, -0.0005, 0.013, 0.71, -0.05, 0.021],
}


def test_every_colmap_model_volcap_applies_is_tested():
    assert set(COLMAP_CAMERAS) == set(COLMAP_MODELS)


@pytest.mark.parametrize("name", sorted(COLMAP_CAMERAS))
def test_colmap_camera_projects_as_colmap(name):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is not installed")
    params = COLMAP_CAMERAS[name]
    rig = Rig.model_validate(_rig(_camera(colmap={"model": name, "params": params})))
    intr = Intrinsics.from_rig(rig, "C0")
    cam = pycolmap.Camera(model=name, width=W, height=H, params=params)
    X = _rays(np.zeros(5))
    colmap_px = cam.img_from_cam(X) - COLMAP_PIXEL_OFFSET     # COLMAP pixels -> OpenCV's
    assert np.abs(intr.project(X) - colmap_px).max() < 1e-6
    # pycolmap's own camera name (CameraModelId.NAME) reads the same
    assert from_colmap_camera(str(cam.model), cam.params)[1] == intr.distortion


@pytest.mark.parametrize("name", ["OPENCV_FISHEYE", "FOV", "THIN_PRISM_FISHEYE", "SIMPLE_DIVISION", "EUCM"])
def test_colmap_models_volcap_cannot_apply_are_refused_by_name(name):
    with pytest.raises(ValidationError, match=f"camera C0: intrinsics: COLMAP camera model {name} is not supported: "):
        Rig.model_validate(_rig(_camera(colmap={"model": name, "params": [900.0, 640.0, 360.0, 0.1]})))


def test_colmap_camera_with_the_wrong_parameter_count_or_a_second_focal_is_refused():
    with pytest.raises(ValidationError, match=r"camera C0: intrinsics: COLMAP camera model OPENCV takes 8 parameters "
                                              r"\(fx, fy, cx, cy, k1, k2, p1, p2\), got 5"):
        Rig.model_validate(_rig(_camera(colmap={"model": "OPENCV", "params": COLMAP_CAMERAS["RADIAL"]})))
    with pytest.raises(ValidationError, match="give colmap without fx"):
        Rig.model_validate(_rig(_camera(fx=900.0, colmap={"model": "PINHOLE", "params": COLMAP_CAMERAS["PINHOLE"]})))


# --------------------------------------------------------------------------- the one-line error

def test_invalid_rig_file_is_one_line_naming_file_camera_and_reason(tmp_path):
    bad = _rig(_camera("C0", fx=905.3, fy=903.9, cx=647.2, cy=356.8, model="OPENCV", params=WEBCAM),
               _camera("C1", **_opencv_intrinsics(VECTORS[8] + [0.001, 0.0, 0.0, 0.0])),
               _camera("C2", **{**_opencv_intrinsics(WEBCAM), "fx": -1.0}),
               _camera("C3", **{**_opencv_intrinsics(WEBCAM), "cx": 5000.0}),
               _camera("C4", **{**_opencv_intrinsics(WEBCAM), "fy": "wide"}))
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError) as err:
        load_rig(path)
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(f"{path}: invalid rig: camera C0: intrinsics: distortion model OPENCV takes 4 parameters "
                           f"(k1, k2, p1, p2), got 5: OpenCV's distCoeffs vector")
    assert "; camera C1: intrinsics: OpenCV distortion term s1 = 0.001 (thin prism)" in text
    assert "; camera C2: intrinsics.fx: Input should be greater than 0 (got -1.0)" in text
    assert text.endswith(" (and 2 more)")


def test_volcap_ingest_of_a_rig_with_an_invalid_lens_is_one_error_line(prefect_api, tmp_path):
    from tests.test_cli_errors import cli_env, one_error_line, volcap
    from prefect.settings import PREFECT_API_URL

    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "rig.json").write_text(json.dumps(_rig(_camera("C0", **_opencv_intrinsics(VECTORS[8] + [0.0025, 0.0, 0.0, 0.0])))))
    (cap / "capture.json").write_text(json.dumps({
        "format": "volcap-capture/1", "name": "webcams", "rig": "rig.json", "fps": 30,
        "take": {"start_timecode": "01:00:00:00", "frame_count": 1},
        "cameras": [{"id": "C0", "path": "C0", "start_timecode": "01:00:00:00", "encoding": "linear"}]}))
    res = volcap("ingest", str(cap), "--store", str(tmp_path / "store"),
                 env=cli_env(PREFECT_API_URL=PREFECT_API_URL.value()))
    line = one_error_line(res)
    assert f"{cap / 'rig.json'}: invalid rig: camera C0: intrinsics: OpenCV distortion term s1 = 0.0025 (thin prism) " \
           f"is not applied by volcap" in line
