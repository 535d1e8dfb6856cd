"""One tracking camera of a capture: the ``calibrate-tracking-camera`` task's step and its record.

:func:`calibrate_tracking_step` registers and refines one tracking camera over the take against
the static reference of the static step; :func:`tracking_record` / :func:`tracking_solution`
carry its result between tasks as a :class:`TrackingCameraRecord` and its frames blob
(:func:`encode_tracking_solution`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np
from pydantic import Field
from safetensors.numpy import load as st_load
from safetensors.numpy import save as st_save

from hardware.rig import Rig
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.inputs import EncoderReadings, FrameSource
from volcap_core.calibration.record import finite_figures
from volcap_core.calibration.tracking.calibrate import calibrate_tracking_cameras
from volcap_core.calibration.tracking.lens import zoom_lens
from volcap_core.calibration.tracking.observe import StaticReference
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.calibration.tracking.solve import TrackingSolution, tracking_support
from volcap_core.records import ArtifactRef, Record


class TrackingCameraRecord(Record):
    """One tracking camera over the take: ``frames`` is safetensors ``K`` [T, 3, 3] and
    ``world_to_camera`` [T, 4, 4] float64; ``gain`` / ``offset`` the fitted encoder correction."""

    kind: ClassVar[str] = "tracking-camera-calibration"
    capture: str
    camera: str
    frames: ArtifactRef
    gain: float
    offset: float
    centre: tuple[float, float, float]
    stats: dict[str, float] = Field(default_factory=dict)
    #: why the camera is left out of the calibration (``TrackingOptions.allow_unsupported``), None
    #: when it is calibrated
    unsupported: str | None = None


class LazyFrames(Sequence):
    """A camera's frames over the take, decoded when read (the library iterates them once)."""

    def __init__(self, load: FrameSource, camera_id: str, count: int):
        self._load, self._id, self._n = load, camera_id, count

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(self._n))]
        if not -self._n <= i < self._n:
            raise IndexError(i)
        return self._load(self._id, i % self._n)


def calibrate_tracking_step(cap_name: str, rig: Rig, camera: str, encoder: EncoderReadings | None,
                            frame_count: int, load: FrameSource, reference: StaticReference | None,
                            options: TrackingOptions = TrackingOptions()) -> TrackingSolution:
    """One tracking camera at every frame of the take, against the fixed static reference, checked
    by :func:`check_tracking_support`.

    ``encoder``: the camera's lens-encoder readings (take indices [S], focal mm [S]); ``load``: its
    frames, read once each as their features are extracted; ``reference``: the static step's
    (:attr:`~volcap_core.calibration.static_step.StaticStep.reference`). The library refines each
    camera's sequence on its own (its normal equations are per camera), so one camera per call gives
    what a batched call gives, but for the batch's shared stopping rule (docs/calibration.md,
    "Tasks"). Refuses (:class:`CalibrationInputError`, naming the capture and camera) a camera the
    rig does not have or does not list as a tracking camera, one without encoder readings, a static
    step without a reference, and too few 2D-3D matches over the take."""
    try:
        rig_cam = rig.camera(camera)
    except (KeyError, ValueError) as exc:
        raise CalibrationInputError(f"capture {cap_name}: camera {camera} is not in rig {rig.name}") from exc
    if not rig_cam.role.tracks:
        raise CalibrationInputError(f"capture {cap_name}: camera {camera} is a {rig_cam.role.value} camera, "
                                    "not a tracking camera")
    if encoder is None or len(encoder[0]) == 0:
        raise CalibrationInputError(f"capture {cap_name}: tracking camera {camera} has no lens-encoder readings")
    if reference is None:
        raise CalibrationInputError(f"capture {cap_name}: the static calibration holds no static reference (it "
                                    "was made for a capture without tracking cameras)")
    frames = LazyFrames(load, camera, frame_count)
    ppm = rig_cam.sensor.width_px / rig_cam.sensor.width_mm
    try:
        # a zoom lens table in the rig: each frame is undistorted with the lens at its focal
        sols = calibrate_tracking_cameras({camera: frames}, {camera: encoder}, {camera: ppm},
                                          {camera: np.asarray(rig_cam.mount.position_m, np.float64)}, reference,
                                          options, lenses={camera: zoom_lens(rig.zoom_intrinsics(camera))})
    except RuntimeError as exc:  # e.g. too few 2D-3D matches over the take
        raise CalibrationInputError(f"capture {cap_name}, tracking camera {camera}: {exc}") from exc
    return check_tracking_support(cap_name, camera, sols[camera], options)


def check_tracking_support(capture_name: str, camera: str, sol: TrackingSolution,
                           options: TrackingOptions = TrackingOptions()) -> TrackingSolution:
    """``sol`` when the camera is supported (:func:`~volcap_core.calibration.tracking.solve.tracking_support`);
    otherwise an error naming the capture, the camera and the reason, or, with
    ``options.allow_unsupported``, ``sol`` marked ``unsupported`` (the calibration leaves it out and
    lists it). The one check of :func:`calibrate_tracking_step`."""
    why = tracking_support(sol, options)
    if why is None:
        return sol
    if not options.allow_unsupported:
        raise CalibrationInputError(
            f"capture {capture_name}: tracking camera {camera} cannot be calibrated: {why}; check its footage, "
            "encoder and mount, or allow it to be left out with --allow-unregistered "
            "(TrackingOptions.allow_unsupported)")
    sol.unsupported = why
    return sol


def encode_tracking_solution(sol: TrackingSolution) -> bytes:
    """Safetensors ``K`` [T, 3, 3] and ``world_to_camera`` [T, 4, 4] float64 of one camera, and its
    ``distortion`` [T, 5|8] (each frame's lens) when its frames were undistorted."""
    arrays = {"K": np.ascontiguousarray(sol.K, np.float64),
              "world_to_camera": np.ascontiguousarray(sol.world_to_camera, np.float64)}
    if sol.distortion is not None:
        arrays["distortion"] = np.ascontiguousarray(sol.distortion, np.float64)
    return st_save(arrays)


def tracking_record(cap_name: str, camera: str, sol: TrackingSolution, frames: ArtifactRef) -> TrackingCameraRecord:
    """The record of one tracking camera; ``frames``: the stored :func:`encode_tracking_solution`."""
    return TrackingCameraRecord(capture=cap_name, camera=camera, frames=frames, gain=float(sol.gain),
                                offset=float(sol.offset), centre=tuple(float(v) for v in sol.centre),
                                stats=finite_figures(sol.stats), unsupported=sol.unsupported)


def tracking_solution(rec: TrackingCameraRecord, frames: bytes) -> TrackingSolution:
    """The library's TrackingSolution from a stored record and its frames blob."""
    arr = st_load(frames)
    return TrackingSolution(arr["K"], arr["world_to_camera"], rec.gain, rec.offset,
                            np.asarray(rec.centre, np.float64), dict(rec.stats), arr.get("distortion"),
                            rec.unsupported)
