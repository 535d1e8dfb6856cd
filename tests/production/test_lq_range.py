"""The LQ range (issue 29): a Scene Rig segment's Gaussians alive in an actor's upper body, per
frame, and their minimum and maximum. Counted exactly on a constructed Poly4DGS model whose
Gaussians sit inside and outside the region, live at some times only, move, or are too faint.
Each test takes well under a second."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from volcap_core.production.lq_range import LQRange, UpperBody, lq_range, upper_body_gaussian_counts
from volcap_core.splat.model import ALPHA_MIN, Poly4DGS, Poly4DGSConfig

HEAD = (0.0, 0.0, 1.6)
#: name, centre (metres, at t0), t0 (s), lifespan (s), velocity (m/s), opacity
GAUSSIANS = [
    ("head centre", (0.0, 0.0, 1.6), 0.0, math.inf, (0, 0, 0), 0.9),
    ("shoulder", (0.2, 0.0, 1.3), 0.0, math.inf, (0, 0, 0), 0.9),           # 0.2 m from the axis' foot
    ("above the crown", (0.0, 0.0, 1.86), 0.0, math.inf, (0, 0, 0), 0.9),   # 0.26 m above the head
    ("chest", (0.0, 0.0, 1.04), 0.0, math.inf, (0, 0, 0), 0.9),             # 0.26 m below the axis' foot
    ("beside", (0.0, 0.26, 1.45), 0.0, math.inf, (0, 0, 0), 0.9),           # 0.26 m off the axis
    ("born at 1 s", (0.24, 0.0, 1.5), 1.0, 0.05, (0, 0, 0), 0.9),            # dead at t = 0
    ("walks in", (1.0, 0.0, 1.6), 0.0, math.inf, (-1, 0, 0), 0.9),           # inside at t = 1 only
    ("faint", (0.0, 0.1, 1.6), 0.0, math.inf, (0, 0, 0), 0.003),             # below 1/255
    ("set", (3.0, 0.0, 1.6), 0.0, math.inf, (0, 0, 0), 0.9),
]


def model() -> Poly4DGS:
    n = len(GAUSSIANS)
    m = Poly4DGS.from_points(Poly4DGSConfig.paper(sh_degree=0), torch.tensor([g[1] for g in GAUSSIANS]),
                             torch.full((n, 3), 0.5), scales=torch.full((n,), 0.01),
                             t0=torch.tensor([g[2] for g in GAUSSIANS]),
                             lifespan_s=torch.tensor([g[3] for g in GAUSSIANS]))
    m.params["means_t"][:, 0] = torch.tensor([g[4] for g in GAUSSIANS], dtype=torch.float32)
    o = torch.tensor([g[5] for g in GAUSSIANS])
    m.params["opacities"] = torch.log(o / (1 - o))
    return m


def test_counts_are_exact_on_a_constructed_model():
    heads = [HEAD, HEAD, (5.0, 0.0, 1.6)]
    counts = upper_body_gaussian_counts(model(), heads, [0.0, 1.0, 1.0])
    # t = 0: the head centre and the shoulder; t = 1: also the one born at 1 s and the one that
    # walked in; with the head elsewhere: none
    assert counts.tolist() == [2, 4, 0] and counts.dtype == np.int64
    # the threshold is the opacity at the time: lowered below the faint one's, it counts
    assert upper_body_gaussian_counts(model(), [HEAD], [0.0], min_opacity=0.001).tolist() == [3]
    assert ALPHA_MIN > 0.003
    # a wider region takes in the ones just outside (above the crown, the chest, beside)
    wide = UpperBody(radius_m=0.27)
    assert upper_body_gaussian_counts(model(), [HEAD], [0.0], region=wide).tolist() == [5]
    # a longer drop reaches the chest only
    long = UpperBody(drop_m=0.6)
    assert upper_body_gaussian_counts(model(), [HEAD], [0.0], region=long).tolist() == [3]


def test_one_model_per_frame_and_the_range():
    empty = model()
    empty.params["opacities"][:] = -20.0                     # nothing alive
    counts = upper_body_gaussian_counts([model(), empty, model()], [HEAD] * 3, [0.0, 0.0, 1.0])
    assert counts.tolist() == [2, 0, 4]
    r = lq_range([counts, np.array([3, 7])])
    assert r == LQRange(low=0, high=7, frames=5)
    assert r.to_json() == {"low": 0, "high": 7, "frames": 5}
    assert lq_range(np.array([5, 2, 9])) == LQRange(low=2, high=9, frames=3)


def test_bad_input_is_one_clear_line():
    with pytest.raises(ValueError, match=r"head_positions_m must be finite \[2, 3\]"):
        upper_body_gaussian_counts(model(), [HEAD], [0.0, 1.0])
    with pytest.raises(ValueError, match="2 models for 3 frame times"):
        upper_body_gaussian_counts([model(), model()], [HEAD] * 3, [0.0, 0.5, 1.0])
    with pytest.raises(ValueError, match="no upper-body counts"):
        lq_range([])
    with pytest.raises(ValueError, match="radius_m"):
        UpperBody(radius_m=0.0)
