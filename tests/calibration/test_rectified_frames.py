"""Footage of distorted cameras after calibration: one rectification (``distortion.rectify_frame``)
for dense points and training, its validity mask, the static step's record carrying the raw
intrinsics and distortion through the flow, scores that leave the border out, and the ground
truth's depth back-projected through the lens."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from volcap_core.calibration.distortion import (Distortion, rectified_valid, rectify_frame, record_distortion,
                                                undistort_image)
from volcap_core.calibration.record import CameraCalibration, matrix4
from volcap_core.calibration.sfm import Intrinsics

W, H = 160, 90
D = Distortion("OPENCV", (0.1, -0.02, 0.0005, -0.0003))    # pincushion: the rectified corners leave the sensor


def _camera(distortion=D, **kw) -> CameraCalibration:
    return CameraCalibration(id="S0", role="static", static=True, width=W, height=H,
                             intrinsics=(150.0, 151.0, 82.0, 43.5),
                             distortion=tuple(float(v) for v in distortion.opencv()[:5]),
                             world_to_camera=matrix4(np.eye(4)), **kw)


def _texture() -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    return np.stack([0.5 + 0.4 * np.sin(u / 5.0), 0.5 + 0.4 * np.cos(v / 4.0),
                     0.5 + 0.2 * np.sin((u + v) / 7.0)], -1).astype(np.float32)


def test_rectify_frame_undoes_the_lens_and_marks_the_border():
    cam = _camera()
    intr = Intrinsics(*cam.intrinsics, W, H)
    pinhole = _texture()
    # the raw frame: the pinhole image seen through the lens (source pixel of raw p = K D^-1 K^-1 p)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    src = D.undistort_pixels(intr.K, np.stack([u.ravel(), v.ravel()], 1)).astype(np.float32)
    import cv2

    raw = cv2.remap(pinhole, src[:, 0].reshape(H, W), src[:, 1].reshape(H, W), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REFLECT)
    out = rectify_frame(raw, cam)
    valid = rectified_valid(cam)
    assert valid.shape == (H, W) and 0.9 < valid.mean() < 1.0       # the corners leave the sensor
    assert not valid[0, 0] and valid[H // 2, W // 2]
    assert (out[~valid] == 0).all()
    inner = valid.copy()
    inner[:3], inner[-3:], inner[:, :3], inner[:, -3:] = False, False, False, False
    err = np.abs(out - pinhole)[inner].mean()
    assert err < 0.01, err                                           # two bilinear resamplings
    assert np.abs(raw - pinhole)[inner].mean() > 5 * err
    # the same maps for a mask, for a torch frame, and the library's own undistortion agrees
    m = rectify_frame(raw[..., 0], cam)
    assert m.shape == (H, W) and np.allclose(m, out[..., 0], atol=1e-6)
    t = rectify_frame(torch.from_numpy(raw), cam)
    assert isinstance(t, torch.Tensor) and np.allclose(t.numpy(), out, atol=1e-6)
    ref = undistort_image(raw, intr, D)
    assert np.allclose(ref[valid], out[valid], atol=1e-5)


def test_a_rational_lens_keeps_all_eight_coefficients_in_the_record():
    rational = Distortion.from_opencv((0.1, -0.02, 0.0005, -0.0003, 0.01, 0.05, -0.01, 0.002))
    assert rational.model == "FULL_OPENCV"
    cam = _camera(distortion=Distortion.none(), ).model_copy(update={"distortion": tuple(rational.opencv())})
    again = CameraCalibration.model_validate_json(cam.model_dump_json())
    assert len(again.distortion) == 8 and record_distortion(again) == rational
    # the rectification uses the rational term: it differs from the same lens without k4-k6
    img = _texture()
    five = _camera(distortion=Distortion("OPENCV", rational.params[:4]))
    assert not np.allclose(rectify_frame(img, again), rectify_frame(img, five), atol=1e-3)
    with pytest.raises(ValueError, match="5 or 8 coefficients"):
        CameraCalibration.model_validate({**cam.model_dump(), "distortion": (0.1, 0.0, 0.0, 0.0, 0.0, 0.0)})


def test_a_pinhole_camera_is_left_alone():
    cam = _camera(Distortion.none())
    img = _texture()
    assert rectify_frame(img, cam) is img and rectified_valid(cam) is None
    assert record_distortion(cam).is_none and not record_distortion(_camera()).is_none
    tracking = CameraCalibration(id="T0", role="tracking-landscape", static=False, width=W, height=H)
    assert rectify_frame(img, tracking) is img
    with pytest.raises(ValueError, match="frame is"):
        rectify_frame(img[:10], _camera())


def test_per_frame_lenses_keep_out_of_the_static_cameras_map_cache():
    """A tracking camera's lens changes with its zoom every frame: its maps must not evict the
    static cameras' (training draws views at random, so a shared cache rebuilt maps on nearly
    every load), and they are not all kept (4K maps are ~75 MB each). The same lens gives the same
    frame through either cache."""
    from volcap_core.calibration import distortion

    static = _camera()
    img = _texture()
    reference = rectify_frame(img, static)
    before = distortion._rectify_maps.cache_info().currsize
    for k in range(40):                                          # 40 frames of a zoom: 40 lenses
        frame_lens = CameraCalibration(id="T0", role="tracking-landscape", static=False, width=W, height=H,
                                       intrinsics=(150.0 + k, 151.0 + k, 82.0, 43.5),
                                       distortion=tuple(float(v) for v in D.opencv()[:5]))
        out = rectify_frame(img, frame_lens)
        assert np.array_equal(rectified_valid(frame_lens), rectified_valid(frame_lens.model_copy(
            update={"static": True})))
        assert np.array_equal(out, rectify_frame(img, frame_lens.model_copy(update={"static": True})))
    assert distortion._frame_rectify_maps.cache_info().currsize <= 4
    # the static camera's maps are still there (40 static lookups above added 40 entries at most)
    hits = distortion._rectify_maps.cache_info().hits
    assert np.array_equal(rectify_frame(img, static), reference)
    assert distortion._rectify_maps.cache_info().hits == hits + 1
    assert distortion._rectify_maps.cache_info().currsize <= before + 40


def test_static_record_carries_raw_intrinsics_and_distortion_into_the_calibration():
    """The flow's static step stores what ``assemble.build_record`` needs: the flow's Calibration
    equals the one-call pipeline's."""
    from hardware.rig import load_rig
    from volcap_core.calibration.assemble import build_record
    from volcap_core.calibration.static import StaticCalibration
    from volcap_core.calibration.static_step import StaticStep, static_calibration, static_record

    rig = load_rig("demo_scene_distorted")
    ids = ["S000", "S001", "S004"]
    K, w2c, raw = {}, {}, {}
    for i, c in enumerate(ids):
        r = Intrinsics.from_rig(rig, c)
        raw[c] = Intrinsics(r.fx * 1.001, r.fy * 1.001, r.cx + 0.2, r.cy - 0.1, r.width, r.height, r.distortion)
        K[c] = np.array([[r.fx, 0, r.cx], [0, r.fx, r.cy], [0, 0, 1.0]])
        R = np.linalg.qr(np.random.default_rng(i).normal(size=(3, 3)))[0]
        R *= np.sign(np.linalg.det(R))
        w2c[c] = np.eye(4)
        w2c[c][:3, :3], w2c[c][:3, 3] = R, [0.1 * i, 0.2, 5.0]
    static = StaticCalibration(camera_ids=ids, K=K, world_to_camera=w2c, size={c: (320, 180) for c in ids},
                               model=SimpleNamespace(points=np.zeros((3, 3))), stats={}, raw_intrinsics=raw)
    rec = static_record("cap", StaticStep(static, 3, [0, 5], {}, None), None)
    back = static_calibration(type(rec).model_validate_json(rec.model_dump_json()))
    assert back.raw_intrinsics == raw
    one_call = build_record("cap", rig, static, {}, 6, 24.0, 3, None)
    flow = build_record("cap", rig, back, {}, 6, 24.0, 3, None)
    assert flow == one_call
    cam = flow.camera("S000")
    assert cam.intrinsics == pytest.approx((raw["S000"].fx, raw["S000"].fy, raw["S000"].cx, raw["S000"].cy))
    assert cam.distortion == pytest.approx(tuple(raw["S000"].distortion.opencv()[:5]))
    # a square pinhole stays as it was: no raw fields
    plain = StaticCalibration(camera_ids=ids[:1], K={ids[0]: K[ids[0]]}, world_to_camera={ids[0]: w2c[ids[0]]},
                              size={ids[0]: (320, 180)}, model=SimpleNamespace(points=np.zeros((0, 3))))
    prec = static_record("cap", StaticStep(plain, 3, [0], {}, None), None)
    assert prec.cameras[0].raw_intrinsics is None and prec.cameras[0].distortion is None
    assert static_calibration(prec).raw_intrinsics == {}


def test_scores_leave_out_the_pixels_without_footage():
    from volcap_core.splat.scoring import score_views

    rng = np.random.default_rng(0)
    truth = [torch.from_numpy(rng.uniform(0.1, 0.8, (48, 48, 3)).astype(np.float32)) for _ in range(2)]
    valid = torch.ones(48, 48, dtype=torch.bool)
    valid[:, :8] = False
    close = [t + 0.01 for t in truth]
    garbage = [c.clone() for c in close]
    for g in garbage:
        g[:, :8] = 5.0
    clean = score_views(close, truth, ["a", "b"], [0, 0])
    masked = score_views(garbage, truth, ["a", "b"], [0, 0], valid=[valid, valid])
    unmasked = score_views(garbage, truth, ["a", "b"], [0, 0])
    for c, m, u in zip(clean, masked, unmasked):
        assert abs(m.psnr_raw - c.psnr_raw) < 0.3 and m.psnr_raw > u.psnr_raw + 10
        assert m.ssim_raw > u.ssim_raw


def test_training_ignores_the_pixels_without_footage():
    """A view whose invalid pixels hold nonsense trains the same model as one whose invalid
    pixels hold the truth: the loss never sees them."""
    from volcap_core.splat import Camera, PointsAtTime, SegmentData, TrainConfig, train_segment

    K = torch.tensor([[40.0, 0, 24.0], [0, 40.0, 16.0], [0, 0, 1]])
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    cam = Camera(K=K, world_to_camera=w2c, width=48, height=32)
    rng = np.random.default_rng(1)
    img = torch.from_numpy(rng.uniform(0.2, 0.6, (32, 48, 3)).astype(np.float32))
    valid = torch.ones(32, 48, dtype=torch.bool)
    valid[:6] = False
    bad = img.clone()
    bad[:6] = 7.0
    pts = [PointsAtTime(0.0, torch.from_numpy(rng.uniform(-0.5, 0.5, (200, 3)).astype(np.float32)),
                        torch.full((200, 3), 0.4))]
    cfg = TrainConfig(steps=6, eval_every=0, checkpoint_every=0)

    def run(image):
        data = SegmentData.build(frames=(0, 1), camera_ids=["c"], fps=24.0, load_image=lambda c, f: image,
                                 camera_for=lambda c, f: cam, load_valid=lambda c, f: valid)
        return train_segment(data, pts, cfg, seed=0).model

    a, b = run(img), run(bad)
    for k in a.params:
        assert torch.equal(a.params[k], b.params[k]), k


def test_ground_truth_depth_backprojects_through_the_lens():
    from volcap_core.synth.geometry import PinholeCamera
    from volcap_core.synth.ground_truth import backproject_depth

    cam = PinholeCamera.looking_at(W, H, 150.0, 151.0, 82.0, 43.5, (0.0, -5.0, 1.3), (0.0, 0.0, 1.3), 0.0, D)
    rng = np.random.default_rng(2)
    pts = np.array([0.0, 0.0, 1.3]) + rng.uniform(-1, 1, (50, 3))
    uv, z = cam.project(pts)
    # the depth of each point at its (rounded) pixel, and that pixel's ray
    ui, vi = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    keep = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    first = np.zeros(len(ui), bool)
    first[np.unique(vi * W + ui, return_index=True)[1]] = True
    keep &= first                                                   # one point a pixel
    depth = np.full((H, W), np.inf, np.float32)
    depth[vi[keep], ui[keep]] = z[keep]
    w2c = cam.world_to_camera
    xyz, _ = backproject_depth(depth, np.zeros((H, W, 3), np.float32), np.array(
        [[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]]), w2c, distortion=D)
    back_uv, _ = cam.project(xyz.astype(np.float64))
    order = np.lexsort((ui[keep], vi[keep]))
    assert np.abs(back_uv - np.stack([ui[keep], vi[keep]], 1)[order]).max() < 1e-3
