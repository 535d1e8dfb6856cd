"""The compiled Adam (volcap_core.adam_numba) is adam_step's torch update bit for bit: with float
and tensor rates, over several steps (the bias correction changes), for frozen parameters and
parameters without a gradient, on one thread or all; float64 and non-contiguous parameters take
the torch code."""

import sys
from pathlib import Path

import pytest
import torch

numba = pytest.importorskip("numba")

sys.path.insert(0, str(Path(__file__).resolve().parent / "splat"))  # _splat_scenes, any import mode

from _splat_scenes import record_kernel_threads, single_thread  # noqa: E402, F401  (fixture)

from volcap_core import adam_numba, checkpoint  # noqa: E402
from volcap_core.checkpoint import AdamState, adam_step  # noqa: E402

if torch.backends.cpu.get_cpu_capability() not in adam_numba._FUSED_CAPABILITIES:
    pytest.skip("torch's CPU kernels here do not fuse add_/addcmul_: the torch code runs",
                allow_module_level=True)


pytestmark = pytest.mark.usefixtures("single_thread")


def _params(dtype=torch.float32):
    """Parameters of the trainer's kinds and sizes that are no multiple of a SIMD width."""
    g = torch.Generator().manual_seed(0)
    shapes = {"means": (1001, 3), "means_t": (777, 4, 3), "opacities": (1003,), "per_row": (65, 5),
              "frozen": (50, 3), "absent": (40,), "no_grad": (30, 2), "scalar": ()}
    return {k: torch.randn(s, generator=g, dtype=dtype).requires_grad_(True) for k, s in shapes.items()}


def _rates(step: int, dtype=torch.float32):
    return {"means": 1.6e-4 * 0.99 ** step, "opacities": 0.05, "frozen": 0.0, "scalar": 1e-3,
            "means_t": torch.tensor([1e-3, 2e-4, 3e-5, 4e-6], dtype=dtype).view(1, 4, 1),
            "per_row": torch.linspace(1e-4, 1e-2, 65, dtype=dtype).view(65, 1)}


def _train(steps: int = 4, *, eps: float = 1e-15, dtype=torch.float32):
    """``steps`` Adam steps on :func:`_params`; each element's gradient has a magnitude of its own
    from 1e-22 (where eps rules the denominator) to 1e2, kept over the steps (so the moments and
    the new gradient's terms are of one size, where every rounding shows), exact zeros among them.
    Returns the parameters and the state."""
    params, g = _params(dtype), torch.Generator().manual_seed(1)
    size = {k: 10.0 ** (torch.rand(p.shape, generator=g, dtype=torch.float64) * 24 - 22)
            for k, p in params.items()}
    state = AdamState.zeros_like(params)
    for step in range(steps):
        for name, p in params.items():
            if name == "no_grad":
                continue
            grad = torch.randn(p.shape, generator=g, dtype=torch.float64) * size[name]
            p.grad = torch.where(torch.rand(p.shape, generator=g) < 0.1, 0.0, grad).to(dtype)
        adam_step(params, _rates(step, dtype), state, eps=eps)
    return params, state


def _torch_only(monkeypatch):
    monkeypatch.setattr(checkpoint, "_compiled_adam", lambda: None)


def _assert_same(a, b):
    (pa, sa), (pb, sb) = a, b
    assert sa.step == sb.step
    for name in pa:
        assert torch.equal(pa[name], pb[name]), name
        assert torch.equal(sa.exp_avg[name], sb.exp_avg[name]), name
        assert torch.equal(sa.exp_avg_sq[name], sb.exp_avg_sq[name]), name


@pytest.mark.parametrize("eps", [1e-15, 1e-8])          # the splat trainer's, the enhancer's
def test_compiled_adam_is_the_torch_update_bit_for_bit(monkeypatch, eps):
    updated = record_kernel_threads(monkeypatch, adam_numba, "adam_update")
    compiled = _train(eps=eps)
    # every parameter with a gradient and a rate went through the kernels, 4 steps each
    assert len(updated) == 4 * 5
    monkeypatch.undo()
    _torch_only(monkeypatch)
    reference = _train(eps=eps)
    _assert_same(compiled, reference)
    params, state = compiled
    start = _params()
    for name in ("frozen", "absent", "no_grad"):              # untouched, moments still zero
        assert torch.equal(params[name], start[name])
        assert not state.exp_avg[name].any() and not state.exp_avg_sq[name].any()
    assert not torch.equal(params["means_t"], start["means_t"])


def test_compiled_adam_bits_do_not_depend_on_the_thread_count(monkeypatch):
    seen = record_kernel_threads(monkeypatch, adam_numba, "_moments")
    cores = numba.config.NUMBA_NUM_THREADS
    monkeypatch.setattr(adam_numba, "_PARALLEL_MIN", 1000)      # all but the smallest on all cores
    all_cores = _train(steps=2)
    # per step: means, means_t, opacities on all cores; per_row and scalar on one thread
    assert seen == [cores, cores, cores, 1, 1] * 2
    assert torch.get_num_threads() == 1                     # the caller's setting is kept
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    one = _train(steps=2)
    assert seen[10:] == [1] * 10
    _assert_same(all_cores, one)


def test_float64_and_non_contiguous_parameters_take_the_torch_code(monkeypatch):
    monkeypatch.setattr(adam_numba, "adam_update", lambda *a, **k: pytest.fail("compiled path taken"))
    params, _ = _train(steps=2, dtype=torch.float64)
    start = _params(torch.float64)
    assert params["means"].dtype == torch.float64 and not torch.equal(params["means"], start["means"])
    p = torch.randn(3, 40).t().requires_grad_(True)           # a transposed view: not contiguous
    before = p.detach().clone()
    p.grad = torch.ones_like(p)
    adam_step({"p": p}, {"p": 1e-2}, AdamState.zeros_like({"p": p}))
    # Adam's first step with a constant gradient moves every element by the rate
    assert torch.allclose(p.detach(), before - 1e-2)
