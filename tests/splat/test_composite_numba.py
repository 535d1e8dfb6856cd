"""The compiled compositor (backend "numba") reproduces the PyTorch compositor: the same image,
alpha and depth and the same gradients, where pixels stop early, where Gaussians reach past the
image, and where nothing is drawn; and a segment trains through it as through torch."""

import math
import os
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import assert_numba_render_matches_torch, moving_scene, random_gaussians, record_kernel_threads, ring_cameras, single_thread  # noqa: E402, F401  (single_thread: fixture)

from volcap_core.splat.composite_numba import rasterize_tiles_numba  # noqa: E402
from volcap_core.splat.model import Gaussians3D  # noqa: E402
from volcap_core.splat.rasterize import (  # noqa: E402
    ALPHA_MAX,
    ALPHA_THRESHOLD,
    EXTEND_MAX,
    TRANSMITTANCE_MIN,
    TileStats,
    rasterize_tiles,
)
from volcap_core.splat.render import BackendUnavailable, render_flow, resolve_backend  # noqa: E402

pytestmark = pytest.mark.usefixtures("single_thread")


def splats(n: int, width: int, height: int, *, seed: int, sigma=(1.0, 6.0), opacity=(0.3, 1.0),
           margin: float = 0.0, values: int = 4, opaque: int = 0):
    """``n`` screen-space Gaussians as :func:`project_gaussians` gives them: centres uniform over
    the image grown by ``margin`` px on each side, random rotation and axis sigmas (px) in
    ``sigma``, opacities in ``opacity`` (the first ``opaque`` exactly 1), footprint radii by the projection's rule; random depths and
    ``values`` channels in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    grown = torch.tensor([width + 2 * margin, height + 2 * margin])
    means = torch.rand(n, 2, generator=g) * grown - margin
    s = sigma[0] + torch.rand(n, 2, generator=g) * (sigma[1] - sigma[0])
    th = torch.rand(n, generator=g) * math.pi
    c, sn = torch.cos(th), torch.sin(th)
    R = torch.stack([c, -sn, sn, c], -1).reshape(n, 2, 2)
    cov = R @ torch.diag_embed(s * s) @ R.transpose(1, 2)
    a, b, cc = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * cc - b * b
    conics = torch.stack([cc / det, -b / det, a / det], -1)
    opac = opacity[0] + torch.rand(n, generator=g) * (opacity[1] - opacity[0])
    opac[:opaque] = 1.0
    extend = torch.sqrt(2 * torch.log(opac / ALPHA_THRESHOLD)).clamp(max=EXTEND_MAX)
    radii = torch.stack([torch.ceil(extend * a.sqrt()), torch.ceil(extend * cc.sqrt())], -1).int()
    return (means, conics, opac, torch.rand(n, generator=g) + 1.0, radii,
            torch.rand(n, values, generator=g))


def composite(fn, means, conics, opac, depths, radii, values, width, height, seed=3):
    """Forward, then backward of a random weighting of the outputs; returns the outputs and the
    gradients of (means2d, conics, opacities, values)."""
    leaves = [t.clone().requires_grad_(True) for t in (means, conics, opac, values)]
    acc, trans = fn(leaves[0], leaves[1], leaves[2], depths, radii, leaves[3], width, height)
    g = torch.Generator().manual_seed(seed)
    w_acc, w_t = torch.rand(acc.shape, generator=g), torch.rand(trans.shape, generator=g)
    ((acc * w_acc).sum() + (trans * w_t).sum()).backward()
    return acc.detach(), trans.detach(), [leaf.grad for leaf in leaves]


def brute_transmittance(means, conics, opac, width, height):
    """``[H, W]`` product of (1 - α) over every Gaussian with α >= 1/255, no stop (float64)."""
    y, x = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    dx = x.reshape(-1, 1).double() - means[:, 0].double()
    dy = y.reshape(-1, 1).double() - means[:, 1].double()
    a, b, c = conics.double().unbind(-1)
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = (opac.double() * torch.exp(-sigma)).clamp(max=ALPHA_MAX)
    alpha = torch.where(alpha >= ALPHA_THRESHOLD, alpha, 0.0)
    return torch.prod(1 - alpha, dim=1).reshape(height, width)


def assert_same(inputs, width, height):
    ours = composite(rasterize_tiles_numba, *inputs, width, height)
    ref = composite(rasterize_tiles, *inputs, width, height)
    assert ours[0].shape == ref[0].shape and ours[1].shape == ref[1].shape
    assert torch.allclose(ours[0], ref[0], atol=1e-5, rtol=0), float((ours[0] - ref[0]).abs().max())
    assert torch.allclose(ours[1], ref[1], atol=1e-5, rtol=0), float((ours[1] - ref[1]).abs().max())
    for name, g, r in zip(("means2d", "conics", "opacities", "values"), ours[2], ref[2]):
        assert torch.isfinite(g).all(), name
        err = float((g - r).abs().max() / r.abs().max().clamp(min=1e-30))
        assert err < 1e-3, (name, err)
    return ours, ref


def test_matches_torch_where_layers_are_opaque_and_pixels_stop_early():
    # 48 x 36 (not a whole number of 8-px tiles), 400 Gaussians overlapping many deep, opacities
    # up to 1, 40 of them exactly 1 (α clamped to 0.999 near their centres: no gradient there)
    W, H = 48, 36
    inputs = splats(400, W, H, seed=0, sigma=(1.0, 6.0), opacity=(0.4, 1.0), opaque=40)
    ours, ref = assert_same(inputs, W, H)
    means, conics, opac = inputs[:3]
    # the stop rule decided the image: without it many pixels would composite past T <= 1e-4
    unstopped = brute_transmittance(means, conics, opac, W, H)
    stopped = unstopped <= TRANSMITTANCE_MIN
    assert int(stopped.sum()) > 200
    # (1 - Σ α_i T_i in float32: the transmittance kept above 1e-4 to within its rounding)
    assert bool((ours[1][stopped] > 0.9 * TRANSMITTANCE_MIN).all())


def test_matches_torch_for_large_gaussians_partly_off_the_image():
    # sigmas up to 30 px on a 40 x 24 image, centres up to 40 px outside it
    W, H = 40, 24
    assert_same(splats(60, W, H, seed=1, sigma=(2.0, 30.0), opacity=(0.2, 0.9), margin=40.0), W, H)


@pytest.mark.parametrize("case", ["no_gaussians", "all_off_image"])
def test_nothing_drawn_gives_the_background_and_zero_gradients(case):
    W, H = 24, 16
    n = 0 if case == "no_gaussians" else 5
    means, conics, opac, depths, radii, values = splats(max(n, 1), W, H, seed=2, sigma=(1.0, 2.0))
    means, conics, opac, depths, radii, values = (t[:n] for t in (means, conics, opac, depths, radii,
                                                                  values))
    means = means + torch.tensor([1000.0, -500.0])            # far outside the image
    acc, trans, grads = composite(rasterize_tiles_numba, means, conics, opac, depths, radii, values, W, H)
    assert acc.shape == (H, W, 4) and trans.shape == (H, W)
    assert bool((acc == 0).all()) and bool((trans == 1).all())
    for g, t in zip(grads, (means, conics, opac, values)):
        assert g is not None and g.shape == t.shape and bool((g == 0).all())


def test_results_do_not_depend_on_the_thread_count_and_torch_keeps_its_one_thread(monkeypatch):
    """Reproducible training runs torch on one thread; the kernels run on numba's count (all
    cores), forward and backward, with the same bits as on one thread, and leave torch at one."""
    import numba

    import volcap_core.splat.composite_numba as cn

    W, H = 40, 32
    inputs = splats(200, W, H, seed=4)
    seen = record_kernel_threads(monkeypatch, cn, "_forward", "_backward")
    cores = numba.config.NUMBA_NUM_THREADS
    all_cores = composite(rasterize_tiles_numba, *inputs, W, H)
    assert torch.get_num_threads() == 1                       # the caller's setting is kept
    assert seen == [cores, cores]
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    one = composite(rasterize_tiles_numba, *inputs, W, H)
    assert seen[2:] == [1, 1]
    for a, b in zip([one[0], one[1], *one[2]], [all_cores[0], all_cores[1], *all_cores[2]]):
        assert torch.equal(a, b)
    ours, ref = TileStats(), TileStats()
    rasterize_tiles_numba(*inputs, W, H, stats=ours)
    rasterize_tiles(*inputs, W, H, stats=ref)
    assert (ours.pairs, ours.intersections) == (ref.pairs, ref.intersections) and ours.pairs > 0


def test_every_compiled_kernels_thread_test_runs_on_two_threads():
    """The thread-count tests of every compiled module, in a process whose kernels may use two
    threads (under `make test`'s workers they have one: tests/conftest.py), so "the same bits on
    one and all threads" compares one thread with two. ~15 s."""
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[2]
    files = ["tests/splat/test_composite_numba.py", "tests/splat/test_project_numba.py",
             "tests/splat/test_colour_numba.py", "tests/splat/test_evaluate_numba.py",
             "tests/splat/test_mcmc_numba.py", "tests/test_adam_numba.py", "tests/calibration/test_guided_numba.py"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_XDIST")}
    env["NUMBA_NUM_THREADS"] = "2"
    probe = subprocess.run([sys.executable, "-c", "import numba; print(numba.config.NUMBA_NUM_THREADS)"],
                           capture_output=True, text=True, env=env, cwd=repo, timeout=120)
    assert probe.stdout.strip() == "2", probe.stderr
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "no:cacheprovider",
                          "-k", "thread and not two_threads", *files],
                         capture_output=True, text=True, env=env, cwd=repo, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert "7 passed" in res.stdout, res.stdout[-2000:]


def test_render_through_numba_matches_torch_rgb_alpha_depth_and_3d_gradients():
    assert_numba_render_matches_torch(random_gaussians(300, seed=3, scale=(0.02, 0.2)),
                                      ring_cameras(1, size=40)[0])


def test_render_flow_through_numba_matches_torch():
    g = random_gaussians(120, seed=6, scale=(0.03, 0.15))
    moved = Gaussians3D(g.means + 0.02 * torch.randn(120, 3, generator=torch.Generator().manual_seed(1)),
                        g.quats, g.scales, g.opacities, g.sh, g.ids)
    cam = ring_cameras(1, size=32)[0]
    ours = render_flow(g, moved, cam, cam, backend="numba")
    ref = render_flow(g, moved, cam, cam, backend="torch")
    assert bool((ref["alpha"] > 0.5).any())
    assert torch.allclose(ours["alpha"], ref["alpha"], atol=1e-5)
    assert torch.allclose(ours["flow"], ref["flow"], atol=1e-3)


def test_numba_is_chosen_for_float32_cpu_tensors_only():
    assert resolve_backend("numba", "cpu").name == "numba"
    assert resolve_backend("auto", "cpu").name == "numba"                 # since 2026-11-28
    assert resolve_backend("auto", "cpu", torch.float64).name == "torch"   # references in float64
    with pytest.raises(BackendUnavailable, match="backend 'numba' composites on the CPU"):
        resolve_backend("numba", "cuda")
    means, conics, opac, depths, radii, values = splats(3, 8, 8, seed=0)
    with pytest.raises(ValueError, match="float32 CPU tensors: values is torch.float64"):
        rasterize_tiles_numba(means, conics, opac, depths, radii, values.double(), 8, 8)


def test_a_segment_trains_through_numba_as_through_torch():
    """The first half of the CPU training test's run (tests/splat/test_splat_train.py: 120 of its
    240 steps, ~3 s in all) through each back-end: the numba one must learn as much (held-out PSNR
    within 0.5 dB of torch's; 28.35 against 28.36 dB when written, 22.50 untrained)."""
    from volcap_core.splat.model import Poly4DGSConfig
    from volcap_core.splat.train import TrainConfig, train_segment

    data, points, _ = moving_scene()
    runs = {}
    for backend in ("numba", "torch"):
        cfg = TrainConfig(model=Poly4DGSConfig.paper(sh_degree=0), grid_size=4, checkpoint_every=0,
                          held_out_cameras=["3"], steps=120, eval_every=120, backend=backend,
                          mcmc=dict(refine_start=60, refine_every=40, refine_stop=10_000, cap_max=600))
        runs[backend] = train_segment(data, points, cfg, seed=0)
    print("held-out PSNR:", {b: [round(e.psnr, 2) for e in r.history] for b, r in runs.items()},
          "wall s:", {b: round(r.wall_s, 1) for b, r in runs.items()})
    ours, ref = runs["numba"], runs["torch"]
    assert ours.backend.name == "numba"
    assert ours.history[-1].psnr > ours.history[0].psnr + 5.0 and ours.history[-1].psnr > 26.0
    assert abs(ours.history[-1].psnr - ref.history[-1].psnr) < 0.5
