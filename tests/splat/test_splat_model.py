"""Poly4DGS model: the paper's polynomials, degree presets, dropping, save/load."""

import math

import pytest
import torch

from volcap_core.checkpoint import safetensors_bytes
from volcap_core.splat.model import (
    Poly4DGS,
    Poly4DGSConfig,
    evaluate,
    load_model,
    opacity_envelope,
    save_model,
)


def _model(config, n=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = Poly4DGS.from_points(config, torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g),
                             scales=torch.full((n,), 0.1), t0=torch.rand(n, generator=g))
    for k, v in m.params.items():
        if k != "t0":
            v.add_(0.3 * torch.randn(v.shape, generator=g))
    return m


def test_polynomials_follow_the_paper():
    m = _model(Poly4DGSConfig(mean_degree=2, quat_degree=1, scale_degree=1, opacity_degree=2,
                              sh_degree=1))
    p = m.params
    p["opacities"].fill_(5.0)
    t = 0.37
    g = evaluate(m, t, min_opacity=0.0)
    dt = t - p["t0"]
    mu = p["means"] + p["means_t"][:, 0] * dt[:, None] + p["means_t"][:, 1] * dt[:, None] ** 2
    q = p["quats"] + p["quats_t"][:, 0] * dt[:, None]
    s = torch.exp(p["scales"] + p["scales_t"][:, 0] * dt[:, None])
    lam = p["log_lambdas"].exp()
    envelope = torch.exp(-0.5 * (lam[:, 0] * dt ** 2 + lam[:, 1] * dt ** 4))
    o = torch.sigmoid(p["opacities"]) * envelope
    torch.testing.assert_close(g.means, mu)
    torch.testing.assert_close(g.quats, q / q.norm(dim=1, keepdim=True))
    torch.testing.assert_close(g.scales, s)
    torch.testing.assert_close(g.opacities, o)
    assert g.sh.shape == (5, 4, 3)


def test_presets_create_only_needed_tensors():
    assert set(Poly4DGSConfig.static(sh_degree=0).param_shapes()) == {
        "means", "quats", "scales", "opacities", "sh0"}
    rotor = Poly4DGSConfig.rotor4d().param_shapes()
    assert rotor["means_t"] == (1, 3) and rotor["log_lambdas"] == (1,)
    assert "quats_t" not in rotor and "scales_t" not in rotor
    paper = Poly4DGSConfig.paper().param_shapes()
    assert paper["means_t"] == (2, 3) and paper["quats_t"] == (1, 4)
    assert paper["log_lambdas"] == (2,) and paper["shN"] == (15, 3)
    # a static model is time-invariant
    m = _model(Poly4DGSConfig.static())
    a, b = evaluate(m, 0.0), evaluate(m, 123.0)
    assert torch.equal(a.means, b.means) and torch.equal(a.opacities, b.opacities)


def test_gaussians_below_1_over_255_are_dropped_with_ids():
    m = _model(Poly4DGSConfig.paper(sh_degree=0), n=6)
    m.params["opacities"][:] = 3.0
    m.params["opacities"][2] = -8.0            # o_0 = 3e-4
    m.params["t0"][4] = 50.0                   # far from t = 0: envelope kills it
    g = evaluate(m, 0.0)
    assert g.ids.tolist() == [0, 1, 3, 5]
    assert (g.opacities >= 1 / 255).all()


def test_gradients_reach_every_parameter():
    m = _model(Poly4DGSConfig.paper(sh_degree=1))
    for v in m.params.values():
        v.requires_grad_(True)
    g = evaluate(m, 0.8, min_opacity=0.0)
    (g.means.sum() + g.quats.sum() + g.scales.sum() + g.opacities.sum() + g.sh.sum()).backward()
    for k, v in m.params.items():
        assert v.grad is not None and torch.isfinite(v.grad).all(), k
        assert v.grad.abs().sum() > 0, k


def test_save_load_round_trip_bytes():
    m = _model(Poly4DGSConfig.rotor4d(sh_degree=2), n=7)
    blob = save_model(m)
    assert isinstance(blob, bytes)
    m2 = load_model(blob)
    assert m2.config == m.config
    for k, v in m.params.items():
        assert torch.equal(v, m2.params[k])
    assert Poly4DGSConfig.model_validate_json(m.config.model_dump_json()) == m.config
    with pytest.raises(ValueError):
        load_model(blob[:20])


def test_saved_bytes_depend_only_on_the_content():
    """safetensors.torch.save writes its metadata in a random order (a Rust HashMap): the same
    model gave two different artifacts. save_model must not."""
    from safetensors.torch import load as st_load
    from safetensors.torch import save as st_save

    m = _model(Poly4DGSConfig.paper(sh_degree=1), n=9)
    blobs = {save_model(m) for _ in range(30)}
    assert len(blobs) == 1
    # a copy built in another order, with the metadata in another order, gives the same bytes
    tensors = {k: v.detach() for k, v in m.params.items()}
    rev = dict(reversed(list(tensors.items())))
    meta = {"format": "f", "volcap.config": "c", "a": "1"}
    assert safetensors_bytes(tensors, meta) == safetensors_bytes(rev, dict(reversed(meta.items())))
    # the format is safetensors': with one metadata key (no ordering to randomise), mixed
    # dtypes, a scalar and an empty tensor it is byte for byte what safetensors writes
    mixed = {"rng": torch.arange(5, dtype=torch.uint8), "w": torch.randn(3, 2),
             "d": torch.randn(4, dtype=torch.float64), "s": torch.tensor(2.5),
             "e": torch.zeros(0, 3), "i": torch.arange(3)}
    assert safetensors_bytes(mixed, {"format": "x"}) == st_save(mixed, metadata={"format": "x"})
    back = st_load(safetensors_bytes(mixed, meta))
    assert set(back) == set(mixed) and all(torch.equal(back[k], v) for k, v in mixed.items())


def test_opacity_envelope_lambda_zero_is_constant():
    o = opacity_envelope(torch.tensor([math.log(0.7)]), torch.tensor([[-math.inf, -math.inf]]),
                         torch.tensor([3.0]))
    torch.testing.assert_close(o, torch.tensor([0.7]))
