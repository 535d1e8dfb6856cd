"""Cost of the Gaussian rasterizer back-ends: ns per (pixel, Gaussian) pair, fwd+bwd.

    python bench/bench_rasterizer.py                  # 10k/50k Gaussians x 128²/256², 1 thread, CPU
    python bench/bench_rasterizer.py --threads 2 --tile-sizes 8 16 --repeats 5
    python bench/bench_rasterizer.py --backends numba torch --threads 1 2   # compiled vs PyTorch
    python bench/bench_rasterizer.py --device cuda --backends gsplat torch \
        --gaussians 100000 1000000 --sizes 256 1080 --tile-sizes 16   # a GPU: gsplat beside torch

A pair is a pixel of a tile times a Gaussian binned to that tile (what the rasterizer evaluates
before padding): the cost model that tile-based rasterizers share, so the figure compares with
gsplat's and with the NOTES (60-120 ns per pair on one core). The scene is a random cloud of
anisotropic Gaussians 4 m in front of a 50° camera, sized like a trained capture (σ 0.5-3 px).
Timings are the minimum over repeats (the machine is shared); "cpu ms" is the process's CPU time
for forward + backward (all its threads, spin-waits included), which a loaded machine disturbs
less than the wall time. Prints a table; takes ~1-3 minutes.

The numba back-end (``--backends numba``) composites the same binning with compiled per-pixel loops
that stop where a pixel is opaque, so its ns/pair divides by the same candidate pairs and partly
measures early termination; the untimed first run loads (or, on a new machine, compiles) its
kernels.

On CUDA (``--device cuda``) each back-end runs on the same scene (``torch.cuda.synchronize`` around
the timed calls). gsplat bins Gaussians to 16-px tiles and reports no pair count, so its ns/pair
divides by the pairs our binning counts at tile 16 (the same definition), whatever ``--tile-sizes``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch

from volcap_core.splat.camera import look_at
from volcap_core.splat.model import Gaussians3D
from volcap_core.splat.rasterize import TileStats
from volcap_core.splat.render import render


def scene(n: int, seed: int = 0) -> Gaussians3D:
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    means = d / d.norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=g) ** (1 / 3) * 1.2
    log_s = math.log(0.004) + torch.rand(n, 3, generator=g) * math.log(6.0)
    return Gaussians3D(means=means, quats=torch.randn(n, 4, generator=g), scales=log_s.exp(),
                       opacities=0.05 + 0.9 * torch.rand(n, generator=g),
                       sh=0.3 * torch.randn(n, 16, 3, generator=g), ids=torch.arange(n))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench(n: int, size: int, tile: int, repeats: int, backend: str = "torch",
          device: torch.device = torch.device("cpu"), threads: int | None = None) -> dict:
    cam = look_at((0, -4, 0), (0, 0, 0), fov_x_deg=50, width=size, height=size).to(device)
    g0 = scene(n)
    g0 = Gaussians3D(*(t.to(device) for t in (g0.means, g0.quats, g0.scales, g0.opacities, g0.sh)),
                     ids=g0.ids.to(device))
    fwd, tot, cpu = [], [], []
    stats = TileStats()
    for r in range(repeats + 1):  # first run warms up allocators and caches
        leaves = [t.clone().requires_grad_(True) for t in
                  (g0.means, g0.quats, g0.scales, g0.opacities, g0.sh)]
        g = Gaussians3D(*leaves, ids=g0.ids)
        stats = TileStats()
        _sync(device)
        c0, t0 = time.process_time(), time.perf_counter()
        out = render(g, cam, backend=backend, tile_size=tile, stats=stats)
        _sync(device)
        t1 = time.perf_counter()
        (out["rgb"].sum() + out["alpha"].sum()).backward()
        _sync(device)
        t2, c2 = time.perf_counter(), time.process_time()
        if r:
            fwd.append(t1 - t0)
            tot.append(t2 - t0)
            cpu.append(c2 - c0)
    if backend == "gsplat":  # gsplat's own binning: 16-px tiles, counted by ours (no grad needed)
        tile, stats = 16, TileStats()
        with torch.no_grad():
            render(g0, cam, backend="torch", tile_size=16, stats=stats)
    return {"backend": backend, "device": str(device), "threads": threads, "n": n, "size": size,
            "tile": tile,
            "pairs": stats.pairs, "padded": stats.padded_pairs, "fwd_s": min(fwd), "total_s": min(tot),
            "cpu_s": min(cpu),
            "ns_pair": min(tot) / stats.pairs * 1e9, "ns_pair_fwd": min(fwd) / stats.pairs * 1e9}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, nargs="+", default=[10_000, 50_000])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--tile-sizes", type=int, nargs="+", default=[8])
    ap.add_argument("--threads", type=int, nargs="+", default=[1], help="CPU threads, each in turn")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--backends", nargs="+", choices=["torch", "numba", "gsplat"], default=["torch"])
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args()
    device = torch.device(args.device)
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"torch {torch.__version__}, {where}, min of {args.repeats} runs")
    print(f"{'backend':>7} {'thr':>3} {'gaussians':>9} {'image':>7} {'tile':>4} {'pairs':>10} {'padded':>10} "
          f"{'fwd ms':>8} {'fwd+bwd ms':>10} {'cpu ms':>7} {'ns/pair fwd':>11} {'ns/pair f+b':>11}")
    rows = []
    for threads in args.threads:
        torch.set_num_threads(threads)  # the numba back-end takes torch's thread count at call time
        for n in args.gaussians:
            for size in args.sizes:
                for backend in args.backends:
                    for tile in args.tile_sizes if backend != "gsplat" else [16]:
                        r = bench(n, size, tile, args.repeats, backend, device, threads)
                        rows.append(r)
                        print(f"{backend:>7} {threads:>3} {r['n']:>9} {f'{size}²':>7} {r['tile']:>4} "
                              f"{r['pairs']:>10} {r['padded']:>10} {r['fwd_s'] * 1e3:>8.1f} "
                              f"{r['total_s'] * 1e3:>10.1f} {r['cpu_s'] * 1e3:>7.1f} {r['ns_pair_fwd']:>11.3g} {r['ns_pair']:>11.3g}",
                              flush=True)
                        if args.json:
                            args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
