"""The EXR structure check: every EXR is validated in pure Python before a decoder sees a byte.

:func:`validate_exr_file` / :func:`validate_exr_buffer` check magic and version flags, every header
attribute's bounds, the channel list, the data window (area limit), and the whole chunk offset
table (every entry inside the file, every chunk's leader naming the chunk the table says it is and
its payload ending inside the file). That refuses truncated, incomplete and fuzzed files with a
precise reason, and bounds what a decoder may allocate, instead of trusting a native decoder to
survive them. What is left for the decoder is damaged *compressed payload*, which OpenEXR 3.x
reports as an error.

The same parse yields each part's header facts (:class:`ExrPart`: storage, channels, windows,
name, views, chromaticities), which :mod:`volcap_core.imageio.parts` turns into the public
:class:`~volcap_core.imageio.parts.PartHeader`, so no reader reads a header twice.

Limits (a file beyond them is refused before decoding; the OpenImageIO reader applies them to the
other formats too): :data:`MAX_PIXELS` data-window pixels and :data:`MAX_DECODED_BYTES` native
decoded bytes per image/part.
"""

from __future__ import annotations

import mmap
import os
import struct
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from volcap_core.imageio.errors import ImageReadError

__all__ = [
    "MAX_PIXELS",
    "MAX_DECODED_BYTES",
    "EXR_MAGIC",
    "FLAG_LONG_NAMES",
    "COMPRESSION_NAMES",
    "ExrChannel",
    "ExrPart",
    "read_header",
    "validate_exr_buffer",
    "validate_exr_file",
    "decodable_part",
]

#: Largest data window accepted, in pixels (2**28 = 16384 x 16384). Fuzzed headers claim windows of
#: 10**9+ pixels to make decoders allocate terabytes; a capture frame is far below this.
MAX_PIXELS = 2**28
#: Largest native decoded size accepted for one image/part, in bytes (all channels).
MAX_DECODED_BYTES = 2**33

EXR_MAGIC = b"\x76\x2f\x31\x01"

# Version-field flags (OpenEXR file layout, "version field").
_FLAG_TILED = 0x200
FLAG_LONG_NAMES = 0x400
_FLAG_NONIMAGE = 0x800  # deep data
_FLAG_MULTIPART = 0x1000
_KNOWN_FLAGS = _FLAG_TILED | FLAG_LONG_NAMES | _FLAG_NONIMAGE | _FLAG_MULTIPART

#: Scan lines per chunk for each compression id, as OpenEXRCore 3.5's
#: ``exr_compression_lines_per_chunk`` returns them (ids 0..13: none, rle, zips, zip, piz, pxr24,
#: b44, b44a, dwaa, dwab, htj2k256, htj2k32, lj2k, zstd).
_LINES_PER_CHUNK = (1, 1, 1, 16, 32, 16, 32, 32, 32, 256, 256, 32, 256, 1)
COMPRESSION_NAMES = (
    "none", "rle", "zips", "zip", "piz", "pxr24", "b44", "b44a", "dwaa", "dwab",
    "htj2k256", "htj2k32", "lj2k", "zstd",
)
_PIXEL_TYPE_BYTES = (4, 2, 4)
_STORAGE_TYPES = ("scanlineimage", "tiledimage", "deepscanline", "deeptile")

_MAX_NAME = 255  # attribute / channel name bytes (the long-names limit; also applied to short names)
_MAX_ATTRIBUTES = 4096  # per header: real files have tens; bounds parse time on crafted input
_MAX_PARTS = 10_000
_MAX_COORD = 2**30  # |window coordinate|: keeps widths inside int32 as the C libraries need


@dataclass(frozen=True)
class ExrChannel:
    name: str
    pixel_type: int  # 0 uint, 1 half, 2 float
    x_sampling: int
    y_sampling: int


@dataclass(frozen=True)
class ExrPart:
    storage: str  # one of _STORAGE_TYPES
    channels: tuple[ExrChannel, ...]
    compression: int
    data_window: tuple[int, int, int, int]
    display_window: tuple[int, int, int, int]
    tiles: tuple[int, int, int, int] | None  # (x size, y size, level mode, rounding mode)
    chunk_count: int
    # what ingest must not drop: which footage the part is, its colour space, its pixel shape
    name: str | None = None  # "name" (required in multi-part files)
    view: str | None = None  # "view": the one view all of a part's channels belong to
    multi_view: tuple[str, ...] = ()  # "multiView": the views of a single-part stereo file, default first
    chromaticities: tuple[float, ...] | None = None  # 8 floats: red, green, blue, white (x, y)
    adopted_neutral: tuple[float, float] | None = None
    pixel_aspect_ratio: float = 1.0

    @property
    def deep(self) -> bool:
        return self.storage.startswith("deep")

    @property
    def width(self) -> int:
        return self.data_window[2] - self.data_window[0] + 1

    @property
    def height(self) -> int:
        return self.data_window[3] - self.data_window[1] + 1


class _Damaged(Exception):
    """Internal: a structural defect; turned into ImageReadError('damaged EXR: ...')."""


def _cstring(buf: Any, pos: int, end: int, what: str) -> tuple[bytes, int]:
    """Null-terminated string at ``pos`` (at most _MAX_NAME bytes); returns (bytes, next pos)."""
    stop = min(end, pos + _MAX_NAME + 1)
    nul = buf.find(b"\x00", pos, stop)
    if nul < 0:
        if stop >= end:
            raise _Damaged(f"header truncated inside {what}")
        raise _Damaged(f"{what} longer than {_MAX_NAME} bytes")
    return bytes(buf[pos:nul]), nul + 1


def _box2i(value: bytes, name: str) -> tuple[int, int, int, int]:
    if len(value) != 16:
        raise _Damaged(f"attribute {name!r} has size {len(value)}, a box2i needs 16")
    box = struct.unpack("<4i", value)
    xmin, ymin, xmax, ymax = box
    if xmax < xmin or ymax < ymin:
        raise _Damaged(f"{name} {box} is empty or inverted")
    if any(abs(c) > _MAX_COORD for c in box):
        raise _Damaged(f"{name} {box} has coordinates beyond +-2**30")
    return box


def _chlist(value: bytes) -> tuple[ExrChannel, ...]:
    channels: list[ExrChannel] = []
    pos, end = 0, len(value)
    while True:
        if pos >= end:
            raise _Damaged("channel list not terminated")
        if value[pos] == 0:
            if pos + 1 != end:
                raise _Damaged("bytes after the end of the channel list")
            break
        raw, pos = _cstring(value, pos, end, "a channel name")
        if pos + 16 > end:
            raise _Damaged("channel list truncated")
        ptype, _plinear, xs, ys = struct.unpack_from("<iB3xii", value, pos)
        pos += 16
        name = raw.decode("utf-8", errors="replace")
        if ptype not in (0, 1, 2):
            raise _Damaged(f"channel {name!r} has unknown pixel type {ptype}")
        if not (1 <= xs <= 2**16 and 1 <= ys <= 2**16):
            raise _Damaged(f"channel {name!r} has sampling ({xs}, {ys})")
        channels.append(ExrChannel(name, ptype, xs, ys))
    if not channels:
        raise _Damaged("no channels")
    names = [c.name for c in channels]
    if len(set(names)) != len(names):
        raise _Damaged("duplicate channel names")
    return tuple(channels)


def read_header(buf: Any, pos: int, size: int) -> tuple[dict[str, tuple[str, bytes]], int]:
    """One header's attributes ``name -> (type, value bytes)``; returns them and the next pos."""
    attrs: dict[str, tuple[str, bytes]] = {}
    while True:
        if pos >= size:
            raise _Damaged("header truncated (no end-of-header byte)")
        if buf[pos] == 0:
            return attrs, pos + 1
        if len(attrs) >= _MAX_ATTRIBUTES:
            raise _Damaged(f"more than {_MAX_ATTRIBUTES} header attributes")
        raw_name, pos = _cstring(buf, pos, size, "an attribute name")
        raw_type, pos = _cstring(buf, pos, size, "an attribute type")
        shown = raw_name.decode("utf-8", errors="replace")[:40]
        if not raw_type:
            raise _Damaged(f"attribute {shown!r} has an empty type name")
        if pos + 4 > size:
            raise _Damaged("header truncated inside an attribute size")
        (length,) = struct.unpack_from("<i", buf, pos)
        pos += 4
        if length < 0 or pos + length > size:
            raise _Damaged(f"attribute {shown!r} claims {length} bytes, beyond the end of the file")
        name = raw_name.decode("utf-8", errors="replace")
        if name in attrs:
            raise _Damaged(f"attribute {name!r} appears twice")
        attrs[name] = (raw_type.decode("latin-1"), bytes(buf[pos : pos + length]))
        pos += length


def _typed(attrs: Mapping[str, tuple[str, bytes]], name: str, type_name: str) -> bytes | None:
    if name not in attrs:
        return None
    t, value = attrs[name]
    if t != type_name:
        raise _Damaged(f"attribute {name!r} has type {t!r}, expected {type_name!r}")
    return value


def _text(attrs: Mapping[str, tuple[str, bytes]], name: str) -> str | None:
    value = _typed(attrs, name, "string")
    return None if value is None else value.decode("utf-8", errors="replace")


def _string_vector(attrs: Mapping[str, tuple[str, bytes]], name: str) -> tuple[str, ...]:
    """A ``stringvector`` attribute: (int32 length, bytes) repeated."""
    value = _typed(attrs, name, "stringvector")
    if value is None:
        return ()
    out, pos = [], 0
    while pos < len(value):
        if pos + 4 > len(value):
            raise _Damaged(f"attribute {name!r} truncated")
        (n,) = struct.unpack_from("<i", value, pos)
        pos += 4
        if n < 0 or pos + n > len(value):
            raise _Damaged(f"attribute {name!r} holds a string of {n} bytes beyond its end")
        out.append(value[pos : pos + n].decode("utf-8", errors="replace"))
        pos += n
    return tuple(out)


def _floats(attrs: Mapping[str, tuple[str, bytes]], name: str, type_name: str, count: int) -> tuple[float, ...] | None:
    value = _typed(attrs, name, type_name)
    if value is None:
        return None
    if len(value) != 4 * count:
        raise _Damaged(f"attribute {name!r} has size {len(value)}, a {type_name} needs {4 * count}")
    return tuple(float(v) for v in struct.unpack(f"<{count}f", value))


def _levels(n: int, level_mode: int, rounding: int) -> int:
    """Number of levels along an axis of size n (OpenEXR ImfTiledMisc)."""
    if level_mode == 0:
        return 1
    # floor/ceil log2 of n, exactly (no float rounding)
    log = n.bit_length() - 1
    if rounding == 1 and (1 << log) < n:
        log += 1
    return log + 1


def _level_size(n: int, level: int, rounding: int) -> int:
    if rounding == 1:
        n += (1 << level) - 1
    return max(n >> level, 1)


def _tile_grid(part_w: int, part_h: int, tiles: tuple[int, int, int, int]) -> list[tuple[int, int, int, int]]:
    """(lx, ly, tiles across, tiles down) per level, in offset-table order."""
    tw, th, mode, rounding = tiles
    if mode == 0:
        pairs = [(0, 0)]
    elif mode == 1:  # mipmap: one level count over max(w, h)
        n = _levels(max(part_w, part_h), mode, rounding)
        pairs = [(lv, lv) for lv in range(n)]
    else:  # ripmap: y levels outermost
        nx, ny = _levels(part_w, mode, rounding), _levels(part_h, mode, rounding)
        pairs = [(lx, ly) for ly in range(ny) for lx in range(nx)]
    grid = []
    for lx, ly in pairs:
        w, h = _level_size(part_w, lx, rounding), _level_size(part_h, ly, rounding)
        grid.append((lx, ly, -(-w // tw), -(-h // th)))
    return grid


def _part_from_header(
    attrs: Mapping[str, tuple[str, bytes]], tiled_flag: bool, deep_flag: bool, multipart: bool
) -> ExrPart:
    # storage type: the "type" attribute (required for multi-part and deep files), else the flags
    type_value = _typed(attrs, "type", "string")
    if type_value is not None:
        storage = type_value.decode("latin-1")
        if storage not in _STORAGE_TYPES:
            raise _Damaged(f"unknown part type {storage!r}")
        if not multipart and ((storage == "tiledimage") != tiled_flag and not deep_flag):
            raise _Damaged(f"part type {storage!r} contradicts the version flags")
    elif multipart or deep_flag:
        raise _Damaged("part has no 'type' attribute")
    else:
        storage = "tiledimage" if tiled_flag else "scanlineimage"

    missing = [n for n in ("channels", "compression", "dataWindow", "displayWindow") if n not in attrs]
    if missing:
        raise _Damaged(f"required attribute(s) missing: {', '.join(missing)}")
    channels = _chlist(_typed(attrs, "channels", "chlist") or b"")
    comp = _typed(attrs, "compression", "compression") or b""
    if len(comp) != 1 or comp[0] >= len(COMPRESSION_NAMES):
        raise _Damaged(f"unknown compression {comp!r}")
    compression = comp[0]
    dw = _box2i(_typed(attrs, "dataWindow", "box2i") or b"", "dataWindow")
    dsp = _box2i(_typed(attrs, "displayWindow", "box2i") or b"", "displayWindow")
    line_order = _typed(attrs, "lineOrder", "lineOrder")
    if line_order is not None and (len(line_order) != 1 or line_order[0] > 2):
        raise _Damaged(f"unknown line order {line_order!r}")

    width, height = dw[2] - dw[0] + 1, dw[3] - dw[1] + 1
    if width * height > MAX_PIXELS:
        raise _Damaged(f"data window {width}x{height} = {width * height} px refused (limit {MAX_PIXELS} px)")
    decoded = width * height * sum(_PIXEL_TYPE_BYTES[c.pixel_type] for c in channels)
    if decoded > MAX_DECODED_BYTES and not storage.startswith("deep"):
        raise _Damaged(f"{decoded} decoded bytes refused (limit {MAX_DECODED_BYTES})")
    for c in channels:
        # OpenEXR requires the data window to align with each channel's sampling grid
        if dw[0] % c.x_sampling or dw[1] % c.y_sampling or width % c.x_sampling or height % c.y_sampling:
            raise _Damaged(
                f"channel {c.name!r} sampling ({c.x_sampling}, {c.y_sampling}) does not divide the data window"
            )

    tiles = None
    if storage in ("tiledimage", "deeptile"):
        td = _typed(attrs, "tiles", "tiledesc")
        if td is None or len(td) != 9:
            raise _Damaged("tiled part without a valid 'tiles' attribute")
        tw, th, mode = struct.unpack("<IIB", td)
        level_mode, rounding = mode & 0x0F, mode >> 4
        if not (1 <= tw <= 2**16 and 1 <= th <= 2**16) or level_mode > 2 or rounding > 1:
            raise _Damaged(f"invalid tile description {tw}x{th} mode {mode:#x}")
        tiles = (tw, th, level_mode, rounding)
        chunk_count = sum(nx * ny for _, _, nx, ny in _tile_grid(width, height, tiles))
    else:
        chunk_count = -(-height // _LINES_PER_CHUNK[compression])

    declared = _typed(attrs, "chunkCount", "int")
    if declared is not None:
        if len(declared) != 4:
            raise _Damaged("chunkCount attribute has the wrong size")
        (n,) = struct.unpack("<i", declared)
        if n != chunk_count:
            raise _Damaged(f"chunkCount {n} disagrees with the {chunk_count} chunks the header implies")
    elif multipart:
        raise _Damaged("multi-part file without 'chunkCount'")
    neutral = _floats(attrs, "adoptedNeutral", "v2f", 2)
    aspect = _floats(attrs, "pixelAspectRatio", "float", 1)
    return ExrPart(storage, channels, compression, dw, dsp, tiles, chunk_count,
                    name=_text(attrs, "name"), view=_text(attrs, "view"),
                    multi_view=_string_vector(attrs, "multiView"),
                    chromaticities=_floats(attrs, "chromaticities", "chromaticities", 8),
                    adopted_neutral=None if neutral is None else (neutral[0], neutral[1]),
                    pixel_aspect_ratio=1.0 if aspect is None else aspect[0])


def _check_chunks(
    buf: Any, size: int, part: ExrPart, index: int, offsets: np.ndarray, table_end: int, multipart: bool
) -> None:
    """Every chunk the offset table names lies inside the file and its leader is the expected one.

    An entry of 0 marks a chunk never written (writers fill the table last). It is refused for
    level 0, the only level ever decoded here, and tolerated for the other mip/rip levels, which
    some writers (the OpenEXR Python bindings) leave out.
    """
    n = offsets.size
    lead = 4 if multipart else 0  # multi-part chunks start with their part number
    if part.deep:
        fields = 0  # deep leaders differ; their parts are refused anyway, only bound-check them
    elif part.tiles is not None:
        fields = 4  # tile x, tile y, level x, level y
    else:
        fields = 1  # first scan line y
    leader = lead + 4 * fields + (4 if fields else 0)  # + int32 packed size

    if part.tiles is not None:
        grid = _tile_grid(part.width, part.height, part.tiles)
        expected = np.concatenate([
            np.stack(np.broadcast_arrays(np.tile(np.arange(nx), ny), np.repeat(np.arange(ny), nx), lx, ly), axis=1)
            for lx, ly, nx, ny in grid
        ]).astype(np.int64)  # [n, 4] (tx, ty, lx, ly) in table order
        optional = (expected[:, 2] > 0) | (expected[:, 3] > 0)
    else:
        lpc = _LINES_PER_CHUNK[part.compression]
        expected = part.data_window[1] + lpc * np.arange(n, dtype=np.int64)  # first line of each chunk
        optional = np.zeros(n, dtype=bool)
    present = ~(optional & (offsets == 0))
    bad = np.flatnonzero(present & ((offsets < table_end) | (offsets > size - max(leader, 1))))
    if bad.size:
        i = int(bad[0])
        what = "is 0 (file incomplete)" if offsets[i] == 0 else f"points outside the file ({int(offsets[i])})"
        raise _Damaged(f"part {index}: chunk offset table entry {i} of {n} {what}")
    if not fields:
        return

    rows = np.flatnonzero(present)
    starts = offsets[rows].astype(np.int64)
    byte_view = np.frombuffer(buf, dtype=np.uint8, count=size)
    words = byte_view[starts[:, None] + np.arange(leader, dtype=np.int64)].view("<i4")  # [m, leader/4]
    del byte_view  # no view may outlive the caller's mmap
    expected = expected[rows]

    def first(mask: np.ndarray) -> int | None:
        hit = np.flatnonzero(mask)
        return None if hit.size == 0 else int(hit[0])

    col = 0
    if multipart:
        if (k := first(words[:, 0] != index)) is not None:
            raise _Damaged(f"part {index}: chunk {int(rows[k])} is labelled part {int(words[k, 0])}")
        col = 1
    if part.tiles is None:
        if (k := first(words[:, col] != expected)) is not None:
            got, want = int(words[k, col]), int(expected[k])
            raise _Damaged(f"part {index}: chunk {int(rows[k])} starts at line {got}, expected {want}")
    elif (k := first(np.any(words[:, col : col + 4] != expected, axis=1))) is not None:
        got, want = tuple(int(v) for v in words[k, col : col + 4]), tuple(int(v) for v in expected[k])
        raise _Damaged(f"part {index}: chunk {int(rows[k])} is tile {got}, expected {want}")
    packed = words[:, -1].astype(np.int64)
    if (k := first((packed < 0) | (starts + leader + packed > size))) is not None:
        raise _Damaged(
            f"part {index}: chunk {int(rows[k])} claims {int(packed[k])} bytes, beyond the end of the file (truncated)"
        )
    if part.compression == 0:
        # Uncompressed chunks hold exactly their pixels: a smaller size is a file trying to make the
        # decoder allocate for pixels that are not there (memory_DOS_2.2).
        unpacked = _unpacked_sizes(part, expected)
        if (k := first(packed != unpacked)) is not None:
            raise _Damaged(
                f"part {index}: uncompressed chunk {int(rows[k])} holds {int(packed[k])} bytes,"
                f" its pixels need {int(unpacked[k])}"
            )


def _unpacked_sizes(part: ExrPart, coords: np.ndarray) -> np.ndarray:
    """Decoded bytes of each chunk: ``coords`` are first lines [n] (scanline) or tile coordinates
    (tx, ty, lx, ly) [n, 4] (tiled)."""
    xmin, ymin, xmax, ymax = part.data_window
    if part.tiles is None:
        lpc = _LINES_PER_CHUNK[part.compression]
        total = np.zeros(coords.shape[0], dtype=np.int64)
        for line in range(lpc):
            y = coords.astype(np.int64) + line
            inside = y <= ymax
            for c in part.channels:
                row_bytes = (part.width // c.x_sampling) * _PIXEL_TYPE_BYTES[c.pixel_type]
                total += np.where(inside & (y % c.y_sampling == 0), row_bytes, 0)
        return total
    tw, th, _, rounding = part.tiles
    pixel_bytes = sum(_PIXEL_TYPE_BYTES[c.pixel_type] for c in part.channels)
    tx, ty, lx, ly = (coords[:, k].astype(np.int64) for k in range(4))
    lw = np.maximum(((part.width + (1 << lx) - 1) if rounding else part.width) >> lx, 1)
    lh = np.maximum(((part.height + (1 << ly) - 1) if rounding else part.height) >> ly, 1)
    w = np.minimum(tw, lw - tx * tw)
    h = np.minimum(th, lh - ty * th)
    return w * h * pixel_bytes


def _parse_exr(buf: Any, size: int) -> list[ExrPart]:
    """Validate an EXR's structure (``buf`` supports the buffer protocol and ``.find``)."""
    if size < 8:
        raise _Damaged("truncated (shorter than the 8-byte preamble)")
    magic, version = struct.unpack_from("<4sI", buf, 0)
    if magic != EXR_MAGIC:
        raise _Damaged("bad magic number")
    if version & 0xFF != 2:
        raise _Damaged(f"unsupported format version {version & 0xFF}")
    flags = version & ~0xFF
    if flags & ~_KNOWN_FLAGS:
        raise _Damaged(f"unknown version flags {flags:#x}")
    multipart = bool(flags & _FLAG_MULTIPART)
    tiled_flag, deep_flag = bool(flags & _FLAG_TILED), bool(flags & _FLAG_NONIMAGE)
    if multipart and tiled_flag:
        raise _Damaged("version flags claim both multi-part and single-part tiled")

    pos = 8
    parts: list[ExrPart] = []
    while True:
        attrs, pos = read_header(buf, pos, size)
        if not attrs:
            if not multipart or not parts:
                raise _Damaged("empty header")
            break  # the empty header ends a multi-part header list
        parts.append(_part_from_header(attrs, tiled_flag, deep_flag, multipart))
        if not multipart:
            break
        if len(parts) > _MAX_PARTS:
            raise _Damaged(f"more than {_MAX_PARTS} parts")

    table_end = pos + 8 * sum(p.chunk_count for p in parts)
    if table_end > size:
        raise _Damaged(f"truncated: chunk offset tables need {table_end} bytes, file has {size}")
    for index, part in enumerate(parts):
        offsets = np.frombuffer(buf, dtype="<u8", count=part.chunk_count, offset=pos).copy()
        pos += 8 * part.chunk_count
        _check_chunks(buf, size, part, index, offsets, table_end, multipart)
    return parts


def validate_exr_buffer(buf: Any, size: int, path: str) -> list[ExrPart]:
    try:
        return _parse_exr(buf, size)
    except _Damaged as exc:
        raise ImageReadError(path, f"damaged EXR: {exc}") from None


def validate_exr_file(path: str) -> list[ExrPart]:
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size == 0:
            raise ImageReadError(path, "damaged EXR: empty file")
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            # numpy views into the map are copied/dropped inside, so closing it here is safe
            return validate_exr_buffer(mm, size, path)


def decodable_part(parts: Sequence[ExrPart], part: int, path: str) -> ExrPart:
    if not 0 <= part < len(parts):
        raise ImageReadError(path, f"part {part} requested, the file has {len(parts)} part(s)")
    p = parts[part]
    if p.deep:
        raise ImageReadError(path, f"deep data not supported (part {part} is {p.storage})")
    return p
