"""volcap_core.imageio: EXR/PNG/TIFF/DPX reading, EXR writing, and refusal of damaged files.

Real-data checks use ``../shared/data`` (openexr-images, OpenImageIO's reference hashes) and skip
without it; the synthetic checks (round trips, integer formats, structural damage) always run.
Damaged files are decoded in one child process so that a decoder crash would fail a test instead
of killing the test run.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import re
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from volcap_core.imageio.check import read_header
from volcap_core.imageio.errors import ImageReadError, SourceChoiceError
from volcap_core.imageio.parts import PartHeader, window_overlap
from volcap_core.imageio.plain_frame import (
    decode_half_exr,
    half_nonfinite_pixels,
    plain_frame_header,
    restamp_exr,
)
from volcap_core.imageio.read import (
    ImageInfo,
    decode_exr,
    probe_footage,
    probe_image,
    read_exr_header,
    read_exr_native,
    read_footage,
    read_image,
)
from volcap_core.imageio.write import _compression_enum, encode_exr, write_exr

REPO = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
EXR = DATA / "exr"
NO_DATA = f"shared test data not found at {DATA} (a clone without ../shared/data skips real-file checks)"
needs_data = pytest.mark.skipif(not EXR.is_dir(), reason=NO_DATA)

BROKEN_COMP = re.compile(r"comp_(bad_.*|early_eof_.*|short_decode_.*|invalid_unknown)\.exr$")


def _tsv(name: str) -> list[dict[str, str]]:
    path = DATA / "reference" / name
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f, delimiter="\t"))


def _params(values: list, ids=None) -> list:
    """Parameters, or one skipped placeholder when the shared data is absent."""
    if values:
        return [pytest.param(v, id=ids(v) if ids else None) for v in values]
    return [pytest.param(None, marks=pytest.mark.skip(reason=NO_DATA))]


SHA_ROWS = _tsv("exr_pixel_sha1.tsv")
INVENTORY = _tsv("exr_inventory.tsv")
_COMP = sorted((EXR / "OpenEXRTest").glob("comp_*.exr"))  # empty when the data is absent
DAMAGED = sorted(p for p in (EXR / "Damaged").glob("*") if p.is_file()) + [p for p in _COMP if BROKEN_COMP.search(p.name)]
GOOD_COMP = [p for p in _COMP if not BROKEN_COMP.search(p.name)]


def _rel(p: Path) -> str:
    return str(p.relative_to(EXR))


# ---------------------------------------------------------------------------------------------------
# Reference decoding: OpenImageIO's committed SHA-1s of the native pixels.


@pytest.mark.parametrize("row", _params(SHA_ROWS, ids=lambda r: f"{r['file']}#{r['subimage']}"))
def test_native_pixels_match_reference_sha1(row):
    pixels, channels = read_exr_native(EXR / row["file"], part=int(row["subimage"]))
    # the layout the hashes cover: [H, W, C] C-contiguous = interleaved channels, scan-line order
    assert pixels.flags.c_contiguous and pixels.ndim == 3 and pixels.shape[2] == len(channels)
    assert hashlib.sha1(pixels.tobytes()).hexdigest().upper() == row["sha1"]


# ---------------------------------------------------------------------------------------------------
# Every readable EXR in the collection.

_SIZE = re.compile(r"^(\d+)x(\d+)(?: dataWin@\((-?\d+),(-?\d+)\))?(?: displayWin (\d+)x(\d+)@\((-?\d+),(-?\d+)\))?")


def _expected_windows(details: str) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """(data window, display window) of the first part, from the inventory's details column."""
    m = _SIZE.match(details.split(" | ")[0])
    assert m, details
    w, h = int(m[1]), int(m[2])
    x, y = int(m[3] or 0), int(m[4] or 0)
    dw = (x, y, x + w - 1, y + h - 1)
    if m[5]:
        dx, dy = int(m[7]), int(m[8])
        return dw, (dx, dy, dx + int(m[5]) - 1, dy + int(m[6]) - 1)
    return dw, dw


@pytest.mark.parametrize("row", _params(INVENTORY, ids=lambda r: r["path"]))
def test_reads_every_exr_of_the_collection(row):
    path = EXR / row["path"]
    data_window, display_window = _expected_windows(row["details"])
    info = probe_image(path)
    assert info.format == "exr" and info.parts == int(row["parts"])
    assert info.data_window == data_window and info.display_window == display_window
    if not ({"R", "G", "B"} <= set(info.channels) or "Y" in info.channels):
        with pytest.raises(ImageReadError, match=r"no RGB channels \(it has G\)"):
            read_image(path)  # TestImages/WideFloatRange.exr: a lone G channel
        return
    pixels, channels = read_image(path)
    assert channels in (("R", "G", "B"), ("R", "G", "B", "A"))
    assert pixels.dtype == np.float32 and pixels.flags.c_contiguous
    assert pixels.shape == (info.height, info.width, len(channels))
    assert (info.width, info.height) == (data_window[2] - data_window[0] + 1, data_window[3] - data_window[1] + 1)


@pytest.mark.parametrize("path", _params(GOOD_COMP, ids=lambda p: p.name))
def test_every_compression_decodes(path):
    pixels, channels = read_image(path)
    assert pixels.shape[:2] in ((674, 586), (675, 587)) and np.isfinite(pixels).any()
    if path.name in {"comp_rle.exr", "comp_zips.exr", "comp_zip.exr", "comp_piz.exr"}:
        # lossless codecs must give exactly the uncompressed file's pixels
        reference, _ = read_image(EXR / "OpenEXRTest" / "comp_none.exr")
        np.testing.assert_array_equal(pixels, reference)


@needs_data
def test_multipart_part_selection():
    path = EXR / "Beachball" / "multipart.0001.exr"
    right, ch_r = read_image(path, part=0)  # rgba_right, data window at (654, 245)
    left, ch_l = read_image(path, part=4)  # rgba_left, data window at (688, 245)
    assert ch_r == ch_l == ("R", "G", "B", "A")
    assert right.shape == left.shape == (876, 877, 4)
    assert not np.array_equal(right, left)
    assert probe_image(path, part=4).data_window == (688, 245, 688 + 876, 245 + 875)
    with pytest.raises(ImageReadError, match=r"no RGB channels \(it has Z\)") as err:
        read_image(path, part=1)  # depth_left
    assert str(path) in str(err.value)
    with pytest.raises(ImageReadError, match="part 10 requested, the file has 10 part"):
        read_image(path, part=10)
    with pytest.raises(ImageReadError, match="part 1 requested"):
        read_image(EXR / "ScanLines" / "Desk.exr", part=1)


@needs_data
def test_display_window_with_negative_offsets():
    info = probe_image(EXR / "DisplayWindow" / "t07.exr")
    assert info.data_window == (0, 0, 399, 299) and info.display_window == (-40, -40, 440, 330)
    assert read_image(EXR / "DisplayWindow" / "t07.exr")[0].shape == (300, 400, 3)
    # same pixels whatever the display window says
    np.testing.assert_array_equal(
        read_image(EXR / "DisplayWindow" / "t07.exr")[0], read_image(EXR / "DisplayWindow" / "t01.exr")[0]
    )
    assert probe_image(EXR / "DisplayWindow" / "t08.exr").data_window == (30, 40, 429, 339)


@needs_data
def test_mipmapped_and_tiled_give_level_zero():
    pixels, channels = read_image(EXR / "MultiResolution" / "ColorCodedLevels.exr")
    assert pixels.shape == (512, 512, 4) and channels == ("R", "G", "B", "A")
    pixels, _ = read_image(EXR / "MultiResolution" / "PeriodicPattern.exr")
    assert pixels.shape == (517, 517, 3)
    assert read_image(EXR / "Tiles" / "GoldenGate.exr")[0].shape == (860, 1262, 3)


@needs_data
def test_luminance_chroma_and_luminance_only_come_back_as_rgb():
    yc, channels = read_image(EXR / "Chromaticities" / "Rec709_YC.exr")
    rgb, _ = read_image(EXR / "Chromaticities" / "Rec709.exr")
    assert channels == ("R", "G", "B") and yc.shape == rgb.shape
    # the same picture stored as Y + subsampled chroma: close, not equal (chroma is 2x2 subsampled)
    assert np.median(np.abs(yc - rgb)) < 0.02 * np.median(np.abs(rgb))
    grey, channels = read_image(EXR / "LuminanceChroma" / "Garden.exr")  # Y only, tiled
    assert channels == ("R", "G", "B")
    np.testing.assert_array_equal(grey[..., 0], grey[..., 1])
    np.testing.assert_array_equal(grey[..., 0], grey[..., 2])
    assert probe_image(EXR / "LuminanceChroma" / "Garden.exr").channels == ("Y",)


@needs_data
def test_nan_and_inf_returned_as_stored():
    path = EXR / "TestImages" / "BrightRingsNanInf.exr"
    pixels, _ = read_image(path)
    native, _ = read_exr_native(path)
    assert np.isnan(pixels).any() and np.isinf(pixels).any()
    np.testing.assert_array_equal(pixels, native.astype(np.float32))  # NaN positions included


@needs_data
def test_deep_file_is_refused_clearly():
    path = EXR / "v2" / "Trunks_deep.exr"
    for read in (probe_image, read_image, read_exr_native):
        with pytest.raises(ImageReadError, match="deep data not supported"):
            read(path)


@needs_data
def test_every_half_value_survives_native_read():
    native, _ = read_exr_native(EXR / "TestImages" / "AllHalfValues.exr")
    assert native.dtype == np.float16
    bits = np.unique(native.view(np.uint16))
    assert bits.size >= 65536 - 2048  # all values bar NaN payload variants


# ---------------------------------------------------------------------------------------------------
# Damaged files: one child process reads them all (a crash there fails the test, not the run).

_CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    # a decoder that tries to allocate absurd memory fails here instead of swapping the machine
    resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30))
    from volcap_core.imageio.errors import ImageReadError
    from volcap_core.imageio.read import probe_image, read_image
    for path in json.load(sys.stdin):
        for fn in (probe_image, read_image):
            t = time.perf_counter()
            try:
                fn(path)
                out = {"ok": True}
            except ImageReadError as e:
                out = {"error": "ImageReadError", "reason": e.reason, "message": str(e)}
            except BaseException as e:  # noqa: BLE001 - reported, the parent decides
                out = {"error": type(e).__name__, "message": str(e)[:300]}
            out.update(path=path, fn=fn.__name__, seconds=time.perf_counter() - t)
            print(json.dumps(out), flush=True)
    # this process's own peak: ru_maxrss would also count the parent's, whose memory the child
    # shared (vfork) until exec - a test process that had held 1.8 GB made it look like ours
    try:
        with open("/proc/self/status") as f:
            peak = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    except (OSError, StopIteration):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"maxrss_kb": peak}), flush=True)
    """
)


def _run_child(paths: list[str], timeout: float = 120) -> tuple[dict, int]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD], input=json.dumps(paths), capture_output=True, text=True,
        timeout=timeout, cwd=REPO, env=env,
    )
    lines = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    last = lines[-1] if lines else "nothing"
    assert proc.returncode == 0, f"reader process died (rc={proc.returncode}) after {last}: {proc.stderr[-2000:]}"
    results = {(r["path"], r["fn"]): r for r in lines if "path" in r}
    return results, lines[-1]["maxrss_kb"]


@pytest.fixture(scope="module")
def damaged_results():
    if not DAMAGED:
        pytest.skip(NO_DATA)
    return _run_child([str(p) for p in DAMAGED])


@pytest.mark.parametrize("path", _params(DAMAGED, ids=_rel))
def test_damaged_file_gives_image_read_error(path, damaged_results):
    results, _ = damaged_results
    probe, read = results[(str(path), "probe_image")], results[(str(path), "read_image")]
    # read_image must refuse; probe_image may pass only a file whose damage is in compressed payload
    assert read.get("error") == "ImageReadError", read
    assert str(path) in read["message"] and read["reason"]
    assert probe.get("ok") or probe.get("error") == "ImageReadError", probe
    assert read["seconds"] < 5 and probe["seconds"] < 5


@needs_data
def test_memory_dos_files_refused_quickly_before_decoding(damaged_results):
    results, maxrss_kb = damaged_results
    for name in ("memory_DOS_1", "memory_DOS_2.2", "openexr_2.2.0_memory_allocation_error_2_exr"):
        r = results[(str(EXR / "Damaged" / name), "probe_image")]
        assert r.get("error") == "ImageReadError" and r["seconds"] < 0.5, r
        assert re.search(r"refused|uncompressed chunk", r["reason"]), r
    assert maxrss_kb < 1_500_000, f"reading damaged files peaked at {maxrss_kb} kB"


def test_structurally_damaged_exrs_never_reach_the_decoder(tmp_path):
    """Synthetic damage, independent of the shared data: every truncation, a zeroed chunk offset,
    a huge data window, a chunk leader pointing elsewhere, an inconsistent uncompressed size."""
    pixels = np.random.default_rng(1).random((40, 24, 3), dtype=np.float32)
    good = encode_exr(pixels, ("R", "G", "B"), compression="none")
    table = read_header(good, 8, len(good))[1]  # end of the header = start of the offset table
    for cut in range(len(good)):  # every truncation
        with pytest.raises(ImageReadError, match="damaged EXR"):
            decode_exr(good[:cut], name=f"cut{cut}")

    def patched(offset: int, fmt: str, *values) -> bytes:
        b = bytearray(good)
        struct.pack_into(fmt, b, offset, *values)
        return bytes(b)

    with pytest.raises(ImageReadError, match=r"entry 3 of 40 is 0 \(file incomplete\)"):
        decode_exr(patched(table + 3 * 8, "<Q", 0))
    with pytest.raises(ImageReadError, match="points outside the file"):
        decode_exr(patched(table + 5 * 8, "<Q", len(good) + 10))
    first_chunk = struct.unpack_from("<Q", good, table)[0]
    with pytest.raises(ImageReadError, match="chunk 0 starts at line 7, expected 0"):
        decode_exr(patched(first_chunk, "<i", 7))
    with pytest.raises(ImageReadError, match="uncompressed chunk 0 holds 8 bytes"):
        decode_exr(patched(first_chunk + 4, "<i", 8))
    dw = good.index(b"dataWindow\x00box2i\x00") + len(b"dataWindow\x00box2i\x00") + 4
    with pytest.raises(ImageReadError, match=r"data window 24x1000000000 = 24000000000 px refused"):
        decode_exr(patched(dw, "<4i", 0, 0, 23, 10**9 - 1), name="dos.exr")
    with pytest.raises(ImageReadError, match="unknown version flags"):
        decode_exr(patched(4, "<I", 2 | 0x8000))
    with pytest.raises(ImageReadError, match="bad magic number"):
        decode_exr(b"\x00" + good[1:])


def test_byte_mutations_never_crash_the_reader(tmp_path):
    """Seeded random byte flips over small EXRs (every codec family): the reader either decodes or
    raises ImageReadError; run in a child process so a native crash would show up as a failure."""
    rng = np.random.default_rng(20261122)
    pixels = rng.random((20, 33, 4), dtype=np.float32)
    paths = []
    for comp in ("none", "rle", "zips", "zip", "piz", "pxr24", "b44", "dwaa", "dwab"):
        good = bytearray(encode_exr(pixels, compression=comp))
        for k in range(12):
            b = bytearray(good)
            for pos in rng.integers(0, len(b), size=int(rng.integers(1, 6))):
                b[pos] = int(rng.integers(0, 256))
            p = tmp_path / f"{comp}_{k}.exr"
            p.write_bytes(bytes(b))
            paths.append(str(p))
    results, _ = _run_child(paths)
    for r in results.values():
        assert "ok" in r or r["error"] == "ImageReadError", r


# ---------------------------------------------------------------------------------------------------
# Integer formats through OpenImageIO.


def _write_oiio(path: Path, pixels: np.ndarray, fmt: str, bits: int | None = None) -> None:
    import OpenImageIO as oiio

    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    if bits:
        spec.attribute("oiio:BitsPerSample", bits)
    if c == 4:
        spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(str(path), spec), oiio.geterror()
    assert out.write_image(pixels), out.geterror()
    out.close()


@pytest.mark.parametrize(
    "name, dtype, channels",
    [("rgba8.png", np.uint8, 4), ("rgb16.png", np.uint16, 3), ("rgb8.tif", np.uint8, 3), ("rgba16.tif", np.uint16, 4)],
)
def test_png_and_tiff_are_normalised_code_values(tmp_path, name, dtype, channels):
    codes = np.random.default_rng(2).integers(0, np.iinfo(dtype).max + 1, (5, 7, channels), dtype=dtype)
    path = tmp_path / name
    _write_oiio(path, codes, "uint8" if dtype == np.uint8 else "uint16")
    pixels, names = read_image(path)
    assert names == ("R", "G", "B", "A")[:channels] and pixels.dtype == np.float32
    # colour is not premultiplied by alpha, not linearised: code / max
    np.testing.assert_allclose(pixels, codes / np.iinfo(dtype).max, rtol=0, atol=1e-7)
    info = probe_image(path)
    assert info == ImageInfo(
        path=str(path), width=7, height=5, channels=names, pixel_types=(np.dtype(dtype).name,) * channels,
        format=name.split(".")[1].replace("tif", "tiff"), parts=1, data_window=(0, 0, 6, 4),
        display_window=(0, 0, 6, 4), bits_per_sample=8 * np.dtype(dtype).itemsize,
        part_headers=(PartHeader(index=0, name=None, view=None, views=(), channels=names,
                                 data_window=(0, 0, 6, 4), display_window=(0, 0, 6, 4)),),
    )


@pytest.mark.parametrize("name, bits", [("plate.dpx", 10), ("plate.dpx", 12), ("scan.tif", 10), ("scan.tif", 12)])
def test_high_bit_depth_gives_code_over_max_code(tmp_path, name, bits):
    # 10/12-bit codes sit in uint16 containers: the value must be code / (2**bits - 1) exactly,
    # not the widened 16-bit value / 65535
    codes = np.random.default_rng(3).integers(0, 2**bits, (6, 8, 3), dtype=np.uint16)
    path = tmp_path / name
    _write_oiio(path, codes.astype(np.float32) / (2**bits - 1), "uint16", bits=bits)
    info = probe_image(path)
    assert info.format == name.split(".")[1].replace("tif", "tiff") and info.bits_per_sample == bits
    pixels, names = read_image(path)
    assert names == ("R", "G", "B")
    np.testing.assert_allclose(pixels, codes / (2**bits - 1), rtol=0, atol=1e-7)


def test_grey_png_comes_back_as_rgb(tmp_path):
    codes = np.arange(16, dtype=np.uint8).reshape(4, 4, 1) * 16
    _write_oiio(tmp_path / "grey.png", codes, "uint8")
    pixels, names = read_image(tmp_path / "grey.png")
    assert names == ("R", "G", "B")
    np.testing.assert_allclose(pixels, np.repeat(codes / 255, 3, axis=2), atol=1e-7)


def test_truncated_png_unknown_and_missing_files(tmp_path):
    codes = np.random.default_rng(4).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    _write_oiio(tmp_path / "full.png", codes, "uint8")
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageReadError, match="damaged PNG") as err:
        read_image(tmp_path / "cut.png")
    assert str(tmp_path / "cut.png") in str(err.value)
    (tmp_path / "notes.exr").write_text("not an image")
    with pytest.raises(ImageReadError, match="bad magic number"):
        read_image(tmp_path / "notes.exr")
    (tmp_path / "blob.bin").write_bytes(b"\x00\x01garbage" * 10)
    with pytest.raises(ImageReadError, match="unsupported or unrecognised image format"):
        probe_image(tmp_path / "blob.bin")
    (tmp_path / "empty.exr").write_bytes(b"")
    with pytest.raises(ImageReadError, match="empty file"):
        read_image(tmp_path / "empty.exr")
    with pytest.raises(ImageReadError, match="cannot read file"):
        read_image(tmp_path / "missing.exr")


# ---------------------------------------------------------------------------------------------------
# Writing.


def _all_finite_halves() -> np.ndarray:
    h = np.arange(65536, dtype=np.uint16).view(np.float16)
    return h[np.isfinite(h)]  # 63488 values


@pytest.mark.parametrize("compression", ["none", "rle", "zips", "zip", "piz"])
def test_half_round_trip_is_exact(compression):
    values = np.concatenate([_all_finite_halves(), np.array([np.inf, -np.inf], np.float16)])
    pixels = np.resize(values, 124 * 256 * 2).reshape(124, 256, 2)
    pixels = np.concatenate([pixels, pixels[:, ::-1, :1]], axis=2).astype(np.float32)
    out, channels = decode_exr(encode_exr(pixels, ("R", "G", "B"), compression=compression))
    assert channels == ("R", "G", "B")
    np.testing.assert_array_equal(out, pixels)
    assert out.view(np.uint32).tobytes() == pixels.view(np.uint32).tobytes()  # -0.0 kept too


def test_float_round_trip_and_nan(tmp_path):
    pixels = np.random.default_rng(5).normal(0, 1e6, (8, 9, 4)).astype(np.float32)
    pixels[0, 0, 0] = np.nan
    write_exr(tmp_path / "f.exr", pixels, pixel_type="float")
    out, channels = read_image(tmp_path / "f.exr")
    assert channels == ("R", "G", "B", "A")
    np.testing.assert_array_equal(out, pixels)
    native, names = read_exr_native(tmp_path / "f.exr")
    assert native.dtype == np.float32 and names == ("R", "G", "B", "A")


def test_half_output_clamps_finite_values_and_keeps_inf_nan():
    pixels = np.array([[[7e4, -1e9, 65519.0], [np.inf, -np.inf, np.nan]]], dtype=np.float32)
    out, _ = decode_exr(encode_exr(pixels, ("R", "G", "B")))
    np.testing.assert_array_equal(out[0, 0], [65504.0, -65504.0, 65504.0])
    assert out[0, 1, 0] == np.inf and out[0, 1, 1] == -np.inf and np.isnan(out[0, 1, 2])


def test_attributes_read_back(tmp_path):
    attributes = {"cameraName": "A07", "focalLengthMm": 35.123456789, "frame": 1042, "captureTime": 1767225600.123456}
    path = tmp_path / "cam.exr"
    write_exr(path, np.zeros((2, 3, 3), np.float32), ("R", "G", "B"), compression="piz", attributes=attributes)
    header = read_exr_header(path)
    assert {k: header[k] for k in attributes} == attributes
    assert str(header["compression"]).endswith("PIZ_COMPRESSION")
    with pytest.raises(ValueError, match="reserved"):
        encode_exr(np.zeros((2, 3, 3)), ("R", "G", "B"), attributes={"dataWindow": "x"})
    with pytest.raises(ValueError, match="only str, float and int"):
        encode_exr(np.zeros((2, 3, 3)), ("R", "G", "B"), attributes={"matrix": [1, 2]})


def test_write_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "frame.exr"
    with pytest.raises(ValueError, match="does not match channels"):
        write_exr(path, np.zeros((4, 4, 3), np.float32))  # 3 planes, 4 channel names
    assert list(tmp_path.iterdir()) == []
    write_exr(path, np.ones((4, 4, 3), np.float32), ("R", "G", "B"))
    before = path.read_bytes()

    def broken_replace(src, dst):
        raise OSError("disk vanished")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk vanished"):
        write_exr(path, np.zeros((4, 4, 3), np.float32), ("R", "G", "B"))
    assert path.read_bytes() == before  # old content intact, temporary file removed
    assert [p.name for p in tmp_path.iterdir()] == ["frame.exr"]


def test_encode_exr_bytes_equal_written_file(tmp_path):
    pixels = np.random.default_rng(6).random((6, 5, 4), dtype=np.float32)
    write_exr(tmp_path / "a.exr", pixels)
    assert (tmp_path / "a.exr").read_bytes() == encode_exr(pixels)
    info = probe_image(tmp_path / "a.exr")
    assert info.pixel_types == ("half",) * 4 and info.channels == ("R", "G", "B", "A")


def test_decode_errors_name_the_source():
    with pytest.raises(ImageReadError, match=r"^store:blake3:ab: damaged EXR: truncated"):
        decode_exr(b"v/1\x01", name="store:blake3:ab")


def test_openexr_core_switch_is_restored():
    import OpenImageIO as oiio

    before = oiio.get_int_attribute("openexr:core", 1)
    decode_exr(encode_exr(np.zeros((2, 2, 3), np.float32), ("R", "G", "B")))
    assert oiio.get_int_attribute("openexr:core", 1) == before


# ---------------------------------------------------------------------------------------------------
# Parts and views: chosen by name (OpenEXR multi-part `name`/`view`, multi-view `multiView`), never guessed.


def _view_pixels(view: str) -> np.ndarray:
    seed = sum(map(ord, view))
    return np.random.default_rng(seed).uniform(0, 8, (4, 5, 3)).astype(np.float16)


def _write_two_view_file(path: Path, views=("left", "right")) -> None:
    """One part, OpenEXR's multi-view convention: ``multiView`` lists the views, default first; the
    default view's channels are unprefixed, the other's prefixed ``<view>.``; a depth channel too."""
    import OpenEXR

    planes = {}
    for i, view in enumerate(views):
        prefix = "" if i == 0 else f"{view}."
        planes.update({f"{prefix}{c}": np.ascontiguousarray(_view_pixels(view)[..., k]) for k, c in enumerate("RGB")})
    planes["Z"] = np.ones((4, 5), np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "multiView": list(views)}
    OpenEXR.File(header, planes).write(str(path))


def _write_stereo_parts(path: Path) -> None:
    """Three parts: ``cam_left`` (view left) and ``cam_right`` (view right) with R,G,B; ``depth`` with Z."""
    import OpenEXR

    def part(name: str, planes: dict, view: str | None = None) -> "OpenEXR.Part":
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        if view is not None:
            header["view"] = view
        return OpenEXR.Part(header, planes, name=name)

    rgb = {v: {c: np.ascontiguousarray(_view_pixels(v)[..., k]) for k, c in enumerate("RGB")} for v in ("left", "right")}
    OpenEXR.File([part("cam_left", rgb["left"], "left"), part("cam_right", rgb["right"], "right"),
                  part("depth", {"Z": np.ones((4, 5), np.float32)})]).write(str(path))


def test_multi_view_file_is_read_by_view_name(tmp_path):
    path = tmp_path / "stereo.exr"
    _write_two_view_file(path)
    for view in ("left", "right"):
        footage = read_footage(path, view=view)
        assert footage.channels == ("R", "G", "B") and footage.source.view == view
        np.testing.assert_array_equal(footage.pixels, _view_pixels(view).astype(np.float32))
    assert read_footage(path, view="right").source.channels == ("right.R", "right.G", "right.B")
    assert read_footage(path, view="left").source.channels == ("R", "G", "B")  # the default view: unprefixed


def test_multi_view_file_without_a_choice_is_refused_listing_its_views(tmp_path):
    path = tmp_path / "stereo.exr"
    _write_two_view_file(path)
    for read in (read_footage, probe_footage):
        with pytest.raises(SourceChoiceError) as err:
            read(path)
        msg = str(err.value)
        assert msg.startswith(f"{path}: holds 2 views (left, right) and no part or view was chosen")
        assert "views 'left', 'right'; 'left' is the default" in msg and "right.R" in msg and "Z" in msg
    with pytest.raises(SourceChoiceError, match=r"holds no view 'centre' with R,G,B \(or Y\) channels; it holds"):
        read_footage(path, view="centre")


def test_multi_part_file_is_read_by_part_or_view_name(tmp_path):
    path = tmp_path / "parts.exr"
    _write_stereo_parts(path)
    right = read_footage(path, part="cam_right")
    assert (right.source.part, right.source.view) == (1, "right")
    np.testing.assert_array_equal(right.pixels, _view_pixels("right").astype(np.float32))
    left = read_footage(path, view="left")
    assert (left.source.part_name, left.source.part) == ("cam_left", 0)
    np.testing.assert_array_equal(left.pixels, _view_pixels("left").astype(np.float32))
    with pytest.raises(SourceChoiceError) as err:
        read_footage(path)
    assert "holds 3 parts and no part or view was chosen" in str(err.value)
    assert "part 'cam_left' (view 'left'): B, G, R; part 'cam_right' (view 'right'): B, G, R; part 'depth': Z" in str(err.value)
    with pytest.raises(SourceChoiceError, match="holds no part 'depth' with R,G,B"):
        read_footage(path, part="depth")
    with pytest.raises(SourceChoiceError, match="holds no part 'cam_left' and view 'right'"):
        read_footage(path, part="cam_left", view="right")


def test_single_picture_needs_no_choice_and_refuses_one_it_does_not_hold(tmp_path):
    path = tmp_path / "plain.exr"
    write_exr(path, np.ones((3, 4, 3), np.float32), ("R", "G", "B"))
    footage = read_footage(path)
    assert (footage.source.part_name, footage.source.view, footage.source.kind) == (None, None, "rgb")
    with pytest.raises(SourceChoiceError, match=r"holds no part 'beauty'.*it holds part 0: B, G, R"):
        read_footage(path, part="beauty")
    with pytest.raises(SourceChoiceError, match="holds no view 'left'"):
        read_footage(path, view="left")


@needs_data
def test_beachball_parts_and_views_by_name():
    multipart = EXR / "Beachball" / "multipart.0001.exr"
    left = read_footage(multipart, part="rgba_left")
    np.testing.assert_array_equal(left.pixels, read_image(multipart, part=4)[0])
    assert left.header.data_window == (688, 245, 1564, 1120) and left.header.display_window == (0, 0, 2047, 1555)
    assert read_footage(multipart, view="right").source.part_name == "rgba_right"  # the only colour part of it
    single = EXR / "Beachball" / "singlepart.0001.exr"
    native, names = read_exr_native(single)
    footage = read_footage(single, view="left")
    expected = native[..., [names.index(c) for c in ("left.R", "left.G", "left.B", "left.A")]]
    np.testing.assert_array_equal(footage.pixels, expected.astype(np.float32))
    assert read_footage(single, view="right").source.channels == ("R", "G", "B", "A")


def test_window_overlap():
    # t13: the display window shares only the data window's lower-right pixel
    assert window_overlap((0, 0, 399, 299), (399, 299, 499, 399)) == (
        (slice(299, 300), slice(399, 400)), (slice(0, 1), slice(0, 1)))
    # t08: data window inside the display window at (30, 40)
    assert window_overlap((30, 40, 429, 339), (0, 0, 500, 400)) == (
        (slice(0, 300), slice(0, 400)), (slice(40, 340), slice(30, 430)))
    assert window_overlap((0, 0, 399, 299), (400, 0, 599, 299)) is None  # t09: side by side


def test_encode_exr_declares_the_working_chromaticities(tmp_path):
    from volcap_core.chromaticities import REC709_D65, Chromaticities

    write_exr(tmp_path / "a.exr", np.zeros((2, 2, 3), np.float32), ("R", "G", "B"))
    np.testing.assert_allclose(read_exr_header(tmp_path / "a.exr")["chromaticities"], REC709_D65, atol=1e-7)
    p3 = Chromaticities(0.680, 0.320, 0.265, 0.690, 0.150, 0.060, 0.3127, 0.3290)
    write_exr(tmp_path / "b.exr", np.zeros((2, 2, 3), np.float32), ("R", "G", "B"), chromaticities=p3)
    np.testing.assert_allclose(probe_image(tmp_path / "b.exr").part_headers[0].chromaticities, p3, atol=1e-7)
    with pytest.raises(ValueError, match="reserved"):
        encode_exr(np.zeros((2, 2, 3)), ("R", "G", "B"), attributes={"chromaticities": "x"})


def test_synthetic_capture_frames_declare_the_working_chromaticities(tmp_path):
    from volcap_core.chromaticities import REC709_D65
    from volcap_core.synth.io import write_exr as synth_write_exr

    synth_write_exr(tmp_path / "f.exr", np.zeros((2, 3, 3), np.float32))
    np.testing.assert_allclose(read_exr_header(tmp_path / "f.exr")["chromaticities"], REC709_D65, atol=1e-7)


# --------------------------------------------------------------------------------------------------
# Plain frames: restamped without re-encoding, decoded from memory


def _noisy_rgba(h: int = 40, w: int = 56, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random((h, w, 4)) * 4.0).astype(np.float32)


@pytest.mark.parametrize("compression", ["zip", "piz", "none", "rle", "zips", "pxr24", "b44", "dwaa"])
def test_a_restamped_frame_keeps_the_source_bits_and_carries_the_new_header(tmp_path, compression):
    src = encode_exr(_noisy_rgba(), "RGBA", compression=compression,
                     attributes={"owner": "a camera vendor", "volcap.camera": "old"})
    assert plain_frame_header(src) is not None
    out = restamp_exr(src, attributes={"volcap.camera": "C07", "volcap.take_index": "12",
                                        "volcap.a_very_long_attribute_name_beyond_31": 2.5, "n": 3})
    # the stored pixels are the source's, bit for bit, through both decoders
    want = decode_half_exr(src)
    got = decode_half_exr(out)
    assert np.array_equal(got.view(np.uint16), want.view(np.uint16))
    path = tmp_path / "stamped.exr"
    path.write_bytes(out)
    oiio_pixels, channels = read_image(path)
    assert channels == ("R", "G", "B", "A") and np.array_equal(oiio_pixels, want.astype(np.float32))
    header = read_exr_header(path)
    assert header["volcap.camera"] == "C07" and header["volcap.take_index"] == "12"
    assert header["volcap.a_very_long_attribute_name_beyond_31"] == 2.5 and header["n"] == 3
    assert "owner" not in header  # what encode_exr would not have written is dropped
    assert header["compression"] == _compression_enum(compression)  # the source's, kept
    from volcap_core.chromaticities import WORKING_CHROMATICITIES, same_chromaticities

    assert same_chromaticities(probe_image(path).part_headers[0].chromaticities, WORKING_CHROMATICITIES)


def test_a_decreasing_y_frame_restamps_and_decodes(tmp_path):
    import io

    import OpenEXR

    pixels = _noisy_rgba(33, 20).astype(np.float16)
    buf = io.BytesIO()
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "lineOrder": OpenEXR.DECREASING_Y}, {"RGBA": pixels}).write(buf)
    out = restamp_exr(buf.getvalue(), attributes={"volcap.camera": "C1"})
    assert np.array_equal(decode_half_exr(out).view(np.uint16), pixels.view(np.uint16))


@pytest.mark.parametrize("what", ["float pixels", "offset data window", "extra channel", "two parts", "rgb only"])
def test_only_plain_frames_are_restamped(what):
    import io

    import OpenEXR

    px = _noisy_rgba(8, 8)
    if what == "float pixels":
        data = encode_exr(px, "RGBA", pixel_type="float")
    elif what == "offset data window":
        buf = io.BytesIO()
        OpenEXR.File({"type": OpenEXR.scanlineimage, "dataWindow": ((2, 2), (9, 9)),
                      "displayWindow": ((0, 0), (11, 11))}, {"RGBA": px.astype(np.float16)}).write(buf)
        data = buf.getvalue()
    elif what == "extra channel":
        data = encode_exr(np.concatenate([px, px[..., :1]], -1), ("R", "G", "B", "A", "Z"))
    elif what == "two parts":
        buf = io.BytesIO()
        parts = [OpenEXR.Part({"type": OpenEXR.scanlineimage}, {"RGBA": px.astype(np.float16)}, name=n)
                 for n in ("a", "b")]
        OpenEXR.File(parts).write(buf)
        data = buf.getvalue()
    else:
        data = encode_exr(px[..., :3], "RGB")
        assert plain_frame_header(data) is not None  # RGB without alpha is plain too
        return
    assert plain_frame_header(data) is None
    with pytest.raises(ValueError, match="not a plain frame"):
        restamp_exr(data)


def test_a_plain_frame_with_a_corrupt_payload_is_refused_and_prints_nothing(capsys):
    data = bytearray(encode_exr(_noisy_rgba(), "RGBA", compression="zip"))
    for i in range(len(data) - 40, len(data) - 20):
        data[i] ^= 0xFF
    with pytest.raises(ImageReadError, match=r"frame\.exr: damaged EXR: pixel data does not decode"):
        decode_half_exr(bytes(data), "frame.exr")
    assert capsys.readouterr().out == ""  # the bindings' printed warning went into the message
    with pytest.raises(ImageReadError, match="does not decode"):
        decode_exr(bytes(data), "frame.exr")


def test_decode_exr_gives_the_same_values_for_plain_and_converted_paths(tmp_path):
    px = _noisy_rgba()
    plain = encode_exr(px, "RGBA")
    pixels, channels = decode_exr(plain)
    path = tmp_path / "f.exr"
    path.write_bytes(plain)
    assert channels == ("R", "G", "B", "A") and pixels.dtype == np.float32
    assert np.array_equal(pixels, read_image(path)[0])


def test_half_nonfinite_pixels_counts_pixels_not_samples():
    px = np.zeros((3, 4, 4), np.float16)
    assert half_nonfinite_pixels(px) == 0
    px[0, 0, :2] = np.inf  # one pixel, two samples
    px[2, 3, 3] = np.nan
    px[1, 1, 0] = -np.inf
    px[1, 2, 0] = 65504.0  # the largest finite half is finite
    assert half_nonfinite_pixels(px) == 3
