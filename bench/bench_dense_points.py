"""Dense points' memory and time: one frame of the ``dense-points-frame`` task's step on a synthetic
rig of 14 static cameras and on the real Pose2Sim capture.

    python bench/bench_dense_points.py synthetic [--width 640] [--references N] [--json out.json]
    python bench/bench_dense_points.py pose2sim [--scale 1.0] [--references N] [--json out.json]

Why: issue 30's target, 14 cameras at 640x360 within 4 GB and <= 2 minutes a frame on 2 cores, and
the memory model of docs/calibration.md ("Dense points: memory and time") checked by measurement.

- ``synthetic``: a rig written here with ``hardware/make_rigs.py``'s conventions (``demo_scene``'s
  sensor and 14 mm lens, its 175-degree arc in front of the stage 5.5 m from the centre, alternating
  1.3 m / 2.5 m high) with 14 static cameras ``--width`` wide at 16:9 (640: 13.5 degrees apart),
  one frame rendered by ``synthesize_capture`` (two actors, no supersampling) and ingested; the
  cameras are the ground truth's (``synth.ground_truth.calibration``: no scene depths, so each
  camera sweeps the stage volume in its view).
- ``pose2sim``: ``../shared/data/real/pose2sim/Demo_SinglePerson``, 4 portrait cameras at
  1080x1920 (cam03/04 1088x1920), ``--frames`` frames of its MP4s ingested and its Qualisys
  calibration imported (``importers.calibration_from_qualisys``, frames fitted to the videos'
  sizes) on a rig written here (the Qualisys poses as mounts, a 4 x 4 x 2.5 m stage around the
  treadmill). ``--scale`` is the task's ``scale`` (0.5: a preset's ``dense_scale`` of 0.5).

Each measurement runs ``dense_points_step`` for one frame in a fresh child process with torch on
``--threads`` threads (2: the project's CPU machine) and reports its wall time, its peak resident
memory (:func:`peak_rss_mb`: the whole process, Python, torch and the libraries included;
``baseline_rss_mb`` is the same child's peak before the step), its CPU time (``cpu_s``, user +
system, and ``user_s``: on a machine shared with other jobs the wall time says more about them),
the load average, the points and the step's progress lines; on the synthetic frame also the points'
distance to the true surface (``metrics.point_errors``: the ground truth's scan and actors).
``--references N`` sweeps only the first N cameras as references (all
cameras still load and serve as neighbours): the per-reference time and the peak of a size whose
14 references would take too long here (1080p, 4K: ``--width 1920`` / ``3840``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

POSE2SIM = REPO.parent / "shared" / "data" / "real" / "pose2sim" / "Demo_SinglePerson"
for k, v in {"DO_NOT_TRACK": "1", "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
             "PREFECT_LOGGING_LEVEL": "WARNING"}.items():
    os.environ.setdefault(k, v)


def synthetic_rig(width: int = 640, cameras: int = 14) -> dict:
    """A rig of ``cameras`` static cameras ``width`` x ``width * 9 / 16`` px: ``demo_scene``'s static
    cameras (``hardware/make_rigs.py``: its sensor, 14 mm lens, 175-degree arc 5.5 m from the
    stage centre, alternating 1.3 / 2.5 m high, looking at (0, 0, 1.3)) spaced evenly over the arc."""
    from hardware.make_rigs import SENSOR_H_MM, SENSOR_W_MM, STATIC_LENS

    height = width * 9 // 16
    cams = []
    for k in range(cameras):
        az = math.radians(-87.5 + 175.0 * k / (cameras - 1))
        pos = [round(5.5 * math.cos(az), 4), round(5.5 * math.sin(az), 4), 1.3 if k % 2 == 0 else 2.5]
        cams.append({"id": f"S{k:03d}", "role": "static",
                     "lens": {"focal_min_mm": STATIC_LENS[0], "focal_max_mm": STATIC_LENS[1]},
                     "sensor": {"width_mm": SENSOR_W_MM, "height_mm": SENSOR_H_MM, "width_px": width,
                                "height_px": height},
                     "mount": {"kind": "tripod", "position_m": pos, "look_at_m": [0.0, 0.0, 1.3]},
                     "nominal_focal_mm": 14.0})
    return {"name": f"dense{cameras}_{width}", "kind": "scene", "fps": 24.0, "stage_size_m": [4.0, 4.0, 3.5],
            "cameras": cams, "lighting": {"description": "the demo rig's strobed white LED strips",
                                          "strobe_hz": 72.0, "flash_ms": 1.0, "led_panels": 0,
                                          "white_lights": 0}}


def _ingest(store: str, capture_dir: Path) -> str:
    from flows.ingest import ingest_flow
    from flows.runtime import run_flow

    return run_flow(ingest_flow, store=store, capture_dir=str(capture_dir)).result.digest


def prepare_synthetic(work: Path, width: int) -> dict:
    """Render (once per ``work``), ingest and store the ground-truth calibration; the child's inputs."""
    from volcap_core.capture import Capture
    from volcap_core.store import ArtifactStore
    from volcap_core.synth import ground_truth, synthesize_capture

    folder = work / f"synthetic_{width}"
    if not (folder / "capture.json").exists():
        folder.mkdir(parents=True, exist_ok=True)
        (work / f"rig_{width}.json").write_text(json.dumps(synthetic_rig(width), indent=1))
        synthesize_capture(folder, rig=str(work / f"rig_{width}.json"), seed=0, frames=1, supersample=1)
    store = ArtifactStore(str(work / "store")).url
    s = ArtifactStore(store)
    capture = _ingest(store, folder)
    cap = s.get_record(capture, Capture)
    cams_json = json.loads((folder / "ground_truth" / "cameras.json").read_text())
    record, _ = ground_truth.calibration(cams_json, cap.name, [c.id for c in cap.cameras], cap.rig.stage_size_m)
    return {"store": store, "capture": capture, "calibration": s.put_record(record).digest, "frame": 0,
            "ground_truth": str(folder / "ground_truth")}


#: Pose2Sim SinglePerson's frame sizes (cam01/cam02 re-encoded at 1080 wide)
POSE2SIM_SIZES = {"cam01": (1080, 1920), "cam02": (1080, 1920), "cam03": (1088, 1920), "cam04": (1088, 1920)}


def write_pose2sim_capture(root: Path, frames: int, start: int = 0):
    """SinglePerson as a capture folder at ``root`` (its MP4s linked, the rig written from its imported
    Qualisys calibration by ``rig_from_calibration`` as ``volcap import-calibration --write-rig`` does:
    the studio's lens as measured intrinsics, its poses as mounts, a 4 x 4 x 2.5 m stage around the
    treadmill, a take of ``frames`` frames from ``start``); returns the imported ``Calibration``."""
    from volcap_core.calibration.importers import calibration_from_qualisys
    from volcap_core.calibration.rig_from_calibration import rig_from_calibration

    if not POSE2SIM.is_dir():
        raise SystemExit(f"{POSE2SIM} is absent (the shared data)")
    xml = (POSE2SIM / "calibration" / "Calib.qca.txt").read_bytes()
    calib = calibration_from_qualisys(xml, "pose2sim", frames, 60.0, source="Calib.qca.txt",
                                      frame_sizes=POSE2SIM_SIZES, stage_size_m=(4.0, 4.0, 2.5))
    (root / "videos").mkdir(parents=True, exist_ok=True)
    for cid in POSE2SIM_SIZES:
        link = root / "videos" / f"{cid}.mp4"
        if not link.exists():
            link.symlink_to(POSE2SIM / "videos" / f"{cid}.mp4")
    rig = rig_from_calibration(calib, name="pose2sim", lighting="a lab's ceiling lights")
    (root / "rig.json").write_text(json.dumps(rig.model_dump(mode="json"), indent=1))
    (root / "capture.json").write_text(json.dumps({
        "format": "volcap-capture/1", "name": "pose2sim", "rig": "rig.json", "fps": 60,
        "take": {"start_timecode": f"01:00:00:{start:02d}", "frame_count": frames},
        "cameras": [{"id": c, "path": f"videos/{c}.mp4", "start_timecode": "01:00:00:00"} for c in POSE2SIM_SIZES]},
        indent=1))
    return calib


def prepare_pose2sim(work: Path, frames: int) -> dict:
    """Ingest ``frames`` frames of SinglePerson's MP4s and import its Qualisys calibration."""
    from volcap_core.store import ArtifactStore

    root = work / "pose2sim"
    calib = write_pose2sim_capture(root, frames)
    store = ArtifactStore(str(work / "store")).url
    capture = _ingest(store, root)
    return {"store": store, "capture": capture, "calibration": ArtifactStore(store).put_record(calib).digest,
            "frame": frames // 2}


def peak_rss_mb() -> float:
    """This process's peak resident memory (MiB): ``VmHWM`` of ``/proc/self/status``, which belongs
    to the process's own memory map (``getrusage``'s ``ru_maxrss`` keeps the parent's peak across
    fork and exec); ``ru_maxrss`` where there is no ``/proc``."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def child(inputs: dict, scale: float, references: int | None, threads: int) -> dict:
    """One frame's ``dense_points_step`` in this process: its wall time, peak RSS and progress."""
    import torch

    torch.set_num_threads(threads)
    from volcap_core.calibration.dense import DenseOptions
    from volcap_core.calibration.dense_points_step import dense_points_step
    from volcap_core.calibration.inputs import frame_loader
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture
    from volcap_core.store import ArtifactStore

    lines: list[str] = []

    def progress(done: int, total: int, info: dict) -> None:   # the task's progress line
        lines.append(f"camera {info['camera']} ({done}/{total}): {info['planes']} planes over "
                     f"{info['depth_m'][0]:.2f}-{info['depth_m'][1]:.2f} m, {info['pixels']} pixels with a depth, "
                     f"{info['seconds']:.0f} s so far ({resource.getrusage(resource.RUSAGE_SELF).ru_utime - cpu0:.0f} s CPU)")

    s = ArtifactStore(inputs["store"])
    cap = s.get_record(s.resolve(inputs["capture"]), Capture)
    calib = s.get_record(s.resolve(inputs["calibration"]), Calibration)
    base_rss = peak_rss_mb()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    cpu0 = r0.ru_utime
    t0 = time.perf_counter()
    out = dense_points_step(cap, calib, inputs["frame"], frame_loader(s.get_bytes, cap), DenseOptions(), scale,
                            references=(calib.static_ids[:references] if references else None), progress=progress)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu, sys_s = r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime
    accuracy = {}
    if inputs.get("ground_truth"):   # the synthetic frame: the points against the true surface
        from volcap_core.calibration.lidar import LidarScan
        from volcap_core.calibration.metrics import load_ground_truth, point_errors

        gt_dir = Path(inputs["ground_truth"])
        scan = LidarScan.from_ply_bytes((gt_dir / "lidar.ply").read_bytes())
        e = point_errors([(0, out.positions)], load_ground_truth(gt_dir), scan)["per_frame"]["0"]
        accuracy = {"median_distance_mm": round(1000 * e["median_distance_m"], 2),
                    "p90_distance_mm": round(1000 * e["p90_distance_m"], 1), "actor_points_3cm": e["actor_points_3cm"]}
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu + sys_s, 1), "user_s": round(cpu, 1), "load_average": round(os.getloadavg()[0], 1), "peak_rss_mb": round(peak_rss_mb()),
            "baseline_rss_mb": round(base_rss), "points": int(len(out.positions)), "cameras": len(out.cameras),
            "references": references or len(out.cameras), "threads": threads, **accuracy, "log": lines}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", choices=("synthetic", "pose2sim"))
    ap.add_argument("--width", type=int, default=640, help="synthetic: the cameras' width (16:9)")
    ap.add_argument("--frames", type=int, default=3, help="pose2sim: frames ingested (the middle one is swept)")
    ap.add_argument("--scale", type=float, default=1.0, help="the task's scale (matching resolution / footage)")
    ap.add_argument("--references", type=int, default=None, help="sweep only the first N cameras")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--workdir", type=Path, default=None, help="keep renders and the store here (reused)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--child", type=str, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(json.loads(args.child), args.scale, args.references, args.threads)))
        return
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench-dense-"))
    work.mkdir(parents=True, exist_ok=True)
    inputs = prepare_synthetic(work, args.width) if args.capture == "synthetic" else prepare_pose2sim(work, args.frames)
    cmd = [sys.executable, __file__, args.capture, "--scale", str(args.scale), "--threads", str(args.threads),
           "--child", json.dumps(inputs)] + (["--references", str(args.references)] if args.references else [])
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if res.returncode != 0:
        raise SystemExit(f"the measurement failed ({res.returncode}):\n{res.stderr[-3000:]}")
    out = {"capture": args.capture, "width": args.width if args.capture == "synthetic" else None,
           "scale": args.scale, **json.loads(res.stdout.strip().splitlines()[-1])}
    for line in out.pop("log"):
        print(line)
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
