"""Shots: parsing and its errors, interpolation, camera convention, cropped EXR frames."""

import io
import json
import math
import os
import tempfile

import numpy as np
import OpenEXR
import pytest
import torch

from volcap_core.imageio.read import decode_exr
from volcap_core.production.performance import Performance, PerformanceSegment
from volcap_core.production.shot import (
    ShotError,
    alpha_crop_window,
    camera_at,
    encode_shot_exr,
    load_shot,
    render_shot_frame,
)
from volcap_core.records import ArtifactRef
from volcap_core.splat.model import Poly4DGS, Poly4DGSConfig
from volcap_core.stage import stage_volume


def shot_dict(**overrides):
    d = {
        "format": "volcap-shot/1",
        "name": "sc12_cu_anna",
        "performance": "take3",
        "frames": [0, 48],
        "fps": 24,
        "resolution": [64, 36],
        "sensor_mm": [36.0, 20.25],
        "enhance": True,
        "keyframes": [
            {"frame": 0, "position": [4.0, 0.0, 1.6], "look_at": [0.0, 0.0, 1.5], "focal_mm": 35},
            {"frame": 24, "position": [0.0, 4.0, 1.7], "look_at": [0.0, 0.0, 1.5], "focal_mm": 70,
             "roll_deg": 4},
            {"frame": 47, "position": [-4.0, 0.0, 1.6], "orientation": [0.5, -0.5, 0.5, -0.5],
             "focal_mm": 50},
        ],
    }
    d.update(overrides)
    return d


def project(cam, point):
    x = cam.world_to_camera.double() @ torch.tensor([*point, 1.0], dtype=torch.float64)
    uv = cam.K.double() @ x[:3]
    return (uv[:2] / uv[2]).tolist(), float(x[2])


def test_parse_file_and_defaults(tmp_path):
    path = tmp_path / "shot.json"
    path.write_text(json.dumps(shot_dict()))
    shot = load_shot(path)
    assert shot.name == "sc12_cu_anna" and shot.enhance and len(shot.keyframes) == 3
    assert shot.interpolation.position == "catmull-rom" and shot.interpolation.focal == "log"
    assert shot.axes == "opencv" and shot.up == (0, 0, 1)
    assert shot.time_at(12) == 0.5
    assert load_shot(shot_dict(sensor_mm=36.0)).sensor_size_mm == (36.0, 20.25)


def test_look_at_keyframes_put_the_target_at_the_image_centre():
    shot = load_shot(shot_dict())
    for frame in (0, 5, 12.5, 24):      # keys and frames between two look-at keys
        cam = camera_at(shot, frame)
        (u, v), depth = project(cam, (0.0, 0.0, 1.5))
        if frame in (0, 12.5):
            assert u == pytest.approx(32.0, abs=1e-4) and v == pytest.approx(18.0, abs=1e-4)
        assert depth > 0
    # keyframe 1 has a roll: the target stays centred, the horizon tilts
    (u, v), _ = project(camera_at(shot, 24), (0.0, 0.0, 1.5))
    assert (u, v) == pytest.approx((32.0, 18.0), abs=1e-4)
    # intrinsics from focal and sensor
    cam = camera_at(shot, 0)
    assert float(cam.K[0, 0]) == pytest.approx(35 * 64 / 36)
    assert float(cam.K[1, 1]) == pytest.approx(35 * 36 / 20.25)
    assert float(cam.K[0, 2]) == 32 and float(cam.K[1, 2]) == 18
    # up is up: a point above the target appears above the centre (smaller v)
    (_, v_up), _ = project(cam, (0.0, 0.0, 1.9))
    assert v_up < 18.0


def test_orientation_conventions_and_roll_sign():
    base = {"frame": 0, "position": [0, 0, 0], "focal_mm": 36}
    cv = camera_at(load_shot(shot_dict(keyframes=[{**base, "orientation": [1, 0, 0, 0]}])), 0)
    assert project(cv, (0, 0, 5))[0] == pytest.approx([32, 18])           # opencv: looks along +z
    gl = camera_at(load_shot(shot_dict(axes="opengl",
                                       keyframes=[{**base, "orientation": [1, 0, 0, 0]}])), 0)
    assert project(gl, (0, 0, -5))[0] == pytest.approx([32, 18])          # opengl: along -z
    (u, v), _ = project(gl, (0, 1, -5))                                  # +y is up in the image
    assert v < 18
    # positive roll: the scene turns counter-clockwise in the image
    rolled = camera_at(load_shot(shot_dict(keyframes=[{**base, "orientation": [1, 0, 0, 0],
                                                       "roll_deg": 10}])), 0)
    (u0, v0), _ = project(cv, (1, 0, 5))
    (u1, v1), _ = project(rolled, (1, 0, 5))
    assert v0 == pytest.approx(18) and v1 < 18 and u1 < u0


def test_interpolation_modes():
    keys = [{"frame": 0, "position": [0, 0, 0], "orientation": [1, 0, 0, 0], "focal_mm": 20},
            {"frame": 10, "position": [1, 0, 0], "orientation": [math.cos(0.5), 0, math.sin(0.5), 0],
             "focal_mm": 80},
            {"frame": 20, "position": [1, 1, 0], "orientation": [1, 0, 0, 0], "focal_mm": 80}]
    lin = load_shot(shot_dict(keyframes=keys, interpolation={"position": "linear",
                                                             "focal": "linear"}))
    cr = load_shot(shot_dict(keyframes=keys))
    from volcap_core.production.shot import camera_pose_at
    p, R, f = camera_pose_at(lin, 5)
    assert p == pytest.approx([0.5, 0, 0]) and f == pytest.approx(50)
    p, R, f = camera_pose_at(cr, 5)
    assert f == pytest.approx(40)                                       # log: geometric mean
    # slerp: half-way rotation is half the angle (1 rad about y -> 0.5 rad)
    angle = math.acos((np.trace(R) - 1) / 2)
    assert angle == pytest.approx(0.5, abs=1e-9)
    # Catmull-Rom passes through the keys and is C1 at an interior key
    for k in keys:
        assert camera_pose_at(cr, k["frame"])[0] == pytest.approx(k["position"])
    h = 1e-4
    v_in = (camera_pose_at(cr, 10)[0] - camera_pose_at(cr, 10 - h)[0]) / h
    v_out = (camera_pose_at(cr, 10 + h)[0] - camera_pose_at(cr, 10)[0]) / h
    assert np.allclose(v_in, v_out, atol=1e-3) and np.allclose(v_in, [0.05, 0.05, 0], atol=1e-3)
    # before the first / after the last key: hold
    assert camera_pose_at(cr, -5)[0] == pytest.approx([0, 0, 0])
    assert camera_pose_at(cr, 30)[0] == pytest.approx([1, 1, 0])


@pytest.mark.parametrize("change, needles", [
    (lambda d: d["keyframes"].reverse(),
     ["sc12_cu_anna", "sorted", "keyframe 1 (frame 24)", "keyframe 0 (frame 47)"]),
    (lambda d: d["keyframes"][1].update(focal_mm=0),
     ["sc12_cu_anna", "keyframe 1 (frame 24): focal_mm", "greater than 0", "got 0"]),
    (lambda d: d["keyframes"][0].update(orientation=[1, 0, 0, 0]),
     ["keyframe 0 (frame 0)", "exactly one of 'orientation' and 'look_at' (both given)"]),
    (lambda d: d["keyframes"][2].pop("orientation"),
     ["keyframe 2 (frame 47)", "(neither given)"]),
    (lambda d: d["keyframes"][0].update(look_at=[4.0, 0.0, 1.6]),
     ["keyframe 0 (frame 0)", "is the camera position itself"]),
    (lambda d: d["keyframes"][0].update(look_at=[4.0, 0.0, 9.0]),
     ["keyframe 0 (frame 0)", "looks along 'up'"]),
    (lambda d: d.update(sensor_mm=[36, 24]), ["sensor 36x24 mm", "give a sensor height of 20.250"]),
    (lambda d: d.update(frames=[10, 10]), ["frames [10, 10) is empty"]),
    (lambda d: d.update(focal=3), ["focal", "Extra inputs are not permitted"]),
    (lambda d: d.update(keyframes=[]), ["keyframes", "at least 1"]),
])
def test_invalid_shots_name_shot_and_keyframe(change, needles):
    d = shot_dict()
    change(d)
    with pytest.raises(ShotError) as info:
        load_shot(d, where="shots/sc12.json")
    msg = str(info.value)
    assert "shots/sc12.json" in msg
    for needle in needles:
        assert needle in msg, msg


def test_unreadable_files(tmp_path):
    with pytest.raises(ShotError, match="not found"):
        load_shot(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{nope")
    with pytest.raises(ShotError, match="not valid JSON"):
        load_shot(bad)


def test_crop_window():
    a = np.zeros((20, 30), np.float32)
    assert alpha_crop_window(a, 0.01, 2) is None
    a[5:8, 10:12] = 0.5
    assert alpha_crop_window(a, 0.01, 2) == (8, 3, 13, 9)
    assert alpha_crop_window(a, 0.6, 2) is None
    a[0, 29] = 1
    assert alpha_crop_window(a, 0.01, 3) == (7, 0, 29, 10)


def read_exr(data: bytes):
    """Header and RGBA pixels (data window) through the OpenEXR bindings (they read paths)."""
    fd, path = tempfile.mkstemp(suffix=".exr")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        f = OpenEXR.File(path)
        header = dict(f.header())
        pixels = f.channels()["RGBA"].pixels
    finally:
        os.unlink(path)
    return header, pixels


def test_exr_is_cropped_half_rgba_with_camera_metadata():
    shot = load_shot(shot_dict(crop={"alpha_threshold": 0.01, "margin_px": 3}))
    cam = camera_at(shot, 12)
    rgba = np.zeros((36, 64, 4), np.float32)
    rgba[10:20, 30:40, :3] = 2.5                          # HDR, premultiplied
    rgba[10:20, 30:40, 3] = 1.0
    rgba[25, 5, 3] = 0.005                                 # below the threshold: cropped away
    data = encode_shot_exr(rgba, cam, shot, 12)
    header, pixels = read_exr(data)
    (x0, y0), (x1, y1) = (tuple(v) for v in header["dataWindow"])
    assert (x0, y0, x1, y1) == (27, 7, 42, 22)
    assert tuple(header["displayWindow"][1]) == (63, 35)
    assert pixels.dtype == np.float16 and pixels.shape == (16, 16, 4)
    assert np.array_equal(pixels.astype(np.float32), rgba[7:23, 27:43])
    assert header["volcap.shot"] == "sc12_cu_anna" and header["volcap.frame"] == 12
    assert header["volcap.performance"] == "take3"
    assert float(header["volcap.time"][0]) == 0.5
    assert np.allclose(header["volcap.K"], cam.K.double().numpy())
    assert np.allclose(header["volcap.worldToCamera"], cam.world_to_camera.double().numpy())
    focal_mm = float(header["volcap.focalMm"][0])
    assert focal_mm == pytest.approx(float(cam.K[0, 0]) * 36 / 64, rel=1e-6)
    assert 35 < focal_mm < 70 and tuple(header["volcap.sensorMm"]) == (36.0, 20.25)
    # the standard worldToCamera: row vectors, y up, z forward
    M = header["worldToCamera"].astype(np.float64)
    centre = cam.centre.double().numpy()
    forward = cam.world_to_camera[2, :3].double().numpy()        # camera z axis in world
    down = cam.world_to_camera[1, :3].double().numpy()
    in_front = np.append(centre + 2 * forward, 1) @ M
    above = np.append(centre + 2 * forward - 0.5 * down, 1) @ M
    assert in_front[:3] == pytest.approx([0, 0, 2], abs=1e-4) and above[1] == pytest.approx(0.5, abs=1e-4)
    # the project's own reader reads the crop
    px, channels = decode_exr(data)
    assert channels == ("R", "G", "B", "A") and px.shape == (16, 16, 4)


def test_empty_frame_keeps_a_pixel():
    shot = load_shot(shot_dict())
    data = encode_shot_exr(np.zeros((36, 64, 4), np.float32), camera_at(shot, 0), shot, 0)
    header, pixels = read_exr(data)
    assert header["volcap.empty"] == 1 and pixels.shape == (1, 1, 4)


def test_render_shot_frame_end_to_end():
    """An actor (a cluster at 1.5 m) on a floor of Gaussians (the set): a ``stage`` shot renders
    and crops to the actor; an ``all`` shot shows the floor too, and its crop grows."""
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    n, m = 30, 400
    cfg = Poly4DGSConfig(mean_degree=1, quat_degree=0, scale_degree=0, opacity_degree=1,
                         sh_degree=0)
    actor = torch.randn(n, 3, generator=g) * 0.15 + torch.tensor([0, 0, 1.5])
    floor = torch.cat([(torch.rand(m, 2, generator=g) - 0.5) * 6, torch.zeros(m, 1)], 1)
    model = Poly4DGS.from_points(cfg, torch.cat([actor, floor]), torch.rand(n + m, 3, generator=g),
                                 scales=torch.full((n + m,), 0.05), t0=torch.full((n + m,), 1.0), opacity=0.9,
                                 lifespan_s=100.0)
    ref = ArtifactRef(digest="blake3:" + "ab" * 32, size=1)
    perf = Performance(name="take3", capture=ref, fps=24, segments=(
        PerformanceSegment(model=ref, frames=(0, 48), core=(0, 48)),))
    stage = stage_volume((4.0, 4.0, 3.5))
    windows = {}
    for content in ("stage", "all"):
        shot = load_shot({**shot_dict(), "content": content, "resolution": [256, 144]})
        data = render_shot_frame(shot, perf, lambda r: model, 0, backend="torch", stage=stage)  # the wide end
        header, pixels = read_exr(data)
        (x0, y0), (x1, y1) = (tuple(v) for v in header["dataWindow"])
        windows[content] = (x1 - x0 + 1) * (y1 - y0 + 1)
        assert pixels[..., 3].max() > 0.5 and header["volcap.frame"] == 0
        assert header["volcap.content"] == content
    assert 0 < windows["stage"] < 0.5 * 256 * 144             # cropped to the actor
    assert windows["all"] > 1.5 * windows["stage"]            # the floor widens it
    shot = load_shot(shot_dict())
    with pytest.raises(ValueError, match="stage volume"):
        render_shot_frame(shot, perf, lambda r: model, 24, backend="torch")
    with pytest.raises(ValueError, match="outside its frames"):
        render_shot_frame(shot, perf, lambda r: model, 48, backend="torch", stage=stage)


# ---------------------------------------------------------------------------------------------
# The exact flow in the frames


def _moving_actor(velocity=(0.4, 0.2, 0.0)):
    """An actor: a cluster of 60 Gaussians at 1.5 m moving at ``velocity`` m/s, plus a floor (the
    set, outside the stage volume)."""
    g = torch.Generator().manual_seed(1)
    n, m = 60, 200
    cfg = Poly4DGSConfig(mean_degree=1, quat_degree=0, scale_degree=0, opacity_degree=1, sh_degree=0)
    actor = torch.randn(n, 3, generator=g) * 0.15 + torch.tensor([0, 0, 1.5])
    floor = torch.cat([(torch.rand(m, 2, generator=g) - 0.5) * 6, torch.zeros(m, 1)], 1)
    model = Poly4DGS.from_points(cfg, torch.cat([actor, floor]), torch.rand(n + m, 3, generator=g),
                                 scales=torch.full((n + m,), 0.06), t0=torch.full((n + m,), 1.0), opacity=0.9,
                                 lifespan_s=float("inf"))
    model.params["means_t"][:n, 0] = torch.tensor(velocity)
    return model


def _channels(data: bytes) -> set:
    return set(OpenEXR.File(io.BytesIO(data)).channels())


def test_shot_frames_carry_the_exact_flow_to_the_previous_frame():
    """Frame 0 has no flow; frame 1 has ``flow.x``/``flow.y`` over its data window, equal (to half
    precision) to :func:`render_performance_flow`, and warping frame 0 with it gives frame 1
    better than no motion compensation (against analytic ground truth: tests/splat/test_rendered_flow.py).
    Readers of RGBA are unaffected."""
    from volcap_core.enhance.production import read_shot_frame
    from volcap_core.enhance.temporal import in_frame, warp
    from volcap_core.production.shot import render_performance_flow

    torch.set_num_threads(1)
    model = _moving_actor()
    ref = ArtifactRef(digest="blake3:" + "ab" * 32, size=1)
    perf = Performance(name="take3", capture=ref, fps=24, segments=(
        PerformanceSegment(model=ref, frames=(0, 48), core=(0, 48)),))
    stage = stage_volume((4.0, 4.0, 3.5))
    shot = load_shot({**shot_dict(), "resolution": [128, 72], "sensor_mm": 36.0})
    d0, d1 = (render_shot_frame(shot, perf, lambda r: model, f, backend="torch", stage=stage) for f in (6, 7))
    first = render_shot_frame(shot, perf, lambda r: model, 0, backend="torch", stage=stage)
    assert _channels(first) == {"RGBA"} and _channels(d1) == {"RGBA", "flow.x", "flow.y"}
    assert decode_exr(d1)[1] == ("R", "G", "B", "A")                        # RGBA readers: unchanged
    plain = render_shot_frame(shot, perf, lambda r: model, 7, backend="torch", stage=stage, flow=False)
    assert _channels(plain) == {"RGBA"}
    _, prev = read_shot_frame(d0)
    header, cur, flow = read_shot_frame(d1, with_flow=True)
    assert np.array_equal(cur, read_shot_frame(plain)[1])                   # the colour is the same render
    exact = render_performance_flow(perf, lambda r: model, camera_at(shot, 7), shot.time_at(7), camera_at(shot, 6),
                                    shot.time_at(6), "torch", volume=stage).numpy()
    (x0, y0), (x1, y1) = (tuple(v) for v in header["dataWindow"])
    window = (slice(y0, y1 + 1), slice(x0, x1 + 1))
    assert np.allclose(flow[window], exact[window], rtol=1e-3, atol=1e-3)  # half precision
    assert not flow[:y0].any() and not flow[y1 + 1:].any()                 # zero outside the crop
    moving = np.linalg.norm(exact, axis=-1)[cur[..., 3] > 0.5]
    assert np.median(moving) > 0.5                                         # it moves (~1 px)
    f = torch.from_numpy(flow).permute(2, 0, 1)
    p, c = (torch.from_numpy(x).permute(2, 0, 1) for x in (prev, cur))
    solid = (-torch.nn.functional.max_pool2d(-c[3][None, None], 3, 1, 1)[0, 0] > 0.5) & (in_frame(f)[0] > 0)
    err = (warp(p, f) - c).abs().amax(0)[solid].mean()
    zero = (p - c).abs().amax(0)[solid].mean()
    assert err < 0.6 * zero, (err, zero)               # measured 0.026 (DIS: 0.028) vs 0.077


def test_no_flow_across_a_segment_boundary_and_a_blended_one_inside_an_overlap():
    """Two segments sharing take frames 24 and 25 (both blended): 23→24 enters the overlap and
    25→26 leaves it (different models: no flow); 24→25 blends the same two segments' exact flows
    (here one model twice: exactly the single-segment flow)."""
    from volcap_core.production.shot import render_performance_flow

    torch.set_num_threads(1)
    model = _moving_actor()
    a, b = (ArtifactRef(digest="blake3:" + c * 64, size=1) for c in "ab")
    perf = Performance(name="take3", capture=a, fps=24, segments=(
        PerformanceSegment(model=a, frames=(0, 26), core=(0, 24)),
        PerformanceSegment(model=b, frames=(24, 48), core=(26, 48))))
    single = Performance(name="take3", capture=a, fps=24, segments=(
        PerformanceSegment(model=a, frames=(0, 48), core=(0, 48)),))
    stage = stage_volume((4.0, 4.0, 3.5))
    shot = load_shot({**shot_dict(), "resolution": [64, 36]})

    def flow(p, f):
        return render_performance_flow(p, lambda r: model, camera_at(shot, f), shot.time_at(f),
                                       camera_at(shot, f - 1), shot.time_at(f - 1), "torch", volume=stage)

    assert flow(perf, 24) is None and flow(perf, 26) is None
    inside, ref = flow(perf, 25), flow(single, 25)
    assert inside is not None and ref.abs().max() > 1.0
    assert torch.allclose(inside, ref, atol=1e-4)
    assert torch.allclose(flow(perf, 23), flow(single, 23), atol=1e-6)    # inside segment 0's core
    data = render_shot_frame(shot, perf, lambda r: model, 24, backend="torch", stage=stage)
    assert _channels(data) == {"RGBA"}                                     # the enhancer will use DIS


def test_encode_shot_exr_writes_the_flow_over_the_crop():
    shot = load_shot(shot_dict(crop={"alpha_threshold": 0.01, "margin_px": 1}))
    cam = camera_at(shot, 5)
    rgba = np.zeros((36, 64, 4), np.float32)
    rgba[10:20, 30:40] = [0.5, 0.5, 0.5, 1.0]
    flow = np.zeros((36, 64, 2), np.float32)
    flow[..., 0], flow[..., 1] = 1.25, -0.5
    data = encode_shot_exr(rgba, cam, shot, 5, flow=flow)
    f = OpenEXR.File(io.BytesIO(data))
    ch = f.channels()
    assert ch["flow.x"].pixels.dtype == np.float16 and ch["flow.x"].pixels.shape == (12, 12)
    assert (ch["flow.x"].pixels == 1.25).all() and (ch["flow.y"].pixels == -0.5).all()
    empty = encode_shot_exr(np.zeros_like(rgba), cam, shot, 5, flow=flow)
    assert _channels(empty) == {"RGBA"}                                    # nothing in view: no flow
    with pytest.raises(ValueError, match="flow must be"):
        encode_shot_exr(rgba, cam, shot, 5, flow=flow[:10])
