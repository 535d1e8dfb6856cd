"""LQ/HQ pairs from a tiny synthetic Face Rig capture, and the bicubic/unsharp baseline."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from volcap_core.enhance.metrics import psnr
from volcap_core.enhance.pairs import (
    PairSet,
    bicubic_unsharp,
    load_face_capture_sequences,
    make_degraded_pairs,
    make_face_pair_sets,
)
from volcap_core.enhance.temporal import to_display
from volcap_core.synth import synthesize_face_capture

CAMS = ["F003", "F002"]   # F002 starts before the take (pre-roll): exercises the take offset
FRAMES = 3


@pytest.fixture(scope="module")
def face_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("face")
    return synthesize_face_capture(root / "cap", frames=FRAMES, supersample=1, cameras=CAMS, write_depth=True)


@pytest.fixture(scope="module")
def face_capture_no_masks(tmp_path_factory):
    root = tmp_path_factory.mktemp("face_nomask")
    return synthesize_face_capture(root / "cap", frames=2, supersample=1, cameras=["F003"])


def test_load_sequences(face_capture):
    from volcap_core.capture import CaptureDescription
    from volcap_core.imageio.read import read_image

    seqs = load_face_capture_sequences(face_capture, CAMS, FRAMES)
    assert list(seqs) == CAMS
    for cid, x in seqs.items():
        assert x.shape == (FRAMES, 4, 180, 320) and x.dtype == torch.float32
        a = x[:, 3]
        assert 0 <= float(a.min()) and float(a.max()) <= 1
        assert 0.01 < float(a.mean()) < 0.9                          # the performer, not the frame
        # premultiplied: black where there is no performer
        assert float(x[:, :3][(a == 0)[:, None].expand(-1, 3, -1, -1)].abs().max()) == 0
    # take index 1 of F002 is its file (1 - take_offset): compare with a direct read
    desc = CaptureDescription.model_validate_json(face_capture.read_text())
    cam = next(c for c in desc.cameras if c.id == "F002")
    rgb, _ = read_image(face_capture.parent / cam.path / f"{1 - desc.take_offset(cam):06d}.exr")
    raw = load_face_capture_sequences(face_capture, ["F002"], [1], premultiply=False)["F002"][0]
    np.testing.assert_array_equal(raw[:3].permute(1, 2, 0).numpy(), rgb[..., :3])
    small = load_face_capture_sequences(face_capture, ["F003"], [0, 2], size=(90, 160))["F003"]
    assert small.shape == (2, 4, 90, 160)
    with pytest.raises(ValueError, match="no camera"):
        load_face_capture_sequences(face_capture, ["F999"], 1)
    with pytest.raises(ValueError, match="outside"):
        load_face_capture_sequences(face_capture, CAMS, [FRAMES])


def test_alpha_is_one_without_masks(face_capture_no_masks):
    x = load_face_capture_sequences(face_capture_no_masks)["F003"]
    assert x.shape == (2, 4, 180, 320) and (x[:, 3] == 1).all()


def test_degraded_pairs_are_worse_than_hq(face_capture):
    seqs = load_face_capture_sequences(face_capture, CAMS, FRAMES)
    ps = make_degraded_pairs(seqs["F003"], scale=4, seed=1, name="F003")
    assert isinstance(ps, PairSet) and len(ps) == FRAMES and ps.flow is None
    assert ps.lq.shape == ps.hq.shape == (FRAMES, 4, 180, 320)
    assert float(ps.lq[:, :3].min()) >= 0 and 0 <= float(ps.lq[:, 3].min()) and float(ps.lq[:, 3].max()) <= 1
    for t in range(FRAMES):
        p = psnr(to_display(ps.lq[t]), to_display(ps.hq[t]))
        assert np.isfinite(p) and 15 < p < 40, p
    # deterministic per seed, different across seeds (the per-frame colour noise)
    again = make_degraded_pairs(seqs["F003"], scale=4, seed=1)
    assert torch.equal(again.lq, ps.lq)
    assert not torch.equal(make_degraded_pairs(seqs["F003"], scale=4, seed=2).lq, ps.lq)
    # noise changes from frame to frame: an LQ of a repeated frame flickers
    rep = make_degraded_pairs(seqs["F003"][:1].expand(2, -1, -1, -1), seed=0)
    assert not torch.equal(rep.lq[0], rep.lq[1])
    # flows pass through and are checked
    flow = torch.zeros(FRAMES - 1, 2, 180, 320)
    assert make_degraded_pairs(seqs["F003"], flow=flow).flow is flow
    with pytest.raises(ValueError, match="flow"):
        make_degraded_pairs(seqs["F003"], flow=torch.zeros(FRAMES, 2, 180, 320))


def test_face_pair_sets_and_baseline(face_capture):
    sets = make_face_pair_sets(face_capture, CAMS, FRAMES, size=(90, 160), seed=0)
    assert [s.name for s in sets] == CAMS
    assert all(s.lq.shape == (FRAMES, 4, 90, 160) for s in sets)
    full = make_face_pair_sets(face_capture, ["F003"], FRAMES)[0]
    base = bicubic_unsharp(full.lq)
    assert base.shape == full.lq.shape
    d = to_display
    assert psnr(d(base), d(full.hq)) > psnr(d(full.lq), d(full.hq))   # the floor is a floor above LQ
    one = bicubic_unsharp(full.lq[0], size=(360, 640))
    assert one.shape == (4, 360, 640) and float(one[3].max()) <= 1


def test_validity_threshold_on_degraded_face_pairs(face_capture):
    """The default validity threshold sits above the LQ degradation's frame-to-frame noise: with DIS
    flow between consecutive LQ frames of the (nearly still) face, nearly every pixel is valid."""
    from volcap_core.enhance.temporal import DisFlow, temporal_condition

    ps = make_face_pair_sets(face_capture, ["F003"], FRAMES)[0]
    dis = DisFlow()
    for t in range(1, FRAMES):
        warped, mask = temporal_condition(ps.hq[t - 1], ps.lq[t - 1], ps.lq[t], dis)
        assert float(mask.mean()) > 0.95
        # where valid, the warped previous HQ is close to the current HQ
        assert psnr(to_display(warped) * mask, to_display(ps.hq[t]) * mask) > 30
