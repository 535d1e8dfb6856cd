"""Poly4DGS on a synthetic capture: held-out error against training time, and the paper's Table 1.

    python bench/bench_poly4dgs.py            # the documented run (19-21 min on 2 shared cores)
    python bench/bench_poly4dgs.py --quick    # smoke run (~30 s): tiny, numbers meaningless
    python bench/bench_poly4dgs.py --json out.json --plot docs/img/poly4dgs_error_vs_time.png

Scene: ``synthesize_capture(rig="demo_scene", seed=0, frames=N, write_depth=True)`` read back from
its files (:mod:`poly4dgs_data`): 12 cameras (8 static, 4 zoom/tracking with veiling glare), each
with its own gain, black offset and vignetting; two static cameras are held out (never trained on).
Initial points are the training cameras' ground-truth depth back-projected per frame ("dense"), or
2% of them ("sparse").

Runs (one seed each, same step budget S):

=================  ==============================================================================
full               Poly4DGS, paper degrees (n_μ, n_q, n_s, n_o) = (2, 1, 0, 2), all components
rotor4d            degrees (1, 0, 0, 1): the sliced 4D-Rotor Gaussian, same training otherwise
per_frame          one static 3DGS (degrees 0) per frame, S / N steps each, that frame's points
no_black           w/o black-level grids (training)
no_exposure        w/o exposure grids (training)
sparse             w/o dense points: 2% of the dense cloud (MCMC may grow it back to the cap)
linear_storage     SH colours stored as linear radiance (no sRGB decode before rasterization)
=================  ==============================================================================

Evaluation (one protocol for every run, the paper's): render all held-out views (2 cameras × N
frames), fit *only* the held-out cameras' exposure and black-level grids (100 Adam steps, lr 1e-2,
per camera jointly over all frames, the model frozen), then PSNR and SSIM of the display encoding
(sRGB clamped to [0, 1]). The ablations change training only: their held-out views get the same
E and B fit as everybody's. Snapshots come from ``train_segment``'s checkpoints; time on the x-axis
is training time only (``wall_s``: evaluation and checkpointing excluded), and the process CPU
time over the same steps (``cpu_s``), which other jobs on a shared machine inflate less (it
still moved ~15 % between identical runs on the 2-core development machine).

Default settings (``Settings.full``): 6 frames, images box-downsampled 2x to 160x90 (90x160
portrait), 5000 dense points per frame (30 000 Gaussians), 360 steps per run (per-frame: 60 per
frame), 3DGS-MCMC relocation 6 times per run (``mcmc_for``; the cap is the initial count, so only
the sparse run grows), SH degree 3. Curves (4 snapshots) for ``--curves`` (default: full, rotor4d,
per_frame, linear_storage), end points only for the rest. Also printed: what each run's exposure and
black-level grids learned against the synthetic cameras' true gain and black offset.

Runs single-threaded (``torch.set_num_threads(1)``; see ``--threads``). Writes the PNG (two
panels: PSNR against wall-clock and against CPU seconds) and, with ``--json``, every number.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load as st_load

sys.path.insert(0, str(Path(__file__).resolve().parent))

from poly4dgs_data import BenchScene, load_scene, subsample_points  # noqa: E402

from volcap_core.splat.grids import ExposureGrids, upsample_grid  # noqa: E402
from volcap_core.splat.loss import display_metrics, reconstruction_loss  # noqa: E402
from volcap_core.splat.mcmc import MCMCConfig  # noqa: E402
from volcap_core.splat.model import Poly4DGS, Poly4DGSConfig, evaluate  # noqa: E402
from volcap_core.splat.optim import AdamState, adam_step  # noqa: E402
from volcap_core.splat.render import render  # noqa: E402
from volcap_core.splat.train import (  # noqa: E402
    LearningRates,
    PointsAtTime,
    SegmentData,
    TrainConfig,
    View,
    init_model,
    train_segment,
)
from volcap_core.synth import synthesize_capture  # noqa: E402

HELD_OUT = ["S002", "S005"]
METHODS = ["full", "rotor4d", "per_frame", "no_black", "no_exposure", "sparse", "linear_storage"]
CURVE_METHODS = ("full", "rotor4d", "per_frame", "linear_storage")
LABELS = {
    "full": "Full (Poly4DGS, degrees 2,1,0,2)",
    "rotor4d": "4D-Rotor degrees (1,0,0,1)",
    "per_frame": "per-frame GS (static 3DGS per frame)",
    "no_black": "w/o black level",
    "no_exposure": "w/o exposure opt.",
    "sparse": "w/o dense points (2% of the points)",
    "linear_storage": "linear colour storage",
}
PAPER = {  # Table 1 of the paper (PSNR, SSIM, LPIPS); linear storage: "about 5 dB" below
    "full": (27.29, 0.9752, 0.0160), "no_black": (24.11, 0.9576, 0.0200),
    "no_exposure": (25.50, 0.9718, 0.0161), "sparse": (25.31, 0.9576, 0.0288),
    "per_frame": (26.11, 0.9697, 0.0204), "rotor4d": (27.08, 0.9730, 0.0171),
}


# ------------------------------------------------------------------------------------ settings

@dataclass(frozen=True)
class Settings:
    frames: int
    downsample: int
    points_per_frame: int
    steps: int
    snapshots: int                 # evaluation points along the curves (plus step 0)
    sparse_fraction: float = 0.02
    eval_fit_steps: int = 100
    sh_degree: int = 3
    seed: int = 0
    lr_exposure: float | None = None   # None: the library's LearningRates default
    lr_black: float | None = None

    @classmethod
    def full(cls) -> "Settings":
        return cls(frames=6, downsample=2, points_per_frame=5000, steps=360, snapshots=4)

    @classmethod
    def quick(cls) -> "Settings":
        return cls(frames=2, downsample=4, points_per_frame=1500, steps=40, snapshots=2,
                   eval_fit_steps=30, sh_degree=1)


def mcmc_for(steps: int, cap: int) -> MCMCConfig:
    """3DGS-MCMC scaled to a short run: relocation (and growth up to ``cap``) 6 times."""
    every = max(2, steps // 8)
    return MCMCConfig(refine_start=2 * every, refine_every=every, refine_stop=steps, cap_max=cap)


# ---------------------------------------------------------------------------------- evaluation

def evaluate_views(model_at, views: list[View], *, fit_steps: int, grid_size: int = 32,
                   lr: float = 1e-2, ssim_weight: float = 0.2) -> tuple[float, float]:
    """The paper's held-out protocol, as :func:`volcap_core.splat.train.evaluate_held_out` (same
    numbers to float rounding), for a model given per time: ``model_at(time) -> Poly4DGS``
    (per-frame GS has one per frame). Every held-out camera's exposure and black-level grids are
    fitted jointly over its views; the views of one camera are batched (the library loops over
    views). The fit's loss is the library's :func:`reconstruction_loss`, on a batch."""
    with torch.no_grad():
        renders = [render(evaluate(model_at(v.time), v.time), v.camera, backend="torch")["rgb"]
                   for v in views]
    cam_ids = sorted({v.camera_id for v in views})
    by_cam = {c: [i for i, v in enumerate(views) if v.camera_id == c] for c in cam_ids}
    R = {c: torch.stack([renders[i] for i in idx]) for c, idx in by_cam.items()}
    T = {c: torch.stack([views[i].load()[..., :3] for i in idx]) for c, idx in by_cam.items()}
    grids = ExposureGrids.identity(cam_ids, grid_size, "cpu")
    fit = {"exposure": grids.exposure.requires_grad_(True),
           "black": grids.black.requires_grad_(True)}
    state = AdamState.zeros_like(fit)

    def adjusted(j: int, c: str) -> torch.Tensor:   # [V_c, H, W, 3], apply_grids batched
        H, W = R[c].shape[1:3]
        black = upsample_grid(fit["black"][j], H, W).permute(1, 2, 0)
        return (R[c] + black) * upsample_grid(fit["exposure"][j], H, W).permute(1, 2, 0)

    for _ in range(fit_steps):
        for t in fit.values():
            t.grad = None
        # mean over views of the per-view loss (all views of a camera have one size)
        loss = sum(len(by_cam[c]) * reconstruction_loss(adjusted(j, c), T[c],
                                                        ssim_weight=ssim_weight)[0]
                   for j, c in enumerate(cam_ids)) / len(views)
        loss.backward()
        adam_step(fit, {"exposure": lr, "black": lr}, state)
    scores = []
    with torch.no_grad():
        for j, c in enumerate(cam_ids):
            out = adjusted(j, c)
            scores += [display_metrics(out[k], T[c][k]) for k in range(len(by_cam[c]))]
    return float(np.mean([s[0] for s in scores])), float(np.mean([s[1] for s in scores]))


# ------------------------------------------------------------------------------------ training

@dataclass
class Snapshot:
    step: int
    wall_s: float
    cpu_s: float
    model: Poly4DGS


@dataclass
class RunLog:
    snapshots: list[Snapshot] = field(default_factory=list)
    cpu_excluded: float = 0.0
    cpu_at_step: float = 0.0
    cpu_start: float = 0.0


def _model_from_checkpoint(blob: bytes) -> tuple[Poly4DGS, dict]:
    n = int.from_bytes(blob[:8], "little")
    meta = json.loads(blob[8:8 + n])["__metadata__"]
    cfg = Poly4DGSConfig.model_validate_json(meta["model_config"])
    t = st_load(blob)
    params = {k[6:]: v.clone() for k, v in t.items() if k.startswith("model/")}
    return Poly4DGS(cfg, params), json.loads(meta["state"])


def train_with_snapshots(data: SegmentData, points: list[PointsAtTime], cfg: TrainConfig,
                         *, seed: int) -> tuple[RunLog, Poly4DGS, ExposureGrids]:
    """``train_segment`` with checkpoints every ``cfg.checkpoint_every`` steps turned into model
    snapshots; CPU time of the steps is tracked beside the trainer's wall time (the CPU spent in
    checkpointing is excluded, as the trainer excludes its wall time)."""
    log = RunLog()

    def progress(step, total, info):
        log.cpu_at_step = time.process_time()

    def checkpoint(blob: bytes, step: int):
        model, state = _model_from_checkpoint(blob)
        train_cpu = log.cpu_at_step - log.cpu_start - log.cpu_excluded
        log.snapshots.append(Snapshot(step, float(state["wall_s"]), train_cpu, model))
        log.cpu_excluded += time.process_time() - log.cpu_at_step

    log.cpu_start = time.process_time()
    result = train_segment(data, points, cfg, checkpoint=checkpoint, progress=progress, seed=seed,
                           device="cpu")
    return log, result.model, result.grids


def base_config(s: Settings, *, model: Poly4DGSConfig, steps: int, cap: int,
                checkpoint_every: int, **kw) -> TrainConfig:
    lr = {k: v for k, v in (("exposure", s.lr_exposure), ("black", s.lr_black)) if v is not None}
    return TrainConfig(model=model, steps=steps, mcmc=mcmc_for(steps, cap), held_out_cameras=[],
                       eval_every=0, checkpoint_every=checkpoint_every, backend="torch",
                       lr=LearningRates(**lr), **kw)


@dataclass
class MethodResult:
    name: str
    curve: list[dict]            # step, wall_s, cpu_s, psnr, ssim (step 0 = the initialisation)
    gaussians: int
    init_gaussians: int
    steps: int
    grids: dict[str, dict] = field(default_factory=dict)   # camera -> learned mean E, B

    @property
    def final(self) -> dict:
        return self.curve[-1]


def run_method(name: str, scene: BenchScene, s: Settings, *, with_curve: bool) -> MethodResult:
    """Train ``name`` (see the module doc) and evaluate it; ``with_curve``: also at
    ``s.snapshots`` points along the run and at its initialisation."""
    train_views = [v for v in scene.data.views if v.camera_id not in scene.held_out]
    held_views = [v for v in scene.data.views if v.camera_id in scene.held_out]
    fit = dict(fit_steps=s.eval_fit_steps)
    n_frames = s.frames
    cap = sum(len(p.xyz) for p in scene.dense)
    model = Poly4DGSConfig.paper(sh_degree=s.sh_degree)
    extra: dict = {}
    points = scene.dense
    if name == "rotor4d":
        model = Poly4DGSConfig.rotor4d(sh_degree=s.sh_degree)
    elif name == "no_black":
        extra["optimise_black_level"] = False
    elif name == "no_exposure":
        extra["optimise_exposure"] = False
    elif name == "sparse":
        points = subsample_points(scene.dense, s.sparse_fraction, seed=s.seed)
    elif name == "linear_storage":
        model = model.model_copy(update={"colour_space": "linear"})
    elif name not in ("full", "per_frame"):
        raise ValueError(name)

    if name == "per_frame":
        return _run_per_frame(scene, s, train_views, held_views, with_curve=with_curve)

    every = s.steps // s.snapshots if with_curve else 0
    cfg = base_config(s, model=model, steps=s.steps, cap=cap, checkpoint_every=every, **extra)
    data = SegmentData(scene.frames, train_views)
    init = init_model(points, cfg, frame_interval_s=1.0 / scene.fps)
    curve = []
    if with_curve:
        p, q = evaluate_views(lambda t: init, held_views, **fit)
        curve.append(dict(step=0, wall_s=0.0, cpu_s=0.0, psnr=p, ssim=q))
    log, final, grids = train_with_snapshots(data, points, cfg, seed=s.seed)
    for snap in log.snapshots:
        p, q = evaluate_views(lambda t, m=snap.model: m, held_views, **fit)
        curve.append(dict(step=snap.step, wall_s=snap.wall_s, cpu_s=snap.cpu_s, psnr=p, ssim=q))
        print(f"  {name:15s} step {snap.step:5d}  wall {snap.wall_s:7.1f} s  cpu "
              f"{snap.cpu_s:7.1f} s  PSNR {p:6.2f}  SSIM {q:.4f}  N {len(snap.model)}", flush=True)
    learned = {c: {"exposure": float(grids.exposure[i].mean()),
                   "black": float(grids.black[i].mean())} for i, c in enumerate(grids.camera_ids)}
    return MethodResult(name, curve, len(final), len(init), s.steps, learned)


def _run_per_frame(scene: BenchScene, s: Settings, train_views, held_views, *,
                   with_curve: bool) -> MethodResult:
    """One static model per frame, S / N steps each (the same total step budget); the curve point
    k sums every frame's time up to its k-th snapshot and evaluates all frames' models together."""
    steps = max(1, s.steps // s.frames)
    every = steps // s.snapshots if with_curve else 0
    model = Poly4DGSConfig.static(sh_degree=s.sh_degree)
    logs: dict[float, RunLog] = {}
    inits: dict[float, Poly4DGS] = {}
    finals: dict[float, Poly4DGS] = {}
    for i, f in enumerate(range(*scene.frames)):
        pts = [scene.dense[i]]
        cfg = base_config(s, model=model, steps=steps, cap=len(pts[0].xyz),
                          checkpoint_every=every)
        data = SegmentData((f, f + 1), [v for v in train_views if v.frame == f])
        t = pts[0].time
        inits[t] = init_model(pts, cfg, frame_interval_s=1.0 / scene.fps)
        logs[t], finals[t], _ = train_with_snapshots(data, pts, cfg, seed=s.seed + i)
    fit = dict(fit_steps=s.eval_fit_steps)
    curve = []
    if with_curve:
        p, q = evaluate_views(lambda t: inits[t], held_views, **fit)
        curve.append(dict(step=0, wall_s=0.0, cpu_s=0.0, psnr=p, ssim=q))
    n_snap = min(len(lg.snapshots) for lg in logs.values())
    for k in range(n_snap):
        snaps = {t: lg.snapshots[k] for t, lg in logs.items()}
        p, q = evaluate_views(lambda t: snaps[t].model, held_views, **fit)
        wall = sum(sn.wall_s for sn in snaps.values())
        cpu = sum(sn.cpu_s for sn in snaps.values())
        step = sum(sn.step for sn in snaps.values())
        curve.append(dict(step=step, wall_s=wall, cpu_s=cpu, psnr=p, ssim=q))
        print(f"  {'per_frame':15s} step {step:5d}  wall {wall:7.1f} s  cpu {cpu:7.1f} s  "
              f"PSNR {p:6.2f}  SSIM {q:.4f}", flush=True)
    return MethodResult("per_frame", curve, sum(len(m) for m in finals.values()),
                        sum(len(m) for m in inits.values()), steps * s.frames)


# ------------------------------------------------------------------------------------- reports

def psnr_at_budgets(curve: list[dict], budgets: list[float], key: str) -> list[float | None]:
    """Best PSNR among the snapshots reached within each time budget (None: none yet)."""
    out = []
    for b in budgets:
        ok = [c["psnr"] for c in curve if c[key] <= b + 1e-9]
        out.append(max(ok) if ok else None)
    return out


def print_tables(results: dict[str, MethodResult], s: Settings) -> str:
    lines = []
    lines.append("Error against training time (held-out PSNR dB / SSIM at each snapshot)")
    lines.append("| method | step | wall s | CPU s | PSNR | SSIM |")
    lines.append("|---|---|---|---|---|---|")
    for name in METHODS:
        if name in results and len(results[name].curve) > 1:
            for c in results[name].curve:
                lines.append(f"| {name} | {c['step']} | {c['wall_s']:.1f} | {c['cpu_s']:.1f} | "
                             f"{c['psnr']:.2f} | {c['ssim']:.4f} |")
    curves = [results[n] for n in METHODS if n in results and len(results[n].curve) > 1]
    if curves:
        longest = max(r.final["wall_s"] for r in curves)
        budgets = [round(longest * f) for f in (0.25, 0.5, 0.75, 1.0)]
        lines.append("")
        lines.append("Best held-out PSNR reached within a wall-time budget")
        lines.append("| method | " + " | ".join(f"<= {b} s" for b in budgets) + " |")
        lines.append("|---|" + "---|" * len(budgets))
        for r in curves:
            vals = psnr_at_budgets(r.curve, budgets, "wall_s")
            lines.append(f"| {r.name} | " + " | ".join("—" if v is None else f"{v:.2f}"
                                                      for v in vals) + " |")
    lines.append("")
    lines.append(f"Table 1 on the synthetic capture ({s.frames} frames, {s.steps} steps)")
    lines.append("| method | PSNR | SSIM | ΔPSNR vs full | paper PSNR | paper ΔPSNR | "
                 "Gaussians (init → end) | train wall s | train CPU s |")
    lines.append("|---|---|---|---|---|---|---|---|---|")
    full = results.get("full")
    for name in METHODS:
        if name not in results:
            continue
        r = results[name]
        f = r.final
        d = f"{f['psnr'] - full.final['psnr']:+.2f}" if full and name != "full" else "—"
        if name in PAPER:
            pp = f"{PAPER[name][0]:.2f}"
            pd = "—" if name == "full" else f"{PAPER[name][0] - PAPER['full'][0]:+.2f}"
        elif name == "linear_storage":
            pp, pd = "—", "≈ −5"
        else:
            pp = pd = "—"
        lines.append(f"| {LABELS[name]} | {f['psnr']:.2f} | {f['ssim']:.4f} | {d} | {pp} | {pd} | "
                     f"{r.init_gaussians} → {r.gaussians} | {f['wall_s']:.0f} | "
                     f"{f['cpu_s']:.0f} |")
    text = "\n".join(lines)
    print(text)
    return text


def grid_table(results: dict[str, MethodResult], scene: BenchScene) -> str:
    """What the training cameras' grids learned against the synthetic camera's truth: relative
    gain (gain × mean channel gain, over the training cameras' geometric mean) and black offset.
    The model's brightness is arbitrary, so E can only match the gains up to one common factor."""
    rows = [r for r in results.values() if r.grids]
    if not rows:
        return ""
    cams = scene.train_cameras
    g = {c: scene.photometric[c]["gain"] * float(np.mean(scene.photometric[c]["channel_gain"]))
         for c in cams}
    gm = math.exp(np.mean([math.log(v) for v in g.values()]))
    shown = rows[:1]
    lines = ["Learned grids (mean over cells and channels) against the truth",
             "| camera | role | true rel. gain | true black | glare | "
             + " | ".join(f"E {r.name} | B {r.name}" for r in shown) + " |",
             "|---|---|---|---|---|" + "---|---|" * len(shown)]
    for c in cams:
        ph = scene.photometric[c]
        cells = " | ".join(f"{r.grids[c]['exposure']:.3f} | {r.grids[c]['black']:+.4f}"
                           for r in shown)
        lines.append(f"| {c} | {ph['role']} | {g[c] / gm:.3f} | "
                     f"{float(np.mean(ph['black_offset'])):.4f} | {ph['glare_fraction']:.3f} | "
                     f"{cells} |")
    lines.append("")
    lines.append("slope of log E against log(true gain) over the training cameras "
                 "(1: E absorbs the gains, 0: E does not move); E and B ranges:")
    for r in rows:
        x = np.log([g[c] for c in cams])
        y = np.log([max(r.grids[c]["exposure"], 1e-6) for c in cams])
        slope = float(np.polyfit(x, y, 1)[0])
        es = [r.grids[c]["exposure"] for c in cams]
        bs = [r.grids[c]["black"] for c in cams]
        lines.append(f"  {r.name:15s} slope {slope:+.3f}  E {min(es):.3f}..{max(es):.3f}  "
                     f"B {min(bs):+.4f}..{max(bs):+.4f}")
    return "\n".join(lines)


def plot(results: dict[str, MethodResult], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    styles = {"full": ("C0", "o-"), "rotor4d": ("C1", "s-"), "per_frame": ("C2", "^-"),
              "linear_storage": ("C3", "D--")}
    for ax, key, xlabel in ((axes[0], "wall_s", "training wall-clock time (s)"),
                            (axes[1], "cpu_s", "training CPU time (s, one thread)")):
        for name in METHODS:
            if name not in results or len(results[name].curve) < 2:
                continue
            c = results[name].curve
            colour, style = styles.get(name, (None, ".--"))
            ax.plot([p[key] for p in c], [p["psnr"] for p in c], style, color=colour,
                    label=LABELS[name])
        for name, marker in (("no_black", "x"), ("no_exposure", "+"), ("sparse", "v"),
                             ("linear_storage", "D"), ("full", "o"), ("rotor4d", "s"),
                             ("per_frame", "^")):
            if name in results and len(results[name].curve) == 1:
                f = results[name].final
                ax.plot([f[key]], [f["psnr"]], marker, color="0.3", markersize=7,
                        label=LABELS[name] + " (end)")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("held-out PSNR (dB, sRGB display)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------- main

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run (< 3 min), tiny settings")
    ap.add_argument("--frames", type=int)
    ap.add_argument("--steps", type=int, help="optimiser steps per run (per-frame: split)")
    ap.add_argument("--downsample", type=int, help="image downsampling factor (320x180 / d)")
    ap.add_argument("--points-per-frame", type=int)
    ap.add_argument("--snapshots", type=int, help="evaluation points along each curve")
    ap.add_argument("--lr-exposure", type=float, help="exposure-grid learning rate "
                    "(default: the library's)")
    ap.add_argument("--lr-black", type=float, help="black-level-grid learning rate "
                    "(default: the library's)")
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=METHODS)
    ap.add_argument("--curves", nargs="+", choices=METHODS, default=list(CURVE_METHODS),
                    help="methods evaluated along the run (the others only at the end)")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    ap.add_argument("--capture", type=Path, help="reuse/keep the synthetic capture here")
    ap.add_argument("--json", type=Path, help="write every number here")
    ap.add_argument("--plot", type=Path, help="PSNR-vs-time PNG (default: none with --quick, "
                    "docs/img/poly4dgs_error_vs_time.png otherwise)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    s = Settings.quick() if args.quick else Settings.full()
    over = {k: getattr(args, k) for k in ("frames", "steps", "downsample", "points_per_frame",
                                          "snapshots", "lr_exposure", "lr_black")
            if getattr(args, k) is not None}
    s = Settings(**{**s.__dict__, **over})
    t_all = time.perf_counter()
    print(f"settings: {s}  threads={torch.get_num_threads()}  load average "
          f"{os.getloadavg()[0]:.2f}", flush=True)

    with tempfile.TemporaryDirectory(prefix="bench-poly4dgs-") as tmp:
        cap_dir = args.capture or Path(tmp) / "capture"
        t0 = time.perf_counter()
        if not (cap_dir / "capture.json").exists():
            synthesize_capture(cap_dir, rig="demo_scene", seed=0, frames=s.frames,
                               write_depth=True)
        t_synth = time.perf_counter() - t0
        t0 = time.perf_counter()
        scene = load_scene(cap_dir, frames=(0, s.frames), held_out=HELD_OUT,
                           downsample=s.downsample, points_per_frame=s.points_per_frame,
                           seed=s.seed)
        t_load = time.perf_counter() - t0
    v0 = scene.data.views[0]
    print(f"capture: {t_synth:.1f} s to synthesize, {t_load:.1f} s to read; "
          f"{len(scene.train_cameras)} training + {len(scene.held_out)} held-out cameras × "
          f"{s.frames} frames at {v0.camera.width}x{v0.camera.height} (and portrait); "
          f"{sum(len(p.xyz) for p in scene.dense)} dense points", flush=True)

    results: dict[str, MethodResult] = {}
    loads = [os.getloadavg()[0]]
    for name in args.methods:
        t0 = time.perf_counter()
        print(f"{name}:", flush=True)
        results[name] = run_method(name, scene, s, with_curve=name in args.curves)
        loads.append(os.getloadavg()[0])
        print(f"  ({time.perf_counter() - t0:.0f} s with evaluation)", flush=True)
    total = time.perf_counter() - t_all
    text = print_tables(results, s) + "\n\n" + grid_table(results, scene)
    print(text[text.index("Learned grids"):])
    print(f"\ntotal {total:.0f} s; load average (1 min) sampled between runs: "
          f"{min(loads):.2f}-{max(loads):.2f}")

    plot_path = args.plot or (None if args.quick else Path("docs/img/poly4dgs_error_vs_time.png"))
    if plot_path is not None:
        plot(results, plot_path, f"Poly4DGS on synthetic demo_scene: {s.frames} frames, "
             f"{v0.camera.width}x{v0.camera.height}, {s.steps} steps, held-out "
             f"{'+'.join(HELD_OUT)}; 1 thread, shared 2-core Xeon")
        print(f"plot: {plot_path}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({
            "settings": s.__dict__, "threads": torch.get_num_threads(),
            "machine": {"cpu": platform.processor() or platform.machine(),
                        "cpus": os.cpu_count(), "load_avg_1min": loads},
            "total_s": total, "capture_s": t_synth,
            "results": {n: {"curve": r.curve, "gaussians": r.gaussians,
                            "init_gaussians": r.init_gaussians, "steps": r.steps,
                            "grids": r.grids}
                        for n, r in results.items()},
            "tables": text}, indent=1))
    if not all(math.isfinite(r.final["psnr"]) for r in results.values()):
        print("non-finite PSNR", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
