"""The alpha loss on performer masks (``TrainConfig.mask_alpha_weight``, on every
``mask_alpha_every``-th step): the performers' alpha (the moving Gaussians' coverage, the set in
front occluding) is pulled toward each view's mask."""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import performers_on_a_floor, single_thread  # noqa: E402, F401  (fixture)

from volcap_core.splat.model import Poly4DGSConfig, evaluate  # noqa: E402
from volcap_core.splat.train import (  # noqa: E402
    SegmentData,
    TrainConfig,
    performer_alpha,
    train_segment,
)

pytestmark = pytest.mark.usefixtures("single_thread")


def _matte_error(result, data: SegmentData) -> float:
    """Mean |performers' alpha - mask| over every view."""
    with torch.no_grad():
        errs = [(performer_alpha(result.model, evaluate(result.model, v.time), v.camera, backend="torch")
                 - v.load_matte()).abs().mean() for v in data.views]
    return float(torch.stack(errs).mean())


def test_the_mask_alpha_loss_pulls_the_performers_alpha_toward_the_mask():
    data, points = performers_on_a_floor()
    base = dict(model=Poly4DGSConfig.paper(sh_degree=0), grid_size=4, checkpoint_every=0, eval_every=0,
                held_out_cameras=[], mcmc=dict(refine_start=1000, cap_max=400))
    initial = _matte_error(train_segment(data, points, TrainConfig(**base, steps=0), seed=0), data)
    without = _matte_error(train_segment(data, points, TrainConfig(**base, steps=60), seed=0), data)
    parts = []
    with_loss = train_segment(data, points, TrainConfig(**base, steps=60, mask_alpha_weight=1.0), seed=0,
                              progress=lambda s, n, info: parts.append(info))
    with_ = _matte_error(with_loss, data)
    print(f"mean |performers' alpha - mask|: initial {initial:.4f}, 60 steps without {without:.4f}, "
          f"with the loss {with_:.4f}")
    assert "matte" in parts[-1]   # the term is reported
    assert with_ < 0.8 * without and with_ < 0.8 * initial


def test_the_loss_can_run_on_every_nth_step_only():
    """``mask_alpha_every`` 3: the term (its extra render) is on steps 3, 6, 9 and no other, and it
    still pulls the alpha toward the masks."""
    data, points = performers_on_a_floor()
    base = dict(model=Poly4DGSConfig.paper(sh_degree=0), grid_size=4, checkpoint_every=0, eval_every=0,
                held_out_cameras=[], mcmc=dict(refine_start=1000, cap_max=400))
    seen = []
    train_segment(data, points, TrainConfig(**base, steps=9, mask_alpha_weight=1.0, mask_alpha_every=3), seed=0,
                  progress=lambda s, n, info: seen.append((s, "matte" in info)))
    assert [s for s, on in seen if on] == [3, 6, 9]
    sparse = train_segment(data, points, TrainConfig(**base, steps=60, mask_alpha_weight=1.0, mask_alpha_every=3),
                           seed=0)
    without = train_segment(data, points, TrainConfig(**base, steps=60), seed=0)
    assert _matte_error(sparse, data) < 0.9 * _matte_error(without, data)


def test_off_the_field_leaves_the_config_json_as_it_was():
    """A train-segment key and a stored record hold the config's JSON: off, the fields are not in it."""
    assert "mask_alpha" not in TrainConfig().model_dump_json()
    assert "mask_alpha" not in TrainConfig(mask_alpha_every=1).model_dump_json()
    assert TrainConfig(mask_alpha_weight=0.5).model_dump()["mask_alpha_weight"] == 0.5
    assert TrainConfig(mask_alpha_weight=0.5, mask_alpha_every=4).model_dump()["mask_alpha_every"] == 4
    assert TrainConfig.model_validate_json(TrainConfig().model_dump_json()) == TrainConfig()
