"""Reading image files (EXR, PNG, TIFF, DPX) through OpenImageIO: header facts without pixels,
and the decoded picture a part/view choice names.

Every EXR passes :mod:`volcap_core.imageio.check` before OpenImageIO opens it, and its part
headers come from that check's parse; the picture read is chosen by
:func:`volcap_core.imageio.parts.choose_colour_source`. The format is told by content, never by
extension (ingest meets misnamed files). :func:`read_footage` / :func:`probe_footage` are what
ingest uses; :func:`read_image` reads a part by index, :func:`read_exr_native` every channel as
stored, :func:`decode_exr` EXR bytes held in memory (a plain frame without OpenImageIO:
:mod:`volcap_core.imageio.plain_frame`), :func:`read_exr_header` the attributes
:func:`volcap_core.imageio.write.write_exr` wrote.
"""

from __future__ import annotations

import os
import tempfile
import threading
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from volcap_core.imageio.check import (
    EXR_MAGIC,
    MAX_DECODED_BYTES,
    MAX_PIXELS,
    decodable_part,
    validate_exr_buffer,
    validate_exr_file,
)
from volcap_core.imageio.errors import ImageReadError
from volcap_core.imageio.parts import ColourSource, PartHeader, choose_colour_source, part_header
from volcap_core.imageio.plain_frame import decode_half_exr, plain_frame_header

__all__ = [
    "ImageInfo",
    "Footage",
    "probe_image",
    "probe_footage",
    "read_image",
    "read_footage",
    "read_exr_native",
    "read_exr_header",
    "decode_exr",
    "decode_exr_native",
]


@dataclass(frozen=True)
class ImageInfo:
    """What a file's header says; no pixels are decoded.

    ``width``/``height`` are the *data window* size (what :func:`read_image` returns).
    ``channels`` are named as the readers return them: R,G,B,A first when present, then the rest in
    file order (a luminance/chroma EXR shows as R,G,B). ``pixel_types`` holds one of
    ``"half" "float" "uint" "uint8" "uint16"`` per channel. ``parts`` counts EXR parts (1 otherwise).
    ``data_window``/``display_window`` are inclusive ``(xmin, ymin, xmax, ymax)`` (EXR convention;
    for other formats both are ``(0, 0, width-1, height-1)``). ``bits_per_sample`` is the integer code
    depth (e.g. 10 for a 10-bit DPX stored in uint16), 0 for float data. ``part_headers`` describes
    every part of the file (one for non-EXR formats): names, views, channels, windows, colour.
    """

    path: str
    width: int
    height: int
    channels: tuple[str, ...]
    pixel_types: tuple[str, ...]
    format: str
    parts: int
    data_window: tuple[int, int, int, int] = (0, 0, -1, -1)
    display_window: tuple[int, int, int, int] = (0, 0, -1, -1)
    bits_per_sample: int = 0
    part_headers: tuple["PartHeader", ...] = ()


@dataclass(frozen=True)
class Footage:
    """One picture of a file, decoded (:func:`read_footage`).

    ``pixels`` float32 ``[H, W, C]`` over the part's *data window* (``header.data_window``), C = 3 or
    4, channels ``("R","G","B")`` or ``("R","G","B","A")``: EXR values as stored, in the primaries
    of ``header.chromaticities`` (luminance-only: R = G = B = Y); integer formats as code values in
    [0, 1]. ``source`` is the picture read, ``header`` its part's header.
    """

    pixels: np.ndarray
    channels: tuple[str, ...]
    source: ColourSource
    header: PartHeader


# --------------------------------------------------------------------------------------------------
# Format detection by content (never by extension: ingest meets misnamed files).

_SIGNATURES: tuple[tuple[bytes, str], ...] = (
    (EXR_MAGIC, "exr"),
    (b"\x89PNG\r\n\x1a\n", "png"),
    (b"II*\x00", "tiff"),
    (b"MM\x00*", "tiff"),
    (b"II+\x00", "tiff"),  # BigTIFF
    (b"MM\x00+", "tiff"),
    (b"SDPX", "dpx"),
    (b"XPDS", "dpx"),
)
#: our format name -> OpenImageIO's reader name
_OIIO_FORMAT = {"exr": "openexr", "png": "png", "tiff": "tiff", "dpx": "dpx"}


def _sniff(head: bytes) -> str | None:
    for sig, fmt in _SIGNATURES:
        if head.startswith(sig):
            return fmt
    return None


# --------------------------------------------------------------------------------------------------
# OpenImageIO access.

# OIIO's default EXR reader ("openexr:core"=1) refuses luminance/chroma (Y, RY, BY with 2x2
# sampling) files; the classic reader (core=0) reads them as RGB and reproduces OIIO's reference
# hashes for every file. The switch is process-global and consulted when a reader is created, so it
# is set around our open() only, under a lock, and restored.
_OIIO_LOCK = threading.Lock()


def _oiio():
    import OpenImageIO as oiio  # imported lazily: it loads a large native library

    return oiio


def _oiio_error(obj: Any, default: str) -> str:
    try:
        msg = obj.geterror()
    except Exception:  # noqa: BLE001 - OIIO can return undecodable bytes as an error message
        msg = ""
    msg = " ".join(str(msg).split())
    return msg[:500] or default


def _sniff_file(path: str) -> str:
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise ImageReadError(path, f"cannot read file: {exc.strerror or exc}") from None
    fmt = _sniff(head)
    if fmt is None:
        if not head:
            raise ImageReadError(path, "empty file")
        if path.lower().endswith(".exr"):
            raise ImageReadError(path, "damaged EXR: bad magic number")
        raise ImageReadError(path, "unsupported or unrecognised image format (expected EXR, PNG, TIFF or DPX)")
    return fmt


def _open_oiio(path: str, fmt: str, subimage: int = 0):
    """Open ``path`` with OpenImageIO's reader for ``fmt`` and seek to ``subimage``."""
    oiio = _oiio()
    config = oiio.ImageSpec()
    # code values as stored: by default OIIO premultiplies PNG/TIFF colour by unassociated alpha
    config.attribute("oiio:UnassociatedAlpha", 1)
    with _OIIO_LOCK:
        previous = oiio.get_int_attribute("openexr:core", 1)
        if fmt == "exr":
            oiio.attribute("openexr:core", 0)
        try:
            inp = oiio.ImageInput.open(path, config)
        finally:
            if fmt == "exr":
                oiio.attribute("openexr:core", previous)
    if inp is None:
        raise ImageReadError(path, f"damaged {fmt.upper()}: {_oiio_error(oiio, 'cannot open')}")
    if inp.format_name() != _OIIO_FORMAT[fmt]:
        inp.close()
        raise ImageReadError(path, f"content looks like {fmt} but OpenImageIO chose its {inp.format_name()} reader")
    if subimage and not inp.seek_subimage(subimage, 0):
        inp.close()
        raise ImageReadError(path, f"part {subimage} not found: {_oiio_error(inp, 'seek failed')}")
    spec = inp.spec()
    if spec.deep:
        inp.close()
        raise ImageReadError(path, "deep data not supported")
    nbytes = spec.width * spec.height * max(spec.depth, 1) * spec.pixel_bytes(True)
    if spec.width * spec.height * max(spec.depth, 1) > MAX_PIXELS or nbytes > MAX_DECODED_BYTES:
        inp.close()
        limits = f"limits {MAX_PIXELS} px, {MAX_DECODED_BYTES} bytes"
        raise ImageReadError(path, f"image {spec.width}x{spec.height} px refused ({limits})")
    return inp, spec


def _pixel_types(spec: Any) -> tuple[str, ...]:
    formats = list(spec.channelformats) or [spec.format] * spec.nchannels
    return tuple(str(t) for t in formats)


def _bits_per_sample(spec: Any) -> int:
    basetype = str(spec.format)
    if basetype in ("half", "float", "double"):
        return 0
    bits = int(spec.getattribute("oiio:BitsPerSample") or 0)
    return bits or int(spec.format.size()) * 8


def _read_oiio(
    path: str, fmt: str, subimage: int, *, native: bool, chbegin: int = 0, chend: int | None = None
) -> tuple[np.ndarray, Any]:
    """Decode one subimage, miplevel 0, channels [chbegin, chend); returns ([H, W, C], spec)."""
    oiio = _oiio()
    inp, spec = _open_oiio(path, fmt, subimage)
    try:
        chend = spec.nchannels if chend is None else chend
        try:
            pixels = inp.read_image(subimage, 0, chbegin, chend, oiio.UNKNOWN if native else oiio.FLOAT)
        except Exception as exc:  # noqa: BLE001 - the bindings raise assorted types on bad data
            raise ImageReadError(path, f"damaged {fmt.upper()}: decoder error: {exc}") from None
        has_error = inp.has_error() if callable(inp.has_error) else inp.has_error  # a property in OIIO 3
        if pixels is None or has_error:
            reason = _oiio_error(inp, "pixel data unreadable (truncated?)")
            raise ImageReadError(path, f"damaged {fmt.upper()}: {reason}")
    finally:
        inp.close()
    pixels = np.asarray(pixels)
    if pixels.ndim == 2:  # single channel arrives as [H, W]
        pixels = pixels[:, :, None]
    expected = (spec.height, spec.width, chend - chbegin)
    if pixels.shape != expected:
        raise ImageReadError(path, f"decoder returned shape {pixels.shape}, header says {expected}")
    return np.ascontiguousarray(pixels), spec


def _rgb_indices(channels: Sequence[str]) -> tuple[list[int], tuple[str, ...]] | None:
    """Indices to take R,G,B(,A) from ``channels``; a luminance-only image gives Y,Y,Y(,A)."""
    names = list(channels)
    alpha = [names.index("A")] if "A" in names else []
    if all(c in names for c in "RGB"):
        return [names.index(c) for c in "RGB"] + alpha, ("R", "G", "B", "A")[: 3 + len(alpha)]
    if "Y" in names:  # luminance: grey is R = G = B = Y
        y = names.index("Y")
        return [y, y, y] + alpha, ("R", "G", "B", "A")[: 3 + len(alpha)]
    return None


def _normalise_integer(pixels: np.ndarray, bits: int) -> np.ndarray:
    """Integer codes to [0, 1] float32: code / (2**bits - 1).

    OIIO widens 10/12-bit DPX/TIFF codes to 16 bits by bit replication, so the true code is the top
    ``bits`` bits; dividing the widened value by 65535 would be off by up to 0.002%. Depths below 8
    (1/2/4-bit grey, palette indices) are already expanded to full 8-bit values: divide by 255.
    """
    container = pixels.dtype.itemsize * 8
    codes = pixels.astype(np.uint32)
    if 8 < bits < container:
        codes >>= container - bits
    else:
        bits = container
    return (codes.astype(np.float64) / float(2**bits - 1)).astype(np.float32)


def _single_part_header(spec: Any) -> PartHeader:
    """The one part of a PNG/TIFF/DPX, from OpenImageIO's spec."""
    window = (0, 0, spec.width - 1, spec.height - 1)
    return PartHeader(index=0, name=None, view=None, views=(), channels=tuple(spec.channelnames),
                      data_window=window, display_window=window)


# --------------------------------------------------------------------------------------------------
# Reading.


def probe_image(path: str | os.PathLike[str], part: int = 0) -> ImageInfo:
    """Header facts of an image file (EXR/PNG/TIFF/DPX) without decoding pixels.

    For EXR the whole file structure is validated (:mod:`volcap_core.imageio.check`); ``part`` picks the
    EXR part described. Raises :class:`ImageReadError`.
    """
    path = os.fspath(path)
    fmt = _sniff_file(path)
    headers: tuple[PartHeader, ...] = ()
    if fmt == "exr":
        parts = validate_exr_file(path)
        decodable_part(parts, part, path)
        headers = tuple(part_header(i, p) for i, p in enumerate(parts))
    elif part != 0:
        raise ImageReadError(path, f"part {part} requested, a {fmt} file has 1 part")
    return _image_info(path, fmt, part, headers)


def _image_info(path: str, fmt: str, part: int, headers: tuple[PartHeader, ...]) -> ImageInfo:
    """ImageInfo of ``part`` once the structure is checked (``headers`` empty for non-EXR)."""
    inp, spec = _open_oiio(path, fmt, part)
    inp.close()
    if not headers:
        headers = (_single_part_header(spec),)
    n_parts = len(headers)
    dw, dsp = headers[part].data_window, headers[part].display_window
    return ImageInfo(
        path=path,
        width=spec.width,
        height=spec.height,
        channels=tuple(spec.channelnames),
        pixel_types=_pixel_types(spec),
        format=fmt,
        parts=n_parts,
        data_window=dw,
        display_window=dsp,
        bits_per_sample=_bits_per_sample(spec),
        part_headers=headers,
    )


def _file_parts(path: str, fmt: str) -> tuple[PartHeader, ...] | None:
    """Every EXR part's header (the structure check included); None for other formats, whose one
    part is described from the decoder's spec."""
    if fmt != "exr":
        return None
    return tuple(part_header(i, p) for i, p in enumerate(validate_exr_file(path)))


def probe_footage(path: str | os.PathLike[str], part: str | None = None,
                  view: str | None = None) -> tuple[ImageInfo, ColourSource]:
    """:func:`probe_image` of the picture that ``part``/``view`` choose (see
    :func:`choose_colour_source`), and that picture. No pixels are decoded."""
    path = os.fspath(path)
    fmt = _sniff_file(path)
    headers = _file_parts(path, fmt)
    if headers is None:
        info = _image_info(path, fmt, 0, ())
        return info, choose_colour_source(info.part_headers, part, view, path=path)
    source = choose_colour_source(headers, part, view, path=path)
    return _image_info(path, fmt, source.part, headers), source


def read_footage(path: str | os.PathLike[str], part: str | None = None, view: str | None = None) -> Footage:
    """Decode the picture of an image file that ``part`` (an EXR part name) and ``view`` (a view
    name) choose: see :func:`choose_colour_source` for the rules, :class:`Footage` for what comes
    back. One structure check and one decode, as :func:`read_image`.

    Raises :class:`SourceChoiceError` for a multi-part or multi-view file without a choice (or a
    choice it does not hold), :class:`ImageReadError` for everything :func:`read_image` refuses.
    """
    path = os.fspath(path)
    fmt = _sniff_file(path)
    headers = _file_parts(path, fmt)
    if headers is not None:
        source = choose_colour_source(headers, part, view, path=path)
        header = headers[source.part]
    inp, spec = _open_oiio(path, fmt, 0 if headers is None else source.part)
    names, bits, base = tuple(spec.channelnames), _bits_per_sample(spec), str(spec.format)
    inp.close()
    if headers is None:
        header = _single_part_header(spec)
        source = choose_colour_source((header,), part, view, path=path)
    indices = _decoder_indices(path, names, source)
    lo, hi = min(indices), max(indices) + 1  # decode only the channel range we need
    integer = fmt != "exr" and base not in ("half", "float", "double")
    pixels, _ = _read_oiio(path, fmt, source.part, native=integer, chbegin=lo, chend=hi)
    pixels = pixels[:, :, [i - lo for i in indices]]
    if integer and np.issubdtype(pixels.dtype, np.unsignedinteger):
        pixels = _normalise_integer(pixels, bits)
    channels = ("R", "G", "B", "A")[: len(indices)]
    return Footage(np.ascontiguousarray(pixels, dtype=np.float32), channels, source, header)


def _decoder_indices(path: str, names: Sequence[str], source: ColourSource) -> list[int]:
    """Indices into the decoder's channels giving R, G, B(, A) of ``source``.

    OpenImageIO names channels as the file does, except that it decodes a luminance/chroma
    picture to R, G, B; a luminance-only picture is grey (R = G = B = Y).
    """
    alpha = [source.channels[-1]] if source.has_alpha else []
    if source.kind == "luminance-chroma":
        prefix = source.channels[0][:-1]  # "" or "<view>."
        wanted = [f"{prefix}{c}" for c in "RGB"] + alpha
    elif source.kind == "luminance":
        wanted = [source.channels[0]] * 3 + alpha
    else:
        wanted = list(source.channels)
    missing = [w for w in wanted if w not in names]
    if missing:
        raise ImageReadError(path, f"the decoder does not present channel(s) {', '.join(missing)} of "
                                   f"{source.label()} (it presents {', '.join(names)})")
    return [list(names).index(w) for w in wanted]


def read_image(path: str | os.PathLike[str], part: int = 0) -> tuple[np.ndarray, tuple[str, ...]]:
    """Decode R,G,B(,A) of an EXR/PNG/TIFF/DPX file.

    Returns ``(pixels, channels)``: ``pixels`` float32 ``[H, W, C]`` over the data window, C = 3 or
    4, ``channels`` ``("R","G","B")`` or ``("R","G","B","A")``. Other channels are ignored.
    EXR: values as stored (scene-linear; NaN/Inf kept: the caller has the policy); mip level 0 of
    mip-mapped files; ``part`` selects the part of a multi-part file; luminance/chroma (Y, RY, BY)
    files come back as RGB and luminance-only (Y) as R = G = B = Y.
    PNG/TIFF/DPX: integer codes normalised to [0, 1] (``code / (2**bits - 1)``), not linearised;
    float TIFFs as stored.
    Raises :class:`ImageReadError` for damaged, truncated, deep, oversized files or files without
    R,G,B (or Y) channels.
    """
    path = os.fspath(path)
    fmt = _sniff_file(path)
    if fmt == "exr":
        decodable_part(validate_exr_file(path), part, path)
    elif part != 0:
        raise ImageReadError(path, f"part {part} requested, a {fmt} file has 1 part")
    return _read_rgb(path, fmt, part)


def _read_rgb(path: str, fmt: str, part: int) -> tuple[np.ndarray, tuple[str, ...]]:
    inp, spec = _open_oiio(path, fmt, part)
    names, bits, base = tuple(spec.channelnames), _bits_per_sample(spec), str(spec.format)
    inp.close()
    pick = _rgb_indices(names)
    if pick is None:
        raise ImageReadError(path, f"no RGB channels (it has {', '.join(names) or 'none'})")
    indices, out_names = pick
    lo, hi = min(indices), max(indices) + 1  # decode only the channel range we need
    integer = fmt != "exr" and base not in ("half", "float", "double")
    pixels, _ = _read_oiio(path, fmt, part, native=integer, chbegin=lo, chend=hi)
    pixels = pixels[:, :, [i - lo for i in indices]]
    if integer and np.issubdtype(pixels.dtype, np.unsignedinteger):
        pixels = _normalise_integer(pixels, bits)
    return np.ascontiguousarray(pixels, dtype=np.float32), out_names


def read_exr_native(path: str | os.PathLike[str], part: int = 0) -> tuple[np.ndarray, tuple[str, ...]]:
    """The decoded native pixels of one EXR part: ``([H, W, C], channel names)``.

    All channels, in the order OpenImageIO presents them (R,G,B,A first when present, then the rest
    in file order; luminance/chroma files as R,G,B), native dtype (float16 / float32 / uint32; a
    part mixing channel types comes as its widest type), data window, top row first, mip level 0.
    ``sha1(pixels.tobytes())`` is what OpenImageIO's reference hashes (``iinfo --hash``) cover.
    """
    path = os.fspath(path)
    fmt = _sniff_file(path)
    if fmt != "exr":
        raise ImageReadError(path, f"not an EXR file (content is {fmt})")
    decodable_part(validate_exr_file(path), part, path)
    pixels, spec = _read_oiio(path, fmt, part, native=True)
    return pixels, tuple(spec.channelnames)


def decode_exr(data: bytes, name: str = "<bytes>", part: int = 0) -> tuple[np.ndarray, tuple[str, ...]]:
    """:func:`read_image` for EXR bytes held in memory; ``name`` labels errors.

    A plain frame (:func:`~volcap_core.imageio.plain_frame.plain_frame_header`: every frame ingest
    stores) is decoded from memory by :func:`~volcap_core.imageio.plain_frame.decode_half_exr`:
    the same values OpenImageIO gives, faster (``docs/benchmarks.md``) and without a temporary
    file; anything else goes through OpenImageIO."""
    data = bytes(data)
    if part == 0 and plain_frame_header(data, name) is not None:
        pixels = decode_half_exr(data, name)
        return pixels.astype(np.float32), ("R", "G", "B", "A")[: pixels.shape[-1]]
    return _decode_exr_bytes(data, name, part, lambda tmp: _read_rgb(tmp, "exr", part))


def decode_exr_native(data: bytes, name: str = "<bytes>", part: int = 0) -> tuple[np.ndarray, tuple[str, ...]]:
    """:func:`read_exr_native` for EXR bytes held in memory (any channels, e.g. a depth ``Z``)."""
    return _decode_exr_bytes(data, name, part, lambda tmp: read_exr_native(tmp, part))


def _decode_exr_bytes(data: bytes, name: str, part: int, read) -> tuple[np.ndarray, tuple[str, ...]]:
    data = bytes(data)  # no copy for bytes; bytearray/memoryview become immutable
    decodable_part(validate_exr_buffer(data, len(data), name), part, name)
    # OpenImageIO's Python bindings read from paths only: go through a private temporary file
    fd, tmp = tempfile.mkstemp(suffix=".exr", prefix="volcap-decode-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        try:
            return read(tmp)
        except ImageReadError as exc:
            raise ImageReadError(name, exc.reason) from None
    finally:
        os.unlink(tmp)


def read_exr_header(path: str | os.PathLike[str], part: int = 0) -> dict[str, Any]:
    """An EXR part's header attributes as Python values (strings, numbers, tuples, numpy arrays).

    This is where attributes given to :func:`~volcap_core.imageio.write.write_exr` (camera metadata)
    are read back.
    """
    path = os.fspath(path)
    fmt = _sniff_file(path)
    if fmt != "exr":
        raise ImageReadError(path, f"not an EXR file (content is {fmt})")
    parts = validate_exr_file(path)
    if not 0 <= part < len(parts):
        raise ImageReadError(path, f"part {part} requested, the file has {len(parts)} part(s)")
    import OpenEXR

    try:
        f = OpenEXR.File(path, header_only=True)
        if len(f.parts) <= part:  # the bindings can return an empty File instead of raising
            raise ImageReadError(path, f"damaged EXR: OpenEXR found {len(f.parts)} part(s)")
        header = dict(f.header(part))
    except ImageReadError:
        raise
    except Exception as exc:  # noqa: BLE001 - e.g. UnicodeDecodeError for non-UTF-8 strings
        raise ImageReadError(path, f"damaged EXR header: {type(exc).__name__}: {exc}") from None
    # the bindings present an EXR "double" as a 1-element float64 array: give it back as a float
    return {
        k: float(v[0]) if isinstance(v, np.ndarray) and v.dtype == np.float64 and v.shape == (1,) else v
        for k, v in header.items()
    }
