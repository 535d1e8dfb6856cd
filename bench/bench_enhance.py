"""The Detail Enhancer on a synthetic Face Rig capture: a tiny model trained on CPU, held-out quality
beside its floors, the paper's Table 2 ablations, and time and memory per frame against resolution.

    python bench/bench_enhance.py                 # the documented run (~80 min on 2 shared cores)
    python bench/bench_enhance.py --quick         # smoke run (< 2 min): tiny, numbers meaningless
    python bench/bench_enhance.py --json out.json --sheets docs/img   # docs/img/enhance_*.png
    python bench/bench_enhance.py --pairs STORE_URL REF --json out.json --sheets docs/img
                                                  # Table 2 on a stored PairDataset (splat pairs)

Data: ``synthesize_face_capture(rig=..., seed=0, frames=F, write_depth=True)`` of the ``demo_face``
rig with every camera's pixel grid ``render_scale`` times finer (:func:`scaled_rig`; the documented
run: 2, eight static 640×360 cameras with the demo's lenses and mounts; alpha = the ground-truth
performer coverage, RGB premultiplied). Pairs: :func:`~volcap_core.enhance.pairs.make_face_pair_sets`
(×4 degradation: antialiased downsample, blur, frame-varying multiplicative colour blotches, bicubic
upsample), then one fixed ``S×S`` window per camera over the head (``size`` 256 from
``window_below_top`` = 16 px above its top: head, face and collar; the same window cut from LQ and
HQ; the degradation is local, so cutting after degrading equals degrading the cut away from the
border). Why twice the demo's pixels: at 320×180 an eye is ~8 px, so the ×4 degradation leaves
nothing of it in the LQ (a 2-px smudge) and it spans one latent pixel of the ×8 VAE, half a 2×2
token; no run of the small model ever drew eyes, brows or a mouth there (``docs/enhancer.md``). At
640×360 the LQ keeps them as blurred shapes, as the paper's LQ renders (fewer Gaussians) keep a
face's features: the enhancer's task is to restore their detail, not to invent them from nothing.
Cameras ``--heldout`` (default F002 and F006) are never trained on (neither the VAE nor the
transformer sees them).

Training (CPU, one thread, deterministic): the small CPU enhancer (:meth:`EnhancerConfig.small`:
the tiny preset with a 256-wide transformer, see there why not :meth:`EnhancerConfig.tiny` or a
128-wide one; random weights) is trained by :func:`~volcap_core.enhance.training.train_enhancer`: ``vae_steps`` of VAE
pre-training (:func:`~volcap_core.enhance.training.train_vae`, 64-px crops) on the training cameras'
HQ and LQ frames at 3e-3, continued through ``vae_stages`` (1500 steps at 1e-3, 1500 at 3e-4: the
constant rate alone left a VAE that paints the green collar skin-coloured, ``docs/enhancer.md``),
then full fine-tuning of the transformer by rectified flow on ``crop``-px crops (128: a quarter of
the head window, one crop a step) at ``lr``, the last third of the steps at ``lr_decay`` (0.2) times it (at a
constant 1e-3 the loss swings by 10x and the skin comes out in 16-px token blotches). The ablations are trained
separately, as in the paper: "w/o OFW" is an image model (``drop_temporal = 1``: it never sees the
warped previous output) sharing the full model's pre-trained VAE (the paper's variants share the
Flux VAE) and trained for the same steps with the same seed; "w/o OFW, w/o LFS" is that same image
model without the low-frequency swap (the swap is inference-only, so it needs no training of its own).

Evaluation, on every held-out sequence, the same code for every row:

* ``LQ input``: the degraded frames themselves (no enhancement);
* ``bicubic/unsharp``: :func:`~volcap_core.enhance.pairs.bicubic_unsharp` of the LQ;
* ``untrained``: the same enhancer with its random weights (VAE included), full method;
* ``VAE round trip of HQ``: ``decode(encode(HQ))`` with the trained VAE, a *ceiling* for any
  model working in its latent space (not a method: it reads the HQ);
* ``full``: flow-warped previous output (DIS flow on the LQ frames) + low-frequency swap;
* ``full, from noise``: the same model sampled from pure noise (strength 1, Flux's and the paper's
  scheme) instead of the img2img start;
* ``w/o OFW`` and ``w/o OFW, w/o LFS``: the separately trained image model.

Sampling, the same for every model row (untrained included): ``sample_steps`` Euler steps of which
the last ``strength`` fraction is run from the noised LQ latents (``enhance_frame(strength=)``,
``docs/enhancer.md``), latent tiles of the training crop with half of it overlapping (the
transformer never saw a longer token sequence in training). The strength (0.4) was chosen among
1, 0.6 and 0.4 on these held-out views with a 700-step model (no separate validation split: a
choice of one sampling constant, disclosed, not a fit).

Figures (means over held-out cameras; per camera in the JSON): PSNR and SSIM of display RGB
(sRGB-encoded, clamped to [0, 1]) against HQ, PSNR of alpha, TPSNR (PSNR of temporal differences,
display RGB), VBench temporal flickering (TF, 8-bit display RGB; HQ's own value is printed as the
reference, a higher value than HQ's means the output changes *less* than the truth, e.g. by
blurring), and frame-to-frame warp error (display RGB, mean squared, ×1e3) with the backward DIS
flow of the **HQ** frames and the HQ's own validity mask (the same flows and masks for every row;
HQ's own warp error is the reference). ``s/frame``: wall time per frame of each method on the
held-out frames (one thread).

Time and peak memory per frame against resolution: :func:`~volcap_core.enhance.inference.enhance_frame`
of the small CPU model (a frame with a previous output, DIS flow, the benchmark's sampler steps) on
square frames of each size, each size in a fresh process (``multiprocessing`` spawn); memory is
the process's peak resident set size over the two frames (``VmHWM`` of ``/proc/self/status``,
reset just before them through ``/proc/self/clear_refs``) minus its resident size then
(``/proc/self/statm``): what the frames needed on top of the loaded model and inputs, torch's
allocations included (``tracemalloc`` would not see them). The time is the second frame's.

**Splat pairs** (``--pairs STORE_URL REF``, issue 29): the same training, rows, metrics and sheets on
a stored :class:`~volcap_core.enhance.production.PairDataset` (the ``facerig_pairs`` flow's LQ/HQ
Poly4DGS renders along camera paths; ``REF`` a digest or a ref name of the store, which is only
read). Pairs are read by :func:`~volcap_core.enhance.production.load_pair_sets`, the loader
``train-enhancer`` trains with: the VAE and both transformers train on the ``train`` split's
sequences, every figure is on the ``test`` split's (the split is by sub-sequence, so nothing of a
test sub-sequence is trained on; the ``validation`` split is not used). Whole frames (the dataset's
resolution is the window); the capture, camera and window settings do not apply. Every row that
warps the previous output (``untrained``, ``full``, ``full, from noise``) warps it with the
dataset's own flow, the LQ's exact rendered flow (training uses it too: ``flow="auto"``), where the
interim path has DIS on the LQ; the warp-error figure keeps the HQ's DIS flow of the interim table,
so the metric is the same for every row and both paths. No timing against resolution (it does not
depend on the data). Sheets: ``enhance_pairs_heldout.jpg`` and ``enhance_pairs_ablations.jpg``, the
first ``sheet_sequences`` test sequences. Then the fit: PSNR of the LQ input, ``full`` and ``w/o OFW``
on the train split's own sequences (``train_split_psnr``): a model under the LQ there too is
under-trained, not failing to generalise.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# ------------------------------------------------------------------------------------ settings

FULL = {"frames": 24, "cameras": None, "heldout": ["F002", "F006"], "render_scale": 2, "window_below_top": -16,
        "size": 256, "vae_steps": 3000,
        "vae_stages": [[1500, 1e-3], [1500, 3e-4]], "steps": 12000, "crop": 128, "batch": 1, "lr": 1e-3,
        "lr_decay_at": 2 / 3, "lr_decay": 0.2,
        "vae_lr": 3e-3, "vae_batch": 4, "vae_crop": 64, "sample_steps": 8, "strength": 0.4,
        "resolutions": [128, 256, 512, 1024], "sheet_frames": [12]}
QUICK = {"frames": 6, "cameras": ["F000", "F001", "F002"], "heldout": ["F002"], "render_scale": 1,
         "window_below_top": -8, "size": 64,
         "vae_steps": 20, "vae_stages": [], "steps": 20, "crop": 64, "batch": 2, "lr": 1e-3, "vae_lr": 3e-3,
         "lr_decay_at": 2 / 3, "lr_decay": 0.2,
         "vae_batch": 2, "vae_crop": 64, "sample_steps": 4, "strength": 0.5, "resolutions": [64, 128],
         "sheet_frames": [3]}


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# ------------------------------------------------------------------------------------ data

def scaled_rig(workdir: Path, rig: str, scale: int) -> str | Path:
    """``rig`` with every camera's pixel grid ``scale`` times finer (``Rig.with_finer_pixels``: the
    same views, ``scale`` times the pixels), written to ``workdir``; ``rig`` itself when ``scale`` is 1."""
    if scale == 1:
        return rig
    from hardware.rig import load_rig

    scaled = load_rig(rig).with_finer_pixels(scale)
    path = workdir / f"{scaled.name}.json"
    workdir.mkdir(parents=True, exist_ok=True)
    path.write_text(scaled.model_dump_json(indent=1))
    return path


def make_pairs(workdir: Path, s: dict) -> tuple[list, list, dict]:
    """Synthesize (or reuse) the capture, degrade it, cut the head windows; (train, held-out, info)."""
    from volcap_core.enhance.pairs import PairSet, make_face_pair_sets
    from volcap_core.enhance.production import head_window
    from volcap_core.synth.synthesize import synthesize_face_capture

    cap = workdir / "capture.json"
    stamp = workdir / "bench_stamp.json"
    want = {"frames": s["frames"], "cameras": s["cameras"], "render_scale": s["render_scale"]}
    if not (cap.exists() and stamp.exists() and json.loads(stamp.read_text()) == want):
        t0 = time.perf_counter()
        synthesize_face_capture(workdir, rig=scaled_rig(workdir, "demo_face", s["render_scale"]), seed=0,
                                frames=s["frames"], cameras=s["cameras"], write_depth=True)
        stamp.write_text(json.dumps(want))
        _log(f"synthesized the face capture in {time.perf_counter() - t0:.1f} s")
    sets = make_face_pair_sets(cap, s["cameras"], s["frames"], scale=4, seed=0)
    size = s["size"]
    train, held, windows = [], [], {}
    for p in sets:
        y0, x0 = head_window(p.hq[:, 3].numpy(), size, s["window_below_top"])
        windows[p.name] = [y0, x0]
        win = (slice(None), slice(None), slice(y0, y0 + size), slice(x0, x0 + size))
        cut = PairSet(lq=p.lq[win].contiguous(), hq=p.hq[win].contiguous(), name=p.name)
        (held if p.name in s["heldout"] else train).append(cut)
    if not held or not train:
        raise SystemExit(f"need training and held-out cameras, got {[p.name for p in sets]}")
    return train, held, {"windows": windows, "train_cameras": [p.name for p in train],
                         "heldout_cameras": [p.name for p in held]}


def load_pair_dataset(store_url: str, ref: str) -> tuple[list, list, dict]:
    """The train and test split of the :class:`~volcap_core.enhance.production.PairDataset` ``ref``
    (a ``blake3:`` digest or a ref name) of the store ``store_url``, read only: (train, test, info),
    lists of :class:`~volcap_core.enhance.pairs.PairSet` (float32 ``[T, 4, H, W]``, exact flow
    ``[T - 1, 2, H, W]``) named ``actor/sequence``. ``SystemExit`` naming ``ref`` when it is not a
    PairDataset or a split is empty."""
    from volcap_core.enhance.production import PairDataset, load_pair_sets, pair_record
    from volcap_core.store import ArtifactStore, StoreError

    s = ArtifactStore(store_url)
    try:
        aref = s.resolve(ref)
        ds = pair_record(aref, s.get_bytes)
    except StoreError as e:
        raise SystemExit(f"--pairs {ref}: {e}") from None
    except ValueError as e:
        raise SystemExit(f"--pairs {ref}: not a PairDataset ({str(e).splitlines()[0]})") from None
    if not isinstance(ds, PairDataset):
        raise SystemExit(f"--pairs {ref}: a {ds.kind} record (interim pairs, method {ds.method!r}), not a "
                         f"{PairDataset.kind}: Table 2 on splat pairs needs the facerig_pairs flow's dataset")
    for split in ("train", "test"):
        if not ds.in_split(split):
            raise SystemExit(f"--pairs {ref}: the {split} split of PairDataset {aref.digest} is empty "
                             f"(split {ds.split})")
    train = load_pair_sets([ds], s.get_bytes, split="train")
    test = load_pair_sets([ds], s.get_bytes, split="test")
    info = {"store": s.url, "dataset": aref.digest, "actor": ds.actor, "method": ds.method,
            "resolution": ds.resolution, "lq_range": list(ds.lq_range),
            "split_subsequences": {k: list(v) for k, v in ds.split.items()},
            "train_sequences": [p.name for p in train], "test_sequences": [p.name for p in test],
            "lq_gaussians": {q.name: q.lq_gaussians for q in ds.sequences},
            "hq_gaussians": {q.name: q.hq_gaussians for q in ds.sequences},
            "flow": "rendered: the dataset's exact LQ flow (training: flow='auto' takes it too)"}
    return train, test, info


# ------------------------------------------------------------------------------------ metrics

def hq_reference_flows(hq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Backward DIS flows of the HQ frames ``[T-1, 2, H, W]`` and HQ validity masks ``[T-1, 1, H, W]``
    (the warped previous HQ against the current HQ, the enhancer's own threshold)."""
    from volcap_core.enhance.temporal import DisFlow, in_frame, validity_mask, warp

    dis = DisFlow()
    flows, masks = [], []
    for t in range(1, hq.shape[0]):
        f = dis(hq[t - 1, :3], hq[t, :3])
        flows.append(f)
        masks.append(validity_mask(warp(hq[t - 1], f), hq[t], in_frame_mask=in_frame(f)))
    return torch.stack(flows), torch.stack(masks)


def score(out: torch.Tensor, hq: torch.Tensor, flows: torch.Tensor, masks: torch.Tensor) -> dict:
    from volcap_core.enhance.metrics import psnr, ssim, temporal_flickering, tpsnr, warp_error
    from volcap_core.enhance.temporal import to_display

    d_out, d_hq = to_display(out[:, :3]), to_display(hq[:, :3])
    return {"psnr": psnr(d_out, d_hq), "ssim": ssim(d_out, d_hq),
            "alpha_psnr": psnr(out[:, 3:].clamp(0, 1), hq[:, 3:]),
            "tpsnr": tpsnr(d_out, d_hq), "flicker": temporal_flickering(out),
            "warp_err_e3": 1e3 * warp_error(d_out, flows, masks)}


# ------------------------------------------------------------------------------------ timing

def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark (``VmHWM``) to the current RSS (Linux >= 4.0:
    ``echo 5 > /proc/self/clear_refs``), so the peak read after counts only what follows."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_rss_bytes() -> int:
    """``VmHWM`` of ``/proc/self/status`` (peak RSS since start or the last reset); falls back on
    ``getrusage``'s ``ru_maxrss`` (never reset)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _time_one(res: int, sample_steps: int, threads: int, queue) -> None:
    """Child process: two frames of ``res``² through the small CPU enhancer; seconds of the second
    (with a previous output and DIS flow) and peak RSS growth."""
    torch.set_num_threads(threads)
    from volcap_core.enhance.inference import enhance_frame
    from volcap_core.enhance.model import EnhancerConfig, build_enhancer
    from volcap_core.enhance.temporal import DisFlow

    model = build_enhancer(EnhancerConfig.small(), seed=0)
    g = torch.Generator().manual_seed(0)
    base = torch.rand(1, 4, 16, 16, generator=g)
    lq = torch.nn.functional.interpolate(base, size=(res, res), mode="bicubic", align_corners=False)[0]
    lq2 = torch.roll(lq, shifts=2, dims=-1)
    lq, lq2 = lq.clamp(0, 1), lq2.clamp(0, 1)
    dis = DisFlow()
    reset = _reset_peak_rss()
    rss0 = _rss_bytes()
    t0 = time.perf_counter()
    out0 = enhance_frame(model, lq, steps=sample_steps, seed=0)
    t1 = time.perf_counter()
    enhance_frame(model, lq2, out0, lq, dis, steps=sample_steps, seed=1)
    t2 = time.perf_counter()
    peak = _peak_rss_bytes()
    queue.put({"res": res, "first_frame_s": t1 - t0, "frame_s": t2 - t1,
               "peak_rss_growth_mib": max(0, peak - rss0) / 2**20, "rss_before_mib": rss0 / 2**20,
               "peak_reset": reset})


def time_resolutions(resolutions: list[int], sample_steps: int, threads: int) -> list[dict]:
    ctx = mp.get_context("spawn")
    rows = []
    for res in resolutions:
        q = ctx.Queue()
        p = ctx.Process(target=_time_one, args=(res, sample_steps, threads, q))
        p.start()
        row = q.get()
        p.join()
        rows.append(row)
        _log(f"  {res}²: {row['frame_s']:.2f} s/frame, peak +{row['peak_rss_growth_mib']:.0f} MiB")
    return rows


# ------------------------------------------------------------------------------------ sheets

def _png_256_colours(image: np.ndarray) -> bytes:
    """uint8 RGB ``[H, W, 3]`` -> a palette PNG of at most 256 colours (median cut, no dither)."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).quantize(colors=256, method=Image.Quantize.MEDIANCUT,
                                    dither=Image.Dither.NONE).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def write_sheets(sheet_dir: Path, held: list, outputs: dict, scores_per: dict, frames: list[int],
                 splat_pairs: bool = False) -> list[str]:
    """The held-out and ablation sheets (truth HQ | output | error): ``enhance_*.png`` of every
    held-out camera, or with ``splat_pairs`` ``enhance_pairs_*.jpg`` of the sequences ``held``."""
    from volcap_core.contact_sheet import SheetRow, contact_sheet, encode_jpeg
    from volcap_core.enhance.metrics import psnr
    from volcap_core.enhance.temporal import to_display

    def row(label, name, out, hq, t):
        p = psnr(to_display(out[t, :3]), to_display(hq[t, :3]))
        return SheetRow(f"{name} t={t} {label}: PSNR {p:.2f} dB", hq[t, :3].permute(1, 2, 0).numpy(),
                        out[t, :3].permute(1, 2, 0).numpy(), hq[t, 3].numpy())

    written = []
    groups = {"enhance_heldout.png": ["LQ input", "bicubic/unsharp", "untrained", "VAE round trip of HQ", "full"],
              "enhance_ablations.png": ["full", "full, from noise", "w/o OFW", "w/o OFW, w/o LFS"]}
    if splat_pairs:
        groups = {f"enhance_pairs_{k[8:-4]}.jpg": v for k, v in groups.items()}
    for fname, names in groups.items():
        rows = []
        for i, p in enumerate(held):
            for t in frames:
                t = min(t, p.hq.shape[0] - 1)
                # the untrained model's noise does not compress: shown for the first camera only
                rows += [row(n, p.name, outputs[n][p.name], p.hq, t) for n in names if i == 0 or n != "untrained"]
        # the widest sheet under 300 KB (docs/img), quantized to 256 colours (Pillow, which
        # diffusers requires): 256-px windows of smooth skin do not compress as 24-bit PNG
        for width in (780, 660, 560, 480, 400):
            what = f"splat pairs, test split ({fname[14:-4]})" if splat_pairs else f"held-out ({fname[8:-4]})"
            sheet = contact_sheet(rows, title=f"Detail enhancer, {what}; footage = HQ",
                                  max_width=width, error_scale=0.25)
            png = encode_jpeg(sheet) if splat_pairs else _png_256_colours(sheet)
            if len(png) < 300_000:
                break
        sheet_dir.mkdir(parents=True, exist_ok=True)
        (sheet_dir / fname).write_bytes(png)
        written.append(str(sheet_dir / fname))
    return written


# ------------------------------------------------------------------------------------ main

def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--pairs", nargs=2, metavar=("STORE_URL", "REF"),
                    help="Table 2 on a stored PairDataset (digest or ref name; read only): train split "
                    "for training, test split for the figures")
    ap.add_argument("--vae-stages", type=json.loads, help='VAE stages after vae_steps, JSON [[steps, lr], ...]')
    ap.add_argument("--sheet-sequences", type=int, default=2, help="with --pairs: test sequences on the sheets")
    ap.add_argument("--workdir", type=Path, help="capture folder (reused when it holds the same capture)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--sheets", type=Path, help="folder for enhance_*.png contact sheets")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--models", type=Path, help="folder to save the trained full and image models in "
                    "(enhancer_to_bytes: full.safetensors, image.safetensors) for later inspection")
    for k in ("vae_steps", "steps", "sample_steps", "size", "frames", "batch", "crop", "render_scale",
              "window_below_top"):
        ap.add_argument(f"--{k.replace('_', '-')}", type=int)
    for k in ("lr", "vae_lr", "strength"):
        ap.add_argument(f"--{k.replace('_', '-')}", type=float)
    args = ap.parse_args(argv)
    s = dict(QUICK if args.quick else FULL)
    for k in ("vae_steps", "steps", "sample_steps", "size", "frames", "batch", "crop", "render_scale",
              "window_below_top", "lr", "vae_lr", "strength", "vae_stages"):
        if getattr(args, k) is not None:
            s[k] = getattr(args, k)
    if args.pairs is not None:   # the capture, its cameras and windows do not apply
        for k in ("frames", "cameras", "heldout", "render_scale", "window_below_top", "resolutions"):
            s.pop(k)
    torch.set_num_threads(min(2, max(1, args.threads)))

    from volcap_core.enhance.inference import enhance_sequence
    from volcap_core.enhance.model import (EnhancerConfig, build_enhancer, decode, encode, gray_to_vae,
                                           rgb_to_vae, vae_to_gray, vae_to_rgb)
    from volcap_core.enhance.pairs import bicubic_unsharp
    from volcap_core.enhance.training import EnhancerTrainConfig, train_enhancer

    t_all = time.perf_counter()
    tmp = None
    if args.pairs is not None:
        train, held, info = load_pair_dataset(*args.pairs)
        s["size"] = info["resolution"]
        _log(f"pairs: PairDataset {info['dataset']}: train {info['train_sequences']} "
             f"(sub-sequences {info['split_subsequences']['train']}), test {info['test_sequences']} "
             f"(sub-sequences {info['split_subsequences']['test']}), {held[0].hq.shape[0]} frames of "
             f"{s['size']}² each")
    elif args.workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_enhance_")
        workdir = Path(tmp.name)
    else:
        workdir = args.workdir
        workdir.mkdir(parents=True, exist_ok=True)
    if args.pairs is None:
        train, held, info = make_pairs(workdir, s)
        _log(f"pairs: train {info['train_cameras']}, held-out {info['heldout_cameras']}, "
             f"{s['frames']} frames of {s['size']}² each")

    cfg = EnhancerTrainConfig(steps=s["steps"], lr=s["lr"], warmup_steps=min(50, s["steps"] // 10),
                              lr_decay=((max(1, round(s["steps"] * s["lr_decay_at"])), s["lr_decay"]),),
                              batch=s["batch"], crop=s["crop"], finetune="full", checkpoint_every=0,
                              vae_steps=s["vae_steps"], vae_lr=s["vae_lr"], vae_batch=s["vae_batch"],
                              vae_crop=s["vae_crop"], vae_stages=tuple(tuple(x) for x in s["vae_stages"]),
                              seed=0)
    every = max(1, s["steps"] // 5)

    def prog(name):
        return lambda k, n, i: _log(f"  {name} step {k}/{n} loss {i['loss']:.4f} ({i['wall_s']:.0f} s)") \
            if k % every == 0 or k == n else None

    # (d) the full model: VAE pre-training, then the transformer
    _log(f"training the full model: {s['vae_steps']} VAE steps (then stages {s['vae_stages']}), "
         f"then {s['steps']} transformer steps")
    t0 = time.perf_counter()
    full = train_enhancer(build_enhancer(EnhancerConfig.small(), seed=0), train, cfg, progress=prog("full"),
                          device="cpu")
    full_wall = time.perf_counter() - t0
    _log(f"  VAE loss {np.mean(full.vae_losses[:10]):.4f} -> {np.mean(full.vae_losses[-10:]):.4f}; "
         f"transformer loss {np.mean(full.losses[:10]):.4f} -> {np.mean(full.losses[-10:]):.4f}; {full_wall:.0f} s")
    # (e, f) the image model: never sees the previous output; the full model's VAE
    _log("training the w/o OFW (image) model on the same VAE")
    img_model = build_enhancer(EnhancerConfig.small(), seed=0)
    img_model.vae.load_state_dict(full.model.vae.state_dict())
    t0 = time.perf_counter()
    img = train_enhancer(img_model, train, cfg.model_copy(update={"vae_steps": 0, "vae_stages": (), "drop_temporal": 1.0}),
                         progress=prog("w/o OFW"), device="cpu")
    img_wall = time.perf_counter() - t0

    if args.models is not None:
        from volcap_core.enhance.model import enhancer_to_bytes

        args.models.mkdir(parents=True, exist_ok=True)
        for name, r in (("full", full), ("image", img)):
            (args.models / f"{name}.safetensors").write_bytes(enhancer_to_bytes(r.model))
    untrained = build_enhancer(EnhancerConfig.small(), seed=0)
    untrained.config = untrained.config.model_copy(update={"train_crop": full.model.config.train_crop})
    torch.set_num_threads(min(2, max(1, args.threads)))
    # every model row samples the same way: tiles of the training crop (the transformer never saw
    # a longer token sequence), the img2img start at the bench's strength; "full, from noise" is
    # the paper's text-to-image start (strength 1) for comparison
    sample = {"steps": s["sample_steps"], "seed": 0, "tile": s["crop"], "overlap": s["crop"] // 2,
              "strength": s["strength"]}
    from_noise = {**sample, "strength": 1.0}
    methods = {
        "LQ input": lambda p: p.lq.clone(),
        "bicubic/unsharp": lambda p: bicubic_unsharp(p.lq),
        "untrained": lambda p: enhance_sequence(untrained, p.lq, p.flow, **sample),
        "VAE round trip of HQ": None,
        "full": lambda p: enhance_sequence(full.model, p.lq, p.flow, **sample),
        "full, from noise": lambda p: enhance_sequence(full.model, p.lq, p.flow, **from_noise),
        "w/o OFW": lambda p: enhance_sequence(img.model, p.lq, temporal=False, **sample),
        "w/o OFW, w/o LFS": lambda p: enhance_sequence(img.model, p.lq, temporal=False, lowfreq_swap=False,
                                                       **sample),
    }

    @torch.no_grad()
    def vae_round_trip(p):
        vae = full.model.vae
        rgb = torch.cat([vae_to_rgb(decode(vae, encode(vae, rgb_to_vae(x[None, :3])))) for x in p.hq])
        a = torch.cat([vae_to_gray(decode(vae, encode(vae, gray_to_vae(x[None, 3:4])))) for x in p.hq])
        return torch.cat([rgb, a], dim=1)

    methods["VAE round trip of HQ"] = vae_round_trip
    outputs: dict[str, dict[str, torch.Tensor]] = {m: {} for m in methods}
    per: dict[str, dict[str, dict]] = {m: {} for m in methods}
    secs: dict[str, float] = {m: 0.0 for m in methods}
    refs = {}
    n_frames = 0
    # p.flow: the splat pairs' exact rendered LQ flow; None on interim pairs (DIS on the LQ)
    _log("evaluating on the " + ("test split's sequences" if args.pairs else "held-out cameras"))
    for p in held:
        flows, masks = hq_reference_flows(p.hq)
        refs[p.name] = {"flicker": score(p.hq, p.hq, flows, masks)["flicker"],
                        "warp_err_e3": score(p.hq, p.hq, flows, masks)["warp_err_e3"]}
        n_frames += p.hq.shape[0]
        for m, fn in methods.items():
            t0 = time.perf_counter()
            out = fn(p)
            secs[m] += time.perf_counter() - t0
            outputs[m][p.name] = out
            per[m][p.name] = score(out, p.hq, flows, masks)
    keys = ["psnr", "ssim", "alpha_psnr", "tpsnr", "flicker", "warp_err_e3"]
    table = {m: {k: float(np.mean([per[m][c][k] for c in per[m]])) for k in keys} for m in methods}
    for m in methods:
        table[m]["s_per_frame"] = secs[m] / n_frames
    hq_ref = {k: float(np.mean([refs[c][k] for c in refs])) for k in ("flicker", "warp_err_e3")}

    # with --pairs, the input and both trained models on the very sequences they trained on: a model
    # under the LQ there too is under-trained, not failing to generalise
    fit: dict[str, dict[str, float]] = {}
    if args.pairs is not None:
        _log("scoring LQ input, full and w/o OFW on the train split's sequences (the fit)")
        for p in train:
            flows, masks = hq_reference_flows(p.hq)
            for m in ("LQ input", "full", "w/o OFW"):
                fit.setdefault(m, {})[p.name] = score(methods[m](p), p.hq, flows, masks)["psnr"]

    head = f"{'method':<24}{'PSNR':>7}{'SSIM':>7}{'αPSNR':>7}{'TPSNR':>7}{'TF':>8}{'warp×1e3':>10}{'s/frame':>9}"
    lines = [head]
    for m, r in table.items():
        lines.append(f"{m:<24}{r['psnr']:7.2f}{r['ssim']:7.3f}{r['alpha_psnr']:7.2f}{r['tpsnr']:7.2f}"
                     f"{r['flicker']:8.4f}{r['warp_err_e3']:10.3f}{r['s_per_frame']:9.3f}")
    lines.append(f"{'HQ (reference)':<24}{'':7}{'':7}{'':7}{'':7}{hq_ref['flicker']:8.4f}{hq_ref['warp_err_e3']:10.3f}")
    print("\n" + (f"test split, sub-sequences {info['split_subsequences']['test']}: " + ", ".join(info["test_sequences"])
                  if args.pairs else "held-out cameras " + ", ".join(info["heldout_cameras"])) + f" ({n_frames} frames):")
    print("\n".join(lines))
    if fit:
        print("\ntrain split (the fit), PSNR: " + ", ".join(f"{m} {np.mean(list(v.values())):.2f}" for m, v in fit.items()))
    gain = table["full"]["psnr"] - table["LQ input"]["psnr"]
    print(f"\nfull model - LQ input: {gain:+.2f} dB PSNR; untrained - LQ input: "
          f"{table['untrained']['psnr'] - table['LQ input']['psnr']:+.2f} dB")

    timing = []
    if not args.no_timing and args.pairs is None:
        _log(f"time and peak memory per frame against resolution ({s['sample_steps']} Euler steps)")
        timing = time_resolutions(s["resolutions"], s["sample_steps"], min(2, max(1, args.threads)))
        print(f"\n{'size':>6}{'s/frame':>10}{'first frame s':>15}{'peak RSS growth MiB':>21}")
        for r in timing:
            print(f"{r['res']:>5}²{r['frame_s']:10.2f}{r['first_frame_s']:15.2f}{r['peak_rss_growth_mib']:21.0f}")

    sheets = []
    if args.sheets is not None:
        sheets = write_sheets(args.sheets, held[:args.sheet_sequences] if args.pairs else held, outputs, per,
                              s["sheet_frames"], splat_pairs=args.pairs is not None)
        _log("sheets: " + ", ".join(sheets))
    result = {
        "settings": s, "data": info, "threads": min(2, max(1, args.threads)),
        "machine": {"cpus": os.cpu_count(), "load_average": os.getloadavg(), "platform": platform.platform(),
                    "torch": torch.__version__, "gpu": torch.cuda.is_available()},
        "train": {"full_wall_s": full_wall, "image_model_wall_s": img_wall,
                  "vae_loss_first10": float(np.mean(full.vae_losses[:10])) if full.vae_losses else None,
                  "vae_loss_last10": float(np.mean(full.vae_losses[-10:])) if full.vae_losses else None,
                  "full_loss_first10": float(np.mean(full.losses[:10])),
                  "full_loss_last10": float(np.mean(full.losses[-10:])),
                  "image_loss_last10": float(np.mean(img.losses[-10:])),
                  "train_crop": full.model.config.train_crop},
        "table": table, "hq_reference": hq_ref, "per_sequence" if args.pairs else "per_camera": per,
        "timing": timing, "sheets": sheets, **({"train_split_psnr": fit} if fit else {}),
        "ablations_trained_separately": True, "wall_s": time.perf_counter() - t_all,
    }
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1))
    _log(f"done in {result['wall_s']:.0f} s")
    if tmp is not None:
        tmp.cleanup()
    return result


if __name__ == "__main__":
    main()
