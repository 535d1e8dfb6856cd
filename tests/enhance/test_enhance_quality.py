"""The Detail Enhancer learns: a small model trained briefly on CPU on pairs made from the synthetic
Face Rig capture moves far above the untrained model on held-out cameras, and the untrained model is
far below the LQ input (the floor is real).

It does NOT yet beat the LQ input with the full method (issue 14 open): see docs/benchmarks.md
"Detail enhancer", where the bench's larger budget is measured against every floor.

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


def test_training_lifts_the_enhancer_far_above_its_untrained_floor_on_held_out_cameras(tmp_path):
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
        trained = score(enhance_sequence(result.model, p.lq, steps=8, seed=0), p)
        floor = score(enhance_sequence(untrained, p.lq, steps=8, seed=0), p)
    finally:
        torch.set_num_threads(before)
    print(f"held-out PSNR: LQ {lq:.2f} dB, trained {trained:.2f} dB, untrained {floor:.2f} dB")
    assert trained > floor + MARGIN_DB, (lq, trained, floor)
    assert floor < lq - MARGIN_DB, (lq, floor)


#: training budget of the test (small, so the suite stays within its time).
#: MEASURED with 600 VAE + 400 transformer steps (2 shared cores, load 11-13, 9 min 50 s): held-out
#: F002 PSNR LQ 20.87 dB, trained 19.03 dB, untrained 10.25 dB. With this budget (2 min under load
#: 9-11): LQ 20.87 dB, trained 19.16 dB, untrained 10.25 dB: the lift is 8.9 dB and the floor sits
#: 10.6 dB under the LQ, so a 3 dB margin on both leaves ~3x room.
SETTINGS = {"vae_steps": 150, "steps": 100}
MARGIN_DB = 3.0
