"""The truth of a synthetic capture for any camera (volcap_core/synth/truth.py): rebuilt from
ground_truth/scene.json, it reproduces a capture camera's footage to within the sensor's noise.

One static pinhole camera of demo_scene, 3 frames (about 2 s to synthesize, 1 s to rebuild)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from volcap_core.synth import synthesize_capture
from volcap_core.synth.ground_truth import GroundTruthFiles, performer_mask
from volcap_core.synth.io import read_exr
from volcap_core.synth.sensor import SensorModel
from volcap_core.synth.truth import capture_camera, render_truth, truth_world, truth_world_from_folder

CAMERA = "S000"


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("truth") / "cap"
    synthesize_capture(root, rig="demo_scene", seed=0, frames=3, supersample=2, cameras=[CAMERA], write_depth=True)
    return root


@pytest.fixture(scope="module")
def world(capture):
    return truth_world_from_folder(capture)


def _cameras(capture) -> dict:
    return json.loads((capture / "ground_truth" / "cameras.json").read_text())


def test_a_capture_cameras_truth_through_its_sensor_without_noise_is_its_footage(capture, world):
    cams = _cameras(capture)
    gt = cams["cameras"][CAMERA]
    sensor = SensorModel.from_json(gt["photometric"])
    k = 1
    truth = render_truth(world, capture_camera(cams, CAMERA, k), k / cams["fps"], content="all", supersample=2)
    expected = sensor.apply(truth.rgb, None)
    frame = read_exr(capture / "frames" / CAMERA / f"{k - gt['take_offset']:06d}.exr")
    neighbour = read_exr(capture / "frames" / CAMERA / f"{k + 1 - gt['take_offset']:06d}.exr")
    # the residual is the sensor's noise: its variance read² + shot·S, per pixel and channel
    signal = np.maximum(expected - np.asarray(sensor.black, np.float32), 0)
    z2 = ((frame - expected) ** 2 / (sensor.read_noise ** 2 + sensor.shot_noise * signal)).mean()
    assert 0.9 < z2 < 1.1, z2
    # where the performers are, the next frame is far from this frame's truth, the frame itself is not
    actors = performer_mask((capture / "ground_truth" / "masks" / CAMERA / f"{k:06d}.exr").read_bytes()) > 0
    assert actors.sum() > 200
    rms_self = np.sqrt(((frame - expected)[actors] ** 2).mean())
    rms_next = np.sqrt(((neighbour - expected)[actors] ** 2).mean())
    assert rms_self < 0.25 * rms_next, (rms_self, rms_next)


def test_the_performers_truth_is_their_masked_radiance_over_nothing(capture, world):
    cams = _cameras(capture)
    for k in range(3):
        cam = capture_camera(cams, CAMERA, k)
        stage = render_truth(world, cam, k / cams["fps"], content="stage", supersample=2)
        full = render_truth(world, cam, k / cams["fps"], content="all", supersample=2)
        mask = performer_mask((capture / "ground_truth" / "masks" / CAMERA / f"{k:06d}.exr").read_bytes())
        off = np.abs(stage.alpha - mask) > 0
        assert off.mean() < 1e-3 and np.abs(stage.alpha - mask).max() <= 0.25, off.sum()
        assert (stage.alpha > 0).sum() > 200
        inside, outside = stage.alpha == 1, stage.alpha == 0
        np.testing.assert_allclose(stage.rgb[inside], full.rgb[inside], atol=1e-6)
        assert not stage.rgb[outside].any()
        # premultiplied: an edge pixel's colour is at most its alpha times the brightest part
        assert (stage.rgb.max(axis=-1) <= stage.alpha * full.rgb.max() + 1e-6).all()
        rgba = stage.rgba
        assert rgba.shape == (cam.height, cam.width, 4) and np.array_equal(rgba[..., 3], stage.alpha)
        assert (full.rgba[..., 3] == 1).all()


def _files(capture, scene: dict) -> GroundTruthFiles:
    data = json.dumps(scene).encode()
    return GroundTruthFiles("tampered", {"scene.json": "scene"}, lambda digest: data)


def test_a_world_that_does_not_match_scene_json_is_refused(capture):
    from volcap_core.capture import CaptureFolder

    rig = CaptureFolder.open(capture).rig
    scene = json.loads((capture / "ground_truth" / "scene.json").read_text())
    rebuilt = truth_world(_files(capture, scene), rig)
    for actor, want in zip(rebuilt.actors, scene["actors"], strict=True):
        for name, colour in want["colours_linear"].items():
            np.testing.assert_allclose(actor.colours[name], colour, atol=1e-6)
    scene["seed"] = 1   # another seed: other actors than the file's
    with pytest.raises(ValueError, match=r"capture tampered: the world rebuilt from ground_truth/scene.json: .*"
                                         r"actor 0 rebuilt from \(seed 1, .* does not match what the file records"):
        truth_world(_files(capture, scene), rig)
    scene["seed"] = 0
    scene["actors"][1]["frames"][0]["parts"][3]["centre_m"][2] += 0.01   # a head 1 cm off
    with pytest.raises(ValueError, match=r"actors\[1\]\.frames\[0\]\.parts\[3\]\.centre_m\[2\]"):
        truth_world(_files(capture, scene), rig)


def test_a_capture_without_synthetic_ground_truth_is_refused_by_name(capture, tmp_path):
    from volcap_core.capture import CaptureFolder

    rig = CaptureFolder.open(capture).rig
    with pytest.raises(ValueError, match="capture real has no synthetic ground truth"):
        truth_world(GroundTruthFiles("real", {"cameras.json": "x"}, lambda d: b"{}"), rig)
    desc = json.loads((capture / "capture.json").read_text())
    del desc["ground_truth"]
    (tmp_path / "capture.json").write_text(json.dumps(desc))
    (tmp_path / "frames").symlink_to(capture / "frames")
    with pytest.raises(ValueError, match=f"capture {desc['name']} has no synthetic ground truth "
                                         r"\(.*capture.json names no ground_truth folder\)"):
        truth_world_from_folder(tmp_path)
