"""Built-in rigs: the paper's counts, sane geometry, and clear validation errors."""

from __future__ import annotations

import json
import math

import pytest
from pydantic import ValidationError

from hardware import make_rigs
from hardware.rig import CameraRole, Rig, builtin_rig_names, load_rig


def _roles(rig: Rig) -> dict[str, int]:
    return {r.value: len(rig.cameras_with_role(r)) for r in CameraRole}


def test_builtin_rigs_listed():
    assert {"scene_rig", "face_rig", "demo_scene", "demo_face"} <= set(builtin_rig_names())


def test_scene_rig_matches_paper():
    rig = load_rig("scene_rig")
    assert rig.kind == "scene" and rig.fps == 24
    assert len(rig.cameras) == 180
    assert _roles(rig) == {"static": 90, "tracking-landscape": 40, "tracking-portrait": 50}
    kinds = [c.mount.kind for c in rig.cameras]
    assert kinds.count("ceiling") == 30 and kinds.count("floor") == 25 and kinds.count("cart") == 125
    assert {c.mount.cart for c in rig.cameras if c.mount.kind == "cart"} == set(range(12))
    for cam in rig.cameras:
        portrait = cam.role is CameraRole.tracking_portrait
        assert (cam.sensor.width_px, cam.sensor.height_px) == ((2160, 3840) if portrait else (3840, 2160))
        if cam.role is CameraRole.static:
            assert (cam.lens.focal_min_mm, cam.lens.focal_max_mm) == (14, 42)
        if cam.role is CameraRole.tracking_landscape:
            assert (cam.lens.focal_min_mm, cam.lens.focal_max_mm) == (45, 175)
        if cam.mount.kind == "ceiling":
            assert cam.mount.position_m[2] > 4.5
        if cam.mount.kind == "cart":
            x, y, _ = cam.mount.position_m
            assert 5.5 < math.hypot(x, y) < 7.5   # carts on a circle around the 6 m x 8 m stage
    assert rig.lighting.strobe_hz == 72 and rig.lighting.flash_ms == 1
    assert rig.stage_size_m[:2] == (6.0, 8.0)


def test_face_rig_matches_paper():
    rig = load_rig("face_rig")
    assert rig.kind == "face" and len(rig.cameras) == 75 and rig.fps == 24
    assert all(c.role is CameraRole.static for c in rig.cameras)
    assert rig.lighting.led_panels == 80 and rig.lighting.white_lights == 110
    assert rig.stage_size_m == (2.76, 2.76, 2.5)
    for cam in rig.cameras:
        x, y, z = cam.mount.position_m
        assert 0 <= z <= 2.5 and math.hypot(x, y) <= 1.38 + 1e-3
        assert cam.mount.look_at_m == (0.0, 0.0, 1.7)
        assert (cam.sensor.width_px, cam.sensor.height_px) == (3840, 2160)


def test_demo_rigs_small_and_registrable():
    scene = load_rig("demo_scene")
    assert len(scene.cameras) == 12
    assert _roles(scene) == {"static": 8, "tracking-landscape": 2, "tracking-portrait": 2}
    for cam in scene.cameras:
        assert cam.sensor.width_px * cam.sensor.height_px <= 320 * 180
    # static cameras: neighbours at most ~30 degrees apart around the stage, at several heights
    static = scene.cameras_with_role(CameraRole.static)
    az = sorted(math.degrees(math.atan2(c.mount.position_m[1], c.mount.position_m[0])) for c in static)
    assert max(b - a for a, b in zip(az, az[1:])) <= 30.5
    assert len({c.mount.position_m[2] for c in static}) >= 2
    # same field of view as the 4K camera: sensor millimetres kept
    full = load_rig("scene_rig").cameras[0].sensor
    assert static[0].sensor.width_mm == full.width_mm
    face = load_rig("demo_face")
    assert len(face.cameras) == 8 and face.kind == "face"


def test_generator_is_deterministic_and_matches_committed(tmp_path):
    written = make_rigs.main(tmp_path)
    for path in written:
        committed = make_rigs.RIGS_DIR / path.name
        assert path.read_bytes() == committed.read_bytes(), f"{path.name}: rerun python -m hardware.make_rigs"


def _demo() -> dict:
    return json.loads((make_rigs.RIGS_DIR / "demo_scene.json").read_text())


def test_duplicate_ids_rejected():
    bad = _demo()
    bad["cameras"][1]["id"] = bad["cameras"][0]["id"]
    with pytest.raises(ValidationError, match="duplicate camera id 'S000'"):
        Rig.model_validate(bad)


def test_focal_outside_lens_rejected():
    bad = _demo()
    bad["cameras"][0]["nominal_focal_mm"] = 50.0    # static lens is 14-42 mm
    with pytest.raises(ValidationError, match=r"camera S000: nominal focal 50.0 mm is outside"):
        Rig.model_validate(bad)


def test_unknown_role_rejected():
    bad = _demo()
    bad["cameras"][0]["role"] = "drone"
    with pytest.raises(ValidationError, match="role"):
        Rig.model_validate(bad)


def test_reversed_lens_and_landscape_portrait_rejected():
    bad = _demo()
    bad["cameras"][0]["lens"] = {"focal_min_mm": 42.0, "focal_max_mm": 14.0}
    with pytest.raises(ValidationError, match="reversed"):
        Rig.model_validate(bad)
    bad = _demo()
    portrait = next(c for c in bad["cameras"] if c["role"] == "tracking-portrait")
    s = portrait["sensor"]
    s["width_px"], s["height_px"] = s["height_px"], s["width_px"]
    with pytest.raises(ValidationError, match="taller than wide"):
        Rig.model_validate(bad)


def test_load_rig_names_the_problem(tmp_path):
    bad = _demo()
    bad["cameras"][1]["id"] = "S000"
    path = tmp_path / "bad_rig.json"
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"(?s)bad_rig.json: invalid rig: .*duplicate"):
        load_rig(path)
    with pytest.raises(ValueError, match="unknown rig 'nope'"):
        load_rig("nope")
