"""A production's face capture must film the actor it is listed for (issue 27).

A capture may name its performer (capture.json ``performer: {capture, actor}``). The spec's check
(``check_face_capture``, run by ``needed_steps`` once the captures' facts are known): the
performer's capture is one of the actor's captures, compared by the names the captures record,
and, when the actor sets ``index``, the performer's actor is that index. A face capture naming no
performer is accepted. Pure planning on hand-made facts and capture.json files: well under 1 s.
"""

from __future__ import annotations

import json

import pytest
import yaml

from flows.production import open_production
from volcap_core.capture import Performer
from volcap_core.production.spec import CaptureInfo, capture_info_from_folder, needed_steps, parse_spec
from volcap_core.store import ArtifactStore

SHOT = {"name": "cu", "performance": "take3", "frames": [0, 4], "fps": 24, "resolution": [64, 36],
        "sensor_mm": 36, "enhance": True,
        "keyframes": [{"frame": 0, "position": [5.0, -2.0, 1.8], "look_at": [0.0, 0.0, 1.5], "focal_mm": 50}]}


def spec_data(index: int | None = None, ben: bool = False) -> dict:
    anna = {"name": "anna", "captures": ["take3"], "face_capture": "anna_face"}
    if index is not None:
        anna["index"] = index
    actors = [anna]
    if ben:     # an actor of another capture, given anna's face capture
        actors.append({"name": "ben", "captures": ["take4"], "face_capture": "anna_face"})
    return {"format": "volcap-production/1", "name": "p", "quality": "test",
            "captures": {"take3": {"ref": "captures/synth-demo_scene-s0"}, "take4": {"ref": "captures/synth-demo_scene-s1"},
                         "anna_face": {"ref": "captures/anna_face"}},
            "actors": actors, "shots": [SHOT]}


def facts(performer: Performer | None) -> dict[str, CaptureInfo]:
    def info(name, **kw):
        return CaptureInfo(has_tracking_cameras=False, fps=24, frame_count=8, width=320, height=180, name=name, **kw)
    return {"take3": info("synth-demo_scene-s0"), "take4": info("synth-demo_scene-s1"),
            "anna_face": info("anna_face", performer=performer)}


def test_a_face_capture_of_the_actors_capture_is_planned():
    steps = needed_steps(parse_spec(spec_data()), facts(Performer(capture="synth-demo_scene-s0", actor=1)))
    assert "face-pairs:anna" in [s.id for s in steps]
    # with the index it names
    needed_steps(parse_spec(spec_data(index=1)), facts(Performer(capture="synth-demo_scene-s0", actor=1)))


def test_a_face_capture_naming_no_performer_is_accepted():
    """Real captures do not say whose actor they film: the spec's word stands."""
    steps = needed_steps(parse_spec(spec_data(index=0, ben=True)), facts(None))
    assert "face-pairs:anna" in [s.id for s in steps]


def test_a_face_capture_of_another_capture_or_actor_is_refused_in_one_line():
    performer = Performer(capture="synth-demo_scene-s0", actor=1)
    with pytest.raises(ValueError) as info:
        needed_steps(parse_spec(spec_data(ben=True)), facts(performer))
    assert str(info.value) == ("actors[1].face_capture: 'anna_face' films actor 1 of the capture named "
                               "'synth-demo_scene-s0', which is not one of actor 'ben''s captures: "
                               "take4 ('synth-demo_scene-s1')")
    with pytest.raises(ValueError) as info:
        needed_steps(parse_spec(spec_data(index=0)), facts(performer))
    assert str(info.value) == ("actors[0].face_capture: 'anna_face' films actor 1 of the capture named "
                               "'synth-demo_scene-s0', but actor 'anna' is actor 0 there (actors[0].index)")
    # captures compare by their recorded names, not by their keys in the spec
    with pytest.raises(ValueError, match="not one of actor 'anna''s captures"):
        needed_steps(parse_spec(spec_data()), facts(Performer(capture="take3", actor=1)))


def test_open_production_checks_the_folders_capture_json_before_anything_runs(tmp_path):
    """From capture folders: the face capture's capture.json names its performer; the scene
    capture's its name (neither needs frames to be planned)."""
    def folder(name: str, performer: dict | None = None):
        desc = {"format": "volcap-capture/1", "name": name, "rig": "demo_scene", "fps": 24,
                "take": {"start_timecode": "01:00:00:00", "frame_count": 8},
                "cameras": [{"id": "S001", "path": "frames/S001", "start_timecode": "01:00:00:00"}]}
        if performer is not None:
            desc["performer"] = performer
        (tmp_path / name).mkdir()
        (tmp_path / name / "capture.json").write_text(json.dumps(desc))
        return str(tmp_path / name)

    data = spec_data(index=0)
    data["captures"] = {"take3": {"folder": folder("synth-demo_scene-s0")},
                        "take4": {"folder": folder("synth-demo_scene-s1")},
                        "anna_face": {"folder": folder("face", {"capture": "synth-demo_scene-s1", "actor": 0})}}
    assert capture_info_from_folder(tmp_path / "face").performer == Performer(capture="synth-demo_scene-s1", actor=0)
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump(data, sort_keys=False))
    store = ArtifactStore(str(tmp_path / "store")).url
    with pytest.raises(ValueError, match=r"spec\.yaml: actors\[0\]\.face_capture: 'anna_face' films actor 0 of the "
                                         r"capture named 'synth-demo_scene-s1', which is not one of actor 'anna''s"):
        open_production(spec, store=store)
    data["actors"][0]["captures"] = ["take3", "take4"]
    spec.write_text(yaml.safe_dump(data, sort_keys=False))
    assert "face-pairs:anna" in [s.id for s in open_production(spec, store=store).steps]
