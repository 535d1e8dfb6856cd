"""The compiled projection (backend "numba") reproduces ``rasterize.project_gaussians``: the same
survivors, radii, screen-space values and gradients to the 3-D parameters, for every culling rule,
on any thread count; and a render through "numba" still matches "torch"."""

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import assert_numba_render_matches_torch, random_gaussians, record_kernel_threads, ring_cameras, single_thread  # noqa: E402, F401  (single_thread: fixture)

from volcap_core.splat.camera import Camera  # noqa: E402
from volcap_core.splat.project_numba import project_gaussians_numba  # noqa: E402
from volcap_core.splat.rasterize import project_gaussians  # noqa: E402

pytestmark = pytest.mark.usefixtures("single_thread")

OUTPUTS = ("means2d", "conics", "opacities", "depths")
PARAMS = ("means", "quats", "scales", "opacities")


def project(fn, params, camera, dtype=torch.float32, *, seed=7, antialiased=True):
    """``fn``'s projection of ``params`` (means, quats, scales, opacities) cast to ``dtype``, and
    the gradients of a random weighting of its four differentiable outputs to the params."""
    leaves = [p.detach().to(dtype).clone().requires_grad_(True) for p in params]
    proj = fn(*leaves, camera, antialiased=antialiased)
    g = torch.Generator().manual_seed(seed)
    loss = sum((getattr(proj, k) * torch.randn(getattr(proj, k).shape, generator=g,
                                               dtype=torch.float64).to(dtype)).sum()
               for k in OUTPUTS)
    if proj.ids.numel():
        loss.backward()
    return proj, [leaf.grad for leaf in leaves]


def assert_matches_torch(params, camera, *, antialiased=True):
    """Same ids and radii as the float32 PyTorch projection; values within float32 rounding of
    the float64 one and gradients within 1e-3 relative of it. Returns the numba projection and
    gradients."""
    ours, g_ours = project(project_gaussians_numba, params, camera, antialiased=antialiased)
    ref32, _ = project(project_gaussians, params, camera, antialiased=antialiased)
    ref, g_ref = project(project_gaussians, params, camera, torch.float64,
                         antialiased=antialiased)
    assert torch.equal(ours.ids, ref32.ids) and torch.equal(ours.ids, ref.ids)
    assert ours.radii.dtype == torch.int32 and torch.equal(ours.radii, ref32.radii)
    for k in OUTPUTS:
        a, b = getattr(ours, k).detach(), getattr(ref, k).detach()
        assert a.dtype == torch.float32 and a.shape == b.shape, k
        err = float(((a.double() - b).abs() / b.abs().clamp(min=1.0)).max()) if a.numel() else 0.0
        assert err < 1e-5, (k, err)
    if ours.ids.numel():
        for k, g, r in zip(PARAMS, g_ours, g_ref):
            assert g.dtype == torch.float32 and bool(torch.isfinite(g).all()), k
            err = float((g.double() - r).abs().max() / r.abs().max())
            assert err < 1e-3, (k, err)
    return ours, g_ours


def scene(n=400, seed=3):
    g = random_gaussians(n, seed=seed, spread=1.6, scale=(0.02, 0.3))
    return [g.means, g.quats, g.scales, g.opacities]


def pinhole(width=40, height=30, f=40.0, far=1e10) -> Camera:
    """Camera at the origin looking along +z (world = camera axes), principal point off-centre."""
    K = [[f, 0.0, 0.45 * width], [0.0, f * 1.1, 0.55 * height], [0.0, 0.0, 1.0]]
    return Camera(K=K, world_to_camera=torch.eye(4), width=width, height=height, far=far)


@pytest.mark.parametrize("antialiased", [True, False])
def test_matches_torch_on_a_scene_reaching_past_the_image(antialiased):
    # 400 Gaussians in a 3.2 m box seen from 3 m: some off-image, some large and reaching in from
    # outside, some with their Jacobian point clamped; both opacity rules
    params = scene()
    cam = ring_cameras(1, size=40)[0]
    ours, _ = assert_matches_torch(params, cam, antialiased=antialiased)
    assert 50 < ours.ids.numel() < 400                       # culling did something
    off = (ours.means2d[:, 0] < 0) | (ours.means2d[:, 0] > 40) | (ours.means2d[:, 1] < 0) \
        | (ours.means2d[:, 1] > 40)
    assert bool(off.any())                                   # kept, reaching in from outside


def test_matches_torch_at_another_camera_and_where_gradients_only_reach_some_outputs():
    params = scene(200, seed=8)
    cam = ring_cameras(3, size=24, fov=60.0)[1].scaled(1.5)
    ours, g_ours = project(project_gaussians_numba, params, cam)
    ref, g_ref = project(project_gaussians, params, cam, torch.float64)
    assert torch.equal(ours.ids, ref.ids)
    # depths alone: only means get gradient, along the camera's viewing axis
    leaves = [p.clone().requires_grad_(True) for p in params]
    project_gaussians_numba(*leaves, cam).depths.sum().backward()
    axis = cam.world_to_camera[2, :3]
    kept = torch.zeros(200, dtype=torch.bool)
    kept[ours.ids] = True
    assert torch.allclose(leaves[0].grad[kept], axis.expand(int(kept.sum()), 3))
    assert bool((leaves[0].grad[~kept] == 0).all())
    for leaf in leaves[1:]:
        assert bool((leaf.grad == 0).all())


def test_every_culling_rule_and_the_gaussians_it_keeps():
    """One Gaussian per case in front of a 40 x 30 camera (depth 2 m unless the case says)."""
    cam = pinhole(far=5.0)
    cases = {                              # name: (mean, quat, scale, opacity), kept?
        "plain": (([0.1, 0.1, 2.0], [1, 0.2, 0, 0], [0.05, 0.03, 0.04], 0.8), True),
        "zero_quaternion": (([-0.2, 0.0, 2.0], [0, 0, 0, 0], [0.08, 0.02, 0.03], 0.8), True),
        # |x/z| = 1.2 > 1.3x the half field of view (0.60 on the right): the Jacobian's point is
        # clamped; centre 26 px off the image, large enough to reach into it
        "clamped_jacobian_x": (([2.4, 0.1, 2.0], [0.9, 0.1, 0.3, 0.1], [0.6, 0.5, 0.7], 0.9), True),
        "clamped_jacobian_y": (([0.0, -1.9, 2.0], [0.8, 0.3, 0.1, 0.2], [0.5, 0.8, 0.6], 0.9), True),
        "behind_camera": (([0.0, 0.0, -2.0], [1, 0, 0, 0], [0.1, 0.1, 0.1], 0.8), False),
        "at_the_near_plane": (([0.0, 0.0, 0.005], [1, 0, 0, 0], [0.1, 0.1, 0.1], 0.8), False),
        "past_far": (([0.0, 0.0, 6.0], [1, 0, 0, 0], [0.3, 0.3, 0.3], 0.8), False),
        "zero_scale": (([0.0, 0.1, 2.0], [1, 0, 0, 0], [0.0, 0.0, 0.0], 0.8), False),
        "tiny_opacity": (([0.1, -0.1, 2.0], [1, 0, 0, 0], [0.05, 0.05, 0.05], 0.003), False),
        "off_image": (([3.0, 0.0, 2.0], [1, 0, 0, 0], [0.01, 0.01, 0.01], 0.8), False),
        "nan_mean": (([math.nan, 0.0, 2.0], [1, 0, 0, 0], [0.05, 0.05, 0.05], 0.8), False),
        "inf_mean": (([0.0, math.inf, 2.0], [1, 0, 0, 0], [0.05, 0.05, 0.05], 0.8), False),
        "nan_quat": (([0.0, 0.0, 2.0], [1, math.nan, 0, 0], [0.05, 0.05, 0.05], 0.8), False),
        "inf_quat": (([0.0, 0.0, 2.0], [math.inf, 0, 0, 0], [0.05, 0.05, 0.05], 0.8), False),
        "nan_scale": (([0.0, 0.0, 2.0], [1, 0, 0, 0], [0.05, math.nan, 0.05], 0.8), False),
        "inf_scale": (([0.0, 0.0, 2.0], [1, 0, 0, 0], [0.05, 0.05, math.inf], 0.8), False),
        "nan_opacity": (([0.0, 0.0, 2.0], [1, 0, 0, 0], [0.05, 0.05, 0.05], math.nan), False),
        "inf_opacity": (([0.0, 0.0, 2.0], [1, 0, 0, 0], [0.05, 0.05, 0.05], math.inf), False),
    }
    names = list(cases)
    params = [torch.tensor([cases[k][0][j] for k in names], dtype=torch.float32)
              for j in range(4)]
    z, lim = params[0][:, 2], {"x": (40 - 18.0) / 40 + 0.3 * 0.5, "y": 16.5 / 44 + 0.3 * 15 / 44}
    assert float(params[0][2, 0] / z[2]) > lim["x"] and float(-params[0][3, 1] / z[3]) > lim["y"]
    ours, g_ours = assert_matches_torch(params, cam)
    ours.means2d, ours.conics = ours.means2d.detach(), ours.conics.detach()
    assert [names[i] for i in ours.ids] == [k for k in names if cases[k][1]]
    assert bool((ours.radii > 0).all())
    at = {names[i]: row for row, i in enumerate(ours.ids.tolist())}   # survivor rows
    assert float(ours.means2d[at["clamped_jacobian_x"], 0]) > 40 + 20
    culled = torch.tensor([not cases[k][1] for k in names])
    for k, g in zip(PARAMS, g_ours):
        assert bool((g[culled] == 0).all()), k               # exactly zero, not NaN
        assert bool((g[~culled] != 0).any()), k
    # the zero quaternion is R = I: the axis-aligned covariance's conic, and no gradient to it
    q0 = at["zero_quaternion"]
    assert float(ours.conics[q0, 1].abs()) < 1e-6 * float(ours.conics[q0, 0])
    assert bool((g_ours[1][names.index("zero_quaternion")] == 0).all())


def test_nothing_survives_gives_empty_outputs_and_zero_gradients():
    cam = pinhole()
    params = [torch.tensor([[0.0, 0.0, -1.0]] * 3), torch.tensor([[1.0, 0, 0, 0]] * 3),
              torch.full((3, 3), 0.1), torch.full((3,), 0.5)]
    leaves = [p.clone().requires_grad_(True) for p in params]
    proj = project_gaussians_numba(*leaves, cam)
    assert proj.ids.shape == (0,) and proj.means2d.shape == (0, 2) and proj.radii.shape == (0, 2)
    (proj.means2d.sum() + proj.opacities.sum()).backward()
    assert all(bool((leaf.grad == 0).all()) for leaf in leaves)


def test_results_do_not_depend_on_the_thread_count(monkeypatch):
    import numba

    import volcap_core.splat.project_numba as pn

    params = scene(300, seed=4)
    cam = ring_cameras(1, size=40)[0]
    seen = record_kernel_threads(monkeypatch, pn, "_forward", "_backward")
    cores = numba.config.NUMBA_NUM_THREADS
    all_cores = project(project_gaussians_numba, params, cam)
    assert torch.get_num_threads() == 1                       # the caller's setting is kept
    assert seen == [cores, cores]
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    one = project(project_gaussians_numba, params, cam)
    assert seen[2:] == [1, 1]
    for k in ("ids", "radii", *OUTPUTS):
        assert torch.equal(getattr(one[0], k), getattr(all_cores[0], k)), k
    for a, b in zip(one[1], all_cores[1]):
        assert torch.equal(a, b)


def test_render_through_numba_projects_with_the_compiled_kernels_and_matches_torch(monkeypatch):
    import volcap_core.splat.project_numba as pn

    calls = record_kernel_threads(monkeypatch, pn, "_forward")
    assert_numba_render_matches_torch(random_gaussians(300, seed=11, spread=1.2, scale=(0.02, 0.25)),
                                      ring_cameras(2, size=40)[1])
    assert len(calls) == 1                                    # numba's render, not torch's


def test_float32_cpu_tensors_only():
    params = scene(3)
    with pytest.raises(ValueError, match="float32 CPU tensors: scales is torch.float64"):
        project_gaussians_numba(params[0], params[1], params[2].double(), params[3], pinhole())
