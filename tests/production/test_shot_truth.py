"""The truth of a shot of a synthetic capture (volcap_core/production/truth.py, the render-truth
task, `volcap truth`): the shot's own camera, encoded like its render frames, from the store.

One static camera of demo_scene, 3 frames (about 3 s to synthesize); the CLI test ingests it and
renders a 2-frame close-up in a subprocess (about 15 s; slow), the refusal of a capture without
ground truth costs the command's imports (about 10 s)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from tests.test_cache_keys import assert_key_behaviour, ref
from tests.test_cli import last_json, volcap
from tests.test_ingest import make_capture
from tasks.production import render_shot_truth
from volcap_core.capture import Capture, CaptureFolder
from volcap_core.enhance.production import read_shot_frame
from volcap_core.production.shot import alpha_crop_window, load_shot
from volcap_core.production.truth import TRUTH_KIND, render_truth_frame, truth_world_of
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture
from volcap_core.synth.geometry import PinholeCamera
from volcap_core.synth.truth import capture_camera, render_truth, truth_world_from_folder

CAMERA = "S000"


@pytest.fixture
def api_env(prefect_api):
    """The command in a subprocess talks to the session's temporary Prefect server."""
    import os

    from prefect.settings import PREFECT_API_URL

    return {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value()}


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("shot-truth") / "cap"
    synthesize_capture(root, rig="demo_scene", seed=0, frames=3, supersample=2, cameras=[CAMERA])
    return root


@pytest.fixture(scope="module")
def world(capture):
    return truth_world_from_folder(capture)


def _cameras(capture) -> dict:
    return json.loads((capture / "ground_truth" / "cameras.json").read_text())


def _shot_at_capture_camera(capture, k: int, **kw):
    """A one-frame shot at capture camera S000's pose, focal and resolution at take index k (a
    shot's principal point is the image centre; the camera's is ~1 px off it)."""
    cam = capture_camera(_cameras(capture), CAMERA, k)
    x, y, z, w = Rotation.from_matrix(cam.R.T).as_quat()   # camera-to-world, OpenCV axes
    shot = {"name": "s000", "performance": "demo", "frames": [k, k + 1], "fps": 24,
            "resolution": [cam.width, cam.height], "sensor_mm": 36.0,
            "keyframes": [{"frame": k, "position": cam.centre.tolist(), "orientation": [w, x, y, z],
                           "focal_mm": cam.fx * 36.0 / cam.width}], **kw}
    centred = PinholeCamera(cam.width, cam.height, cam.fx, cam.fx, (cam.width - 1) / 2, (cam.height - 1) / 2,
                            cam.R, cam.t)
    return load_shot(shot), centred


def test_a_shot_truth_frame_is_the_truth_of_its_camera_encoded_like_a_render_frame(capture, world):
    k = 1
    shot, centred = _shot_at_capture_camera(capture, k)
    header, rgba = read_shot_frame(render_truth_frame(shot, world, k))
    want = render_truth(world, centred, k / 24.0, content="stage").rgba
    assert rgba.shape == want.shape == (180, 320, 4)
    # half floats of the same pixels: a half-pixel error in the principal point would be far off
    err = np.abs(rgba - want)
    shifted = PinholeCamera(320, 180, centred.fx, centred.fy, centred.cx + 0.5, centred.cy + 0.5, centred.R, centred.t)
    err_shifted = np.abs(rgba - render_truth(world, shifted, k / 24.0, content="stage").rgba)
    assert (err > 2e-3).mean() < 2e-3 and err.mean() < 0.05 * err_shifted.mean(), (err.mean(), err_shifted.mean())
    # the render frames' conventions: full display window, data window = the alpha's crop
    assert header["volcap.truth"] == TRUTH_KIND and header["volcap.content"] == "stage"
    assert header["volcap.truthSupersample"] == 2 and header["volcap.frame"] == k
    (x0, y0), (x1, y1) = (tuple(int(v) for v in p) for p in header["dataWindow"])
    assert (x0, y0, x1, y1) == alpha_crop_window(want[..., 3], shot.crop.alpha_threshold, shot.crop.margin_px)
    assert (x1 - x0 + 1) * (y1 - y0 + 1) < 0.8 * 320 * 180   # cropped to the performers
    np.testing.assert_allclose(np.asarray(header["volcap.K"])[0, 2], 160.0)


def test_an_all_content_shot_truth_is_the_whole_set_opaque(capture, world):
    k = 2
    shot, centred = _shot_at_capture_camera(capture, k, content="all")
    header, rgba = read_shot_frame(render_truth_frame(shot, world, k, supersample=1))
    want = render_truth(world, centred, k / 24.0, content="all", supersample=1)
    assert (rgba[..., 3] == 1).all() and header["volcap.content"] == "all"
    assert [list(p) for p in header["dataWindow"]] == [[0, 0], [319, 179]]
    np.testing.assert_allclose(rgba[..., :3], want.rgb, rtol=2e-3, atol=2e-3)
    with pytest.raises(ValueError, match=r"shot s000: frame 0 is outside its frames \[2, 3\)"):
        render_truth_frame(shot, world, 0)


def test_the_truth_renders_from_the_store_and_only_for_synthetic_captures(capture, world, tmp_path):
    s = ArtifactStore(str(tmp_path / "store"))
    folder = CaptureFolder.open(capture)
    record = Capture(name="demo", rig=folder.rig, fps=24.0, start_timecode="01:00:00:00", frame_count=3, cameras=(),
                     ground_truth=s.put_directory(capture / "ground_truth"))
    shot, _ = _shot_at_capture_camera(capture, 0)
    stored = truth_world_of(s, record)
    assert render_truth_frame(shot, stored, 0) == render_truth_frame(shot, world, 0)
    with pytest.raises(ValueError, match="capture demo has no synthetic ground truth .its record carries no "
                                         "ground_truth tree."):
        truth_world_of(s, record.model_copy(update={"ground_truth": None}))
    (tmp_path / "gt").mkdir()
    (tmp_path / "gt" / "cameras.json").write_bytes((capture / "ground_truth" / "cameras.json").read_bytes())
    with pytest.raises(ValueError, match=r"capture demo has no synthetic ground truth \(its ground truth has no "
                                         r"scene.json\)"):
        truth_world_of(s, record.model_copy(update={"ground_truth": s.put_directory(tmp_path / "gt")}))


def test_render_truth_keys():
    shot = {"name": "s1", "frames": [0, 4]}
    assert_key_behaviour(render_shot_truth, dict(capture=ref("a"), shot=shot),
                         misses={"capture": {"capture": ref("b")}, "shot": {"shot": {**shot, "frames": [0, 5]}},
                                 "supersampling": {"supersample": 4}},
                         hits={"the default, spelled out": {"supersample": 2}})


def _spec(path, capture, shot: dict, store) -> str:
    spec = {"format": "volcap-production/1", "name": "truth-test", "store": str(store), "quality": "test",
            "captures": {shot["performance"]: {"folder": str(capture)}}, "shots": [shot]}
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return str(path)


@pytest.mark.slow
def test_volcap_truth_writes_the_frames_and_names_them_in_the_store(api_env, capture, tmp_path):
    scene = json.loads((capture / "ground_truth" / "scene.json").read_text())
    head = np.asarray(scene["actors"][0]["frames"][0]["head_centre_m"])
    shot = {"name": "cu", "performance": "demo", "frames": [0, 2], "fps": 24, "resolution": [96, 54],
            "sensor_mm": 36, "keyframes": [{"frame": 0, "position": (head + [1.2, 0.3, 0.05]).tolist(),
                                            "look_at": head.tolist(), "focal_mm": 60}]}
    store = tmp_path / "store"
    spec = _spec(tmp_path / "spec.yaml", capture, shot, store)
    res = volcap("truth", spec, "--shot", "cu", "--out", str(tmp_path / "out"), "--json", env=api_env)
    assert res.returncode == 0, res.stderr
    doc = last_json(res.stdout)
    assert doc["ref"] == "productions/truth-test/truth/cu" and doc["frames"] == 2 and doc["tasks_failed"] == 0
    assert doc["out"] == [str(tmp_path / "out" / f"{f:06d}.exr") for f in range(2)]
    s = ArtifactStore(str(store))
    assert s.get_ref("productions/truth-test/truth/cu").digest == doc["truth"]
    tree = s.get_tree(doc["truth"])
    for f in range(2):
        data = (tmp_path / "out" / f"{f:06d}.exr").read_bytes()
        assert data == s.get_bytes(tree[f"{f:06d}.exr"].digest)
        header, rgba = read_shot_frame(data)
        # a close-up of the head: the performer fills the middle of the frame
        assert header["volcap.truth"] == TRUTH_KIND and rgba.shape == (54, 96, 4) and rgba[27, 48, 3] == 1


def test_volcap_truth_refuses_a_capture_without_synthetic_ground_truth(capture, tmp_path):
    real = make_capture(tmp_path / "real")
    shot = {"name": "cu", "performance": "tiny", "frames": [0, 2], "fps": 24, "resolution": [64, 36],
            "sensor_mm": 36, "keyframes": [{"frame": 0, "position": [3, 0, 1.6], "look_at": [0, 0, 1.5],
                                            "focal_mm": 50}]}
    spec = _spec(tmp_path / "spec.yaml", real, shot, tmp_path / "store")
    res = volcap("truth", spec, "--shot", "cu")
    assert res.returncode == 1
    assert res.stderr.strip().splitlines() == [
        f"volcap: error: {spec}: shot cu: capture tiny has no synthetic ground truth ({real / 'capture.json'} "
        "names no ground_truth folder): the truth is rendered only for synthetic captures (volcap synth)"]
    assert not ArtifactStore(str(tmp_path / "store")).list_refs()


def test_a_truth_scored_against_itself_is_perfect_and_an_empty_render_sits_at_its_floor(capture, world):
    """The truth renderer's cropped frames and the scorer meet: the same pixels, the same camera."""
    from volcap_core.production.closeup import score_shot_exrs
    from volcap_core.production.shot import camera_at, encode_shot_exr

    scene = json.loads((capture / "ground_truth" / "scene.json").read_text())
    head = np.asarray(scene["actors"][0]["frames"][0]["head_centre_m"])
    shot = load_shot({"name": "cu", "performance": "demo", "frames": [0, 2], "fps": 24, "resolution": [96, 54],
                      "sensor_mm": 36, "keyframes": [{"frame": 0, "position": (head + [1.2, 0.3, 0.05]).tolist(),
                                                      "look_at": head.tolist(), "focal_mm": 60}]})
    truth = [(f"{f:06d}.exr", render_truth_frame(shot, world, f, supersample=1)) for f in range(2)]
    scores, sheet = score_shot_exrs(truth, truth, scene)
    face = scores["rows"]["render"]["face"]
    assert face["views"] == 2 and face["psnr"] == 200.0 and face["ssim"] == pytest.approx(1.0)
    assert face["detail"] == pytest.approx(1.0)
    # an empty render (a 1x1 data window, as render-shot writes a frame with nothing in it) keeps the truth's camera
    empty = []
    for f, (name, data) in enumerate(truth):
        _, rgba = read_shot_frame(data)
        empty.append((name, encode_shot_exr(np.zeros_like(rgba), camera_at(shot, f), shot, f)))
    scores, _ = score_shot_exrs(truth, empty, scene)
    for region in ("face", "performers"):
        assert scores["rows"]["render"][region]["psnr"] == pytest.approx(scores["rows"]["empty"][region]["psnr"])
    assert sheet.ndim == 3 and sheet.shape[2] == 3
