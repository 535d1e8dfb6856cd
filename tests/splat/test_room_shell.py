"""The room shell that stands in for a lidar scan on real footage (``splat.init.room_shell``;
docs/poly4dgs.md, "Real footage"): a box whose floor is the stage frame's z = 0 and whose walls and
ceiling stand beyond the stage and every camera, so each camera sees it in every direction it
looks (a camera inside it never looks past it). <1 s."""

from __future__ import annotations

import numpy as np

from volcap_core.splat.camera import look_at
from volcap_core.splat.init import room_shell
from volcap_core.stage import stage_volume


def _cameras():
    a = np.radians([0, 100, 200, 290])
    return np.stack([3.5 * np.cos(a), 3.5 * np.sin(a), np.full(4, 1.9)], 1)


def test_the_shell_encloses_the_stage_and_the_cameras_with_its_floor_at_zero():
    centres = _cameras()
    stage = stage_volume((4.0, 4.0, 2.5))
    pts = room_shell(centres, stage, margin_m=1.0, spacing_m=0.1)
    lo, hi = pts.min(0), pts.max(0)
    assert lo[2] == 0.0                                       # the floor is the stage's
    np.testing.assert_allclose(lo[:2], centres[:, :2].min(0) - 1.0)   # walls a margin beyond the cameras
    np.testing.assert_allclose(hi[:2], np.maximum(centres[:, :2].max(0), 2.0) + 1.0)
    assert hi[2] == 2.5 + 1.0                                 # the ceiling above the stage's top
    # every point on one of the six faces, none inside
    on_face = np.isclose(pts, lo).any(1) | np.isclose(pts, hi).any(1)
    assert on_face.all()
    floor = pts[pts[:, 2] == 0.0]
    step = np.diff(np.unique(floor[:, 0]))
    assert step.max() <= 0.1 + 1e-9                            # no gap wider than the spacing


def test_every_camera_sees_the_shell_in_all_its_pixels():
    """A camera inside the shell, looking anywhere, finds shell points over its whole frame: the
    initial model can cover the view (before: the sweep's points alone, 5-8 % of the pixels on
    Pose2Sim)."""
    centres = _cameras()
    pts = room_shell(centres, stage_volume((4.0, 4.0, 2.5)), spacing_m=0.05)
    for C in centres:
        for target in ((0.0, 0.0, 0.8), (C[0] * 2, C[1] * 2, 3.0)):     # at the stage, and away at the wall
            cam = look_at(C, target, fov_x_deg=60.0, width=16, height=12)
            K = cam.K.double().numpy()
            W = cam.world_to_camera.double().numpy()
            pc = pts @ W[:3, :3].T + W[:3, 3]
            pc = pc[pc[:, 2] > 0.1]                                   # in front of the camera
            uv = np.floor(pc[:, :2] / pc[:, 2:] @ K[:2, :2].T + K[:2, 2]).astype(int)
            covered = np.zeros((12, 16), bool)
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < 16) & (uv[:, 1] >= 0) & (uv[:, 1] < 12)
            covered[uv[ok, 1], uv[ok, 0]] = True
            assert covered.mean() > 0.99, (C, target, covered.mean())
