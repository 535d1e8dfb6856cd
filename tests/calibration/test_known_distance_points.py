"""A known distance between named scene points (``volcap_core.calibration.scale``): two marks a
studio measured with a tape, given by their pixels in two or more static cameras, triangulated with
the calibrated cameras and used to scale a calibration without a lidar scan. Analytic cameras (a
ring of 8 looking at the stage, 320x180), no images: a fraction of a second.

The synthetic capture end to end (the flow, its ground truth): tests/test_capture_without_lidar.py.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from volcap_core.calibration.distortion import Distortion
from volcap_core.calibration.errors import KnownPointsError
from volcap_core.calibration.geometry import Similarity, camera_centre, look_at_rotation, pose_matrix
from volcap_core.calibration.scale import (KnownPoints, check_known_points, scale_to_known_points,
                                           triangulate_marks)
from volcap_core.calibration.sfm import Intrinsics
from volcap_core.calibration.static import StaticCalibration

W, H = 320, 180
K0 = np.array([[300.0, 0, 159.5], [0, 300.0, 89.5], [0, 0, 1]])
A = np.array([-0.8, -0.5, 0.0])
B = np.array([0.9, 0.7, 0.0])
C = np.array([0.2, 1.1, 0.9])


def _ring(n: int = 8, radius: float = 5.0) -> dict[str, np.ndarray]:
    out = {}
    for i in range(n):
        a = 2 * np.pi * i / n
        centre = np.array([radius * np.cos(a), radius * np.sin(a), 2.5])
        R = look_at_rotation(centre, np.array([0.0, 0.0, 1.0]))
        out[f"C{i}"] = pose_matrix(R, -R @ centre)
    return out


TRUE = _ring()
MOUNTS = {c: camera_centre(w) for c, w in TRUE.items()}


def _static(w2c: dict, raw: dict | None = None, reasons: dict | None = None) -> StaticCalibration:
    ids = sorted(w2c)
    return StaticCalibration(camera_ids=ids, K={c: K0.copy() for c in ids}, world_to_camera=dict(w2c),
                             size={c: (W, H) for c in ids}, model=None, stats={"frame": {"scale": 1.0}},
                             raw_intrinsics=raw or {}, reasons=reasons or {}, unregistered=sorted(reasons or {}))


def _pixel(X: np.ndarray, w2c: np.ndarray, distortion: Distortion | None = None) -> list[float]:
    x = w2c[:3, :3] @ X + w2c[:3, 3]
    n = x[:2] / x[2]
    if distortion is not None:
        n = distortion.distort(n[None])[0]
    return [float(K0[0, 0] * n[0] + K0[0, 2]), float(K0[1, 1] * n[1] + K0[1, 2])]


def _marks(X: np.ndarray, cams, w2c=TRUE, noise: float = 0.0, rng=None, distortion=None) -> dict:
    out = {}
    for c in cams:
        u, v = _pixel(X, w2c[c], distortion)
        if noise:
            u, v = u + rng.normal(0, noise), v + rng.normal(0, noise)
        out[c] = [u, v]
    return out


def _shrunk(factor: float) -> dict[str, np.ndarray]:
    """The true cameras in a world scaled by ``factor`` about the mounts' centroid (what mounts
    surveyed ``factor`` too small would give)."""
    c0 = np.mean(list(MOUNTS.values()), axis=0)
    T = Similarity(factor, np.eye(3), c0 - factor * c0)
    return {c: T.apply_pose(w) for c, w in TRUE.items()}


def test_two_marked_points_recover_the_scale_exactly():
    d = float(np.linalg.norm(A - B))
    known = KnownPoints(points={"A": _marks(A, ["C0", "C1", "C7"]), "B": _marks(B, ["C2", "C3"])}, distance_m=d)
    # a calibration read back from its record carries each camera's scene depths: metres, scaled too
    shrunk = replace(_static(_shrunk(0.97)), scene_depth={"C0": (0.97 * 3.0, 0.97 * 5.0, 0.97 * 8.0)})
    out = scale_to_known_points(shrunk, known, MOUNTS, has_scan=False)
    f = out.stats["frame"]
    assert f["scale_source"] == 2.0 and abs(f["known_points_scale"] - 1 / 0.97) < 1e-9
    assert np.allclose(out.scene_depth["C0"], (3.0, 5.0, 8.0), atol=1e-9)
    assert abs(f["known_points_triangulated_m"] - 0.97 * d) < 1e-9 and f["known_points_residual_max_m"] < 1e-9
    for c in TRUE:   # the cameras are back where they are
        assert np.allclose(out.world_to_camera[c], TRUE[c], atol=1e-9)
    assert f["mount_residual_max_m"] < 1e-9 and f["mount_outliers"] == 0
    pts = out.stats["known_points"]["points"]
    assert pts["A"]["cameras"] == 3 and pts["A"]["reprojection_max_px"] < 1e-6 and pts["A"]["angle_deg"] > 40


def test_marks_placed_to_a_pixel_give_the_scale_to_a_fraction_of_a_percent():
    rng = np.random.default_rng(0)
    d = float(np.linalg.norm(A - B))
    errs, sigmas = [], []
    for _ in range(20):
        known = KnownPoints(points={"A": _marks(A, ["C0", "C1", "C7"], noise=1.0, rng=rng),
                                    "B": _marks(B, ["C2", "C3", "C4"], noise=1.0, rng=rng)}, distance_m=d)
        f = scale_to_known_points(_static(_shrunk(1.02)), known, MOUNTS, has_scan=False).stats["frame"]
        errs.append(f["known_points_scale"] * 1.02 - 1)
        sigmas.append(f["known_points_sigma_m"] / d)
    # the reported 1σ (for marks placed to 1 px) matches the scatter of the scale. Measured: 0.91 %
    # rms against 1.14 % reported (2.1 m seen from 5-6 m at 300 px focal: 1 px is ~2 cm there)
    print("scale error rms %.4f %%, reported sigma %.4f %%" % (100 * np.sqrt(np.mean(np.square(errs))),
                                                             100 * np.mean(sigmas)))
    assert np.sqrt(np.mean(np.square(errs))) < 0.015
    assert 0.5 < np.sqrt(np.mean(np.square(errs))) / np.mean(sigmas) < 2.0


def test_several_distances_least_squares_and_their_residuals():
    dab, dbc = float(np.linalg.norm(A - B)), float(np.linalg.norm(B - C))
    known = KnownPoints(points={"A": _marks(A, ["C0", "C1"]), "B": _marks(B, ["C2", "C3"]),
                                "C": _marks(C, ["C3", "C4", "C5"])},
                        distances=(("A", "B", dab), ("B", "C", dbc * 1.01)))   # one tape reading 1 % long
    out = scale_to_known_points(_static(_shrunk(0.95)), known, MOUNTS, has_scan=False)
    f = out.stats["frame"]
    assert f["known_points_distances"] == 2.0
    rows = out.stats["known_points"]["distances"]
    assert set(rows) == {"A-B", "B-C"}
    # least squares between the two readings: neither exact, both within the 1 % disagreement
    assert 0 < f["known_points_residual_max_m"] < 0.01 * dbc
    assert 1 / 0.95 < f["known_points_scale"] < 1.01 / 0.95


def test_with_a_scan_the_distance_is_only_checked():
    d = float(np.linalg.norm(A - B))
    known = KnownPoints(points={"A": _marks(A, ["C0", "C1"]), "B": _marks(B, ["C2", "C3"])}, distance_m=d + 0.01)
    out = scale_to_known_points(_static(TRUE), known, MOUNTS, has_scan=True)
    f = out.stats["frame"]
    assert "scale_source" not in f and abs(f["known_points_residual_max_m"] - 0.01) < 1e-9
    assert all(np.array_equal(out.world_to_camera[c], TRUE[c]) for c in TRUE)


def test_a_distorted_cameras_marks_are_undistorted_through_its_lens():
    lens = Distortion("RADIAL", (0.12, -0.02))
    raw = {c: Intrinsics(300.0, 300.0, 159.5, 89.5, W, H, lens) for c in ("C0", "C1")}
    d = float(np.linalg.norm(A - B))
    known = KnownPoints(points={"A": _marks(A, ["C0", "C1"], distortion=lens), "B": _marks(B, ["C2", "C3"])},
                        distance_m=d)
    out = scale_to_known_points(_static(TRUE, raw), known, MOUNTS, has_scan=False)
    assert abs(out.stats["frame"]["known_points_scale"] - 1) < 1e-9
    # read as pinhole pixels, the same marks give another distance
    plain = scale_to_known_points(_static(TRUE), known, MOUNTS, has_scan=False)
    assert abs(plain.stats["frame"]["known_points_scale"] - 1) > 1e-3


def test_bad_json_names_the_field():
    two = {"C0": [10, 10], "C1": [20, 20]}
    cases = [({"points": {"A": {"C0": [1, 2]}, "B": two}, "distance_m": 1.0}, "point A is marked in 1 camera"),
             ({"points": {"A": two, "B": two, "C": two}, "distance_m": 1.0}, "exactly two points"),
             ({"points": {"A": two, "B": two}}, "either distance_m"),
             ({"points": {"A": two, "B": two}, "distances": [["A", "D", 1.0]]}, "point(s) D"),
             ({"points": {"A": two, "B": two}, "distance_m": -1.0}, "distance_m"),
             ({"points": {"A": two, "B": two}, "distance_m": 1.0, "colour": 1}, "colour")]
    for doc, words in cases:
        with pytest.raises(KnownPointsError) as err:
            KnownPoints.parse(doc, "marks.json")
        assert str(err.value).startswith("marks.json: ") and words in str(err.value), (words, str(err.value))


def test_bad_marks_name_the_point_and_the_camera():
    d = float(np.linalg.norm(A - B))
    good_b = _marks(B, ["C2", "C3"])

    def fails(points, words, static=None, **kw):
        known = KnownPoints(points=points, distance_m=d, **kw)
        with pytest.raises(KnownPointsError) as err:
            scale_to_known_points(static or _static(TRUE), known, MOUNTS, has_scan=False)
        assert all(w in str(err.value) for w in words), (words, str(err.value))
        return str(err.value)

    # a pixel outside the image
    fails({"A": {"C0": [400.0, 20.0], "C1": _marks(A, ["C1"])["C1"]}, "B": good_b},
          ["point A in camera C0", "(400, 20)", "outside its 320x180 image"])
    # a camera that is not calibrated, and one that was left out (then A has one camera left)
    fails({"A": {**_marks(A, ["C0"]), "C9": [100.0, 100.0]}, "B": good_b},
          ["point A", "camera C9", "not a calibrated static camera"])
    left = _static({c: w for c, w in TRUE.items() if c != "C1"}, reasons={"C1": "0 observations in the sparse SfM"})
    fails({"A": _marks(A, ["C0", "C1"]), "B": good_b},
          ["point A is seen in 1 calibrated camera(s) (C0)", "C1 was left out of the calibration (0 observations"],
          static=left)
    # one mark 15 px off among four: the camera is named
    marks = _marks(A, ["C0", "C1", "C6", "C7"])
    marks["C6"][0] += 15.0
    fails({"A": marks, "B": good_b}, ["point A", "marks disagree", "in C6"])
    # a point behind a camera: two cameras facing each other, marks of a point 2 m behind E0 (the
    # image centre in E0, its mirror image) and in front of E1
    facing = {}
    for cid, pos, target in (("E0", (0.0, 0.0, 1.5), (10.0, 0.0, 1.5)), ("E1", (10.0, 0.5, 1.5), (0.0, 0.5, 1.5))):
        R = look_at_rotation(np.array(pos), np.array(target))
        facing[cid] = pose_matrix(R, -R @ np.array(pos))
    behind = np.array([-2.0, 0.0, 1.5])
    both = {**TRUE, **facing}
    known = KnownPoints(points={"A": {c: _pixel(behind, facing[c]) for c in facing}, "B": good_b}, distance_m=d)
    with pytest.raises(KnownPointsError, match=r"point A triangulates behind camera\(s\) E0 \(depth -2.00 m\)"):
        scale_to_known_points(_static(both), known, {c: camera_centre(w) for c, w in both.items()}, has_scan=False)
    # rays meeting at a small angle: two cameras 5 cm apart
    near = dict(TRUE)
    near["C0b"] = pose_matrix(TRUE["C0"][:3, :3], TRUE["C0"][:3, 3] + np.array([0.05, 0.0, 0.0]))
    mounts = {**MOUNTS, "C0b": camera_centre(near["C0b"])}
    known = KnownPoints(points={"A": _marks(A, ["C0", "C0b"], w2c=near), "B": good_b}, distance_m=d)
    with pytest.raises(KnownPointsError, match=r"point A is ill-conditioned: its rays from C0, C0b meet at 0\.\d+°"):
        scale_to_known_points(_static(near), known, mounts, has_scan=False)
    # two points a centimetre apart: the distance is determined to a few % only
    A2 = A + np.array([0.01, 0.0, 0.0])
    fails({"A": _marks(A, ["C0", "C1"]), "B": _marks(A2, ["C2", "C3"])}, ["distance A-B is ill-conditioned"])


def test_marks_in_a_tracking_or_unknown_camera_are_refused_before_calibrating():
    two = {**_marks(A, ["C0"]), "T001": [100.0, 100.0]}
    known = KnownPoints(points={"A": two, "B": _marks(B, ["C2", "C3"])}, distance_m=1.0)
    with pytest.raises(KnownPointsError, match="camera T001, a tracking camera"):
        check_known_points(known, sorted(TRUE), ["T001"])
    with pytest.raises(KnownPointsError, match="camera T001, not a static camera of the capture"):
        check_known_points(known, sorted(TRUE), [])


def test_triangulated_marks_report_their_geometry():
    known = KnownPoints(points={"A": _marks(A, ["C0", "C2"]), "B": _marks(B, ["C2", "C3"])}, distance_m=1.0)
    marks = triangulate_marks(known, {c: K0 for c in TRUE}, TRUE, {c: (W, H) for c in TRUE})
    assert np.allclose(marks["A"].position, A, atol=1e-9) and np.allclose(marks["B"].position, B, atol=1e-9)
    assert 40 < marks["A"].angle_deg < 100 and marks["A"].depth_m["C0"] > 4
    assert np.all(np.linalg.eigvalsh(marks["A"].covariance) > 0)


# --------------------------------------------------------------------------- through the static step
# ``static_step.calibrate_static_step`` checks and applies the known points for both the calibrate-static
# task and ``pipeline.calibrate_capture``. The SfM is replaced by the analytic ring (a calibration
# shrunk by 3 %, what mounts surveyed 3 % short give), the frames are blank: no images are matched.

class _Role:
    def __init__(self, tracks: bool):
        self.tracks, self.value = tracks, ("tracking" if tracks else "static")


class _Camera:
    def __init__(self, position, tracks: bool = False):
        self.role = _Role(tracks)
        self.mount = type("Mount", (), {"position_m": tuple(float(v) for v in position)})()


class _Rig:
    """What the static step and the record read of a rig: roles, mounts, the stage size."""

    stage_size_m = (8.0, 8.0, 4.0)

    def __init__(self, trackers=()):
        self.cameras = {c: _Camera(MOUNTS[c]) for c in TRUE}
        self.cameras.update({t: _Camera((0.0, 6.0, 1.5), tracks=True) for t in trackers})

    def camera(self, cid):
        return self.cameras[cid]


def _blank(camera_id: str, take_index: int) -> np.ndarray:
    return np.zeros((H, W, 3), np.float32)


@pytest.fixture
def shrunk_sfm(monkeypatch):
    """The static step's SfM replaced by the analytic cameras shrunk by 3 %; records its calls."""
    from volcap_core.calibration import static_step

    calls = []

    def fake(images, rig, scan, **kw):
        calls.append(sorted(images))
        return _static(_shrunk(0.97))

    monkeypatch.setattr(static_step, "calibrate_static_cameras", fake)
    return calls


def _known() -> KnownPoints:
    d = float(np.linalg.norm(A - B))
    return KnownPoints(points={"A": _marks(A, ["C0", "C1", "C7"]), "B": _marks(B, ["C2", "C3"])}, distance_m=d)


def test_calibrate_capture_scales_to_known_points(shrunk_sfm):
    from volcap_core.calibration.pipeline import calibrate_capture

    ids = sorted(TRUE)
    plain = calibrate_capture(_blank, _Rig(), ids, 2, 24.0, capture_name="cap-k", encoder={}, scan=None)
    res = calibrate_capture(_blank, _Rig(), ids, 2, 24.0, capture_name="cap-k", encoder={}, scan=None,
                            known_points=_known())
    assert shrunk_sfm == [ids, ids]
    # without the marks the calibration stays 3 % small; with them the true cameras come back
    assert abs(np.linalg.norm(camera_centre(plain.static.world_to_camera["C0"]) - MOUNTS["C0"]) - 0.15) < 1e-6
    for c in ids:
        assert np.allclose(res.static.world_to_camera[c], TRUE[c], atol=1e-9), c
        assert np.allclose(res.record.camera(c).world_to_camera, TRUE[c], atol=1e-9), c
    assert res.static.stats["frame"]["scale_source"] == 2.0
    assert abs(res.record.stats["static_frame_known_points_scale"] - 1 / 0.97) < 1e-9
    assert set(res.static.stats["known_points"]["points"]) == {"A", "B"}


def test_calibrate_capture_refuses_bad_known_points_before_calibrating(shrunk_sfm):
    from volcap_core.calibration.pipeline import CalibrationOptions, calibrate_capture
    from volcap_core.calibration.errors import CalibrationInputError
    from volcap_core.calibration.static import StaticCalibrationOptions

    ids = sorted(TRUE)
    bad = KnownPoints(points={"A": {**_marks(A, ["C0"]), "T001": [100.0, 100.0]}, "B": _marks(B, ["C2", "C3"])},
                      distance_m=1.0)
    with pytest.raises(CalibrationInputError, match=r"capture cap-k: known points: point A is marked in camera "
                                                    r"T001, a tracking camera"):
        calibrate_capture(_blank, _Rig(["T001"]), ids + ["T001"], 2, 24.0, capture_name="cap-k", encoder={},
                          scan=None, known_points=bad)
    both = CalibrationOptions(static=StaticCalibrationOptions(known_distance=("C0", "C4", 10.0)))
    with pytest.raises(CalibrationInputError, match="capture cap-k: give either a known distance"):
        calibrate_capture(_blank, _Rig(), ids, 2, 24.0, capture_name="cap-k", encoder={}, scan=None,
                          options=both, known_points=_known())
    assert shrunk_sfm == []


def test_tracking_cameras_without_a_scan_are_refused_with_known_points(shrunk_sfm):
    """Known points scale the static cameras; the tracking cameras register against the static
    reference lifted onto a scan, which known points do not replace: refused, naming the capture."""
    from volcap_core.calibration.errors import CalibrationInputError
    from volcap_core.calibration.pipeline import calibrate_capture

    ids = sorted(TRUE) + ["T001"]
    with pytest.raises(CalibrationInputError, match=r"capture cap-k has tracking cameras \(T001\) but no lidar scan"
                                                    r".*known points scale the static cameras only"):
        calibrate_capture(_blank, _Rig(["T001"]), ids, 2, 24.0, capture_name="cap-k", encoder={}, scan=None,
                          known_points=_known())
    assert shrunk_sfm == []


def test_the_static_reference_is_built_from_the_scaled_cameras(shrunk_sfm, monkeypatch):
    """The static step applies the known points before it builds the static reference, so the
    reference and the static cameras it is handed back with are in one frame (with a scan nothing
    moves; the step is checked here with its no-scan refusal lifted)."""
    from volcap_core.calibration import static_step
    from volcap_core.calibration.tracking.observe import StaticReference

    seen = {}

    def reference(images, K, world_to_camera, scan, **kw):
        seen.update(world_to_camera)
        return StaticReference(np.zeros((0, 3)), np.zeros((0, 128), np.uint8))

    monkeypatch.setattr(static_step, "build_static_reference", reference)
    sentinel = object()                                  # a "scan" the step only hands on
    monkeypatch.setattr(static_step.scale, "apply_to_static_step",
                        lambda *a, has_scan, **kw: static_step.scale.scale_to_known_points(
                            a[2], a[3], MOUNTS, has_scan=False))   # scale as without a scan
    step = static_step.calibrate_static_step("cap-k", _Rig(["T001"]), sorted(TRUE), ["T001"], 2, _blank, sentinel,
                                       known_points=_known())
    assert step.reference is not None
    for c in TRUE:
        assert np.allclose(seen[c], step.calibration.world_to_camera[c]) and np.allclose(seen[c], TRUE[c], atol=1e-9)
