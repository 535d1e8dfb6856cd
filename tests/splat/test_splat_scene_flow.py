"""The performers' initial motion (splat/scene_flow.py, reconstruction.with_scene_flow): a textured
card moving in front of a textured wall, filmed by four cameras, must get its velocity back; the
velocity must reach the initial Gaussians through the thinning and into the model's motion."""

import math

import numpy as np
import pytest
import torch

from volcap_core import reconstruction
from volcap_core.splat import PointsAtTime, SegmentData, TrainConfig
from volcap_core.splat.train import init_model
from volcap_core.splat.camera import look_at
from volcap_core.splat.init import initial_gaussians
from volcap_core.splat.scene_flow import moved_points

FPS = 24.0
VELOCITY = np.array([0.3, 0.6, -0.3])   # m/s: 2.5 cm a frame sideways, toward the cameras and down
CARD = (0.5, 0.4)                       # the card's half-extent in y and z (metres), centred at (0, 0, 1)


def _texture(seed: int, n: int = 256) -> np.ndarray:
    """A smooth random grey texture ``[n, n]`` in [0.05, 0.95] (blobs of a few texels)."""
    from scipy.ndimage import gaussian_filter

    t = gaussian_filter(np.random.default_rng(seed).random((n, n)), 1.5)
    return 0.05 + 0.9 * (t - t.min()) / (t.max() - t.min())


CARD_TEX, WALL_TEX = _texture(0), _texture(1)


def _lookup(tex: np.ndarray, u: np.ndarray, v: np.ndarray, texel: float) -> np.ndarray:
    n = tex.shape[0]
    i = np.floor(u / texel).astype(np.int64) % n
    j = np.floor(v / texel).astype(np.int64) % n
    return tex[j, i]


def _render(camera, t: float) -> torch.Tensor:
    """``[H, W, 3]`` linear: the card (plane x = card_x(t)) over the wall at x = -1.5."""
    K = camera.opencv_K()
    W = camera.world_to_camera.double().numpy()
    R, c = W[:3, :3], -W[:3, :3].T @ W[:3, 3]
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1) @ R
    shift = VELOCITY * t
    img = np.zeros(u.shape)
    s_wall = (-1.5 - c[0]) / rays[..., 0]
    p = c + s_wall[..., None] * rays
    img[:] = _lookup(WALL_TEX, p[..., 1] + 5, p[..., 2] + 5, 0.02)
    s = (shift[0] - c[0]) / rays[..., 0]
    q = c + s[..., None] * rays - np.array([0.0, 0.0, 1.0]) - shift
    on = (np.abs(q[..., 1]) < CARD[0]) & (np.abs(q[..., 2]) < CARD[1]) & (s > 0)
    img[on] = _lookup(CARD_TEX, q[..., 1][on] + CARD[0], q[..., 2][on] + CARD[1], 0.006)
    return torch.from_numpy(np.repeat(img[..., None], 3, -1).astype(np.float32))


def _scene(frames: int = 3, cameras=(-40.0, -15.0, 15.0, 40.0)) -> SegmentData:
    cams = {}
    for k, az in enumerate(cameras):
        a = math.radians(az)
        cams[f"C{k}"] = look_at((3.0 * math.cos(a), 3.0 * math.sin(a), 1.3), (0.0, 0.0, 1.0),
                                fov_x_deg=45.0, width=240, height=180)
    return SegmentData.build(frames=(0, frames), camera_ids=sorted(cams), fps=FPS, lazy=False,
                             load_image=lambda c, f: _render(cams[c], f / FPS), camera_for=lambda c, f: cams[c])


def _card_points(t: float, spacing: float = 0.02) -> np.ndarray:
    y, z = np.meshgrid(np.arange(-0.45, 0.45, spacing), np.arange(-0.35, 0.35, spacing))
    return np.stack([np.zeros_like(y), y, z + 1.0], -1).reshape(-1, 3) + VELOCITY * t


def test_moved_points_triangulates_an_exact_move():
    """Projections of the moved points through two cameras give the moved points back."""
    data = _scene(frames=1)
    x = _card_points(0.0)
    to = x + np.array([0.01, -0.02, 0.015])
    obs = []
    for v in data.views[:2]:
        K, W = v.camera.opencv_K(), v.camera.world_to_camera.double().numpy()
        pc = to @ W[:3, :3].T + W[:3, 3]
        obs.append((K, W, pc[:, :2] / pc[:, 2:] @ K[:2, :2].T + K[:2, 2], np.ones(len(x), bool)))
    moved, cams, rms = moved_points(x, obs)
    assert (cams == 2).all()
    assert np.abs(moved - to).max() < 1e-6 and rms.max() < 1e-4
    # seen by one camera only: the move along its ray is unobserved, the point is not trusted
    _, cams, _ = moved_points(x, [obs[0], (*obs[1][:3], np.zeros(len(x), bool))])
    assert (cams == 1).all()


def test_scene_flow_recovers_a_moving_cards_velocity():
    """The card's points at the middle frame, their velocity from the four cameras' flow: within 5 %
    of the truth (median error), every point's, while the static wall's points keep zero."""
    data = _scene()
    x = _card_points(1 / FPS)
    wall = np.stack([np.full(50, -1.5), np.linspace(-1, 1, 50), np.linspace(0.5, 1.5, 50)], -1)
    xyz = np.concatenate([x, wall]).astype(np.float32)
    static = np.r_[np.zeros(len(x), bool), np.ones(len(wall), bool)]
    cloud = PointsAtTime(1 / FPS, torch.from_numpy(xyz), torch.full((len(xyz), 3), 0.5),
                         static=torch.from_numpy(static))
    [out] = reconstruction.with_scene_flow([cloud], data)
    v = out.velocity.numpy()
    err = np.linalg.norm(v[: len(x)] - VELOCITY, axis=1) / np.linalg.norm(VELOCITY)
    assert np.median(err) < 0.05, np.median(err)
    assert np.percentile(err, 90) < 0.1
    assert (v[len(x):] == 0).all()
    # a held-out camera's footage never feeds it: with three of four cameras held out nothing triangulates
    [alone] = reconstruction.with_scene_flow([cloud], data, held_out=["C0", "C1", "C2"])
    assert (alone.velocity.numpy() == 0).all()


def test_velocity_reaches_the_model_through_thinning():
    """Every initial moving Gaussian keeps the velocity of the point it was drawn from; the static
    ones get none; the model's first motion coefficient is that velocity."""
    rng = np.random.default_rng(0)
    frames = []
    for f in range(3):
        xyz = rng.uniform(-1, 1, (3000, 3))
        vel = np.stack([xyz[:, 0] * 0.5, np.full(3000, 0.1 * f), xyz[:, 2]], -1)
        static = np.arange(3000) < 1000
        vel[static] = 0
        frames.append((f / FPS, xyz, np.full((3000, 3), 0.4), static, None, vel))
    split = initial_gaussians(frames, budget=2000, seed=1)
    moving = ~split.static
    f = np.round(split.t0[moving] * FPS).astype(int)
    expect = np.stack([split.xyz[moving, 0] * 0.5, 0.1 * f, split.xyz[moving, 2]], -1)
    np.testing.assert_allclose(split.velocity[moving], expect, atol=1e-12)
    assert (split.velocity[split.static] == 0).all()
    assert initial_gaussians([fr[:5] for fr in frames], budget=2000, seed=1).velocity is None

    points = [PointsAtTime(t, torch.from_numpy(x).float(), torch.from_numpy(c).float(), torch.from_numpy(s),
                           velocity=torch.from_numpy(v).float()) for t, x, c, s, _, v in frames]
    model = init_model(points, TrainConfig(init_max_points=2000, init_cap_fraction=1.0), frame_interval_s=1 / FPS)
    mov = model.moving()
    mu1 = model.params["means_t"][:, 0]
    assert mu1[mov].abs().sum() > 0 and (mu1[~mov] == 0).all()
    no_motion = init_model([PointsAtTime(p.time, p.xyz, p.rgb, p.static) for p in points],
                           TrainConfig(init_max_points=2000, init_cap_fraction=1.0), frame_interval_s=1 / FPS)
    assert (no_motion.params["means_t"] == 0).all()


def test_scene_flow_is_off_in_the_json_of_a_config_without_it():
    """A config that does not ask for it keeps its bytes (stored configs, train-segment keys)."""
    assert "init_scene_flow" not in TrainConfig().model_dump_json()
    assert '"init_scene_flow":true' in TrainConfig(init_scene_flow=True).model_dump_json()


def test_velocity_needs_a_temporal_mean():
    from volcap_core.splat import Poly4DGS, Poly4DGSConfig

    with pytest.raises(ValueError, match="mean_degree"):
        Poly4DGS.from_points(Poly4DGSConfig(mean_degree=0), torch.zeros(2, 3), torch.zeros(2, 3),
                             scales=torch.ones(2), t0=torch.zeros(2), velocity=torch.zeros(2, 3))


def test_points_keep_their_velocity_when_subset_and_refuse_a_mismatch():
    """A subset (the set trained apart keeps a cloud's moving points only) carries each point's
    velocity with it; a velocity of another length is refused, naming the field."""
    xyz = torch.arange(12, dtype=torch.float32).view(4, 3)
    p = PointsAtTime(0.5, xyz, xyz.clone(), static=torch.tensor([True, False, True, False]), velocity=xyz * 2)
    q = p.subset(~p.static)
    assert torch.equal(q.xyz, xyz[[1, 3]]) and torch.equal(q.velocity, xyz[[1, 3]] * 2)
    with pytest.raises(ValueError, match="velocity has 3 rows for 4 points"):
        PointsAtTime(0.5, xyz, xyz.clone(), velocity=xyz[:3])
