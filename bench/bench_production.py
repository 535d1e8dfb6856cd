"""Production benchmark: segment fan-out overhead through a Prefect server and workers, against
in-process, and the cached-rerun time of the demo production.

    python bench/bench_production.py [--segments 6] [--workers 2] [--steps 5] [--skip-demo | --only-demo]

Fan-out: a capture of the demo rig with ``segments`` frames and a spec whose quality makes
``segments`` one-frame segments (no overlap), each trained for a handful of steps, so a segment
costs little and the overhead shows. The store is on a local S3 server (moto), as on a cluster.

1. ``volcap run`` in-process (``--segment-runs local``) computes everything once (ingest,
   calibration, dense points, segments, the shot);
2. the number of training steps goes up by one and the spec runs again in-process: only the
   segments (and the shot) are computed again;
3. one more step, and the spec runs with ``--segment-runs deployment`` against a ``prefect server``
   with ``--workers`` process workers on the ``gpu`` pool (``deploy/setup-pool.sh``,
   ``deploy/prefect.yaml``, ``volcap worker``);
4. both again: cached reruns (nothing trains).

The overhead per segment is (3 - 2) / segments when the workers run one segment at a time each
(run 2 trains all segments at once in one process's thread pool: on 2 cores both use both cores).
Demo production: the demo capture (``volcap synth``'s default, 24 frames), a shot over its first 8
frames at the ``test`` quality, run in-process; the figure is the cached rerun's wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from tests.prefect_cluster import BIN, Cluster, set_up_studio, start_gpu_workers  # noqa: E402
from tests.s3_server import moto_s3_server  # noqa: E402


def write_spec(path: Path, name: str, capture: Path, store: str, frames: int, quality: dict) -> Path:
    shot = {"name": "orbit", "performance": "cap", "frames": [0, frames], "fps": 24, "resolution": [64, 36],
            "sensor_mm": 36,
            "keyframes": [{"frame": 0, "position": [5.0, -2.0, 1.8], "look_at": [0.0, 0.0, 1.0], "focal_mm": 24},
                          {"frame": frames - 1, "position": [5.0, 2.0, 1.8], "look_at": [0.0, 0.0, 1.0],
                           "focal_mm": 28}]}
    path.write_text(yaml.safe_dump({"format": "volcap-production/1", "name": name, "store": store,
                                    "quality": quality, "captures": {"cap": {"folder": str(capture)}},
                                    "shots": [shot]}, sort_keys=False))
    return path


def timed_run(cluster: Cluster, spec: Path, mode: str) -> tuple[float, dict]:
    t0 = time.perf_counter()
    res = cluster.run([str(BIN / "volcap"), "run", str(spec), "--segment-runs", mode, "--json"], timeout=3600)
    wall = time.perf_counter() - t0
    return wall, json.loads(res.stdout.strip().splitlines()[-1])


def fan_out(tmp: Path, segments: int, workers: int, steps: int) -> dict:
    from volcap_core.synth import synthesize_capture

    capture = synthesize_capture(tmp / "cap", rig="demo_scene", seed=0, frames=segments, supersample=1).parent
    out: dict = {"segments": segments, "workers": workers}
    with moto_s3_server() as s3:
        cluster = Cluster(tmp, s3.env)
        try:
            store = s3.store_url()
            # the resolution and SH degree the figures of docs/benchmarks.md were measured at
            quality = {"preset": "test", "max_segment_frames": 1, "overlap": 0, "train_scale": 0.25, "sh_degree": 0}

            def spec(k: int) -> Path:
                return write_spec(tmp / f"spec{k}.yaml", "bench-fanout", capture, store, segments,
                                  {**quality, "train_steps": steps + k})

            # the first run needs no server: keep it off the clock of the server's start
            cluster.env.pop("PREFECT_API_URL")
            out["first_run_local_s"], first = timed_run(cluster, spec(0), "local")
            out["segments_planned"] = sum(k.startswith("train-segment:") for k in first["steps"])
            out["segments_local_s"], _ = timed_run(cluster, spec(1), "local")
            out["cached_rerun_local_s"], again = timed_run(cluster, spec(1), "local")
            assert again["tasks_run"] == 0, again
            cluster.env["PREFECT_API_URL"] = f"http://127.0.0.1:{cluster.port}/api"
            t0 = time.perf_counter()
            set_up_studio(cluster, gpus=workers)
            start_gpu_workers(cluster, [f"w{i}" for i in range(workers)])
            out["studio_setup_s"] = time.perf_counter() - t0
            out["segments_deployment_s"], dep = timed_run(cluster, spec(2), "deployment")
            assert dep["segment_runs"] == "deployment", dep
            out["cached_rerun_deployment_s"], again = timed_run(cluster, spec(2), "deployment")
            assert again["tasks_run"] == 0, again
            out["overhead_per_segment_s"] = (out["segments_deployment_s"] - out["segments_local_s"]) / segments
        finally:
            cluster.stop()
    return out


def demo_production(tmp: Path) -> dict:
    from volcap_core.synth import synthesize_capture

    capture = synthesize_capture(tmp / "demo", rig="demo_scene", seed=0).parent
    spec = write_spec(tmp / "demo.yaml", "demo", capture, str(tmp / "demo-store"), 8, "test")
    cluster = Cluster(tmp, {})
    cluster.env.pop("PREFECT_API_URL")
    out = {}
    out["first_run_s"], first = timed_run(cluster, spec, "local")
    out["segments"] = sum(k.startswith("train-segment:") for k in first["steps"])
    out["cached_rerun_s"], again = timed_run(cluster, spec, "local")
    out["cached_rerun_tasks"] = again["tasks_cached"]
    assert again["tasks_run"] == 0, again
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--segments", type=int, default=6)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--skip-demo", action="store_true")
    ap.add_argument("--only-demo", action="store_true", help="only the demo production's first run and rerun")
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"load {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory(prefix="volcap-bench-prod-") as tmp:
        res = {}
        if not args.only_demo:
            res["fan_out"] = fan_out(Path(tmp) / "fan", args.segments, args.workers, args.steps)
            print_fan_out(res["fan_out"], args)
        if not args.skip_demo:
            res["demo"] = demo_production(Path(tmp) / "demo")
            d = res["demo"]
            print(f"demo production ({d['segments']} segments): first run {d['first_run_s']:.1f} s, cached rerun "
                  f"{d['cached_rerun_s']:.1f} s ({d['cached_rerun_tasks']} tasks cached)")
        print(f"load after: {os.getloadavg()[0]:.1f}")
        print(json.dumps(res))


def print_fan_out(f: dict, args) -> None:
    print(f"fan-out, {f['segments_planned']} segments x {args.steps}+ steps, {args.workers} workers:")
    print(f"  first run (in-process, everything)   {f['first_run_local_s']:7.1f} s")
    print(f"  segments in-process                  {f['segments_local_s']:7.1f} s")
    print(f"  segments through server + workers    {f['segments_deployment_s']:7.1f} s "
          f"(studio set-up {f['studio_setup_s']:.1f} s, not included)")
    print(f"  overhead per segment                 {f['overhead_per_segment_s']:7.1f} s")
    print(f"  cached rerun: in-process {f['cached_rerun_local_s']:.1f} s, "
          f"through the server {f['cached_rerun_deployment_s']:.1f} s")


if __name__ == "__main__":
    main()
