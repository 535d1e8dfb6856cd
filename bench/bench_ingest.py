"""Ingest at realistic frame sizes against a bare decode, and what a fully cached rerun costs.

    python bench/bench_ingest.py [--quick] [--sizes 1920x1080,3840x2160] [--cameras 16] [--frames 10]
                                 [--repeat 2] [--skip-demo | --only-demo] [--work DIR]

Everything in one run, side by side, on one machine state:

1. Synthetic captures at each size (``--cameras`` static cameras of the Scene Rig x ``--frames``
   frames, half-float RGBA, ZIP, as cameras write them). ``volcap_core.synth`` renders the scene at
   960x540 once (a 4K render costs ~20 s a frame); each frame is then resized to the capture's size,
   the low 4 mantissa bits of every colour sample are replaced by seeded noise (a sensor's noise:
   without it the upscaled pictures compress far better than footage does) and an alpha of 1 is
   added. The rig is the chosen cameras at the capture's resolution.
2. The baseline, per size: a bare ``OpenEXR.File`` decode of every frame (every channel's pixels)
   plus one ``ArtifactStore.put_file`` of the same file's bytes into an empty store.
3. The ingest flow on the same files, in this process, against a ``prefect server`` this benchmark
   starts (``tests/prefect_cluster.py``): the first run (fingerprint, checks, restamp or convert, decode,
   store put; one Prefect task run per camera and step), then a fully cached rerun.
4. ``volcap ingest`` of the same capture as a command (a new process: imports, the flow, exit)
   against that server, cached: at least 3 runs, median and spread. The same for the demo capture.
5. The per-frame breakdown of ingest's conversion (cProfile of two cameras, one thread): header
   probe, the fingerprint's BLAKE3 pass and the unchanged check's (on the bytes read once), the
   structure check and restamp of a plain frame, its decode and NaN check; for frames that are
   converted instead, linearise, working primaries, windows and encode; the store put. Rows the
   run never reached are left out.
6. The demo (``--skip-demo`` leaves it out, ``--only-demo`` runs only it): ``volcap synth`` of the
   demo capture (timed apart), then ``volcap demo`` on it without a server (what ``make demo``
   does: a temporary Prefect API, its database migrated beforehand as on any machine past its first
   command), then cached reruns without and with the server.

Prints the three figures the cache issue asks for: cached demo rerun / first run (target <= 5 %),
a cached ``volcap ingest`` of the demo capture against a running server (target < 3 s), and
ingest / (decode + put) at each size (target <= 1.5x); then one JSON object with everything.
``--quick``: 4 cameras x 3 frames, one repeat, no demo (a smoke test: ~2 min).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import platform
import pstats
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
for k, v in {"DO_NOT_TRACK": "1", "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "PREFECT_LOGGING_LEVEL": "WARNING",
             "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}.items():
    os.environ.setdefault(k, v)

RENDER_SIZE = (960, 540)
VOLCAP = [sys.executable, "-m", "flows.cli"]


# ---------------------------------------------------------------------------------------------
# Synthetic captures at realistic sizes
# ---------------------------------------------------------------------------------------------


def _rig_doc(cameras: int, size: tuple[int, int]) -> dict:
    """The Scene Rig cut to ``cameras`` static cameras spread around it, sensors at ``size``."""
    doc = json.loads((REPO / "hardware" / "rigs" / "scene_rig.json").read_text())
    static = [c for c in doc["cameras"] if c["role"] == "static"]
    picked = [static[(i * len(static)) // cameras] for i in range(cameras)]
    for c in picked:
        c["sensor"]["width_px"], c["sensor"]["height_px"] = size
    doc["cameras"] = picked
    doc["name"] = f"bench-{cameras}cam"
    return doc


def render_source(work: Path, cameras: int, frames: int) -> Path:
    """The scene rendered once at RENDER_SIZE (the captures are resized from it)."""
    from volcap_core.synth import synthesize_capture

    rig = work / "render-rig.json"
    rig.write_text(json.dumps(_rig_doc(cameras, RENDER_SIZE)))
    return synthesize_capture(work / "render", rig=str(rig), seed=0, frames=frames, supersample=1).parent


def _resize_frame(job: tuple[str, str, int, int, int]) -> int:
    """One frame: resize, sensor-noise bits, alpha 1, half RGBA ZIP; returns the file's bytes."""
    import io

    import cv2
    import numpy as np
    import OpenEXR

    from volcap_core.files import write_atomic
    from volcap_core.synth.io import read_exr

    src, dst, width, height, seed = job
    rgb = cv2.resize(read_exr(Path(src)), (width, height), interpolation=cv2.INTER_LINEAR)
    half = np.ascontiguousarray(rgb.astype(np.float16))
    bits = half.view(np.uint16)
    noise = np.frombuffer(np.random.default_rng(seed).bytes(bits.size), np.uint8).reshape(bits.shape)
    bits ^= (noise & 0x0F).astype(np.uint16)
    channels = {c: np.ascontiguousarray(half[..., i]) for i, c in enumerate("RGB")}
    channels["A"] = np.ones((height, width), np.float16)
    out = io.BytesIO()
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(out)
    write_atomic(Path(dst), out.getvalue())
    return len(out.getvalue())


def make_capture(source: Path, out: Path, size: tuple[int, int], cameras: int) -> Path:
    """A capture folder at ``size`` made from the rendered source (same layout, same take)."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(source, out, ignore=shutil.ignore_patterns("*.exr"))
    (out / "rig.json").write_text(json.dumps(_rig_doc(cameras, size)))
    jobs = []
    for i, src in enumerate(sorted((source / "frames").rglob("*.exr"))):
        dst = out / src.relative_to(source)
        dst.parent.mkdir(parents=True, exist_ok=True)
        jobs.append((str(src), str(dst), size[0], size[1], 1000 + i))
    # spawn: this process may hold threads (never fork under them); 2 workers for the 2 cores
    with ProcessPoolExecutor(max_workers=min(2, os.cpu_count() or 1), mp_context=get_context("spawn")) as pool:
        list(pool.map(_resize_frame, jobs))
    return out


def frame_files(capture: Path) -> list[Path]:
    """The files ingest converts: every camera's frames of the take (not the frames some cameras
    recorded before it, which ingest leaves out and the baseline must not count)."""
    from volcap_core import ingest
    from volcap_core.capture import CaptureFolder

    folder = CaptureFolder.open(capture.resolve())
    desc = folder.description
    return [f.path for c in desc.cameras for f in ingest.select_take(desc, c, folder.frame_files(c.id))[0]]


def warm(files: list[Path]) -> None:
    """Read every file once, so both sides of a comparison start from the page cache."""
    for f in files:
        with open(f, "rb") as fh:
            while fh.read(16 << 20):
                pass


# ---------------------------------------------------------------------------------------------
# The measurements
# ---------------------------------------------------------------------------------------------


def bare_decode_and_put(files: list[Path], store_dir: Path) -> dict:
    """Decode every channel of every frame with OpenEXR, and put each file's bytes in a store once."""
    import OpenEXR

    from volcap_core.store import ArtifactStore

    if store_dir.exists():
        shutil.rmtree(store_dir)
    store = ArtifactStore(str(store_dir))
    decode = put = 0.0
    for f in files:
        t0 = time.perf_counter()
        with OpenEXR.File(str(f)) as exr:
            for ch in exr.channels().values():
                _ = ch.pixels
        t1 = time.perf_counter()
        store.put_file(f)
        put += time.perf_counter() - t1
        decode += t1 - t0
    shutil.rmtree(store_dir)
    return {"decode_s": decode, "put_s": put, "total_s": decode + put}


def ingest_in_process(capture: Path, store_dir: Path) -> dict:
    """The ingest flow, first run then fully cached, in this process (the benchmark's server)."""
    from flows.ingest import ingest_flow
    from flows.runtime import run_flow

    if store_dir.exists():
        shutil.rmtree(store_dir)
    first = run_flow(ingest_flow, store=str(store_dir), capture_dir=str(capture))
    cached = run_flow(ingest_flow, store=str(store_dir), capture_dir=str(capture))
    assert cached.tasks_run == 0 and cached.result == first.result, (cached.counts(), first.counts())
    return {"first_s": first.wall_s, "first_tasks_run": first.tasks_run, "cached_s": cached.wall_s,
            "cached_tasks": cached.tasks_cached, "capture": first.result.digest}


def cli_runs(args: list[str], env: dict, repeat: int, pause_s: float = 1.0) -> list[tuple[float, dict]]:
    """(wall seconds, --json object) of ``volcap ARGS`` as a new process, ``repeat`` times (a pause
    before each run lets the server finish recording the previous one, as between a coordinator's
    commands)."""
    runs = []
    for _ in range(repeat):
        time.sleep(pause_s)
        t0 = time.perf_counter()
        res = subprocess.run([*VOLCAP, *args, "--json"], cwd=REPO, env=env, capture_output=True, text=True,
                             timeout=7200)
        wall = time.perf_counter() - t0
        if res.returncode != 0:
            raise RuntimeError(f"volcap {' '.join(args)} -> {res.returncode}\n{res.stdout[-2000:]}\n{res.stderr[-2000:]}")
        runs.append((wall, json.loads(res.stdout.strip().splitlines()[-1])))
    return runs


def spread(xs: list[float]) -> dict:
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": [round(x, 3) for x in xs]}


#: What ingest spends a frame on, by the function that does it (cProfile's cumulative time): label ->
#: candidates (caller or None, function); the first candidate the code has counts, so a renamed or
#: removed function is simply absent from the table.
BREAKDOWN: tuple[tuple[str, tuple[tuple[str | None, str], ...]], ...] = (
    ("header probe (flow checks)", ((None, "check_headers"),)),
    ("hash pass 1 (fingerprint)", (("fingerprint", "digest_file"),)),
    ("hash pass 2 (unchanged check)", (("convert_frame", "digest_bytes"), ("convert_frame", "digest_file"))),
    ("read the file (once)", (("convert_frame", "read_bytes"),)),
    ("structure check + restamp", ((None, "plain_frame_header"), (None, "restamp_exr"))),
    ("decode", ((None, "decode_half_exr"), (None, "read_footage"), (None, "read_image"))),
    ("NaN/Inf check (half bits)", ((None, "half_nonfinite_pixels"),)),
    ("linearise", ((None, "to_scene_linear"),)),
    ("NaN/Inf check", ((None, "apply_nan_policy"),)),
    ("working primaries", ((None, "to_working_primaries"),)),
    ("windows (visible, display)", ((None, "visible_pixels"), (None, "in_display_window"))),
    ("encode (half, ZIP; converted frames only)", ((None, "encode_exr"),)),
    ("store put (hash, write, fsync)", ((None, "put_bytes"),)),
)


def _cumulative(stats: dict, caller: str | None, name: str) -> float:
    total = 0.0
    for (file, _line, fn), (_cc, _nc, _tt, ct, callers) in stats.items():
        if fn != name:
            continue
        if caller is None:  # our own function, anywhere
            total += ct if file.startswith(str(REPO)) else 0.0
        else:  # any function (a library's too) as called by our ``caller``
            total += sum(v[3] for c, v in callers.items() if c[2] == caller and c[0].startswith(str(REPO)))
    return total


def per_frame_breakdown(capture: Path, store_dir: Path, cameras: int = 2) -> dict:
    """cProfile of ingest's per-frame work on ``cameras`` cameras, in one thread; seconds a frame."""
    from volcap_core import ingest
    from volcap_core.capture import CaptureFolder
    from volcap_core.records import MEDIA_EXR
    from volcap_core.store import ArtifactStore

    if store_dir.exists():
        shutil.rmtree(store_dir)
    store = ArtifactStore(str(store_dir))
    folder = CaptureFolder.open(capture.resolve())
    desc = folder.description
    rig_cams, _ = ingest.match_rig(desc, folder.rig)
    prof = cProfile.Profile()
    n, wall = 0, 0.0
    for cam in desc.cameras[:cameras]:
        scan, _ = ingest.select_take(desc, cam, folder.frame_files(cam.id))
        t0 = time.perf_counter()
        prof.enable()
        ingest.check_headers(cam, rig_cams[cam.id], scan)
        entries = ingest.fingerprint(scan)
        ingest.convert_camera(cam, rig_cams[cam.id], entries, desc.take_offset(cam), desc.take.frame_count,
                              ocio_config=None, nan_policy="error", lens=None,
                              put_frame=lambda data: store.put_bytes(data, MEDIA_EXR))
        prof.disable()
        wall += time.perf_counter() - t0
        n += len(scan)
    shutil.rmtree(store_dir)
    stats = pstats.Stats(prof).stats  # {(file, line, name): (cc, nc, tt, ct, callers)}
    rows: dict[str, float] = {}
    for label, candidates in BREAKDOWN:
        for caller, name in candidates:
            if (t := _cumulative(stats, caller, name)) > 0:
                rows[label] = rows.get(label, 0.0) + t / n
                if label != "windows (visible, display)":
                    break
    rows["other (profiled total - above)"] = max(0.0, wall / n - sum(rows.values()))
    return {"frames": n, "wall_per_frame_s": wall / n, "per_frame_s": rows}


# ---------------------------------------------------------------------------------------------
# The demo
# ---------------------------------------------------------------------------------------------


def demo_runs(work: Path, server_env: dict, repeat: int) -> dict:
    no_server = {k: v for k, v in server_env.items() if k != "PREFECT_API_URL"}
    no_server["PREFECT_HOME"] = str(work / "demo-prefect-home")  # a temporary API each run, own database
    out, store = work / "demo", work / "demo-store"
    # the temporary API's database migrated beforehand, as on any machine past its first command
    subprocess.run([sys.executable, "-m", "prefect", "server", "database", "upgrade", "-y"], cwd=REPO,
                   env=no_server, check=True, capture_output=True, timeout=600)
    t0 = time.perf_counter()
    subprocess.run([*VOLCAP, "synth", str(out / "capture"), "--depth"], cwd=REPO, env=no_server, check=True,
                   capture_output=True, timeout=3600)
    synth_s = time.perf_counter() - t0
    [(first_s, first)] = cli_runs(["demo", "--store", str(store), "--out", str(out)], no_server, 1, pause_s=0)
    assert first["tasks_run"] > 0, first
    cached = cli_runs(["demo", "--store", str(store), "--out", str(out)], no_server, repeat)
    against = cli_runs(["demo", "--store", str(store), "--out", str(out)], server_env, repeat)
    for _, doc in cached + against:
        assert doc["tasks_run"] == 0 and doc["segment"] == first["segment"], doc
    ingest_cli = cli_runs(["ingest", str(out / "capture"), "--store", str(store)], server_env, max(repeat, 3))
    return {"synth_s": synth_s, "first_s": first_s, "first_flow_s": first["wall_s"], "first_tasks": first["tasks_run"],
            "cached_temporary_api_s": spread([w for w, _ in cached]),
            "cached_temporary_api_flow_s": spread([d["wall_s"] for _, d in cached]),
            "cached_server_s": spread([w for w, _ in against]),
            "cached_server_flow_s": spread([d["wall_s"] for _, d in against]),
            "cached_tasks": cached[0][1]["tasks_cached"],
            "ingest_cli_cached_server_s": spread([w for w, _ in ingest_cli]),
            "ingest_cli_cached_flow_s": spread([d["wall_s"] for _, d in ingest_cli])}


# ---------------------------------------------------------------------------------------------


def parse_size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="1920x1080,3840x2160")
    ap.add_argument("--cameras", type=int, default=16)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=2, help="repeats of each comparison and of each cached command")
    ap.add_argument("--quick", action="store_true", help="4 cameras x 3 frames, one repeat, no demo")
    ap.add_argument("--skip-demo", action="store_true")
    ap.add_argument("--only-demo", action="store_true")
    ap.add_argument("--work", type=Path, help="keep the captures and stores here (default: a temporary folder)")
    args = ap.parse_args()
    if args.quick:
        args.cameras, args.frames, args.repeat, args.skip_demo = 4, 3, 1, True
    sizes = [parse_size(s) for s in args.sizes.split(",") if s]

    from tests.prefect_cluster import Cluster

    work = args.work or Path(tempfile.mkdtemp(prefix="volcap-bench-ingest-"))
    work.mkdir(parents=True, exist_ok=True)
    res: dict = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs",
                 "load_before": os.getloadavg()[0], "cameras": args.cameras, "frames": args.frames}
    print(f"machine: {res['machine']}, load {res['load_before']:.1f}; work in {work}", flush=True)
    captures = {}
    if not args.only_demo:
        t0 = time.perf_counter()
        source = render_source(work, args.cameras, args.frames)
        res["render_s"] = time.perf_counter() - t0
        for size in sizes:
            t0 = time.perf_counter()
            captures[size] = make_capture(source, work / f"capture-{size[0]}x{size[1]}", size, args.cameras)
            print(f"capture {size[0]}x{size[1]}: {len(frame_files(captures[size]))} frames, "
                  f"{sum(f.stat().st_size for f in frame_files(captures[size])) / 1e9:.2f} GB, made in "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)

    cluster = Cluster(work, {})
    cluster.start_server()
    server_env = {**cluster.env, "PREFECT_LOGGING_LEVEL": "WARNING"}
    os.environ["PREFECT_API_URL"] = cluster.env["PREFECT_API_URL"]  # before this process imports prefect
    os.environ["PREFECT_HOME"] = cluster.env["PREFECT_HOME"]
    try:
        res["sizes"] = {}
        for size, capture in captures.items():
            name = f"{size[0]}x{size[1]}"
            files = frame_files(capture)
            r: dict = {"frames": len(files), "bytes": sum(f.stat().st_size for f in files), "bare": [], "ingest": []}
            for _ in range(args.repeat):  # side by side, alternating
                warm(files)
                r["bare"].append(bare_decode_and_put(files, work / "bare-store"))
                warm(files)
                r["ingest"].append(ingest_in_process(capture, work / f"store-{name}"))
            r["cli_cached"] = spread([w for w, _ in cli_runs(["ingest", str(capture), "--store",
                                                               str(work / f"store-{name}")], server_env,
                                                              max(args.repeat, 3))])
            r["breakdown"] = per_frame_breakdown(capture, work / "breakdown-store")
            shutil.rmtree(work / f"store-{name}", ignore_errors=True)
            ratios = [i["first_s"] / b["total_s"] for b, i in zip(r["bare"], r["ingest"])]
            r["ratio_ingest_over_decode_put"] = spread(ratios)
            res["sizes"][name] = r
            print_size(name, r, args.cameras)
        if not args.skip_demo:
            res["demo"] = demo_runs(work, server_env, args.repeat)
            print_demo(res["demo"])
    finally:
        cluster.stop()
    res["load_after"] = os.getloadavg()[0]
    print_summary(res)
    print(json.dumps(res, default=str))
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


def print_size(name: str, r: dict, cameras: int) -> None:
    n = r["frames"]
    print(f"\n{name}: {n} frames ({cameras} cameras), {r['bytes'] / n / 1e6:.1f} MB a frame")
    for b, i in zip(r["bare"], r["ingest"]):
        print(f"  bare decode {b['decode_s']:.1f} s + put {b['put_s']:.1f} s = {b['total_s']:.1f} s "
              f"({n / b['total_s']:.1f} frames/s) | ingest first run {i['first_s']:.1f} s "
              f"({n / i['first_s']:.1f} frames/s, {i['first_tasks_run']} tasks) -> "
              f"{i['first_s'] / b['total_s']:.2f}x | cached rerun in-process {i['cached_s']:.2f} s")
    c = r["cli_cached"]
    print(f"  cached `volcap ingest` against the server: median {c['median']:.2f} s ({c['min']:.2f}-{c['max']:.2f})")
    bd = r["breakdown"]
    print(f"  per frame, one thread ({bd['frames']} frames, {bd['wall_per_frame_s']:.3f} s a frame):")
    for label, s in bd["per_frame_s"].items():
        print(f"    {label:34s} {s * 1000:8.1f} ms")


def print_demo(d: dict) -> None:
    print(f"\ndemo: synth {d['synth_s']:.1f} s; `volcap demo` first run {d['first_s']:.1f} s (flow {d['first_flow_s']:.1f} s, "
          f"{d['first_tasks']} tasks)")
    for label, key in (("cached, temporary API", "cached_temporary_api"), ("cached, against the server", "cached_server")):
        w, f = d[f"{key}_s"], d[f"{key}_flow_s"]
        print(f"  {label:28s} {w['median']:6.2f} s (runs {w['runs']}), flow {f['median']:.2f} s")
    c = d["ingest_cli_cached_server_s"]
    print(f"  cached `volcap ingest` of the demo capture against the server: median {c['median']:.2f} s "
          f"(runs {c['runs']}), flow {d['ingest_cli_cached_flow_s']['median']:.2f} s")


def print_summary(res: dict) -> None:
    print("\nthe three figures (targets in brackets):")
    d = res.get("demo")
    if d:
        print(f"  cached demo rerun / first run     {100 * d['cached_temporary_api_s']['median'] / d['first_s']:5.1f} %  "
              f"(<= 5 %; against a server {100 * d['cached_server_s']['median'] / d['first_s']:.1f} %; flow to flow "
              f"{100 * d['cached_temporary_api_flow_s']['median'] / d['first_flow_s']:.1f} %)")
        print(f"  cached `volcap ingest`, demo      {d['ingest_cli_cached_server_s']['median']:5.2f} s  (< 3 s)")
    for name, r in res.get("sizes", {}).items():
        x = r["ratio_ingest_over_decode_put"]
        print(f"  ingest / (decode + put), {name:9s} {x['median']:5.2f} x  (<= 1.5 x; runs {x['runs']})")


if __name__ == "__main__":
    main()
