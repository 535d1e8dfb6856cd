"""Ingest flow on small hand-made capture folders: conversion, caching, every refusal."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from flows.ingest import ingest_flow
from flows.runtime import run_flow
from hardware.rig import load_rig
from volcap_core.capture import Capture, IngestError
from volcap_core.colour import srgb_encode
from volcap_core.imageio.read import decode_exr, read_exr_header
from volcap_core.imageio.write import write_exr
from volcap_core.store import ArtifactStore, MissingRefError

W, H, FRAMES = 16, 12, 4


def _rig_json() -> dict:
    cams = []
    for i, role in enumerate(["static", "static", "tracking-landscape"]):
        zoom = role != "static"
        cams.append({
            "id": f"C{i}", "role": role,
            "lens": {"focal_min_mm": 45.0 if zoom else 14.0, "focal_max_mm": 175.0 if zoom else 42.0},
            "sensor": {"width_mm": 24.0, "height_mm": 18.0, "width_px": W, "height_px": H},
            "mount": {"kind": "tripod", "position_m": [3.0 * np.cos(i), 3.0 * np.sin(i), 1.5],
                      "look_at_m": [0.0, 0.0, 1.0]},
            "nominal_focal_mm": 60.0 if zoom else 20.0})
    return {"name": "tiny", "kind": "scene", "fps": 24.0, "stage_size_m": [6.0, 8.0, 4.0], "cameras": cams,
            "lighting": {"description": "test"}}


def _pixels(cam: int, frame: int) -> np.ndarray:
    rng = np.random.default_rng(100 * cam + frame)
    return rng.uniform(0.0, 4.0, size=(H, W, 3)).astype(np.float32)


def make_capture(root: Path) -> Path:
    """3 cameras x 4 frames: C0 linear EXR, C1 sRGB 16-bit PNG, C2 a tracking camera that started
    2 frames before the take (its files are numbered from the camera's own start)."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "rig.json").write_text(json.dumps(_rig_json()))
    cameras = []
    for cam in range(3):
        folder = root / f"C{cam}"
        folder.mkdir()
        early = 2 if cam == 2 else 0
        for f in range(FRAMES):
            px = _pixels(cam, f)
            if cam == 1:
                code = np.round(srgb_encode(np.clip(px / 4.0, 0, 1)) * 65535).astype(np.uint16)
                _write_png16(folder / f"{f:06d}.png", code)
            else:
                write_exr(folder / f"{f + early:06d}.exr", px, ("R", "G", "B"), pixel_type="float")
        src = {"id": f"C{cam}", "path": f"C{cam}", "start_timecode": "01:00:00:00" if cam != 2 else "00:59:59:22",
               "encoding": "srgb" if cam == 1 else "linear"}
        if cam == 2:
            src["lens_encoder"] = [{"frame": f, "focal_mm": 60.0 + f} for f in range(FRAMES + early)]
        cameras.append(src)
    desc = {"format": "volcap-capture/1", "name": "tiny", "rig": "rig.json", "fps": 24,
            "take": {"start_timecode": "01:00:00:00", "frame_count": FRAMES}, "cameras": cameras}
    (root / "capture.json").write_text(json.dumps(desc, indent=1))
    return root


def _write_png16(path: Path, code: np.ndarray) -> None:
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(code.shape[1], code.shape[0], 3, oiio.UINT16))
    out.write_image(code)
    out.close()


@pytest.fixture
def capture_dir(tmp_path: Path) -> Path:
    return make_capture(tmp_path / "capture")


@pytest.fixture
def store_url(tmp_path: Path) -> str:
    return ArtifactStore(str(tmp_path / "store")).url


def test_ingest_converts_every_camera_to_linear_half_exr(prefect_api, capture_dir, store_url):
    summary = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    s = ArtifactStore(store_url)
    assert s.get_ref("captures/tiny") == summary.result
    capture = s.get_record(summary.result, Capture)
    assert [c.id for c in capture.cameras] == ["C0", "C1", "C2"]
    assert capture.frame_count == FRAMES and all(len(c.frames) == FRAMES for c in capture.cameras)
    assert (summary.tasks_run, summary.tasks_cached, summary.tasks_failed) == (7, 0, 0)

    # Linear EXR stored as half: equal to the source within half precision.
    px, ch = decode_exr(s.get_bytes(capture.camera("C0").frames[2]))
    assert ch == ("R", "G", "B")
    np.testing.assert_allclose(px, _pixels(0, 2), rtol=1e-3)
    # sRGB PNG linearised (16-bit quantisation of the encoded value).
    px, _ = decode_exr(s.get_bytes(capture.camera("C1").frames[1]))
    np.testing.assert_allclose(px, np.clip(_pixels(1, 1) / 4.0, 0, 1), atol=2e-3)
    # The camera that started 2 frames early: take index 0 is its file 000002.
    px, _ = decode_exr(s.get_bytes(capture.camera("C2").frames[0]))
    np.testing.assert_allclose(px, _pixels(2, 0), rtol=1e-3)
    lens = capture.camera("C2").lens_encoder
    assert [l.frame for l in lens] == list(range(FRAMES)) and lens[0].focal_mm == 62.0
    assert capture.camera("C0").lens_encoder is None


def test_rerun_is_all_cached_and_one_replaced_camera_reingests_alone(prefect_api, capture_dir, store_url):
    first = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    again = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    assert (again.tasks_run, again.tasks_cached) == (0, 7)
    assert again.result == first.result

    # Same bytes rewritten (new ctime): re-fingerprinted, but the conversion is a cache hit.
    f = capture_dir / "C0" / "000001.exr"
    data = f.read_bytes()
    f.unlink()
    f.write_bytes(data)
    touched = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    assert (touched.tasks_run, touched.tasks_cached) == (1, 6)
    assert touched.result == first.result

    # New content for one camera: that camera and the record only.
    write_exr(f, _pixels(0, 1) * 2, ("R", "G", "B"), pixel_type="float")
    changed = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    assert (changed.tasks_run, changed.tasks_cached) == (3, 4)
    assert changed.result != first.result


def test_vanished_outputs_are_recomputed_not_served(prefect_api, capture_dir, store_url):
    first = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    s = ArtifactStore(store_url)
    capture = s.get_record(first.result, Capture)
    lost = capture.camera("C1").frames[3]
    os.remove(s._object_path(lost.digest))
    again = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    assert again.tasks_run >= 1
    assert s.exists(lost) and again.result == first.result


def _break(capture_dir: Path, how: str) -> str:
    """Damage the folder one way; returns a fragment the error message must contain."""
    desc_path = capture_dir / "capture.json"
    desc = json.loads(desc_path.read_text())
    if how == "missing-frame":
        (capture_dir / "C0" / "000002.exr").unlink()
        return "camera C0: 1 frame(s) missing"
    if how == "duplicate-frame":
        shutil.copy(capture_dir / "C0" / "000001.exr", capture_dir / "C0" / "1.exr")
        return "camera C0: frame 1 is duplicated"
    if how == "out-of-take":  # camera C0 stopped recording a frame early
        (capture_dir / "C0" / "000003.exr").unlink()
        return ("camera C0: the take 01:00:00:00-01:00:00:03 is out of the camera's recording "
                "01:00:00:00-01:00:00:02 (camera frames 0-2); the common timecode range of all cameras is "
                "01:00:00:00-01:00:00:02")
    if how == "unknown-camera":
        desc["cameras"][0]["id"] = "X9"
        desc["cameras"][0]["path"] = "C0"
        desc_path.write_text(json.dumps(desc))
        return "X9 are not in rig tiny"
    if how == "resolution":
        write_exr(capture_dir / "C1" / "000003.png".replace(".png", ".exr"),
                  np.zeros((H + 1, W, 3), np.float32), ("R", "G", "B"))
        (capture_dir / "C1" / "000003.png").unlink()
        return "camera C1, frame 3"
    if how == "channels":
        write_exr(capture_dir / "C0" / "000000.exr", np.zeros((H, W, 4), np.float32), ("R", "G", "B", "A"))
        return "camera C0, frame 1"
    if how == "damaged":
        f = capture_dir / "C0" / "000003.exr"
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
        return "camera C0, frame 3"
    if how == "nan":
        px = _pixels(0, 2)
        px[1, 1, 0] = np.nan
        px[2, 2, 1] = np.inf
        write_exr(capture_dir / "C0" / "000002.exr", px, ("R", "G", "B"), pixel_type="float")
        return "camera C0, frame 2"
    if how == "no-lens":
        del desc["cameras"][2]["lens_encoder"]
        desc_path.write_text(json.dumps(desc))
        return "camera C2: tracking camera without lens_encoder"
    if how == "bad-json":
        desc_path.write_text("{not json")
        return "capture.json: invalid capture description"
    if how == "two-views-no-choice":  # C0's files become stereo files; capture.json chooses no view
        for f in range(FRAMES):
            _write_two_view_exr(capture_dir / "C0" / f"{f:06d}.exr", _pixels(0, f), _pixels(1, f))
        return ("camera C0, frame 0: " + str(capture_dir / "C0" / "000000.exr")
                + ": holds 2 views (left, right) and no part or view was chosen")
    raise AssertionError(how)


def _write_two_view_exr(path: Path, left: np.ndarray, right: np.ndarray) -> None:
    """OpenEXR's multi-view convention: ``multiView`` = [left, right], the default (left) view's
    channels unprefixed, the right view's prefixed ``right.``."""
    import OpenEXR

    planes = {c: np.ascontiguousarray(left[..., i]) for i, c in enumerate("RGB")}
    planes.update({f"right.{c}": np.ascontiguousarray(right[..., i]) for i, c in enumerate("RGB")})
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "multiView": ["left", "right"]}
    OpenEXR.File(header, planes).write(str(path))


@pytest.mark.parametrize("how", ["missing-frame", "duplicate-frame", "out-of-take", "unknown-camera", "resolution",
                                 "channels", "damaged", "nan", "no-lens", "bad-json", "two-views-no-choice"])
def test_bad_folders_are_refused_by_name_and_nothing_is_recorded(prefect_api, capture_dir, store_url, how):
    fragment = _break(capture_dir, how)
    with pytest.raises(IngestError) as err:
        run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    assert fragment in str(err.value)
    with pytest.raises(MissingRefError):
        ArtifactStore(store_url).get_ref("captures/tiny")


def test_a_stereo_pair_shares_a_folder_of_two_view_files(prefect_api, capture_dir, store_url):
    """C0 and C1 are the left and right eyes of one camera body writing two-view EXRs: both entries
    name the same folder and pick their view; each stored frame says which view it is."""
    stereo = capture_dir / "stereo"
    stereo.mkdir()
    for f in range(FRAMES):
        _write_two_view_exr(stereo / f"{f:06d}.exr", _pixels(0, f), _pixels(1, f))
    desc = json.loads((capture_dir / "capture.json").read_text())
    desc["cameras"][0].update(path="stereo", exr_view="left")
    desc["cameras"][1].update(path="stereo", encoding="linear", exr_view="right")
    (capture_dir / "capture.json").write_text(json.dumps(desc))

    summary = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    s = ArtifactStore(store_url)
    capture = s.get_record(summary.result, Capture)
    for cam, view in (("C0", "left"), ("C1", "right")):
        record = capture.camera(cam)
        assert (record.source_view, record.source_part) == (view, None)
        data = s.get_bytes(record.frames[2])
        px, _ = decode_exr(data)
        np.testing.assert_allclose(px, _pixels(0 if view == "left" else 1, 2), rtol=1e-3)
        (capture_dir / "stored.exr").write_bytes(data)
        assert read_exr_header(capture_dir / "stored.exr")["volcap.source_view"] == view


def test_frames_recorded_outside_the_take_are_left_out(prefect_api, capture_dir, store_url):
    shutil.copy(capture_dir / "C0" / "000001.exr", capture_dir / "C0" / "000009.exr")
    summary = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    capture = ArtifactStore(store_url).get_record(summary.result, Capture)
    assert len(capture.camera("C0").frames) == FRAMES


def test_nan_repair_policy(prefect_api, capture_dir, store_url):
    _break(capture_dir, "nan")
    summary = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir), nan_policy="repair")
    s = ArtifactStore(store_url)
    px, _ = decode_exr(s.get_bytes(s.get_record(summary.result, Capture).camera("C0").frames[2]))
    assert np.isfinite(px).all() and px[1, 1, 0] == 0.0 and px[2, 2, 1] == 65504.0


def test_demo_rig_matches_the_layout(capture_dir):
    # The tiny rig used above has the shape of the built-in ones.
    assert load_rig(str(capture_dir / "rig.json")).has_tracking_cameras


def test_camera_log_footage_is_linearised_through_an_ocio_config(prefect_api, capture_dir, store_url):
    """C0 re-encoded as ARRI LogC3 through OpenColorIO's studio config; ingest must undo it."""
    import PyOpenColorIO as ocio

    config = ocio.Config.CreateFromBuiltinConfig("studio-config-latest")
    # volcap's working space is linear Rec.709 primaries: the config's scene_linear role says so.
    config.setRole(ocio.ROLE_SCENE_LINEAR, "Linear Rec.709 (sRGB)")
    (capture_dir / "studio.ocio").write_text(config.serialize())
    to_log = config.getProcessor("Linear Rec.709 (sRGB)", "ARRI LogC3 (EI800)").getDefaultCPUProcessor()
    for f in range(FRAMES):
        px = _pixels(0, f).copy()
        to_log.applyRGB(px)
        write_exr(capture_dir / "C0" / f"{f:06d}.exr", px, ("R", "G", "B"), pixel_type="float")
    desc = json.loads((capture_dir / "capture.json").read_text())
    desc["ocio_config"] = "studio.ocio"
    desc["cameras"][0].update(encoding="ocio", ocio_colorspace="ARRI LogC3 (EI800)")
    (capture_dir / "capture.json").write_text(json.dumps(desc))

    summary = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    s = ArtifactStore(store_url)
    px, _ = decode_exr(s.get_bytes(s.get_record(summary.result, Capture).camera("C0").frames[1]))
    np.testing.assert_allclose(px, _pixels(0, 1), rtol=3e-3, atol=1e-4)
