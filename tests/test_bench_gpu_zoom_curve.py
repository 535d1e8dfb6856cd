"""bench/gpu_zoom_curve.py: prepared here, run where Prefect, pycolmap and OpenCV are absent, and
scored as ``volcap reconstruct --json`` scores (issue 28's GPU item)."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from flows.ingest import ingest_flow
from flows.reconstruct import reconstruct_flow
from flows.runtime import run_flow
from volcap_core import reconstruction
from volcap_core.calibration.record import Calibration
from volcap_core.capture import Capture
from volcap_core.masks import write_plate_masks
from volcap_core.pointcloud import PointCloudSequence
from volcap_core.production.presets import named_preset
from volcap_core.segment import tracking_frames
from volcap_core.splat.grids import ExposureGrids
from volcap_core.splat.report import score_segment
from volcap_core.splat.train import frame_interval, init_model
from volcap_core.store import ArtifactStore
from volcap_core.synth import ground_truth, synthesize_capture

from tests.gpu_machine import load_bench, run_without_absent

# four static cameras and two tracking ones: the demo preset holds out S003 and S009 (each
# camera's views cost their floors' colour fits, several times over: the test's most)
CAMERAS = ["S001", "S002", "S003", "S004", "S008", "S009"]


@pytest.mark.slow
def test_prepare_run_report(prefect_api, tmp_path):
    """A 2-frame capture of 6 cameras without a lidar scan reconstructed for its refs (1 step),
    prepared at 1 000 Gaussians a frame, trained 4 steps on CPU in a process where Prefect,
    pycolmap and OpenCV cannot be imported, reported. 155 s of CPU on the 2-core machine under a
    load of ~25 (2026-11-27; 8 cameras: 202 s), most of it the floors' colour fits per view."""
    root = synthesize_capture(tmp_path / "cap", rig="demo_scene", seed=3, frames=2, cameras=CAMERAS,
                              supersample=1, write_depth=True, lidar=False, plates=True).parent
    write_plate_masks(root, plates=root / "plates")   # the capture's own masks, as the demo's
    store = ArtifactStore(str(tmp_path / "store")).url
    capture = run_flow(ingest_flow, store=store, capture_dir=str(root)).result.digest
    recon = run_flow(reconstruct_flow, store=store, capture=capture, preset="test", points_per_frame=1500,
                     held_out=["S003", "S009"], ground_truth=True, steps=1).result
    refs = [recon["capture"]["digest"], recon["calibration"]["digest"], recon["points"]["digest"]]
    bench = load_bench("gpu_zoom_curve")
    src = tmp_path / "prep"
    bench.main(["--prepare", str(src), "--store", store, "--capture", refs[0], "--calibration", refs[1],
                "--points", refs[2], "--frames", "0", "2", "--steps", "4", "--gaussians-per-frame", "1000",
                "--plates", str(root / "plates")])
    meta = json.loads((src / "segment.json").read_text())
    assert meta["held_out"] == ["S003", "S009"] and meta["gaussians"] == 2000   # 1 000 a frame, as asked
    # without --gaussians-per-frame: the production preset's budget a frame (a GPU's size)
    assert bench.demo_quality(4).gaussians_per_frame == named_preset("production").gaussians_per_frame == 100_000
    assert len(meta["views"]) == 2 * len(CAMERAS)
    # the capture's own masks travel as the views' mattes (the demo preset's alpha loss trains on them
    # there, as in the train-segment task); the ground truth's stay the scored masks
    prep = bench.Prepared(src)
    with_matte = sorted({v.camera_id for v in prep.data.views if v.matte is not None})
    assert with_matte == ["S001", "S002", "S003", "S004"]   # the static cameras: no plate behind a tracking one
    v = next(v for v in prep.data.views if v.camera_id == "S001")
    assert not torch.equal(v.load_matte(), v.load_mask())

    # the run part: no Prefect, pycolmap, OpenCV or OpenImageIO in its process
    out = tmp_path / "out"
    proc = run_without_absent("gpu_zoom_curve", ["--run", src, "--out", out, "--device", "cpu", "--steps", "4",
                                                 "--evals", "2", "--budget-s", "600"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    curve = json.loads((out / "curve.json").read_text())
    assert curve["backend"] == "numba" and curve["stopped"] == "steps"
    assert [p["step"] for p in curve["points"]] == [0, 2, 4]
    walls = [p["wall_s"] for p in curve["points"]]
    assert walls[0] == 0 and walls[1] > 0 and walls[2] > walls[1]
    assert all(p["gaussians"] > 0 for p in curve["points"]) and curve["trace"][-1][0] == 4
    for which, per_role in curve["floors"].items():
        assert set(per_role) == ({"static", "tracking"} if which == "held_out" else set(per_role)), which
        for role, r in per_role.items():
            for floor in ("empty", "initial"):
                assert set(r[floor]) == {"performers", "face"}
            assert r["empty"]["performers"]["detail"] == 0.0
            for p in curve["points"]:
                fig = p["regions"][which][role]["trained"]
                assert fig["performers"]["psnr"] is not None and fig["performers"]["detail"] is not None
    assert curve["floors"]["held_out"]["tracking"]["cameras"] == ["S009"]
    # step 0 is the untrained model: its figures are the untrained floor's
    assert curve["points"][0]["regions"]["held_out"]["tracking"]["trained"] == \
        curve["floors"]["held_out"]["tracking"]["initial"]
    crops = __import__("numpy").load(out / "sheet.npz")
    assert {"S008/truth", "S008/trained", "S009/initial", "S009/face"} <= set(crops.files)

    sheet = tmp_path / "sheet.png"
    bench.main(["--report", str(out), "--sheet", str(sheet)])
    assert sheet.stat().st_size > 1000

    # issue 28's routes through the same run: the set from the static cameras' plates (the held-out
    # S003's left out), then the performers alone over it; an MCMC field, a learning rate and
    # TrainConfig fields over the preset's
    assert sorted(bench.Prepared(src).plates) == ["S001", "S002", "S003", "S004"]
    routes = tmp_path / "routes"
    proc = run_without_absent("gpu_zoom_curve", ["--run", src, "--out", routes, "--device", "cpu", "--steps", "2",
                                                 "--evals", "1", "--budget-s", "600", "--set-steps", "2",
                                                 "--mcmc", "gradient_weight=2", "--lr", "scales=0.01",
                                                 "--train", "init_lifespan_frames=1.5", "--train", "ssim_weight=0.4"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "the set from 3 plates (S001, S002, S004)" in proc.stdout
    routed = json.loads((routes / "curve.json").read_text())
    assert routed["set_steps"] == 2 and 0 < routed["set_gaussians"] <= 1000   # half the segment's 2 000
    assert routed["train_config"]["mcmc"]["gradient_weight"] == 2.0
    assert routed["train_config"]["lr"]["scales"] == 0.01 and routed["train_config"]["lr"]["sh0"] == 2.5e-3
    assert routed["train_config"]["init_lifespan_frames"] == 1.5 and routed["train_config"]["ssim_weight"] == 0.4
    assert routed["train_config"]["init_finest_level"] == -3    # the preset's, where --train is silent
    assert routed["points"][-1]["gaussians"] > routed["set_gaussians"]       # the set and the performers
    # a preset that reads the moving points' footprints, on points without them (a folder prepared for
    # a preset that did not read them): refused by the initial model the run builds, not trained as if
    # every Gaussian started at its neighbours' spacing; --train can switch the fields off
    bare = bench.Prepared(src)
    bare.init = [dataclasses.replace(p, footprint=None) for p in bare.init]
    interval = frame_interval(bare.data.times)
    with pytest.raises(ValueError, match="footprint"):
        init_model(bare.init, bare.config(), frame_interval_s=interval)
    off = bare.config(train={"init_finest_level": 0, "init_moving_scale_px": None})
    assert off.init_finest_level == 0 and len(init_model(bare.init, off, frame_interval_s=interval)) > 0

    # bench_train_time on the same folder: a training's wall time, loss thirds and model digest,
    # the same digest run after run (the CPU training is bit-reproducible)
    timer = load_bench("bench_train_time")
    one, two = (timer.run_once(bench.Prepared(src), 6) for _ in range(2))
    assert one["wall_s"] > 0 and len(one["loss_thirds"]) == 3 and one["digest"] == two["digest"]

    # a budget spent before the first checkpoint: training stops, the floors and step 0 are written
    spent = bench.run(src, tmp_path / "spent", torch.device("cpu"), budget_s=1e-3, steps=4, evals=2)
    assert spent["stopped"] == "budget" and [p["step"] for p in spent["points"]] == [0]
    assert json.loads((tmp_path / "spent" / "curve.json").read_text())["floors"] == curve["floors"]

    # the figures are score_segment's, on the store's own views and points (not the exported ones)
    s = ArtifactStore(store)
    cap = s.get_record(s.resolve(refs[0]), Capture)
    calib = s.get_record(s.resolve(refs[1]), Calibration)
    prep = bench.Prepared(src)
    config = prep.config()
    files = ground_truth.GroundTruthFiles(cap.name, {p: e.digest for p, e in s.get_tree(cap.ground_truth).items()},
                                          s.get_bytes)
    data = reconstruction.segment_data(cap, calib, tracking_frames(s.get_bytes, calib), (0, 2),
                                       reconstruction.FrameCache(s.get_bytes), load_mask=ground_truth.mask_loader(files))
    init = reconstruction.segment_init(s.get_bytes, cap, s.get_record(s.resolve(refs[2]), PointCloudSequence), data,
                                       config.held_out_cameras, zoom_stride_px=config.init_zoom_stride_px,
                                       scene_flow=config.init_scene_flow)
    scene = json.loads(files.read("scene.json"))
    train_cams = sorted({c for c in data.camera_ids if c not in config.held_out_cameras})
    grids = ExposureGrids.identity(train_cams, config.grid_size)
    scorer = bench.RegionScorer(prep, config, torch.device("cpu"), seed=0)
    ours = scorer.figures(scorer.outputs(scorer.initial, grids), floors=True)
    theirs = score_segment(scorer.initial, grids, data, init, config, seed=0,
                           roles={c.id: "static" if c.static else "tracking" for c in calib.cameras},
                           head_region=lambda v: ground_truth.face_region(scene, v.time, v.camera.K.numpy(),
                                                                          v.camera.world_to_camera.numpy(),
                                                                          v.camera.width, v.camera.height))
    assert ours["regions"] == theirs.regions
    assert ours["training"] == theirs.training.to_json()
    assert ours["held_out"] == theirs.held_out["trained"].to_json()
    # and the prepared points are the library's: the same initial model, parameter for parameter (the
    # moving points' footprints, which the preset's levels and scale cap read, travel exactly)
    assert config.init_finest_level < 0 and config.init_moving_scale_px is not None
    ours_init, theirs_init = (init_model(points, config, frame_interval_s=frame_interval(data.times),
                                         generator=torch.Generator().manual_seed(0)) for points in (prep.init, init))
    assert ours_init.params.keys() == theirs_init.params.keys()
    for name, value in ours_init.params.items():
        assert torch.equal(value, theirs_init.params[name]), name
