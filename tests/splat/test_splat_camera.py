"""The splat renderer's ``look_at`` camera: the library's one look-at rotation, plus intrinsics."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from volcap_core.calibration.geometry import look_at_rotation, pose_matrix
from volcap_core.splat.camera import look_at


@pytest.mark.parametrize("eye, target, up", [
    ((0.3, -2.5, 0.4), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ((1.0, 2.0, 3.0), (-0.5, 0.1, 0.2), (0.2, 1.0, 0.3)),
    ((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),  # straight down: the fallback, no error
])
def test_look_at_camera_is_the_shared_rotation_with_centred_intrinsics(eye, target, up):
    cam = look_at(eye, target, up, fov_x_deg=60.0, width=40, height=30)
    R = look_at_rotation(eye, target, up=up)
    expected = torch.as_tensor(pose_matrix(R, -R @ np.asarray(eye)), dtype=torch.float32)
    assert torch.equal(cam.world_to_camera, expected)
    f = 20.0 / np.tan(np.radians(30.0))
    np.testing.assert_allclose(cam.K.numpy(), [[f, 0, 20.0], [0, f, 15.0], [0, 0, 1]], rtol=1e-6)
    # the target is on the optical axis, in front of the camera
    p = cam.world_to_camera.double() @ torch.tensor([*target, 1.0], dtype=torch.float64)
    assert abs(p[0]) < 1e-6 and abs(p[1]) < 1e-6 and p[2] > 0
