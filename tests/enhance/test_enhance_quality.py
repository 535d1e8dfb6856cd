"""The Detail Enhancer learns: a small model trained briefly on CPU on pairs made from the synthetic
Face Rig capture beats the LQ input on a held-out camera with the full method (flow-warped previous
output, low-frequency swap), far above the untrained model, which is itself far below the LQ input
(the floor is real). docs/benchmarks.md "Detail enhancer" measures the bench's larger budget against
every floor, with the contact sheets.

A smaller version of ``bench/bench_enhance.py`` (which documents the protocol): 4 cameras of the
``demo_face`` rig, one held out; 8 frames; ×4 degraded pairs cut to a 96-px window over the head;
VAE pre-training then full fine-tuning of the transformer; held-out PSNR of display RGB.
"""

from __future__ import annotations

import pytest
import torch

pytestmark = pytest.mark.slow


def _window(alpha: torch.Tensor, size: int) -> tuple[int, int]:
    h, w = alpha.shape[-2:]
    cov = (alpha >= 0.5).any(dim=0)
    rows = torch.nonzero(cov.any(dim=1)).flatten()
    y0 = max(0, min(h - size, int(rows.min()) - 8))
    cols = torch.nonzero(cov[y0:y0 + size].any(dim=0)).flatten().float()
    x0 = max(0, min(w - size, int(round(float(cols.mean()) - size / 2))))
    return y0, x0


def test_a_briefly_trained_enhancer_beats_the_lq_input_on_a_held_out_camera(tmp_path):
    from volcap_core.enhance.inference import enhance_sequence
    from volcap_core.enhance.metrics import psnr
    from volcap_core.enhance.model import EnhancerConfig, build_enhancer
    from volcap_core.enhance.pairs import PairSet, make_face_pair_sets
    from volcap_core.enhance.temporal import to_display
    from volcap_core.enhance.training import EnhancerTrainConfig, train_enhancer
    from volcap_core.synth.synthesize import synthesize_face_capture

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cams = ["F000", "F001", "F002", "F003"]
        cap = synthesize_face_capture(tmp_path / "cap", rig="demo_face", seed=0, frames=8, cameras=cams,
                                      write_depth=True)
        size = 96
        train, held = [], []
        for p in make_face_pair_sets(cap, cams, 8, scale=4, seed=0):
            y0, x0 = _window(p.hq[:, 3], size)
            win = (slice(None), slice(None), slice(y0, y0 + size), slice(x0, x0 + size))
            cut = PairSet(lq=p.lq[win].contiguous(), hq=p.hq[win].contiguous(), name=p.name)
            (held if p.name == "F002" else train).append(cut)
        cfg = EnhancerTrainConfig(steps=SETTINGS["steps"], lr=1e-3, warmup_steps=30, batch=4, crop=64,
                                  finetune="full", checkpoint_every=0, vae_steps=SETTINGS["vae_steps"],
                                  vae_lr=3e-3, vae_batch=4, vae_crop=64, seed=0)
        result = train_enhancer(build_enhancer(EnhancerConfig.small(), seed=0), train, cfg, device="cpu")
        untrained = build_enhancer(EnhancerConfig.small(), seed=0)
        untrained.config = untrained.config.model_copy(update={"train_crop": result.model.config.train_crop})

        def score(x: torch.Tensor, p: PairSet) -> float:
            return psnr(to_display(x[:, :3]), to_display(p.hq[:, :3]))

        p = held[0]
        lq = score(p.lq, p)
        trained = score(enhance_sequence(result.model, p.lq, **SAMPLING), p)
        floor = score(enhance_sequence(untrained, p.lq, **SAMPLING), p)
    finally:
        torch.set_num_threads(before)
    print(f"held-out PSNR: LQ {lq:.2f} dB, trained {trained:.2f} dB, untrained {floor:.2f} dB")
    assert trained > lq + GAIN_DB, (lq, trained, floor)
    assert trained > floor + MARGIN_DB, (lq, trained, floor)
    assert floor < lq - MARGIN_DB, (lq, floor)


#: training budget of the test (small, so the suite stays within its time) and the bench's sampling
#: (8 Euler steps, the last 40 % from the noised LQ, 64-px latent tiles: the training crop).
#: MEASURED (2026-11-27, EnhancerConfig.small() 256 wide, 200 VAE + 120 transformer steps):
#: held-out F002 PSNR LQ 20.87 dB, trained 22.20 dB, untrained 7.62 dB; the other budgets and widths
#: measured: docs/benchmarks.md "Detail enhancer". (Sampled from pure noise over the whole frame, the
#: 256-wide model trained 150 + 100 steps gave 21.06 dB, the 128-wide 600 + 400 steps 19.03.) The gain
#: over the LQ is asserted at 0.6 dB (half the 1.29 dB measured at the earlier 600 + 400 steps); the
#: lift over the floor and the floor's depth under the LQ at 3 dB (measured 14.6 and 13.3).
SETTINGS = {"vae_steps": 200, "steps": 120}
SAMPLING = {"steps": 8, "seed": 0, "tile": 64, "overlap": 32, "strength": 0.4}
GAIN_DB = 0.6
MARGIN_DB = 3.0
