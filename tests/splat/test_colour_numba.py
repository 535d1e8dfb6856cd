"""The compiled survivors' colours (backend "numba") reproduce ``gaussian_colours`` of the selected
Gaussians: values within float32 rounding and gradients to the SH rows and means within 1e-3
relative of float64, for SH degrees 0..3 and both colour spaces, on any thread count; a render
through "numba" colours with them, matches "torch" and still culls a non-finite colour."""

import sys
from pathlib import Path

import numba
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import assert_numba_render_matches_torch, random_gaussians, record_kernel_threads, ring_cameras, single_thread  # noqa: E402, F401  (single_thread: fixture)

import volcap_core.splat.colour_numba as cnb  # noqa: E402
from volcap_core.splat.colour_numba import survivor_colours_numba  # noqa: E402
from volcap_core.splat.model import Gaussians3D  # noqa: E402
from volcap_core.splat.render import gaussian_colours  # noqa: E402

pytestmark = pytest.mark.usefixtures("single_thread")

CAMERA = ring_cameras(3, size=24)[1]


def scene(sh_degree: int, n: int = 200, seed: int = 0):
    """Random SH rows and means around the origin, and the ids of ~60 % of them (ascending)."""
    g = random_gaussians(n, seed=seed, spread=1.0, sh_degree=sh_degree)
    ids = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[: n * 3 // 5].sort()
    return g.sh, g.means, ids.values


def coloured(sh, means, ids, space, dtype=torch.float32, *, compiled=True):
    """The colours of ``ids`` (compiled, or ``gaussian_colours`` of the selection) and the
    gradients of a fixed random weighting of them to ``sh`` and ``means``."""
    s = sh.detach().to(dtype).clone().requires_grad_(True)
    m = means.detach().to(dtype).clone().requires_grad_(True)
    if compiled:
        c = survivor_colours_numba(s, m, ids, CAMERA.centre, linearise=space != "linear")
    else:
        g = Gaussians3D(means=m, quats=m, scales=m, opacities=m[:, 0], sh=s,
                        ids=torch.arange(len(m)), colour_space=space)
        c = gaussian_colours(g.select(ids), CAMERA)
    w = torch.randn(c.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    (c * w.to(dtype)).sum().backward()
    return c.detach(), s.grad, m.grad


@pytest.mark.parametrize("space", ["srgb_unbounded", "linear"])
@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_values_and_gradients_match_gaussian_colours(sh_degree, space):
    sh, means, ids = scene(sh_degree)
    c, g_sh, g_means = coloured(sh, means, ids, space)
    ref, r_sh, r_means = coloured(sh, means, ids, space, torch.float64, compiled=False)
    assert c.dtype == torch.float32 and c.shape == (len(ids), 3)
    assert float(((c.double() - ref).abs() / ref.abs().clamp(min=1.0)).max()) < 1e-5
    unused = torch.ones(len(means), dtype=torch.bool)
    unused[ids] = False
    assert not bool(g_sh[unused].any())
    assert float((g_sh.double() - r_sh).abs().max() / r_sh.abs().max()) < 1e-3
    if sh_degree == 0:                              # no view dependence: no gradient to the means
        assert g_means is None and r_means is None
    else:
        assert not bool(g_means[unused].any())
        assert float((g_means.double() - r_means).abs().max() / r_means.abs().max()) < 1e-3


def test_a_gaussian_at_the_camera_centre_gets_its_dc_colour():
    sh, means, ids = scene(3, n=20)
    means[ids[0]] = CAMERA.centre.float()
    c, _, g_means = coloured(sh, means, ids, "linear")
    assert torch.allclose(c[0], 0.28209479177387814 * sh[ids[0], 0] + 0.5)
    assert bool(torch.isfinite(g_means).all())


def test_same_bits_on_one_and_all_threads(monkeypatch):
    sh, means, ids = scene(3, n=3000, seed=2)
    all_cores = coloured(sh, means, ids, "srgb_unbounded")
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    one = coloured(sh, means, ids, "srgb_unbounded")
    assert torch.get_num_threads() == 1
    for a, b in zip(one, all_cores):
        assert torch.equal(a, b)


def test_render_through_numba_colours_with_the_kernel_and_culls_non_finite_colours(monkeypatch):
    calls = record_kernel_threads(monkeypatch, cnb, "_forward")
    g0 = random_gaussians(300, seed=11, spread=1.2, scale=(0.02, 0.25), sh_degree=3)
    g0.sh[5] = float("nan")                         # culled: no NaN in the image or gradients
    g0.sh[6, 0] = 1e20                              # its decoded colour overflows to inf: culled
    _, gn = assert_numba_render_matches_torch(g0, ring_cameras(2, size=40)[1])
    assert len(calls) == 2                          # the colours, then again without the culled
    for k in gn:
        assert not bool(gn[k][5:7].any()), k


def test_float32_cpu_tensors_only():
    sh, means, ids = scene(1, n=5)
    with pytest.raises(ValueError, match="float32 CPU tensors: sh is torch.float64"):
        survivor_colours_numba(sh.double(), means, ids, CAMERA.centre, linearise=True)
