"""Flow back-ends, warping, validity masks and the temporal conditions of the detail enhancer."""

from __future__ import annotations

import pytest
import torch

from volcap_core.enhance.temporal import (
    VALIDITY_THRESHOLD,
    DisFlow,
    FlowBackend,
    FlowUnavailable,
    RaftFlow,
    in_frame,
    temporal_condition,
    to_display,
    to_display_u8,
    validity_mask,
    warp,
)


def _texture(h: int, w: int, shift: tuple[float, float] = (0.0, 0.0), seed: int = 0, n: int = 300,
             channels: int = 3) -> torch.Tensor:
    """Sum of random Gaussian blobs evaluated at continuous coordinates: content moved by ``shift``
    (px, x then y) exactly, sub-pixel shifts included."""
    g = torch.Generator().manual_seed(seed)
    cx = torch.rand(n, generator=g, dtype=torch.float64) * (w + 20) - 10
    cy = torch.rand(n, generator=g, dtype=torch.float64) * (h + 20) - 10
    s = torch.rand(n, generator=g, dtype=torch.float64) * 3 + 1.5
    col = torch.rand(n, channels, generator=g, dtype=torch.float64) * 0.5
    ys = torch.arange(h, dtype=torch.float64)[:, None] - shift[1]
    xs = torch.arange(w, dtype=torch.float64)[None, :] - shift[0]
    d2 = (xs[None] - cx[:, None, None]) ** 2 + (ys[None] - cy[:, None, None]) ** 2
    blobs = torch.exp(-d2 / (2 * s[:, None, None] ** 2))            # [n, h, w]
    img = torch.einsum("nc,nhw->chw", col, blobs)
    return (img * 0.6 + 0.02).float()


def _const_flow(h: int, w: int, dx: float, dy: float) -> torch.Tensor:
    f = torch.empty(2, h, w)
    f[0], f[1] = dx, dy
    return f


def test_warp_integer_translation():
    img = torch.rand(4, 20, 30, generator=torch.Generator().manual_seed(0))
    # current content = previous moved right by 3 and down by 2: cur(x, y) = prev(x - 3, y - 2)
    flow = _const_flow(20, 30, -3.0, -2.0)
    out = warp(img, flow)
    # (grid_sample's normalised coordinates round the sample positions by ~1e-6 px)
    torch.testing.assert_close(out[:, 2:, 3:], img[:, :-2, :-3], rtol=0, atol=1e-5)
    # the revealed border (no previous pixel) is 0 and invalid
    assert (out[:, :2] == 0).all() and (out[:, :, :3] == 0).all()
    m = in_frame(flow)
    assert m.shape == (1, 20, 30)
    assert (m[0, :2] == 0).all() and (m[0, :, :3] == 0).all() and (m[0, 2:, 3:] == 1).all()
    # the other direction
    out = warp(img, _const_flow(20, 30, 5.0, 0.0))
    torch.testing.assert_close(out[:, :, :-5], img[:, :, 5:], rtol=0, atol=1e-5)
    assert (out[:, :, -5:] == 0).all()


def test_warp_subpixel_is_bilinear_and_zero_flow_is_identity():
    img = torch.rand(3, 8, 9, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(warp(img, torch.zeros(2, 8, 9)), img, rtol=0, atol=1e-6)
    out = warp(img, _const_flow(8, 9, 0.25, 0.0))
    want = 0.75 * img[:, :, :-1] + 0.25 * img[:, :, 1:]
    torch.testing.assert_close(out[:, :, :-1], want, rtol=0, atol=1e-5)
    assert (out[:, :, -1] == 0).all()      # samples at x = 8.25 > W - 1: out of frame
    with pytest.raises(ValueError, match="flow"):
        warp(img, torch.zeros(2, 8, 8))


def test_validity_mask_threshold_and_out_of_frame():
    cur = torch.full((4, 10, 12), 0.2)
    prev = cur.clone()
    prev[:3, 3, 4] += 0.5                     # a changed pixel
    m = validity_mask(prev, cur)
    assert m.shape == (1, 10, 12) and m.dtype == torch.float32
    assert m[0, 3, 4] == 0 and m.sum() == 10 * 12 - 1
    m = validity_mask(prev, cur, threshold=1.0)
    assert (m == 1).all()
    alpha_changed = cur.clone()
    alpha_changed[3, 0, 0] = 1.0              # alpha differs by 0.8: invalid
    assert validity_mask(alpha_changed, cur)[0, 0, 0] == 0
    inside = in_frame(_const_flow(10, 12, -2.0, 0.0))
    m = validity_mask(cur, cur, in_frame_mask=inside)
    assert (m[0, :, :2] == 0).all() and (m[0, :, 2:] == 1).all()
    # the threshold is in display units: a linear change of 0.01 at 0.2 is 0.0106 after sRGB encoding
    near = cur.clone()
    near[:3] += 0.01
    d = float((to_display(near) - to_display(cur)).abs().max())
    assert validity_mask(near, cur, threshold=d + 1e-4).min() == 1
    assert validity_mask(near, cur, threshold=d - 1e-4).max() == 0


def test_temporal_condition_first_frame_is_zeros():
    cur = torch.rand(4, 16, 24)
    warped, mask = temporal_condition(None, None, cur, DisFlow())
    assert warped.shape == (4, 16, 24) and mask.shape == (1, 16, 24)
    assert (warped == 0).all() and (mask == 0).all()
    warped, mask = temporal_condition(None, torch.rand(4, 16, 24), cur, None)
    assert (warped == 0).all() and (mask == 0).all()
    with pytest.raises(ValueError, match="prev_lq"):
        temporal_condition(torch.rand(4, 16, 24), None, cur, None)


def test_temporal_condition_with_exact_flow():
    prev_lq = torch.cat([_texture(40, 56), torch.ones(1, 40, 56)])
    cur_lq = torch.zeros_like(prev_lq)
    cur_lq[:, :, 4:] = prev_lq[:, :, :-4]     # moved right by 4 px
    cur_lq[:, :, :4] = 0.9                     # new content revealed on the left
    prev_out = prev_lq * 1.1
    flow = _const_flow(40, 56, -4.0, 0.0)
    warped, mask = temporal_condition(prev_out, prev_lq, cur_lq, flow)
    torch.testing.assert_close(warped[:, :, 4:], prev_out[:, :, :-4], rtol=0, atol=1e-6)
    assert (mask[:, :, :4] == 0).all() and (mask[:, :, 4:] == 1).all()
    # zero flow (no motion compensation): the moved texture mismatches in many places
    _, mask0 = temporal_condition(prev_out, prev_lq, cur_lq, None)
    assert mask0.mean() < mask.mean()


def test_dis_recovers_translation():
    d = (2.6, -1.4)
    prev, cur = _texture(96, 128), _texture(96, 128, d)
    dis = DisFlow()
    assert isinstance(dis, FlowBackend)
    flow = dis(prev, cur)
    assert flow.shape == (2, 96, 128) and flow.dtype == torch.float32
    inner = flow[:, 8:-8, 8:-8]
    # backward flow: the current pixel was at x - d in the previous frame
    epe = ((inner[0] + d[0]) ** 2 + (inner[1] + d[1]) ** 2).sqrt()
    assert epe.mean() < 0.5 and epe.quantile(0.9) < 0.5, (epe.mean(), epe.quantile(0.9))
    # measured: mean end-point error ~0.03 px with the medium preset
    assert epe.mean() < 0.1
    # and through the temporal condition: the warped previous frame matches the current one
    prev4, cur4 = torch.cat([prev, torch.ones(1, 96, 128)]), torch.cat([cur, torch.ones(1, 96, 128)])
    warped, mask = temporal_condition(prev4, prev4, cur4, dis)
    assert mask[:, 8:-8, 8:-8].mean() > 0.98
    err = ((warped - cur4).abs() * mask)[:, 8:-8, 8:-8].amax()
    assert err < VALIDITY_THRESHOLD


def test_dis_presets_and_tone_map():
    with pytest.raises(ValueError, match="preset"):
        DisFlow("slowest")
    x = torch.tensor([[[0.0]], [[0.18]], [[4.0]], [[0.5]]])        # RGBA, HDR red above 1
    u8 = to_display_u8(x)
    assert u8.dtype == torch.uint8 and u8.flatten().tolist() == [0, 118, 255, 128]


def test_raft_refuses_without_torchvision_or_weights(tmp_path):
    try:
        import torchvision  # noqa: F401
    except ImportError:
        with pytest.raises(FlowUnavailable, match="torchvision"):
            RaftFlow(tmp_path / "raft.pth")
        return
    with pytest.raises(FlowUnavailable, match="weights"):
        RaftFlow(None)
    with pytest.raises(FlowUnavailable, match="no weights file"):
        RaftFlow(tmp_path / "missing.pth")


@pytest.mark.gpu
def test_raft_runs_from_a_local_state_dict(tmp_path):
    """RaftFlow with torchvision (installed here only on the GPU machines, beside CUDA torch):
    a state dict written to disk loads, the flow comes back ``[2, H, W]`` for a frame that is no
    multiple of 8 (RAFT needs at least 128 px a side), on the device asked for and back on the
    input's. The weights are random (none
    ship): this checks the machinery, not RAFT's accuracy."""
    tv = pytest.importorskip("torchvision.models.optical_flow", reason="needs torchvision")
    path = tmp_path / "raft_small.pth"
    torch.manual_seed(0)
    torch.save(tv.raft_small(weights=None).state_dict(), path)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    raft = RaftFlow(path, small=True, device=device, iters=4)
    prev, cur = _texture(130, 150), _texture(130, 150, (2.0, -1.0))
    flow = raft(prev, cur)
    assert flow.shape == (2, 130, 150) and flow.device == cur.device and torch.isfinite(flow).all()
    with pytest.raises(FlowUnavailable, match="weights"):
        RaftFlow(None)
