"""Distortion that follows the zoom, for tracking cameras: the rig's zoom lens table and its
interpolation, the tracking solve on frames seen through a zoom lens (analytic: no rendering),
the records carrying each frame's lens, and the readers rectifying each tracking frame with its own.

The rig's validation errors are in ``tests/test_rigs.py``; the measured figures on the rendered
demo capture are in ``docs/benchmarks.md`` ("Through distorted lenses").
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from safetensors.numpy import save as st_save

from hardware.rig import ZoomIntrinsics, load_rig
from tests.calibration.test_calib_tracking import tracking_observations
from volcap_core.calibration.distortion import Distortion, rectified_valid, rectify_frame
from volcap_core.calibration.geometry import look_at_rotation, rotation_angle_deg
from volcap_core.calibration.record import (Calibration, CameraCalibration, TrackingFrames, camera_at,
                                            decode_tracking_frames, encode_tracking_frames, frame_camera,
                                            tracking_frames_ref)
from volcap_core.calibration.tracking.calibrate import TrackingProblem, solve_tracking
from volcap_core.calibration.tracking.lens import frame_undistorter, lens_corner_shift_px, smooth_encoder_focal, zoom_lens
from volcap_core.calibration.tracking.observe import undistort_observations
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.calibration.tracking.solve import initialise_tracking

T, W, H = 24, 320, 180
CX, CY = (W - 1) / 2, (H - 1) / 2
PX_PER_MM = W / 14.44
HALF_DIAG_MM = math.hypot(14.44, 8.12) / 2


# --------------------------------------------------------------------------- the table


def _table(with_principal=False) -> ZoomIntrinsics:
    pp = (lambda cx, cy: {"cx": cx, "cy": cy}) if with_principal else (lambda cx, cy: {})
    return ZoomIntrinsics.model_validate({"model": "OPENCV", "samples": [
        {"focal_mm": 45.0, "params": [-0.4, 0.01, 0.001, -0.002], **pp(161.0, 90.0)},
        {"focal_mm": 90.0, "params": [-0.2, 0.0, 0.002, 0.0], **pp(160.0, 89.0)},
        {"focal_mm": 175.0, "params": [2.0, 0.0, 0.004, 0.002], **pp(158.0, 89.5)}]})


def test_zoom_table_is_linear_in_focal_between_samples_and_clamped_outside():
    z = _table(with_principal=True)
    assert z.at(90.0).params == (-0.2, 0.0, 0.002, 0.0)                    # exact at a sample
    mid = z.at(67.5)                                                      # halfway from 45 to 90 mm
    np.testing.assert_allclose(mid.params, (-0.3, 0.005, 0.0015, -0.001), atol=1e-12)
    assert (mid.cx, mid.cy) == pytest.approx((160.5, 89.5))
    q = z.at(90.0 + 0.25 * 85.0)                                          # a quarter from 90 to 175 mm
    np.testing.assert_allclose(q.params, (-0.2 + 0.25 * 2.2, 0.0, 0.0025, 0.0005), atol=1e-12)
    assert z.at(40.0).params == z.samples[0].params                       # clamped below the table
    assert z.at(190.0).params == z.samples[-1].params                     # and above it
    assert z.at(190.0).focal_mm == 190.0
    every = z.at_each(np.array([45.0, 67.5, 175.0]))
    assert [s.params for s in every] == [z.at(f).params for f in (45.0, 67.5, 175.0)]
    # the library's view of it: OpenCV's 5 coefficients per focal and the principal point
    coeffs, pp = zoom_lens(z)(np.array([45.0, 67.5]))
    np.testing.assert_allclose(coeffs, [[-0.4, 0.01, 0.001, -0.002, 0.0], [-0.3, 0.005, 0.0015, -0.001, 0.0]])
    np.testing.assert_allclose(pp, [[161.0, 90.0], [160.5, 89.5]])
    assert zoom_lens(_table())(np.array([45.0]))[1] is None and zoom_lens(None) is None


def test_demo_rig_zoom_lenses_go_from_barrel_to_pincushion():
    rig = load_rig("demo_scene_distorted")
    for cam in rig.cameras:
        z = cam.zoom_intrinsics
        assert (z is not None) == cam.role.tracks
        if z is None:
            continue
        assert (z.samples[0].focal_mm, z.samples[-1].focal_mm) == (cam.lens.focal_min_mm, cam.lens.focal_max_mm)
        h = math.hypot(cam.sensor.width_mm, cam.sensor.height_mm) / 2
        # the radial distortion at the image corner, % of its radius: k1 r² with r = h / f
        corner = [100 * s.params[0] * (h / s.focal_mm) ** 2 for s in z.samples]
        assert -3.1 < corner[0] < -1.3 and 0.4 < corner[-1] < 1.2, (cam.id, corner)
        assert z.samples[0].params[0] < 0 < z.samples[-1].params[0]


# --------------------------------------------------------------------------- the tracking solve


def _lens():
    """A zoom lens over the analytic camera's zoom (1550-2100 px): barrel of 2.4 % at the image
    corner at 1500 px, 0.6 % at 2200 px, linear in log focal (k1 = D / r², r = corner radius)."""
    corner_px = math.hypot(W / 2, H / 2)
    focals = np.array([1500.0, 1700.0, 1900.0, 2200.0]) / PX_PER_MM          # mm
    samples = []
    for f_mm in focals:
        d = -0.024 + 0.018 * math.log(f_mm / focals[0]) / math.log(focals[-1] / focals[0])
        r2 = (corner_px / (f_mm * PX_PER_MM)) ** 2
        samples.append({"focal_mm": float(f_mm), "params": [d / r2, 0.0, 0.0002, -0.0001]})
    return ZoomIntrinsics.model_validate({"model": "OPENCV", "samples": samples})


def _scene(lens, seed=0, n3=8, sigma3=1.0):
    """test_calib_tracking's pan/tilt/zoom camera, its frames seen through ``lens`` at their true
    focal: ``n3`` 2D-3D matches a frame (noise ``sigma3`` px) with outliers, 2D-2D matches with a
    still 'actor'."""
    rng = np.random.default_rng(seed)
    C = np.array([4.9, -2.3, 1.9])
    f = 1800 * np.exp(0.15 * np.sin(2 * np.pi * np.arange(T) / 40 + 0.3))
    coeffs, _ = zoom_lens(lens)(f / PX_PER_MM)
    dist = [Distortion.from_opencv(c) for c in coeffs]
    targets = np.stack([np.array([0.0, -0.6 + 0.05 * t, 1.6 + 0.01 * math.sin(t / 3)]) for t in range(T)])
    R = np.stack([look_at_rotation(C, targets[t]) for t in range(T)])
    wall = np.stack([np.full(20000, -3.5), rng.uniform(-7, 7, 20000), rng.uniform(0, 4, 20000)], 1)

    def proj(t, X):
        p = (X - C) @ R[t].T
        return f[t] * dist[t].distort(p[:, :2] / p[:, 2:3]) + [CX, CY], p[:, 2]

    def seen(t, X):
        # in the image, and near it before the lens (a barrel lens folds points far outside the
        # field of view back into the image: the model holds only up to its fold)
        uv, z = proj(t, X)
        p = (X - C) @ R[t].T
        pin = f[t] * p[:, :2] / np.maximum(p[:, 2:3], 1e-9) + [CX, CY]
        near = (np.abs(pin[:, 0] - CX) < 0.6 * W) & (np.abs(pin[:, 1] - CY) < 0.6 * H)
        return (z > 0) & near & (uv[:, 0] > 0) & (uv[:, 0] < W - 1) & (uv[:, 1] > 0) & (uv[:, 1] < H - 1)

    obs = tracking_observations(rng, proj, seen, wall, n3, sigma3)
    enc = f * 1.008 + 6.0 + rng.normal(0, 0.002 * f)            # encoder in px: gain, offset, noise
    mount = C + np.array([0.01, -0.012, 0.008])
    return obs, C, R, f, enc, mount, coeffs


def _errors(sol, C, R, f, true_coeffs):
    """(focal shape %, rotation mean °, centre mean cm, footage alignment px, focal mean %): the
    focal's course over the zoom (max |ln(f_est / f) - mean|, the mean being the encoder prior's
    bias along the zoom/dolly valley), and how far the calibration puts points 8 m away from where
    the footage, as downstream reads it (rectified with the solution's lens, or raw), shows them."""
    lf = np.log(sol.K[:, 0, 0] / f)
    re = np.array([rotation_angle_deg(sol.world_to_camera[t, :3, :3], R[t]) for t in range(T)])
    Ce = -np.einsum("tji,tj->ti", sol.world_to_camera[:, :3, :3], sol.world_to_camera[:, :3, 3])
    gu, gv = np.meshgrid(np.linspace(0, W - 1, 16), np.linspace(0, H - 1, 9))
    grid = np.stack([gu.ravel(), gv.ravel()], 1)
    align = []
    for t in range(T):
        x = (grid - [CX, CY]) / f[t]
        X = C + (np.c_[x, np.ones(len(x))] * 8.0) @ R[t]
        raw = f[t] * Distortion.from_opencv(true_coeffs[t]).distort(x) + [CX, CY]
        footage = raw
        if sol.distortion is not None:
            footage = Distortion.from_opencv(sol.distortion[t]).undistort_pixels(sol.K[t], raw)
        q = (X - Ce[t]) @ sol.world_to_camera[t, :3, :3].T
        align.append(np.linalg.norm(sol.K[t, 0, 0] * q[:, :2] / q[:, 2:] + sol.K[t, :2, 2] - footage, axis=1))
    return (100 * np.abs(lf - lf.mean()).max(), re.mean(), 100 * np.linalg.norm(Ce - C, axis=1).mean(),
            float(np.mean(align)), 100 * np.abs(np.exp(lf) - 1).mean())


@pytest.fixture(scope="module")
def solved():
    """The scene with 40 2D-3D matches a frame at 0.5 px, so that the zoom/dolly valley (which sets
    test_calib_tracking's errors) does not hide the lens: solved with the lens at the smoothed
    encoder focal, and with the lens ignored (raw pixels as a pinhole's)."""
    lens = _lens()
    obs, C, R, f, enc, mount, true_coeffs = _scene(lens, n3=40, sigma3=0.5)
    prior = smooth_encoder_focal(np.arange(T), enc, T, 4.0)
    pp = np.tile([CX, CY], (T, 1))
    coeffs, _ = zoom_lens(lens)(prior / PX_PER_MM)          # the lens at the smoothed encoder focal
    out = {"truth": (C, R, f), "prior": prior, "coeffs": coeffs, "true_coeffs": true_coeffs, "obs": obs}
    starts = TrackingOptions(focal_scale_starts=(0.99, 1.0, 1.01))
    for name, ob, d in (("lens", undistort_observations(obs, frame_undistorter(prior, pp, coeffs)), coeffs),
                        ("ignored", obs, None)):
        Ri, Ci, fi, _ = initialise_tracking(ob, prior, mount, (CX, CY))
        problem = TrackingProblem(["S"], [ob], [(Ri, Ci, fi)], [prior], [pp], [mount], {"S": {}}, [d])
        out[name] = solve_tracking(problem, starts)["S"]
    return out


def test_undistorting_at_the_encoder_focal_is_as_good_as_at_the_true_one(solved):
    """The lens is taken at the smoothed encoder focal (1.2 % off here: gain 1.008, +6 px), not the
    true one: the undistorted corners move by about a tenth of a pixel (3 ε k1 r² of the corner
    radius, ε the focal error). Solved with the lens at the true focal instead, or a second pass
    at the estimated focal, the focal and rotation errors change by ≤ 0.01 % and 0.01° (seeds
    0-2, 2026-11: docs/calibration.md, "Lens distortion"), so one pass at the prior is kept."""
    C, R, f = solved["truth"]
    pp = np.tile([CX, CY], (T, 1))
    corners = np.array([[0.0, 0.0], [W - 1.0, 0.0], [0.0, H - 1.0], [W - 1.0, H - 1.0]])
    at_prior = frame_undistorter(solved["prior"], pp, solved["coeffs"])
    at_truth = frame_undistorter(f, pp, solved["true_coeffs"])
    diff = max(np.abs(at_prior(t, corners)[0] - at_truth(t, corners)[0]).max() for t in range(T))
    shift = lens_corner_shift_px(f, pp, solved["true_coeffs"], W, H)
    # measured: the lens moves the corners 1.9-3.9 px; the two undistortions differ by 0.12 px
    assert shift.min() > 1.5 and shift.max() < 4.5, shift
    assert diff < 0.2, diff
    assert abs(np.mean(solved["prior"] / f) - 1) > 0.008        # the encoder is off by ~1 %


def test_the_zoom_lens_recovers_focal_and_rotation_better_than_ignoring_it(solved):
    C, R, f = solved["truth"]
    lens = _errors(solved["lens"], C, R, f, solved["true_coeffs"])
    ignored = _errors(solved["ignored"], C, R, f, solved["true_coeffs"])
    print("focal shape %, rotation °, centre cm, alignment px, focal mean %: lens", np.round(lens, 3),
          "ignored", np.round(ignored, 3))
    # measured (seed 0, 2026-11): lens 0.046 %, 0.061°, 3.9 cm, 0.32 px, 0.41 %; ignored 0.19 %,
    # 0.27°, 7.6 cm, 1.40 px, 0.21 %. The same scene through a pinhole: 0.065 %, 0.036°, 3.8 cm,
    # 0.40 % focal; over seeds 0-2 the lens stays within 0.05 % / 0.05° / 1 cm of the pinhole's
    # and ignoring it gives 0.18-0.24 % / 0.14-0.27° / 7.4-7.8 cm.
    # The focal's course over the zoom: ignored, the barrel (2.4 % at 1500 px, 0.6 % at 2200 px)
    # bends it; 4.2x the lens's (2x margin)
    assert ignored[0] > 2 * lens[0] and lens[0] < 0.1, (lens, ignored)
    # the pose: rotation 4.3x (2x margin), centre 1.9x (1.4x margin)
    assert ignored[1] > 2 * lens[1] and lens[1] < 0.12, (lens, ignored)
    assert ignored[2] > 1.4 * lens[2], (lens, ignored)
    # where the footage is: 4.4x (2x margin)
    assert ignored[3] > 2 * lens[3], (lens, ignored)
    # the mean focal is the encoder prior's bias (+1.2 %) along the zoom/dolly valley in this scene
    # (0.40 % through a pinhole): the lens keeps it there; ignoring the barrel, which shrinks the
    # image, happens to pull it the other way (0.21 %)
    assert lens[4] < 0.6, lens
    # the solution carries the lens it was undistorted with, frame by frame
    np.testing.assert_array_equal(solved["lens"].distortion, solved["coeffs"])
    assert solved["ignored"].distortion is None


def test_a_principal_point_per_frame_is_held_per_frame():
    """A zoom lens whose axis moves with the zoom: the principal point of each frame is the
    table's, and the solve keeps it (K[t] has it)."""
    obs, C, R, f, enc, mount, _ = _scene(_lens(), seed=1)
    prior = smooth_encoder_focal(np.arange(T), enc, T, 4.0)
    pp = np.stack([CX + np.linspace(-1.0, 1.0, T), CY + np.linspace(0.5, -0.5, T)], 1)
    Ri, Ci, fi, _ = initialise_tracking(obs, prior, mount, pp)
    problem = TrackingProblem(["S"], [obs], [(Ri, Ci, fi)], [prior], [pp], [mount], {"S": {}})
    sol = solve_tracking(problem, TrackingOptions(focal_scale_starts=(1.0,), iterations=3))["S"]
    np.testing.assert_allclose(sol.K[:, 0, 2], pp[:, 0])
    np.testing.assert_allclose(sol.K[:, 1, 2], pp[:, 1])


# --------------------------------------------------------------------------- records and readers


def _pose(c, look=(0.0, 0.0, 1.6)):
    R = look_at_rotation(c, look)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, -R @ np.asarray(c, float)
    return m


def _frames(T=4, distorted=True):
    K = np.stack([np.array([300.0 + 20 * t, 300.0 + 20 * t, 80.5 + 0.1 * t, 44.5]) for t in range(T)])
    W2C = np.stack([_pose((5.0, 0.1 * t, 1.8)) for t in range(T)])
    D = np.stack([[-0.2 + 0.05 * t, 0.01, 0.0005, -0.0003, 0.0] for t in range(T)]) if distorted else None
    return {"T1": TrackingFrames(K, W2C, D)}


def _record(blob: bytes) -> Calibration:
    cams = (CameraCalibration(id="T1", role="tracking-landscape", static=False, width=160, height=90),)
    return Calibration(capture="demo", frame_count=4, fps=24.0, reference_frame=2, stage_size_m=(4.0, 4.0, 3.5),
                       cameras=cams, tracking_frames=tracking_frames_ref(blob))


def test_tracking_blob_carries_each_frames_lens_and_is_versioned():
    frames = _frames()
    blob = encode_tracking_frames(frames)
    assert b"volcap-tracking-frames/2" in blob[:400]
    back = decode_tracking_frames(blob)
    np.testing.assert_array_equal(back["T1"].distortion, frames["T1"].distortion)
    np.testing.assert_array_equal(back["T1"].intrinsics, frames["T1"].intrinsics)
    # without distortion: format 1, the bytes written before distortion existed
    plain = _frames(distorted=False)
    old = st_save({"T1/intrinsics": plain["T1"].intrinsics, "T1/world_to_camera": plain["T1"].world_to_camera},
                  metadata={"format": "volcap-tracking-frames/1"})
    assert encode_tracking_frames(plain) == old
    assert decode_tracking_frames(old)["T1"].distortion is None
    # refused: a distortion of another length or frame count, a blob of an unknown format
    bad = {"T1": TrackingFrames(frames["T1"].intrinsics, frames["T1"].world_to_camera, np.zeros((4, 4)))}
    with pytest.raises(ValueError, match=r"camera T1: distortion must be \[T, 5\] or \[T, 8\]"):
        encode_tracking_frames(bad)
    with pytest.raises(ValueError, match="camera T1: distortion must be"):
        encode_tracking_frames({"T1": TrackingFrames(frames["T1"].intrinsics, frames["T1"].world_to_camera,
                                                     np.zeros((3, 5)))})
    future = st_save({"T1/intrinsics": plain["T1"].intrinsics, "T1/world_to_camera": plain["T1"].world_to_camera},
                     metadata={"format": "volcap-tracking-frames/9"})
    with pytest.raises(ValueError, match="format 'volcap-tracking-frames/9'"):
        decode_tracking_frames(future)
    # read for a calibration (what training and rendering do): the error names the blob and capture
    from volcap_core.segment import tracking_frames

    rec = _record(future)
    with pytest.raises(ValueError, match=rf"capture 'demo': tracking frames {rec.tracking_frames.digest}: "
                                         r"tracking-frames blob of format 'volcap-tracking-frames/9'"):
        tracking_frames(lambda ref: future, rec)


def test_frame_camera_rectifies_each_tracking_frame_with_its_own_lens():
    frames = _frames()
    tf = decode_tracking_frames(encode_tracking_frames(frames))
    rec = _record(encode_tracking_frames(frames))
    v, u = np.mgrid[0:90, 0:160].astype(np.float32)
    pinhole = np.stack([0.5 + 0.4 * np.sin(u / 5.0), 0.5 + 0.4 * np.cos(v / 4.0), 0.5 + 0.0 * u], -1)
    import cv2

    for t in (0, 3):
        cam = frame_camera(rec, "T1", t, tf)
        K, w2c, _, _ = camera_at(rec, "T1", t, tf)
        assert cam.intrinsics == tuple(K[[0, 1, 0, 1], [0, 1, 2, 2]])
        assert cam.distortion == tuple(frames["T1"].distortion[t])
        np.testing.assert_allclose(np.asarray(cam.world_to_camera), w2c, atol=1e-9)
        # the raw frame t: the pinhole image seen through frame t's lens; rectified back
        d = Distortion.from_opencv(cam.distortion)
        src = d.undistort_pixels(K, np.stack([u.ravel(), v.ravel()], 1)).astype(np.float32)
        raw = cv2.remap(pinhole.astype(np.float32), src[:, 0].reshape(90, 160), src[:, 1].reshape(90, 160),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        out = rectify_frame(raw, cam)
        valid = rectified_valid(cam)
        inner = valid.copy()
        inner[:4], inner[-4:], inner[:, :4], inner[:, -4:] = False, False, False, False
        err = np.abs(out - pinhole)[inner].mean()
        assert err < 0.01 and np.abs(raw - pinhole)[inner].mean() > 3 * err, (t, err)
    # another frame's lens does not undo it as well: the lens really is per frame
    assert frame_camera(rec, "T1", 0, tf).distortion != frame_camera(rec, "T1", 3, tf).distortion
    # a pinhole tracking camera's frames come back as they are
    plain = _frames(distorted=False)
    tfp = decode_tracking_frames(encode_tracking_frames(plain))
    cam = frame_camera(_record(encode_tracking_frames(plain)), "T1", 1, tfp)
    assert rectify_frame(pinhole, cam) is pinhole and rectified_valid(cam) is None


def test_tracking_solution_and_assembled_record_carry_the_lens(tmp_path):
    from volcap_core.calibration.assemble import tracking_blob
    from volcap_core.calibration.tracking.solve import TrackingSolution
    from volcap_core.calibration.tracking_step import encode_tracking_solution, tracking_record, tracking_solution

    frames = _frames()["T1"]
    K = np.zeros((4, 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = (*frames.intrinsics.T, 1.0)
    sol = TrackingSolution(K, frames.world_to_camera, 1.0, 0.0, np.zeros(3), {"cost": 1.0}, frames.distortion)
    back = tracking_solution(tracking_record("demo", "T1", sol, tracking_frames_ref(b"x")),
                             encode_tracking_solution(sol))
    np.testing.assert_array_equal(back.distortion, frames.distortion)
    tf = decode_tracking_frames(tracking_blob({"T1": back}))
    np.testing.assert_array_equal(tf["T1"].distortion, frames.distortion)
    np.testing.assert_allclose(tf["T1"].intrinsics, frames.intrinsics)
    sol.distortion = None
    assert tracking_solution(tracking_record("demo", "T1", sol, tracking_frames_ref(b"x")),
                             encode_tracking_solution(sol)).distortion is None


def test_ground_truth_calibration_carries_the_tracking_lens_per_frame():
    from volcap_core.synth.ground_truth import calibration

    frames = []
    for t in range(3):
        frames.append({"take_index": t, "frame": t, "fx": 300.0 + t, "fy": 300.0 + t, "cx": 80.0, "cy": 45.0,
                       "world_to_camera": _pose((5.0, 0.1 * t, 1.8)).tolist(),
                       "distortion": {"model": "OPENCV", "params": [-0.1 * t, 0.0, 0.001, 0.0]}})
    cams = {"frame_count": 3, "fps": 24.0,
            "cameras": {"T1": {"role": "tracking-landscape", "width": 160, "height": 90, "frames": frames}}}
    rec, blob = calibration(cams, "demo", ["T1"], (4.0, 4.0, 3.5))
    tf = decode_tracking_frames(blob)
    np.testing.assert_allclose(tf["T1"].distortion[:, 0], [0.0, -0.1, -0.2])
    assert tf["T1"].distortion.shape == (3, 5)
    assert frame_camera(rec, "T1", 2, tf).distortion == (-0.2, 0.0, 0.001, 0.0, 0.0)


def test_a_tracking_frame_is_rendered_through_its_lens_at_its_focal(tmp_path):
    """The synthetic capture renders a tracking camera through its zoom lens at each frame's true
    focal: undistorted with the ground truth's lens of that frame, it matches the same camera
    rendered as a pinhole (the table's distortion zeroed)."""
    import cv2

    from volcap_core.calibration.distortion import undistort_image, undistort_valid_mask
    from volcap_core.calibration.sfm import Intrinsics
    from volcap_core.capture import CaptureFolder
    from volcap_core.synth import synthesize_capture

    rig = json.loads(json.dumps(load_rig("demo_scene_distorted").model_dump(mode="json")))
    cam = next(c for c in rig["cameras"] if c["id"] == "S010")
    for s in cam["zoom_intrinsics"]["samples"]:
        s["params"] = [0.0, 0.0, 0.0, 0.0]
    (tmp_path / "flat.json").write_text(json.dumps(rig))
    kw = dict(frames=2, cameras=["S010"], supersample=1, lidar_spacing_m=0.5)
    a = synthesize_capture(tmp_path / "a", rig="demo_scene_distorted", **kw).parent
    b = synthesize_capture(tmp_path / "b", rig=tmp_path / "flat.json", **kw).parent
    out = []
    for root in (a, b):
        gt = json.loads((root / "ground_truth/cameras.json").read_text())["cameras"]["S010"]
        fr = gt["frames"][1]
        intr = Intrinsics(fr["fx"], fr["fy"], fr["cx"], fr["cy"], gt["width"], gt["height"])
        d = Distortion.from_json(fr["distortion"])
        img = CaptureFolder.open(root).load("S010", 1)
        out.append((img, undistort_image(img, intr, d), undistort_valid_mask(intr, d, margin_px=1.5), d, gt))
    (raw_a, und_a, va, da, gta), (raw_b, und_b, vb, db, _) = out
    # the lens differs from frame to frame (it follows the focal) and is the table's at that focal
    focal = [f["focal_mm"] for f in gta["frames"]]
    k1 = [f["distortion"]["params"][0] for f in gta["frames"]]
    table = ZoomIntrinsics.model_validate(gta["zoom_lens"])
    assert k1[0] != k1[1] and k1 == pytest.approx([table.at(f).params[0] for f in focal])
    assert abs(db.params[0]) < 0.05 and da.params[0] < -0.1
    valid = va & vb

    def diff(x, y):
        return np.abs(cv2.GaussianBlur(x - y, (0, 0), 1.5))[valid].mean()

    raw_diff, und_diff = diff(raw_a, raw_b), diff(und_a, und_b)
    print("mean |a - b|: raw", raw_diff, "undistorted", und_diff)
    # measured (2026-11): 0.0050 raw, 0.00092 undistorted (S010 at ~30 mm: -1.6 % at the corner)
    assert und_diff < 0.4 * raw_diff, (und_diff, raw_diff)


def test_training_views_of_a_zoom_camera_are_rectified_frame_by_frame():
    """segment_data (what training and scoring read): a tracking camera's frame t is rectified with
    frame t's lens, and its pixels without footage are marked per frame."""
    import cv2
    import torch

    from volcap_core.reconstruction import segment_data

    frames = _frames()
    D = frames["T1"].distortion.copy()
    D[:, 0] = [0.05, 0.1, 0.2, 0.3]                      # pincushion: the rectified corners leave the sensor
    frames = {"T1": TrackingFrames(frames["T1"].intrinsics, frames["T1"].world_to_camera, D)}
    tf = decode_tracking_frames(encode_tracking_frames(frames))
    rec = _record(encode_tracking_frames(frames))
    v, u = np.mgrid[0:90, 0:160].astype(np.float32)
    pinhole = np.stack([0.5 + 0.4 * np.sin(u / 5.0), 0.5 + 0.4 * np.cos(v / 4.0), 0.5 + 0.1 * np.sin(v / 3.0)], -1)
    raws = []
    for t in range(4):
        K = camera_at(rec, "T1", t, tf)[0]
        src = Distortion.from_opencv(D[t]).undistort_pixels(K, np.stack([u.ravel(), v.ravel()], 1)).astype(np.float32)
        raws.append(torch.from_numpy(cv2.remap(pinhole.astype(np.float32), src[:, 0].reshape(90, 160),
                                               src[:, 1].reshape(90, 160), cv2.INTER_LINEAR,
                                               borderMode=cv2.BORDER_REFLECT)))

    class _Cap:     # what segment_data reads of a Capture record
        name, fps = "demo", 24.0

        class _Cam:
            id, frames = "T1", [0, 1, 2, 3]              # a frame's "ref" is its take index here
            masks = None                                 # no performer masks

        cameras = [_Cam]

        def take_range(self, f):
            return tuple(f)

        def camera(self, cid):
            return self._Cam

    data = segment_data(_Cap(), rec, tf, (0, 4), lambda ref: raws[ref])
    fractions = []
    for view in data.views:
        img = (view.image() if callable(view.image) else view.image).numpy()
        valid = view.load_valid().numpy()
        inner = valid.copy()
        inner[:4], inner[-4:], inner[:, :4], inner[:, -4:] = False, False, False, False
        assert np.abs(img - pinhole)[inner].mean() < 0.01, view.frame
        assert (img[~valid] == 0).all()
        fractions.append(valid.mean())
    # the stronger the frame's pincushion, the more of its rectified frame has no footage
    assert fractions == sorted(fractions, reverse=True) and fractions[0] > fractions[-1] + 0.01, fractions
