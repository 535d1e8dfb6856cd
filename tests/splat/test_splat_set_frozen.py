"""The set frozen for the last part of a segment's training (``TrainConfig.set_frozen_from``): from
that step on the static Gaussians keep their values, each training view's render of them is the
background the performers are composited over, the performers keep training within the segment's
Gaussian budget, and checkpoints still hold (and resume) the whole model."""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import performers_on_a_floor, single_thread  # noqa: E402, F401  (fixture)

from volcap_core.production.presets import named_preset  # noqa: E402
from volcap_core.production.steps import TrainSegment  # noqa: E402
from volcap_core.splat.model import Poly4DGSConfig, evaluate  # noqa: E402
from volcap_core.splat.render import render  # noqa: E402
from volcap_core.splat.train import TrainConfig, _deserialise, train_segment  # noqa: E402

pytestmark = pytest.mark.usefixtures("single_thread")
BASE = dict(model=Poly4DGSConfig.paper(sh_degree=0), grid_size=4, eval_every=0, held_out_cameras=[],
            backend="torch", mcmc=dict(refine_start=5, refine_every=5, refine_stop=35, cap_max=300))


def _train(data, points, steps: int, **kw):
    blobs: dict[int, bytes] = {}
    result = train_segment(data, points, TrainConfig(**BASE, steps=steps, **kw), seed=0,
                           checkpoint=lambda blob, step: blobs.__setitem__(step, blob))
    return result, blobs


def _error(model, data) -> float:
    """Mean |render - footage| over every view (linear)."""
    with torch.no_grad():
        return float(torch.stack([(render(evaluate(model, v.time), v.camera, backend="torch")["rgb"]
                                   - v.load()[..., :3]).abs().mean() for v in data.views]).mean())


def test_the_set_keeps_its_values_from_the_freeze_and_the_performers_train_on():
    data, points = performers_on_a_floor()
    result, blobs = _train(data, points, 40, set_frozen_from=0.5, checkpoint_every=10)
    at_freeze = _deserialise(blobs[20], "cpu")[0].model      # the checkpoint the step before it
    set_then = at_freeze.subset(~at_freeze.moving())
    final = result.model
    n = len(set_then)
    assert n > 0 and bool((~final.moving()[:n]).all()) and bool(final.moving()[n:].all())
    for k, v in set_then.params.items():            # the set, first in the result, as it was frozen
        assert torch.equal(final.params[k][:n], v), k
    performers_then = at_freeze.subset(at_freeze.moving())
    assert not torch.equal(final.params["means"][n:n + 5], performers_then.params["means"][:5])
    assert len(final) <= 300                         # the segment's budget holds the set and performers


def test_the_frozen_phase_fits_as_the_joint_training_does():
    """Freezing the set after half of the steps keeps most of the fit on a scene whose set the first
    half learned: at least half of the joint training's gain over the untrained model, and within
    15 % of its mean error."""
    data, points = performers_on_a_floor()
    joint, _ = _train(data, points, 60, checkpoint_every=0)
    frozen, _ = _train(data, points, 60, set_frozen_from=0.5, checkpoint_every=0)
    initial, _ = _train(data, points, 0, checkpoint_every=0)
    e_joint, e_frozen, e0 = (_error(r.model, data) for r in (joint, frozen, initial))
    print(f"mean |render - footage|: initial {e0:.4f}, joint {e_joint:.4f}, set frozen at 30 {e_frozen:.4f}")
    assert e0 - e_frozen > 0.5 * (e0 - e_joint) and e_frozen < 1.15 * e_joint


def test_after_the_freeze_the_performers_are_composited_over_the_views_render_of_the_set(monkeypatch):
    """Each training step's render before the freeze is over the config's colour; after it, over the
    drawn view's render of the frozen set (what the view's footage shows behind the performers)."""
    import volcap_core.splat.train as train

    data, points = performers_on_a_floor()
    seen = []
    real = train.render

    def spy(gaussians, camera, **kw):
        if gaussians.colour_space != "linear" and torch.is_grad_enabled():   # a step's render
            seen.append((camera, kw["background"]))
        return real(gaussians, camera, **kw)

    monkeypatch.setattr(train, "render", spy)
    result, _ = _train(data, points, 20, set_frozen_from=0.5, checkpoint_every=0)
    assert len(seen) == 20 and all(b.shape == (3,) for _, b in seen[:10])
    the_set = result.model.subset(~result.model.moving())
    for camera, b in seen[10:]:
        # the camera's render of the set at one of its frames (a camera object serves every frame)
        with torch.no_grad():
            expected = [real(evaluate(the_set, v.time), camera, backend="torch", background=torch.zeros(3))["rgb"]
                        for v in data.views if v.camera is camera]
        assert any(b.shape == e.shape and torch.allclose(b, e, atol=1e-6) for e in expected)


def test_beyond_the_kept_renders_budget_the_set_is_rendered_again_to_the_same_result(monkeypatch):
    """A production's views would not all fit as kept renders: with none kept, each draw renders
    the set again, and the training ends on the same bits."""
    import volcap_core.splat.train as train

    data, points = performers_on_a_floor()
    kept, _ = _train(data, points, 30, set_frozen_from=0.5, checkpoint_every=0)
    monkeypatch.setattr(train, "SET_RENDERS_KEPT_BYTES", 0)
    again, _ = _train(data, points, 30, set_frozen_from=0.5, checkpoint_every=0)
    for k, v in kept.model.params.items():
        assert torch.equal(again.model.params[k], v), k


def test_a_run_resumed_after_the_freeze_ends_as_the_uninterrupted_one():
    data, points = performers_on_a_floor()
    whole, blobs = _train(data, points, 40, set_frozen_from=0.5, checkpoint_every=10)
    for at in (20, 30):                               # the step before the freeze, and after it
        resumed = train_segment(data, points, TrainConfig(**BASE, steps=40, set_frozen_from=0.5, checkpoint_every=10),
                                seed=0, resume_from=blobs[at])
        for k, v in whole.model.params.items():
            assert torch.equal(resumed.model.params[k], v), (at, k)


def test_off_the_field_leaves_configs_and_journals_as_they_were():
    """A train-segment key, a stored record and a plan's journal hold these JSONs: off, the field is
    not in them; on, it is."""
    assert "set_frozen_from" not in TrainConfig().model_dump_json()
    assert TrainConfig(set_frozen_from=0.6).model_dump()["set_frozen_from"] == 0.6
    quality = named_preset("test")
    assert quality.train_config().set_frozen_from is None
    assert quality.with_overrides(set_frozen_from=0.6).train_config().set_frozen_from == 0.6
    step = TrainSegment(capture="c", segment=0, frames=(0, 2), core=(0, 2), overlap=0, gaussians=10,
                        memory_bytes=1, **quality.training())
    assert "set_frozen_from" not in step.as_json()
    on = TrainSegment(capture="c", segment=0, frames=(0, 2), core=(0, 2), overlap=0, gaussians=10,
                      memory_bytes=1, **quality.with_overrides(set_frozen_from=0.6).training())
    assert on.as_json()["set_frozen_from"] == 0.6


# ------------------------------------------------------------- a set trained already (set_model)

def _set_from_plates(data, points, plates, steps: int = 30):
    """The set trained from the cameras' clean plates alone (the static points, one frame)."""
    from volcap_core.splat.train import PointsAtTime, SegmentData, View

    t = data.times[0]
    views = [View(c, data.frames[0], t, next(v.camera for v in data.views if v.camera_id == c), img)
             for c, img in plates.items()]
    p = points[0]
    floor = PointsAtTime(t, p.xyz[p.static], p.rgb[p.static], p.static[p.static])
    return train_segment(SegmentData((data.frames[0], data.frames[0] + 1), views), [floor],
                         TrainConfig(**BASE, steps=steps, checkpoint_every=0, init_static_share=1.0), seed=0).model


def _performers_error(model, data) -> float:
    """Mean |render - footage| over the performers' pixels (matte > 0.5) of every view."""
    with torch.no_grad():
        return float(torch.cat([(render(evaluate(model, v.time), v.camera, backend="torch")["rgb"]
                                 - v.load()[..., :3]).abs().mean(-1)[v.load_matte() > 0.5]
                                for v in data.views]).mean())


def test_a_set_trained_already_stays_as_it_was_and_the_performers_fit_over_it():
    """Given a set trained from the plates, the segment starts from it and the performers' moving
    points alone; the set, first in the result, keeps its values to the bit; the performers
    (every Gaussian after it) stay within MCMC's whole budget and train: their pixels' error falls
    by a tenth from the untrained performers over the same set. (This scene's floor hides some
    performers from some cameras, which compositing over the set's render does not model, so the
    fall is smaller than joint training's.)"""
    data, points, plates = performers_on_a_floor(plates=True)
    the_set = _set_from_plates(data, points, plates)
    assert len(the_set) > 0 and not bool(the_set.moving().any())
    config = TrainConfig(**BASE, steps=40, checkpoint_every=0)
    result = train_segment(data, points, config, set_model=the_set, seed=0)
    n = len(the_set)
    for k, v in the_set.params.items():
        assert torch.equal(result.model.params[k][:n], v), k
    performers = result.model.subset(slice(n, None))
    assert len(performers) > 0 and bool(performers.moving().all()) and len(performers) <= BASE["mcmc"]["cap_max"]
    untrained = train_segment(data, points, config.model_copy(update={"steps": 0}), set_model=the_set, seed=0)
    e0, e = _performers_error(untrained.model, data), _performers_error(result.model, data)
    print(f"performers' mean |render - footage|: untrained over the set {e0:.4f}, trained {e:.4f}")
    assert e < 0.9 * e0


def test_a_set_holding_performers_is_refused():
    data, points = performers_on_a_floor()
    joint, _ = _train(data, points, 0, checkpoint_every=0)
    with pytest.raises(ValueError, match="static Gaussians only"):
        train_segment(data, points, TrainConfig(**BASE, steps=5, checkpoint_every=0), set_model=joint.model)


def test_a_run_over_a_set_trained_already_resumes_to_the_same_bits():
    data, points, plates = performers_on_a_floor(plates=True)
    the_set = _set_from_plates(data, points, plates, steps=10)
    blobs: dict[int, bytes] = {}
    config = TrainConfig(**BASE, steps=30, checkpoint_every=10)
    whole = train_segment(data, points, config, set_model=the_set, seed=0,
                          checkpoint=lambda blob, step: blobs.__setitem__(step, blob))
    resumed = train_segment(data, points, config, set_model=the_set, seed=0, resume_from=blobs[20])
    for k, v in whole.model.params.items():
        assert torch.equal(resumed.model.params[k], v), k
