"""A rig from a calibration a studio trusts: its lenses as measured intrinsics, its poses as mounts.

A studio whose cameras are calibrated already (a Qualisys, COLMAP or OpenCV file, imported as a
Calibration record by :mod:`volcap_core.calibration.importers`) should not have to type a rig to
ingest its footage. :func:`rig_from_calibration` writes one from the record:

- each camera's sensor at its frames' size (the record's ``width`` x ``height``, after any fit to
  resampled frames), square pixels, its longer side ``sensor_long_side_mm`` (a calibration in
  pixels says nothing of millimetres: the sensor size only sets the millimetre figures, the focal in
  pixels is the measured one);
- its lens calibration (``intrinsics`` and OpenCV ``distortion``) as the camera's measured
  intrinsics, so the static step holds it as a lens calibration (docs/calibration.md);
- a fixed lens at its measured focal (``nominal_focal_mm``, the lens range that focal);
- its pose as its mount: ``position_m`` the optical centre, ``look_at_m`` one metre along its optical
  axis, ``roll_deg`` the roll about that axis that gives the pose's rotation (:func:`mount_roll`), so
  that the mount's nominal pose is the imported pose (to ~1e-6°);
- the stage size the record states (an importer's default: the cameras' extent).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from hardware.rig import Rig
from volcap_core.calibration.geometry import camera_centre, look_at_rotation, rotation_angle_deg
from volcap_core.calibration.record import Calibration

#: the longer side of the sensor a rig written from a calibration states (mm): a full-frame sensor's;
#: only the millimetre figures (nominal focal, lens range) depend on it
SENSOR_LONG_SIDE_MM = 36.0


def mount_roll(R: np.ndarray, position: np.ndarray, target: np.ndarray) -> float:
    """The mount roll (degrees) whose look-at rotation from ``position`` towards ``target`` is the
    world-to-camera rotation ``R`` [3, 3] (OpenCV axes), ``target`` on ``R``'s optical axis."""
    Rr = R @ look_at_rotation(position, target, 0.0).T
    a = float(np.degrees(np.arctan2(Rr[1, 0], Rr[0, 0])))
    return min((a, -a), key=lambda r: rotation_angle_deg(look_at_rotation(position, target, r), R))


def rig_from_calibration(calibration: Calibration, *, name: str | None = None, fps: float | None = None,
                         sensor_long_side_mm: float = SENSOR_LONG_SIDE_MM,
                         stage_size_m: Sequence[float] | None = None, lighting: str | None = None) -> Rig:
    """The rig of ``calibration``'s cameras (module docstring): every camera static, measured
    intrinsics its lens calibration, mount its pose. ``name`` (default: the calibration's capture),
    ``fps`` (default: the calibration's), ``stage_size_m`` (default: the calibration's),
    ``lighting`` a description (default: "not stated").

    Raises ValueError naming the camera when one has no pose or intrinsics in the record (a
    tracking camera, whose lens and pose change per frame), and the rig's own validation errors (a
    principal point outside the frame)."""
    cams = []
    for c in calibration.cameras:
        if c.intrinsics is None or c.world_to_camera is None:
            raise ValueError(f"calibration of {calibration.capture}: camera {c.id} has no fixed pose and intrinsics "
                             f"(a {c.role} camera): a rig from a calibration takes static cameras only")
        W = np.asarray(c.world_to_camera, np.float64)
        C = camera_centre(W)
        target = C + W[2, :3]
        fx, fy, cx, cy = c.intrinsics
        pitch_mm = sensor_long_side_mm / max(c.width, c.height)
        focal_mm = fx * pitch_mm
        cams.append({"id": c.id, "role": "static", "lens": {"focal_min_mm": focal_mm, "focal_max_mm": focal_mm},
                     "sensor": {"width_mm": pitch_mm * c.width, "height_mm": pitch_mm * c.height,
                                "width_px": c.width, "height_px": c.height},
                     "mount": {"kind": "tripod", "position_m": C.tolist(), "look_at_m": target.tolist(),
                               "roll_deg": mount_roll(W[:3, :3], C, target)},
                     "nominal_focal_mm": focal_mm,
                     "intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "opencv": list(c.distortion)}})
    return Rig.model_validate({
        "name": name or calibration.capture, "kind": "scene", "fps": fps or calibration.fps,
        "stage_size_m": list(stage_size_m if stage_size_m is not None else calibration.stage_size_m),
        "cameras": cams,
        "lighting": {"description": lighting or f"not stated (rig written from a calibration of {calibration.capture})"}})
