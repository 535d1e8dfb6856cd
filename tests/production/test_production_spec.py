"""Production spec: validation errors (path, value, line) and what needed_steps decides."""

import json
import re
from pathlib import Path

import pytest
import yaml

from volcap_core.production.presets import PRESETS
from volcap_core.production.segments import SegmentBudget, plan_segments
from volcap_core.production.spec import (
    CaptureInfo,
    SpecError,
    capture_info_from_folder,
    load_spec,
    needed_steps,
    parse_spec,
    segment_plan_for,
)
from volcap_core.splat.mcmc import MCMCConfig

DOCS = Path(__file__).resolve().parents[2] / "docs"


def doc_block(name: str, lang: str) -> str:
    text = (DOCS / name).read_text()
    return re.search(rf"```{lang}\n(.*?)```", text, re.S).group(1)


@pytest.fixture
def doc_spec(tmp_path) -> Path:
    """The example of docs/production-spec.md, with the shot file of docs/shots.md beside it."""
    (tmp_path / "shots").mkdir()
    (tmp_path / "shots" / "sc12_cu_anna.json").write_text(doc_block("shots.md", "json"))
    path = tmp_path / "ep3.yaml"
    path.write_text(doc_block("production-spec.md", "yaml"))
    return path


def info(tracking=True, frames=1440, plan=None):
    return CaptureInfo(has_tracking_cameras=tracking, fps=24, frame_count=frames, width=3840,
                       height=2160, segment_plan=plan)


def ids(steps, kind=None):
    return [s.id for s in steps if kind is None or s.kind == kind]


def test_documented_example_validates_and_plans(doc_spec):
    spec = load_spec(doc_spec)
    assert [s.name for s in spec.shots] == ["sc12_cu_anna", "sc12_wide"]
    assert spec.quality_preset() == PRESETS["production"]
    facts = {"sc12_take3": info(), "anna_face": info(tracking=False, frames=600)}
    steps = needed_steps(spec, facts)
    # sc12_take4 is shown by no shot; ben is in no enhanced shot: neither is touched
    assert not [s for s in steps if "take4" in s.id or "ben" in s.id]
    assert ids(steps, "ingest") == ["ingest:sc12_take3"]                # anna_face is a ref
    assert ids(steps, "calibrate-tracking") == ["calibrate-tracking:sc12_take3"]
    assert ids(steps, "face-pairs") == ["face-pairs:anna"]
    assert ids(steps, "train-enhancer") == ["train-enhancer:anna"]
    assert ids(steps, "enhance-shot") == ["enhance-shot:sc12_cu_anna"]
    # frames [0, 1440) in 13 segments of 113-114 frames (at most 120), overlap 3; the wide shot
    # shows take frames 0..239, the close-up 0..47: only the first three segments are needed
    assert ids(steps, "train-segment") == ["train-segment:sc12_take3:000000-000114",
                                           "train-segment:sc12_take3:000111-000225",
                                           "train-segment:sc12_take3:000222-000336"]
    seg = next(s for s in steps if s.kind == "train-segment")
    assert seg.parameters.gaussians == 11_400_000 and seg.parameters.train_steps == 30_000
    assert len(segment_plan_for(spec, "sc12_take3", facts["sc12_take3"]).segments) == 13
    face = next(s for s in steps if s.kind == "face-pairs")
    # the interim pairs read the face capture's ingested frames (a ref: already ingested) and
    # nothing else: no calibration of a face capture is planned for them
    assert face.inputs == () and face.parameters.face_capture == "anna_face"
    assert not [s.id for s in steps if s.id.endswith(":anna_face")]


def write_spec(tmp_path, data) -> Path:
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def base_spec():
    shot = {"name": "wide", "performance": "take", "frames": [0, 20], "fps": 24,
            "resolution": [64, 36], "sensor_mm": 36,
            "keyframes": [{"frame": 0, "position": [5, 0, 1.6], "look_at": [0, 0, 1.2],
                           "focal_mm": 24}]}
    return {
        "format": "volcap-production/1", "name": "t", "store": "memory://t",
        "quality": "test",
        "rigs": {"scene": "demo_scene", "face": "demo_face"},
        "captures": {"take": {"folder": "/data/take", "rig": "scene"},
                     "other": {"folder": "/data/other", "rig": "scene"},
                     "anna_face": {"ref": "captures/anna_face", "rig": "face"},
                     "ben_face": {"folder": "/data/ben_face", "rig": "face"}},
        "actors": [{"name": "anna", "captures": ["take"], "face_capture": "anna_face"},
                   {"name": "ben", "captures": ["take", "other"], "face_capture": "ben_face"}],
        "shots": [shot,
                  {**shot, "name": "cu_anna", "frames": [60, 70], "actors": ["anna"],
                   "enhance": True}],
    }


@pytest.mark.parametrize("change, needles", [
    (lambda d: d["actors"][0]["captures"].__setitem__(0, "take9"),
     ["actors[0].captures[0]: unknown capture 'take9'", "[line "]),
    (lambda d: d["shots"][1]["keyframes"][0].__setitem__("focal_mm", -5),
     ["shots[1].keyframes[0].focal_mm", "greater than 0", "(got -5)", "[line "]),
    (lambda d: d.__setitem__("quality", "prod"),
     ["quality: unknown preset 'prod' (known: test, demo, preview, production)", "[line 4]"]),
    (lambda d: d.__setitem__("quality", {"preset": "test", "train_stepz": 3}),
     ["quality.train_stepz", "Extra inputs are not permitted"]),
    (lambda d: d.__setitem__("quality", {"preset": "test", "train_steps": 0}),
     ["quality.train_steps", "greater than 0", "(got 0)"]),
    (lambda d: d.__setitem__("store", "s3://AKIA123:secret@bucket/x"),
     ["store: ", "must not carry credentials"]),
    (lambda d: d["captures"]["take"].__setitem__("ref", "captures/take"),
     ["captures.take", "exactly one of 'folder' and 'ref' (both given)"]),
    (lambda d: d["captures"]["take"].__setitem__("rig", "scenery"),
     ["captures.take.rig: 'scenery' is not one of rigs (scene, face)"]),
    (lambda d: d["actors"][1].pop("face_capture") and d["shots"][1].__setitem__("actors", ["ben"]),
     ["shots[1] (cu_anna).enhance: true needs a face capture for actor 'ben'",
      "actors[1].face_capture is not set"]),
    (lambda d: d["shots"][1].__setitem__("performance", "take7"),
     ["shots[1] (cu_anna).performance: unknown capture 'take7'"]),
    (lambda d: d["shots"][1].__setitem__("actors", ["carl"]),
     ["shots[1] (cu_anna).actors: unknown actor 'carl'"]),
    (lambda d: d["shots"].append(dict(d["shots"][0])), ["shot 'wide' is listed twice"]),
    (lambda d: d["captures"]["take"].__setitem__("frames", [10, 5]),
     ["captures.take", "0 <= start < end"]),
    (lambda d: d.__setitem__("shotz", []), ["shotz: Extra inputs are not permitted"]),
    (lambda d: d["shots"].append("shots/missing.json"), ["shots", "shot file 2", "not found"]),
])
def test_spec_errors_name_field_path_and_value(tmp_path, change, needles):
    data = base_spec()
    change(data)
    with pytest.raises(SpecError) as exc:
        load_spec(write_spec(tmp_path, data))
    msg = str(exc.value)
    assert "spec.yaml: invalid production spec" in msg
    for needle in needles:
        assert needle in msg, msg


def test_unreadable_spec(tmp_path):
    with pytest.raises(SpecError, match="not found"):
        load_spec(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1,\n")
    with pytest.raises(SpecError, match="not valid YAML"):
        load_spec(bad)
    bad.write_text("- 1\n")
    with pytest.raises(SpecError, match="a YAML mapping"):
        load_spec(bad)


def facts(take_tracking=True):
    return {"take": info(tracking=take_tracking, frames=100), "other": info(frames=100),
            "anna_face": info(tracking=False, frames=50), "ben_face": info(tracking=False, frames=50)}


def test_no_tracking_calibration_without_tracking_cameras():
    spec = parse_spec(base_spec())
    with_tracking = needed_steps(spec, facts(True))
    without = needed_steps(spec, facts(False))
    assert "calibrate-tracking:take" in ids(with_tracking)
    assert "calibrate-tracking:take" not in ids(without)
    pts = next(s for s in without if s.kind == "dense-points")
    assert pts.inputs == ("ingest:take", "calibrate-static:take")
    pts = next(s for s in with_tracking if s.kind == "dense-points")
    assert pts.inputs == ("ingest:take", "calibrate-tracking:take")


def test_face_rig_work_only_for_enhanced_shots_and_their_actors():
    spec = parse_spec(base_spec())
    steps = needed_steps(spec, facts())
    kinds = {s.kind for s in steps}
    assert {"face-pairs", "train-enhancer", "enhance-shot"} <= kinds
    assert ids(steps, "face-pairs") == ["face-pairs:anna"]          # ben is in no enhanced shot
    assert not [s for s in steps if "ben_face" in s.id]
    # only the wide shot: no Face Rig work at all, no face capture needed
    wide = needed_steps(spec, {"take": info(frames=100)}, shots=["wide"])
    assert not {"face-pairs", "train-enhancer", "enhance-shot"} & {s.kind for s in wide}
    assert not [s for s in wide if "face" in s.id]
    # both actors in enhanced shots: one enhancer over both actors' pairs
    data = base_spec()
    data["shots"][0]["enhance"] = True                              # wide shows anna and ben
    steps = needed_steps(parse_spec(data), facts())
    assert ids(steps, "face-pairs") == ["face-pairs:anna", "face-pairs:ben"]
    enh = next(s for s in steps if s.kind == "train-enhancer")
    assert enh.id == "train-enhancer:anna+ben" and enh.inputs == ("face-pairs:anna", "face-pairs:ben")
    assert "ingest:ben_face" in ids(steps)                          # a folder face capture is ingested
    assert ids(steps, "enhance-shot") == ["enhance-shot:wide", "enhance-shot:cu_anna"]


def test_only_segments_the_shots_cover():
    spec = parse_spec(base_spec())                                  # test preset: 8 frames, overlap 2
    plan = segment_plan_for(spec, "take", facts()["take"])
    assert [s.frames for s in plan.segments][:3] == [(0, 8), (6, 14), (12, 20)]
    wide = needed_steps(spec, facts(), shots=["wide"])              # frames 0..19
    assert ids(wide, "train-segment") == ["train-segment:take:000000-000008",
                                          "train-segment:take:000006-000014",
                                          "train-segment:take:000012-000020",
                                          "train-segment:take:000018-000026"]  # blends at 18, 19
    cu = needed_steps(spec, facts(), shots=["cu_anna"])             # frames 60..69
    segs = [s for s in cu if s.kind == "train-segment"]
    assert [list(s.parameters.frames) for s in segs] == [[54, 62], [60, 68], [66, 74]]
    assert len(plan.segments) == 17                                  # ceil((100 - 2) / (8 - 2))
    render = next(s for s in cu if s.kind == "render-shot")
    assert render.inputs == tuple(s.id for s in segs)
    # a given plan is used as is
    own = plan_segments((0, 100), SegmentBudget(gaussians_per_frame=1, max_gaussians=50), overlap=4)
    steps = needed_steps(spec, {**facts(), "take": info(frames=100, plan=own)}, shots=["wide"])
    assert ids(steps, "train-segment") == ["train-segment:take:000000-000036"]


def test_quality_overrides_reach_the_plan_and_the_training():
    """``quality: {preset: production, train_steps: 20000, ...}``: single fields of the one preset
    table replaced; the steps carry them and the segment's TrainConfig is built from them."""
    data = base_spec()
    data["quality"] = {"preset": "production", "train_steps": 20_000, "checkpoint_every": 500,
                       "max_segment_frames": 30}
    spec = parse_spec(data)
    q = spec.quality_preset()
    assert q == PRESETS["production"].with_overrides(train_steps=20_000, checkpoint_every=500, max_segment_frames=30)
    assert q.gpu_memory_gb == PRESETS["production"].gpu_memory_gb                  # the rest is the preset's
    steps = needed_steps(spec, facts(), shots=["wide"])
    # 100 frames in 4 segments of at most 30 (not 1 of 100), the wide shot in the first
    assert len(segment_plan_for(spec, "take", facts()["take"]).segments) == 4
    assert ids(steps, "train-segment") == ["train-segment:take:000000-000028"]
    train = next(s for s in steps if s.kind == "train-segment")
    assert train.parameters.train_steps == 20_000 and train.parameters.checkpoint_every == 500
    assert next(s for s in steps if s.kind == "dense-points").parameters.dense_scale == q.dense_scale
    cfg = q.train_config(held_out=["S004"], max_gaussians=train.parameters.gaussians)
    assert (cfg.steps, cfg.checkpoint_every, cfg.mcmc.cap_max) == (20_000, 500, train.parameters.gaussians)
    assert cfg.mcmc.refine_stop == PRESETS["production"].refine_stop          # an override is not a stretch
    # what the spec changed, not only the steps, changes the train-segment step (its cache journal)
    data["quality"]["grid_size"] = 16
    again = next(s for s in needed_steps(parse_spec(data), facts(), shots=["wide"]) if s.kind == "train-segment")
    assert again.parameters.grid_size == 16 != train.parameters.grid_size


def test_the_alpha_loss_is_a_quality_field_whose_default_leaves_the_journal_as_it_was():
    """``quality: {mask_alpha_weight: 1, mask_alpha_every: 4}`` reaches the segment's TrainConfig and
    the train-segment step; left at their defaults (off) the step's JSON, which the production's
    journal fingerprints, holds neither field, as before they existed."""
    data = base_spec()
    data["quality"] = {"preset": "production"}
    train = next(s for s in needed_steps(parse_spec(data), facts(), shots=["wide"]) if s.kind == "train-segment")
    assert not any(k.startswith("mask_alpha") for k in train.parameters.as_json())
    data["quality"].update(mask_alpha_weight=1.0, mask_alpha_every=4)
    spec = parse_spec(data)
    train = next(s for s in needed_steps(spec, facts(), shots=["wide"]) if s.kind == "train-segment")
    assert (train.parameters.as_json()["mask_alpha_weight"], train.parameters.as_json()["mask_alpha_every"]) == (1.0, 4)
    cfg = spec.quality_preset().train_config(held_out=["S004"])
    assert (cfg.mask_alpha_weight, cfg.mask_alpha_every) == (1.0, 4)


def test_mcmcs_opacity_regulariser_is_a_quality_field_whose_default_leaves_the_journal_as_it_was():
    """``quality: {opacity_reg: 0.001}`` reaches the segment's MCMC and the train-segment step; at
    its default (3DGS-MCMC's 0.01) neither the step's JSON nor the TrainConfig changes."""
    data = base_spec()
    data["quality"] = {"preset": "production"}
    spec = parse_spec(data)
    train = next(s for s in needed_steps(spec, facts(), shots=["wide"]) if s.kind == "train-segment")
    assert "opacity_reg" not in train.parameters.as_json()
    assert spec.quality_preset().train_config().mcmc.opacity_reg == MCMCConfig().opacity_reg == 0.01
    data["quality"]["opacity_reg"] = 0.001
    spec = parse_spec(data)
    again = next(s for s in needed_steps(spec, facts(), shots=["wide"]) if s.kind == "train-segment")
    assert again.parameters.as_json()["opacity_reg"] == 0.001
    cfg = spec.quality_preset().train_config(held_out=["S004"])
    assert cfg.mcmc.opacity_reg == 0.001 and cfg.mcmc.refine_stop == PRESETS["production"].refine_stop


def test_plan_order_stability_and_reconstruct():
    spec = parse_spec(base_spec())
    a, b = needed_steps(spec, facts()), needed_steps(spec, facts())
    assert a == b
    seen = set()
    for s in a:                                                     # inputs come first
        assert set(s.inputs) <= seen, s.id
        seen.add(s.id)
    json.dumps([s.model_dump() for s in a])                         # parameters are plain JSON
    data = base_spec()
    data["captures"]["other"]["reconstruct"] = True
    steps = needed_steps(parse_spec(data), facts(), shots=["wide"])
    plan = segment_plan_for(spec, "other", facts()["other"])
    assert len(ids(steps, "train-segment")) == 4 + len(plan.segments)
    assert "render-shot:cu_anna" not in ids(steps)


def test_planning_errors():
    spec = parse_spec(base_spec())
    with pytest.raises(ValueError, match=r"no capture info for capture 'take' \(shown by shot 'wide'\)"):
        needed_steps(spec, {})
    with pytest.raises(ValueError, match="shot 'cu_anna'.*does not cover"):
        needed_steps(spec, {**facts(), "take": info(frames=40)})
    with pytest.raises(KeyError, match="no shot 'nope'"):
        needed_steps(spec, facts(), shots=["nope"])


def test_capture_info_from_a_capture_folder(tmp_path):
    desc = {"format": "volcap-capture/1", "name": "d", "rig": "demo_scene", "fps": 24,
            "take": {"start_timecode": "01:00:00:00", "frame_count": 30},
            "cameras": [{"id": "S000", "path": "S000", "start_timecode": "01:00:00:00"}]}
    (tmp_path / "capture.json").write_text(json.dumps(desc))
    ci = capture_info_from_folder(tmp_path)
    assert not ci.has_tracking_cameras and ci.frame_count == 30 and ci.fps == 24
    from hardware.rig import load_rig
    tracker = next(c.id for c in load_rig("demo_scene").cameras if c.role.tracks)
    desc["cameras"].append({"id": tracker, "path": tracker, "start_timecode": "01:00:00:00"})
    (tmp_path / "capture.json").write_text(json.dumps(desc))
    assert capture_info_from_folder(tmp_path).has_tracking_cameras


def test_capture_info_agrees_on_the_folder_and_the_ingested_capture(tmp_path):
    """A portrait camera counts at its landscape size before ingest (rig sensors) and after (the
    record's images), so a folder capture and the same capture ingested plan the same segments."""
    from types import SimpleNamespace

    from hardware.rig import load_rig

    rig = load_rig("demo_scene")
    portrait = next(c for c in rig.cameras if c.sensor.width_px < c.sensor.height_px)
    desc = {"format": "volcap-capture/1", "name": "d", "rig": "demo_scene", "fps": 24,
            "take": {"start_timecode": "01:00:00:00", "frame_count": 30},
            "cameras": [{"id": c, "path": c, "start_timecode": "01:00:00:00"} for c in ("S000", portrait.id)]}
    (tmp_path / "capture.json").write_text(json.dumps(desc))
    record = SimpleNamespace(name="d", performer=None, ground_truth=None, rig=rig, fps=24, frame_count=30, cameras=[
        SimpleNamespace(id="S000", width=320, height=180),
        SimpleNamespace(id=portrait.id, width=portrait.sensor.width_px, height=portrait.sensor.height_px)])
    before, after = capture_info_from_folder(tmp_path), CaptureInfo.from_capture(record)
    assert before == after and (after.width, after.height) == (320, 180)
