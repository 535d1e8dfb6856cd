"""The detail enhancer at full size on a GPU: seconds and memory per denoising step at 1024² and 4K,
a whole 4K frame, and bf16 LoRA training steps. FLUX.1-dev's architecture with random weights
(timing and memory need no trained weights; no weights are downloaded).

    python bench/bench_enhance_gpu.py --json out.json             # ~3-4 min on one H100/H200
    python bench/bench_enhance_gpu.py --config small --quick      # smoke run of the same code (CPU ok)

What is timed, all through the code a production runs (``volcap_core.enhance``):

* **denoising step**: one :func:`~volcap_core.enhance.inference.tiled_velocity` call, the
  transformer's forward at one noise level with the six packed input latents, on a frame's latent.
  1024² is one pass (4096 image tokens + 512 prompt tokens); 3840×2160 is tiled as a shot is
  (``enhancer_tile`` 1024 px, overlap 256 px: 15 tiles, ``tile_batch`` 4), blended. bf16 weights
  and activations (the FLUX presets' inference dtype). The median of ``--repeats`` after a warm-up;
  ``torch.cuda.synchronize`` around each.
* **VAE**: encoding the four conditions of a frame and decoding its RGB and alpha latents
  (``encode_conditions`` / ``decode_rgba``, diffusers' VAE tiling on, as in ``enhance_frame``).
* **whole frame**: :func:`~volcap_core.enhance.inference.enhance_frame` at 3840×2160 with a
  previous output (warp, validity mask), ``--frame-steps`` Euler steps, the low-frequency swap;
  a production's 28 steps cost this plus (28 − frame-steps) denoising steps.
* **training**: :func:`~volcap_core.enhance.training.train_enhancer` with ``finetune="lora"`` (rank
  16) and ``frozen_dtype="bfloat16"`` (the FLUX presets) on random LQ/HQ pairs, at crops 512 and
  1024, batch 1, with and without the transformer's gradient checkpointing; seconds per step (mean
  of the steps after the first) and the peak of ``torch.cuda.max_memory_allocated``.

Every figure comes with the GPU's name, torch and diffusers versions. Random weights make the
outputs meaningless; only time and memory are measured.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from volcap_core.enhance.inference import enhance_frame, tiled_velocity  # noqa: E402
from volcap_core.enhance.model import (  # noqa: E402
    EnhancerConfig, build_enhancer, decode_rgba, encode_conditions)
from volcap_core.enhance.pairs import PairSet  # noqa: E402
from volcap_core.enhance.training import EnhancerTrainConfig, train_enhancer  # noqa: E402


def _log(msg: str) -> None:
    print(msg, flush=True)


@contextlib.contextmanager
def default_dtype(dtype: torch.dtype):
    before = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(before)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def peak_gib(device: torch.device) -> float | None:
    return torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None


def timed(fn, device: torch.device, repeats: int) -> tuple[float, list[float]]:
    """Median seconds of ``fn()`` over ``repeats`` runs after one warm-up run."""
    fn()
    sync(device)
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync(device)
        runs.append(time.perf_counter() - t0)
    return statistics.median(runs), runs


def frame(h: int, w: int, seed: int, device: torch.device) -> torch.Tensor:
    """A smooth random RGBA frame ``[4, h, w]`` (linear RGB premultiplied, alpha in [0, 1])."""
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(1, 4, 9, 16, generator=g)
    x = torch.nn.functional.interpolate(base, size=(h, w), mode="bicubic", align_corners=False)[0].clamp(0, 1)
    x[:3] *= x[3:]
    return x.to(device)


def build(config: EnhancerConfig, device: torch.device, dtype: torch.dtype):
    """Random weights initialised directly on ``device`` in ``dtype`` (a 12 B model initialised
    on the CPU in float32 would take 48 GB and minutes)."""
    t0 = time.perf_counter()
    with torch.device(device), default_dtype(dtype):
        model = build_enhancer(config, seed=0)
    model.to(device=device, dtype=dtype).eval()
    sync(device)
    n = sum(p.numel() for p in model.transformer.parameters())
    _log(f"built: transformer {n / 1e9:.2f} B parameters, {dtype}, {time.perf_counter() - t0:.1f} s")
    return model, n


def bench_step(model, h: int, w: int, tile: int | None, device, repeats: int) -> dict:
    """One denoising step (the transformer over every tile, blended) on a ``h x w`` frame."""
    dt = model.transformer.dtype
    c = model.config.latent_channels
    lq = frame(h, w, 0, device)[None].to(dt)
    with torch.no_grad():
        cond = encode_conditions(model, lq, None, None).to(dt)
        x = torch.randn((1, 2 * c, h // 8, w // 8), device=device)
        prompt = model.prompt()
        tile_l = None if tile is None else tile // 8
        overlap_l = 0 if tile is None else (tile // 4) // 16 * 16 // 8
        reset_peak(device)
        med, runs = timed(lambda: tiled_velocity(model, x, cond, 0.5, prompt, tile=tile_l,
                                                 overlap=overlap_l, tile_batch=4), device, repeats)
    row = {"what": "denoising step", "size": f"{w}x{h}", "tile": tile, "s": med, "runs_s": runs,
           "peak_gib": peak_gib(device)}
    _log(f"  step {w}x{h} tile {tile}: {med:.3f} s (runs {', '.join(f'{r:.3f}' for r in runs)}), "
         f"peak {row['peak_gib'] or 0:.1f} GiB")
    return row


def bench_vae(model, h: int, w: int, device, repeats: int) -> list[dict]:
    from volcap_core.enhance.inference import _vae_tiling

    dt = model.transformer.dtype
    lq = frame(h, w, 0, device)[None].to(dt)
    prev = frame(h, w, 1, device)[None].to(dt)
    mask = torch.ones(1, 1, h, w, device=device, dtype=dt)
    rows = []
    with torch.no_grad(), _vae_tiling(model.vae, True):
        reset_peak(device)
        med, runs = timed(lambda: encode_conditions(model, lq, prev, mask), device, repeats)
        rows.append({"what": "VAE encode, 4 conditions", "size": f"{w}x{h}", "s": med, "runs_s": runs,
                     "peak_gib": peak_gib(device)})
        lat = torch.randn(1, 2 * model.config.latent_channels, h // 8, w // 8, device=device, dtype=dt)
        reset_peak(device)
        med, runs = timed(lambda: decode_rgba(model, lat), device, repeats)
        rows.append({"what": "VAE decode, RGB + alpha", "size": f"{w}x{h}", "s": med, "runs_s": runs,
                     "peak_gib": peak_gib(device)})
    for r in rows:
        _log(f"  {r['what']} {r['size']}: {r['s']:.3f} s, peak {r['peak_gib'] or 0:.1f} GiB")
    return rows


def bench_frame(model, h: int, w: int, tile: int, steps: int, device) -> dict:
    """A whole second frame (previous output, zero flow) through ``enhance_frame``, the frames on
    the CPU as ``enhance-shot`` reads them (``enhance_frame`` moves them to the model's device)."""
    cpu = torch.device("cpu")
    lq0, lq1 = frame(h, w, 0, cpu), frame(h, w, 2, cpu)
    prev_out = frame(h, w, 1, cpu)
    zero_flow = torch.zeros(2, h, w)
    reset_peak(device)
    run = lambda: enhance_frame(model, lq1, prev_out, lq0, zero_flow, steps=steps, seed=1, tile=tile)  # noqa: E731
    med, runs = timed(run, device, 1)
    row = {"what": f"whole frame, {steps} steps", "size": f"{w}x{h}", "tile": tile, "s": med, "runs_s": runs,
           "peak_gib": peak_gib(device)}
    _log(f"  frame {w}x{h}, {steps} steps: {med:.2f} s, peak {row['peak_gib'] or 0:.1f} GiB")
    return row


def bench_training(model, crop: int, checkpointing: bool, steps: int, device) -> dict:
    pairs = [PairSet(lq=torch.stack([frame(crop, crop, 10 + t, torch.device("cpu")) for t in range(2)]),
                     hq=torch.stack([frame(crop, crop, 20 + t, torch.device("cpu")) for t in range(2)]),
                     name="random")]
    cfg = EnhancerTrainConfig(steps=steps, batch=1, crop=crop, finetune="lora", lora_rank=16,
                              frozen_dtype="bfloat16", checkpoint_every=0, flow="zero")
    if checkpointing:
        model.transformer.enable_gradient_checkpointing()
    else:
        model.transformer.disable_gradient_checkpointing()
    reset_peak(device)
    walls: list[float] = []
    last = [0.0]

    def progress(step, total, info):
        sync(device)
        walls.append(info["wall_s"] - last[0])
        last[0] = info["wall_s"]

    error = None
    try:
        train_enhancer(model, pairs, cfg, device=device, progress=progress)
    except torch.OutOfMemoryError as e:  # measured, not hidden: the row says so
        error = f"out of memory: {str(e).splitlines()[0]}"
    model.transformer.disable_gradient_checkpointing()
    model.to(torch.bfloat16)
    row = {"what": "LoRA training step (bf16 frozen)", "crop": crop, "gradient_checkpointing": checkpointing,
           "s_per_step": statistics.mean(walls[1:]) if len(walls) > 1 else None, "steps_s": walls,
           "peak_gib": peak_gib(device), "error": error}
    _log(f"  train crop {crop} ckpt {checkpointing}: "
         + (error or f"{row['s_per_step']:.3f} s/step, peak {row['peak_gib'] or 0:.1f} GiB"))
    return row


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", choices=["flux-dev", "small", "tiny"], default="flux-dev")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--frame-steps", type=int, default=4)
    ap.add_argument("--train-steps", type=int, default=4)
    ap.add_argument("--quick", action="store_true", help="small frames (smoke run of the same code)")
    ap.add_argument("--skip", nargs="*", default=[], choices=["step", "vae", "frame", "train"])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    config = {"flux-dev": EnhancerConfig.flux_dev, "small": EnhancerConfig.small,
              "tiny": EnhancerConfig.tiny}[args.config]()
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    import diffusers

    env = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
           "torch": torch.__version__, "diffusers": diffusers.__version__, "config": args.config}
    _log(json.dumps(env))
    sizes = [(128, 128), (256, 448)] if args.quick else [(1024, 1024), (2160, 3840)]
    tile = 128 if args.quick else 1024
    crops = [64] if args.quick else [512, 1024]
    model, n = build(config, device, dtype)
    rows: list[dict] = []
    out = {"env": env, "transformer_parameters": n, "rows": rows}

    def stage(name: str, fn) -> None:
        """Run one measurement; a failure is recorded as a row (it is a finding) and the rest go on."""
        if name.split()[0] in args.skip:
            return
        try:
            got = fn()
            rows.extend(got if isinstance(got, list) else [got])
        except Exception as e:  # noqa: BLE001 - reported in the output, not hidden
            rows.append({"what": name, "error": f"{type(e).__name__}: {e}"})
            _log(f"  {name}: FAILED {type(e).__name__}: {e}")
        if args.json:
            args.json.write_text(json.dumps(out, indent=1))

    for h, w in sizes:
        stage(f"step {w}x{h}", lambda h=h, w=w: bench_step(model, h, w, None if (h, w) == sizes[0] else tile,
                                                          device, args.repeats))
    stage("vae", lambda: bench_vae(model, *sizes[-1], device, max(1, args.repeats - 1)))
    stage("frame", lambda: bench_frame(model, *sizes[-1], tile, args.frame_steps, device))
    for crop in crops:
        for ckpt in (False, True):
            stage(f"train crop {crop} checkpointing {ckpt}",
                  lambda crop=crop, ckpt=ckpt: bench_training(model, crop, ckpt, args.train_steps, device))
    return out


if __name__ == "__main__":
    main()
