"""``scores.alpha`` (:func:`volcap_core.splat.report.alpha_figures`): the performers' alpha of a
model against the views' masks, per camera role, beside the empty model's."""

import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import performers_on_a_floor, single_thread  # noqa: E402, F401  (fixture)

from volcap_core.splat.model import Poly4DGSConfig  # noqa: E402
from volcap_core.splat.report import alpha_figures  # noqa: E402
from volcap_core.splat.train import TrainConfig, train_segment  # noqa: E402

pytestmark = pytest.mark.usefixtures("single_thread")


def test_the_alpha_figures_against_the_masks_beside_the_empty_model():
    data, points = performers_on_a_floor()
    views = [v for v in data.views if v.camera_id in ("0", "3")]
    # the scene's mattes are the performers' true coverage: score them as the views' masks
    scored = [replace(v, mask=v.load_matte()) for v in views]
    config = TrainConfig(model=Poly4DGSConfig.paper(sh_degree=0), grid_size=4, eval_every=0, checkpoint_every=0,
                         backend="torch", mcmc=dict(refine_start=1000, cap_max=400))
    trained = train_segment(data, points, config.model_copy(update={"steps": 60, "mask_alpha_weight": 1.0}),
                            seed=0).model
    untrained = train_segment(data, points, config.model_copy(update={"steps": 0}), seed=0).model
    figs = alpha_figures(scored, {"trained": trained, "initial": untrained, "empty": None}, config,
                         {"3": "tracking"})
    print(figs)
    assert figs["static"]["cameras"] == ["0"] and figs["tracking"]["cameras"] == ["3"]
    for role, f in figs.items():
        masks = [v.load_mask() for v in scored if (v.camera_id == "3") == (role == "tracking")]
        # the empty model draws nothing: its error is the masks' mean, no alpha on or off them
        assert f["empty"] == {"error": round(float(torch.stack([m.mean() for m in masks]).mean()), 4),
                              "on": 0.0, "spill": 0.0, "views": 2}
        # trained with the alpha loss the performers' alpha is nearer the masks, and more solid on them
        assert f["trained"]["error"] < f["initial"]["error"] < f["empty"]["error"]
        assert f["initial"]["on"] < f["trained"]["on"] <= 1.0 and f["trained"]["spill"] > 0.0
