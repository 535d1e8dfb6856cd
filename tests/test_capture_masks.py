"""Performer masks in the capture layout: read, checked, stored; a broken mask refused by name.

The tiny capture of ``tests/test_ingest.py`` (3 cameras of 16x12, 4 frames; C2 started 2 frames
before the take, so its files, masks included, are numbered from its own start).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from flows.ingest import ingest_flow
from flows.runtime import run_flow
from tests.test_ingest import FRAMES, H, W, make_capture
from volcap_core.capture import Capture, CaptureFolder, IngestError
from volcap_core.imageio.read import decode_exr
from volcap_core.imageio.write import write_exr
from volcap_core.store import ArtifactStore, MissingRefError


def _mask(cam: int, take_index: int) -> np.ndarray:
    """A soft-edged disc moving with the frame: coverage in [0, 1]."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    r = np.hypot(xx - 4 - 2 * take_index - cam, yy - 6)
    return np.clip(4.0 - r, 0.0, 1.0).astype(np.float32)


def _grey_png16(path: Path, mask: np.ndarray) -> None:
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(mask.shape[1], mask.shape[0], 1, oiio.UINT16))
    out.write_image(np.ascontiguousarray(np.round(mask * 65535).astype(np.uint16)[..., None]))
    out.close()


def add_masks(root: Path) -> Path:
    """Masks for C0 (16-bit PNG) and C2 (float EXR, camera frame numbers, one more before the
    take); C1 has none. capture.json names the folder."""
    for f in range(FRAMES):
        (root / "masks" / "C0").mkdir(parents=True, exist_ok=True)
        _grey_png16(root / "masks" / "C0" / f"{f:06d}.png", _mask(0, f))
    (root / "masks" / "C2").mkdir()
    for n in range(FRAMES + 2):
        write_exr(root / "masks" / "C2" / f"{n:06d}.exr", _mask(2, n - 2)[..., None], ("A",), pixel_type="float")
    desc = json.loads((root / "capture.json").read_text())
    desc["masks"] = "masks"
    (root / "capture.json").write_text(json.dumps(desc, indent=1))
    return root


@pytest.fixture
def capture_dir(tmp_path: Path) -> Path:
    return add_masks(make_capture(tmp_path / "capture"))


@pytest.fixture
def store_url(tmp_path: Path) -> str:
    return ArtifactStore(str(tmp_path / "store")).url


def test_the_folder_reads_masks_by_take_index(capture_dir):
    folder = CaptureFolder.open(capture_dir)
    assert folder.mask_cameras == ["C0", "C2"]
    assert folder.mask_files("C1") is None
    # C2's file 000003 is take index 1 (it started 2 frames early); its 000000 and 000001 lie before the take
    assert folder.mask_files("C2")[1].name == "000003.exr" and min(folder.mask_files("C2")) == -2
    np.testing.assert_allclose(folder.load_mask("C2", 1), _mask(2, 1), atol=1e-6)
    np.testing.assert_allclose(folder.load_mask("C0", 3), _mask(0, 3), atol=1 / 65535)


def test_ingest_stores_masks_with_their_camera(prefect_api, capture_dir, store_url):
    summary = run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    s = ArtifactStore(store_url)
    capture = s.get_record(summary.result, Capture)
    assert capture.camera("C1").masks is None
    for cam, index in (("C0", 0), ("C2", 2)):
        masks = capture.camera(cam).masks
        assert len(masks) == FRAMES
        for i, ref in enumerate(masks):
            pixels, channels = decode_exr(s.get_bytes(ref))
            assert pixels.shape == (H, W, 3)          # one channel Y, read as grey
            np.testing.assert_allclose(pixels[..., 0], _mask(index, i), atol=1e-3)   # half precision
    record = json.loads(s.get_bytes(summary.result))
    assert "masks" not in next(c for c in record["cameras"] if c["id"] == "C1")


def test_a_capture_without_masks_keeps_its_record(prefect_api, tmp_path, store_url):
    """The same folder with and without a masks folder: the frames are the same objects, and the
    record of the capture without masks has no trace of the field (its digest is what it was)."""
    plain = make_capture(tmp_path / "plain")
    s = ArtifactStore(store_url)
    without = s.get_record(run_flow(ingest_flow, store=store_url, capture_dir=str(plain)).result, Capture)
    assert b'"masks"' not in s.get_bytes(s.get_ref("captures/tiny"))
    masked = run_flow(ingest_flow, store=store_url, capture_dir=str(add_masks(plain)))
    assert masked.tasks_run == 1          # only the record: no camera is converted again
    with_masks = s.get_record(masked.result, Capture)
    assert [c.frames for c in with_masks.cameras] == [c.frames for c in without.cameras]


def _break(root: Path, how: str) -> str:
    """Damage one mask; returns what the one-line error must say."""
    c0 = root / "masks" / "C0"
    if how == "size":
        write_exr(c0 / "000002.png", np.zeros((H, W + 1, 1), np.float32), ("Y",))
        return f"camera C0, frame 2: mask {c0 / '000002.png'} is 17x12, the camera's frames are 16x12"
    if how == "values":
        m = _mask(2, 1)
        m[0, :3] = 1.5
        write_exr(root / "masks" / "C2" / "000003.exr", m[..., None], ("A",), pixel_type="float")
        return f"camera C2, frame 3: mask {root / 'masks' / 'C2' / '000003.exr'} has 3 pixel(s) outside [0, 1]"
    if how == "nan":
        m = _mask(2, 0)
        m[1, 1] = np.nan
        write_exr(root / "masks" / "C2" / "000002.exr", m[..., None], ("A",), pixel_type="float")
        return f"camera C2, frame 2: mask {root / 'masks' / 'C2' / '000002.exr'} has 1 NaN/Inf pixel(s)"
    if how == "channels":
        write_exr(c0 / "000001.png", np.zeros((H, W, 3), np.float32), ("R", "G", "B"))
        return f"camera C0, frame 1: mask {c0 / '000001.png'} has channels R, G, B; a mask has one"
    if how == "missing":
        (c0 / "000003.png").unlink()
        return "camera C0: 1 take frame(s) without a mask in"
    if how == "stray-camera":
        (root / "masks" / "C9").mkdir()
        return f"masks: unexpected folder {root / 'masks' / 'C9'}"
    if how == "damaged":
        f = c0 / "000000.png"
        f.write_bytes(f.read_bytes()[:40])
        return f"camera C0, frame 0: {f}"
    raise AssertionError(how)


@pytest.mark.parametrize("how", ["size", "values", "nan", "channels", "missing", "stray-camera", "damaged"])
def test_a_broken_mask_is_refused_by_name_and_nothing_is_stored(prefect_api, capture_dir, store_url, how):
    fragment = _break(capture_dir, how)
    with pytest.raises(IngestError) as err:
        run_flow(ingest_flow, store=store_url, capture_dir=str(capture_dir))
    assert fragment in str(err.value) and "\n" not in str(err.value)
    s = ArtifactStore(store_url)
    with pytest.raises(MissingRefError):
        s.get_ref("captures/tiny")
    assert list(s.iter_objects()) == []    # refused before any frame was converted
