"""Dense points in bounded memory: the sweep's batches stay within their budget and give the same
depths whatever the budget, frames are read when the sweep needs them (never every view at once),
each camera reports its progress, a calibration without scene depths sweeps the stage, and
``volcap reconstruct`` reuses the dense frames made from the same cameras at the same scale.

A tiny synthetic capture (4 static + 1 tracking camera of the demo rig, one frame at 320x180)
matched at half or quarter resolution; about 50 s on 2 cores, the reuse test most of it.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from prefect import flow

from volcap_core.calibration.dense import (SWEEP_BYTES_PER_HYPOTHESIS_PIXEL, DenseOptions, _Sweep, _View,
                                           dense_points, depth_map)
from volcap_core.calibration.dense_points_step import dense_points_step, stage_sweeps
from volcap_core.calibration.metrics import load_ground_truth
from volcap_core.capture import Capture, CaptureCamera, CaptureFolder
from volcap_core.synth import ground_truth, synthesize_capture

CAMERAS = ["S002", "S003", "S004", "S005", "S008"]   # S008: a landscape tracker
STATIC = CAMERAS[:4]


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("dense")
    return synthesize_capture(root / "cap", rig="demo_scene", seed=2, frames=1, cameras=CAMERAS, supersample=1,
                              write_depth=True).parent


@pytest.fixture(scope="module")
def frame(capture_dir):
    """(images, true cameras) of take index 0."""
    folder = CaptureFolder.open(capture_dir)
    gt = load_ground_truth(capture_dir / "ground_truth")
    return {c: folder.load(c, 0) for c in STATIC}, {c: gt.cameras[c][0] for c in STATIC}


def test_batches_cover_every_hypothesis_and_row_within_the_budget():
    """The plan of a sweep: every (hypothesis, row) once, each batch's working set (halo rows
    included) within the budget, down to one plane on a band of rows at 4K."""
    import torch

    for (H, W), n, budget_mb in (((90, 160), 300, 256), ((2160, 3840), 17, 256), ((2160, 3840), 300, 64),
                                 ((360, 640), 5, 1)):
        view = _View(torch.zeros(1, 1, H, W), np.eye(3), np.eye(4))
        sweep = _Sweep(view, [view], window=5, budget_bytes=budget_mb * 2 ** 20)
        seen = np.zeros((n, H), np.int32)
        for h0, h1, r0, r1 in sweep.batches(n):
            seen[h0:h1, r0:r1] += 1
            rows = min(H, r1 + 2) - max(0, r0 - 2)
            assert (h1 - h0) * rows * W * SWEEP_BYTES_PER_HYPOTHESIS_PIXEL <= budget_mb * 2 ** 20 or (
                h1 - h0 == 1 and r1 - r0 == 1), (H, W, n, h0, h1, r0, r1)
        assert (seen == 1).all(), (H, W, n)


def test_the_depths_do_not_depend_on_the_budget(frame):
    """A 1 MiB budget (bands of a few rows, a few planes a batch) gives bit for bit the depths of
    the default budget (whole images, dozens of planes a batch): the bands' halo rows make each
    row's windows whole."""
    images, cams = frame
    opts = DenseOptions(scale=4.0, depth_min=3.0, depth_max=12.0)
    nbs = ["S002", "S004", "S005"]
    whole = depth_map(images, cams, "S003", nbs, opts)
    banded = depth_map(images, cams, "S003", nbs, opts, budget_mb=1)
    assert np.count_nonzero(whole.depth) > 500
    np.testing.assert_array_equal(banded.depth, whole.depth)


def test_a_quarter_resolution_coarse_level_finds_the_true_depths(capture_dir, frame):
    """Above ``coarse_quarter_above_px`` wide the coarse planes are swept at a quarter of the
    resolution (half the planes, a sixteenth of the pixels) and refined at half: here forced at
    320x180 (a coarse image of 80x45, harsher than the 160x90 of 640 px), its depths lie on the
    true surface nearly as often (within 1 %) and as closely as the half-resolution sweep's (which
    a 320-px-wide image keeps by default)."""
    from volcap_core.imageio.read import decode_exr_native

    images, cams = frame
    nbs = ["S002", "S004", "S005"]
    opts = DenseOptions(depth_min=3.0, depth_max=12.0)
    half = depth_map(images, cams, "S003", nbs, opts)
    quarter = depth_map(images, cams, "S003", nbs, replace(opts, coarse_quarter_above_px=160))
    assert quarter.planes <= half.planes // 2 + 1
    truth = decode_exr_native((capture_dir / "ground_truth" / "depth" / "S003" / "000000.exr").read_bytes())[0][..., 0]
    for dm in (half, quarter):
        assert dm.depth.shape == truth.shape
    hits = {}
    for name, dm in (("half", half), ("quarter", quarter)):
        ok = (dm.depth > 0) & np.isfinite(truth)
        rel = np.abs(dm.depth[ok] / truth[ok] - 1)
        hits[name] = int(np.count_nonzero(rel < 0.01))
        assert ok.sum() > 5000 and np.median(rel) < 0.005, (name, ok.sum(), np.median(rel))
    # 0.93 measured; 0.86 without the median filter of the coarse depths
    assert hits["quarter"] >= 0.9 * hits["half"], hits


def test_frames_are_read_when_needed_and_progress_is_reported(capture_dir):
    """The step reads each camera's frame at most twice (its matching images, then its colours as
    a reference), one at a time: the sweep never holds every view. Progress: one call per camera,
    in order, with its planes, depth range and pixels with a depth. The points lie on the true
    surfaces."""
    folder = CaptureFolder.open(capture_dir)
    gt = load_ground_truth(capture_dir / "ground_truth")
    cams_json = json.loads((capture_dir / "ground_truth" / "cameras.json").read_text())
    calib, _ = ground_truth.calibration(cams_json, folder.name, STATIC, folder.rig.stage_size_m)
    cap = Capture(name=folder.name, rig=folder.rig, fps=folder.fps, start_timecode="00:00:00:00", frame_count=1,
                  cameras=tuple(CaptureCamera(id=c, width=320, height=180, channels=("R", "G", "B"),
                                              source_encoding="linear", frames=()) for c in STATIC))
    reads: list[str] = []

    def load(cid: str, f: int) -> np.ndarray:
        reads.append(cid)
        return folder.load(cid, f)

    calls = []
    out = dense_points_step(cap, calib, 0, load, DenseOptions(), scale=0.5,
                            progress=lambda done, total, info: calls.append((done, total, dict(info))))
    assert sorted(set(reads)) == STATIC and max(reads.count(c) for c in STATIC) == 2, reads
    assert [(d, t, i["camera"]) for d, t, i in calls] == [(k + 1, 4, c) for k, c in enumerate(STATIC)]
    sweeps = stage_sweeps(calib, STATIC, 0)
    for _, _, info in calls:
        lo, _, hi = sweeps[info["camera"]]
        assert info["depth_m"] == (lo, hi) and info["planes"] >= 8 and info["pixels"] > 0
        assert info["seconds"] > 0
    assert len(out.positions) > 1000
    # the stage sweep finds the actors: the points within the stage volume lie on them
    from volcap_core.calibration.metrics import distance_to_parts

    parts = [p for a in gt.parts for p in a[0]]
    P = out.positions
    on_stage = (np.abs(P[:, 0]) < 2) & (np.abs(P[:, 1]) < 2) & (P[:, 2] > 0.1)
    d = distance_to_parts(P[on_stage], parts)
    assert on_stage.sum() > 300 and np.median(d) < 0.05, (on_stage.sum(), np.median(d))


def test_a_calibration_without_scene_depths_sweeps_the_stage_in_view(capture_dir):
    """Each camera's sweep spans the stage volume in its view (with the margins of
    ``dense.sweep_range``): the true depth of every actor pixel lies inside it; the fixed 1-14 m
    of ``DenseOptions`` would sweep 3-4 times the planes."""
    from volcap_core.imageio.read import decode_exr_native

    folder = CaptureFolder.open(capture_dir)
    cams_json = json.loads((capture_dir / "ground_truth" / "cameras.json").read_text())
    calib, _ = ground_truth.calibration(cams_json, folder.name, STATIC, folder.rig.stage_size_m)
    sweeps = stage_sweeps(calib, STATIC, 0)
    assert sorted(sweeps) == STATIC
    for c in STATIC:
        lo, mid, hi = sweeps[c]
        gt_dir = capture_dir / "ground_truth"
        depth = decode_exr_native((gt_dir / "depth" / c / "000000.exr").read_bytes())[0][..., 0]
        mask = ground_truth.performer_mask((gt_dir / "masks" / c / "000000.exr").read_bytes()) > 0.5
        z = depth[mask & np.isfinite(depth)]
        assert len(z) > 100 and lo < z.min() and z.max() < hi and lo < mid < hi, (c, sweeps[c], z.min(), z.max())
        assert (1 / lo - 1 / hi) < 0.5 * (1 / 1.0 - 1 / 14.0), (c, sweeps[c])


def test_dense_points_library_keeps_its_contract(frame):
    """``dense_points`` on in-memory images (the static step's stand-in surface calls it so)."""
    images, cams = frame
    out = dense_points(images, cams, references=["S003", "S004"], options=DenseOptions(scale=4.0),
                       sweeps={c: (3.0, 5.5, 12.0) for c in STATIC})
    assert out["positions"].dtype == np.float32 and out["colours"].shape == out["positions"].shape
    assert len(out["positions"]) == len(out["views"]) > 100 and set(out["depth_maps"]) == {"S003", "S004"}


@pytest.mark.slow
def test_reconstruct_reuses_the_dense_points_calibrate_made(prefect_api, capture_dir, tmp_path):
    """Dense frames made as ``volcap calibrate`` makes them (every static camera, full scale) are
    reused by ``volcap reconstruct`` on the same calibration when its held-out camera takes no
    part in them (a tracking camera) and the preset matches at the same scale: no dense task runs
    again, only the training. A held-out static camera recomputes them without it."""
    from flows.calibrate import point_cloud_for_frames
    from flows.ingest import ingest_flow
    from flows.reconstruct import reconstruct_flow
    from flows.runtime import run_flow
    from tasks.reconstruct import ground_truth_calibration
    from volcap_core.pointcloud import PointCloudSequence
    from volcap_core.store import ArtifactStore

    store = ArtifactStore(str(tmp_path / "store")).url
    capture = run_flow(ingest_flow, store=store, capture_dir=str(capture_dir)).result

    @flow(name="calibrate-like", persist_result=False)
    def calibrate_like(store: str, capture) -> tuple:
        calib = ground_truth_calibration(store, capture)
        return calib, point_cloud_for_frames(store, capture, calib, [0])   # as calibrate_flow calls it

    calib, points = run_flow(calibrate_like, store=store, capture=capture).result
    s = ArtifactStore(store)
    made = s.get_record(points, PointCloudSequence)
    common = dict(store=store, capture=capture.digest, calibration=calib.digest, preset="demo", steps=2,
                  max_gaussians=2000)
    again = run_flow(reconstruct_flow, **common, held_out=["S008"])
    assert again.result["points"]["digest"] == points.digest
    assert (again.tasks_run, again.tasks_cached) == (1, 2), (again.tasks_run, again.tasks_cached)  # training only
    held = run_flow(reconstruct_flow, **common, held_out=["S003"])
    assert held.tasks_run == 3   # the dense frame and its sequence without S003, the training
    seq = s.get_record(held.result["points"]["digest"], PointCloudSequence)
    assert seq.frames[0].points != made.frames[0].points
