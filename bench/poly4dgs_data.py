"""Synthetic-capture scene for the Poly4DGS benchmarks (``bench/bench_poly4dgs.py``).

A ``demo_scene`` capture from :func:`volcap_core.synth.synthesize_capture` (per-camera gain, black
offsets, vignetting, veiling glare on the zoom cameras) read back as a reconstruction would see it:

* images: the linear EXRs under ``frames/`` via :func:`volcap_core.imageio.read_image`, mapped to
  take indices with each camera's ``take_offset`` (pre-roll cameras' files start earlier), and
  optionally box-downsampled (``cv2.INTER_AREA``) by an integer factor;
* cameras: ``ground_truth/cameras.json`` (OpenCV: pixel centres at integer coordinates) converted
  to :class:`volcap_core.splat.camera.Camera` (pixel centres at +0.5, so ``cx + 0.5``);
* performer masks: ``ground_truth/masks/<camera>/<take index>.exr``
  (:func:`volcap_core.synth.ground_truth.performer_mask`), area-downsampled like the images and
  attached to every view (``View.mask``): scoring reads them for the performers-only figures;
* the performers' heads: ``ground_truth/scene.json`` (its actors), for the face regions
  (:meth:`BenchScene.head_region`, :func:`volcap_core.synth.ground_truth.face_region`);
* the lidar scan of the empty stage: ``ground_truth/lidar.ply`` (the same bytes as the capture's
  ``lidar.ply``), read with :class:`volcap_core.calibration.lidar.LidarScan`;
* dense points per frame: the ground-truth depth maps (``ground_truth/depth``) of the *training*
  cameras back-projected with the image colours, ``points_per_frame`` of them drawn at random.

:func:`production_points` turns those into the initial points exactly as the reconstruction task
does: it hands them to :func:`volcap_core.reconstruction.segment_points` (as an in-memory
:class:`~volcap_core.pointcloud.PointCloudSequence`) with the scan and the static training
cameras' views at the middle frame (:func:`background_views`, the rule of
``reconstruction.background_views``): every point is classified static or moving (on the scan or
persistent over the segment) and the scan, coloured by those views, is appended as one more static
cloud. :func:`subsample_points` gives the sparse ("w/o dense points") ablation's points.

Ground truth is used only where a real capture would have calibration, a lidar scan and a dense
multi-view stereo cloud; the held-out cameras' depth and images never enter the initial points
(they neither give points nor colour the scan), and their masks are read by scoring only.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from hardware.rig import CameraRole
from volcap_core.imageio.read import read_image
from volcap_core.splat.camera import Camera
from volcap_core.splat.train import PointsAtTime, SegmentData, View
from volcap_core.synth import read_exr
from volcap_core.synth.ground_truth import face_region, performer_mask

__all__ = ["BenchScene", "InitPoints", "background_views", "load_scene", "production_points",
           "subsample_points"]


@dataclass
class BenchScene:
    data: SegmentData                 # every camera (training and held out), every frame
    dense: list[PointsAtTime]         # per frame, training cameras' depth back-projected
    fps: float
    train_cameras: list[str]
    held_out: list[str]
    frames: tuple[int, int]
    photometric: dict[str, dict]      # camera -> cameras.json "photometric" plus its "role"
    scan_ply: bytes | None = None     # the lidar scan of the empty stage (PLY bytes), if any
    scene: dict | None = None         # ground_truth/scene.json (the actors), if any

    @property
    def static_cameras(self) -> list[str]:
        """Cameras that do not track (``CameraRole.tracks`` False), held-out ones included."""
        return [c for c, ph in self.photometric.items() if not CameraRole(ph["role"]).tracks]

    @property
    def roles(self) -> dict[str, str]:
        """Camera id -> ``"static"`` or ``"tracking"``: the roles of the region figures (what
        ``fit_segment`` gives ``score_segment`` from the calibration)."""
        return {c: "tracking" if CameraRole(ph["role"]).tracks else "static"
                for c, ph in self.photometric.items()}

    def head_region(self, view: View) -> np.ndarray | None:
        """``[H, W]`` bool, where the performers' heads are in ``view``
        (:func:`~volcap_core.synth.ground_truth.face_region` without coverage, on the view's own
        camera and time, as ``fit_segment`` hands it to ``score_segment``); None without a
        ``scene.json``."""
        if self.scene is None:
            return None
        cam = view.camera
        return face_region(self.scene, view.time, cam.K.detach().cpu().numpy(),
                           cam.world_to_camera.detach().cpu().numpy(), cam.width, cam.height)


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


def _downsample(img: np.ndarray, downsample: int) -> np.ndarray:
    """Area averaging by an integer factor (``cv2.INTER_AREA``), as a smaller sensor integrates."""
    if downsample == 1:
        return img
    h, w = img.shape[:2]
    return cv2.resize(img, (round(w / downsample), round(h / downsample)),
                      interpolation=cv2.INTER_AREA)


def load_scene(capture_dir: str | Path, *, frames: tuple[int, int], held_out: list[str],
               downsample: int = 1, points_per_frame: int = 30_000,
               seed: int = 0) -> BenchScene:
    """Read a synthetic capture folder into a :class:`BenchScene` (images and performer masks
    loaded eagerly; masks are None where the capture has none)."""
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
            img = _downsample(img, downsample)
            mask_file = root / "ground_truth" / "masks" / cid / f"{f:06d}.exr"
            mask = None
            if mask_file.exists():
                mask = torch.from_numpy(np.ascontiguousarray(
                    _downsample(performer_mask(mask_file.read_bytes()), downsample)))
            cam = _camera(rec, fr, downsample)
            views.append(View(cid, f, f / fps, cam, torch.from_numpy(np.ascontiguousarray(img)),
                              mask))
    for f in range(a, b):
        xyz = np.concatenate(per_frame_xyz[f])
        rgb = np.concatenate(per_frame_rgb[f])
        keep = rng.choice(len(xyz), size=min(points_per_frame, len(xyz)), replace=False)
        dense.append(PointsAtTime(time=f / fps, xyz=torch.from_numpy(xyz[keep]).float(),
                                  rgb=torch.from_numpy(rgb[keep]).float().clamp(min=0)))
    train = [c for c in cam_ids if c not in held_out]
    photometric = {c: {**gt["cameras"][c]["photometric"], "role": gt["cameras"][c]["role"]}
                   for c in cam_ids}
    scan_ply = None
    for candidate in (root / "ground_truth" / "lidar.ply", root / "lidar.ply"):
        if candidate.exists():
            scan_ply = candidate.read_bytes()
            break
    scene_file = root / "ground_truth" / "scene.json"
    scene = json.loads(scene_file.read_text()) if scene_file.exists() else None
    return BenchScene(SegmentData((a, b), views), dense, fps, train, list(held_out), (a, b),
                      photometric, scan_ply, scene)


@dataclass
class InitPoints:
    """The initial points of a segment as production builds them.

    Attributes:
        frames: one :class:`PointsAtTime` per frame, ``static`` set (scan or persistence).
        scan: the lidar scan coloured by the static training cameras at the middle frame, all
            static (None without a scan or without a static training camera).
    """

    frames: list[PointsAtTime]
    scan: PointsAtTime | None

    @property
    def all(self) -> list[PointsAtTime]:
        """What training gets: the frames' clouds, then the coloured scan."""
        return self.frames + ([self.scan] if self.scan is not None else [])

    def summary(self) -> str:
        n = [len(p.xyz) for p in self.frames]
        st = [int(p.static.sum()) for p in self.frames]
        scan = f"{len(self.scan.xyz)} coloured scan points" if self.scan is not None else "no scan"
        share = 100 * sum(st) / max(1, sum(n))
        return (f"{sum(n)} dense points over {len(n)} frames, {share:.0f} % "
                f"static (on the scan or persistent); {scan}")


def background_views(scene: BenchScene) -> list[View]:
    """The static training cameras' views at the segment's middle frame: what colours the scan
    (``volcap_core.reconstruction.background_views``' rule, on the bench's camera roles)."""
    a, b = scene.frames
    mid = a + (b - a) // 2
    static = set(scene.static_cameras) - set(scene.held_out)
    return [v for v in scene.data.views if v.frame == mid and v.camera_id in static]


def production_points(scene: BenchScene) -> InitPoints:
    """The scene's dense points through :func:`volcap_core.reconstruction.segment_points`, the
    function the reconstruction task calls: static/moving classification with the capture's
    lidar scan (``LidarScan.surface_distance``) and persistence, and the scan coloured by
    :func:`background_views` appended as one more static cloud. The per-frame clouds are handed
    over as an in-memory :class:`~volcap_core.pointcloud.PointCloudSequence` (content digests,
    nothing stored)."""
    from volcap_core.digest import digest_bytes
    from volcap_core.pointcloud import (POINTS_MEDIA, PointCloudFrame, PointCloudSequence,
                                        encode_points)
    from volcap_core.reconstruction import segment_points
    from volcap_core.records import ArtifactRef

    a, b = scene.frames
    blobs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    records = []
    for f, p in zip(range(a, b), scene.dense):
        xyz, rgb = p.xyz.numpy(), p.rgb.numpy()
        blob = encode_points(xyz, rgb)
        ref = ArtifactRef(digest=digest_bytes(blob), size=len(blob), media_type=POINTS_MEDIA)
        blobs[ref.digest] = (xyz, rgb)
        records.append(PointCloudFrame(frame=f, time=p.time, count=len(xyz), points=ref))
    nowhere = ArtifactRef(digest=digest_bytes(b"bench: no calibration record"), size=0)
    seq = PointCloudSequence(calibration=nowhere, frames=tuple(records),
                             method="bench: ground-truth depth of the training cameras")
    out = segment_points(seq, (a, b), lambda ref: blobs[ref.digest], static_scan=scene.scan_ply,
                         background=background_views(scene))
    n = b - a
    return InitPoints(out[:n], out[n] if len(out) > n else None)


def subsample_points(points: list[PointsAtTime], fraction: float, seed: int = 0
                     ) -> list[PointsAtTime]:
    """A random ``fraction`` of each frame's points (the sparse initialisation), static flags
    kept."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for p in points:
        n = max(8, round(fraction * len(p.xyz)))
        keep = torch.randperm(len(p.xyz), generator=g)[:n].sort().values
        out.append(PointsAtTime(p.time, p.xyz[keep], p.rgb[keep],
                                None if p.static is None else p.static[keep]))
    return out
