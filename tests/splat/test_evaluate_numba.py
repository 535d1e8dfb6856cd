"""The compiled slice (``model.evaluate`` of float32 CPU parameters) reproduces the PyTorch
``evaluate``: the same live Gaussians, their values within float32 rounding and gradients to every
parameter within 1e-3 relative of float64, for each config's degrees and every numerical guard, on
any thread count; float64 models keep the PyTorch path."""

import math
import sys
from pathlib import Path

import numba
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import single_thread  # noqa: E402, F401

import volcap_core.splat.evaluate_numba as en  # noqa: E402
import volcap_core.splat.model as model_mod  # noqa: E402
from volcap_core.splat.model import (  # noqa: E402
    LOG_SCALE_MAX,
    MAX_ABS_DT,
    STATIC_LOG_LAMBDA,
    Poly4DGS,
    Poly4DGSConfig,
    evaluate,
)

pytestmark = pytest.mark.usefixtures("single_thread")

OUTPUTS = ("means", "quats", "scales", "opacities", "sh")
T = 1.0

CONFIGS = {
    "paper_sh3": Poly4DGSConfig.paper(),
    "static_sh0": Poly4DGSConfig.static(sh_degree=0),
    "rotor4d_sh1": Poly4DGSConfig.rotor4d(sh_degree=1),
    "high_degrees_sh2": Poly4DGSConfig(mean_degree=3, quat_degree=2, scale_degree=2,
                                       opacity_degree=3, sh_degree=2),
    "linear_colour": Poly4DGSConfig(sh_degree=3, colour_space="linear"),
}


def random_model(config: Poly4DGSConfig, n: int = 300, seed: int = 0) -> Poly4DGS:
    """Random parameters: centres within 2 s of ``T``, lifespans spanning decades (some
    Gaussians dead at ``T``), peak opacities from ~0 to ~1."""
    g = torch.Generator().manual_seed(seed)
    p = {name: 0.5 * torch.randn((n, *shape), generator=g)
         for name, shape in config.param_shapes().items()}
    p["opacities"] = 3.0 * torch.randn(n, generator=g)
    if "t0" in p:
        p["t0"] = T + 2.0 * (torch.rand(n, generator=g) - 0.5)
    if "log_lambdas" in p:
        p["log_lambdas"] = 1.0 + 1.5 * torch.randn(p["log_lambdas"].shape, generator=g)
    return Poly4DGS(config, p)


def sliced(model: Poly4DGS, dtype=torch.float32, *, t: float = T, seed: int = 3):
    """``evaluate`` of ``model`` cast to ``dtype`` at ``t``, and the gradients of a random
    weighting of its outputs to the parameters (dict by name)."""
    leaves = {k: v.detach().to(dtype).clone().requires_grad_(True)
              for k, v in model.params.items()}
    gs = evaluate(Poly4DGS(model.config, leaves), t)
    g = torch.Generator().manual_seed(seed)
    loss = sum((getattr(gs, k) * torch.randn(getattr(gs, k).shape, generator=g,
                                             dtype=torch.float64).to(dtype)).sum()
               for k in OUTPUTS)
    if len(gs):
        loss.backward()
    return gs, {k: v.grad for k, v in leaves.items()}


def torch_path(monkeypatch, model, **kw):
    """The PyTorch ``evaluate`` of float32 parameters (the compiled path switched off)."""
    with monkeypatch.context() as m:
        m.setattr(model_mod, "_numba_slicer", lambda: None)
        return sliced(model, **kw)


def assert_matches_torch(monkeypatch, model, *, t: float = T):
    """Same live ids as the float32 and float64 PyTorch paths; values within float32 rounding of
    float64 and gradients within 1e-3 relative of it; exactly zero gradient on dropped rows.
    Returns the compiled slice and its gradients."""
    ours, g_ours = sliced(model, t=t)
    ref32, _ = torch_path(monkeypatch, model, t=t)
    ref, g_ref = sliced(model, torch.float64, t=t)
    assert ours.means.grad_fn is not None and "SliceNumba" in type(ours.means.grad_fn).__name__
    assert torch.equal(ours.ids, ref32.ids) and torch.equal(ours.ids, ref.ids)
    assert ours.colour_space == model.config.colour_space
    for k in OUTPUTS:
        a, b = getattr(ours, k).detach(), getattr(ref, k).detach()
        assert a.dtype == torch.float32 and a.shape == b.shape, k
        err = float(((a.double() - b).abs() / b.abs().clamp(min=1.0)).max()) if a.numel() else 0.0
        assert err < 1e-5, (k, err)
    dropped = torch.ones(len(model), dtype=torch.bool)
    dropped[ours.ids] = False
    assert set(g_ours) == set(model.params)
    for k, g in g_ours.items():
        # the PyTorch path gives a NaN parameter (a NaN opacity logit) a NaN gradient through the
        # envelope of all N; the compiled one differentiates the live Gaussians only: exactly 0
        r = torch.nan_to_num(g_ref[k], nan=0.0)
        assert g.dtype == torch.float32 and bool(torch.isfinite(g).all()), k
        assert not bool(g[dropped].any()), k
        if r.abs().max() > 0:
            err = float((g.double() - r).abs().max() / r.abs().max())
            assert err < 1e-3, (k, err)
        else:
            assert not bool(g.any()), k
    return ours, g_ours


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_values_and_gradients_match_torch_for_each_config(monkeypatch, name):
    model = random_model(CONFIGS[name])
    ours, _ = assert_matches_torch(monkeypatch, model)
    assert 0 < len(ours) < len(model)        # some Gaussians dropped, most live
    assert ours.sh.shape[1:] == (model.config.param_shapes().get("shN", (0, 3))[0] + 1, 3)


def test_gaussians_outside_their_lifespan_and_nan_opacities_are_dropped(monkeypatch):
    model = random_model(Poly4DGSConfig.paper(), seed=1)
    p = model.params
    p["t0"][:10] = T + 50.0                  # far outside a lifespan of ~1 s
    p["log_lambdas"][:10] = 0.0
    p["opacities"][10:20] = float("nan")
    p["opacities"][20:30] = 8.0              # near-opaque and alive: kept
    p["log_lambdas"][20:30] = STATIC_LOG_LAMBDA
    ours, grads = assert_matches_torch(monkeypatch, model)
    live = set(ours.ids.tolist())
    assert live.isdisjoint(range(20)) and live.issuperset(range(20, 30))
    assert not bool(grads["opacities"][10:20].any())   # a NaN logit poisons no gradient


def test_guards_dt_at_its_cap_dt_zero_and_clamped_log_scales(monkeypatch):
    config = Poly4DGSConfig(mean_degree=2, quat_degree=1, scale_degree=1, opacity_degree=2)
    model = random_model(config, seed=2)
    p = model.params
    p["log_lambdas"][:20] = STATIC_LOG_LAMBDA - 40.0   # alive at |dt| = MAX_ABS_DT
    p["opacities"][:20] = 4.0
    p["means_t"][:20] *= 1e-12
    p["quats_t"][:20] *= 1e-6
    p["scales_t"][:20] = 0.0
    p["t0"][:10] = T - 3 * MAX_ABS_DT                 # dt clamped to +MAX_ABS_DT
    p["t0"][10:20] = T + 3 * MAX_ABS_DT               # and to -MAX_ABS_DT
    p["t0"][20:30] = T                                 # dt exactly 0: log|dt| floored
    p["opacities"][20:30] = 4.0
    p["scales"][30:40] = LOG_SCALE_MAX + 1.0           # clamped: no scale gradient
    p["opacities"][30:40] = 4.0
    p["t0"][30:40] = T
    ours, grads = assert_matches_torch(monkeypatch, model)
    live = set(ours.ids.tolist())
    assert live.issuperset(range(40))
    assert not bool(grads["t0"][:20].any())           # outside the clamp: no t0 gradient
    assert bool(grads["log_lambdas"][:20].any())
    assert not bool(grads["scales"][30:40].any()) and not bool(grads["scales_t"][30:40].any())
    row = ours.ids.tolist().index(30)
    assert torch.allclose(ours.scales[row].detach(), torch.full((3,), math.exp(LOG_SCALE_MAX)))


def test_same_bits_on_one_and_all_threads(monkeypatch):
    model = random_model(Poly4DGSConfig.paper(), n=2000, seed=4)
    all_cores = sliced(model)
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    one = sliced(model)
    assert torch.get_num_threads() == 1                # the caller's torch setting is kept
    for k in (*OUTPUTS, "ids"):
        assert torch.equal(getattr(one[0], k), getattr(all_cores[0], k)), k
    for k in model.params:
        assert torch.equal(one[1][k], all_cores[1][k]), k


def test_float64_takes_the_torch_path_and_float32_the_compiled_one(monkeypatch):
    calls = []
    real = en.slice_poly4dgs_numba

    def spy(*a, **kw):
        calls.append(a[0]["means"].dtype)
        return real(*a, **kw)

    monkeypatch.setattr(model_mod, "_numba_slicer", lambda: spy)
    model = random_model(Poly4DGSConfig.paper(), n=50)
    gs64, _ = sliced(model, torch.float64)
    assert calls == [] and gs64.means.dtype == torch.float64
    sliced(model)
    assert calls == [torch.float32]


def test_rejects_tensors_it_cannot_take():
    model = random_model(Poly4DGSConfig.static(), n=5)
    params = dict(model.params, means=model.params["means"].double())
    with pytest.raises(ValueError, match="means is torch.float64"):
        en.slice_poly4dgs_numba(params, T, 1 / 255, max_abs_dt=MAX_ABS_DT, log_term_cap=80.0,
                                log_scale_min=-30.0, log_scale_max=LOG_SCALE_MAX)
