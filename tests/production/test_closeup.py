"""Close-up scores (volcap_core.production.closeup) and the detail measure they report."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from volcap_core.contact_sheet import contact_sheet
from volcap_core.image_metrics import detail, gradient_energy
from volcap_core.production.closeup import bicubic_floor, closeup_sheet_rows, score_closeup

H, W, T = 72, 96, 3


def _truth(seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """T frames of a textured performer (alpha 1 inside an ellipse) over a dim set, and a face
    mask over the ellipse's upper part."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W]
    body = ((xx - 48) / 28.0) ** 2 + ((yy - 36) / 30.0) ** 2 <= 1.0
    face = body & (yy < 30)
    frames = []
    for _ in range(T):
        tex = 0.25 + 0.2 * np.sin(xx / 2.3) * np.cos(yy / 3.1) + 0.05 * rng.standard_normal((H, W))
        rgb = np.stack([tex, 0.8 * tex, 0.6 * tex], -1).clip(0.01, None)
        rgb = np.where(body[..., None], rgb, 0.05)
        frames.append(np.concatenate([rgb, body[..., None].astype(np.float64)], -1).astype(np.float32))
    return frames, [face] * T


def test_truth_scores_perfectly_and_floors_are_the_same_code():
    truth, faces = _truth()
    s = score_closeup(truth, truth, faces, enhanced=[np.zeros_like(t) for t in truth])
    json.dumps(s)                                           # JSON-able
    for region in ("performers", "face"):
        r = s["rows"]["render"][region]
        assert r["psnr"] == pytest.approx(200.0) and r["ssim"] == pytest.approx(1.0) and r["detail"] == 1.0
        assert r["views"] == T
        # an all-zero output scores exactly at the empty floor: same code, same pixels
        assert s["rows"]["enhanced"][region] == s["rows"]["empty"][region]
        assert s["rows"]["empty"][region]["detail"] == 0.0
        # the bicubic floor sits between them
        b = s["rows"]["bicubic"][region]
        assert s["rows"]["empty"][region]["psnr"] < b["psnr"] < 200 and 0 < b["detail"] < 1
    assert s["floors"] == {"render": ["empty", "bicubic"], "enhanced": ["render", "empty", "bicubic"]}
    assert s["temporal"]["render"] == s["temporal"]["truth"]
    assert s["temporal"]["empty"]["flickering"] == 1.0          # a constant video does not flicker
    assert s["temporal"]["truth"]["warp_error"] is None         # no flows given


def test_detail_sees_blur_and_noise_that_psnr_barely_separates():
    truth, faces = _truth()
    blurred = [np.concatenate([cv2.GaussianBlur(t[..., :3], (0, 0), 1.2), t[..., 3:]], -1) for t in truth]
    rng = np.random.default_rng(1)
    noisy = [np.concatenate([t[..., :3] + 0.03 * rng.standard_normal(t[..., :3].shape).astype(np.float32),
                             t[..., 3:]], -1) for t in truth]
    sb = score_closeup(truth, blurred, faces)["rows"]["render"]
    sn = score_closeup(truth, noisy, faces)["rows"]["render"]
    for region in ("performers", "face"):
        assert sb[region]["detail"] < 0.6, sb
        assert sn[region]["detail"] > 1.1, sn
        assert sb[region]["psnr"] < 200 and sn[region]["psnr"] < 200


def test_detail_definition():
    """Gradient energy over a region counts the differences whose two pixels are both inside."""
    x = torch.zeros(4, 5, 1)
    x[:, 2:] = 1.0                                   # one vertical edge between columns 1 and 2
    assert gradient_energy(x) == 4.0
    m = torch.zeros(4, 5, dtype=torch.bool)
    m[:, :2] = True                                  # the edge's right pixel is outside
    assert gradient_energy(x, m) == 0.0
    assert detail(x, x, m) is None                   # flat truth: no ratio
    assert detail(0.5 * x, x) == pytest.approx(0.25)


def test_warp_error_with_the_shots_flows():
    truth, faces = _truth()
    flows = [None] + [np.zeros((H, W, 2), np.float32)] * (T - 1)
    static = [truth[0]] * T
    s = score_closeup(static, static, faces[:T], flows=flows)
    assert s["temporal"]["truth"]["warp_error"] == 0.0
    moving = score_closeup(static, truth, faces, flows=flows)  # the render's texture changes every frame
    assert moving["temporal"]["render"]["warp_error"] > 1e-4
    with pytest.raises(ValueError, match="flow of frame 1"):
        score_closeup(static, static, faces, flows=[None, np.zeros((H, W), np.float32), None])


def test_bad_input_names_the_frame():
    truth, faces = _truth()
    with pytest.raises(ValueError, match="render frame 1: 48x36 does not match the truth's 96x72"):
        score_closeup(truth, [truth[0], np.zeros((36, 48, 4), np.float32), truth[2]], faces)
    with pytest.raises(ValueError, match="3 truth frames but 2 render"):
        score_closeup(truth, truth[:2], faces)


def test_bicubic_floor_keeps_a_smooth_image():
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    smooth = np.stack([xx / W, yy / H, np.full_like(xx, 0.5), np.ones_like(xx)], -1)
    up = bicubic_floor(smooth)
    assert up.shape == smooth.shape
    # away from the edges (clamped taps) within a fifth of one pixel's step of the ramp: registered,
    # not shifted (torch's a = -0.75 cubic is off by 0.12 px on a ramp)
    assert np.abs(up - smooth)[12:-12, 12:-12].max() < 0.2 / H


def test_sheet_rows_first_middle_last():
    truth, faces = _truth()
    enhanced = [np.clip(t * 1.05, 0, None) for t in truth]
    s = score_closeup(truth, truth, faces, enhanced=enhanced)
    rows = closeup_sheet_rows(truth, truth, faces, s, enhanced=enhanced, frame_numbers=[1001, 1002, 1003])
    assert [r.label.split(":")[0] for r in rows] == ["frame 1001 render", "frame 1001 enhanced",
                                                   "frame 1002 render", "frame 1002 enhanced",
                                                   "frame 1003 render", "frame 1003 enhanced"]
    assert "face PSNR 200.0 dB" in rows[0].label
    sheet = contact_sheet(rows, title="close-up")
    assert sheet.dtype == np.uint8 and sheet.shape[0] > 6 * H


def test_score_shot_exrs_finds_the_face_through_the_render_frames_cameras():
    """From EXR bytes: the render-shot frames' cameras and times place the actor's head; a render
    equal to the truth scores perfectly on the face, and the sheet is drawn."""
    from volcap_core.imageio.write import encode_exr
    from volcap_core.production.closeup import score_shot_exrs
    from volcap_core.production.shot import camera_at, encode_shot_exr, load_shot

    shot = load_shot({"name": "cu", "performance": "p", "frames": [0, 3], "fps": 24, "resolution": [96, 64],
                      "sensor_mm": 36.0, "keyframes": [{"frame": 0, "position": [1.2, 0.0, 1.6],
                                                        "look_at": [0.0, 0.0, 1.6], "focal_mm": 50}]})
    head = {"name": "head", "kind": "ellipsoid", "centre_m": [0.0, 0.0, 1.6], "rotation": np.eye(3).tolist(),
            "semi_axes_m": [0.1, 0.08, 0.115]}
    scene = {"actors": [{"index": 0, "frames": [{"take_index": k, "time_s": k / 24, "parts": [head]}
                                                for k in range(3)]}]}
    truth, render = [], []
    rng = np.random.default_rng(0)
    for f in shot.frame_numbers():
        cam = camera_at(shot, f)
        rgba = np.zeros((64, 96, 4), np.float32)
        rgba[8:56, 20:76, :3] = 0.2 + 0.1 * rng.random((48, 56, 3))      # the performer, textured
        rgba[8:56, 20:76, 3] = 1.0
        name = f"{f:06d}.exr"
        truth.append((name, encode_exr(rgba, ("R", "G", "B", "A"), pixel_type="float")))
        flow = np.zeros((64, 96, 2), np.float32) if f > 0 else None
        render.append((name, encode_shot_exr(rgba, cam, shot, f, flow=flow)))
    scores, sheet = score_shot_exrs(truth, render, scene, enhanced=render)
    assert scores["shot_frames"] == [0, 1, 2]
    face = scores["rows"]["render"]["face"]
    assert face["views"] == 3 and face["psnr"] > 60 and face["detail"] == pytest.approx(1.0, abs=1e-3)
    # the head (0.23 m tall at 1.2 m, 50 mm on 36 mm: ~25 px) is a part of the performer's 48x56 px
    assert scores["rows"]["render"]["performers"]["views"] == 3
    assert scores["temporal"]["render"]["warp_error"] is not None
    assert sheet.dtype == np.uint8 and sheet.ndim == 3
    with pytest.raises(ValueError, match="the render frames"):
        score_shot_exrs(truth, render[:2], scene)


def test_score_shot_task_key():
    """The score-shot task reruns when any input frame set, the capture or the face choice changes."""
    import tasks.production as production_tasks
    from tests.test_cache_keys import assert_key_behaviour, ref

    base = dict(truth=ref("a"), render=ref("b"), capture=ref("c"))
    assert_key_behaviour(production_tasks.score_shot, base,
                         misses={"truth": {"truth": ref("d")}, "render": {"render": ref("e")},
                                 "capture": {"capture": ref("f")}, "enhanced": {"enhanced": ref("1")},
                                 "actors": {"actors": [1]}, "margin": {"margin_m": 0.05}},
                         hits={"the default margin, spelled out": {"margin_m": 0.03}})
