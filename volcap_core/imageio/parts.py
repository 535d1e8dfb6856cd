"""The parts and views an image file holds, and which picture a part name and a view name choose.

An EXR may hold several parts (OpenEXR multi-part: each part named by its ``name`` attribute,
stereo parts by ``view``) and, within one part, several views (the multi-view convention:
``multiView`` lists the views, the default first; channels of the others are prefixed
``<view>.``). A PNG/TIFF/DPX holds one part. :class:`PartHeader` is what a part's header says;
:func:`colour_sources` lists the pictures (part, view) with colour channels, and
:func:`choose_colour_source` picks one by name or refuses: a multi-part or multi-view file is never
read as its first part or default view by accident.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from volcap_core.chromaticities import Chromaticities
from volcap_core.imageio.check import ExrPart
from volcap_core.imageio.errors import ImageReadError, SourceChoiceError

__all__ = [
    "PartHeader",
    "ColourSource",
    "part_header",
    "colour_sources",
    "choose_colour_source",
    "describe_parts",
    "window_overlap",
]


@dataclass(frozen=True)
class PartHeader:
    """What one part of an image file holds, from its header (EXR; a PNG/TIFF/DPX has one part
    with no name, no views, no chromaticities and both windows ``(0, 0, W-1, H-1)``).

    ``channels`` are the names stored in the file, in file order (a luminance/chroma EXR shows
    Y, RY, BY here). ``view`` is the part's ``view`` attribute (every channel of the part belongs to
    it: multi-part stereo); ``views`` its ``multiView`` attribute (single-part stereo: channels of
    view ``v`` are prefixed ``v.``, the default view ``views[0]`` unprefixed). ``chromaticities`` are
    the 8 numbers of the ``chromaticities`` attribute (None when absent: Rec.709/D65 by the EXR
    specification); ``adopted_neutral`` the ``adoptedNeutral`` (x, y).
    """

    index: int
    name: str | None
    view: str | None
    views: tuple[str, ...]
    channels: tuple[str, ...]
    data_window: tuple[int, int, int, int]
    display_window: tuple[int, int, int, int]
    chromaticities: Chromaticities | None = None
    adopted_neutral: tuple[float, float] | None = None
    pixel_aspect_ratio: float = 1.0
    deep: bool = False

    @property
    def display_size(self) -> tuple[int, int]:
        """(width, height) of the display window: the size of the picture, whatever the data window."""
        x0, y0, x1, y1 = self.display_window
        return (x1 - x0 + 1, y1 - y0 + 1)


@dataclass(frozen=True)
class ColourSource:
    """One picture a file holds: a part, and within it a view (None for a file without views).

    ``channels`` are the file's channel names it is made of, in the order R, G, B(, A) for
    ``kind`` "rgb", Y(, A) for "luminance" (grey: R = G = B = Y) and Y, RY, BY(, A) for
    "luminance-chroma" (decoded to RGB in the file's primaries).
    """

    part: int
    part_name: str | None
    view: str | None
    channels: tuple[str, ...]
    kind: str  # "rgb" | "luminance" | "luminance-chroma"

    @property
    def has_alpha(self) -> bool:
        return self.channels[-1].rsplit(".", 1)[-1] == "A"

    def label(self) -> str:
        """How messages name it: ``part 'rgba' view 'left'``."""
        label = f"part {self.part_name!r}" if self.part_name is not None else f"part {self.part}"
        return label if self.view is None else f"{label} view {self.view!r}"


def part_header(index: int, part: ExrPart) -> PartHeader:
    """The header of part ``index`` as the structure check parsed it."""
    chroma = part.chromaticities
    return PartHeader(
        index=index, name=part.name, view=part.view, views=part.multi_view,
        channels=tuple(c.name for c in part.channels),
        data_window=part.data_window, display_window=part.display_window,
        chromaticities=None if chroma is None else Chromaticities(*chroma),
        adopted_neutral=part.adopted_neutral, pixel_aspect_ratio=part.pixel_aspect_ratio, deep=part.deep,
    )


def _view_prefixes(part: PartHeader, view: str | None) -> tuple[str, ...]:
    """Channel-name prefixes of ``view`` in ``part`` (OpenEXR ImfMultiView: in a ``multiView`` part
    the default view, listed first, is unprefixed or prefixed, every other view ``<view>.``)."""
    if not part.views:
        return ("",)
    return ("", f"{view}.") if view == part.views[0] else (f"{view}.",)


def _colour_channels(names: set[str], prefixes: Sequence[str]) -> tuple[tuple[str, ...], str] | None:
    """R,G,B(,A), else Y,RY,BY(,A), else Y(,A) under the first prefix that has them."""
    for prefix in prefixes:
        if all(f"{prefix}{c}" in names for c in "RGB"):
            alpha = (f"{prefix}A",) if f"{prefix}A" in names else ()
            return tuple(f"{prefix}{c}" for c in "RGB") + alpha, "rgb"
    for prefix in prefixes:
        if f"{prefix}Y" in names:
            alpha = (f"{prefix}A",) if f"{prefix}A" in names else ()
            chroma = (f"{prefix}RY", f"{prefix}BY")
            if all(c in names for c in chroma):
                return (f"{prefix}Y",) + chroma + alpha, "luminance-chroma"
            return (f"{prefix}Y",) + alpha, "luminance"
    return None


def colour_sources(parts: Sequence[PartHeader]) -> tuple[ColourSource, ...]:
    """Every picture (part, view) the parts hold with colour channels, in file order, a part's
    default view first. Deep parts hold none (they are not supported)."""
    out = []
    for part in parts:
        if part.deep:
            continue
        names = set(part.channels)
        views: Sequence[str | None] = part.views or (part.view,)
        for view in views:
            found = _colour_channels(names, _view_prefixes(part, view))
            if found is not None:
                out.append(ColourSource(part.index, part.name, view, found[0], found[1]))
    return tuple(out)


def describe_parts(parts: Sequence[PartHeader]) -> str:
    """What a file holds, for messages: each part by name with its view(s) and channels."""
    items = []
    for part in parts:
        label = f"part {part.name!r}" if part.name is not None else f"part {part.index}"
        if part.view is not None:
            label += f" (view {part.view!r})"
        if part.views:
            label += f" (views {', '.join(repr(v) for v in part.views)}; {part.views[0]!r} is the default)"
        if part.deep:
            label += " (deep)"
        items.append(f"{label}: {', '.join(part.channels)}")
    return "; ".join(items)


def _declared_views(parts: Sequence[PartHeader]) -> list[str]:
    seen: list[str] = []
    for part in parts:
        for v in part.views or ((part.view,) if part.view is not None else ()):
            if v not in seen:
                seen.append(v)
    return seen


def choose_colour_source(parts: Sequence[PartHeader], part: str | None = None, view: str | None = None,
                         *, path: str = "") -> ColourSource:
    """The one picture of a file that ``part`` (a part name) and ``view`` (a view name) choose.

    With neither given, the file must hold a single part and at most one view: a multi-part or
    multi-view file is refused rather than read as its first part or default view. A choice that
    matches no picture, or several, is refused. Errors (:class:`SourceChoiceError`, or
    :class:`ImageReadError` for a file with no colour at all) list what the file holds.
    """
    sources = colour_sources(parts)
    holds = describe_parts(parts)
    views = _declared_views(parts)
    if part is None and view is None:
        if len(parts) > 1 or len(views) > 1:
            what = f"{len(parts)} parts" if len(parts) > 1 else f"{len(views)} views ({', '.join(views)})"
            raise SourceChoiceError(path, f"holds {what} and no part or view was chosen; it holds {holds}")
        if not sources:
            if parts and all(p.deep for p in parts):
                raise ImageReadError(path, "deep data not supported")
            raise ImageReadError(path, f"no R,G,B (or Y) channels (it has {', '.join(parts[0].channels) or 'none'})")
        return sources[0]
    matches = [s for s in sources if (part is None or s.part_name == part) and (view is None or s.view == view)]
    if len(matches) == 1:
        return matches[0]
    chosen = " and ".join(f"{k} {v!r}" for k, v in (("part", part), ("view", view)) if v is not None)
    if not matches:
        raise SourceChoiceError(path, f"holds no {chosen} with R,G,B (or Y) channels; it holds {holds}")
    raise SourceChoiceError(path, f"{chosen} matches {len(matches)} pictures "
                                  f"({', '.join(m.label() for m in matches)}); it holds {holds}")


def window_overlap(data_window: tuple[int, int, int, int], display_window: tuple[int, int, int, int]
                   ) -> tuple[tuple[slice, slice], tuple[slice, slice]] | None:
    """Where a data window's pixels land in the display window.

    Windows are inclusive ``(xmin, ymin, xmax, ymax)``. Returns ``(src, dst)``: ``(rows, cols)``
    slices into the data-window array ``[Hd, Wd, C]`` and into the display-window array
    ``[Hp, Wp, C]`` covering the pixels both windows share; None when they share none.
    """
    dx0, dy0, dx1, dy1 = data_window
    px0, py0, px1, py1 = display_window
    x0, y0, x1, y1 = max(dx0, px0), max(dy0, py0), min(dx1, px1), min(dy1, py1)
    if x0 > x1 or y0 > y1:
        return None
    src = (slice(y0 - dy0, y1 - dy0 + 1), slice(x0 - dx0, x1 - dx0 + 1))
    dst = (slice(y0 - py0, y1 - py0 + 1), slice(x0 - px0, x1 - px0 + 1))
    return src, dst

