"""bench/gpu_zoom_curve.py on a real capture without ground truth (issue 30's GPU item): Pose2Sim
SinglePerson prepared by bench/bench_pose2sim_heldout.py --gpu-prepare (its rectified frames as
8-bit PNG, its own performer masks, no face regions, cam02 held out), run where Prefect, pycolmap
and OpenCV cannot be imported, reported. Skipped without ../shared."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from bench.bench_dense_points import POSE2SIM
from tests.gpu_machine import load_bench, run_without_absent



@pytest.mark.slow
def test_real_capture_prepare_run_report(prefect_api, tmp_path):
    """2 frames of the 4 cameras at 1/16 size (68x120), masks against the whole videos' medians, dense
    points at 1/8 without cam02, the performers' hull and the sweep's clean-up (the capture has masks),
    500 Gaussians a frame, 4 steps.
    ~75 s on the 2 busy cores (2026-11-28), most of it the ingest of the 1080x1920 MP4 frames."""
    if not POSE2SIM.is_dir():
        pytest.skip(f"needs {POSE2SIM} (absent without ../shared)")
    from volcap_core import reconstruction
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture
    from volcap_core.colour import srgb_encode
    from volcap_core.store import ArtifactStore

    p2s = load_bench("bench_pose2sim_heldout")
    bench = load_bench("gpu_zoom_curve")
    work = tmp_path / "w"
    work.mkdir()
    inputs = p2s.prepare(work, start=48, frames=2)
    points = p2s.dense_points(inputs, work, "cam02", 0.125, 70.0)
    src = tmp_path / "prep"
    args = argparse.Namespace(held="cam02", scale=1 / 16, dense_scale=0.125, steps=4, gaussians_per_frame=500,
                              fill_shell=False, hull_oracle=False, gpu_prepare=src)
    p2s.gpu_prepare(inputs, points, args)

    meta = json.loads((src / "segment.json").read_text())
    assert meta["held_out"] == ["cam02"] and meta["gaussians"] == 1000 and meta["footage"] == "png"
    assert len(meta["views"]) == 8 and not (src / "faces.npz").exists()   # no faces: none faked
    assert set(meta["performer_boxes"]) == {"cam01", "cam02", "cam03", "cam04"}
    # the footage that travels is the rectified footage segment_data gives, to half an 8-bit code
    s = ArtifactStore(inputs["store"])
    cap = s.get_record(s.resolve(inputs["capture"]), Capture)
    calib = s.get_record(s.resolve(inputs["calibration"]), Calibration)
    data = reconstruction.segment_data(cap, calib, None, (0, 2), reconstruction.FrameCache(s.get_bytes), scale=1 / 16)
    prep = bench.Prepared(src)
    assert prep.faces is None
    for theirs, ours in zip(data.views, prep.data.views):
        assert (theirs.camera_id, theirs.frame) == (ours.camera_id, ours.frame)
        diff = np.abs(srgb_encode(theirs.load()[..., :3].clamp(0, 1).numpy()) - srgb_encode(ours.load().numpy()))
        assert diff.max() <= 0.5 / 255 + 1e-6
        assert np.array_equal(theirs.load_valid().numpy(), ours.load_valid().numpy())   # rectified lenses
        assert np.allclose(theirs.load_mask().numpy(), ours.load_mask().numpy())
        assert ours.load_matte() is not None   # the capture's own masks are its matte too

    out = tmp_path / "out"
    proc = run_without_absent("gpu_zoom_curve", ["--run", src, "--out", out, "--device", "cpu", "--steps", "4",
                                                 "--evals", "2", "--budget-s", "600"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    curve = json.loads((out / "curve.json").read_text())
    assert curve["stopped"] == "steps" and [p["step"] for p in curve["points"]] == [0, 2, 4]
    assert curve["floors"]["held_out"]["static"]["cameras"] == ["cam02"]
    for which in ("held_out", "training"):
        r = curve["floors"][which]["static"]
        assert set(r["empty"]) == set(r["initial"]) == {"performers"}   # no face region
        assert r["empty"]["performers"]["detail"] == 0.0
        for floor in ("empty", "initial"):
            assert curve["floor_summaries"][floor][which]["psnr"] is not None
    for p in curve["points"]:
        assert p["held_out"]["psnr_raw"] is not None and p["held_out"]["psnr_performers"] is not None
        assert p["held_out_raw"]["static"]["psnr"] is not None
    # step 0 is the untrained model, and the untrained model draws the room the empty one lacks
    assert curve["points"][0]["held_out_raw"]["static"] == curve["floors_held_out_raw"]["static"]["initial"]
    assert curve["points"][0]["held_out"] == curve["floor_summaries"]["initial"]["held_out"]
    assert curve["floor_summaries"]["initial"]["held_out"]["psnr_raw"] > \
        curve["floor_summaries"]["empty"]["held_out"]["psnr_raw"] + 3
    crops = np.load(out / "sheet.npz")
    assert {"cam02/truth", "cam02/trained", "cam02/trained_raw", "cam02/whole/trained", "cam01/initial"} \
        <= set(crops.files)
    y0, y1, x0, x1 = meta["performer_boxes"]["cam02"]
    assert crops["cam02/truth"].shape == (y1 - y0, x1 - x0, 3)   # the performer at 1:1

    sheet = tmp_path / "sheet.png"
    bench.main(["--report", str(out), "--sheet", str(sheet)])
    assert sheet.stat().st_size > 1000
