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


# --------------------------------------------------------------------------- measured intrinsics

def _intrinsics(**kw) -> dict:
    d = {"fx": 311.0, "fy": 311.2, "cx": 163.0, "cy": 87.0, "model": "OPENCV", "params": [-0.1, 0.02, 0.0, 0.0]}
    d.update(kw)
    return d


def test_distorted_demo_rig_carries_measured_intrinsics():
    from volcap_core.calibration.sfm import Intrinsics

    rig = load_rig("demo_scene_distorted")
    plain = load_rig("demo_scene")
    assert [c.id for c in rig.cameras] == [c.id for c in plain.cameras]
    k1 = []
    for cam in rig.cameras_with_role(CameraRole.static):
        m = rig.measured_intrinsics(cam.id)
        assert m is not None and m.model == "OPENCV"
        k1.append(m.params[0])
        intr = Intrinsics.from_rig(rig, cam.id)
        assert (intr.fx, intr.fy, intr.cx, intr.cy) == (m.fx, m.fy, m.cx, m.cy)
        assert intr.distortion.params == tuple(m.params)
        off = math.hypot(m.cx - 159.5, m.cy - 89.5)
        assert 2.0 < off < 8.0
    assert min(k1) == -0.1 and max(k1) == 0.1
    # S006 and S007 share their lens group's intrinsics
    assert rig.measured_intrinsics("S006") == rig.measured_intrinsics("S007") == rig.lens_groups["zoom14-b"]
    # trackers and the plain rig fall back to the nominal intrinsics
    assert rig.measured_intrinsics("S008") is None
    nominal = Intrinsics.from_rig(plain, "S000")
    assert nominal.distortion.is_none and nominal.cx == 159.5 and nominal.fx == nominal.fy


def test_rig_without_intrinsics_serialises_as_before():
    # the Capture record holds the rig: rigs without measured intrinsics must dump as they did
    dumped = load_rig("demo_scene").model_dump(mode="json")
    assert "lens_groups" not in dumped
    assert not {"intrinsics", "lens_group"} & set(dumped["cameras"][0])
    rig = load_rig("demo_scene_distorted")
    again = Rig.model_validate(rig.model_dump(mode="json"))
    assert again == rig


@pytest.mark.parametrize("change, message", [
    (dict(model="FISHEYE"), "unknown distortion model 'FISHEYE'"),
    (dict(params=[0.1]), "OPENCV takes 4 parameters"),
    (dict(cx=400.0), "camera S000: measured principal point .* outside the 320x180 image"),
    (dict(fx=14.0, fy=14.0), "camera S000: measured fx 14.0 px .* outside its lens range"),
    (dict(fx=-3.0), "greater than 0"),
])
def test_measured_intrinsics_validation(change, message):
    bad = _demo()
    bad["cameras"][0]["intrinsics"] = _intrinsics(**change)
    with pytest.raises(ValidationError, match=message):
        Rig.model_validate(bad)


def test_lens_group_validation():
    bad = _demo()
    tracker = next(c for c in bad["cameras"] if c["role"] != "static")
    tracker["intrinsics"] = _intrinsics()
    with pytest.raises(ValidationError, match=f"camera {tracker['id']}: measured intrinsics on a tracking"):
        Rig.model_validate(bad)
    ok = _demo()
    ok["cameras"][0]["lens_group"] = ok["cameras"][1]["lens_group"] = "g1"
    ok["lens_groups"] = {"g1": _intrinsics()}
    rig = Rig.model_validate(ok)
    assert rig.measured_intrinsics("S001").fx == 311.0
    both = json.loads(json.dumps(ok))
    both["cameras"][0]["intrinsics"] = _intrinsics()
    with pytest.raises(ValidationError, match="camera S000 has its own intrinsics and lens group 'g1'"):
        Rig.model_validate(both)
    unused = json.loads(json.dumps(ok))
    unused["lens_groups"]["g2"] = _intrinsics()
    with pytest.raises(ValidationError, match=r"lens group\(s\) \['g2'\] are used by no camera"):
        Rig.model_validate(unused)
    mixed = json.loads(json.dumps(ok))
    mixed["cameras"][1]["sensor"]["width_px"] = 640
    with pytest.raises(ValidationError, match="camera S001 is in lens group 'g1' with camera S000 but has another"):
        Rig.model_validate(mixed)
    zoom = json.loads(json.dumps(ok))
    tr = next(c for c in zoom["cameras"] if c["role"] != "static")
    tr["lens_group"] = "g1"
    with pytest.raises(ValidationError, match="another sensor or lens|tracking"):
        Rig.model_validate(zoom)


# --------------------------------------------------------------------------- zoom lens tables

def _zoom(**kw) -> dict:
    d = {"model": "OPENCV", "samples": [{"focal_mm": 45.0, "params": [-0.44, 0.0, 0.0005, -0.0003]},
                                        {"focal_mm": 90.0, "params": [-0.57, 0.0, 0.001, -0.0006]},
                                        {"focal_mm": 175.0, "params": [2.2, 0.0, 0.002, -0.0013]}]}
    d.update(kw)
    return d


def _with_zoom(zoom: dict, camera: str = "S008") -> dict:
    rig = _demo()
    next(c for c in rig["cameras"] if c["id"] == camera)["zoom_intrinsics"] = zoom
    return rig


def test_zoom_lens_table_accepted_and_serialised():
    rig = Rig.model_validate(_with_zoom(_zoom()))
    z = rig.camera("S008").zoom_intrinsics
    assert z.focals_mm == (45.0, 90.0, 175.0) and not z.has_principal
    assert z.at(67.5).params[0] == pytest.approx(-0.505)
    again = Rig.model_validate(rig.model_dump(mode="json"))
    assert again == rig
    # cameras without a table serialise as before (no zoom_intrinsics key, no cx/cy keys)
    dumped = rig.model_dump(mode="json")
    assert "zoom_intrinsics" not in dumped["cameras"][0]
    assert "cx" not in dumped["cameras"][8]["zoom_intrinsics"]["samples"][0]
    with_pp = _zoom()
    for s, c in zip(with_pp["samples"], (160.1, 159.6, 158.9)):
        s.update(cx=c, cy=89.5)
    assert Rig.model_validate(_with_zoom(with_pp)).camera("S008").zoom_intrinsics.at(175.0).cx == 158.9


def _samples(*focals_params):
    return [{"focal_mm": f, "params": p} for f, p in focals_params]


@pytest.mark.parametrize("zoom, message", [
    (_zoom(samples=_samples((45.0, [-0.4, 0, 0, 0]), (175.0, [2.0, 0, 0, 0]), (90.0, [-0.5, 0, 0, 0]))),
     "camera S008: zoom_intrinsics: samples must be in increasing focal order: 90.0 mm comes after 175.0 mm"),
    (_zoom(samples=_samples((45.0, [-0.4, 0, 0, 0]), (90.0, [-0.5, 0, 0, 0]), (90.0, [-0.5, 0, 0, 0]),
                            (175.0, [2.0, 0, 0, 0]))),
     "camera S008: zoom_intrinsics: focal 90.0 mm is sampled twice"),
    (_zoom(samples=_samples((45.0, [-0.4, 0, 0, 0]), (90.0, [-0.5, 0.0]), (175.0, [2.0, 0, 0, 0]))),
     r"camera S008: zoom_intrinsics: the sample at 90.0 mm: distortion model OPENCV takes 4 parameters .* got 2"),
    (_zoom(model="FISHEYE"), "camera S008: zoom_intrinsics: unknown distortion model 'FISHEYE'"),
    (_zoom(samples=_samples((45.0, [-0.4, 0, 0, 0]))),
     "camera S008: zoom_intrinsics: a zoom lens table needs at least two samples"),
    (_zoom(samples=_samples((45.0, [-0.4, 0, 0, 0]), (998.0, [2.0, 0, 0, 0]))),
     r"camera S008: zoom lens sample at 998.0 mm is outside its lens range 45.0-175.0 mm \(focals in mm, not "
     r"pixels\)"),
    (_zoom(samples=_samples((45.0, [-0.4, 0, 0, 0]), (140.0, [1.0, 0, 0, 0]))),
     "camera S008: the zoom lens table covers 45.0-140.0 mm of its lens range 45.0-175.0 mm"),
    (_zoom(samples=[{"focal_mm": 45.0, "params": [-0.4, 0, 0, 0], "cx": 160.0},
                    {"focal_mm": 175.0, "params": [2.0, 0, 0, 0], "cx": 160.0}]),
     "camera S008: zoom_intrinsics: the sample at 45.0 mm: give both cx and cy, or neither"),
    (_zoom(samples=[{"focal_mm": 45.0, "params": [-0.4, 0, 0, 0], "cx": 160.0, "cy": 90.0},
                    {"focal_mm": 175.0, "params": [2.0, 0, 0, 0]}]),
     "camera S008: zoom_intrinsics: the principal point .* is given at some samples and not at others"),
    (_zoom(samples=[{"focal_mm": 45.0, "params": [-0.4, 0, 0, 0], "cx": 400.0, "cy": 90.0},
                    {"focal_mm": 175.0, "params": [2.0, 0, 0, 0], "cx": 160.0, "cy": 90.0}]),
     r"camera S008: zoom lens sample at 45.0 mm: principal point \(400.0, 90.0\) px is outside the 320x180 image"),
    (_zoom(samples=_samples((-45.0, [-0.4, 0, 0, 0]), (175.0, [2.0, 0, 0, 0]))),
     "camera S008: zoom_intrinsics.samples.0.focal_mm: Input should be greater than 0"),
])
def test_zoom_lens_table_validation_names_the_camera(zoom, message):
    with pytest.raises(ValidationError, match=message):
        Rig.model_validate(_with_zoom(zoom))


def test_zoom_lens_table_only_on_tracking_cameras():
    with pytest.raises(ValidationError, match="camera S000: a zoom lens table .* on a static camera"):
        Rig.model_validate(_with_zoom(_zoom(samples=_samples((14.0, [-0.1, 0, 0, 0]), (42.0, [0.1, 0, 0, 0]))),
                                      camera="S000"))
    # a tracking camera's measured intrinsics point to the table
    bad = _demo()
    next(c for c in bad["cameras"] if c["id"] == "S008")["intrinsics"] = _intrinsics(fx=1600.0, fy=1600.0)
    with pytest.raises(ValidationError, match=r"camera S008: measured intrinsics on a tracking-landscape camera: "
                                              r".*\(zoom_intrinsics\)"):
        Rig.model_validate(bad)


def _zoom_group(table: dict, members=("S008", "S009"), name: str = "zoom45-175") -> dict:
    rig = _demo()
    for c in rig["cameras"]:
        if c["id"] in members:
            c["lens_group"] = name
    rig["zoom_lens_groups"] = {name: table}
    return rig


def test_zoom_lens_group_shares_one_table():
    """Tracking cameras of one zoom lens model share the table calibrated once for it; each unit is
    still drawn (synthetic capture) and solved as its own camera."""
    from volcap_core.synth.synthesize import _plans

    rig = Rig.model_validate(_zoom_group(_zoom()))
    table = rig.zoom_lens_groups["zoom45-175"]
    assert rig.zoom_intrinsics("S008") is table and rig.zoom_intrinsics("S009") is table
    assert rig.zoom_intrinsics("S010") is None and rig.zoom_intrinsics("S000") is None
    assert Rig.model_validate(rig.model_dump(mode="json")) == rig
    assert "zoom_lens_groups" not in Rig.model_validate(_demo()).model_dump(mode="json")   # rigs without: as before
    # the synthetic units render through the group's table plus each its own calibration error
    plans = {p.cam.id: p for p in _plans(rig, 0, [(0.0, 0.0)], ["S008", "S009", "S010"])}
    z8, z9 = plans["S008"].zoom, plans["S009"].zoom
    assert z8 is not None and z9 is not None and plans["S010"].zoom is None
    assert z8.focals_mm == z9.focals_mm == table.focals_mm and z8 != z9
    # the same units as when each camera carries the table itself
    own = _demo()
    for c in own["cameras"]:
        if c["id"] in ("S008", "S009"):
            c["zoom_intrinsics"] = _zoom()
    alone = {p.cam.id: p.zoom for p in _plans(Rig.model_validate(own), 0, [(0.0, 0.0)], ["S008", "S009", "S010"])}
    assert (alone["S008"], alone["S009"]) == (z8, z9)


@pytest.mark.parametrize("change, message", [
    (lambda r: r["cameras"][0].update(lens_group="zoom45-175"),
     "static camera S000 is in lens group 'zoom45-175', a zoom lens table"),
    (lambda r: next(c for c in r["cameras"] if c["id"] == "S008").update(zoom_intrinsics=_zoom()),
     "camera S008 has its own zoom lens table and lens group 'zoom45-175' has one too"),
    (lambda r: r.update(lens_groups={"zoom45-175": _intrinsics()}),
     r"lens group\(s\) \['zoom45-175'\] are given both measured intrinsics and a zoom lens table"),
    (lambda r: r["zoom_lens_groups"].update(spare=_zoom()), r"lens group\(s\) \['spare'\] are used by no camera"),
    (lambda r: r["zoom_lens_groups"].update({"zoom45-175": _zoom(samples=_samples((45.0, [-0.4, 0, 0, 0]),
                                                                                  (140.0, [1.0, 0, 0, 0])))}),
     "zoom lens group 'zoom45-175': camera S008: the zoom lens table covers 45.0-140.0 mm"),
    (lambda r: next(c for c in r["cameras"] if c["id"] == "S010").update(lens_group="zoom45-175"),
     "camera S010 is in lens group 'zoom45-175' with camera S008 but has another sensor or lens"),
])
def test_zoom_lens_group_validation(change, message):
    rig = _zoom_group(_zoom())
    change(rig)
    with pytest.raises(ValidationError, match=message):
        Rig.model_validate(rig)


def test_finer_pixels_see_the_same_views():
    """A rig with pixel grids twice as fine: a point lands on the same spot of the image (OpenCV
    pixel centres: u' = (u + 0.5) 2 - 0.5) through the measured intrinsics of a camera and of a lens
    group, and through a zoom table's principal point; distortion (normalized) is unchanged."""
    with_pp = _zoom()
    for s, c in zip(with_pp["samples"], (160.1, 159.6, 158.9)):
        s.update(cx=c, cy=89.5)
    data = load_rig("demo_scene_distorted").model_dump(mode="json")
    for c in data["cameras"]:
        if c["id"] in ("S008", "S009"):
            c.pop("zoom_intrinsics", None)
            c["lens_group"] = "zoom45-175"
    rig = Rig.model_validate(dict(data, zoom_lens_groups={"zoom45-175": with_pp}))
    fine = rig.with_finer_pixels(2)
    assert fine.name == f"{rig.name}_x2" and rig.with_finer_pixels(1) is rig
    x, y = 0.21, -0.13                                           # a normalized (undistorted) direction
    for cam in ("S001", "S006"):                                 # its own intrinsics; lens group zoom14-b
        a, b = rig.measured_intrinsics(cam), fine.measured_intrinsics(cam)
        assert (a.model, a.params) == (b.model, b.params)
        assert fine.camera(cam).sensor.width_px == 2 * rig.camera(cam).sensor.width_px
        assert b.fx * x + b.cx == pytest.approx((a.fx * x + a.cx + 0.5) * 2 - 0.5)
        assert b.fy * y + b.cy == pytest.approx((a.fy * y + a.cy + 0.5) * 2 - 0.5)
    za, zb = rig.zoom_intrinsics("S008").at(100.0), fine.zoom_intrinsics("S008").at(100.0)
    assert za.params == zb.params and zb.cx == pytest.approx((za.cx + 0.5) * 2 - 0.5)
    assert fine.zoom_intrinsics("S008") is fine.zoom_lens_groups["zoom45-175"]
    with pytest.raises(ValueError, match="pixel scale must be a positive integer, got 0"):
        rig.with_finer_pixels(0)
