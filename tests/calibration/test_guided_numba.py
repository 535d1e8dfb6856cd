"""The compiled scores of the guided patch search (calibration/guided_numba.py) against the torch
code they replace: the same NCC to float32 rounding at every shift (templates by the image's border
too, where the samples clamp), the same matches and the same accepted ones through
``_match_patches``, and the same bits on one thread or all."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

numba = pytest.importorskip("numba")

from volcap_core.calibration import guided, guided_numba  # noqa: E402
from volcap_core.calibration.guided import GuidedMatchOptions, _match_patches, _ncc, _sample  # noqa: E402


def _search(n: int = 600, seed: int = 0):
    """A textured log-luminance image [120, 160], ``n`` templates of 9x9 pixels at random places
    (some reaching past the border), mapped into it with a scale and a shear (a plane seen from
    another camera), and each template's true shift of up to 2.5 px."""
    rng = np.random.default_rng(seed)
    image = cv2.GaussianBlur(rng.normal(size=(120, 160)).astype(np.float32), (0, 0), 1.2)
    grid = np.arange(-4, 5)
    offsets = np.stack(np.meshgrid(grid, grid, indexing="xy"), -1).reshape(-1, 2).astype(np.float64)
    warp = np.array([[1.06, 0.12], [-0.05, 0.94]])
    centres = rng.uniform([-4, -4], [164, 124], (n, 2))
    warped = centres[:, None] + offsets @ warp.T
    truth = rng.uniform(-2.5, 2.5, (n, 1, 2))
    img = torch.as_tensor(image)
    template = _sample(img, torch.as_tensor(warped + truth))
    return img, template, warped, truth[:, 0]


def test_compiled_scores_are_the_torch_ncc_at_every_shift():
    img, template, warped, _ = _search()
    steps = torch.arange(-3.0, 3.0 + 1e-9, 0.5)
    shifts = torch.stack(torch.meshgrid(steps, steps, indexing="xy"), -1).reshape(-1, 2)
    w = torch.as_tensor(warped, dtype=torch.float32)
    ref = _ncc(template[:, None], _sample(img, w[:, None] + shifts[None, :, None, :])).reshape(len(w), 13, 13)
    ours = guided_numba.shifted_ncc(img.numpy(), template.numpy(), w.numpy(), steps.numpy())
    assert ours.shape == (len(w), 13, 13) and ours.dtype == np.float32
    assert float(np.abs(ours - ref.numpy()).max()) < 2e-4
    assert float(ref.abs().max()) > 0.99     # the true shifts score ~1: the comparison covers the peaks


def test_match_patches_finds_the_same_matches_through_both_paths(monkeypatch):
    img, template, warped, truth = _search()
    options = GuidedMatchOptions(chunk_anchors=128)
    ours, ok = _match_patches(img, template, warped, options)
    monkeypatch.setattr(guided, "_compiled_scores", lambda: None)
    ref, ref_ok = _match_patches(img, template, warped, options)
    assert (ok == ref_ok).all() and ok.mean() > 0.8
    assert float(np.abs(ours - ref)[ok].max()) < 2e-3
    centre = warped[:, warped.shape[1] // 2]
    # a match is where the template came from: its true shift within the parabola's accuracy
    assert float(np.median(np.abs(ours - centre - truth)[ok])) < 0.05


def test_guided_scores_bits_do_not_depend_on_the_thread_count(monkeypatch):
    img, template, warped, _ = _search(n=300, seed=3)
    steps = np.arange(-3.0, 3.0 + 1e-9, 0.5, dtype=np.float32)
    args = (img.numpy(), template.numpy(), warped.astype(np.float32), steps)
    everyone = guided_numba.shifted_ncc(*args)
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    one = guided_numba.shifted_ncc(*args)
    assert np.array_equal(one, everyone)
