"""The same actor in both rigs (issue 27): a Face Rig capture of a Scene Rig capture's actor.

``synthesize_face_capture(actor_of=(scene_dir, n))`` films actor ``n`` of a synthetic Scene Rig
capture: the same person (scale, colours, texture arrays, freckles) with an expression track of
its own, and capture.json says whose actor it is (``performer``). Checked here: the rebuilt
actors, the colours the footage of both rigs shows on the head (an albedo read back from each
capture's frames through its ground truth), the field through ingest, and the refusals.

The captures: the demo scene rig's two head-tracking cameras (S008 follows actor 1, S009 actor 0),
1 frame; the face rig's side camera F002 (the frontal F003 sees the colour chart in front of the
face at the start), 2 frames; one sample per pixel. ~3 s to render both, ~3 s for the ingest
(plus the session's Prefect server, ~25 s when this file starts it), ~10 s for the command line
(five ``volcap synth`` processes, one rendering the whole face rig for one frame)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flows.ingest import ingest_flow
from flows.runtime import run_flow
from volcap_core.calibration.distortion import Distortion
from volcap_core.capture import Capture, CaptureDescription, Performer
from volcap_core.store import ArtifactStore
from volcap_core.synth import read_exr, synthesize_capture, synthesize_face_capture
from volcap_core.synth.actors import HEAD_CENTRE_HEIGHT
from volcap_core.synth.geometry import PinholeCamera, intersect_ellipsoid
from volcap_core.synth.sensor import SensorModel
from volcap_core.synth.stage import Lighting
from volcap_core.synth.synthesize import scene_actors_of

SCENE = "scene-a"
ACTOR = 1           # the face capture films actor 1 (its index there) of the scene capture
HEAD_CAMERA = {0: "S009", 1: "S008"}   # the scene rig's head-tracking camera following each actor
FACE_CAMERA = "F002"


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("same-actor")
    synthesize_capture(root / "scene", frames=1, supersample=1, cameras=sorted(HEAD_CAMERA.values()),
                       write_depth=True, name=SCENE)
    synthesize_face_capture(root / "face", frames=2, supersample=1, cameras=[FACE_CAMERA], write_depth=True,
                            actor_of=(root / "scene", ACTOR))
    return {"scene": root / "scene", "face": root / "face"}


def head_albedo(capture: Path, camera: str, take_index: int, actor: int) -> dict[str, np.ndarray]:
    """Median linear albedo (RGB) of an actor's skin and hair as a capture's frame shows them: the
    footage's photometrics undone (``cameras.json`` ``photometric``: black level, gain, channel
    gains, vignetting), divided by the irradiance at each pixel's true head normal (``scene.json``
    lighting and head part), over head pixels that are the visible surface (ground-truth depth).
    Skin: the sides of the face (away from eyes, brows, mouth and cheeks); hair: above the hairline."""
    gt = capture / "ground_truth"
    cam_gt = json.loads((gt / "cameras.json").read_text())["cameras"][camera]
    scene = json.loads((gt / "scene.json").read_text())
    f = cam_gt["frames"][take_index]
    w2c = np.array(f["world_to_camera"])
    cam = PinholeCamera(cam_gt["width"], cam_gt["height"], f["fx"], f["fy"], f["cx"], f["cy"], w2c[:3, :3],
                        w2c[:3, 3], Distortion.from_json(f.get("distortion")))
    ph = cam_gt["photometric"]
    vignette = SensorModel(ph["gain"], tuple(ph["channel_gain"]), tuple(ph["black_offset"]), ph["vignette_k"],
                           tuple(ph["vignette_gradient"]), 0.0, 0.15, 0.0, 0.0).vignette(cam.width, cam.height)
    img = read_exr(capture / "frames" / camera / f"{f['frame']:06d}.exr")[..., :3]
    radiance = (img - np.array(ph["black_offset"])) / (ph["gain"] * vignette[..., None] * np.array(ph["channel_gain"]))
    light = scene["lighting"]
    lighting = Lighting(light["ambient"], light["sky"], light["key"], tuple(light["key_dir"]))
    head = next(p for p in scene["actors"][actor]["frames"][take_index]["parts"] if p["name"] == "head")
    R, centre, semi = np.array(head["rotation"]), np.array(head["centre_m"]), np.array(head["semi_axes_m"])
    d = cam.ray_directions(1)
    t = intersect_ellipsoid(cam.centre, d, centre, R, semi)
    depth = read_exr(gt / "depth" / camera / f"{take_index:06d}.exr").reshape(t.shape)
    seen = np.isfinite(t) & (np.abs(t * (d @ cam.R[2].astype(np.float32)) - depth) < 0.005)
    local = (cam.centre + t[seen][:, None] * d[seen] - centre) @ R
    q = local / semi
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    lon, lat = np.arctan2(q[:, 1], q[:, 0]), np.arcsin(np.clip(q[:, 2], -1, 1))
    normal = (local / semi ** 2) @ R.T
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    albedo = radiance[seen] / lighting.irradiance(normal)[:, None]
    hairline = 0.55 - 0.9 * ((1 - np.cos(lon)) / 2) ** 1.5       # actors.py's, with 0.05 rad of margin
    regions = {"hair": lat > hairline + 0.05,
               "skin": (lat < hairline - 0.05) & (np.abs(lon) > 0.9) & (lat > -0.5) & (lat < 0.3)}
    out = {}
    for name, m in regions.items():
        assert m.sum() >= 200, f"{capture.name} {camera}: only {m.sum()} {name} pixels"
        out[name] = np.median(albedo[m], axis=0)
    return out


def test_the_face_capture_actor_is_the_scene_actor(captures):
    scene = scene_actors_of(captures["scene"] / "ground_truth" / "scene.json")
    [face] = scene_actors_of(captures["face"] / "ground_truth" / "scene.json")
    same = scene[ACTOR]
    assert face.scale == same.scale and face.colours == same.colours
    assert set(face.textures) == set(same.textures)
    for name, tex in face.textures.items():
        assert all(np.array_equal(a, b) for a, b in zip(tex.levels, same.textures[name].levels)), name
    np.testing.assert_array_equal(face.freckles, same.freckles)
    assert face.colours != scene[1 - ACTOR].colours
    # standing at the face rig's centre facing +x, on a riser that puts the rest head at 1.7 m
    gt = json.loads((captures["face"] / "ground_truth" / "scene.json").read_text())
    rec = gt["actors"][0]
    assert rec["riser_m"] == pytest.approx(1.7 - HEAD_CENTRE_HEIGHT * same.scale, abs=1e-6)
    assert rec["frames"][0]["root_m"][2] == pytest.approx(rec["riser_m"], abs=1e-6)
    assert rec["frames"][0]["yaw_rad"] == 0.0 and not rec["walking"]
    head = np.array(rec["frames"][0]["head_centre_m"])
    assert abs(head[2] - 1.7) < 0.02 and np.linalg.norm(head[:2]) < 0.05
    # its own performance: the expression and head pose differ from the scene take's at the same instant
    scene_gt = json.loads((captures["scene"] / "ground_truth" / "scene.json").read_text())
    walking = scene_gt["actors"][ACTOR]["frames"][0]
    assert rec["frames"][0]["expression"] != walking["expression"]
    assert rec["frames"][0]["expression"] != rec["frames"][1]["expression"]
    # what scene.json records of whose actor it is
    assert gt["performer"] == {"capture": SCENE, "actor": ACTOR, "seed": 0, "rig": "demo_scene",
                               "stage_size_m": scene_gt["stage"]["size_m"], "actors": 2, "head_height_m": 1.7}


def test_both_rigs_footage_shows_the_same_skin_and_hair(captures):
    """The head's skin and hair albedo read back from the face capture's frame and from the scene
    capture's head-tracking camera agree within 8 % (the two cameras' noise, the tracking camera's
    veiling glare, the black level on the dark hair: 1-6 % here), and differ from the other
    actor's by more than 25 %."""
    face = head_albedo(captures["face"], FACE_CAMERA, 1, 0)
    same = head_albedo(captures["scene"], HEAD_CAMERA[ACTOR], 0, ACTOR)
    other = head_albedo(captures["scene"], HEAD_CAMERA[1 - ACTOR], 0, 1 - ACTOR)
    for region in ("skin", "hair"):
        np.testing.assert_allclose(face[region], same[region], rtol=0.08, err_msg=region)
        assert np.abs(face[region] / other[region] - 1).max() > 0.25, region


def test_capture_json_records_the_performer_and_ingest_keeps_it(captures, prefect_api, tmp_path):
    desc = CaptureDescription.model_validate_json((captures["face"] / "capture.json").read_text())
    assert desc.performer == Performer(capture=SCENE, actor=ACTOR)
    store = ArtifactStore(str(tmp_path / "store")).url
    capture = ArtifactStore(store).get_record(run_flow(ingest_flow, store=store,
                                                       capture_dir=str(captures["face"])).result, Capture)
    assert capture.performer == desc.performer
    # a capture that names no performer: no field in capture.json nor in the record
    plain = CaptureDescription.model_validate_json((captures["scene"] / "capture.json").read_text())
    assert plain.performer is None and "performer" not in json.loads((captures["scene"] / "capture.json").read_text())
    assert "performer" not in capture.model_copy(update={"performer": None}).model_dump(mode="json")


def test_without_actor_of_the_face_capture_has_its_own_actor(tmp_path, captures):
    path = synthesize_face_capture(tmp_path / "own", frames=1, supersample=1, cameras=[FACE_CAMERA])
    assert "performer" not in json.loads(path.read_text())
    gt = json.loads((path.parent / "ground_truth" / "scene.json").read_text())
    assert "performer" not in gt and "riser_m" not in gt["actors"][0]
    [own] = scene_actors_of(path.parent / "ground_truth" / "scene.json")
    assert all(own.colours != a.colours for a in scene_actors_of(captures["scene"] / "ground_truth" / "scene.json"))


def test_a_folder_that_is_not_a_synthetic_scene_capture_is_refused_by_name(captures, tmp_path):
    def refused(folder, index, match):
        with pytest.raises(ValueError, match=match) as info:
            synthesize_face_capture(tmp_path / "out", frames=1, supersample=1, cameras=[FACE_CAMERA],
                                    actor_of=(folder, index))
        assert "\n" not in str(info.value) and str(folder) in str(info.value)

    refused(tmp_path / "nowhere", 0, "no capture description")
    refused(captures["face"], 0, "is a face capture, not a Scene Rig capture")
    refused(captures["scene"], 2, "has actors 0..1, no actor 2")
    real = tmp_path / "real"
    real.mkdir()
    desc = json.loads((captures["scene"] / "capture.json").read_text())
    del desc["ground_truth"]
    (real / "capture.json").write_text(json.dumps(desc))
    refused(real, 0, "is not a synthetic capture")
    assert not (tmp_path / "out").exists()          # refused before anything is written


def test_a_scene_json_the_rebuild_does_not_match_is_refused(captures, tmp_path):
    """A capture synthesized by a version that drew other actors: the file, actor and value named."""
    old = tmp_path / "old"
    shutil.copytree(captures["scene"], old)
    path = old / "ground_truth" / "scene.json"
    gt = json.loads(path.read_text())
    gt["actors"][1]["colours_linear"]["hair"][0] += 0.01
    path.write_text(json.dumps(gt))
    with pytest.raises(ValueError, match=r"actor 1 rebuilt from .* does not match .*colours_linear\.hair\[0\].*"
                                         r"another version of volcap"):
        synthesize_face_capture(tmp_path / "out", frames=1, supersample=1, cameras=[FACE_CAMERA], actor_of=(old, 1))
    gt["actors"][1]["colours_linear"]["hair"][0] -= 0.01
    gt["actors"][0]["frames"][0]["parts"][3]["centre_m"][2] += 0.001      # the head, moved 1 mm
    path.write_text(json.dumps(gt))
    with pytest.raises(ValueError, match=r"actor 0 rebuilt .*frames\[0\]\.parts\[3\]\.centre_m\[2\]"):
        scene_actors_of(path)


def test_volcap_synth_actor_of(captures, tmp_path):
    """``volcap synth OUT --rig demo_face --actor-of DIR:N``; a bad one is one line on stderr."""
    repo = Path(__file__).resolve().parents[1]

    def volcap(*args):
        return subprocess.run([sys.executable, "-m", "flows.cli", "synth", *args], capture_output=True, text=True,
                              cwd=repo)

    out = tmp_path / "face"
    done = volcap(str(out), "--rig", "demo_face", "--frames", "1", "--actor-of", f"{captures['scene']}:{ACTOR}")
    assert done.returncode == 0, done.stderr
    assert json.loads((out / "capture.json").read_text())["performer"] == {"capture": SCENE, "actor": ACTOR}
    for bad, says in ((f"{captures['scene']}:7", "no actor 7"), (str(captures["scene"]), "SCENE_CAPTURE_DIR:N"),
                      (f"{tmp_path / 'nowhere'}:0", "no capture description")):
        failed = volcap(str(tmp_path / "bad"), "--rig", "demo_face", "--actor-of", bad)
        lines = failed.stderr.strip().splitlines()
        assert failed.returncode == 1 and len(lines) == 1 and says in lines[0], failed.stderr
    failed = volcap(str(tmp_path / "bad"), "--actor-of", f"{captures['scene']}:0")      # the scene rig
    assert failed.returncode == 1 and "--actor-of is for face rigs" in failed.stderr
