"""A capture's own performer masks in reconstruction: its performer scores where no ground truth
has masks, and training's matte (never a ground truth). The capture: a synthetic one whose
ground-truth masks are moved into the capture layout's masks folder, as a studio's imported masks
(its ground truth keeps the cameras and depth maps that give the calibration and points)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import ndimage

from flows.ingest import ingest_flow
from flows.runtime import run_flow
from volcap_core import reconstruction
from volcap_core.capture import Capture, CaptureFolder
from volcap_core.imageio.read import read_exr_native
from volcap_core.splat.train import TrainConfig, evaluate_held_out
from volcap_core.store import ArtifactStore
from volcap_core.synth import ground_truth, synthesize_capture


def _imported_masks_capture(root: Path, cameras: list[str], frames: int) -> Path:
    root = synthesize_capture(root, rig="demo_scene", seed=3, frames=frames, cameras=cameras, supersample=1,
                              write_depth=True).parent
    shutil.move(root / "ground_truth" / "masks", root / "masks")
    # the ground truth numbers them by take index, the layout by the camera's own frame number
    offsets = CaptureFolder.open(root).offsets
    for cam in cameras:
        for i in reversed(range(frames)):
            (root / "masks" / cam / f"{i:06d}.exr").rename(root / "masks" / cam / f"{i - offsets[cam]:06d}.exr")
    desc = json.loads((root / "capture.json").read_text())
    desc["masks"] = "masks"
    (root / "capture.json").write_text(json.dumps(desc, indent=2))
    return root


def _truth_mask(root: Path, cam: str, f: int) -> torch.Tensor:
    path = CaptureFolder.open(root).mask_files(cam)[f]
    return torch.from_numpy(read_exr_native(path)[0][..., 0].astype(np.float32))


def test_views_carry_the_capture_masks_and_score_the_performers(prefect_api, tmp_path):
    """~15 s: 2 static cameras, 2 frames."""
    root = _imported_masks_capture(tmp_path / "cap", ["S000", "S003"], 2)
    s = ArtifactStore(str(tmp_path / "store"))
    cap = s.get_record(run_flow(ingest_flow, store=s.url, capture_dir=str(root)).result, Capture)
    calib, _ = ground_truth.calibration(json.loads((root / "ground_truth" / "cameras.json").read_text()),
                                        cap.name, ["S000", "S003"], cap.rig.stage_size_m)
    frames = reconstruction.FrameCache(s.get_bytes)
    data = reconstruction.segment_data(cap, calib, None, (0, 2), frames, scale=0.5)
    v = next(v for v in data.views if v.camera_id == "S003" and v.frame == 1)
    want = torch.nn.functional.interpolate(_truth_mask(root, "S003", 1)[None, None], size=(90, 160), mode="area")[0, 0]
    torch.testing.assert_close(v.load_mask(), want, atol=2e-3, rtol=0)     # stored as half
    torch.testing.assert_close(v.load_matte(), v.load_mask())
    # a ground truth's masks, when given, are what the scores use; the matte stays the capture's
    other = reconstruction.segment_data(cap, calib, None, (0, 2), frames, scale=0.5,
                                        load_mask=lambda c, f: np.zeros((180, 320), np.float32))
    v2 = next(v for v in other.views if v.camera_id == "S003" and v.frame == 1)
    assert float(v2.load_mask().abs().sum()) == 0.0 and torch.equal(v2.load_matte(), v.load_matte())
    # the empty model scored on the held-out views: performer figures beside the whole frame's
    scores = evaluate_held_out(None, [v for v in data.views if v.camera_id == "S003"], TrainConfig())
    assert all(sc.psnr_performers is not None and sc.ssim_performers is not None for sc in scores)


@pytest.mark.slow
def test_reconstruct_scores_performers_on_imported_masks(prefect_api, tmp_path):
    """~60 s on 2 cores: `volcap reconstruct` (ground-truth cameras and points, the test preset) on
    a capture whose only masks are its imported ones: performer figures beside both floors."""
    from flows.reconstruct import reconstruct_flow

    cams = ["S000", "S001", "S002", "S003", "S004", "S005"]
    root = _imported_masks_capture(tmp_path / "cap", cams, 2)
    store = ArtifactStore(str(tmp_path / "store")).url
    capture = run_flow(ingest_flow, store=store, capture_dir=str(root)).result.digest
    # 4 000 Gaussians: the figures are checked for being there, not for their level
    out = run_flow(reconstruct_flow, store=store, capture=capture, preset="test", points_per_frame=2000,
                   held_out=["S002"], ground_truth=True, max_gaussians=4000).result
    scores = out["segments"][0]["scores"]
    for model in ("trained", "initial", "empty"):
        assert scores["held_out"][model]["psnr_performers"] is not None, model
    held = scores["regions"]["held_out"]["static"]
    assert held["cameras"] == ["S002"] and held["trained"]["performers"]["views"] == 2
    print("held-out performers (trained / initial / empty):",
          [scores["held_out"][m]["psnr_performers"] for m in ("trained", "initial", "empty")])


def test_a_capture_with_masks_starts_from_its_performers_hull(prefect_api, tmp_path):
    """The capture's own masks carve the performers' visual hull into each frame's initial points
    (``reconstruction.with_performer_hull``, what ``segment_init`` does for a capture with masks),
    and the sweep's moving points outside the stage are dropped; static points are kept. The hull
    lands on the performers: drawn into a camera that carved nothing (held out), its points fall
    on that camera's true performer mask. ~20 s: 4 static cameras, 1 frame."""
    from volcap_core.splat import PointsAtTime
    from volcap_core.stage import stage_volume

    cams = ["S000", "S001", "S002", "S003"]
    root = _imported_masks_capture(tmp_path / "cap", cams, 1)
    s = ArtifactStore(str(tmp_path / "store"))
    cap = s.get_record(run_flow(ingest_flow, store=s.url, capture_dir=str(root)).result, Capture)
    calib, _ = ground_truth.calibration(json.loads((root / "ground_truth" / "cameras.json").read_text()),
                                        cap.name, cams, cap.rig.stage_size_m)
    data = reconstruction.segment_data(cap, calib, None, (0, 1), reconstruction.FrameCache(s.get_bytes), scale=0.5)
    assert reconstruction.has_performer_mattes(data, ["S003"])
    volume = stage_volume(cap.rig.stage_size_m)
    t = data.views[0].time
    sweep = PointsAtTime(time=t, xyz=torch.tensor([[0.0, 0.0, 1.0], [40.0, 0.0, 1.0], [40.0, 0.0, 0.0]]),
                         rgb=torch.full((3, 3), 0.5), static=torch.tensor([False, False, True]))
    [out] = reconstruction.with_performer_hull([sweep], data, ["S003"], volume)

    assert torch.equal(out.xyz[:2], sweep.xyz[[0, 2]])            # inside kept, outside moving dropped,
    assert out.static[1] and not out.static[0]                    # the static point kept whatever its place
    hull = out.xyz[2:].double().numpy()
    assert len(hull) > 200 and not out.static[2:].any() and torch.isfinite(out.rgb).all()
    held = next(v for v in data.views if v.camera_id == "S003")
    K, W = held.camera.K.double().numpy(), held.camera.world_to_camera.double().numpy()
    pc = hull @ W[:3, :3].T + W[:3, 3]
    uv = np.floor(pc[:, :2] / pc[:, 2:] @ K[:2, :2].T + K[:2, 2]).astype(int)   # pixel centres at +0.5
    h, w = held.camera.height, held.camera.width
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    mask = held.load_mask().numpy() >= 0.5
    on_performer = mask[uv[inside, 1], uv[inside, 0]]
    drawn = np.zeros_like(mask)
    for dy in range(-2, 3):                                   # each point drawn as a 5x5 splat
        for dx in range(-2, 3):
            drawn[np.clip(uv[inside, 1] + dy, 0, h - 1), np.clip(uv[inside, 0] + dx, 0, w - 1)] = True
    covered = (drawn & mask).sum() / mask.sum()
    print(f"hull {len(hull)} points, {inside.mean():.2f} in the held-out view, {on_performer.mean():.2f} on its "
          f"performers (they fill {mask.mean():.3f} of it), covering {covered:.2f} of them")
    # a hull holds the true shape: drawn, it covers the performers; three cameras carve phantoms beside
    # them, yet its points are far likelier on the performers than the frame's share of them
    assert inside.mean() > 0.9 and covered > 0.9 and on_performer.mean() > 5 * mask.mean()

    # the benchmarks' diagnostic (``carve_only``): the held-out camera's mask carves too, so the hull's
    # points in its view fall on its performers (its mask closed and filled: a pixel or two beyond)
    [oracle] = reconstruction.with_performer_hull([sweep], data, ["S003"], volume, carve_only=["S003"])
    hull2 = oracle.xyz[2:].double().numpy()
    pc2 = hull2 @ W[:3, :3].T + W[:3, 3]
    uv2 = np.floor(pc2[:, :2] / pc2[:, 2:] @ K[:2, :2].T + K[:2, 2]).astype(int)
    in2 = (uv2[:, 0] >= 0) & (uv2[:, 0] < w) & (uv2[:, 1] >= 0) & (uv2[:, 1] < h)
    near = ndimage.binary_dilation(mask, iterations=2)
    print(f"carved by S003 too: {len(hull2)} points, {near[uv2[in2, 1], uv2[in2, 0]].mean():.2f} on its performers")
    assert len(hull2) > 100 and near[uv2[in2, 1], uv2[in2, 0]].mean() > 0.95 > near[uv[inside, 1], uv[inside, 0]].mean()
