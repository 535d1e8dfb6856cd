"""Qualisys XML import on Pose2Sim's real calibration (skipped without ../shared): units, the
axis convention checked by reprojection of hand-picked correspondences, and the 1080-wide
re-encodes of SinglePerson's cam01/cam02; plus errors naming the file and the camera."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.importers import QUALISYS_TO_OPENCV, calibration_from_qualisys, fit_to_frames

QCA = "real/pose2sim/Demo_SinglePerson/calibration/Calib.qca.txt"

# Static points of the treadmill seen by all four cameras, picked by hand (pixels of the 1088x1920
# images calibration/extrinsics/camNN_ext.png, which are SinglePerson's own frames for cam03/cam04:
# SIFT registers them to the video's first frame with the identity): each point found on a 4x
# zoomed crop with a pixel ruler; P1/P2: the centre of the top opening of the two black posts at
# the treadmill's end (P1 is the one with the cable in all four views); B1/B2: the nut of the
# bolted bracket nearest each post on the treadmill's long edges. About +-3 px each.
PICKS = {
    "P1": {"cam01": (673.3, 1522.3), "cam02": (275.0, 1319.7), "cam03": (259.9, 970.0), "cam04": (828.9, 860.6)},
    "P2": {"cam01": (954.7, 1429.0), "cam02": (635.5, 1347.2), "cam03": (60.0, 1059.5), "cam04": (608.1, 920.7)},
    "B1": {"cam01": (280.9, 1362.9), "cam02": (286.1, 1215.7), "cam03": (531.6, 1076.6), "cam04": (932.4, 1056.2)},
    "B2": {"cam01": (792.3, 1277.7), "cam02": (808.2, 1268.6), "cam03": (140.5, 1268.4), "cam04": (485.9, 1134.2)},
}

# SinglePerson's cam01/cam02 videos (1080x1920) against the same cameras' 1088x1920 extrinsics
# images: SIFT matches (ratio 0.7) and cv2.estimateAffine2D (RANSAC, 1 px) on the video's first
# frame gave u' = a u + b, v' = c v + d with these (a, b, c, d): a uniform scale, not a crop.
MEASURED_RESAMPLE = {"cam01": (0.9927, 0.11, 0.9926, 7.07), "cam02": (0.9927, -0.24, 0.9924, 7.08)}


@pytest.fixture
def qca(shared_data):
    path = shared_data / QCA
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    return path


def _cv_camera(cam):
    fx, fy, cx, cy = cam.intrinsics
    m = np.asarray(cam.world_to_camera)
    return m[:3, :3], m[:3, 3], np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), np.asarray(cam.distortion)


def _leave_one_out_errors(cams: dict) -> np.ndarray:
    """Each pick triangulated (linear, undistorted rays) from the other views of the same point,
    reprojected (with distortion) into the left-out view: the error in pixels."""
    errs = []
    for obs in PICKS.values():
        for c in obs:
            rows = []
            for o in obs:
                if o == c:
                    continue
                R, t, K, d = cams[o]
                x = cv2.undistortPoints(np.float64([[obs[o]]]), K, d).reshape(2)
                P = np.hstack([R, t[:, None]])
                rows += [x[0] * P[2] - P[0], x[1] * P[2] - P[1]]
            X = np.linalg.svd(np.array(rows))[2][-1]
            X = X[:3] / X[3]
            R, t, K, d = cams[c]
            uv, _ = cv2.projectPoints(X[None], cv2.Rodrigues(R)[0], t, K, d)
            errs.append(np.linalg.norm(uv.ravel() - obs[c]) if (R @ X + t)[2] > 0 else np.inf)
    return np.array(errs)


def test_units_and_cameras(qca):
    rec = calibration_from_qualisys(qca.read_bytes(), "pose2sim-single", 100, 60.0, source=str(qca))
    assert [c.id for c in rec.cameras] == ["cam01", "cam02", "cam03", "cam04"]
    cam01 = rec.camera("cam01")
    assert (cam01.width, cam01.height) == (1088, 1920)
    fx, fy, cx, cy = cam01.intrinsics
    assert fx == pytest.approx(107599.671875 / 64) and fx == pytest.approx(1681.2, abs=0.1)
    assert (cx, cy) == pytest.approx((34110.316406 / 64, 60680.792969 / 64))
    assert cam01.distortion == pytest.approx((-0.046183, 0.139983, 0.000608, 0.00069, 0.0))
    m = np.asarray(cam01.world_to_camera)
    centre = -m[:3, :3].T @ m[:3, 3]
    assert centre == pytest.approx([1.4602323709, -1.9091590482, 1.8965058524], abs=1e-9)   # mm -> m
    assert (rec.frame_count, rec.fps, rec.capture) == (100, 60.0, "pose2sim-single")
    assert all(c.static for c in rec.cameras) and not rec.unregistered


def test_axis_convention_by_reprojection(qca):
    """The importer's convention puts every pick, triangulated from the three other views, within
    26 px of where it was picked (median ~16 px: a per-camera offset of 10-20 px that the picks'
    geometry shows, the calibration being older than these frames); the other readings of the
    same numbers (transposed, image turned 180 degrees, Qualisys axes taken as OpenCV's) miss by
    hundreds of pixels or put the points behind the cameras."""
    rec = calibration_from_qualisys(qca.read_bytes(), "pose2sim-single", 1, 60.0, source=str(qca))
    cams = {c.id: _cv_camera(c) for c in rec.cameras}
    errs = _leave_one_out_errors(cams)
    assert np.median(errs) < 20 and errs.max() < 30, errs

    raw = {cid: QUALISYS_TO_OPENCV @ R for cid, (R, *_) in cams.items()}   # r_ij as written in the file
    centres = {cid: -R.T @ t for cid, (R, t, *_) in cams.items()}
    others = {"transposed": lambda r: QUALISYS_TO_OPENCV @ r.T,
              "turned 180 degrees": lambda r: np.diag([-1.0, 1.0, -1.0]) @ r,
              "Qualisys axes as OpenCV's": lambda r: r,
              "transposed, as OpenCV's": lambda r: r.T}
    for name, f in others.items():
        alt = {}
        for cid, (R, t, K, d) in cams.items():
            Ra = f(raw[cid])
            alt[cid] = (Ra, -Ra @ centres[cid], K, d)
        alt_errs = _leave_one_out_errors(alt)
        assert np.median(alt_errs) > 100, (name, np.median(alt_errs))   # 160 px to behind the cameras
    # and the picks triangulate to a treadmill lying flat: the brackets on the floor frame's z = 0
    # within 3 cm, the post tops ~18 cm above, 0.6 m apart
    pts = {}
    for p, obs in PICKS.items():
        rows = []
        for o, uv in obs.items():
            R, t, K, d = cams[o]
            x = cv2.undistortPoints(np.float64([[uv]]), K, d).reshape(2)
            P = np.hstack([R, t[:, None]])
            rows += [x[0] * P[2] - P[0], x[1] * P[2] - P[1]]
        X = np.linalg.svd(np.array(rows))[2][-1]
        pts[p] = X[:3] / X[3]
    assert abs(pts["B1"][2]) < 0.03 and abs(pts["B2"][2]) < 0.03
    assert 0.15 < pts["P1"][2] < 0.22 and 0.15 < pts["P2"][2] < 0.22
    assert 0.55 < np.linalg.norm(pts["P1"] - pts["P2"]) < 0.75


def test_pairwise_triangulation_agrees(qca):
    """Every pair of cameras triangulates each pick to the same point within 6 cm."""
    rec = calibration_from_qualisys(qca.read_bytes(), "pose2sim-single", 1, 60.0, source=str(qca))
    cams = {c.id: _cv_camera(c) for c in rec.cameras}
    for obs in PICKS.values():
        pts = []
        for a, b in itertools.combinations(sorted(obs), 2):
            n = [cv2.undistortPoints(np.float64([[obs[c]]]), cams[c][2], cams[c][3]).reshape(2, 1) for c in (a, b)]
            X = cv2.triangulatePoints(np.hstack([cams[a][0], cams[a][1][:, None]]),
                                      np.hstack([cams[b][0], cams[b][1][:, None]]), n[0], n[1])
            pts.append((X[:3] / X[3]).ravel())
        pts = np.array(pts)
        assert np.linalg.norm(pts - pts.mean(0), axis=1).max() < 0.06, pts


def test_1080_wide_reencodes_are_scaled_and_letterboxed(qca):
    """SinglePerson's cam01/cam02 frames are the 1088x1920 ones scaled by 1080/1088 and centred
    (7 px bars top and bottom): the imported intrinsics for 1080x1920 frames follow the affine
    measured between the images."""
    rec = calibration_from_qualisys(qca.read_bytes(), "pose2sim-single", 100, 60.0, source=str(qca),
                                    frame_sizes={"cam01": (1080, 1920), "cam02": (1080, 1920)})
    full = calibration_from_qualisys(qca.read_bytes(), "pose2sim-single", 100, 60.0, source=str(qca))
    for cid, (a, b, c, d) in MEASURED_RESAMPLE.items():
        cam, orig = rec.camera(cid), full.camera(cid)
        assert (cam.width, cam.height) == (1080, 1920)
        fx, fy, cx, cy = cam.intrinsics
        fx0, fy0, cx0, cy0 = orig.intrinsics
        assert fx / fx0 == pytest.approx(a, abs=1e-3) and fy / fy0 == pytest.approx(c, abs=1e-3)
        assert cx == pytest.approx(a * cx0 + b, abs=0.5) and cy == pytest.approx(c * cy0 + d, abs=0.5)
        assert cam.quality["resample_pad_y_px"] == pytest.approx(7.06, abs=0.01)
        assert cam.world_to_camera == orig.world_to_camera and cam.distortion == orig.distortion
    assert rec.camera("cam03") == full.camera("cam03")


def test_fit_to_frames_pillarbox_and_identity(qca):
    cam = calibration_from_qualisys(qca.read_bytes(), "x", 1, 1.0, source=str(qca)).camera("cam03")
    assert fit_to_frames(cam, 1088, 1920) is cam
    half = fit_to_frames(cam, 544, 960)
    assert half.intrinsics[0] == pytest.approx(cam.intrinsics[0] / 2)
    assert half.intrinsics[2] == pytest.approx((cam.intrinsics[2] + 0.5) / 2 - 0.5)
    wide = fit_to_frames(cam, 1200, 1920)             # pillarbox: 56 px each side
    assert wide.intrinsics[2] == pytest.approx(cam.intrinsics[2] + 56)


XML = b"""<calibration><cameras>
<camera active="1" serial="camA"><fov_video left="0" top="0" right="639" bottom="359"/>
<transform r11="1" r12="0" r13="0" r21="0" r22="1" r23="0" r31="0" r32="0" r33="1" x="0" y="0" z="%s"/>
<intrinsic focalLengthU="32000" focalLengthV="32000" centerPointU="20480" centerPointV="11520"
 radialDistortion1="0" radialDistortion2="0" radialDistortion3="0" tangentalDistortion1="0" tangentalDistortion2="0"/>
</camera>
<camera active="0" serial="camB"/>
</cameras></calibration>"""


def test_small_file_offsets_inactive_and_errors():
    rec = calibration_from_qualisys(XML % b"2000", "cap", 10, 25.0, source="lab.qca.txt")
    assert [c.id for c in rec.cameras] == ["camA"] and rec.unregistered == {"camB": "inactive in the Qualisys calibration"}
    cam = rec.camera("camA")
    assert cam.intrinsics == (500.0, 500.0, 320.0, 180.0) and (cam.width, cam.height) == (640, 360)
    # Qualisys camera looking down its -z: OpenCV's optical axis is world -z, centre 2 m up
    assert np.asarray(cam.world_to_camera)[2, :3] == pytest.approx([0, 0, -1])
    with pytest.raises(CalibrationInputError, match=r"lab\.qca\.txt: camera camA: <transform> z='2 m'"):
        calibration_from_qualisys(XML % b"2 m", "cap", 10, 25.0, source="lab.qca.txt")
    with pytest.raises(CalibrationInputError, match=r"lab\.qca\.txt: not XML"):
        calibration_from_qualisys(b"<calibration>", "cap", 10, 25.0, source="lab.qca.txt")
    with pytest.raises(CalibrationInputError, match=r"lab\.qca\.txt: frame sizes given for camera\(s\) camZ"):
        calibration_from_qualisys(XML % b"2000", "cap", 10, 25.0, source="lab.qca.txt", frame_sizes={"camZ": (1, 1)})
    bad = (XML % b"2000").replace(b'r11="1"', b'r11="2"')
    with pytest.raises(CalibrationInputError, match=r"lab\.qca\.txt: camera camA: the rotation is not a proper rotation"):
        calibration_from_qualisys(bad, "cap", 10, 25.0, source="lab.qca.txt")


def test_cli_import_with_a_stored_capture(qca, tmp_path):
    """`volcap import-calibration`: a stored capture gives frames, fps and its frames' sizes (cam01/
    cam02 at 1080x1920, as SinglePerson's videos), the record is stored and named, its ref printed."""
    import json

    from typer.testing import CliRunner

    import flows.cli as cli
    from hardware.rig import load_rig
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture, CaptureCamera
    from volcap_core.store import ArtifactStore

    s = ArtifactStore(str(tmp_path / "store"))
    cams = tuple(CaptureCamera(id=c, width=1080 if c in ("cam01", "cam02") else 1088, height=1920,
                               channels=("R", "G", "B"), source_encoding="linear", frames=())
                 for c in ("cam01", "cam02", "cam03", "cam04", "cam05"))
    s.set_ref("captures/single", s.put_record(Capture(name="single", rig=load_rig("demo_scene"), fps=60.0,
                                                      start_timecode="00:00:00:00", frame_count=100, cameras=cams)))
    res = CliRunner().invoke(cli.app, ["import-calibration", str(qca), "--format", "qualisys", "--capture", "single",
                                       "--store", s.url, "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output.strip().splitlines()[-1])
    assert out["name"] == "imported-calibrations/single" and out["capture_cameras_missing"] == ["cam05"]
    rec = s.get_record(s.get_ref("imported-calibrations/single"), Calibration)
    assert rec.model_dump() == s.get_record(s.resolve(out["calibration"]["digest"]), Calibration).model_dump()
    assert (rec.frame_count, rec.fps) == (100, 60.0)
    assert rec.camera("cam01").width == 1080 and rec.camera("cam03").width == 1088
    assert "cam01: 1080x1920" in res.output and "scaled by 0.99265" in res.output

    res = CliRunner().invoke(cli.app, ["import-calibration", str(qca), "--format", "qualisys", "--capture", "other",
                                       "--store", s.url])
    assert isinstance(res.exception, cli.CommandError) and "give --frames and --fps" in str(res.exception)
    res = CliRunner().invoke(cli.app, ["import-calibration", str(qca), "--format", "colmap", "--capture", "single",
                                       "--store", s.url])
    assert isinstance(res.exception, cli.CommandError) and "--format colmap reads a folder" in str(res.exception)
