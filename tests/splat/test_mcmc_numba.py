"""MCMC's position noise through the compiled kernel (volcap_core.splat.mcmc_numba) moves every
Gaussian bit for bit as the torch code does and leaves the generator where the torch code leaves
it, on one thread or all; float64 models take the torch code."""

import sys
from pathlib import Path

import pytest
import torch

numba = pytest.importorskip("numba")

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import record_kernel_threads, single_thread  # noqa: E402, F401  (fixture)

from volcap_core.splat import mcmc, mcmc_numba  # noqa: E402
from volcap_core.splat.mcmc import MCMCConfig, inject_noise  # noqa: E402
from volcap_core.splat.model import LOG_SCALE_MAX, LOG_SCALE_MIN, Poly4DGS, Poly4DGSConfig  # noqa: E402


pytestmark = pytest.mark.usefixtures("single_thread")


def _model(n: int = 2000, seed: int = 0) -> Poly4DGS:
    """Gaussians whose gates span dead to opaque, with unnormalised quaternions (one zero: R = I;
    one of norm 1e-9, below the normalisation's eps 1e-8), scales beyond both clamps and means far from the origin (so a move rounds)."""
    g = torch.Generator().manual_seed(seed)
    m = Poly4DGS.from_points(Poly4DGSConfig.paper(sh_degree=0), 30 * torch.randn(n, 3, generator=g),
                             torch.rand(n, 3, generator=g), scales=torch.full((n,), 0.05),
                             t0=torch.rand(n, generator=g))
    p = m.params
    with torch.no_grad():
        p["opacities"].copy_(torch.randn(n, generator=g) * 4 - 5)      # o_0 from ~1e-6 to ~0.5
        p["quats"].copy_(torch.randn(n, 4, generator=g) * torch.rand(n, 1, generator=g) * 3)
        p["quats"][0] = 0.0
        p["quats"][2] = torch.tensor([0.3, -0.5, 0.7, 0.4]) * 1e-9
        p["scales"].copy_(torch.randn(n, 3, generator=g) * 3 - 3)
        p["scales"][1] = torch.tensor([LOG_SCALE_MIN - 1.0, LOG_SCALE_MAX + 1.0, 0.0])
    return m


def _noise(model: Poly4DGS, seed: int = 5) -> torch.Generator:
    gen = torch.Generator().manual_seed(seed)
    inject_noise(model, 1.6e-4 * 4.0, MCMCConfig(), gen, scene_scale=4.0)
    return gen


def test_compiled_noise_is_the_torch_move_bit_for_bit(monkeypatch):
    calls = record_kernel_threads(monkeypatch, mcmc_numba, "add_position_noise")
    compiled, start = _model(), _model()
    gen_compiled = _noise(compiled)
    assert len(calls) == 1
    monkeypatch.setattr(mcmc, "_compiled_noise", lambda: None)
    reference = _model()
    gen_reference = _noise(reference)
    assert torch.equal(compiled.params["means"], reference.params["means"])
    assert torch.equal(gen_compiled.get_state(), gen_reference.get_state())
    moved = (compiled.params["means"] != start.params["means"]).any(1)
    assert moved.sum() > 1000                                   # the noise moved most Gaussians


def test_compiled_noise_bits_do_not_depend_on_the_thread_count(monkeypatch):
    seen = record_kernel_threads(monkeypatch, mcmc_numba, "_add_noise")
    cores = numba.config.NUMBA_NUM_THREADS
    small = _model()
    _noise(small)                                               # 2000 Gaussians: one thread
    monkeypatch.setattr(mcmc_numba, "_PARALLEL_MIN", 1000)
    all_cores = _model()
    _noise(all_cores)
    assert torch.get_num_threads() == 1                        # the caller's setting is kept
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    one = _model()
    _noise(one)
    assert seen == [1, cores, 1]
    assert torch.equal(all_cores.params["means"], one.params["means"])
    assert torch.equal(small.params["means"], one.params["means"])


def test_float64_models_take_the_torch_code(monkeypatch):
    monkeypatch.setattr(mcmc_numba, "add_position_noise", lambda *a: pytest.fail("compiled path taken"))
    model, start = _model(200), _model(200)
    for k, v in model.params.items():
        model.params[k] = v.detach().double()
    _noise(model)
    moved = model.params["means"] - start.params["means"].double()
    assert model.params["means"].dtype == torch.float64 and (moved != 0).any()
