"""`errors_against`: a solved calibration against one the studio trusts (`volcap calibrate --against`).

A camera turned by a known angle, moved by a known distance, its focal and principal point changed,
reads back those figures beside its stated sigma; a reference of another frame size is refused by
name. Well under a second.
"""

from __future__ import annotations

import numpy as np
import pytest

from volcap_core.calibration.geometry import look_at_rotation
from volcap_core.calibration.metrics import errors_against
from volcap_core.calibration.record import Calibration, CameraCalibration, matrix4


def _camera(cid: str, centre, roll_deg: float, fx: float, size=(640, 360), cx: float = 320.0, **quality):
    R = look_at_rotation(np.asarray(centre), np.zeros(3), roll_deg)
    W = np.eye(4)
    W[:3, :3], W[:3, 3] = R, -R @ np.asarray(centre, float)
    return CameraCalibration(id=cid, role="static", static=True, width=size[0], height=size[1],
                             intrinsics=(fx, fx, cx, 180.0), world_to_camera=matrix4(W), quality=quality)


def _calibration(*cams) -> Calibration:
    return Calibration(capture="c", frame_count=1, fps=24.0, reference_frame=0, stage_size_m=(4.0, 4.0, 2.5),
                       cameras=cams)


def test_each_camera_against_the_reference_beside_its_sigma():
    reference = _calibration(_camera("A", [3.0, 0.0, 1.5], 0.0, 500.0), _camera("B", [0.0, 3.0, 1.5], 0.0, 500.0),
                             _camera("C", [-3.0, 0.0, 1.5], 0.0, 500.0))
    solved = _calibration(_camera("A", [3.0, 0.0, 1.5], 0.5, 505.0, cx=323.0, rotation_sigma_deg=0.25, focal_sigma_pct=0.5,
                                  centre_sigma_m=0.03),
                          _camera("B", [0.0, 3.02, 1.5], 0.0, 500.0))   # states no sigma; C not solved
    got = errors_against(solved, reference)
    assert sorted(got) == ["A", "B"]
    assert got["A"]["rotation_deg"] == pytest.approx(0.5, abs=1e-9)
    assert got["A"]["rotation_sigmas"] == pytest.approx(2.0) and got["A"]["centre_sigma_m"] == 0.03
    assert got["A"]["focal_pct"] == pytest.approx(1.0) and got["A"]["principal_px"] == pytest.approx(3.0)
    assert got["A"]["focal_sigma_pct"] == 0.5 and got["B"]["focal_sigma_pct"] is None
    assert got["B"]["centre_m"] == pytest.approx(0.02) and got["B"]["rotation_sigma_deg"] is None
    assert got["B"]["rotation_sigmas"] is None


def test_a_reference_of_other_frames_is_refused_by_name():
    reference = _calibration(_camera("A", [3.0, 0.0, 1.5], 0.0, 500.0, size=(1280, 720)))
    with pytest.raises(ValueError, match="camera A: calibrated at 640x360, the reference describes 1280x720"):
        errors_against(_calibration(_camera("A", [3.0, 0.0, 1.5], 0.0, 500.0)), reference)
