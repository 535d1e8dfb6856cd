"""Synthetic-capture scene for the Poly4DGS benchmarks (``bench/bench_poly4dgs.py``).

A ``demo_scene`` capture from :func:`volcap_core.synth.synthesize_capture` (per-camera gain, black
offsets, vignetting, veiling glare on the zoom cameras) read back as a reconstruction would see it:

* images: the linear EXRs under ``frames/`` via :func:`volcap_core.imageio.read_image`, mapped to
  take indices with each camera's ``take_offset`` (pre-roll cameras' files start earlier), and
  optionally box-downsampled (``cv2.INTER_AREA``) by an integer factor;
* cameras: ``ground_truth/cameras.json`` (OpenCV: pixel centres at integer coordinates) converted
  to :class:`volcap_core.splat.camera.Camera` (pixel centres at +0.5, so ``cx + 0.5``);
* initial points: the ground-truth depth maps (``ground_truth/depth``) of the *training* cameras
  back-projected at every frame with the image colours ("dense"), or a small random subset of
  them ("sparse", the paper's "w/o dense points" ablation).

Ground truth is used only where a real capture would have calibration and a dense multi-view
stereo cloud; the held-out cameras' depth is never used.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from volcap_core.imageio import read_image
from volcap_core.splat.camera import Camera
from volcap_core.splat.train import PointsAtTime, SegmentData, View
from volcap_core.synth import read_exr

__all__ = ["BenchScene", "load_scene", "subsample_points"]


@dataclass
class BenchScene:
    data: SegmentData                 # every camera (training and held out), every frame
    dense: list[PointsAtTime]         # per frame, back-projected training-camera depth
    fps: float
    train_cameras: list[str]
    held_out: list[str]
    frames: tuple[int, int]
    photometric: dict[str, dict]      # camera -> cameras.json "photometric" plus its "role"


def _camera(rec: dict, fr: dict, downsample: int) -> Camera:
    K = np.array([[fr["fx"], 0.0, fr["cx"] + 0.5], [0.0, fr["fy"], fr["cy"] + 0.5], [0, 0, 1]])
    cam = Camera(K=K, world_to_camera=np.asarray(fr["world_to_camera"], np.float64),
                 width=rec["width"], height=rec["height"], near=0.05, far=100.0)
    return cam.scaled(1.0 / downsample) if downsample != 1 else cam


def _backproject(depth: np.ndarray, rgb: np.ndarray, fr: dict) -> tuple[np.ndarray, np.ndarray]:
    """World points and colours of every pixel with a finite depth (OpenCV pixel centres)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = depth.astype(np.float64)
    ok = np.isfinite(z) & (z > 0) & (z < 1e3)
    x = (u - fr["cx"]) / fr["fx"] * z
    y = (v - fr["cy"]) / fr["fy"] * z
    pc = np.stack([x[ok], y[ok], z[ok]], -1)
    w2c = np.asarray(fr["world_to_camera"], np.float64)
    R, t = w2c[:3, :3], w2c[:3, 3]
    return (pc - t) @ R, rgb[ok].astype(np.float64)


def load_scene(capture_dir: str | Path, *, frames: tuple[int, int], held_out: list[str],
               downsample: int = 1, points_per_frame: int = 30_000,
               seed: int = 0) -> BenchScene:
    """Read a synthetic capture folder into a :class:`BenchScene` (images loaded eagerly)."""
    root = Path(capture_dir)
    gt = json.loads((root / "ground_truth" / "cameras.json").read_text())
    fps = float(gt["fps"])
    rng = np.random.default_rng(seed)
    a, b = frames
    views: list[View] = []
    dense: list[PointsAtTime] = []
    per_frame_xyz: dict[int, list[np.ndarray]] = {f: [] for f in range(a, b)}
    per_frame_rgb: dict[int, list[np.ndarray]] = {f: [] for f in range(a, b)}
    cam_ids = sorted(gt["cameras"])
    for cid in cam_ids:
        rec = gt["cameras"][cid]
        for f in range(a, b):
            fr = rec["frames"][f]
            assert fr["take_index"] == f
            img, _ = read_image(root / "frames" / cid / f"{fr['frame']:06d}.exr")
            img = img[..., :3]
            if cid not in held_out:
                depth = read_exr(root / "ground_truth" / "depth" / cid / f"{f:06d}.exr")
                xyz, rgb = _backproject(depth, img, fr)
                per_frame_xyz[f].append(xyz)
                per_frame_rgb[f].append(rgb)
            if downsample != 1:
                h, w = img.shape[:2]
                img = cv2.resize(img, (round(w / downsample), round(h / downsample)),
                                 interpolation=cv2.INTER_AREA)
            cam = _camera(rec, fr, downsample)
            views.append(View(cid, f, f / fps, cam, torch.from_numpy(np.ascontiguousarray(img))))
    for f in range(a, b):
        xyz = np.concatenate(per_frame_xyz[f])
        rgb = np.concatenate(per_frame_rgb[f])
        keep = rng.choice(len(xyz), size=min(points_per_frame, len(xyz)), replace=False)
        dense.append(PointsAtTime(time=f / fps, xyz=torch.from_numpy(xyz[keep]).float(),
                                  rgb=torch.from_numpy(rgb[keep]).float().clamp(min=0)))
    train = [c for c in cam_ids if c not in held_out]
    photometric = {c: {**gt["cameras"][c]["photometric"], "role": gt["cameras"][c]["role"]}
                   for c in cam_ids}
    return BenchScene(SegmentData((a, b), views), dense, fps, train, list(held_out), (a, b),
                      photometric)


def subsample_points(points: list[PointsAtTime], fraction: float, seed: int = 0
                     ) -> list[PointsAtTime]:
    """A random ``fraction`` of each frame's points (the sparse initialisation)."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for p in points:
        n = max(8, round(fraction * len(p.xyz)))
        keep = torch.randperm(len(p.xyz), generator=g)[:n].sort().values
        out.append(PointsAtTime(p.time, p.xyz[keep], p.rgb[keep]))
    return out
