"""One frame's dense points: the ``dense-points-frame`` task's step and its record.

:func:`dense_points_step` sweeps and fuses a frame over the calibration's static cameras (the
library: :mod:`volcap_core.calibration.dense`); :class:`DensePointsFrame` carries the result to
the ``point-cloud-sequence`` task, which thins each frame to a budget with :func:`thin_points`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from volcap_core.calibration.dense import DenseOptions, dense_points, sweep_range
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


def dense_points_step(cap: Capture, calib: Calibration, frame: int, load: FrameSource,
                      options: DenseOptions = DenseOptions(), scale: float = 1.0,
                      exclude_cameras: Sequence[str] = ()) -> DenseFrame:
    """One frame's dense points: a plane sweep per calibrated static camera, fused by cross-view
    consistency (``volcap_core.calibration.dense``), colours linear. ``exclude_cameras`` (a
    reconstruction's held-out cameras) take no part: points seen or coloured by a camera would
    leak its footage into the model it is meant to test. ``scale`` < 1 matches downscaled images
    (a quarter of the work at 0.5): previews and tests. A distorted camera's frame is rectified
    first (:func:`~volcap_core.calibration.distortion.rectify_frame`: the pinhole of its record's
    K) and its pixels outside the source take no part."""
    if not 0 <= frame < cap.frame_count:
        raise CalibrationInputError(f"capture {cap.name}: frame {frame} outside the take [0, {cap.frame_count})")
    if calib.capture != cap.name:
        raise CalibrationInputError(f"calibration of capture {calib.capture} given for capture {cap.name}")
    if not 0 < scale <= 1:
        raise CalibrationInputError(f"dense points: scale must be in (0, 1], got {scale}")
    # Static cameras only: the zoomed tracking views see the scene 5-7x larger, which the
    # fixed-size NCC windows of the sweep do not match across.
    present, excluded = {c.id for c in cap.cameras}, set(exclude_cameras)
    ids = [c for c in calib.static_ids if c in present and c not in excluded]
    if len(ids) < 2:
        raise CalibrationInputError(f"capture {cap.name}, frame {frame}: dense points need two calibrated static "
                                    f"cameras, the calibration has {len(ids)}")
    # a distorted camera's frame is resampled into the pinhole of its record's K (rectify_frame)
    images = {c: rectify_frame(load(c, frame), calib.camera(c)) for c in ids}
    cams = {c: camera_at(calib, c, frame)[:2] for c in ids}
    # DenseOptions.scale is the library's downscale *factor* (2 = half size), hence the division.
    valid = {c: rectified_valid(calib.camera(c)) for c in ids}
    # each camera sweeps around the static scene it saw at calibration (a stage of any size); a
    # calibration recorded before scene depths were takes DenseOptions' fixed range
    sweeps = {c: sweep_range(calib.camera(c).scene_depth_m) for c in ids if calib.camera(c).scene_depth_m}
    out = dense_points(images, cams, options=replace(options, scale=options.scale / scale), valid=valid,
                       sweeps=sweeps)
    if len(out["positions"]) == 0:
        log.warning("capture %s, frame %d: no dense point passed the consistency check", cap.name, frame)
    return DenseFrame(out["positions"], out["colours"], ids, float(out["seconds"]))


def thin_points(xyz: np.ndarray, rgb: np.ndarray, budget: int, seed: int, frame: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """At most ``budget`` of a frame's points, uniformly (seeded by ``seed`` and the frame), in order."""
    if len(xyz) <= budget:
        return xyz, rgb
    keep = np.sort(np.random.default_rng([seed, frame]).choice(len(xyz), budget, replace=False))
    return xyz[keep], rgb[keep]
