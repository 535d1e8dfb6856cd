"""Performer masks computed against background plates: what ``volcap masks`` writes into a capture
folder's masks folder (``docs/capture-layout.md``, "Performer masks"), for captures that came
without masks.

A camera's mask at a frame is where the frame differs from the camera's **background plate** (the
stage without performers, seen by the same camera), both in scene-linear light::

    r    = max over R, G, B of |frame - plate| / ((frame + plate) / 2 + DARK_FLOOR)
    mask = clip((r - LOW) / (HIGH - LOW), 0, 1)

``r`` is a relative difference (a change of 20 % on a bright wall weighs as on a dark one;
``DARK_FLOOR`` keeps sensor noise in the blacks from reading as performers), and the ramp between
``LOW`` and ``HIGH`` is the soft edge. A **shadow** the performers cast on the set differs from
the plate too, as the plate darkened with its colour kept; such a pixel (its three channels'
ratios ``frame / plate`` within ``SHADOW_CHROMA`` of their mean ``k``, ``k`` within
``SHADOW_GAIN``; the brightness and chromaticity distortions of Horprasert et al., "A statistical
approach for real-time robust background subtraction and shadow detection", 1999) is then no
performer (``drop_shadows``): on the demo capture's 8 static cameras, against clean plates, this
lifts the IoU with the ground truth from 0.82 to 0.86 (``docs/capture-layout.md``). It is off by
default: a performer in the colour of the wall behind, darker, reads as shadow too, and on Pose2Sim's
footage (the plate the median of the recording, skin in front of a beige wall) it cut 1.4-4 % of the
masks' pixels, all inside the bodies, with no cast shadow to remove.

The plate of a camera is a file the user gives (a clean plate: the empty stage, shot by that
camera), or, without one, the per-pixel median of the camera's take frames (:func:`volcap_core.calibration.photometric.background_plate`, the
calibration's own background plate: performers who move leave it). Only static cameras get
masks: a tracking camera moves, and no plate stands behind it.

How well they agree with the synthetic captures' ground-truth masks is measured in
``tests/test_masks_from_plates.py`` (figures in ``docs/capture-layout.md``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from volcap_core.capture import CaptureFolder, Encoding, IngestError, video_encoding
from volcap_core.files import write_atomic
from volcap_core.imageio.errors import ImageReadError
from volcap_core.imageio.read import read_image
from volcap_core.imageio.video import iter_video_frames
from volcap_core.imageio.write import encode_exr
from volcap_core.ingest import to_scene_linear, video_to_scene_linear

#: the relative difference (``r`` above) below which a pixel is the plate, and above which a performer
LOW, HIGH = 0.2, 0.5
#: linear light added to the mean of frame and plate before dividing: the blacks' noise floor
DARK_FLOOR = 0.02
#: a shadow's brightness, as a fraction of the plate's (lowest, highest), and the most its channels'
#: ratios to the plate may spread around their mean, as a fraction of it (module doc); measured on
#: the demo capture's shadows: brightness 0.55-0.74, spread 0.06 median, 0.15 at the 90th percentile
SHADOW_GAIN = (0.45, 0.85)
SHADOW_CHROMA = 0.10
#: the masks folder ``volcap masks`` writes when ``capture.json`` names none
DEFAULT_MASKS_FOLDER = "masks"
#: how many take frames, evenly spread, make a plate when the user gives none
MEDIAN_PLATE_FRAMES = 24


def plate_mask(frame: np.ndarray, plate: np.ndarray, *, low: float = LOW, high: float = HIGH,
               dark_floor: float = DARK_FLOOR, drop_shadows: bool = False) -> np.ndarray:
    """The performers' mask of one frame against its background plate (module doc).

    Args:
        frame, plate: ``[H, W, 3]`` scene-linear RGB of one camera.
        drop_shadows: leave what reads as the performers' shadows out of the mask (:func:`shadow`);
            False: every difference from the plate is a performer.
    Returns:
        ``[H, W]`` float32 in [0, 1].
    """
    f = np.asarray(frame, np.float32)[..., :3]
    p = np.asarray(plate, np.float32)[..., :3]
    if f.shape != p.shape:
        raise ValueError(f"frame {f.shape[1]}x{f.shape[0]} and plate {p.shape[1]}x{p.shape[0]} differ in size")
    r = (np.abs(f - p) / (0.5 * np.maximum(f + p, 0.0) + dark_floor)).max(axis=-1)
    mask = np.clip((r - low) / (high - low), 0.0, 1.0).astype(np.float32)
    if drop_shadows:
        mask[shadow(f, p)] = 0.0
    return mask


def shadow(frame: np.ndarray, plate: np.ndarray, *, gain: tuple[float, float] = SHADOW_GAIN,
           chroma: float = SHADOW_CHROMA) -> np.ndarray:
    """``[H, W]`` bool: where ``frame`` is ``plate`` darkened with its colour kept (module doc): the
    mean ``k`` of the channels' ratios ``frame / plate`` within ``gain`` and each ratio within
    ``chroma · k`` of it. Both ``[H, W, 3]`` scene-linear RGB of one camera."""
    ratio = frame / np.maximum(plate, 1e-4)
    k = ratio.mean(axis=-1)
    spread = np.abs(ratio - k[..., None]).max(axis=-1)
    return (k >= gain[0]) & (k <= gain[1]) & (spread <= chroma * k)


def linear_frames(folder: CaptureFolder, camera_id: str, take_indices: Sequence[int]) -> Iterator[tuple[int, np.ndarray]]:
    """``(take index, [H, W, 3] scene-linear RGB)`` of a camera's frames, in ascending take order:
    image files decoded and linearised by their ``encoding`` (:func:`volcap_core.ingest.to_scene_linear`),
    a video streamed once and its transfer undone (:func:`volcap_core.ingest.video_to_scene_linear`).
    Primaries are not converted: frame and plate are the same camera's."""
    cam = folder.camera(camera_id)
    wanted = sorted(set(take_indices))
    if not wanted:
        return
    if cam.is_video:
        info = folder.video_info(camera_id)
        enc = video_encoding(cam, info)
        offset = folder.offsets[camera_id]
        first = wanted[0]
        try:
            for n, rgb in iter_video_frames(info, first - offset, wanted[-1] - first + 1,
                                            signal_range=enc.range, matrix=enc.matrix):
                if n + offset in wanted:
                    yield n + offset, video_to_scene_linear(rgb, enc)
        except ImageReadError as exc:
            raise IngestError(f"camera {camera_id}: {exc}") from exc
        return
    for i in wanted:
        yield i, _linear(folder, camera_id, folder.load(camera_id, i), f"camera {camera_id}, take index {i}")


def _linear(folder: CaptureFolder, camera_id: str, pixels: np.ndarray, where: str) -> np.ndarray:
    cam = folder.camera(camera_id)
    if cam.is_video:   # a still of the video: R'G'B' after range and matrix, as its frames decode
        return video_to_scene_linear(pixels[..., :3], video_encoding(cam, folder.video_info(camera_id)))
    ocio = folder.root / folder.description.ocio_config if folder.description.ocio_config else None
    return np.asarray(to_scene_linear(pixels[..., :3], cam.encoding, ocio_config=ocio,
                                      ocio_colorspace=cam.ocio_colorspace, where=where), np.float32)


def read_plate(folder: CaptureFolder, camera_id: str, path: Path) -> np.ndarray:
    """A user's background plate of a camera: ``[H, W, 3]`` scene-linear, decoded as the camera's
    frames are (its ``encoding``; a video camera's plate is a still of its video, R'G'B' as a
    frame grabber writes it, its transfer undone as the video's). :class:`IngestError` naming the
    file and camera when it cannot be read or is not the camera's size."""
    try:
        pixels, _ = read_image(path)
    except ImageReadError as exc:
        raise IngestError(f"camera {camera_id}: background plate: {exc}") from exc
    sensor = folder.rig.camera(camera_id).sensor
    if pixels.shape[:2] != (sensor.height_px, sensor.width_px):
        raise IngestError(f"camera {camera_id}: background plate {path} is {pixels.shape[1]}x{pixels.shape[0]}, "
                          f"the camera's frames are {sensor.width_px}x{sensor.height_px}")
    if folder.camera(camera_id).encoding is Encoding.ocio and not folder.description.ocio_config:
        raise IngestError(f"camera {camera_id}: encoding 'ocio' but the capture has no ocio_config")
    return _linear(folder, camera_id, pixels, f"camera {camera_id}: background plate {path}")


def median_plate(folder: CaptureFolder, camera_id: str, frames: int = MEDIAN_PLATE_FRAMES, *,
                 whole_recording: bool = False) -> np.ndarray:
    """A camera's background plate from its own footage: the per-pixel median of ``frames`` frames
    evenly spread (the calibration's :func:`~volcap_core.calibration.photometric.background_plate`)
    over the take or, with ``whole_recording``, over a video camera's whole file (a take of a few
    frames cut from a longer recording: the performers have moved further over the whole of it).
    An image-sequence camera's frames outside the take are not listed, so it uses the take."""
    from volcap_core.calibration.photometric import background_plate

    lo, hi = 0, folder.frame_count - 1
    if whole_recording and folder.camera(camera_id).is_video:
        offset = folder.offsets[camera_id]   # take index of the video's frame 0
        lo, hi = offset, offset + folder.video_info(camera_id).frame_count - 1
    picks = np.unique(np.linspace(lo, hi, min(frames, hi - lo + 1)).round().astype(int)).tolist()
    return background_plate([rgb for _, rgb in linear_frames(folder, camera_id, picks)])


def plate_files(plates: Path, camera_ids: Sequence[str]) -> dict[str, Path]:
    """``<plates>/<camera id>.<exr|png|tif|tiff|dpx>`` of each camera that has one (one file a
    camera: two are refused)."""
    out: dict[str, Path] = {}
    if not plates.is_dir():
        raise IngestError(f"background plates: {plates} is not a folder")
    for p in sorted(plates.iterdir()):
        if p.stem in camera_ids and p.suffix.lower() in (".exr", ".png", ".tif", ".tiff", ".dpx"):
            if p.stem in out:
                raise IngestError(f"camera {p.stem}: two background plates, {out[p.stem]} and {p}")
            out[p.stem] = p
    return out


def write_plate_masks(capture_dir: str | Path, *, plates: str | Path | None = None,
                      cameras: Sequence[str] | None = None, whole_recording: bool = False,
                      drop_shadows: bool = False,
                      progress: Callable[[str, int, int], None] | None = None) -> dict[str, int]:
    """Compute every static camera's performer masks against its background plate and write them
    into the capture folder's masks folder (``capture.json``'s ``masks``; when it names none,
    ``masks/``, added to ``capture.json``): ``<masks>/<camera id>/<camera frame number>.exr``, one
    channel ``Y``, half float, a mask per take frame. Existing masks of those cameras are replaced.

    ``plates``: a folder of plates named by camera id (:func:`plate_files`); a static camera without
    one (or every camera, when None) gets the median of its take (:func:`median_plate`), or of its
    whole video with ``whole_recording``.
    ``cameras``: only these (default: every static camera). ``drop_shadows``: :func:`plate_mask`'s
    (the performers' shadows left out). Returns camera id -> masks written.
    ``progress(camera, done, total)`` after each mask."""
    folder = CaptureFolder.open(capture_dir)
    static = [c for c in folder.camera_ids if not folder.rig.camera(c).role.tracks]
    chosen = list(cameras) if cameras is not None else static
    for c in chosen:
        if c not in folder.camera_ids:
            raise IngestError(f"capture {folder.name} has no camera {c!r} (it has {', '.join(folder.camera_ids)})")
        if c not in static:
            raise IngestError(f"camera {c} is a tracking camera: it moves, so no background plate stands behind it")
    given = plate_files(Path(plates), chosen) if plates is not None else {}
    rel = folder.description.masks or DEFAULT_MASKS_FOLDER
    out_root = folder.root / rel
    written: dict[str, int] = {}
    for c in chosen:
        plate = (read_plate(folder, c, given[c]) if c in given
                 else median_plate(folder, c, whole_recording=whole_recording))
        out = out_root / c
        out.mkdir(parents=True, exist_ok=True)
        for old in out.iterdir():
            if old.is_file():
                old.unlink()
        n = folder.frame_count
        for i, rgb in linear_frames(folder, c, range(n)):
            number = i - folder.offsets[c]
            data = encode_exr(plate_mask(rgb, plate, drop_shadows=drop_shadows)[..., None], ("Y",), pixel_type="half",
                              compression="zip",
                              attributes={"volcap.camera": c, "volcap.mask_source": "plate " +
                                          (given[c].name if c in given else "median of the " +
                                           ("recording" if whole_recording else "take")) +
                                          (", shadows dropped" if drop_shadows else "")})
            write_atomic(out / f"{number:06d}.exr", data)
            if progress is not None:
                progress(c, i + 1, n)
        written[c] = n
    if folder.description.masks is None:
        doc = json.loads(folder.description_path.read_text())
        doc["masks"] = rel
        write_atomic(folder.description_path, (json.dumps(doc, indent=2) + "\n").encode())
    return written
