"""The calibration's compiled CPU kernels against the torch code they replace: time and difference.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python bench/bench_calibration_kernels.py [--anchors 20000]

Why: step 5 of a static calibration (the guided patch matching and its bundle adjustments) was
most of a capture's calibration without a scan (the lego capture's, the test suite's longest
fixture). Two kernels replace its hot loops (``volcap_core/calibration/guided_numba.py``,
``volcap_core/calibration/bundle_numba.py``). This times, on one thread each:

1. the guided search (:func:`volcap_core.calibration.guided._match_patches`) of ``--anchors``
   templates (9×9, sheared as a plane seen from another camera) in a textured 320×180 log-luminance
   image, through the compiled scores and through the torch code; prints seconds per 1 000 anchors,
   the largest match difference (px) and how many acceptances differ;
2. one bundle adjustment (:func:`volcap_core.calibration.bundle.bundle_adjust`) of a rig like the
   lego capture's step 5: ``--cameras`` on a ring around ``--points`` points, each point seen by
   a tenth of them (~58 000 observations at the defaults, the lego capture's count), 0.1 px of noise, through both
   paths; prints seconds and the largest pose difference (the kernel's design: none).

Figures: ``docs/benchmarks.md`` ("Calibration's step 5, compiled").
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from volcap_core.calibration import bundle, guided  # noqa: E402
from volcap_core.calibration.bundle import BundleOptions, bundle_adjust  # noqa: E402
from volcap_core.calibration.geometry import look_at_rotation, pose_matrix, so3_exp  # noqa: E402


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def guided_search(n: int, seed: int = 0) -> dict:
    """Both paths of the patch search on ``n`` synthetic templates (module docstring, 1)."""
    import cv2

    rng = np.random.default_rng(seed)
    img = torch.as_tensor(cv2.GaussianBlur(rng.normal(size=(180, 320)).astype(np.float32), (0, 0), 1.2))
    grid = np.arange(-4, 5)
    offsets = np.stack(np.meshgrid(grid, grid, indexing="xy"), -1).reshape(-1, 2) @ np.array([[1.06, 0.12],
                                                                                               [-0.05, 0.94]]).T
    warped = rng.uniform([8, 8], [312, 172], (n, 2))[:, None] + offsets[None]
    template = guided._sample(img, torch.as_tensor(warped + rng.uniform(-2.5, 2.5, (n, 1, 2))))
    options = guided.GuidedMatchOptions()
    guided._match_patches(img, template[:64], warped[:64], options)          # compile outside the clock
    (ours, ok), t_ours = _timed(lambda: guided._match_patches(img, template, warped, options))
    compiled = guided._compiled_scores
    guided._compiled_scores = lambda: None
    try:
        (ref, ref_ok), t_ref = _timed(lambda: guided._match_patches(img, template, warped, options))
    finally:
        guided._compiled_scores = compiled
    both = ok & ref_ok
    return {"anchors": n, "compiled_s_per_1000": 1000 * t_ours / n, "torch_s_per_1000": 1000 * t_ref / n,
            "max_match_diff_px": float(np.abs(ours - ref)[both].max()), "acceptance_differs": int((ok != ref_ok).sum()),
            "accepted": int(ok.sum())}


def ring_adjustment(cameras: int, points: int, seed: int = 0) -> dict:
    """Both paths of one bundle adjustment of a ring rig (module docstring, 2)."""
    rng = np.random.default_rng(seed)
    X = rng.normal(0, 0.4, (points, 3))
    poses, start = [], []
    for a in np.linspace(0, 2 * np.pi, cameras, endpoint=False):
        c = np.array([4 * np.cos(a), 4 * np.sin(a), 1.0 + 0.5 * np.sin(3 * a)])
        R = look_at_rotation(c, (0.0, 0.0, 0.0))
        poses.append(pose_matrix(R, -R @ c))
        Rs = so3_exp(rng.normal(0, 0.002, 3)) @ R
        cs = c + rng.normal(0, 0.01, 3)
        start.append(pose_matrix(Rs, -Rs @ cs))
    f, pp = 300.0, np.array([149.5, 149.5])
    oc, op, uv = [], [], []
    for i, W in enumerate(poses):
        p = X @ W[:3, :3].T + W[:3, 3]
        x = p[:, :2] / p[:, 2:] * f + pp
        facing = (X - X.mean(0)) @ (-W[:3, :3].T @ W[:3, 3]) > -0.05      # a point is seen from its side
        vis = np.flatnonzero(facing & (x[:, 0] > 0) & (x[:, 0] < 299) & (x[:, 1] > 0) & (x[:, 1] < 299))
        vis = vis[rng.random(len(vis)) < 0.18]
        oc.append(np.full(len(vis), i))
        op.append(vis)
        uv.append(x[vis] + rng.normal(0, 0.1, (len(vis), 2)))
    oc, op, uv = map(np.concatenate, (oc, op, uv))
    mounts = np.stack([-W[:3, :3].T @ W[:3, 3] for W in poses]) + rng.normal(0, 0.02, (cameras, 3))

    def run():
        return bundle_adjust(np.stack(start), np.full(cameras, f), np.tile(pp, (cameras, 1)),
                             X + rng.normal(0, 0.01, X.shape), oc, op, uv, focal_prior=np.full(cameras, f),
                             centre_prior=mounts, options=BundleOptions(pixel_sigma=0.1, focal_sigma_rel=0.03,
                                                                        centre_sigma_m=0.3, principal_sigma_px=2.0))

    state = rng.bit_generator.state
    ours, t_ours = _timed(run)
    compiled = bundle._compiled_normal_equations
    bundle._compiled_normal_equations = lambda: None
    try:
        rng.bit_generator.state = state
        ref, t_ref = _timed(run)
    finally:
        bundle._compiled_normal_equations = compiled
    return {"cameras": cameras, "points": points, "observations": len(oc), "compiled_s": t_ours, "torch_s": t_ref,
            "max_pose_diff": float(np.abs(ours.world_to_camera - ref.world_to_camera).max()),
            "rounds": len(ours.stats["cost_per_round"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--anchors", type=int, default=20_000)
    ap.add_argument("--cameras", type=int, default=40)
    ap.add_argument("--points", type=int, default=16_000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    g = guided_search(args.anchors)
    print(f"guided search, {g['anchors']} anchors ({g['accepted']} accepted): compiled "
          f"{g['compiled_s_per_1000']:.3f} s / 1000, torch {g['torch_s_per_1000']:.3f} s / 1000 "
          f"(x{g['torch_s_per_1000'] / g['compiled_s_per_1000']:.1f}); matches differ by at most "
          f"{g['max_match_diff_px']:.2e} px, acceptance differs for {g['acceptance_differs']}")
    b = ring_adjustment(args.cameras, args.points)
    print(f"bundle adjustment, {b['cameras']} cameras, {b['points']} points, {b['observations']} observations, "
          f"{b['rounds']} rounds: compiled {b['compiled_s']:.1f} s, torch {b['torch_s']:.1f} s "
          f"(x{b['torch_s'] / b['compiled_s']:.1f}); poses differ by at most {b['max_pose_diff']:.1e}")


if __name__ == "__main__":
    main()
