"""bench/gpu_facerig_pairs.py: a Face Rig sub-sequence prepared here, its pair models trained and
rendered where Prefect, pycolmap, OpenCV and OpenImageIO cannot be imported, and reported (issue
29's GPU item, checked on CPU at tiny sizes)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flows.ingest import ingest_flow
from flows.runtime import run_flow
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture, synthesize_face_capture

from tests.gpu_machine import load_bench, run_without_absent



@pytest.mark.slow   # ~50 s wall, ~27 s of CPU: an end-to-end run of the bench's three parts
def test_prepare_run_report(prefect_api, tmp_path):
    """A 3-frame, 4-camera Face Rig capture and a 1-camera Scene Rig capture (the colour matrix's
    charts), prepared at 1 000 / 100-200 Gaussians a frame with two 32- and 48-px paths, trained
    4 steps after growth and rendered on CPU in a process without Prefect, pycolmap, OpenCV or
    OpenImageIO, then reported."""
    face = synthesize_face_capture(tmp_path / "face", frames=3, cameras=["F002", "F003", "F004", "F005"],
                                   supersample=1, write_depth=True, name="face-gpu").parent
    scene = synthesize_capture(tmp_path / "scene", frames=1, cameras=["S001"], actors=1, supersample=1,
                               name="scene-gpu").parent
    store = ArtifactStore(str(tmp_path / "store")).url
    refs = [run_flow(ingest_flow, store=store, capture_dir=str(d)).result.digest for d in (face, scene)]
    bench = load_bench("gpu_facerig_pairs")
    src = tmp_path / "prep"
    meta = bench.prepare(src, store, capture=refs[0], scene=refs[1], frames=(0, 3), cameras=["F003"],
                         points_per_frame=1500, paths=2, sizes=(32, 48),
                         overrides={"face_hq_gaussians_per_frame": 1000, "face_lq_gaussians": (100, 200)})
    # the held-out camera travels (training checks it exists) beside the cameras asked for
    assert meta["held_out"] == ["F004"] and meta["cameras"] == ["F003", "F004"] and len(meta["views"]) == 6
    assert 100 <= meta["lq_gaussians_per_frame"] <= 200 and meta["hq_gaussians_per_frame"] == 1000
    # the same paths at both sizes: the intrinsics scale with the size, the cameras do not move
    small, large = (meta["paths"][k][0]["views"][1] for k in ("32", "48"))
    assert np.allclose(small["world_to_camera"], large["world_to_camera"], atol=1e-12)
    assert abs(large["K"][0][0] / small["K"][0][0] - 1.5) < 1e-9
    assert meta["colour"]["after"]["delta_e2000_mean"] < meta["colour"]["before"]["delta_e2000_mean"]

    out = tmp_path / "out"
    proc = run_without_absent("gpu_facerig_pairs", ["--run", src, "--out", out, "--device", "cpu", "--hq-steps", "4",
                                                    "--lq-steps", "4", "--budget-s", "600"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in out.iterdir()) == ["facerig_pairs.json", "facerig_pairs.log"]
    fig = json.loads((out / "facerig_pairs.json").read_text())
    assert not fig["skipped"] and "error" not in fig
    assert list(fig["stages"]) == ["train-lq", "train-hq", "render-lq-32", "render-hq-32", "render-lq-48",
                                   "render-hq-48"]
    for label, per_frame in (("lq", meta["lq_gaussians_per_frame"]), ("hq", 1000)):
        st = fig["stages"][f"train-{label}"]
        # grown to the flow's budget (a frame's count times the frames) before the timed steps
        assert st["gaussians_after_growth"] == st["gaussians"] == 3 * per_frame
        assert st["steps_done"] == st["steps"] and st["step_s"]["n"] == 4 - bench.WARMUP_STEPS
    for px in (32, 48):
        lq, hq = fig["stages"][f"render-lq-{px}"], fig["stages"][f"render-hq-{px}"]
        assert len(lq["per_frame"]) == len(hq["per_frame"]) == 3
        assert all(f["exr_bytes"] > 0 and f["render_s"] > 0 for f in lq["per_frame"] + hq["per_frame"])
        # the LQ's flow: one per frame pair, the path's frames (the colour matrix applied inside
        # render_path) identical to the frames rendered and colour-mapped one by one
        assert len(lq["flow"]["exr_bytes"]) == 2 and lq["flow"]["max_diff_to_per_frame_renders"] == 0
        assert "flow" not in hq
        # the path's EXRs encoded together on the host's threads, as render-pairs encodes them
        assert lq["threaded_encode"]["frames"] == hq["threaded_encode"]["frames"] == 3
        assert lq["flow"]["threaded_encode"]["frames"] == 2 and lq["threaded_encode"]["threads"] >= 1
    table = bench.report(out)
    assert "| train-hq | 3000 Gaussians (1000 a frame)" in table and "| render-lq-48 | 48²" in table
    assert "3 EXRs on" in table and "2 EXRs on" in table


def test_encode_check_times_encodes_beside_a_gil_free_control():
    """``--encode-check`` (~2 s): the encodes one by one and on threads through encode_frames, the
    sha256 control, and the GIL probe, whose GIL-holding reference does stall the loop."""
    bench = load_bench("gpu_facerig_pairs")
    f = bench.encode_check(48, frames=2, workers=2, repeats=1)
    assert f["workers"] == 2 and len(f["rounds"]) == 1
    assert all(f[k] > 0 for k in ("encode_one_by_one_s", "encode_threads_s", "sha256_one_by_one_s",
                                  "sha256_threads_s", "encode_speedup", "sha256_speedup"))
    assert set(f["python_loop_beside"]) == {"encode", "sha256", "sum_range"}
    assert f["python_loop_beside"]["sum_range"] < 0.5          # a call that holds the GIL stops the loop
