"""The held-out protocol cannot be fooled: a transform fitted on other frames only, raw figures,
performer figures, and floors that stay low."""

import numpy as np
import torch

from volcap_core.splat.scoring import (
    ColourTransform,
    cross_fitted_transforms,
    fit_colour_transform,
    score_views,
    summarise,
)


def _frames(n=4, size=48, seed=0):
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(size, size, 3, generator=g) * 0.6 + 0.05      # a textured scene
    return [base.roll(k, dims=1) for k in range(n)]


def test_gain_and_offset_are_recovered_from_other_frames():
    truth = _frames()
    # the camera sees the model's colours through its own exposure and black level
    cam = ColourTransform((1.3, 0.8, 1.1), (0.01, 0.02, -0.005))
    targets = [cam.apply(t) for t in truth]
    tf = fit_colour_transform(truth[:2], targets[:2])
    assert np.allclose(tf.gain, cam.gain, atol=2e-3) and np.allclose(tf.offset, cam.offset, atol=2e-3)
    scores = score_views(truth, targets, ["c"] * 4, [0, 1, 2, 3])
    assert all(s.psnr > 45 for s in scores)           # the right model, once its exposure is fitted
    assert all(s.psnr_raw < 30 for s in scores)       # raw shows the exposure difference


def test_a_scored_frame_never_influences_its_own_transform():
    truth = _frames()
    targets = [t.clone() for t in truth]
    before = cross_fitted_transforms(truth, targets, ["c"] * 4, [0, 1, 2, 3])
    targets[0] = targets[0] * 3.0                     # change the footage of frame 0 only
    after = cross_fitted_transforms(truth, targets, ["c"] * 4, [0, 1, 2, 3])
    assert before[0] == after[0] and before[2] == after[2]      # frames 0, 2 fitted on 1, 3
    assert before[1] != after[1]                                # frame 1's fit saw frame 0
    # one frame: nothing else to fit on, no transform at all
    assert cross_fitted_transforms(truth[:1], targets[:1], ["c"], [0]) == [ColourTransform()]


def test_an_invisible_model_scores_only_the_mean_colour_floor():
    truth = _frames(n=6)
    empty = [torch.zeros_like(t) for t in truth]
    s_empty = summarise(score_views(empty, truth, ["c"] * 6, list(range(6))))
    s_true = summarise(score_views(truth, truth, ["c"] * 6, list(range(6))))
    # the floor is what drawing each channel's mean colour gives (the offsets can do no more)
    mean_colour = [torch.ones_like(t) * torch.stack(truth).mean((0, 1, 2)) for t in truth]
    s_mean = summarise(score_views(mean_colour, truth, ["c"] * 6, list(range(6))))
    assert abs(s_empty.psnr - s_mean.psnr) < 0.3
    assert s_empty.psnr < 18 and s_true.psnr > 60 and s_empty.psnr_raw < s_empty.psnr


def test_performer_figures_look_only_inside_the_mask():
    truth = _frames(n=2)
    render = [t.clone() for t in truth]
    mask = torch.zeros(48, 48)
    mask[10:30, 10:30] = 1
    for r in render:
        r[mask < 0.5] = 0.0                            # the set is wrong, the performer right
    # two cameras seen once each: no other frame to fit on, so no transform (identity)
    scores = score_views(render, truth, ["a", "b"], [0, 0], [mask, mask])
    assert all(s.psnr_performers > 40 and s.psnr < 25 for s in scores)
    assert all(s.ssim_performers > s.ssim for s in scores)
    empty_mask = score_views(render, truth, ["a", "b"], [0, 0], [torch.zeros(48, 48)] * 2)
    assert all(s.psnr_performers is None for s in empty_mask)


def test_the_fit_is_the_one_autograd_gives():
    """The fit's hand-written gradient gives the transform that L-BFGS through autograd gives
    (the fit before it), on a render that is noisy, clipped and off in exposure and black level:
    every stored held-out figure keeps its meaning."""
    from volcap_core.colour import srgb_encode

    g = torch.Generator().manual_seed(3)
    truth = [torch.rand(40, 60, 3, generator=g, dtype=torch.float64) ** 2.2 for _ in range(3)]
    renders = [(t * 0.9 + 0.03 + 0.08 * torch.randn(t.shape, generator=g, dtype=torch.float64)).clamp(min=0)
               for t in truth]
    r = torch.cat([x.reshape(-1, 3) for x in renders])
    t = torch.cat([x.reshape(-1, 3) for x in truth])
    rm, tm = r.mean(0), t.mean(0)
    gain = (((r - rm) * (t - tm)).mean(0) / ((r - rm) ** 2).mean(0)).clamp(min=0)
    params = torch.cat([gain, tm - gain * rm]).requires_grad_(True)
    opt = torch.optim.LBFGS([params], lr=1.0, max_iter=30, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = ((srgb_encode(r * params[:3] + params[3:]) - srgb_encode(t)) ** 2).mean()
        loss.backward()
        return loss

    opt.step(closure)
    tf = fit_colour_transform(renders, truth)
    # the same iterates: only rounding differs (1e-9 here), far below any printed figure
    assert np.allclose(tf.gain + tf.offset, params.detach().numpy(), rtol=0, atol=1e-7)
