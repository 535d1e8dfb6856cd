"""Contact sheets: the pictures a person looks at before believing a metric.

A held-out PSNR of 23.1 dB says nothing about *where* the render is wrong (a blurred face, a
missing arm, a colour cast over the whole frame, a floater in the background). A contact sheet puts
one row per view on a single image::

    <title>                                                     (optional)
    footage              | render               | error (|sRGB diff| / 0.25)
    <row label, e.g. "S004 frame 4 held-out PSNR 23.1 dB">
    [ground truth, sRGB] | [model render, sRGB] | [error heat map, mask outline]
    <next row label>
    ...

Footage and render are shown as display sRGB (IEC 61966-2-1, clamped to ``[0, 1]``), the way an
artist sees them. The error panel is the per-pixel mean over R, G, B of ``|sRGB(truth) -
sRGB(output)|``, divided by ``error_scale`` and clamped to ``[0, 1]``, through OpenCV's *inferno*
colour map: black is "no difference", yellow-white is "off by ``error_scale`` or more". The
difference is taken in sRGB rather than linear light because that is what the eye compares (a
0.01 linear error in a shadow is glaring, in a highlight invisible). Non-finite pixels (NaN/inf in
either image) count as the maximal error so a numerical bug is bright, not hidden. An optional mask
(e.g. where the performers are) is outlined in cyan on the error panel, a colour the inferno map
never produces.

Every panel of a sheet has the same width (about ``max_width / 3``): large images are shrunk with
area averaging, small ones (a 160x90 test capture) are enlarged with nearest neighbour so the
pixels stay visible as pixels rather than being blurred into something that looks better than it
is. The output is deterministic (same input, same bytes).

This module is pure numpy/OpenCV (no Prefect): ``tasks/artifacts.py`` puts the PNG in the UI.
"""

from __future__ import annotations

import os
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from volcap_core.colour import srgb_encode
from volcap_core.files import write_atomic

__all__ = ["SheetRow", "contact_sheet", "encode_jpeg", "encode_png", "write_sheet"]

#: Pixels between panels, and around the sheet.
GAP = 4
_BACKGROUND = (24, 24, 24)  # RGB; dark so the panels, not the frame, draw the eye
_TEXT = (235, 235, 235)
_MASK_OUTLINE = (0, 255, 255)  # RGB cyan: absent from the inferno map, visible on black and on yellow
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_LABEL_SCALE = 0.5  # ~12 px cap height: readable at 100 % and on a laptop screen
_TITLE_SCALE = 0.7
_MIN_SCALE = 0.35  # below this Hershey glyphs turn into smudges; truncate instead


@dataclass(frozen=True)
class SheetRow:
    """One row of a contact sheet.

    Attributes:
        label: text drawn above the row, e.g. ``"S004 frame 4 held-out PSNR 23.1 dB"`` (ASCII is
            drawn as is; other characters are transliterated where possible, else ``?``).
        truth: the footage, scene-linear float RGB ``[H, W, 3]`` (any float dtype; HDR > 1 and
            slightly negative values allowed, both clamped for display).
        output: the render of the same view, scene-linear float RGB ``[H, W, 3]``, same shape.
        mask: optional ``[H, W]`` weights in ``[0, 1]`` (e.g. performer coverage); its 0.5
            iso-line is outlined on the error panel.
    """

    label: str
    truth: np.ndarray
    output: np.ndarray
    mask: np.ndarray | None = None


def contact_sheet(rows: Sequence[SheetRow], *, title: str | None = None, max_width: int = 1600,
                  error_scale: float = 0.25, truth_label: str = "footage") -> np.ndarray:
    """Lay out ``footage | render | error`` for every row, with labels, on one RGB image.

    Args:
        rows: at least one :class:`SheetRow`; rows may have different image sizes.
        title: optional line drawn at the very top (e.g. the segment and model digest).
        max_width: width of the sheet in pixels (the result is at most this wide); each panel is
            ``(max_width - 4 * GAP) // 3`` pixels wide.
        error_scale: sRGB difference (mean over channels, ``[0, 1]`` units) shown at full
            brightness; 0.25 makes a 1/4-of-full-range mistake saturate while a 0.01 one is still a
            visible dark purple.
        truth_label: the first column's heading: ``footage`` (a camera's frames) or ``truth``
            (a synthetic stage's render for a virtual camera).

    Returns:
        uint8 RGB image ``[H_sheet, W_sheet, 3]`` with ``W_sheet <= max_width``.

    Raises:
        ValueError: no rows; a truth/output that is not a float ``[H, W, 3]`` array; truth and
            output of a row with different shapes; a mask that is not ``[H, W]``; a non-positive
            ``error_scale``; a ``max_width`` too small for three panels.
    """
    rows = list(rows)
    if not rows:
        raise ValueError("contact_sheet needs at least one SheetRow, got none")
    if not (np.isfinite(error_scale) and error_scale > 0):
        raise ValueError(f"error_scale must be a positive number, got {error_scale!r}")
    panel_w = (int(max_width) - 4 * GAP) // 3
    if panel_w < 8:
        raise ValueError(f"max_width {max_width} is too small for three panels (need >= {4 * GAP + 24})")
    sheet_w = 3 * panel_w + 4 * GAP
    # Validate everything before drawing anything: a bad row 7 must not cost the work on rows 0-6.
    checked = [_check_row(i, row) for i, row in enumerate(rows)]

    parts: list[np.ndarray] = []
    if title:
        parts.append(_text_strip(sheet_w, [(GAP, title)], _TITLE_SCALE, thickness=1))
    headers = [truth_label, "render", f"error (|sRGB diff| / {error_scale:g})"]
    parts.append(_text_strip(sheet_w, [(GAP + k * (panel_w + GAP), h) for k, h in enumerate(headers)],
                             _LABEL_SCALE, thickness=1, max_text_w=panel_w))
    for row, (truth, output, mask) in zip(rows, checked):
        parts.append(_text_strip(sheet_w, [(GAP, row.label)], _LABEL_SCALE, thickness=1))
        parts.append(_row_panels(truth, output, mask, panel_w, sheet_w, error_scale))
    parts.append(_blank(GAP, sheet_w))
    return np.ascontiguousarray(np.concatenate(parts, axis=0))


def encode_png(image: np.ndarray) -> bytes:
    """uint8 RGB ``[H, W, 3]`` -> PNG file bytes (OpenCV's default, deterministic, compression).

    Raises:
        ValueError: not a uint8 ``[H, W, 3]`` array, or the encoder failed.
    """
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape[:2]:
        raise ValueError(f"encode_png expects a uint8 RGB image [H, W, 3], got {image.dtype} {image.shape}")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image[:, :, ::-1]))  # OpenCV writes BGR
    if not ok:
        raise ValueError(f"OpenCV could not encode a {image.shape} image as PNG")
    return buf.tobytes()


def encode_jpeg(image: np.ndarray, quality: int = 85) -> bytes:
    """uint8 RGB ``[H, W, 3]`` -> JPEG bytes: a tenth of the PNG for pages that embed a sheet
    (footage with sensor noise compresses badly as PNG)."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape[:2]:
        raise ValueError(f"encode_jpeg expects a uint8 RGB image [H, W, 3], got {image.dtype} {image.shape}")
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(image[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"OpenCV could not encode a {image.shape} image as JPEG")
    return buf.tobytes()


def write_sheet(path: str | os.PathLike[str], image: np.ndarray) -> None:
    """A sheet to ``path`` as PNG, or JPEG when the name ends in ``.jpg``/``.jpeg``, atomically
    (temporary file in the same folder, fsync, rename): a crash leaves ``path`` absent or as it
    was, never a truncated image a viewer chokes on."""
    path = Path(path)
    data = encode_jpeg(image) if path.suffix.lower() in (".jpg", ".jpeg") else encode_png(image)
    write_atomic(path, data)


# -- validation ------------------------------------------------------------------------------------


def _check_row(i: int, row: SheetRow) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    name = f"row {i} ({row.label!r})"
    truth = _check_image(f"{name}: truth", row.truth)
    output = _check_image(f"{name}: output", row.output)
    if truth.shape != output.shape:
        raise ValueError(f"{name}: truth {truth.shape} and output {output.shape} must have the same shape")
    mask = None
    if row.mask is not None:
        mask = np.asarray(row.mask)
        if mask.ndim == 3 and mask.shape[2] == 1:
            mask = mask[:, :, 0]
        if mask.shape != truth.shape[:2]:
            raise ValueError(f"{name}: mask must be [H, W] = {truth.shape[:2]}, got {mask.shape}")
        if not (np.issubdtype(mask.dtype, np.floating) or np.issubdtype(mask.dtype, np.bool_)
                or np.issubdtype(mask.dtype, np.integer)):
            raise ValueError(f"{name}: mask must be numeric or bool, got {mask.dtype}")
        mask = np.nan_to_num(mask.astype(np.float32), nan=0.0)
    return truth, output, mask


def _check_image(name: str, image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"{name} must be an RGB image [H, W, 3], got shape {a.shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{name} is empty: shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        # uint8 footage would silently be treated as linear 0..255 and show as white
        raise ValueError(f"{name} must be scene-linear float, got {a.dtype} (decode integer codes first)")
    return a


# -- panels ----------------------------------------------------------------------------------------


def _display(linear: np.ndarray, finite: np.ndarray) -> np.ndarray:
    """Scene-linear ``[H, W, 3]`` -> display sRGB float32 ``[H, W, 3]`` in ``[0, 1]``, non-finite -> 0."""
    x = np.where(finite[..., None], np.asarray(linear, dtype=np.float32), 0.0).astype(np.float32)
    return srgb_encode(np.ascontiguousarray(x))


def _row_panels(truth: np.ndarray, output: np.ndarray, mask: np.ndarray | None, panel_w: int, sheet_w: int,
                error_scale: float) -> np.ndarray:
    """The three panels of one row, resized to ``panel_w``, on the background: ``[h, sheet_w, 3]`` uint8."""
    finite = np.isfinite(truth).all(axis=2) & np.isfinite(output).all(axis=2)
    t = _display(truth, finite)
    o = _display(output, finite)
    # The error is computed at native resolution, then resized as a scalar field, then coloured:
    # colouring first and area-averaging after would invent colours that are not on the map.
    err = np.abs(t - o).mean(axis=2) / np.float32(error_scale)
    err = np.where(finite, np.clip(err, 0.0, 1.0), 1.0).astype(np.float32)

    h, w = truth.shape[:2]
    panel_h = max(1, round(h * panel_w / w))
    interp = cv2.INTER_AREA if panel_w <= w else cv2.INTER_NEAREST

    def fit(a: np.ndarray) -> np.ndarray:
        return cv2.resize(a, (panel_w, panel_h), interpolation=interp)

    t8 = _to_u8(fit(t))
    o8 = _to_u8(fit(o))
    e8 = _to_u8(fit(err))
    heat = cv2.applyColorMap(e8, cv2.COLORMAP_INFERNO)[:, :, ::-1]  # BGR -> RGB
    heat = np.ascontiguousarray(heat)
    if mask is not None:
        m = fit(np.clip(mask, 0.0, 1.0))
        contours, _ = cv2.findContours((m >= 0.5).astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(heat, contours, -1, _MASK_OUTLINE, thickness=1, lineType=cv2.LINE_8)

    band = _blank(panel_h, sheet_w)
    for k, panel in enumerate((t8, o8, heat)):
        x0 = GAP + k * (panel_w + GAP)
        band[:, x0:x0 + panel_w] = panel
    return band


def _to_u8(x: np.ndarray) -> np.ndarray:
    # rint, not truncation: 0.5/255 steps round to the nearest code like every image writer does
    return np.rint(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def _blank(h: int, w: int) -> np.ndarray:
    band = np.empty((h, w, 3), np.uint8)
    band[:] = _BACKGROUND
    return band


# -- text ------------------------------------------------------------------------------------------


def _ascii(text: str) -> str:
    """Hershey fonts draw ASCII only: transliterate what has an ASCII form (é -> e), else ``?``."""
    out = []
    for ch in " ".join(str(text).split()):  # newlines/tabs -> single spaces: one line per strip
        if ch.isascii():
            out.append(ch)
        else:
            folded = unicodedata.normalize("NFKD", ch).encode("ascii", "ignore").decode()
            out.append(folded or {"\u2014": "-", "\u2013": "-", "\u00d7": "x", "\u00b5": "u"}.get(ch, "?"))
    return "".join(out)


def _fit(text: str, scale: float, thickness: int, max_w: int) -> tuple[str, float]:
    """Shrink the font down to ``_MIN_SCALE``, then cut the text with ``...``, until it fits ``max_w``."""
    width = cv2.getTextSize(text, _FONT, scale, thickness)[0][0]
    if width <= max_w:
        return text, scale
    scale = max(_MIN_SCALE, scale * max_w / width)
    while text and cv2.getTextSize(text, _FONT, scale, thickness)[0][0] > max_w:
        text = text[:-4] + "..." if len(text) > 3 else ""
    return text, scale


def _text_strip(sheet_w: int, items: list[tuple[int, str]], scale: float, *, thickness: int,
                max_text_w: int | None = None) -> np.ndarray:
    """A background strip ``[h, sheet_w, 3]`` with each ``(x, text)`` drawn at its left edge ``x``."""
    (_, cap_h), baseline = cv2.getTextSize("Ag", _FONT, scale, thickness)
    strip_h = cap_h + baseline + 2 * GAP + 2
    strip = _blank(strip_h, sheet_w)
    for x, text in items:
        limit = max_text_w if max_text_w is not None else sheet_w - x - GAP
        fitted, s = _fit(_ascii(text), scale, thickness, limit)
        if not fitted:
            continue
        # same baseline for every item, whatever its (possibly shrunk) scale: the headers line up
        y = GAP + 1 + cap_h
        cv2.putText(strip, fitted, (x, y), _FONT, s, _TEXT, thickness, cv2.LINE_AA)
    return strip
