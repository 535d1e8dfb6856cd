"""The demo's product stage (flows/demo.py, issue 27): after the reconstruction, a production on the
demo capture delivers an enhanced close-up of one actor, scored against the truth beside its
floors, with the sheet in the output folder.

The end-to-end test runs the stage as ``volcap demo`` runs it, on the smallest settings that
exercise every step: a 4-frame capture of the demo rig's static cameras (no tracking cameras to
calibrate), the ``test`` preset's 20-step segment of its 4 frames trained by the reconstruct flow
as the demo trains its own, then :func:`flows.demo.closeup_production` with the same preset (the
demo preset's Face Rig and enhancer sizes). The pure parts (the shot's framing and width, the
spec) are checked without running anything.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from PIL import Image

from flows.demo import (CLOSEUP_DISTANCE_M, CLOSEUP_FOCAL_MM, CLOSEUP_SENSOR_MM, closeup_shot, closeup_spec,
                        head_track, honest_width)
from volcap_core.production.shot import camera_at, load_shot
from volcap_core.production.spec import parse_spec

STATIC = [f"S00{i}" for i in range(8)]


def _scene(heads, rotations):
    return {"actors": [{"frames": [{"take_index": k, "head_centre_m": h, "head_rotation": r}
                                   for k, (h, r) in enumerate(zip(heads, rotations))]}]}


def test_the_closeup_looks_at_the_head_from_in_front_of_the_face():
    heads = [[0.3, 1.0, 1.6], [0.25, 1.05, 1.61], [0.2, 1.1, 1.62]]
    facing_y = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]      # head local x (facing) = world +y
    heads_m, facing = head_track(_scene(heads, [facing_y] * 3), 0, range(3))
    assert np.allclose(facing, [0, 1, 0])
    shot = load_shot(closeup_shot(heads_m, facing, (0, 3), 24.0, 304, actor="actor0", performance="demo"))
    assert shot.resolution == (304, 172) and shot.enhance and tuple(shot.actors) == ("actor0",)
    for k, head in enumerate(heads):
        cam = camera_at(shot, k)
        x = cam.world_to_camera[:3, :3] @ np.asarray(head) + cam.world_to_camera[:3, 3]
        assert x[2] == pytest.approx(CLOSEUP_DISTANCE_M, abs=1e-4)   # in front, at the close-up's distance
        u, v = cam.K[0, 0] * x[0] / x[2] + cam.K[0, 2], cam.K[1, 1] * x[1] / x[2] + cam.K[1, 2]
        assert (u, v) == pytest.approx((152, 86), abs=1e-3)          # the head at the image centre
        centre = -cam.world_to_camera[:3, :3].T @ cam.world_to_camera[:3, 3]
        assert centre[1] > head[1]                                    # on the side the face looks to
    assert 50 <= CLOSEUP_FOCAL_MM <= 85 and CLOSEUP_SENSOR_MM == 36.0
    with pytest.raises(ValueError, match="no actor 1"):
        head_track(_scene(heads, [facing_y] * 3), 1, range(3))
    with pytest.raises(ValueError, match=r"no ground truth at take indices \[3\]"):
        head_track(_scene(heads, [facing_y] * 3), 0, range(4))


def test_the_closeup_is_no_finer_on_the_head_than_the_finest_footage():
    # 372 px/m (the demo's zoom tracking camera on actor 0's head) at 1.5 m through 65 mm on 36 mm
    w = honest_width(372.0, 65.0, 36.0, 1.5)
    assert w == 304 and w % 16 == 0
    assert (w * 65.0 / 36.0) / 1.5 <= 372.0 < ((w + 16) * 65.0 / 36.0) / 1.5


def test_the_demo_spec_is_a_valid_production_of_one_enhanced_closeup(tmp_path):
    heads, facing = np.array([[0.3, 1.0, 1.6]] * 8), np.array([1.0, 0.0, 0.0])
    shot = closeup_shot(heads, facing, (0, 8), 24.0, 304, actor="actor0", performance="demo")
    data = closeup_spec(str(tmp_path / "store"), "captures/synth-demo_scene-s0", (0, 8), "face_capture", shot,
                        {"preset": "demo", "enhancer_steps": 40})
    spec = parse_spec(yaml.safe_load(yaml.safe_dump(data)), base_dir=tmp_path)
    assert spec.captures["demo"].frames == (0, 8) and spec.captures["demo"].ref == "captures/synth-demo_scene-s0"
    assert spec.captures["face"].folder == "face_capture"
    [actor] = spec.actors
    assert (actor.name, actor.face_capture, actor.index) == ("actor0", "face", 0)
    assert [s.name for s in spec.shots if s.enhance] == ["closeup"]
    assert spec.quality_preset().enhancer_steps == 40


@pytest.mark.slow
def test_the_demo_delivers_an_enhanced_closeup_scored_beside_its_floors(prefect_api, tmp_path):
    """4 min 6 s wall at load average 10 on the 2 shared cores (1 min 36 s of CPU)."""
    from prefect import flow

    from flows.demo import closeup_production
    from flows.ingest import ingest_flow
    from flows.reconstruct import reconstruct_flow
    from flows.runtime import run_flow
    from volcap_core.store import ArtifactStore
    from volcap_core.synth import synthesize_capture

    capture_dir = synthesize_capture(tmp_path / "capture", rig="demo_scene", seed=0, frames=4, supersample=1,
                                     cameras=STATIC).parent
    store = ArtifactStore(str(tmp_path / "store")).url
    out = tmp_path / "demo"
    out.mkdir()

    @flow
    def demo_stage():
        capture = ingest_flow(store=store, capture_dir=str(capture_dir))
        recon = reconstruct_flow(store=store, capture=capture.digest, frames=(0, 4), preset="test")
        segment = ArtifactStore(store).resolve(recon["segments"][0]["model"]["digest"])
        return closeup_production(store, capture_dir, out, capture_ref=capture, segment_ref=segment,
                                  preset="test", enhancer="demo"), segment

    result, segment = run_flow(demo_stage).result
    # the production reused the demo's segment instead of training its own
    assert result["segment_reused"]
    # the sheet: truth | render | error and truth | enhanced | error rows at 3 frames
    sheet = Image.open(result["sheet"])
    assert sheet.width > 3 * result["resolution"][0] and sheet.height > 6 * result["resolution"][1]
    for region in ("face", "performers"):
        rows = result[region]
        assert set(rows) == {"render", "enhanced", "empty", "bicubic"}
        for row in rows.values():
            assert row["psnr"] is not None and row["ssim"] is not None
        # a trained render beats the empty model's on the same pixels
        assert rows["render"]["psnr"] > rows["empty"]["psnr"] + 3
        assert rows["empty"]["detail"] == 0.0
    assert result["floors"]["enhanced"] == ["render", "empty", "bicubic"]
    assert {"truth", "render", "enhanced"} <= set(result["temporal"])
    assert "smoke run" in result["enhancer_budget"] and "~50 min" in result["enhancer_budget"]
    # the frames and the spec are in the output folder; the face capture films the demo actor
    for what in ("render", "enhanced", "truth"):
        assert len(list((out / "closeup" / what).glob("*.exr"))) == 4
    face = json.loads((out / "face_capture" / "capture.json").read_text())
    assert face["performer"]["actor"] == 0
    spec = yaml.safe_load((out / "production.yaml").read_text())
    assert spec["captures"]["demo"]["frames"] == [0, 4] and spec["shots"][0]["enhance"] is True
