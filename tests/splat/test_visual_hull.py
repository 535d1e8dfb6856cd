"""The performers' visual hull from their masks (``splat.init.visual_hull``; docs/poly4dgs.md, "Real
footage"), and the masks' hole filling it is built from (``splat.init.filled_silhouette``). A sphere seen by
four cameras: the hull's surface holds the sphere (no point inside it), stays within the masks of
every camera, and fills each camera's mask when drawn back. ~10 s at load 15-20 (6 s the sphere)."""

from __future__ import annotations

import numpy as np

from volcap_core.splat.camera import look_at
from volcap_core.splat.init import filled_silhouette, visual_hull

CENTRE, RADIUS = np.array([0.2, -0.1, 1.0]), 0.3
#: the volume carved: around the sphere (the stage volume in use; a small one keeps the test fast)
VOLUME = ((-0.4, -0.7, 0.4), (0.8, 0.5, 1.6))
W_PX, H_PX = 96, 72


def _camera(angle_deg: float):
    a = np.radians(angle_deg)
    cam = look_at((3.0 * np.cos(a), 3.0 * np.sin(a), 1.8), tuple(CENTRE), fov_x_deg=40.0, width=W_PX, height=H_PX)
    K = cam.K.double().numpy().copy()
    K[:2, 2] -= 0.5          # OpenCV pixel centres at integers, as visual_hull takes them
    return K, cam.world_to_camera.double().numpy()


def _sphere_mask(K, W):
    """The sphere's exact silhouette: pixels whose ray passes within RADIUS of the centre."""
    R, t = W[:3, :3], W[:3, 3]
    C = -R.T @ t
    u, v = np.meshgrid(np.arange(W_PX), np.arange(H_PX))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1) @ R
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    d = CENTRE - C
    miss = np.linalg.norm(d - (rays @ d)[..., None] * rays, axis=-1)
    return (miss <= RADIUS).astype(np.float32)


def _project(K, W, xyz):
    pc = xyz @ W[:3, :3].T + W[:3, 3]
    return np.round(pc[:, :2] / pc[:, 2:] @ K[:2, :2].T + K[:2, 2]).astype(int)


def test_the_hull_of_a_sphere_holds_it_and_matches_every_silhouette():
    cams = [(*_camera(a), None) for a in (0, 70, 160, 250)]
    cams = [(K, W, _sphere_mask(K, W)) for K, W, _ in cams]
    pts = visual_hull(cams, VOLUME, spacing_m=0.02)
    assert len(pts) > 500
    dist = np.linalg.norm(pts - CENTRE, axis=1)
    assert dist.min() >= RADIUS - 0.035           # holds the sphere (less a pixel's rounding at 3 m)
    assert dist.max() <= RADIUS * 1.6             # four views carve close to it
    for K, W, mask in cams:
        uv = _project(K, W, pts)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W_PX) & (uv[:, 1] >= 0) & (uv[:, 1] < H_PX)
        assert inside.all()
        assert mask[uv[:, 1], uv[:, 0]].mean() > 0.97          # within each silhouette (rounding at its edge)
        drawn = np.zeros_like(mask, bool)
        drawn[uv[:, 1], uv[:, 0]] = True
        assert (drawn & (mask > 0)).sum() / (mask > 0).sum() > 0.9   # and filling it


def test_a_camera_alone_pins_no_depth():
    """What only one camera sees (its silhouette's cone) is not a hull: min_views=2 drops it."""
    K, W = _camera(0)
    assert len(visual_hull([(K, W, _sphere_mask(K, W))], VOLUME, spacing_m=0.05)) == 0


def test_filled_closes_a_silhouette_with_a_hole_and_keeps_its_soft_edge():
    y, x = np.mgrid[:60, :60]
    r = np.hypot(x - 30, y - 30)
    ring = ((r >= 8) & (r <= 20)).astype(np.float32)      # a torso whose middle matched the plate
    ring[(r > 20) & (r <= 21)] = 0.3                       # the soft edge outside
    out = filled_silhouette(ring, close_px=2)
    assert out[30, 30] == 1.0 and (out[r < 8] == 1.0).all()
    assert np.allclose(out[(r > 20.5) & (r <= 21)], 0.3)   # the soft edge kept, not hardened
    assert out[0, 0] == 0.0                                 # the outside untouched
    assert (out >= ring).all()
