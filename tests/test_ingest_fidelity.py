"""Ingest drops nothing silently: parts and views are chosen by name, colour primaries are
converted to the working space (or refused), frames are stored display-window sized.

Per-frame checks (``check_headers``, ``convert_frame``) on the openexr-images files in
``../shared/data`` (skipped without them) and on files written here with the OpenEXR bindings;
the flow-level stereo test is in ``tests/test_ingest.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hardware.rig import RigCamera
from volcap_core.capture import CameraSource, CaptureCamera, Encoding, IngestError
from volcap_core.chromaticities import REC709_D65, Chromaticities
from volcap_core.digest import digest_file
from volcap_core.imageio.plain_frame import decode_half_exr
from volcap_core.imageio.read import decode_exr, probe_image, read_exr_header, read_exr_native, read_image
from volcap_core.imageio.write import HALF_MAX, _compression_enum, encode_exr, write_exr
from volcap_core.ingest import RawFrame, check_headers, convert_frame

REPO = Path(__file__).resolve().parents[1]
EXR = REPO.parent / "shared" / "data" / "exr"
needs_data = pytest.mark.skipif(not EXR.is_dir(), reason=f"needs {EXR} (absent without ../shared)")

P3_D65 = Chromaticities(0.680, 0.320, 0.265, 0.690, 0.150, 0.060, 0.3127, 0.3290)


def _camera(**fields) -> CameraSource:
    return CameraSource(id="CAM3", path="x", start_timecode="00:00:00:00", **fields)


def _rig_camera(width: int, height: int) -> RigCamera:
    return RigCamera.model_validate({
        "id": "CAM3", "role": "static", "lens": {"focal_min_mm": 14.0, "focal_max_mm": 42.0},
        "sensor": {"width_mm": 24.0, "height_mm": 24.0 * height / width, "width_px": width, "height_px": height},
        "mount": {"kind": "tripod", "position_m": [3.0, 0.0, 1.5], "look_at_m": [0.0, 0.0, 1.0]},
        "nominal_focal_mm": 20.0})


def _frame(path: Path, number: int = 1) -> RawFrame:
    return RawFrame(take_index=number, camera_frame=number, path=path)


def _ingest(path: Path, cam: CameraSource | None = None, *, nan_policy: str = "error", want_alpha: bool = False,
            ocio_config: Path | None = None) -> tuple[np.ndarray, dict]:
    """convert_frame → (stored pixels [H, W, C] float32, stored header)."""
    data, _ = convert_frame(_frame(path), digest_file(path)[0], cam or _camera(), ocio_config=ocio_config,
                            nan_policy=nan_policy, want_alpha=want_alpha)
    pixels, _ = decode_exr(data)
    import OpenEXR
    import io

    header = OpenEXR.File(io.BytesIO(data), header_only=True).header()
    return pixels, header


def _half(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, np.float32).astype(np.float16).astype(np.float32)


# --------------------------------------------------------------------------------------------------
# Parts and views


@needs_data
def test_a_multi_part_file_without_a_choice_is_refused_listing_what_it_holds():
    path = EXR / "Beachball" / "multipart.0001.exr"
    for run in (lambda: check_headers(_camera(), _rig_camera(2048, 1556), [_frame(path)]), lambda: _ingest(path)):
        with pytest.raises(IngestError) as err:
            run()
        msg = str(err.value)
        assert msg.startswith(f"camera CAM3, frame 1: {path}: holds 10 parts and no part or view was chosen")
        assert "part 'rgba_left' (view 'left'): A, B, G, R" in msg and "part 'depth_left' (view 'left'): Z" in msg
        assert '"exr_part" (a part name) and/or "exr_view" (a view name)' in msg


@needs_data
def test_a_chosen_part_is_stored_in_its_display_window_and_says_where_it_came_from():
    path = EXR / "Beachball" / "multipart.0001.exr"
    cam = _camera(exr_part="rgba_left")
    check_headers(cam, _rig_camera(2048, 1556), [_frame(path)])
    stored, header = _ingest(path, cam)
    assert stored.shape == (1556, 2048, 4)
    source, _ = read_image(path, part=4)  # rgba_left: data window (688, 245)-(1564, 1120)
    np.testing.assert_array_equal(stored[245:1121, 688:1565], source)
    outside = np.ones(stored.shape[:2], bool)
    outside[245:1121, 688:1565] = False
    assert not stored[outside].any()  # colour and alpha 0 outside the data window
    assert (header["volcap.source_part"], header["volcap.source_view"]) == ("rgba_left", "left")
    assert header["volcap.source_data_window"] == "688 245 1564 1120"
    assert header["volcap.source_display_window"] == "0 0 2047 1555"


@needs_data
def test_a_view_of_a_single_part_stereo_file_is_chosen_by_name():
    path = EXR / "Beachball" / "singlepart.0001.exr"
    with pytest.raises(IngestError, match=r"holds 2 views \(right, left\) and no part or view was chosen"):
        check_headers(_camera(), _rig_camera(2048, 1556), [_frame(path)])
    stored, header = _ingest(path, _camera(exr_view="left"))
    native, names = read_exr_native(path)
    left = native[..., [names.index(c) for c in ("left.R", "left.G", "left.B", "left.A")]].astype(np.float32)
    np.testing.assert_array_equal(stored[245:1121, 654:1565], left)
    assert header["volcap.source_view"] == "left" and header["volcap.source_part"] == "rgba"
    with pytest.raises(IngestError, match="holds no view 'centre'"):
        _ingest(path, _camera(exr_view="centre"))


def test_capture_json_names_parts_and_views_and_old_records_still_load():
    assert _camera(exr_part="rgba_left", exr_view="left").exr_view == "left"
    with pytest.raises(ValueError):
        _camera(exr_view="")
    old = {"id": "C0", "width": 4, "height": 3, "channels": ["R", "G", "B"], "source_encoding": "linear", "frames": []}
    cam = CaptureCamera.model_validate(old)
    assert (cam.source_part, cam.source_view, cam.source_chromaticities) == (None, None, None)


# --------------------------------------------------------------------------------------------------
# Colour primaries


@needs_data
def test_xyz_footage_is_stored_as_the_rec709_it_was_made_from():
    folder = EXR / "Chromaticities"
    rec709, header = _ingest(folder / "Rec709.exr")
    np.testing.assert_array_equal(rec709, read_image(folder / "Rec709.exr")[0])  # nothing to convert
    np.testing.assert_allclose(header["chromaticities"], REC709_D65, atol=1e-7)
    assert "volcap.source_chromaticities" not in header
    xyz, header = _ingest(folder / "XYZ.exr")
    assert header["volcap.source_chromaticities"] == "1 0 0 1 0 0 0.333333 0.333333"
    np.testing.assert_allclose(header["chromaticities"], REC709_D65, atol=1e-7)
    # the same picture: equal up to the half rounding of XYZ.exr's values, amplified up to ~5x by the
    # XYZ -> RGB matrix (stored as XYZ, they were unadapted; a Bradford adaptation from its white E
    # would be off by up to 20%)
    np.testing.assert_allclose(xyz, rec709, rtol=4e-3, atol=1e-3)
    # luminance/chroma files decode to RGB in their own primaries and are converted like their RGB
    # twins. Their chroma is 2x2-subsampled (in each file's own primaries), so they match the RGB
    # picture only typically: the XYZ one as well as the Rec.709 one (median error 0.0018 measured),
    # where leaving it unconverted (0.021) or adapting it from white E (0.017) is ~10x off.
    def median_error(name: str) -> float:
        return float(np.median(np.abs(_ingest(folder / name)[0] - rec709)))

    assert median_error("XYZ_YC.exr") <= 1.2 * median_error("Rec709_YC.exr") < 0.003


def test_wide_gamut_footage_is_converted_as_opencolorio_converts_it(tmp_path):
    import PyOpenColorIO as ocio

    p3 = np.random.default_rng(8).uniform(0.0, 4.0, (6, 7, 3)).astype(np.float32)
    path = tmp_path / "p3.exr"
    write_exr(path, p3, ("R", "G", "B"), pixel_type="float", chromaticities=P3_D65)
    stored, header = _ingest(path)
    config = ocio.Config.CreateFromBuiltinConfig("studio-config-latest")
    expected = p3.copy()
    config.getProcessor("Linear P3-D65", "Linear Rec.709 (sRGB)").getDefaultCPUProcessor().applyRGB(expected)
    np.testing.assert_array_equal(stored, _half(expected))
    assert not np.allclose(stored, _half(p3), rtol=1e-2)  # the conversion is not a no-op
    assert header["volcap.source_chromaticities"] == "0.68 0.32 0.265 0.69 0.15 0.06 0.3127 0.329"


def test_ocio_footage_takes_its_primaries_from_its_colourspace_not_twice(tmp_path):
    import PyOpenColorIO as ocio

    config = ocio.Config.CreateFromBuiltinConfig("studio-config-latest")
    config.setRole(ocio.ROLE_SCENE_LINEAR, "Linear Rec.709 (sRGB)")
    (tmp_path / "studio.ocio").write_text(config.serialize())
    p3 = np.random.default_rng(9).uniform(0.0, 4.0, (6, 7, 3)).astype(np.float32)
    path = tmp_path / "p3.exr"
    write_exr(path, p3, ("R", "G", "B"), pixel_type="float", chromaticities=P3_D65)
    cam = _camera(encoding=Encoding.ocio, ocio_colorspace="Linear P3-D65")
    stored, _ = _ingest(path, cam, ocio_config=tmp_path / "studio.ocio")
    expected = p3.copy()
    config.getProcessor("Linear P3-D65", "Linear Rec.709 (sRGB)").getDefaultCPUProcessor().applyRGB(expected)
    np.testing.assert_array_equal(stored, _half(expected))


def test_chromaticities_that_define_no_conversion_are_refused(tmp_path):
    path = tmp_path / "000001.exr"
    collinear = Chromaticities(0.2, 0.2, 0.4, 0.4, 0.6, 0.6, 0.3127, 0.3290)
    write_exr(path, np.ones((3, 4, 3), np.float32), ("R", "G", "B"), chromaticities=collinear)
    with pytest.raises(IngestError) as err:
        check_headers(_camera(), _rig_camera(4, 3), [_frame(path)])
    assert str(err.value).startswith(f"camera CAM3, frame 1: {path}: its colour cannot be converted to the "
                                     "working space: chromaticities")
    assert "collinear" in str(err.value)
    with pytest.raises(IngestError, match="collinear"):
        _ingest(path)


def test_a_camera_whose_frames_disagree_on_their_primaries_is_refused(tmp_path):
    a, b = tmp_path / "000001.exr", tmp_path / "000002.exr"
    write_exr(a, np.ones((3, 4, 3), np.float32), ("R", "G", "B"))
    write_exr(b, np.ones((3, 4, 3), np.float32), ("R", "G", "B"), chromaticities=P3_D65)
    with pytest.raises(IngestError, match=r"camera CAM3, frame 2: .*000002.exr declares chromaticities \(red \(0.68"):
        check_headers(_camera(), _rig_camera(4, 3), [_frame(a, 1), _frame(b, 2)])


# --------------------------------------------------------------------------------------------------
# Windows


@needs_data
def test_the_rig_resolution_is_the_display_window():
    t08 = EXR / "DisplayWindow" / "t08.exr"  # 400x300 data window at (30, 40) in a 501x401 display window
    check_headers(_camera(), _rig_camera(501, 401), [_frame(t08)])
    with pytest.raises(IngestError, match=r"t08.exr is 501x401 \(display window \(0, 0, 500, 400\)\), the rig says 400x300"):
        check_headers(_camera(), _rig_camera(400, 300), [_frame(t08)])


@needs_data
@pytest.mark.parametrize("n", range(1, 17))
def test_display_window_set(n):
    """Every t01..t16 stored at its display window's size, the 400x300 picture at its offset."""
    path = EXR / "DisplayWindow" / f"t{n:02d}.exr"
    picture, _ = read_image(EXR / "DisplayWindow" / "t01.exr")  # all 16 hold these pixels
    info = probe_image(path)
    (dx0, dy0, _, _), (px0, py0, px1, py1) = info.data_window, info.display_window
    rig = _rig_camera(px1 - px0 + 1, py1 - py0 + 1)
    if n in (15, 16):  # pixel aspect ratio 1.5 and 0.667: the camera model's pixels are square
        with pytest.raises(IngestError, match=r"pixelAspectRatio (1\.5|0\.666667); the rig's cameras have square pixels"):
            check_headers(_camera(), rig, [_frame(path)])
        return
    check_headers(_camera(), rig, [_frame(path)])
    stored, _ = _ingest(path)
    assert stored.shape == (py1 - py0 + 1, px1 - px0 + 1, 3)
    for y, x in [(0, 0), (0, 399), (299, 0), (299, 399), (150, 200), (17, 333)]:  # picture pixels
        sy, sx = y + dy0 - py0, x + dx0 - px0  # where they land in the display window
        if 0 <= sy < stored.shape[0] and 0 <= sx < stored.shape[1]:
            np.testing.assert_array_equal(stored[sy, sx], picture[y, x])
    covered = np.zeros(stored.shape[:2], bool)
    covered[max(dy0 - py0, 0):max(dy0 - py0 + 300, 0), max(dx0 - px0, 0):max(dx0 - px0 + 400, 0)] = True
    assert not stored[~covered].any()  # no picture there: 0


def _write_windowed(path: Path, pixels: np.ndarray, channels: str, data_window, display_window) -> None:
    import OpenEXR

    def box(w):
        return (np.array(w[:2], np.int32), np.array(w[2:], np.int32))

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "dataWindow": box(data_window), "displayWindow": box(display_window)}
    OpenEXR.File(header, {c: np.ascontiguousarray(pixels[..., i]) for i, c in enumerate(channels)}).write(str(path))


def test_alpha_is_zero_outside_the_data_window(tmp_path):
    rgba = np.random.default_rng(3).uniform(0.1, 1.0, (3, 4, 4)).astype(np.float32)
    path = tmp_path / "rgba.exr"
    _write_windowed(path, rgba, "RGBA", (2, 1, 5, 3), (0, 0, 7, 5))
    stored, _ = _ingest(path)
    assert stored.shape == (6, 8, 4)
    np.testing.assert_array_equal(stored[1:4, 2:6], _half(rgba))
    stored[1:4, 2:6] = 0
    assert not stored.any()
    # footage without alpha in a camera that has it: alpha 1 where the data window is, 0 elsewhere
    rgb = tmp_path / "rgb.exr"
    _write_windowed(rgb, rgba[..., :3], "RGB", (2, 1, 5, 3), (0, 0, 7, 5))
    stored, _ = _ingest(rgb, want_alpha=True)
    assert stored[..., 3].sum() == 12 and (stored[1:4, 2:6, 3] == 1).all()


def test_overscan_is_left_out_and_not_policed(tmp_path):
    """Pixels of the data window outside the display window are not stored: a NaN there does not
    refuse the frame."""
    rgb = np.ones((6, 8, 3), np.float32)
    rgb[0, 0] = np.nan  # in the overscan
    path = tmp_path / "overscan.exr"
    _write_windowed(path, rgb, "RGB", (-2, -1, 5, 4), (0, 0, 3, 2))
    stored, _ = _ingest(path, nan_policy="error")
    np.testing.assert_array_equal(stored, np.ones((3, 4, 3), np.float32))


# --------------------------------------------------------------------------------------------------
# Plain frames (already what ingest stores) are restamped, not re-encoded


def _plain_source(tmp_path: Path, pixels: np.ndarray, **kw) -> Path:
    path = tmp_path / "000001.exr"
    path.write_bytes(encode_exr(pixels, "RGBA", **kw))
    return path


def test_a_plain_linear_frame_is_stored_bit_exact_in_its_own_compression(tmp_path):
    px = (np.random.default_rng(3).random((24, 32, 4)) * 3).astype(np.float32)
    path = _plain_source(tmp_path, px, compression="piz", attributes={"owner": "vendor"})
    data, repaired = convert_frame(_frame(path), digest_file(path)[0], _camera(), ocio_config=None,
                                   nan_policy="error", want_alpha=True)
    source = decode_half_exr(path.read_bytes())
    assert repaired == 0
    assert np.array_equal(decode_half_exr(data).view(np.uint16), source.view(np.uint16))
    stored = tmp_path / "stored.exr"
    stored.write_bytes(data)
    header = read_exr_header(stored)
    assert header["compression"] == _compression_enum("piz")
    assert header["volcap.camera"] == "CAM3" and header["volcap.take_index"] == "1"
    assert header["volcap.source_display_window"] == "0 0 31 23" and "owner" not in header
    assert "chromaticities" in header


@pytest.mark.parametrize("policy", ["error", "repair"])
def test_nan_in_a_plain_frame_still_meets_the_policy(tmp_path, policy):
    px = np.ones((8, 8, 4), np.float32)
    px[2, 3, 1] = np.nan
    px[5, 5, 0] = np.inf
    path = _plain_source(tmp_path, px)
    if policy == "error":
        with pytest.raises(IngestError, match=r"camera CAM3, frame 1 .*: 2 pixel\(s\) hold NaN or Inf"):
            _ingest(path, want_alpha=True)
        return
    stored, _ = _ingest(path, nan_policy="repair", want_alpha=True)
    assert np.isfinite(stored).all() and stored[2, 3, 1] == 0.0 and stored[5, 5, 0] == HALF_MAX


def test_a_plain_frame_with_a_damaged_payload_is_refused_naming_camera_and_frame(tmp_path):
    path = _plain_source(tmp_path, (np.random.default_rng(1).random((32, 32, 4))).astype(np.float32))
    data = bytearray(path.read_bytes())
    for i in range(len(data) - 40, len(data) - 20):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(IngestError, match=r"camera CAM3, frame 1: .*000001\.exr: damaged EXR: pixel data does not decode"):
        _ingest(path, want_alpha=True)


def test_a_plain_frame_in_other_primaries_is_converted_not_restamped(tmp_path):
    px = np.full((4, 4, 4), 0.5, np.float32)
    px[..., 0] = 0.9
    path = _plain_source(tmp_path, px, chromaticities=P3_D65)
    stored, header = _ingest(path, want_alpha=True)
    assert not np.allclose(stored[..., :3], _half(px[..., :3]), atol=1e-3)  # converted to Rec.709
    assert header["volcap.source_chromaticities"].startswith("0.68 0.32")
