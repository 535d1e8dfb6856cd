"""Wall time of a real CPU training run: the first N steps of the demo segment.

    python bench/gpu_zoom_curve.py --prepare P --store STORE --steps 550 --gaussians-per-frame 10000
    OMP_NUM_THREADS=1 python bench/bench_train_time.py P --steps 150 [--repeat 2]

Why: a step's cost on a synthetic ball (``bench_poly4dgs_step.py``) is not a training run's. This
runs :func:`volcap_core.splat.train.train_segment` as the train-segment task does (inside
``deterministic_torch``, backend ``"auto"``) on a folder written by ``gpu_zoom_curve.py --prepare``
(the demo segment: 12 cameras at 320×180, its initial points, the preset at the folder's budget,
the demo preset's 820-step schedule cut to its first ``--steps``), and prints per run the training
wall time (initialisation included), the mean loss over each third of the steps, the held-out PSNR
the trainer reports at the end, and the trained model's digest: two runs of one tree give the same digest, so
a change that should keep the bits shows it, and one that should not shows by how much the loss
moves. Measured figures: ``docs/benchmarks.md`` ("Rasterizer").
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gpu_zoom_curve import Prepared  # noqa: E402

from volcap_core.checkpoint import deterministic_torch  # noqa: E402
from volcap_core.splat.model import save_model  # noqa: E402
from volcap_core.splat.train import train_segment  # noqa: E402


def run_once(prep: Prepared, steps: int) -> dict:
    """One training of the first ``steps`` steps; its wall time, loss thirds, PSNR and digest."""
    # eval_every 0: the trainer evaluates once, at the end (history[-1])
    config = prep.config(820, evals=1).model_copy(update={"steps": steps, "checkpoint_every": 0,
                                                          "eval_every": 0})
    losses: list[float] = []
    with deterministic_torch("cpu"):
        t = time.perf_counter()
        result = train_segment(prep.data, prep.init, config, seed=int(prep.meta["seed"]),
                               device=torch.device("cpu"),
                               progress=lambda step, total, info: losses.append(info["loss"]))
        wall = time.perf_counter() - t
    third = max(1, len(losses) // 3)
    return {"wall_s": wall, "loss_thirds": [sum(losses[i:i + third]) / len(losses[i:i + third])
                                            for i in range(0, 3 * third, third)],
            "held_out_psnr": result.history[-1].psnr if result.history else float("nan"),
            "digest": hashlib.sha256(save_model(result.model)).hexdigest()[:16]}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("prepared", type=Path, help="a folder written by gpu_zoom_curve.py --prepare")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args(argv)
    prep = Prepared(args.prepared)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} torch thread(s) outside training; "
          f"{args.steps} steps of {args.prepared}", flush=True)
    for i in range(args.repeat):
        r = run_once(prep, args.steps)
        thirds = " / ".join(f"{x:.4f}" for x in r["loss_thirds"])
        print(f"run {i + 1}: {r['wall_s']:.1f} s, loss by thirds {thirds}, held-out PSNR "
              f"{r['held_out_psnr']:.3f} dB, model digest {r['digest']}", flush=True)


if __name__ == "__main__":
    main()
