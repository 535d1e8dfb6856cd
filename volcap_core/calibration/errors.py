"""The calibration's errors, in one place so that every module of the package (and the flows and
the CLI that report them) can raise or catch them without importing the steps that raise them.

:class:`CalibrationInputError` is what a user sees: input that cannot be calibrated, the message
naming the capture, camera and frame. The others are the library's own refusals, which the steps
turn into a :class:`CalibrationInputError` naming the capture.
"""

from __future__ import annotations

from typing import Mapping


class CalibrationInputError(ValueError):
    """Bad calibration input; the message names the capture, camera and frame concerned."""


class UnsupportedCameraError(RuntimeError):
    """Static cameras the adjustment cannot support (``reasons``: camera id -> why), raised unless
    ``StaticCalibrationOptions.allow_unregistered``."""

    def __init__(self, reasons: Mapping[str, str]):
        self.reasons = dict(reasons)
        super().__init__("; ".join(f"{c}: {r}" for c, r in sorted(self.reasons.items())))


class KnownDistanceError(ValueError):
    """``StaticCalibrationOptions.known_distance`` names a camera that is not calibrated, or a
    distance that is not positive."""


class KnownPointsError(ValueError):
    """Known scene points that cannot give a scale; the message names the point and the camera."""
