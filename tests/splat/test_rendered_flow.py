"""The exact rendered flow (:func:`volcap_core.splat.render.render_flow`) against ground truth.

The scene: a textured wall of Gaussians (a grid on the plane z = 0, random colours, overlapping
footprints so its inside is opaque) moving at a known constant velocity (a Poly4DGS of mean
degree 1), seen by a camera that also moves. The ground truth per pixel is analytic: the ray of the
pixel at frame ``t`` meets the wall at ``X``; that point was at ``X − v Δt`` at frame ``t-1``,
which the previous camera projects to the pixel's previous position.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import single_thread  # noqa: E402, F401  (fixture)

from volcap_core.enhance.temporal import in_frame, warp  # noqa: E402
from volcap_core.splat.camera import Camera  # noqa: E402
from volcap_core.splat.model import Gaussians3D, Poly4DGS, Poly4DGSConfig, evaluate  # noqa: E402
from volcap_core.splat.render import (  # noqa: E402
    _render_flow_gsplat,
    _render_flow_torch,
    gaussians_at,
    gsplat_available,
    render,
    render_flow,
)

FPS = 10.0
W, H, F = 64, 48, 60.0


def wall(velocity=(0.3, -0.1, 0.0), *, nx=16, ny=12, pitch=0.14, seed=0) -> Poly4DGS:
    """``nx × ny`` Gaussians on a grid of ``pitch`` m on the plane z = 0 (centred on the origin),
    random colours, scale 0.6 pitch (overlapping: opaque inside), moving at ``velocity`` m/s."""
    g = torch.Generator().manual_seed(seed)
    xs = (torch.arange(nx) - (nx - 1) / 2) * pitch
    ys = (torch.arange(ny) - (ny - 1) / 2) * pitch
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    xyz = torch.stack([xx.reshape(-1), yy.reshape(-1), torch.zeros(nx * ny)], -1)
    cfg = Poly4DGSConfig(mean_degree=1, quat_degree=0, scale_degree=0, opacity_degree=1, sh_degree=0)
    model = Poly4DGS.from_points(cfg, xyz, torch.rand(nx * ny, 3, generator=g),
                                 scales=torch.full((nx * ny,), 0.6 * pitch), t0=torch.zeros(nx * ny),
                                 opacity=0.95, lifespan_s=float("inf"))
    model.params["means_t"][:, 0] = torch.tensor(velocity)
    model.params["scales"][:, 2] = np.log(1e-4)                  # flat: a wall, one depth
    return model


def camera(centre=(0.0, 0.0, -3.0), yaw_deg: float = 0.0) -> Camera:
    """Looking along +z (the wall is 3 m ahead), turned by ``yaw_deg`` about the camera's y."""
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])  # world -> camera
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ np.asarray(centre, float)
    return Camera(K=[[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], world_to_camera=w2c, width=W, height=H)


def analytic_flow(cam: Camera, prev_cam: Camera, velocity, dt: float, t: float) -> np.ndarray:
    """``[H, W, 2]`` the true backward flow of the wall (float64) at time ``t`` (the plane
    z = v_z t, the wall having left z = 0 at t = 0)."""
    K = cam.K.double().numpy()
    w2c, p2c = cam.world_to_camera.double().numpy(), prev_cam.world_to_camera.double().numpy()
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)            # rasterizer pixel centres
    rays_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R, tr = w2c[:3, :3], w2c[:3, 3]
    centre = -R.T @ tr
    rays_w = rays_c @ R                                                   # R.T @ ray, per pixel
    s = (velocity[2] * t - centre[2]) / rays_w[..., 2]
    X = centre + s[..., None] * rays_w - np.asarray(velocity) * dt      # where the point was
    Xp = X @ p2c[:3, :3].T + p2c[:3, 3]
    up = K[0, 0] * Xp[..., 0] / Xp[..., 2] + K[0, 2]
    vp = K[1, 1] * Xp[..., 1] / Xp[..., 2] + K[1, 2]
    return np.stack([up - u, vp - v], -1)


def flow_of(model, t, cam, prev_cam, **kw):
    g = evaluate(model, t)
    return render_flow(g, gaussians_at(model, t - 1 / FPS, g.ids), cam, prev_cam, backend="torch", **kw)


def test_gaussians_at_are_evaluate_s_and_defined_outside_the_lifespan():
    model = wall()
    model.params["t0"][:5] = 1.0                                       # born late: invisible at t = 0
    model.params["log_lambdas"][:5] = np.log(1 / 0.02 ** 2)
    g = evaluate(model, 0.0)
    assert len(g) == len(model) - 5                                    # evaluate drops them...
    same = gaussians_at(model, 0.0, g.ids)
    for name in ("means", "quats", "scales", "opacities", "sh", "ids"):
        assert torch.equal(getattr(same, name), getattr(g, name)), name
    every = gaussians_at(model, 0.0, torch.arange(len(model)))         # ...but are defined then
    expect = model.params["means"][:5] + model.params["means_t"][:5, 0] * (0.0 - 1.0)
    assert torch.allclose(every.means[:5], expect) and every.means.shape == (len(model), 3)
    assert (every.opacities[:5] < 1e-10).all() and torch.equal(every.ids, torch.arange(len(model)))
    model.params["opacities"][7] = float("nan")                        # rows stay aligned with ids
    odd = gaussians_at(model, 0.0, torch.tensor([7, 8]))
    assert odd.means[0].isnan().all() and torch.equal(odd.means[1], every.means[8])


def test_translation_and_a_moving_camera_give_the_analytic_uniform_flow(single_thread):
    v = (0.3, -0.1, 0.0)
    t = 0.5
    cam, prev_cam = camera((0.02, 0.01, -3.0)), camera((0.0, 0.0, -3.0))
    out = flow_of(wall(v), t, cam, prev_cam)
    flow, alpha = out["flow"].numpy(), out["alpha"][..., 0].numpy()
    assert flow.shape == (H, W, 2) and out["alpha"].shape == (H, W, 1)
    # every Gaussian moves by the same d = f (−v Δt − C_prev + C_cur) / Z: the flow is exactly that
    d = F * (-np.asarray(v[:2]) / FPS + np.array([0.02, 0.01])) / 3.0
    covered = alpha > 0.5
    assert covered.mean() > 0.4
    err = np.abs(flow[covered] - d).max()
    assert err < 1e-4, err
    # alpha is the render's (every displacement is defined)
    ref = render(evaluate(wall(v), t), cam, backend="torch")["alpha"][..., 0].numpy()
    assert np.allclose(alpha, ref, atol=1e-6)
    # nothing there: flow 0 (the documented fallback)
    empty = alpha < 1 / 255
    assert empty.any() and np.array_equal(flow[empty], np.zeros_like(flow[empty]))


@pytest.mark.parametrize("case", ["dolly", "pan"])
def test_a_dolly_or_a_pan_gives_the_analytic_per_pixel_flow(case, single_thread):
    """A non-uniform flow: the camera dollies in 10 cm (the image scales by 3 %) or turns 1.5°,
    and the wall moves. Each Gaussian's first-order (affine) motion across its footprint is
    composited, not only its centre's: a dolly is exact (the centre alone was off by the flow's
    gradient times the distance to the centres: 0.06 px here, 0.23 px at 256x192); a pan leaves
    the second-order (projective) term: 0.0015 px here."""
    v = (0.2, 0.15, 0.1)
    if case == "dolly":
        cam, tol_mean, tol_max = camera((0.03, 0.0, -2.9)), 1e-4, 5e-4
    else:
        cam, tol_mean, tol_max = camera((0.03, 0.0, -3.0), yaw_deg=1.5), 0.004, 0.008
    prev_cam = camera((0.0, 0.0, -3.0))
    out = flow_of(wall(v), 0.5, cam, prev_cam)
    flow, alpha = out["flow"].numpy(), out["alpha"][..., 0].numpy()
    truth = analytic_flow(cam, prev_cam, v, 1 / FPS, 0.5)
    covered = alpha > 0.9
    assert covered.mean() > 0.4
    assert np.ptp(truth[covered][:, 0]) > 0.1                               # not uniform
    err = np.linalg.norm(flow - truth, axis=-1)[covered]
    assert err.mean() < tol_mean and err.max() < tol_max, (err.mean(), err.max())


def test_a_turning_gaussian_carries_its_rotation_across_its_footprint(single_thread):
    """One elongated Gaussian turning about the optical axis (a Poly4DGS quaternion of degree 1):
    its centre stays put, the points it draws turn with it: flow = (Rot(α) − I)(p − c)."""
    cfg = Poly4DGSConfig(mean_degree=1, quat_degree=1, scale_degree=0, opacity_degree=1, sh_degree=0)
    model = Poly4DGS.from_points(cfg, torch.zeros(1, 3), torch.full((1, 3), 0.5), scales=torch.tensor([[0.4, 0.1, 1e-4]]),
                                 t0=torch.zeros(1), opacity=0.95, lifespan_s=float("inf"))
    model.params["quats_t"][0, 0] = torch.tensor([0.0, 0.0, 0.0, 0.5])     # ω = 1 rad/s about z
    t = 0.5
    angle = lambda time: 2 * np.arctan(0.5 * time)                          # noqa: E731
    alpha_ = angle(t - 1 / FPS) - angle(t)                                 # the turn back to t-1 (rad)
    cam = camera()
    out = flow_of(model, t, cam, cam)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    du, dv = u - W / 2, v - H / 2
    truth = np.stack([np.cos(alpha_) * du - np.sin(alpha_) * dv - du, np.sin(alpha_) * du + np.cos(alpha_) * dv - dv], -1)
    covered = out["alpha"][..., 0].numpy() > 0.3
    assert covered.sum() > 50 and np.abs(truth[covered]).max() > 0.3         # it turns by ~0.5 px at the tips
    assert np.abs(out["flow"].numpy()[covered] - truth[covered]).max() < 1e-3


def test_warping_the_previous_render_with_it_reproduces_the_current_render(single_thread):
    """The wall moves and the camera dollies in (a non-uniform, radial flow of ~1 px; a yaw is left
    out here: it reorders the flat wall's equal-depth Gaussians and changes the composite itself)."""
    v = (0.6, -0.3, 0.0)
    model = wall(v, nx=10, ny=8, pitch=0.22)                              # a texture smoother than 1 px
    t = 0.5
    cam, prev_cam = camera((0.02, 0.01, -2.9)), camera((0.0, 0.0, -3.0))

    def rgba(time, c):
        out = render(evaluate(model, time), c, backend="torch")
        return torch.cat([out["rgb"], out["alpha"]], -1).permute(2, 0, 1)

    prev, cur = rgba(t - 1 / FPS, prev_cam), rgba(t, cam)
    flow = flow_of(model, t, cam, prev_cam)["flow"].permute(2, 0, 1)
    # covered: alpha > 0.9 in a 5x5 neighbourhood (bilinear sampling mixes across a silhouette)
    solid = -torch.nn.functional.max_pool2d(-cur[3][None, None], 5, 1, 2)[0, 0] > 0.9
    solid &= in_frame(flow)[0] > 0
    assert solid.float().mean() > 0.3

    def error(f):
        return (warp(prev, f) - cur).abs().amax(0)[solid]

    err = error(flow)
    assert err.mean() < 0.01 and err.max() < 0.04, (err.mean(), err.max())   # bilinear resampling only
    assert (prev - cur).abs().amax(0)[solid].mean() > 8 * err.mean()          # no motion compensation
    for dx, dy in ((0.2, 0), (-0.2, 0), (0, 0.2), (0, -0.2)):                # the flow is the best warp
        assert error(flow + torch.tensor([dx, dy])[:, None, None]).mean() > 1.4 * err.mean()


def test_a_gaussian_invisible_in_the_previous_frame_has_a_flow(single_thread):
    """Born between the frames (opacity ~1e-5 at t-1, dropped by evaluate): its centre then is
    still defined, and its pixels carry its displacement."""
    v = (0.3, -0.1, 0.0)
    model = wall(v, nx=1, ny=1)
    model.params["t0"][:] = 0.5
    model.params["log_lambdas"][:] = np.log(1 / 0.02 ** 2)                 # σ_t = 20 ms
    assert len(evaluate(model, 0.4)) == 0 and len(evaluate(model, 0.5)) == 1
    cam = camera()
    out = flow_of(model, 0.5, cam, cam)
    d = F * -np.asarray(v[:2]) / FPS / 3.0
    covered = out["alpha"][..., 0].numpy() > 0.5
    assert covered.any()
    assert np.abs(out["flow"].numpy()[covered] - d).max() < 1e-4


def test_a_centre_behind_the_previous_camera_adds_no_flow_and_shapes_are_checked(single_thread):
    model = wall((0.0, 0.0, 0.0), nx=2, ny=1, pitch=1.0)
    model.params["scales"][:, :2] = np.log(0.1)                          # 2 px: the two do not overlap
    g = evaluate(model, 0.0)
    prev = gaussians_at(model, 0.0, g.ids)
    prev.means[0, 2] = -10.0                                              # behind the camera at t-1
    cam = camera()
    out = render_flow(g, prev, cam, cam, backend="torch")
    solo = render_flow(g.select(torch.tensor([1])), prev.select(torch.tensor([1])), cam, cam, backend="torch")
    assert torch.allclose(out["alpha"], solo["alpha"], atol=1e-6)        # only the defined one weighs
    assert out["flow"].abs().max() == 0                                   # ...and it did not move
    with pytest.raises(ValueError, match="previous Gaussians"):
        render_flow(g, prev.select(torch.tensor([0])), cam, cam, backend="torch")


def test_the_gsplat_path_composites_the_same_values(monkeypatch, single_thread):
    """gsplat cannot run without CUDA: its ``rasterization`` is replaced by a stand-in built on
    the torch rasterizer (N-channel colours, antialiased), which checks that the CUDA path passes
    the same per-Gaussian values and normalises the same way."""
    gsplat = pytest.importorskip("gsplat")
    from volcap_core.splat.rasterize import EPS2D, project_gaussians, rasterize_tiles

    calls = []

    def rasterization(*, means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
                      far_plane, eps2d, rasterize_mode, render_mode, packed):
        calls.append((colors.shape, render_mode, rasterize_mode, eps2d))
        cam = Camera(K=Ks[0], world_to_camera=viewmats[0], width=width, height=height, near=near_plane,
                     far=far_plane)
        p = project_gaussians(means, quats, scales, opacities, cam, eps2d=EPS2D, antialiased=True)
        acc, trans = rasterize_tiles(p.means2d, p.conics, p.opacities, p.depths, p.radii, colors[p.ids],
                                     width, height)
        return acc[None], (1 - trans)[None, ..., None], {}

    monkeypatch.setattr(gsplat, "rasterization", rasterization)
    model = wall((0.3, -0.1, 0.05))
    g = evaluate(model, 0.5)
    prev = gaussians_at(model, 0.4, g.ids)
    cam, prev_cam = camera((0.02, 0.0, -3.0), yaw_deg=1.0), camera()
    a = _render_flow_gsplat(g, prev, cam, prev_cam)
    b = _render_flow_torch(g, prev, cam, prev_cam, 8)
    assert calls == [((len(g), 7), "RGB", "antialiased", EPS2D)]
    assert torch.allclose(a, b, atol=1e-5)


def _on_cuda(g: Gaussians3D) -> Gaussians3D:
    return Gaussians3D(**{f: getattr(g, f).cuda() for f in ("means", "quats", "scales", "opacities", "sh", "ids")},
                       colour_space=g.colour_space)


@pytest.mark.gpu
@pytest.mark.skipif(not gsplat_available(), reason="needs CUDA and gsplat")
def test_gsplat_flow_on_cuda_matches_the_torch_flow_and_the_truth():
    """The gsplat back-end's flow, on a GPU: the same flow and alpha as the torch back-end on the
    CPU, and the analytic flow of a translating wall seen by a moving camera."""
    v, t = (0.3, -0.1, 0.0), 0.5
    model = wall(v)
    cam, prev_cam = camera((0.02, 0.01, -3.0)), camera((0.0, 0.0, -3.0))
    g = evaluate(model, t)
    prev = gaussians_at(model, t - 1 / FPS, g.ids)
    cpu = render_flow(g, prev, cam, prev_cam, backend="torch")
    gpu = render_flow(_on_cuda(g), _on_cuda(prev), cam, prev_cam, backend="gsplat")
    assert gpu["flow"].is_cuda
    torch.testing.assert_close(gpu["alpha"].cpu(), cpu["alpha"], atol=2e-4, rtol=1e-3)
    inside = cpu["alpha"][..., 0] > 0.5
    assert inside.float().mean() > 0.4
    torch.testing.assert_close(gpu["flow"].cpu()[inside], cpu["flow"][inside], atol=2e-3, rtol=0)
    truth = torch.from_numpy(analytic_flow(cam, prev_cam, v, 1 / FPS, t)).float()
    assert (gpu["flow"].cpu()[inside] - truth[inside]).abs().max() < 1e-2
