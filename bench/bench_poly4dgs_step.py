"""Time per optimisation step of Poly4DGS against a static 3DGS with the same number of Gaussians.

    python bench/bench_poly4dgs_step.py --device cpu     # 5000 Gaussians, 128², torch back-end
    python bench/bench_poly4dgs_step.py --device cpu --backend numba --gaussians 60000 --size 240
    python bench/bench_poly4dgs_step.py --device cuda --json out.json  # 100k and 1M, 1024², gsplat
    python bench/bench_poly4dgs_step.py --device cuda --frames 1 8     # and a layout over 8 frames

Why: the paper picks the degrees (n_μ, n_q, n_s, n_o) = (2, 1, 0, 2) for "a slight improvement in
PSNR (+0.2dB) without introducing visible overhead". A Poly4DGS step does more work than a 3DGS step
on the same Gaussians. It evaluates the polynomials at t and the temporal opacity envelope, and it
carries more floats per Gaussian through backward and Adam: 72 instead of 59 at SH degree 3
(``means_t``, ``quats_t``, ``log_lambdas``, ``t0``). This bench measures that cost per step with
the project's own code. The rasterizer and the loss are the same for both models.

What one step is: the step of :func:`volcap_core.splat.train.train_segment`, through the very
functions it calls: :func:`~volcap_core.splat.train.learning_rates`, grads cleared,
:func:`~volcap_core.splat.train.step_loss` (evaluate at t, render — ``"gsplat"`` on CUDA, ``"torch"``
on CPU — the camera's grids, L1 + SSIM, the grid and MCMC regularisers), the non-finite-loss check,
backward, and :func:`~volcap_core.splat.train.optimiser_step` (Adam on the model and the grids,
MCMC's noise). All settings are ``TrainConfig()``'s defaults. Left out are the parts of a training
step that do not depend on the model: loading the view (the target is one fixed image already on
the device), plus progress, evaluation and checkpoints; relocation and growth run every 100 steps
only, past the timed steps.

Scene: :func:`bench_rasterizer.scene`, anisotropic Gaussians in a 1.2 m ball with σ 4-24 mm,
opacity 0.05-0.95 and SH degree 3 coefficients, cut to ``--sh-degree``. The camera is
``--distance`` m from the centre with a 50° field of view and ``--size``² pixels. Both models get
the same means, rotations, scales, opacities and SH. The Poly4DGS model also gets the initial
lifespans of :func:`~volcap_core.splat.train.init_model`. A share of ``init_static_share`` of the
Gaussians is static: it lives for ever (log λ = ``STATIC_LOG_LAMBDA``), has no motion and has t0
at the middle of the segment. The rest move. Their t0 lies on a frame of the segment, spread evenly
over ``F`` frames at ``--fps``, with temporal σ = ``init_lifespan_frames`` frame intervals and
random normal polynomial coefficients (standard deviation 0.3 m/s^i for the means, 0.5 /s^i
for the quaternions).
``--frames 1`` is the default. With it, every Gaussian is alive at the timed t, so both models
rasterize the same N Gaussians and the difference is the cost of the representation alone. With
``--frames F`` > 1 (a segment of F frames of N Gaussians), the timed steps cycle t over the
segment's frames as training draws views. Then only the moving Gaussians near t survive
``evaluate``'s opacity cut, and the ``visible`` column gives how many are rasterized (a median).
Scene scale (the means' learning rate and the noise) is 1.1 × the distance: the value for a ring
of cameras at that distance.

Timing: ``--warmup`` steps, then the median of ``--steps`` timed steps. Each step runs between two
``torch.cuda.synchronize`` calls with ``time.perf_counter``. The split into forward (learning
rates, evaluate, render, loss), backward and optimiser (freeze, both Adam steps, noise) comes from
CUDA events recorded between the phases, which add no synchronisation (``perf_counter`` on CPU).
Peak memory is ``torch.cuda.max_memory_allocated`` during the config's steps. It includes the
model, its gradients and Adam's moments, and the memory is reset before each config. The models
run one after the other, each freed before the next. Prints a table and the ratio
Poly4DGS / static per (N, image, F). ``--json`` gets rewritten after every row.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
# this tree's volcap_core (not whichever checkout is installed), and bench_rasterizer beside us
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]

from bench_rasterizer import scene  # noqa: E402

from volcap_core.splat.camera import Camera, look_at  # noqa: E402
from volcap_core.checkpoint import AdamState  # noqa: E402
from volcap_core.splat.grids import ExposureGrids  # noqa: E402
from volcap_core.splat.model import (  # noqa: E402
    Gaussians3D,
    Poly4DGS,
    Poly4DGSConfig,
    evaluate,
)
from volcap_core.splat.render import render, resolve_backend  # noqa: E402
from volcap_core.splat.sh import num_sh_bases  # noqa: E402
from volcap_core.splat.train import (  # noqa: E402
    TrainConfig,
    learning_rates,
    optimiser_step,
    step_loss,
)

#: standard deviation of the random polynomial coefficients of moving Gaussians, per unit s^-i
MEAN_COEFF_STD, QUAT_COEFF_STD, SCALE_COEFF_STD = 0.3, 0.5, 0.3


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def build_model(config: Poly4DGSConfig, n: int, frames: int, fps: float, tc: TrainConfig,
                seed: int = 0) -> tuple[Poly4DGS, list[float]]:
    """The bench scene as a model of ``config`` (on the CPU), and the frame times of its segment.
    Same seed, same geometry and SH, whatever the config (see the module doc)."""
    g3 = scene(n, seed)
    gen = torch.Generator().manual_seed(seed + 1)
    times = torch.arange(frames, dtype=torch.float32) / fps
    moving = torch.rand(n, generator=gen) >= tc.init_static_share
    t0 = torch.where(moving, times[torch.arange(n) % frames], times.mean())
    lifespan = torch.where(moving, torch.tensor(tc.init_lifespan_frames / fps),
                           torch.tensor(math.inf))
    model = Poly4DGS.from_points(config, g3.means, torch.full((n, 3), 0.5), scales=g3.scales,
                                 t0=t0, lifespan_s=lifespan)
    p = model.params
    sh = g3.sh[:, :num_sh_bases(config.sh_degree)]
    p["quats"] = g3.quats.clone()
    p["opacities"] = torch.logit(g3.opacities)
    p["sh0"] = sh[:, :1].clone()
    if "shN" in p:
        p["shN"] = sh[:, 1:].clone()
    for name, std in (("means_t", MEAN_COEFF_STD), ("quats_t", QUAT_COEFF_STD),
                      ("scales_t", SCALE_COEFF_STD)):
        if name in p:
            p[name] = std * torch.randn(p[name].shape, generator=gen) * moving[:, None, None]
    return model, times.tolist()


def _clone_to(g: Gaussians3D, device: torch.device) -> Gaussians3D:
    return Gaussians3D(g.means.to(device), g.quats.to(device), g.scales.to(device),
                       g.opacities.to(device), g.sh.to(device), g.ids.to(device))


class _Clock:
    """Phase boundaries of one step: CUDA events on CUDA (no extra synchronisation), else
    ``perf_counter``; the step's total is ``perf_counter`` between two synchronisations."""

    def __init__(self, device: torch.device):
        self.device = device
        self.cuda = device.type == "cuda"

    def start(self) -> None:
        _sync(self.device)
        self.marks: list = []
        self.t0 = time.perf_counter()
        self.mark()

    def mark(self) -> None:
        if self.cuda:
            ev = torch.cuda.Event(enable_timing=True)
            ev.record()
            self.marks.append(ev)
        else:
            self.marks.append(time.perf_counter())

    def stop(self) -> tuple[float, list[float]]:
        self.mark()
        _sync(self.device)
        total = time.perf_counter() - self.t0
        if self.cuda:
            phases = [a.elapsed_time(b) / 1e3 for a, b in zip(self.marks, self.marks[1:])]
        else:
            phases = [b - a for a, b in zip(self.marks, self.marks[1:])]
        return total, phases


def bench(config: Poly4DGSConfig, label: str, n: int, size: int, frames: int, *, fps: float,
          distance: float, backend: str, device: torch.device, target: torch.Tensor,
          camera: Camera, warmup: int, steps: int, seed: int = 0) -> dict:
    """Median step time of one model config (the training step of the module doc)."""
    tc = TrainConfig(model=config)
    model, times = build_model(config, n, frames, fps, tc, seed)
    model = model.to(device)
    for v in model.params.values():
        v.requires_grad_(True)
    adam = AdamState.zeros_like(model.params)
    grids = ExposureGrids.identity(["cam0"], tc.grid_size, device)
    grid_params = {"exposure": grids.exposure.requires_grad_(True),
                   "black": grids.black.requires_grad_(True)}
    grid_lrs = {"exposure": tc.lr.exposure, "black": tc.lr.black}
    grid_adam = AdamState.zeros_like(grid_params)
    gen = torch.Generator().manual_seed(seed + 2)
    bg = torch.tensor(tc.background, device=device)
    scene_scale = 1.1 * distance
    time_scale = tc.time_scale_s or max(0.5 * (times[-1] - times[0]), 1.0 / fps)
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
    clock = _Clock(device)
    totals, phases, visible = [], [], []
    for i in range(warmup + steps):
        step = i + 1
        t = times[i % len(times)]
        clock.start()
        lrs = learning_rates(tc, step, scene_scale, time_scale, model)
        for p in (*model.params.values(), *grid_params.values()):
            p.grad = None
        loss, _ = step_loss(model, t, camera, target, None, grid_params["exposure"], 0, grid_params["black"], tc,
                            backend=backend, background=bg)
        if not torch.isfinite(loss.detach()):
            raise FloatingPointError(f"{label}: step {step}: loss is {float(loss.detach())}")
        clock.mark()
        loss.backward()
        clock.mark()
        optimiser_step(model, adam, grid_params, grid_lrs, grid_adam, lrs, tc, step, gen, scene_scale=scene_scale)
        total, split = clock.stop()
        if i >= warmup:
            totals.append(total)
            phases.append(split)
            with torch.no_grad():  # outside the timed step
                visible.append(len(evaluate(model, t)))
    peak = torch.cuda.max_memory_allocated(device) if device.type == "cuda" else None
    per_gaussian = sum(math.prod(s) for s in config.param_shapes().values())
    row = {"model": label, "config": config.model_dump(), "n": n, "size": size,
           "frames": frames if config.temporal else None,
           "visible": int(statistics.median(visible)), "floats_per_gaussian": per_gaussian,
           "backend": backend, "device": str(device), "warmup": warmup, "steps": steps,
           "step_s": statistics.median(totals), "step_s_min": min(totals),
           "step_s_all": totals, "peak_bytes": peak}
    for k, name in enumerate(("fwd_s", "bwd_s", "opt_s")):
        row[name] = statistics.median(s[k] for s in phases)
    del model, adam, grids, grid_params, grid_adam, loss
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--gaussians", type=int, nargs="+",
                    help="default 100000 1000000 on CUDA, 5000 on CPU")
    ap.add_argument("--size", type=int,
                    help="image width = height (px); default 1024 on CUDA, 128 on CPU")
    ap.add_argument("--frames", type=int, nargs="+", default=[1],
                    help="segment lengths F of the Poly4DGS layout (module doc); 1: all alive at t")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--distance", type=float, default=3.0, help="camera to scene centre (m)")
    ap.add_argument("--sh-degree", type=int, default=Poly4DGSConfig().sh_degree)
    ap.add_argument("--backend", choices=["gsplat", "torch", "numba"],
                    help="default gsplat on CUDA, torch on CPU")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=20, help="timed steps per config (the median)")
    ap.add_argument("--threads", type=int, help="torch CPU threads (default 1 on CPU)")
    ap.add_argument("--json", type=Path, help="write the rows and ratios here")
    args = ap.parse_args()
    if args.steps < 1 or args.warmup < 0:
        ap.error("need --steps >= 1 and --warmup >= 0")
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    if args.threads or not cuda:
        torch.set_num_threads(args.threads or 1)
    sizes = args.gaussians or ([100_000, 1_000_000] if cuda else [5_000])
    size = args.size or (1024 if cuda else 128)
    # an explicit back-end that cannot run here fails now, with its cause
    backend = resolve_backend(args.backend or ("gsplat" if cuda else "torch"), device).name
    poly = Poly4DGSConfig.paper(sh_degree=args.sh_degree)
    static = Poly4DGSConfig.static(sh_degree=args.sh_degree)
    tc = TrainConfig()
    where = (torch.cuda.get_device_name(device) if cuda
             else f"{platform.machine()}, {torch.get_num_threads()} thread(s)")
    meta = {"torch": torch.__version__, "device": where, "backend": backend,
            "python": platform.python_version(), "distance_m": args.distance, "fps": args.fps,
            "init_static_share": tc.init_static_share,
            "init_lifespan_frames": tc.init_lifespan_frames, "warmup": args.warmup,
            "steps": args.steps}
    print(f"torch {torch.__version__}, {where}, back-end {backend}; median of {args.steps} steps "
          f"after {args.warmup} warm-up; Poly4DGS degrees (n_μ, n_q, n_s, n_o) = "
          f"({poly.mean_degree}, {poly.quat_degree}, {poly.scale_degree}, {poly.opacity_degree}), "
          f"SH {args.sh_degree}, static share {tc.init_static_share}, "
          f"σ_t {tc.init_lifespan_frames} frames at {args.fps:g} fps")
    print(f"{'model':>8} {'F':>3} {'gaussians':>9} {'visible':>9} {'image':>6} {'floats/G':>8} "
          f"{'step ms':>8} {'fwd ms':>7} {'bwd ms':>7} {'opt ms':>7} {'peak MiB':>8}")
    rows, ratios = [], []

    def write() -> None:
        if args.json:
            doc = {"meta": meta, "rows": rows, "ratios": ratios}
            args.json.write_text(json.dumps(doc, indent=1))

    for n in sizes:
        cam = look_at((0, -args.distance, 0), (0, 0, 0), fov_x_deg=50, width=size,
                      height=size).to(device)
        # a fixed target: another cloud of the same kind, seen by the same camera
        with torch.no_grad():
            target = render(_clone_to(scene(n, seed=1), device), cam, backend=backend)["rgb"]
        runs = [("static", static, 1)] + [("poly4dgs", poly, f) for f in args.frames]
        base = None
        for label, config, frames in runs:
            r = bench(config, label, n, size, frames, fps=args.fps, distance=args.distance,
                      backend=backend, device=device, target=target, camera=cam,
                      warmup=args.warmup, steps=args.steps)
            rows.append(r)
            peak = (f"{r['peak_bytes'] / 2**20:>8.0f}" if r["peak_bytes"] is not None
                    else f"{'-':>8}")
            print(f"{label:>8} {frames if config.temporal else '-':>3} {n:>9} {r['visible']:>9} "
                  f"{f'{size}²':>6} {r['floats_per_gaussian']:>8} {r['step_s'] * 1e3:>8.2f} "
                  f"{r['fwd_s'] * 1e3:>7.2f} {r['bwd_s'] * 1e3:>7.2f} "
                  f"{r['opt_s'] * 1e3:>7.2f} {peak}",
                  flush=True)
            if base is None:
                base = r
            else:
                ratios.append({"n": n, "size": size, "frames": frames,
                               "step": r["step_s"] / base["step_s"],
                               "peak": (r["peak_bytes"] / base["peak_bytes"]
                                        if r["peak_bytes"] is not None else None)})
            write()
        del target
    print("Poly4DGS / static per step:")
    for q in ratios:
        mem = f", peak memory x{q['peak']:.3f}" if q["peak"] is not None else ""
        print(f"  {q['n']:>9} Gaussians, {q['size']}², F={q['frames']}: "
              f"time x{q['step']:.3f}{mem}")


if __name__ == "__main__":
    main()
