"""One frame's dense points: the ``dense-points-frame`` task's step and its record.

:func:`dense_points_step` sweeps and fuses a frame over the calibration's static cameras (the
library: :mod:`volcap_core.calibration.dense`); :class:`DensePointsFrame` carries the result to
the ``point-cloud-sequence`` task, which thins each frame to a budget with :func:`thin_points`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from volcap_core.calibration.dense import DenseOptions, DenseProgress, dense_points, sweep_range
from volcap_core.calibration.distortion import rectified_valid, rectify_frame
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.inputs import FrameSource
from volcap_core.calibration.record import Calibration, camera_at
from volcap_core.capture import Capture
from volcap_core.records import ArtifactRef, Record

log = logging.getLogger("volcap.calibrate")


class DensePointsFrame(Record):
    """One frame's dense points (``points``: safetensors ``xyz``, ``rgb`` as in
    :mod:`volcap_core.pointcloud`), fused from the calibration's static cameras."""

    kind: ClassVar[str] = "dense-points-frame"
    calibration: ArtifactRef
    frame: int
    time: float
    count: int
    points: ArtifactRef
    cameras: tuple[str, ...]
    seconds: float


@dataclass
class DenseFrame:
    positions: np.ndarray   # [N, 3] float32, metres, stage frame
    colours: np.ndarray     # [N, 3] float32, linear
    cameras: list[str]
    seconds: float


class _RectifiedFrames(Mapping):
    """A frame's rectified images by camera id, loaded on each access and not kept: the sweep
    reads each camera twice (its matching images, its colours), so one full image at a time is
    in memory instead of every view."""

    def __init__(self, calib: Calibration, ids: Sequence[str], frame: int, load: FrameSource):
        self.calib, self.ids, self.frame, self.load = calib, list(ids), frame, load

    def __getitem__(self, cid: str) -> np.ndarray:
        if cid not in self.ids:
            raise KeyError(cid)
        return rectify_frame(self.load(cid, self.frame), self.calib.camera(cid))

    def __iter__(self):
        return iter(self.ids)

    def __len__(self) -> int:
        return len(self.ids)


def stage_sweeps(calib: Calibration, ids: Sequence[str], frame: int) -> dict[str, tuple[float, float, float]]:
    """Each camera's sweep ``(nearest, neighbours', farthest)`` (metres, :func:`sweep_range`) over
    the rig's performance volume in its view (``stage_volume(calib.stage_size_m)`` sampled on a
    25 x 25 x 11 grid, the points in its image at least the rig's camera spacing away), as the
    static step measures it (``static.scene_depths``) for a calibration without its sparse points
    (imported, ground truth). A camera that sees none of the volume is left out."""
    from volcap_core.calibration.geometry import camera_gaps, depths_in_view
    from volcap_core.stage import stage_volume

    (x0, y0, z0), (x1, y1, z1) = stage_volume(calib.stage_size_m, floor_clearance_m=0.0)
    grid = np.stack(np.meshgrid(np.linspace(x0, x1, 25), np.linspace(y0, y1, 25), np.linspace(z0, z1, 11),
                                indexing="ij"), -1).reshape(-1, 3)
    cams = {c: camera_at(calib, c, frame)[:2] for c in ids}
    _, spacing = camera_gaps([cams[c][1] for c in ids])
    out = {}
    for c in ids:
        cam = calib.camera(c)
        z = depths_in_view(grid, cams[c][0], cams[c][1], (cam.width, cam.height))
        z = z[z >= spacing]
        if len(z):
            out[c] = sweep_range((float(z.min()), float(np.median(z)), float(z.max())))
    return out


def dense_points_step(cap: Capture, calib: Calibration, frame: int, load: FrameSource,
                      options: DenseOptions = DenseOptions(), scale: float = 1.0,
                      exclude_cameras: Sequence[str] = (), references: Sequence[str] | None = None,
                      progress: DenseProgress | None = None) -> DenseFrame:
    """One frame's dense points: a plane sweep per calibrated static camera, fused by cross-view
    consistency (``volcap_core.calibration.dense``), colours linear. ``exclude_cameras`` (a
    reconstruction's held-out cameras) take no part: points seen or coloured by a camera would
    leak its footage into the model it is meant to test. ``scale`` < 1 matches downscaled images
    (a quarter of the work at 0.5): previews and tests. A distorted camera's frame is rectified
    first (:func:`~volcap_core.calibration.distortion.rectify_frame`: the pinhole of its record's
    K) and its pixels outside the source take no part. Frames are loaded when the sweep reads
    them, never all at once. Each camera sweeps around the scene it saw at calibration
    (``scene_depth_m``) or, without one (an imported or ground-truth calibration), the stage
    volume in its view (:func:`stage_sweeps`). ``references``: the cameras swept (default: all;
    benchmarks); ``progress``: called after each camera's depth map
    (:data:`~volcap_core.calibration.dense.DenseProgress`)."""
    if not 0 <= frame < cap.frame_count:
        raise CalibrationInputError(f"capture {cap.name}: frame {frame} outside the take [0, {cap.frame_count})")
    if calib.capture != cap.name:
        raise CalibrationInputError(f"calibration of capture {calib.capture} given for capture {cap.name}")
    if not 0 < scale <= 1:
        raise CalibrationInputError(f"dense points: scale must be in (0, 1], got {scale}")
    ids = dense_cameras(cap, calib, exclude_cameras)
    if len(ids) < 2:
        raise CalibrationInputError(f"capture {cap.name}, frame {frame}: dense points need two calibrated static "
                                    f"cameras, the calibration has {len(ids)}")
    unknown = sorted(set(references or ()) - set(ids))
    if unknown:
        raise CalibrationInputError(f"capture {cap.name}, frame {frame}: dense points: reference camera(s) "
                                    f"{', '.join(unknown)} are not among the calibrated static cameras {', '.join(ids)}")
    # a distorted camera's frame is resampled into the pinhole of its record's K (rectify_frame)
    images = _RectifiedFrames(calib, ids, frame, load)
    cams = {c: camera_at(calib, c, frame)[:2] for c in ids}
    # DenseOptions.scale is the library's downscale *factor* (2 = half size), hence the division.
    valid = {c: rectified_valid(calib.camera(c)) for c in ids}
    # each camera sweeps around the static scene it saw at calibration (a stage of any size); a
    # calibration without scene depths sweeps the stage volume in each camera's view
    sweeps = {c: sweep_range(calib.camera(c).scene_depth_m) for c in ids if calib.camera(c).scene_depth_m}
    missing = [c for c in ids if c not in sweeps]
    if missing:
        sweeps.update(stage_sweeps(calib, missing, frame))
    out = dense_points(images, cams, options=replace(options, scale=options.scale / scale), valid=valid,
                       sweeps=sweeps, references=list(references) if references else None, progress=progress)
    if len(out["positions"]) == 0:
        log.warning("capture %s, frame %d: no dense point passed the consistency check", cap.name, frame)
    return DenseFrame(out["positions"], out["colours"], ids, float(out["seconds"]))


def dense_cameras(cap: Capture, calib: Calibration, exclude_cameras: Sequence[str] = ()) -> list[str]:
    """The cameras a frame's dense points are made from: the calibration's static cameras present
    in the capture but ``exclude_cameras``. Static only: the zoomed tracking views see the scene
    5-7x larger, which the fixed-size NCC windows of the sweep do not match across."""
    present, excluded = {c.id for c in cap.cameras}, set(exclude_cameras)
    return [c for c in calib.static_ids if c in present and c not in excluded]


def thin_points(xyz: np.ndarray, rgb: np.ndarray, budget: int, seed: int, frame: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """At most ``budget`` of a frame's points, uniformly (seeded by ``seed`` and the frame), in order."""
    if len(xyz) <= budget:
        return xyz, rgb
    keep = np.sort(np.random.default_rng([seed, frame]).choice(len(xyz), budget, replace=False))
    return xyz[keep], rgb[keep]
