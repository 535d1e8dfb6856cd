"""3DGS-MCMC relocation, growth and noise on Poly4DGS models."""

import math

import pytest
import torch

from volcap_core.checkpoint import AdamState
from volcap_core.splat.mcmc import (
    MCMCConfig,
    add_gaussians,
    inject_noise,
    mcmc_regulariser,
    relocate_dead,
    relocation_opacity_scale,
)
from volcap_core.splat.model import Poly4DGS, Poly4DGSConfig


def _model(n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = Poly4DGS.from_points(Poly4DGSConfig.paper(sh_degree=1), torch.randn(n, 3, generator=g),
                             torch.rand(n, 3, generator=g), scales=torch.full((n,), 0.05),
                             t0=torch.rand(n, generator=g))
    for k, v in m.params.items():
        if k != "t0":
            v.add_(0.1 * torch.randn(v.shape, generator=g))
    return m


@pytest.mark.parametrize("o", [0.01, 0.3, 0.9, 1 - 1e-7])
@pytest.mark.parametrize("n", [1, 2, 7, 51])
def test_split_preserves_opacity_and_1d_opacity_mass(o, n):
    o_new, s_new = relocation_opacity_scale(torch.tensor([o]), torch.tensor([[1.0, 2.0, 3.0]]),
                                            torch.tensor([n]))
    assert torch.isfinite(o_new).all() and torch.isfinite(s_new).all()
    o_new, s = float(o_new), float(s_new[0, 0])
    # N stacked copies composite to the original peak opacity ...
    assert 1 - (1 - o_new) ** n == pytest.approx(o, rel=1e-5)
    # ... and carry the same 1D opacity mass: ∫ 1 - (1 - o_new e^{-x²/2s²})^N dx = o·sqrt(2π)
    x = torch.linspace(-30, 30, 200001, dtype=torch.float64)
    mass = torch.trapezoid(1 - (1 - o_new * torch.exp(-x * x / (2 * s * s))) ** n, x)
    assert float(mass) == pytest.approx(o * math.sqrt(2 * math.pi), rel=1e-4)


def test_relocation_moves_dead_onto_live_copies_everything_and_resets_moments():
    m = _model()
    adam = AdamState.zeros_like(m.params)
    for d in (adam.exp_avg, adam.exp_avg_sq):
        for v in d.values():
            v.fill_(1.0)
    m.params["opacities"][:10] = -10.0  # o_0 ≈ 4.5e-5: dead
    cfg = MCMCConfig()
    n = relocate_dead(m, adam, cfg, torch.Generator().manual_seed(0))
    assert n == 10 and len(m) == 40
    o0 = torch.sigmoid(m.params["opacities"])
    assert (o0 >= cfg.min_opacity).all()
    for i in range(10):  # each dead slot is now an exact copy of a live (sampled) Gaussian
        src = [j for j in range(10, 40)
               if torch.equal(m.params["means_t"][j], m.params["means_t"][i])]
        assert src, "relocated Gaussian must copy a live one's coefficients"
        j = src[0]
        for name in ("means", "quats_t", "log_lambdas", "t0", "shN", "opacities", "scales"):
            assert torch.equal(m.params[name][i], m.params[name][j]), name
        assert (adam.exp_avg["means"][i] == 0).all() and (adam.exp_avg_sq["means"][j] == 0).all()


def test_growth_is_five_percent_and_capped():
    m = _model(40)
    adam = AdamState.zeros_like(m.params)
    gen = torch.Generator().manual_seed(1)
    assert add_gaussians(m, adam, MCMCConfig(), gen) == 2 and len(m) == 42
    assert all(v.shape[0] == 42 for v in adam.exp_avg.values())
    assert add_gaussians(m, adam, MCMCConfig(cap_max=43), gen) == 1 and len(m) == 43
    assert add_gaussians(m, adam, MCMCConfig(cap_max=43), gen) == 0


def test_noise_moves_transparent_gaussians_not_opaque_ones():
    m = _model(20)
    m.params["opacities"][:10] = 6.0    # o ≈ 0.9975
    m.params["opacities"][10:] = -7.0   # o ≈ 0.0009
    before = m.params["means"].clone()
    inject_noise(m, 1.6e-4, MCMCConfig(), torch.Generator().manual_seed(0))
    moved = (m.params["means"] - before).norm(dim=1)
    assert moved[:10].max() < 1e-6 * moved[10:].min()
    assert (moved[10:] > 0).all()


@pytest.mark.parametrize("logit", [-200.0, -math.inf])
def test_all_opacities_zero_means_nothing_to_sample(logit):
    # every o_0 underflowed to 0 (float32 sigmoid of < -104, reached at 300-1000x the learning
    # rate): before, add_gaussians divided 0/0 and torch.multinomial raised
    m = _model(20)
    m.params["opacities"].fill_(logit)
    assert float(torch.sigmoid(m.params["opacities"]).max()) == 0.0
    before = {k: v.clone() for k, v in m.params.items()}
    adam = AdamState.zeros_like(m.params)
    gen = torch.Generator().manual_seed(0)
    state = gen.get_state()
    assert relocate_dead(m, adam, MCMCConfig(), gen) == 0
    assert add_gaussians(m, adam, MCMCConfig(), gen) == 0
    assert len(m) == 20 and all(v.shape[0] == 20 for v in adam.exp_avg.values())
    for k, v in m.params.items():
        assert torch.equal(v, before[k]), k
    assert torch.equal(gen.get_state(), state)          # no random draw was spent either


def test_non_finite_opacities_are_never_sampled():
    # before: a NaN o_0 counted as alive, its NaN weight reached torch.multinomial, which raised
    m = _model(40)
    m.params["opacities"][:10] = -10.0                   # dead
    m.params["opacities"][10:14] = math.nan
    m.params["opacities"][14:16] = math.inf              # o_0 = 1, but a non-finite logit
    adam = AdamState.zeros_like(m.params)
    gen = torch.Generator().manual_seed(0)
    # the dead and the NaN Gaussians are replaced by copies of live finite ones
    assert relocate_dead(m, adam, MCMCConfig(), gen) == 14
    logit = m.params["opacities"]
    assert torch.isfinite(logit[:14]).all() and (torch.sigmoid(logit[:14]) >= 0.005).all()
    assert torch.equal(logit[14:16], torch.full((2,), math.inf))   # never a source: untouched
    for i in range(14):
        assert any(torch.equal(m.params["means_t"][i], m.params["means_t"][j])
                   for j in range(16, 40))
    # growth samples only finite ones; with only non-finite left there is nothing to sample
    assert add_gaussians(m, adam, MCMCConfig(), gen) == 2
    assert torch.isfinite(m.params["opacities"][40:]).all()
    m.params["opacities"][:] = math.nan
    m.params["opacities"][:3] = math.inf
    assert relocate_dead(m, adam, MCMCConfig(), gen) == 0
    assert add_gaussians(m, adam, MCMCConfig(), gen) == 0


def test_noise_is_scale_invariant():
    # a scene k times larger (means and scales × k) trained with lr × k and scene_scale × k moves
    # by exactly k times as much: the noise is relative to the scene, like gsplat's in its
    # normalised world. Before, the noise scaled as Σ · lr = k³ (no scene_scale argument).
    # (float64 so that reading the displacement back off the means loses nothing)
    def model(k):
        m = _model(30, seed=2)
        for name in m.params:
            m.params[name] = m.params[name].double()
        m.params["opacities"][:15] = -7.0                # transparent: they move
        m.params["means"].mul_(k)
        m.params["scales"].add_(math.log(k))             # log-scales: s × k
        return m

    def displacement(k, lr, scene_scale):
        m = model(k)
        before = m.params["means"].clone()
        inject_noise(m, lr, MCMCConfig(), torch.Generator().manual_seed(5),
                     scene_scale=scene_scale)
        return m.params["means"] - before

    base = displacement(1.0, 1.6e-4 * 2.0, 2.0)
    assert base[:15].norm(dim=1).min() > 0
    for k in (7.3, 0.01, 1e3):
        torch.testing.assert_close(displacement(k, 1.6e-4 * 2.0 * k, 2.0 * k), k * base,
                                   rtol=1e-9, atol=1e-15 * k)
    # scene_scale divides the noise by scene_scale²; the default is 1 (the old formula)
    torch.testing.assert_close(displacement(1.0, 1.6e-4 * 2.0, 1.0), 4.0 * base,
                               rtol=1e-12, atol=0.0)
    m = model(1.0)
    before = m.params["means"].clone()
    inject_noise(m, 1.6e-4 * 2.0, MCMCConfig(), torch.Generator().manual_seed(5))
    torch.testing.assert_close(m.params["means"] - before, 4.0 * base, rtol=1e-12, atol=0.0)


def test_regulariser_is_differentiable():
    m = _model(10)
    for v in m.params.values():
        v.requires_grad_(True)
    mcmc_regulariser(m, MCMCConfig()).backward()
    assert (m.params["opacities"].grad > 0).all() and (m.params["scales"].grad > 0).all()


def _grown_from(m: Poly4DGS, adam: AdamState | None, cfg: MCMCConfig, first: int) -> tuple[int, torch.Tensor]:
    """Grow ``m`` once (seeded): how many copies came from Gaussians ``first`` onward (each copy
    sits on its source), and the copies' means."""
    before = m.params["means"].detach().clone()
    n = add_gaussians(m, adam, cfg, torch.Generator().manual_seed(3))
    new = m.params["means"][-n:]
    return int((torch.cdist(new, before).argmin(dim=1) >= first).sum()), new


def test_moving_weight_spends_growth_on_the_performers():
    """Half the Gaussians static (unbounded lifespan), half moving, same opacities: growth copies
    sources ∝ opacity (about half moving) unless ``moving_weight`` favours the moving ones; with
    weight 1 the draws are exactly those of a config without the field."""
    from volcap_core.splat.model import STATIC_LOG_LAMBDA

    def half_static() -> Poly4DGS:
        m = _model(n=400)
        m.params["opacities"].fill_(0.0)
        m.params["log_lambdas"][:200] = STATIC_LOG_LAMBDA
        return m

    even, new_even = _grown_from(half_static(), None, MCMCConfig(grow_rate=0.5, moving_weight=1.0), 200)
    favoured, _ = _grown_from(half_static(), None, MCMCConfig(grow_rate=0.5, moving_weight=9.0), 200)
    assert 70 <= even <= 130                      # ~half of 200
    assert favoured >= 170                        # ~90 %
    _, unweighted = _grown_from(half_static(), None, MCMCConfig(grow_rate=0.5), 200)
    assert torch.equal(unweighted, new_even)


def test_gradient_weight_sends_growth_where_the_loss_still_pulls():
    """Same opacities everywhere; a quarter of the Gaussians carry a large positional gradient in
    Adam's second moment (an under-fit region). Without the weight growth copies about a quarter
    of its sources from them; with ``gradient_weight`` most; off (0) the draws are exactly those
    of a config without the field, and it is left out of the config's JSON."""
    def pulled() -> tuple[Poly4DGS, AdamState]:
        m = _model(n=400)
        m.params["opacities"].fill_(0.0)
        adam = AdamState.zeros_like(m.params)
        adam.exp_avg_sq["means"][:] = 1e-8
        adam.exp_avg_sq["means"][300:] = 1e-4            # RMS gradient 100x the rest's
        return m, adam

    even, new_even = _grown_from(*pulled(), MCMCConfig(grow_rate=0.5, gradient_weight=0.0), 300)
    favoured, _ = _grown_from(*pulled(), MCMCConfig(grow_rate=0.5, gradient_weight=2.0), 300)
    assert 30 <= even <= 70                               # ~a quarter of 200
    # weights 1 + 2 * 3.88 = 8.76 against 1 + 2 * 0.039 = 1.08: 100 * 8.76 / (876 + 300 * 1.08) = 73 %
    assert 125 <= favoured <= 165
    _, unweighted = _grown_from(*pulled(), MCMCConfig(grow_rate=0.5), 300)
    assert torch.equal(unweighted, new_even)
    assert "gradient_weight" not in MCMCConfig().model_dump_json()
    assert MCMCConfig(gradient_weight=2.0).model_dump()["gradient_weight"] == 2.0
