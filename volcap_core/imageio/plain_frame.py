"""Plain frames: the one EXR shape ingest stores, handled without OpenImageIO and without
re-encoding.

A *plain frame* is a single-part scanline EXR whose only channels are R, G, B (and A), all half,
not subsampled, without part name or views, its data window equal to its display window at
(0, 0), with square pixels: what :func:`volcap_core.imageio.write.encode_exr` writes. A camera
frame already in that shape is stored by :func:`restamp_exr` (a new header, the camera's
compressed chunks copied byte for byte) instead of being decoded, converted and re-compressed, and
every plain frame is decoded from memory by :func:`decode_half_exr` (OpenEXR, no temporary file).
What these save per frame is measured in ``docs/benchmarks.md`` (Ingest).
"""

from __future__ import annotations

import io
import struct
from typing import Mapping

import numpy as np

from volcap_core.chromaticities import WORKING_CHROMATICITIES, Chromaticities
from volcap_core.imageio.check import EXR_MAGIC, FLAG_LONG_NAMES, ExrPart, read_header, validate_exr_buffer
from volcap_core.imageio.errors import ImageReadError
from volcap_core.imageio.parts import PartHeader, part_header
from volcap_core.imageio.write import extra_attributes
from volcap_core.native_stderr import binding_prints

__all__ = ["plain_frame_header", "restamp_exr", "decode_half_exr", "half_nonfinite_pixels"]


#: what a restamped frame keeps of its source header: what a reader needs to decode and place it
_DECODING_ATTRIBUTES = ("channels", "compression", "dataWindow", "displayWindow", "lineOrder",
                        "pixelAspectRatio", "screenWindowCenter", "screenWindowWidth")


def _attribute_bytes(name: str, type_name: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + type_name.encode() + b"\0" + struct.pack("<i", len(value)) + value


def _typed_attribute(name: str, value: str | float | int) -> bytes:
    if isinstance(value, str):
        return _attribute_bytes(name, "string", value.encode("utf-8"))
    if isinstance(value, float):
        return _attribute_bytes(name, "double", struct.pack("<d", value))
    return _attribute_bytes(name, "int", struct.pack("<i", value))


def _plain_part(data: bytes, path: str) -> ExrPart | None:
    if not data.startswith(EXR_MAGIC):
        return None  # another format
    parts = validate_exr_buffer(data, len(data), path)
    if len(parts) != 1:
        return None
    part = parts[0]
    names = sorted(c.name for c in part.channels)
    origin_window = (0, 0, part.width - 1, part.height - 1)
    if (part.storage != "scanlineimage" or names not in (["B", "G", "R"], ["A", "B", "G", "R"])
            or any(c.pixel_type != 1 or c.x_sampling != 1 or c.y_sampling != 1 for c in part.channels)
            or part.view is not None or part.multi_view or part.name is not None
            or part.data_window != origin_window or part.display_window != origin_window
            or part.pixel_aspect_ratio != 1.0):
        return None
    return part


def plain_frame_header(data: bytes, path: str = "<bytes>") -> PartHeader | None:
    """The header of ``data`` (an EXR file's bytes) when it is a *plain frame*, else None.

    Plain: a single-part scanline EXR whose only channels are R, G, B (and A), all half, not
    subsampled, without part name or views, its data window equal to its display window at (0, 0),
    with square pixels: what :func:`~volcap_core.imageio.write.encode_exr` writes, so
    :func:`restamp_exr` can store it without re-encoding. None for other formats. The structure is
    validated (:class:`ImageReadError` for a damaged EXR).
    """
    part = _plain_part(data, path)
    return None if part is None else part_header(0, part)


def restamp_exr(
    data: bytes,
    *,
    attributes: Mapping[str, str | float | int] | None = None,
    chromaticities: Chromaticities = WORKING_CHROMATICITIES,
    path: str = "<bytes>",
) -> bytes:
    """A plain frame (:func:`plain_frame_header`) with a new header and its compressed pixel
    chunks untouched.

    For such a frame this replaces decoding, converting and re-compressing (the compressor is most
    of that cost: ``docs/benchmarks.md``) by a copy: the stored pixels are the source's bits
    exactly, in the source's compression. The new header holds the source's decoding attributes
    (``channels``, ``compression``, the windows, ``lineOrder``, ``pixelAspectRatio``, the screen
    window), ``chromaticities`` and ``attributes`` (typed as
    :func:`~volcap_core.imageio.write.encode_exr` types them); every other source attribute is
    dropped, as ``encode_exr`` would not have written it. The chunk offset table is shifted by the
    change in header length. The compressed payload is not decoded here (:func:`decode_half_exr`
    does). Raises ``ValueError`` for a frame that is not plain.
    """
    part = _plain_part(data, path)
    if part is None:
        raise ValueError(f"{path}: not a plain frame (single-part scanline half RGB(A), windows at the origin)")
    source_attrs, header_end = read_header(data, 8, len(data))
    extra = extra_attributes(attributes)
    header = [_attribute_bytes(n, *source_attrs[n]) for n in _DECODING_ATTRIBUTES if n in source_attrs]
    header.append(_attribute_bytes("chromaticities", "chromaticities",
                                   struct.pack("<8f", *Chromaticities(*chromaticities))))
    header += [_typed_attribute(k, v) for k, v in sorted(extra.items())]
    long_names = any(len(n) > 31 for n in extra) or any(
        len(n) > 31 or len(source_attrs[n][0]) > 31 for n in _DECODING_ATTRIBUTES if n in source_attrs)
    version = 2 | (FLAG_LONG_NAMES if long_names else 0)
    head = struct.pack("<4sI", EXR_MAGIC, version) + b"".join(header) + b"\0"
    table = np.frombuffer(data, dtype="<u8", count=part.chunk_count, offset=header_end)
    shifted = (table.astype(np.int64) + (len(head) - header_end)).astype("<u8")
    chunks = memoryview(data)[header_end + 8 * part.chunk_count:]
    return b"".join((head, shifted.tobytes(), chunks))


def decode_half_exr(data: bytes, path: str = "<bytes>") -> np.ndarray:
    """The pixels of a plain frame (:func:`restamp_exr`) as stored: float16 ``[H, W, C]``, C = 3
    (R, G, B) or 4 (R, G, B, A), decoded from memory by OpenEXR (faster than OpenImageIO on these
    files: ``docs/benchmarks.md``). Structure is not re-checked: call it on what :func:`restamp_exr`
    returned. A damaged compressed payload raises :class:`ImageReadError`."""
    import OpenEXR

    try:
        with binding_prints() as said:  # a failed decode is printed, and returns a file of 0 parts
            f = OpenEXR.File(io.BytesIO(data))  # R,G,B(,A) come as one interleaved [H, W, C] array
    except Exception as exc:  # noqa: BLE001 - the bindings raise assorted types on bad data
        raise ImageReadError(path, f"damaged EXR: decoder error: {' '.join(str(exc).split())[:500]}") from None
    if len(f.parts) != 1:
        reason = " ".join(said.getvalue().split())[:500] or f"the decoder found {len(f.parts)} parts"
        raise ImageReadError(path, f"damaged EXR: pixel data does not decode ({reason})")
    channels = f.channels()
    plane = channels.get("RGBA", channels.get("RGB"))
    pixels = None if plane is None else plane.pixels
    if pixels is None or pixels.dtype != np.float16 or pixels.ndim != 3:
        raise ImageReadError(path, f"damaged EXR: the decoder found channels {', '.join(channels) or 'none'}")
    return pixels


def half_nonfinite_pixels(pixels: np.ndarray) -> int:
    """Pixels of a float16 ``[H, W, C]`` holding NaN or +-Inf in any channel (exponent bits all
    set; checked on the bits, much cheaper than ``np.isfinite`` on half: ``docs/benchmarks.md``)."""
    exponent = np.ascontiguousarray(pixels).view(np.uint16) & 0x7C00
    if exponent.max(initial=0) != 0x7C00:
        return 0
    return int((exponent == 0x7C00).any(axis=-1).sum())
