"""The Face Rig pairs bench's flow check (``bench/bench_facerig_pairs.py``, issue 29: "the rendered
flow warps frame t−1 onto frame t with a lower error than zero flow and than DIS"): every flow is
scored on the same pixels, so a flow cannot win by sending the pixels it gets wrong out of the
frame (< 1 s)."""

from __future__ import annotations

import pytest
import torch

from tests.gpu_machine import load_bench


@pytest.fixture(scope="module")
def bench():
    return load_bench("bench_facerig_pairs")


def test_flows_are_scored_on_the_pixels_every_flow_keeps_in_frame(bench):
    # frame 1: the left half as in frame 0, the right half moved 3 px left (cur(x) = prev(x + 3))
    h, w = 32, 64
    prev = torch.rand(3, h, w, generator=torch.Generator().manual_seed(0))
    cur = prev.clone()
    cur[:, :, w // 2:w - 3] = prev[:, :, w // 2 + 3:]
    frames = torch.stack([prev, cur])
    right = torch.zeros(1, 2, h, w)
    right[:, 0, :, w // 2:] = 1.0
    exact = 3.0 * right
    # off by half a pixel on the left, and out of the frame on the right half, where it is wrong
    escape = 0.5 * (1 - right) + 1000.0 * right
    escape[:, 1] = 0.0
    drawn = torch.ones(1, 1, h, w)
    errors = bench.flow_warp_errors(frames, {"exact": exact, "zero": torch.zeros_like(exact), "escape": escape}, drawn)

    assert errors["in_frame_escape"] == pytest.approx(0.5)
    assert errors["in_frame_zero"] == 1.0 and errors["in_frame_exact"] == pytest.approx(1 - 3 / w, abs=1e-4)
    assert errors["scored"] == pytest.approx(0.5)                # the left half: what all three keep
    # there zero flow is exact: the flow that dropped the right half does not beat it
    assert errors["zero"] < 1e-12 and errors["exact"] < 1e-12
    assert errors["escape"] > 1e-3
