"""What the calibration steps read of a capture: its frames, decoded one at a time, its lidar scan,
its cameras' roles and a tracking camera's lens-encoder readings.

The steps take plain values (a frame source, the rig, camera ids), so that the tasks, which read an
ingested :class:`~volcap_core.capture.Capture` from the store, and
:func:`volcap_core.calibration.pipeline.calibrate_capture`, which is handed frames by its caller,
run the same steps. This module turns a stored capture into those values; bytes come through a
``get_bytes(ref)`` callable, never a store.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from hardware.rig import Rig
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.lidar import LidarScan
from volcap_core.capture import Capture
from volcap_core.imageio.read import decode_exr
from volcap_core.records import ArtifactRef

GetBytes = Callable[[ArtifactRef], bytes]
#: ``load(camera_id, take_index) -> float32 [H, W, 3]`` scene-linear RGB
FrameSource = Callable[[str, int], np.ndarray]
#: a tracking camera's lens-encoder readings: (take indices [S] int64, focal mm [S] float64)
EncoderReadings = tuple[np.ndarray, np.ndarray]


def split_cameras(capture_name: str, rig: Rig, camera_ids: Sequence[str]) -> tuple[list[str], list[str]]:
    """(static, tracking) ids of a capture's cameras ``camera_ids``, in their order, by the rig's roles;
    a :class:`CalibrationInputError` naming a camera the rig does not have."""
    statics, trackers = [], []
    for cid in camera_ids:
        try:
            role = rig.camera(cid).role
        except (KeyError, ValueError) as exc:
            raise CalibrationInputError(f"capture {capture_name}: camera {cid} is not in rig {rig.name}") from exc
        (trackers if role.tracks else statics).append(cid)
    return statics, trackers


def capture_cameras(cap: Capture) -> tuple[list[str], list[str]]:
    """(static, tracking) camera ids of an ingested capture (:func:`split_cameras`)."""
    return split_cameras(cap.name, cap.rig, [c.id for c in cap.cameras])


def tracking_camera_ids(cap: Capture) -> list[str]:
    """The tracking cameras of an ingested capture (:func:`split_cameras`)."""
    return capture_cameras(cap)[1]


def frame_loader(get_bytes: GetBytes, cap: Capture) -> FrameSource:
    """``load(camera_id, take_index) -> float32 [H, W, 3]`` decoding the capture's ingested EXRs."""

    def load(camera_id: str, take_index: int) -> np.ndarray:
        cam = cap.camera(camera_id)
        if not 0 <= take_index < len(cam.frames):
            raise CalibrationInputError(f"capture {cap.name}, camera {camera_id}: no frame {take_index} "
                                        f"(take has {len(cam.frames)})")
        ref = cam.frames[take_index]
        pixels, _ = decode_exr(get_bytes(ref), name=f"{cap.name}/{camera_id}/{take_index} ({ref.digest})")
        return np.ascontiguousarray(pixels[..., :3], dtype=np.float32)

    return load


def load_lidar(get_bytes: GetBytes, cap: Capture) -> LidarScan | None:
    """The capture's lidar scan (an input, like the frames), None when it has none."""
    if cap.lidar is None:
        return None
    try:
        return LidarScan.from_ply_bytes(get_bytes(cap.lidar))
    except (ValueError, KeyError, IndexError) as exc:
        raise CalibrationInputError(f"capture {cap.name}: lidar scan {cap.lidar.digest} is not a readable PLY: "
                                    f"{exc}") from exc


def lens_encoder(cap: Capture, camera: str) -> EncoderReadings | None:
    """Camera ``camera``'s lens-encoder readings (take indices, as ingested), None when it has none;
    a :class:`CalibrationInputError` when the capture has no such camera."""
    ids = [c.id for c in cap.cameras]
    if camera not in ids:
        raise CalibrationInputError(f"capture {cap.name} has no camera {camera!r} (it has {', '.join(ids)})")
    lens = cap.camera(camera).lens_encoder
    if not lens:
        return None
    return np.array([r.frame for r in lens], np.int64), np.array([r.focal_mm for r in lens], np.float64)
