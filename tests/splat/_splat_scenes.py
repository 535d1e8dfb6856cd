"""Shared tiny scenes for the splat tests (imported by name: tests/splat is on sys.path)."""

import math

import torch

from volcap_core.splat.camera import Camera, look_at
from volcap_core.splat.model import Gaussians3D


def ring_cameras(n: int = 6, *, radius: float = 3.0, size: int = 32, fov: float = 40.0,
                 height: float = 0.6) -> list[Camera]:
    """``n`` cameras on a circle around the origin, looking at it (z up)."""
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = (radius * math.cos(a), radius * math.sin(a), height * (1 if i % 2 else -1))
        cams.append(look_at(eye, (0, 0, 0), fov_x_deg=fov, width=size, height=size))
    return cams


def random_gaussians(n: int, *, seed: int = 0, spread: float = 0.4, scale=(0.03, 0.12),
                     sh_degree: int = 1, dtype=torch.float32) -> Gaussians3D:
    g = torch.Generator().manual_seed(seed)
    K = (sh_degree + 1) ** 2
    sh = torch.randn(n, K, 3, generator=g, dtype=dtype) * 0.2
    sh[:, 0] = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) / 0.2820948
    return Gaussians3D(
        means=(torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * spread,
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=scale[0] + torch.rand(n, 3, generator=g, dtype=dtype) * (scale[1] - scale[0]),
        opacities=0.3 + 0.6 * torch.rand(n, generator=g, dtype=dtype),
        sh=sh, ids=torch.arange(n))


import pytest  # noqa: E402


@pytest.fixture(autouse=False)
def single_thread():
    """Run a test on one intra-op thread: as reproducible training runs torch (the compiled kernels'
    tests check that they keep the caller's setting), and on a shared 2-core machine OpenMP
    spin-waits make small tensor ops ~10x slower with 2 threads when the other core is busy.
    Restores the setting."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def moving_scene(n: int = 40, *, frames=(0, 3), fps: float = 10.0, cameras: int = 6,
                 size: int = 32, seed: int = 5):
    """A known dynamic scene: ``n`` Gaussians moving at constant velocity, rendered from a ring of
    cameras. Returns (SegmentData, init points per frame, cameras)."""
    from volcap_core.colour import srgb_decode_unbounded
    from volcap_core.splat.render import render
    from volcap_core.splat.sh import sh_to_colour
    from volcap_core.splat.train import PointsAtTime, SegmentData

    gt = random_gaussians(n, seed=seed, sh_degree=0, scale=(0.05, 0.15))
    gt.opacities[:] = 0.9
    vel = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed + 1)) * 0.3
    cams = ring_cameras(cameras, size=size)

    def at(t):
        return Gaussians3D(gt.means + vel * t, gt.quats, gt.scales, gt.opacities, gt.sh, gt.ids)

    with torch.no_grad():
        images = {(str(i), f): render(at(f / fps), c, backend="torch")["rgb"]
                  for i, c in enumerate(cams) for f in range(*frames)}
    data = SegmentData.build(frames=frames, camera_ids=[str(i) for i in range(cameras)], fps=fps,
                             load_image=lambda c, f: images[(c, f)],
                             camera_for=lambda c, f: cams[int(c)])
    g = torch.Generator().manual_seed(seed + 2)
    linear = srgb_decode_unbounded(sh_to_colour(gt.sh, gt.means)).clamp(0, 1)
    points = []
    for f in range(*frames):
        # a noisy "dense" cloud: 3 points per true Gaussian, 5 cm jitter
        xyz = at(f / fps).means.repeat(3, 1) + 0.05 * torch.randn(3 * n, 3, generator=g)
        points.append(PointsAtTime(f / fps, xyz, linear.repeat(3, 1)))
    return data, points, cams


def performers_on_a_floor(*, frames=(0, 2), fps: float = 10.0, size: int = 24, plates: bool = False):
    """Performers (30 Gaussians moving at constant velocity) on a static floor (a grid of flat
    Gaussians at z = -0.45), seen by 5 ring cameras; per view the footage and the performers'
    true coverage (the view's matte). Returns (SegmentData, initial points per frame: the
    performers' noisy, the floor's as it is and marked static) and, with ``plates``, each
    camera's clean plate (the floor alone, ``{camera id: [H, W, 3]}``)."""
    from volcap_core.colour import srgb_decode_unbounded
    from volcap_core.splat.render import render
    from volcap_core.splat.sh import SH_C0, sh_to_colour
    from volcap_core.splat.train import PointsAtTime, SegmentData

    actors = random_gaussians(30, seed=3, sh_degree=0, spread=0.3, scale=(0.05, 0.12))
    actors.opacities[:] = 0.9
    vel = torch.randn(30, 3, generator=torch.Generator().manual_seed(4)) * 0.3
    u = torch.linspace(-1.0, 1.0, 9)
    floor_xyz = torch.stack([*torch.meshgrid(u, u, indexing="ij"), torch.full((9, 9), -0.45)], -1).reshape(-1, 3)
    nf = len(floor_xyz)
    floor = Gaussians3D(floor_xyz, torch.tensor([[1.0, 0, 0, 0]]).repeat(nf, 1),
                        torch.tensor([[0.14, 0.14, 0.01]]).repeat(nf, 1), torch.full((nf,), 0.95),
                        torch.full((nf, 1, 3), 0.1 / SH_C0), torch.arange(nf))
    cams = ring_cameras(5, size=size)

    def at(t: float, flag: bool = False) -> Gaussians3D:
        sh = torch.cat([actors.sh, floor.sh])
        if flag:   # colour 1 on the performers, 0 on the floor: their coverage, occluded by the floor
            sh = torch.cat([torch.full_like(actors.sh, 0.5 / SH_C0), torch.full_like(floor.sh, -0.5 / SH_C0)])
        return Gaussians3D(torch.cat([actors.means + vel * t, floor.means]), torch.cat([actors.quats, floor.quats]),
                           torch.cat([actors.scales, floor.scales]), torch.cat([actors.opacities, floor.opacities]),
                           sh, torch.arange(30 + nf), colour_space="linear" if flag else "srgb_unbounded")

    with torch.no_grad():
        images = {(str(i), f): render(at(f / fps), c, backend="torch")["rgb"] for i, c in enumerate(cams)
                  for f in range(*frames)}
        masks = {(str(i), f): render(at(f / fps, True), c, backend="torch")["rgb"][..., 0]
                 for i, c in enumerate(cams) for f in range(*frames)}
        clean = {str(i): render(floor, c, backend="torch")["rgb"] for i, c in enumerate(cams)}
    data = SegmentData.build(frames=frames, camera_ids=[str(i) for i in range(5)], fps=fps,
                             load_image=lambda c, f: images[(c, f)], camera_for=lambda c, f: cams[int(c)],
                             load_matte=lambda c, f: masks[(c, f)])
    g = torch.Generator().manual_seed(9)
    colour = srgb_decode_unbounded(sh_to_colour(actors.sh, actors.means)).clamp(0, 1)
    points = []
    for f in range(*frames):
        # a noisy "dense" cloud: the performers 3 points a Gaussian with 6 cm jitter, the floor as it is
        xyz = torch.cat([(actors.means + vel * f / fps).repeat(3, 1) + 0.06 * torch.randn(90, 3, generator=g),
                         floor_xyz])
        rgb = torch.cat([colour.repeat(3, 1), torch.full((nf, 3), 0.01)])
        static = torch.cat([torch.zeros(90, dtype=torch.bool), torch.ones(nf, dtype=torch.bool)])
        points.append(PointsAtTime(f / fps, xyz, rgb, static))
    return (data, points, clean) if plates else (data, points)


def record_kernel_threads(monkeypatch, module, *kernels: str) -> list[int]:
    """Wrap the compiled ``kernels`` (names in ``module``) so each call records numba's thread
    count at that moment; returns the record (one int per call, in call order)."""
    import numba

    seen: list[int] = []
    for name in kernels:
        kernel = getattr(module, name)

        def run(*a, _kernel=kernel, **kw):
            seen.append(numba.get_num_threads())
            return _kernel(*a, **kw)
        monkeypatch.setattr(module, name, run)
    return seen


def assert_numba_render_matches_torch(gaussians: Gaussians3D, camera: Camera):
    """Render ``gaussians`` into ``camera`` through back-ends "numba" and "torch" and backpropagate
    one fixed random weighting of the ``[H, W, 5]`` rgb, alpha and depth to the 3-D parameters.
    Asserts numba's rgb and alpha within 1e-5 of torch's (finite), its depth within 1e-5 relative
    where torch's alpha > 0.01 (some pixel is) and its gradients to means, quats, scales,
    opacities and sh finite and within 1e-3 relative of torch's. Returns numba's (outputs
    detached, gradients by parameter name)."""
    from volcap_core.splat.render import render

    weights = torch.rand(camera.height, camera.width, 5, generator=torch.Generator().manual_seed(5))
    results = {}
    for backend in ("numba", "torch"):
        leaves = {k: getattr(gaussians, k).clone().requires_grad_(True)
                  for k in ("means", "quats", "scales", "opacities", "sh")}
        out = render(Gaussians3D(**leaves, ids=gaussians.ids), camera, backend=backend)
        loss = (torch.cat([out["rgb"], out["alpha"], out["depth"]], -1) * weights).sum()
        loss.backward()
        results[backend] = ({k: v.detach() for k, v in out.items()},
                            {k: v.grad for k, v in leaves.items()})
    (o, gn), (r, gt) = results["numba"], results["torch"]
    assert bool(torch.isfinite(o["rgb"]).all())
    assert torch.allclose(o["rgb"], r["rgb"], atol=1e-5), float((o["rgb"] - r["rgb"]).abs().max())
    assert torch.allclose(o["alpha"], r["alpha"], atol=1e-5), float((o["alpha"] - r["alpha"]).abs().max())
    hit = r["alpha"] > 0.01
    assert bool(hit.any())
    assert float(((o["depth"] - r["depth"]).abs() / r["depth"].abs())[hit].max()) < 1e-5
    for k in gn:
        assert bool(torch.isfinite(gn[k]).all()), k
        assert float((gn[k] - gt[k]).abs().max() / gt[k].abs().max()) < 1e-3, k
    return o, gn
