"""The production across machines, for real: a Prefect server, an S3 server, two GPU-pool workers.

One test, in the order a studio lives it:

1. ``prefect server start`` on loopback with a temporary home (SQLite), moto's S3 server;
   ``deploy/setup-pool.sh`` makes the pools and the ``gpu-slots`` limit, ``prefect deploy`` the
   deployments of ``deploy/prefect.yaml`` (their heartbeats every 30 s instead of 60), and the
   zombie automation of ``deploy/automations`` is installed with a short window; two
   ``volcap worker --pool gpu --limit 1`` processes start.
2. ``volcap run`` on a production spec over the demo capture (rendered here, a few frames) whose
   quality makes three segments, with the store on S3.
3. While a worker trains its second segment (a checkpoint of it is in the store), the worker and
   its flow-run process are killed (SIGKILL). The run is marked Crashed by the automation, the
   production submits it again, the other worker resumes it from the checkpoint.
4. The production completes: both workers trained segments, the resumed segment's model is
   bit-identical to an uninterrupted training of the same segment in this process.
5. ``volcap run`` again: nothing is trained or computed again.

Every process started is killed at the end, whatever happened.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest
import yaml

from tests.prefect_cluster import BIN, Cluster, kill_tree, set_up_studio, start_gpu_workers, submissions
from tests.s3_server import s3_endpoint  # noqa: F401  (fixture)

pytestmark = pytest.mark.slow

#: segment runs send heartbeats every 60 s (deploy/prefect.yaml), here every 30 s (Prefect's least);
#: the test automation crashes a run after 50 s without one (production: 300 s, 5 missed heartbeats):
#: a heartbeat may come 20 s late on a loaded machine before a live run is taken for a dead one
HEARTBEAT_S = 30
ZOMBIE_WITHIN_S = 50


@pytest.fixture
def cluster(tmp_path, s3_endpoint):  # noqa: F811
    c = Cluster(tmp_path, s3_endpoint.env)
    try:
        yield c
    finally:
        c.stop()


def _past_first_checkpoint_of_second_run(log: Path) -> bool:
    """The worker's second flow run has logged a training step after its first checkpoint (10)."""
    text = log.read_text(errors="replace") if log.exists() else ""
    marks = [m.start() for m in re.finditer(r"[Ss]ubmitting flow run '", text)]
    if len(marks) < 2:
        return False
    steps = [int(k) for k in re.findall(r"\): step (\d+)/\d+", text[marks[1]:])]
    return any(10 < k for k in steps)


def _spec(tmp: Path, capture: Path, store: str) -> Path:
    shot = {"name": "orbit", "performance": "demo", "frames": [0, 7], "fps": 24, "resolution": [64, 36],
            "sensor_mm": 36,
            "keyframes": [{"frame": 0, "position": [5.0, -2.0, 1.8], "look_at": [0.0, 0.0, 1.0], "focal_mm": 24},
                          {"frame": 6, "position": [5.0, 2.0, 1.8], "look_at": [0.0, 0.0, 1.0], "focal_mm": 28}]}
    spec = {"format": "volcap-production/1", "name": "cluster-test", "store": store,
            # three segments over 7 frames; enough steps that a segment is still training when the
            # worker is killed after its first checkpoint (every 10 steps in the test preset): at a
            # quarter of the resolution, SH degree 0, a step takes ~0.1 s on a quiet core and the
            # worker logs every 10th, so the test polls the worker's log (every 0.5 s) from step 20
            # through a ~8 s window
            "quality": {"preset": "test", "max_segment_frames": 3, "overlap": 1, "train_steps": 100,
                        "train_scale": 0.25, "sh_degree": 0},
            "captures": {"demo": {"folder": str(capture)}}, "shots": [shot]}
    path = tmp / "spec.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def test_production_over_two_workers_survives_a_killed_worker_and_reruns_cached(cluster, tmp_path, s3_endpoint):  # noqa: F811
    from volcap_core.synth import synthesize_capture

    # the 8 static cameras and one tracking camera (the production's calibrate-tracking step runs; the
    # other three trackers would add their tasks and nothing this test checks)
    capture = synthesize_capture(tmp_path / "demo", rig="demo_scene", seed=0, frames=7, supersample=1,
                                 cameras=[f"S{i:03d}" for i in range(8)] + ["S010"]).parent
    store = s3_endpoint.store_url()
    spec = _spec(tmp_path, capture, store)

    # -- 1. the studio
    set_up_studio(cluster, gpus=2, zombie_within_s=ZOMBIE_WITHIN_S, heartbeat_s=HEARTBEAT_S)
    start_gpu_workers(cluster, ["w1", "w2"])

    # -- 2. the production, with the store on S3
    run = cluster.start("run1", [str(BIN / "volcap"), "run", str(spec), "--segment-runs", "deployment", "--json"])

    # -- 3. kill the worker that is on its second segment once that segment has a checkpoint
    # (its own progress lines past the first checkpoint, at step 10: not any checkpoint in the store,
    # which may be the other worker's, nor a run still Pending, which sends no heartbeat yet)
    from volcap_core.store import ArtifactStore

    s = ArtifactStore(store)
    victim = None
    deadline = time.monotonic() + 900
    while victim is None and time.monotonic() < deadline and run.poll() is None:
        time.sleep(0.5)
        for name in ("w1", "w2"):
            if _past_first_checkpoint_of_second_run(cluster.log(name)):
                victim = name
                break
    assert victim is not None, ("no worker reached a second segment with a checkpoint\n"
                                + cluster.log("run1").read_text()[-4000:])
    kill_tree(cluster.procs[victim])
    survivor = "w2" if victim == "w1" else "w1"

    assert run.wait(timeout=900) == 0, cluster.log("run1").read_text()[-6000:]
    result = json.loads(cluster.log("run1").read_text().strip().splitlines()[-1])

    # -- 4. what happened
    assert result["segment_runs"] == "deployment"
    assert result["shots"]["orbit"]["count"] == 7
    segments = {k: v["segment"] for k, v in result["steps"].items() if k.startswith("train-segment:")}
    assert len(segments) == 3
    runs = cluster.segment_runs()
    crashed = [r for r in runs if r["state_type"] == "CRASHED"]
    assert crashed, [(r["name"], r["state_type"]) for r in runs]
    assert all(r["state_type"] in ("COMPLETED", "CRASHED") for r in runs)
    assert len([r for r in runs if r["state_type"] == "COMPLETED"]) == 3
    assert len(submissions(cluster.log(victim))) >= 2 and submissions(cluster.log(survivor))
    survivor_log = cluster.log(survivor).read_text(errors="replace")
    assert "resuming from checkpoints/" in survivor_log, survivor_log[-4000:]
    assert not s.list_refs("checkpoints/"), "a finished segment leaves no checkpoint behind"

    # the resumed segment ends bit-identical to an uninterrupted training of it
    frames = re.search(r"segment-(\d{6})-(\d{6})-attempt-0", crashed[0]["name"]).groups()
    resumed_id = f"train-segment:demo:{frames[0]}-{frames[1]}"
    _assert_bit_identical_to_uninterrupted(s, segments[resumed_id])

    # -- 5. a rerun trains and computes nothing
    before = len(runs)
    again = cluster.run([str(BIN / "volcap"), "run", str(spec), "--segment-runs", "deployment", "--json"],
                        timeout=600)
    rerun = json.loads(again.stdout.strip().splitlines()[-1])
    assert rerun["tasks_run"] == 0 and rerun["tasks_failed"] == 0, rerun
    assert rerun["steps"] == result["steps"] and rerun["shots"] == result["shots"]
    assert len(cluster.segment_runs()) == before
    plan = json.loads(cluster.run([str(BIN / "volcap"), "plan", str(spec), "--json"]).stdout.strip().splitlines()[-1])
    assert {p["status"] for p in plan["steps"]} == {"cached"}


def _assert_bit_identical_to_uninterrupted(s, segment_digest: str) -> None:
    """Train the segment again here, uninterrupted and without checkpoints, from the same inputs."""
    import torch

    from volcap_core.segment import tracking_frames
    from volcap_core import reconstruction
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture
    from volcap_core.checkpoint import deterministic_torch
    from volcap_core.pointcloud import PointCloudSequence
    from volcap_core.splat import save_model, train_segment
    from volcap_core.splat.train import TrainConfig

    rec = s.get_record(segment_digest, reconstruction.SegmentModel)
    cap = s.get_record(rec.capture, Capture)
    calib = s.get_record(rec.calibration, Calibration)
    tracking = tracking_frames(s.get_bytes, calib)
    config = TrainConfig.model_validate({**rec.config, "checkpoint_every": 0})
    data = reconstruction.segment_data(cap, calib, tracking, rec.frames, reconstruction.FrameCache(s.get_bytes),
                                       scale=config.image_scale)
    pts = s.get_record(_points_of(s, segment_digest), PointCloudSequence)
    init = reconstruction.segment_init(s.get_bytes, cap, pts, data, config.held_out_cameras)
    torch.set_num_threads(1)
    with deterministic_torch("cpu"):
        result = train_segment(data, init, config, seed=0, device="cpu")
    assert save_model(result.model) == s.get_bytes(rec.model)


def _points_of(s, segment_digest: str):
    """The PointCloudSequence a segment was trained from (the production journal has it)."""
    for name in s.list_refs("productions/cluster-test/steps/train-segment/"):
        from volcap_core.production.journal import StepEntry

        entry = s.get_record(s.get_ref(name), StepEntry)
        if entry.outputs["segment"].digest == segment_digest:
            dense = next(k for k in entry.fingerprint["inputs"] if k.startswith("dense-points:"))
            dense_entry = s.get_record(s.get_ref("productions/cluster-test/steps/" + dense.replace(":", "/")),
                                       StepEntry)
            return dense_entry.outputs["points"]
    raise AssertionError(f"no journal entry for segment {segment_digest}")
