"""Ingest: check a capture folder, then convert each camera's frames to scene-linear half EXR.

Pure functions on a :class:`~volcap_core.capture.CaptureFolder`; the Prefect tasks in
``tasks/ingest.py`` call them and store what they return. Every error is an
:class:`~volcap_core.capture.IngestError` whose message names the file, camera and frame concerned.

Checks, in the order a coordinator meets them (all run before any pixel is converted, so a bad
folder fails in seconds, and nothing is recorded unless every camera converts):

1. ``capture.json`` parses and is valid; the rig loads (:meth:`CaptureFolder.open`).
2. Every camera of ``capture.json`` exists in the rig (rig cameras absent from the capture are
   allowed: a dead camera is left out of ``capture.json`` and reported).
3. Each camera folder holds one file per frame number (``000012.exr`` and ``000012.png``, or
   ``12.exr`` and ``0012.exr``, are duplicates); the take lies inside every camera's recording (the
   common timecode range) with no hole. Frames recorded outside the take are left out.
4. Each file's header is readable; the picture the camera's ``exr_part``/``exr_view`` choose is
   there (a multi-part or multi-view file without a choice is refused, listing what it holds);
   its *display window* is the rig sensor's resolution, its pixels are square, it holds RGB (or
   Y); its ``chromaticities`` define a conversion to the working space; alpha and chromaticities
   are the same in every frame of the camera.
5. Tracking cameras carry lens-encoder readings for every take frame.
   The lidar scan named by ``capture.json`` (if any) is a readable PLY of finite points.
   Performer masks (if ``capture.json`` names a masks folder): a camera that has masks has one for
   every take frame (:func:`select_masks`), each one channel at the camera's resolution with
   finite values in [0, 1] (:func:`check_masks`, every mask decoded here, before anything is stored).
6. While converting: damaged pixel data, and NaN/Inf pixels under the ``nan_policy``:
   ``"error"`` (default) refuses the frame, naming how many pixels; ``"repair"`` replaces NaN by 0
   and ±Inf by ±65504 (the largest half) and logs it.

A converted frame (:func:`convert_frame`) is the source's display window: the data window's pixels
placed at their offset, everything outside the data window 0 (alpha 0 too), data outside the display
window (overscan) left out; its colour is scene-linear in the working space
(:mod:`volcap_core.chromaticities`: linear Rec.709/D65), converted from the file's
``chromaticities`` when they differ. Its header says where it came from (``volcap.source_*``).
A source that already is such a frame (:func:`plain_frame_header`, scene-linear, working
primaries, no NaN/Inf) is restamped rather than converted: new header, the camera's compressed
chunks copied, its pixels decoded once to prove they decode. Re-compressing costs ~3x a decode, so
this is what keeps ingest near the cost of reading the footage (``bench/bench_ingest.py``).

A video camera (its ``path`` a video file) is checked by :func:`check_video` (size, square pixels,
frame rate, decodable colour tags) in place of step 4, and converted by
:func:`convert_video_camera`: decoded frame by frame (:mod:`volcap_core.imageio.video`), its range
and matrix expanded, its transfer undone and primaries converted as its
:class:`~volcap_core.capture.VideoEncoding` says (``docs/capture-layout.md``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from hardware.rig import Rig, RigCamera
from volcap_core.capture import (
    frames_to_timecode,
    timecode_to_frames,
    CameraSource,
    CaptureCamera,
    CaptureDescription,
    CaptureFolder,
    Encoding,
    IngestError,
    LensSample,
    VideoEncoding,
    video_encoding,
)
from volcap_core.chromaticities import (
    EXR_DEFAULT_CHROMATICITIES,
    REC709_D65,
    Chromaticities,
    convert_to_working,
    needs_conversion,
    to_working_matrix,
)
from volcap_core.colour import bt709_oetf_inverse, srgb_decode, srgb_decode_unbounded
from volcap_core.digest import digest_bytes, digest_file
from volcap_core.imageio.errors import ImageReadError, SourceChoiceError
from volcap_core.imageio.parts import ColourSource, PartHeader, window_overlap
from volcap_core.imageio.plain_frame import (
    decode_half_exr,
    half_nonfinite_pixels,
    plain_frame_header,
    restamp_exr,
)
from volcap_core.imageio.read import ImageInfo, probe_footage, read_footage
from volcap_core.imageio.video import VideoInfo, iter_video_frames, probe_video
from volcap_core.imageio.write import HALF_MAX, encode_exr

NanPolicy = Literal["error", "repair"]


@dataclass(frozen=True)
class RawFrame:
    take_index: int
    camera_frame: int   # the number in the file name
    path: Path          # absolute


def match_rig(desc: CaptureDescription, rig: Rig) -> tuple[dict[str, RigCamera], list[str]]:
    """Rig camera for each capture camera, and the rig cameras the capture leaves out."""
    known = {c.id: c for c in rig.cameras}
    unknown = [c.id for c in desc.cameras if c.id not in known]
    if unknown:
        raise IngestError(f"capture {desc.name}: camera(s) {', '.join(unknown)} are not in rig {rig.name}")
    listed = {c.id for c in desc.cameras}
    return {c.id: known[c.id] for c in desc.cameras}, [i for i in known if i not in listed]


def common_range(files: dict[str, dict[int, Path]]) -> tuple[int, int]:
    """[first, last] take indices every camera recorded (the intersection of their spans)."""
    first = max(min(f) for f in files.values())
    last = min(max(f) for f in files.values())
    return first, last


def select_take(desc: CaptureDescription, cam: CameraSource, files: dict[int, Path],
                common: tuple[int, int] | None = None) -> tuple[list[RawFrame], int]:
    """The camera's frames in take order, and how many recorded frames fall outside the take.

    ``files``: the camera's frame files by take index (:meth:`CaptureFolder.frame_files`).

    Frames recorded before or after the take are normal (cameras start and stop at different
    times) and are left out. A take reaching outside what the camera recorded, or a hole inside it,
    is an error naming the camera, the frame numbers and the common timecode range.
    """
    n = desc.take.frame_count
    offset = desc.take_offset(cam)
    lo, hi = min(files), max(files)
    if lo > 0 or hi < n - 1:
        tc0 = timecode_to_frames(desc.take.start_timecode, desc.fps)
        def tc(i: int) -> str:
            return frames_to_timecode(tc0 + i, desc.fps)
        msg = (f"camera {cam.id}: the take {tc(0)}-{tc(n - 1)} is out of the camera's recording "
               f"{tc(lo)}-{tc(hi)} (camera frames {lo - offset}-{hi - offset})")
        if cam.encoding is Encoding.video:
            msg += f" ({files[lo]} holds {hi - lo + 1} frames)"
        if common is not None:
            msg += (f"; the common timecode range of all cameras is {tc(common[0])}-{tc(common[1])}"
                    if common[0] <= common[1] else "; the cameras share no common timecode range")
        raise IngestError(msg)
    missing = [i for i in range(n) if i not in files]
    if missing:
        shown = ", ".join(str(i - offset) for i in missing[:10]) + (" ..." if len(missing) > 10 else "")
        raise IngestError(f"camera {cam.id}: {len(missing)} frame(s) missing in "
                          f"{files[lo].parent}: camera frame number(s) {shown}")
    outside = sum(1 for i in files if not 0 <= i < n)
    return [RawFrame(i, i - offset, files[i]) for i in range(n)], outside


#: the camera model's pixels are square (``Sensor.focal_px``); a pixel aspect ratio further than this
#: from 1 would put every projection off by that factor along x
PIXEL_ASPECT_TOLERANCE = 1e-3


def probe_source(cam: CameraSource, frame: RawFrame) -> tuple[ImageInfo, ColourSource]:
    """The header of the picture ``cam`` chooses in ``frame``'s file; errors name camera and frame."""
    try:
        return probe_footage(frame.path, cam.exr_part, cam.exr_view)
    except ImageReadError as exc:
        raise _read_error(cam, frame, exc) from exc


def _read_error(cam: CameraSource, frame: RawFrame, exc: ImageReadError) -> IngestError:
    """An imageio error as an IngestError naming camera and frame (its message names the file);
    an ambiguous file also says where the choice goes."""
    msg = f"camera {cam.id}, frame {frame.camera_frame}: {exc}"
    if isinstance(exc, SourceChoiceError):
        msg += (f". Say which picture is camera {cam.id}'s footage with \"exr_part\" (a part name) and/or "
                f"\"exr_view\" (a view name) in its capture.json entry")
    return IngestError(msg)


def _applies_primaries(cam: CameraSource, source: ColourSource) -> bool:
    """Whether the file's chromaticities are this camera's primaries: not for ``ocio`` footage (its
    colourspace names the primaries; applying both would convert twice), not for luminance-only
    pictures (Y is CIE luminance: R = G = B = Y is the same grey in any space)."""
    return cam.encoding is not Encoding.ocio and source.kind != "luminance"


def check_headers(cam: CameraSource, rig_cam: RigCamera, frames: list[RawFrame]) -> ImageInfo:
    """Every file readable, its chosen picture at the rig sensor's resolution (display window),
    with square pixels, RGB channels and convertible primaries, all frames alike; returns the
    first frame's header."""
    first: tuple[ImageInfo, ColourSource, PartHeader] | None = None
    want = (rig_cam.sensor.width_px, rig_cam.sensor.height_px)
    for f in frames:
        info, source = probe_source(cam, f)
        header = info.part_headers[source.part]
        where = f"camera {cam.id}, frame {f.camera_frame}: {f.path}"
        size = header.display_size
        if size != want:
            raise IngestError(f"{where} is {size[0]}x{size[1]} (display window {header.display_window}), "
                              f"the rig says {want[0]}x{want[1]}")
        if abs(header.pixel_aspect_ratio - 1.0) > PIXEL_ASPECT_TOLERANCE:
            raise IngestError(f"{where} has pixelAspectRatio {header.pixel_aspect_ratio:g}; the rig's cameras "
                              "have square pixels: resample the footage to square pixels first")
        if _applies_primaries(cam, source) and needs_conversion(header.chromaticities, header.adopted_neutral):
            try:
                to_working_matrix(header.chromaticities or EXR_DEFAULT_CHROMATICITIES, header.adopted_neutral)
            except ValueError as exc:
                raise IngestError(f"{where}: its colour cannot be converted to the working space: {exc}") from exc
        if first is None:
            first = (info, source, header)
            continue
        first_source, first_header = first[1], first[2]
        if source.has_alpha != first_source.has_alpha:
            raise IngestError(f"camera {cam.id}, frame {f.camera_frame}: channels {', '.join(source.channels)} "
                              f"differ from the camera's first frame ({', '.join(first_source.channels)})")
        if (header.chromaticities, header.adopted_neutral) != (first_header.chromaticities, first_header.adopted_neutral):
            raise IngestError(f"{where} declares chromaticities {_chroma_text(header)}, the camera's first "
                              f"frame {first[0].path} {_chroma_text(first_header)}")
    assert first is not None
    return first[0]


def _chroma_text(header: PartHeader) -> str:
    text = f"({header.chromaticities})" if header.chromaticities is not None else "(none: Rec.709/D65)"
    return text + (f" with adoptedNeutral {header.adopted_neutral}" if header.adopted_neutral else "")


def lens_for_take(desc: CaptureDescription, cam: CameraSource, rig_cam: RigCamera) -> tuple[LensSample, ...] | None:
    """Lens readings re-indexed to take indices; tracking cameras must cover every take frame."""
    if cam.lens_encoder is None:
        if rig_cam.role.tracks:
            raise IngestError(f"camera {cam.id}: tracking camera without lens_encoder readings")
        return None
    offset = desc.take_offset(cam)
    samples = {}
    for s in cam.lens_encoder:
        i = s.frame + offset
        if 0 <= i < desc.take.frame_count:
            samples[i] = LensSample(frame=i, focal_mm=s.focal_mm, focus_m=s.focus_m)
    missing = [i - offset for i in range(desc.take.frame_count) if i not in samples]
    if rig_cam.role.tracks and missing:
        raise IngestError(f"camera {cam.id}: lens_encoder has no reading for camera frame(s) "
                          f"{', '.join(map(str, missing[:10]))}{' ...' if len(missing) > 10 else ''}")
    return tuple(samples[i] for i in sorted(samples))


#: media type of a stored lidar scan (the PLY bytes as captured)
MEDIA_PLY = "application/x-ply"
#: fewer scan points than this cannot constrain a calibration: refused as a wrong file
MIN_LIDAR_POINTS = 100


def check_lidar(folder: CaptureFolder) -> Path | None:
    """The capture's lidar scan file, checked to be a PLY with at least ``MIN_LIDAR_POINTS`` finite
    points (and finite normals when it has them); None when the capture names no scan."""
    path = folder.lidar_path
    if path is None:
        return None
    if not path.is_file():
        raise IngestError(f"{folder.description_path}: lidar scan {path} does not exist")
    from volcap_core.calibration.lidar import decode_ply_points

    try:
        points, normals = decode_ply_points(path.read_bytes())
    except (ValueError, KeyError, IndexError, UnicodeDecodeError) as exc:
        # a truncated binary body, a header without x/y/z or a bad ASCII row all land here
        raise IngestError(f"lidar scan {path}: not a readable PLY point cloud ({type(exc).__name__}: {exc})") from exc
    if len(points) < MIN_LIDAR_POINTS:
        raise IngestError(f"lidar scan {path}: {len(points)} point(s), need at least {MIN_LIDAR_POINTS}")
    bad = ~np.isfinite(points).all(1)
    if normals is not None:
        bad |= ~np.isfinite(normals).all(1)
    if bad.any():
        raise IngestError(f"lidar scan {path}: {int(bad.sum())} point(s) hold NaN or Inf")
    return path


#: a mask value this far outside [0, 1] is refused; within it, clipped (float masks from a matting
#: tool land a rounding error past 1)
MASK_TOLERANCE = 1e-3


def select_masks(folder: CaptureFolder, cam: CameraSource) -> list[Path] | None:
    """The camera's performer mask files in take order (take index ``i`` at position ``i``), None
    when it has no masks; masks of frames outside the take are left out, a take frame without
    one is an error naming the camera and its frame numbers."""
    files = folder.mask_files(cam.id)
    if files is None:
        return None
    n = folder.frame_count
    missing = [i - folder.offsets[cam.id] for i in range(n) if i not in files]
    if missing:
        shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
        raise IngestError(f"camera {cam.id}: {len(missing)} take frame(s) without a mask in "
                          f"{folder.masks_path / cam.id}: camera frame number(s) {shown}")
    return [files[i] for i in range(n)]


def checked_mask(folder: CaptureFolder, camera_id: str, take_index: int, width: int, height: int) -> np.ndarray:
    """One performer mask decoded (:meth:`CaptureFolder.load_mask`) and checked: ``height``×``width``
    (the camera's frames), finite, within [0, 1] (:data:`MASK_TOLERANCE`). Returns it clipped to
    [0, 1], float32 ``[H, W]``; an :class:`IngestError` names the file, camera and frame."""
    m = folder.load_mask(camera_id, take_index)
    path = folder.mask_files(camera_id)[take_index]
    where = f"camera {camera_id}, frame {take_index - folder.offsets[camera_id]}: mask {path}"
    if m.shape != (height, width):
        raise IngestError(f"{where} is {m.shape[1]}x{m.shape[0]}, the camera's frames are {width}x{height}")
    finite = np.isfinite(m)
    if not finite.all():
        raise IngestError(f"{where} has {int((~finite).sum())} NaN/Inf pixel(s); a mask holds coverage in [0, 1]")
    outside = (m < -MASK_TOLERANCE) | (m > 1 + MASK_TOLERANCE)
    if outside.any():
        raise IngestError(f"{where} has {int(outside.sum())} pixel(s) outside [0, 1] (from {float(m.min()):g} to "
                          f"{float(m.max()):g}); a mask holds coverage in [0, 1]")
    return np.clip(m, 0.0, 1.0)


def check_masks(folder: CaptureFolder, cam: CameraSource, rig_cam: RigCamera) -> int:
    """Every take frame's mask of a camera decoded and checked (:func:`checked_mask`) at the rig
    sensor's resolution; the number checked (0: the camera has no masks)."""
    files = select_masks(folder, cam)
    for i in range(len(files or ())):
        checked_mask(folder, cam.id, i, rig_cam.sensor.width_px, rig_cam.sensor.height_px)
    return len(files or ())


def mask_exr(mask: np.ndarray, camera_id: str, take_index: int, source: Path) -> bytes:
    """A checked mask ``[H, W]`` as it is stored: a one-channel (``Y``) half-float EXR, ZIP
    compressed, its header naming the camera, take index and source file."""
    return encode_exr(mask[..., None], ("Y",), pixel_type="half", compression="zip",
                      attributes={"volcap.camera": camera_id, "volcap.take_index": str(take_index),
                                  "volcap.source_mask": source.name})


def fingerprint(frames: list[RawFrame]) -> list[dict]:
    """BLAKE3 of each raw file (chunked): what the conversion's cache key is made of."""
    out = []
    for f in frames:
        digest, size = digest_file(f.path)
        out.append({"take_index": f.take_index, "camera_frame": f.camera_frame, "file": str(f.path),
                    "digest": digest, "size": size})
    return out


def to_scene_linear(pixels: np.ndarray, encoding: Encoding, *, ocio_config: Path | None = None,
                    ocio_colorspace: str | None = None, where: str = "") -> np.ndarray:
    """[H, W, C] float32 as read → scene-linear float32 (alpha, channel 3, passes through)."""
    rgb = pixels[..., :3]
    if encoding is Encoding.linear:
        lin = rgb
    elif encoding is Encoding.srgb:
        lin = srgb_decode(np.ascontiguousarray(rgb))
    else:
        import PyOpenColorIO as ocio

        if ocio_config is None:
            raise IngestError(f"{where}: encoding 'ocio' but the capture has no ocio_config")
        try:
            config = ocio.Config.CreateFromFile(str(ocio_config))
            proc = config.getProcessor(ocio_colorspace, ocio.ROLE_SCENE_LINEAR).getDefaultCPUProcessor()
        except Exception as exc:  # OCIO raises its own Exception type
            raise IngestError(f"{where}: OpenColorIO cannot convert {ocio_colorspace!r} to scene-linear "
                              f"with {ocio_config}: {exc}") from exc
        lin = np.ascontiguousarray(rgb, dtype=np.float32).copy()
        proc.applyRGB(lin)
    out = np.concatenate([lin, pixels[..., 3:4]], axis=-1) if pixels.shape[-1] > 3 else lin
    return np.ascontiguousarray(out, dtype=np.float32)


def apply_nan_policy(pixels: np.ndarray, policy: NanPolicy, where: str) -> tuple[np.ndarray, int]:
    bad = ~np.isfinite(pixels)
    n = int(bad.any(axis=-1).sum())
    if not n:
        return pixels, 0
    if policy == "error":
        raise IngestError(f"{where}: {n} pixel(s) hold NaN or Inf (nan_policy 'error'; use 'repair' "
                          "to set NaN to 0 and ±Inf to ±65504)")
    return np.nan_to_num(pixels, nan=0.0, posinf=HALF_MAX, neginf=-HALF_MAX), n


def to_working_primaries(rgb: np.ndarray, header: PartHeader, where: str) -> np.ndarray:
    """Scene-linear ``[h, w, 3|4]`` float32 in the primaries ``header`` declares → the working space
    (alpha passes through); the array itself when they are the working space already.

    Values are clamped to ±65504 first: they would be when stored, and a float EXR's ±3e38 would
    overflow the matrix to ±Inf after the NaN policy has run.
    """
    if not needs_conversion(header.chromaticities, header.adopted_neutral):
        return rgb
    chroma = header.chromaticities or EXR_DEFAULT_CHROMATICITIES
    try:
        lin = convert_to_working(np.clip(rgb[..., :3], -HALF_MAX, HALF_MAX), chroma, header.adopted_neutral)
    except ValueError as exc:
        raise IngestError(f"{where}: its colour cannot be converted to the working space: {exc}") from exc
    return np.concatenate([lin, rgb[..., 3:4]], axis=-1) if rgb.shape[-1] > 3 else lin


def in_display_window(pixels: np.ndarray, data_window: tuple[int, int, int, int],
                      display_window: tuple[int, int, int, int]) -> np.ndarray:
    """The data window's visible pixels ``[h, w, C]`` (``pixels`` cropped by
    :func:`visible_pixels`) placed in a display-window-sized ``[H, W, C]`` array, 0 elsewhere
    (alpha included: outside the data window there is nothing)."""
    x0, y0, x1, y1 = display_window
    shape = (y1 - y0 + 1, x1 - x0 + 1, pixels.shape[-1])
    overlap = window_overlap(data_window, display_window)
    if overlap is not None and pixels.shape == shape:
        return pixels  # the data window covers the display window exactly: nothing to place
    out = np.zeros(shape, dtype=np.float32)
    if overlap is not None:
        out[overlap[1]] = pixels
    return out


def visible_pixels(pixels: np.ndarray, data_window: tuple[int, int, int, int],
                   display_window: tuple[int, int, int, int]) -> np.ndarray:
    """The part of the data window's pixels ``[Hd, Wd, C]`` inside the display window (a view; zero
    rows when they do not overlap): only these are converted and stored."""
    overlap = window_overlap(data_window, display_window)
    return pixels[overlap[0]] if overlap is not None else pixels[:0, :0]


def _window_text(window: tuple[int, int, int, int]) -> str:
    return " ".join(str(v) for v in window)


def source_attributes(cam: CameraSource, take_index: int, header: PartHeader,
                      source: ColourSource | None) -> dict[str, str]:
    """The stored frame's ``volcap.*`` header: camera, take index, and what the source was (encoding,
    part, view, chromaticities as declared, windows as inclusive ``xmin ymin xmax ymax``).
    ``source`` None: the file's only picture, without part name or view."""
    attrs = {"volcap.camera": cam.id, "volcap.take_index": str(take_index),
             "volcap.source_encoding": cam.encoding.value,
             "volcap.source_data_window": _window_text(header.data_window),
             "volcap.source_display_window": _window_text(header.display_window)}
    if source is not None and source.part_name is not None:
        attrs["volcap.source_part"] = source.part_name
    if source is not None and source.view is not None:
        attrs["volcap.source_view"] = source.view
    if header.chromaticities is not None:
        attrs["volcap.source_chromaticities"] = " ".join(f"{v:.6g}" for v in header.chromaticities)
    if header.adopted_neutral is not None:
        attrs["volcap.source_adopted_neutral"] = " ".join(f"{v:.6g}" for v in header.adopted_neutral)
    return attrs


def _restamped(raw: bytes, frame: RawFrame, cam: CameraSource, *, want_alpha: bool) -> bytes | None:
    """The stored frame without converting its pixels, when the source already is one: a plain
    half EXR (:func:`restamp_exr`), scene-linear (``encoding`` linear), in the working
    primaries, without NaN/Inf, with alpha exactly when the camera's frames have it. Its pixels are
    decoded once, from the restamped bytes, to prove they decode (a damaged payload is refused as
    the converting path would) and to check NaN/Inf. None: convert it (also for NaN/Inf, so the
    policy reports or repairs them in one place)."""
    if cam.encoding is not Encoding.linear or cam.exr_part is not None or cam.exr_view is not None:
        return None
    try:
        header = plain_frame_header(raw, path=str(frame.path))
        if header is None or ("A" in header.channels) != want_alpha:
            return None
        if needs_conversion(header.chromaticities, header.adopted_neutral):
            return None
        stored = restamp_exr(raw, attributes=source_attributes(cam, frame.take_index, header, None),
                             path=str(frame.path))
        pixels = decode_half_exr(stored, path=str(frame.path))
    except ImageReadError as exc:
        raise _read_error(cam, frame, exc) from exc
    if half_nonfinite_pixels(pixels):
        return None
    return stored


def convert_frame(frame: RawFrame, expected_digest: str, cam: CameraSource, *, ocio_config: Path | None,
                  nan_policy: NanPolicy, want_alpha: bool) -> tuple[bytes, int]:
    """One raw frame → (half-float scene-linear EXR bytes, repaired pixel count).

    The picture ``cam.exr_part``/``cam.exr_view`` choose, its display window (module docstring),
    its transfer function undone (``cam.encoding``), NaN/Inf under ``nan_policy``, its primaries
    converted to the working space. Refuses a file whose content changed since it was
    fingerprinted: the cache key would lie.
    """
    where = f"camera {cam.id}, frame {frame.camera_frame} ({frame.path})"
    raw = frame.path.read_bytes()  # read once: hashed, restamped, and decoded from memory
    digest = digest_bytes(raw)
    if digest != expected_digest:
        raise IngestError(f"{where}: file changed during ingest (was {expected_digest}, now {digest}); rerun")
    stored = _restamped(raw, frame, cam, want_alpha=want_alpha)
    if stored is not None:
        return stored, 0
    del raw
    try:
        footage = read_footage(frame.path, cam.exr_part, cam.exr_view)
    except ImageReadError as exc:  # its message already names the file
        raise _read_error(cam, frame, exc) from exc
    header = footage.header
    # overscan (data outside the display window) is not stored, so it is neither converted nor
    # counted by the NaN policy
    visible = visible_pixels(footage.pixels, header.data_window, header.display_window)
    repaired = 0
    if visible.size:
        lin = to_scene_linear(visible, cam.encoding, ocio_config=ocio_config,
                              ocio_colorspace=cam.ocio_colorspace, where=where)
        lin, repaired = apply_nan_policy(lin, nan_policy, where)
        if _applies_primaries(cam, footage.source):
            lin = to_working_primaries(lin, header, where)
    else:
        lin = np.ascontiguousarray(visible, dtype=np.float32)
    if want_alpha and lin.shape[-1] == 3:
        lin = np.concatenate([lin, np.ones_like(lin[..., :1])], axis=-1)
    lin = in_display_window(lin, header.data_window, header.display_window)
    channels_out = ("R", "G", "B", "A") if lin.shape[-1] == 4 else ("R", "G", "B")
    attrs = source_attributes(cam, frame.take_index, header, footage.source)
    return encode_exr(lin, channels_out, pixel_type="half", compression="zip", attributes=attrs), repaired


def raw_manifest_json(camera_id: str, entries: list[dict]) -> dict:
    return {"camera": camera_id, "frames": entries}


def parse_raw_manifest(data: bytes) -> list[dict]:
    return json.loads(data)["frames"]


def convert_camera(camera: CameraSource, rig_camera: RigCamera, entries: list[dict], take_offset: int,
                   frame_count: int, *, ocio_config: Path | None, nan_policy: NanPolicy,
                   lens: list[LensSample] | None, put_frame) -> CaptureCamera:
    """One camera's fingerprinted frames (``entries`` of :func:`parse_raw_manifest`) converted to
    scene-linear half EXR, each handed to ``put_frame(bytes) -> ArtifactRef`` as it is made (one
    frame in memory at a time); the camera's record in the capture."""
    if len(entries) != frame_count:
        raise IngestError(f"camera {camera.id}: manifest has {len(entries)} frames, take has {frame_count}")
    raws = [RawFrame(e["take_index"], e["take_index"] - take_offset, Path(e["file"])) for e in entries]
    info, source = probe_source(camera, raws[0])
    want_alpha = source.has_alpha
    frames = []
    for raw, entry in zip(raws, entries):
        data, _ = convert_frame(raw, entry["digest"], camera, ocio_config=ocio_config, nan_policy=nan_policy,
                                want_alpha=want_alpha)
        frames.append(put_frame(data))
    chroma = info.part_headers[source.part].chromaticities
    return CaptureCamera(id=camera.id, width=rig_camera.sensor.width_px, height=rig_camera.sensor.height_px,
                         channels=("R", "G", "B", "A") if want_alpha else ("R", "G", "B"),
                         source_encoding=camera.encoding, frames=tuple(frames),
                         lens_encoder=tuple(lens) if lens is not None else None,
                         source_part=source.part_name, source_view=source.view,
                         source_chromaticities=tuple(chroma) if chroma is not None else None)



#: the primaries a video's ``primaries`` names (ITU-R BT.709, BT.601 625- and 525-line, BT.2020;
#: all D65)
VIDEO_PRIMARIES: dict[str, Chromaticities] = {
    "bt709": REC709_D65,
    "bt601-625": Chromaticities(0.64, 0.33, 0.29, 0.60, 0.15, 0.06, 0.3127, 0.3290),
    "bt601-525": Chromaticities(0.630, 0.340, 0.310, 0.595, 0.155, 0.070, 0.3127, 0.3290),
    "bt2020": Chromaticities(0.708, 0.292, 0.170, 0.797, 0.131, 0.046, 0.3127, 0.3290),
}


#: relative frame-rate difference a video may have from the capture's: 30000/1001 is 0.1 % off 30
FPS_TOLERANCE = 2e-3


def check_video(cam: CameraSource, rig_cam: RigCamera, info: VideoInfo, fps: float) -> VideoEncoding:
    """A video camera's probed file against the rig and the capture: picture size the rig sensor's,
    square pixels, a frame rate within 0.2 % of the capture's (NTSC's 30000/1001 footage is a 30 fps
    capture, as its non-drop timecode counts it), colour tags it can decode (or overridden). Returns the decoding it will use (:func:`volcap_core.capture.video_encoding`)."""
    where = f"camera {cam.id}: {info.path}"
    want = (rig_cam.sensor.width_px, rig_cam.sensor.height_px)
    if (info.width, info.height) != want:
        raise IngestError(f"{where} is {info.width}x{info.height} ({info.codec}), the rig says {want[0]}x{want[1]}")
    if abs(info.sample_aspect_ratio - 1.0) > PIXEL_ASPECT_TOLERANCE:
        raise IngestError(f"{where} has sample aspect ratio {info.sample_aspect_ratio:g}; the rig's cameras have "
                          "square pixels: resample the footage to square pixels first")
    if info.fps > 0 and abs(info.fps - fps) > FPS_TOLERANCE * fps:
        raise IngestError(f"{where} runs at {info.fps:g} fps, the capture at {fps:g} fps")
    return video_encoding(cam, info)


def video_to_scene_linear(rgb: np.ndarray, encoding: VideoEncoding) -> np.ndarray:
    """Non-linear R'G'B' ``[H, W, 3]`` (nominal black 0, white 1) → scene-linear float32 in the
    working primaries: the transfer function undone (unbounded, so limited range's foot- and
    head-room survive), then the primaries converted when they are not Rec.709."""
    if encoding.transfer == "bt709":
        lin = bt709_oetf_inverse(rgb)
    elif encoding.transfer == "srgb":
        lin = srgb_decode_unbounded(rgb)
    else:
        lin = rgb
    chroma = VIDEO_PRIMARIES[encoding.primaries]
    if needs_conversion(chroma, None):
        lin = convert_to_working(np.clip(lin, -HALF_MAX, HALF_MAX), chroma, None)
    return np.ascontiguousarray(lin, dtype=np.float32)


def video_frame_attributes(cam: CameraSource, take_index: int, camera_frame: int, info: VideoInfo,
                           encoding: VideoEncoding) -> dict[str, str]:
    """The stored frame's ``volcap.*`` header for a video frame: camera, take index, the file, its
    frame number and the decoding used."""
    window = _window_text((0, 0, info.width - 1, info.height - 1))
    return {"volcap.camera": cam.id, "volcap.take_index": str(take_index),
            "volcap.source_encoding": Encoding.video.value, "volcap.source_data_window": window,
            "volcap.source_display_window": window, "volcap.source_video": info.path.name,
            "volcap.source_frame": str(camera_frame), "volcap.source_codec": f"{info.codec} {info.pix_fmt}",
            "volcap.source_transfer": encoding.transfer, "volcap.source_range": encoding.range,
            "volcap.source_matrix": encoding.matrix, "volcap.source_primaries": encoding.primaries}


def convert_video_camera(camera: CameraSource, rig_camera: RigCamera, entries: list[dict], take_offset: int,
                         frame_count: int, fps: float, *, nan_policy: NanPolicy,
                         lens: list[LensSample] | None, put_frame) -> CaptureCamera:
    """A video camera's take converted to scene-linear half EXRs, each handed to
    ``put_frame(bytes) -> ArtifactRef`` as it is decoded (one picture in memory at a time).

    ``entries``: the fingerprint manifest of the video file (one entry). Take index ``i`` is the
    video's frame ``i - take_offset``. Refuses a file whose bytes changed since it was fingerprinted
    (the cache key would lie), one that ends before the take does, and every check of
    :func:`check_video`; each error names the camera, the file and the frame."""
    if len(entries) != 1:
        raise IngestError(f"camera {camera.id}: a video camera's manifest holds one file, got {len(entries)}")
    path = Path(entries[0]["file"])
    digest, _ = digest_file(path)
    if digest != entries[0]["digest"]:
        raise IngestError(f"camera {camera.id}: {path} changed during ingest (was {entries[0]['digest']}, "
                          f"now {digest}); rerun")
    try:
        info = probe_video(path)
    except ImageReadError as exc:
        raise IngestError(f"camera {camera.id}: {exc}") from exc
    encoding = check_video(camera, rig_camera, info, fps)
    first = -take_offset
    frames = []
    try:
        for n, rgb in iter_video_frames(info, first, frame_count, signal_range=encoding.range,
                                        matrix=encoding.matrix):
            where = f"camera {camera.id}, frame {n} of {path}"
            lin, _ = apply_nan_policy(video_to_scene_linear(rgb, encoding), nan_policy, where)
            attrs = video_frame_attributes(camera, n + take_offset, n, info, encoding)
            frames.append(put_frame(encode_exr(lin, ("R", "G", "B"), pixel_type="half", compression="zip",
                                               attributes=attrs)))
    except ImageReadError as exc:
        raise IngestError(f"camera {camera.id}: {exc}") from exc
    return CaptureCamera(id=camera.id, width=info.width, height=info.height, channels=("R", "G", "B"),
                         source_encoding=Encoding.video, frames=tuple(frames),
                         lens_encoder=tuple(lens) if lens is not None else None, source_video=encoding)
