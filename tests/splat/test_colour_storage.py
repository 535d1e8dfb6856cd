"""Colour storage of the Gaussians (``Poly4DGSConfig.colour_space``): unbounded sRGB (the paper's
choice, the default) against linear radiance (the paper's "training in linear space" ablation).

Both render linear images and train with the same loss (unbounded sRGB); they differ only in what
the SH colour means, so a linear-storage model whose colours are ``srgb_decode_unbounded`` of an
sRGB-storage model's colours renders the same image (exactly, for SH degree 0)."""

import json
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import (  # noqa: E402, F401  (single_thread: fixture)
    moving_scene,
    random_gaussians,
    ring_cameras,
    single_thread,
)

from volcap_core.colour import srgb_decode_unbounded, srgb_encode_unbounded  # noqa: E402
from volcap_core.splat.model import (  # noqa: E402
    Poly4DGS,
    Poly4DGSConfig,
    evaluate,
    load_model,
    save_model,
)
from volcap_core.splat.render import render  # noqa: E402
from volcap_core.splat.sh import SH_C0  # noqa: E402
from volcap_core.splat.train import TrainConfig, init_model, train_segment  # noqa: E402

pytestmark = pytest.mark.usefixtures("single_thread")


def _model_pair(n: int = 60, seed: int = 3, temporal: bool = True):
    """The same Gaussians twice: sRGB storage with colours c, linear storage with decode(c).
    Colours span negative, [0, 1] and HDR (> 1) unbounded-sRGB values."""
    g = random_gaussians(n, seed=seed, sh_degree=0)
    gen = torch.Generator().manual_seed(seed + 1)
    srgb = torch.rand(n, 3, generator=gen) * 1.6 - 0.2            # [-0.2, 1.4]
    base = Poly4DGSConfig.paper(sh_degree=0) if temporal else Poly4DGSConfig.static(sh_degree=0)
    t0 = torch.rand(n, generator=gen) * 0.2 if temporal else None
    kw = dict(scales=g.scales, t0=t0, opacity=0.7, lifespan_s=0.3)
    m_srgb = Poly4DGS.from_points(base, g.means, srgb, **kw)
    m_lin = Poly4DGS.from_points(base.model_copy(update={"colour_space": "linear"}), g.means,
                                 srgb_decode_unbounded(srgb), **kw)
    for m in (m_srgb, m_lin):  # some rotation and motion, identical in both
        m.params["quats"] = g.quats.clone()
        if temporal:
            m.params["means_t"] = 0.3 * torch.randn(n, 2, 3, generator=torch.Generator()
                                                    .manual_seed(seed + 2))
    return m_srgb, m_lin, srgb


@pytest.mark.parametrize("temporal", [True, False])
def test_linear_storage_of_decoded_colours_renders_the_same_image(temporal):
    m_srgb, m_lin, _ = _model_pair(temporal=temporal)
    assert m_srgb.config.colour_space == "srgb_unbounded" and m_lin.config.colour_space == "linear"
    bg = torch.tensor([0.05, 0.1, 0.2])
    for cam in ring_cameras(3, size=40):
        for t in (0.0, 0.1):
            g_s, g_l = evaluate(m_srgb, t), evaluate(m_lin, t)
            assert (g_s.colour_space, g_l.colour_space) == ("srgb_unbounded", "linear")
            a = render(g_s, cam, backend="torch", background=bg)
            b = render(g_l, cam, backend="torch", background=bg)
            assert float(a["alpha"].mean()) > 0.05                  # something is drawn
            torch.testing.assert_close(b["rgb"], a["rgb"], rtol=1e-5, atol=2e-6)
            torch.testing.assert_close(b["alpha"], a["alpha"], rtol=0, atol=0)
            torch.testing.assert_close(b["depth"], a["depth"], rtol=0, atol=0)


def test_linear_storage_skips_the_decode_and_srgb_storage_applies_it():
    """Same SH, different meaning: the sRGB model rasterizes decode(c), the linear model c."""
    m_srgb, _, srgb = _model_pair(temporal=False)
    m_same = Poly4DGS(m_srgb.config.model_copy(update={"colour_space": "linear"}),
                      {k: v.clone() for k, v in m_srgb.params.items()})
    # one Gaussian over the centre pixel: the pixel shows its colour times its alpha
    keep = torch.tensor([0])
    for m in (m_srgb, m_same):
        m.params = {k: v[keep].clone() for k, v in m.params.items()}
        m.params["means"][:] = 0.0
        m.params["scales"][:] = torch.log(torch.tensor(0.3))
        m.params["opacities"][:] = 2.0
    cam = ring_cameras(1, size=17)[0]
    c = srgb[0]
    out_s = render(evaluate(m_srgb, 0.0), cam, backend="torch")
    out_l = render(evaluate(m_same, 0.0), cam, backend="torch")
    w = out_s["alpha"][8, 8]                     # one Gaussian, black background: rgb = w · colour
    assert float(w) > 0.5
    torch.testing.assert_close(out_l["alpha"], out_s["alpha"], rtol=0, atol=0)
    torch.testing.assert_close(out_s["rgb"][8, 8], w * srgb_decode_unbounded(c), rtol=1e-5,
                               atol=1e-7)
    torch.testing.assert_close(out_l["rgb"][8, 8], w * c, rtol=1e-5, atol=1e-7)


def test_gradients_flow_to_linear_colours():
    _, m_lin, _ = _model_pair()
    for v in m_lin.params.values():
        v.requires_grad_(True)
    out = render(evaluate(m_lin, 0.05), ring_cameras(1, size=32)[0], backend="torch")
    srgb_encode_unbounded(out["rgb"]).sum().backward()
    assert torch.isfinite(m_lin.params["sh0"].grad).all()
    assert m_lin.params["sh0"].grad.abs().sum() > 0


def test_default_is_serialised_as_before_and_linear_round_trips():
    # The default adds nothing to the JSON: configs (task cache keys) and saved models written
    # before the field existed are unchanged, and they read back as unbounded-sRGB storage.
    old = '{"mean_degree":2,"quat_degree":1,"scale_degree":0,"opacity_degree":2,"sh_degree":3}'
    assert Poly4DGSConfig.paper().model_dump_json() == old
    assert Poly4DGSConfig.model_validate_json(old).colour_space == "srgb_unbounded"
    assert "colour_space" not in TrainConfig().model_dump_json()
    assert json.loads(TrainConfig().model_dump_json())["model"] == json.loads(old)
    lin = Poly4DGSConfig.paper().model_copy(update={"colour_space": "linear"})
    assert json.loads(lin.model_dump_json())["colour_space"] == "linear"
    assert Poly4DGSConfig.model_validate_json(lin.model_dump_json()) == lin
    tc = TrainConfig(model=lin)
    assert TrainConfig.model_validate_json(tc.model_dump_json()).model.colour_space == "linear"
    with pytest.raises(ValueError):
        Poly4DGSConfig(colour_space="log")

    _, m_lin, _ = _model_pair()
    back = load_model(save_model(m_lin))
    assert back.config.colour_space == "linear"
    cam = ring_cameras(1, size=24)[0]
    torch.testing.assert_close(render(evaluate(back, 0.1), cam, backend="torch")["rgb"],
                               render(evaluate(m_lin, 0.1), cam, backend="torch")["rgb"])


def test_select_keeps_the_colour_space():
    _, m_lin, _ = _model_pair()
    g = evaluate(m_lin, 0.0)
    sub = g.select(torch.arange(len(g)) % 2 == 0)
    assert sub.colour_space == "linear" and len(sub) == (len(g) + 1) // 2


def test_init_stores_point_colours_in_the_configured_space():
    _, points, _ = moving_scene(n=20)
    rgb = torch.cat([p.rgb for p in points])
    for space, expect in (("srgb_unbounded", srgb_encode_unbounded(rgb)), ("linear", rgb)):
        cfg = TrainConfig(model=Poly4DGSConfig(sh_degree=1, colour_space=space))
        m = init_model(points, cfg, frame_interval_s=0.1)
        torch.testing.assert_close(m.params["sh0"][:, 0] * SH_C0 + 0.5, expect, rtol=1e-5,
                                   atol=1e-6)


def test_both_storages_train_and_the_default_is_unchanged():
    data, points, _ = moving_scene()
    base = dict(grid_size=4, checkpoint_every=0, held_out_cameras=["3"],
                steps=30, eval_every=0,
                mcmc=dict(refine_start=10, refine_every=10, refine_stop=10_000, cap_max=600))
    default = train_segment(data, points, TrainConfig(model=Poly4DGSConfig.paper(sh_degree=1),
                                                      **base), seed=0)
    explicit = train_segment(data, points, TrainConfig(
        model=Poly4DGSConfig.paper(sh_degree=1).model_copy(
            update={"colour_space": "srgb_unbounded"}), **base), seed=0)
    for k, v in default.model.params.items():
        torch.testing.assert_close(explicit.model.params[k], v, rtol=0, atol=0)
    linear = train_segment(data, points, TrainConfig(
        model=Poly4DGSConfig(sh_degree=1, colour_space="linear"), **base), seed=0)
    assert linear.model.config.colour_space == "linear"
    assert all(torch.isfinite(v).all() for v in linear.model.params.values())
    first, last = linear.history[0], linear.history[-1]
    assert last.step == 30 and torch.isfinite(torch.tensor(last.psnr))
    assert last.psnr > 10.0, (first, last)
