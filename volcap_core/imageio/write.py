"""Writing EXR files: a single-part scanline EXR of an ``[H, W, C]`` array, through the OpenEXR
bindings, declaring its ``chromaticities``; to bytes (:func:`encode_exr`, what the store holds) or
to a file, atomically (:func:`write_exr`).

The bytes are a function of the pixels, channels, pixel type, compression, attributes and
chromaticities alone: stored frames are content-addressed and their digests feed cache keys.
"""

from __future__ import annotations

import io
import os
from typing import Any, Mapping, Sequence

import numpy as np

from volcap_core.chromaticities import WORKING_CHROMATICITIES, Chromaticities
from volcap_core.files import write_atomic
from volcap_core.imageio.check import COMPRESSION_NAMES

__all__ = ["HALF_MAX", "encode_exr", "write_exr", "extra_attributes", "to_half"]

#: Largest finite half-float value; ``write_exr(..., pixel_type="half")`` clamps finite values to it.
HALF_MAX = 65504.0

_RESERVED_ATTRIBUTES = frozenset({
    "channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
    "screenWindowCenter", "screenWindowWidth", "tiles", "type", "name", "version", "chunkCount",
    "maxSamplesPerPixel", "chromaticities",
})


def _compression_enum(name: str):
    import OpenEXR

    key = name.lower()
    if key not in COMPRESSION_NAMES:
        raise ValueError(f"unknown EXR compression {name!r}; one of {', '.join(COMPRESSION_NAMES)}")
    return getattr(OpenEXR.Compression, "NO_COMPRESSION" if key == "none" else f"{key.upper()}_COMPRESSION")


def to_half(pixels: np.ndarray) -> np.ndarray:
    """float -> float16, clamping finite values to +-HALF_MAX (a plain cast would turn 70000 into
    inf, which downstream would read as a blown-out pixel rather than a very bright one); NaN and
    +-inf stay as they are."""
    p = np.asarray(pixels, dtype=np.float32)
    half = np.clip(p, -HALF_MAX, HALF_MAX).astype(np.float16)  # clip keeps NaN, bounds +-inf
    infinite = np.isinf(p)
    if infinite.any():
        half[infinite] = p[infinite]
    return half


def encode_exr(
    pixels: np.ndarray,
    channels: Sequence[str] = ("R", "G", "B", "A"),
    *,
    pixel_type: str = "half",
    compression: str = "zip",
    attributes: Mapping[str, str | float | int] | None = None,
    chromaticities: Chromaticities = WORKING_CHROMATICITIES,
) -> bytes:
    """A single-part scanline EXR of ``pixels`` (float ``[H, W, C]``, C = len(channels)) as bytes.

    ``pixel_type`` "half" (finite values clamped to +-65504, NaN/Inf kept) or "float".
    ``compression`` one of none, rle, zips, zip, piz, pxr24, b44, b44a, dwaa, dwab, zstd (...).
    ``attributes`` extra header attributes: ``str`` -> string, ``float`` -> float, ``int`` -> int;
    standard attribute names (channels, dataWindow, ...) are refused.
    ``chromaticities`` the primaries and white the pixels are in, written as the standard
    ``chromaticities`` attribute: volcap's working space unless told otherwise
    (:mod:`volcap_core.chromaticities`), so no reader has to assume.
    Data window = display window = ``(0, 0, W-1, H-1)``.
    """
    import OpenEXR

    p = np.asarray(pixels)
    if p.ndim == 2:
        p = p[:, :, None]
    channels = tuple(channels)
    if p.ndim != 3 or p.shape[2] != len(channels):
        raise ValueError(f"pixels shape {np.shape(pixels)} does not match channels {channels}")
    if p.shape[0] < 1 or p.shape[1] < 1:
        raise ValueError(f"empty image {p.shape}")
    if len(set(channels)) != len(channels) or not all(channels):
        raise ValueError(f"channel names must be unique and non-empty: {channels}")
    if not np.issubdtype(p.dtype, np.floating) and not np.issubdtype(p.dtype, np.integer):
        raise ValueError(f"pixels must be numeric, got {p.dtype}")
    if pixel_type == "half":
        data = to_half(p)
    elif pixel_type == "float":
        data = p.astype(np.float32)
    else:
        raise ValueError(f"pixel_type must be 'half' or 'float', got {pixel_type!r}")

    header: dict[str, Any] = {"compression": _compression_enum(compression), "type": OpenEXR.scanlineimage,
                              "chromaticities": tuple(float(v) for v in Chromaticities(*chromaticities))}
    for key, value in extra_attributes(attributes).items():
        # a Python float would become a 32-bit EXR "float"; a 1-element float64 array is written as
        # a "double", so values such as timestamps survive the round trip exactly
        header[key] = np.array([value], dtype=np.float64) if isinstance(value, float) else value
    planes = {name: np.ascontiguousarray(data[:, :, i]) for i, name in enumerate(channels)}
    out = io.BytesIO()
    OpenEXR.File(header, planes).write(out)
    return out.getvalue()


def extra_attributes(attributes: Mapping[str, str | float | int] | None) -> dict[str, str | float | int]:
    """``attributes`` checked: non-reserved names, str/float/int values (float -> "double")."""
    out = dict(attributes or {})
    for key, value in out.items():
        if not isinstance(key, str) or not key or key in _RESERVED_ATTRIBUTES:
            raise ValueError(f"attribute name {key!r} is reserved or invalid")
        if isinstance(value, bool) or not isinstance(value, (str, float, int)):
            kind = type(value).__name__
            raise ValueError(f"attribute {key!r}: only str, float and int values are supported, got {kind}")
    return out


def write_exr(
    path: str | os.PathLike[str],
    pixels: np.ndarray,
    channels: Sequence[str] = ("R", "G", "B", "A"),
    *,
    pixel_type: str = "half",
    compression: str = "zip",
    attributes: Mapping[str, str | float | int] | None = None,
    chromaticities: Chromaticities = WORKING_CHROMATICITIES,
) -> None:
    """:func:`encode_exr` to ``path``, atomically: the bytes go to a temporary file in the same
    folder, are flushed to disk, then renamed over ``path``; a failure at any point leaves
    ``path`` untouched (absent or its previous content) and no temporary file behind
    (:func:`volcap_core.files.write_atomic`)."""
    data = encode_exr(pixels, channels, pixel_type=pixel_type, compression=compression, attributes=attributes,
                      chromaticities=chromaticities)
    write_atomic(path, data)
