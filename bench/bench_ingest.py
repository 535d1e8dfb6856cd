"""Ingest throughput against a bare OpenEXR decode, and a fully cached rerun against the first run.

    python bench/bench_ingest.py [--capture DIR] [--frames N]

Without ``--capture`` it renders the demo capture (demo_scene rig) into a temporary folder.
Prints frames/s of the ingest flow (fingerprint + checks + decode + linearise + half EXR encode +
store put, through Prefect) and of a bare ``OpenEXR.File`` decode of the same files, their ratio,
and the wall time of a second, fully cached run.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")


def bare_decode(files: list[Path]) -> float:
    import OpenEXR

    t0 = time.perf_counter()
    for f in files:
        with OpenEXR.File(str(f)) as exr:
            for ch in exr.channels().values():
                _ = ch.pixels
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--capture", type=Path)
    ap.add_argument("--frames", type=int, default=24)
    args = ap.parse_args()

    from prefect.testing.utilities import prefect_test_harness

    from flows.ingest import ingest_flow
    from flows.runtime import run_flow
    from volcap_core.store import ArtifactStore

    work = Path(tempfile.mkdtemp(prefix="volcap-bench-ingest-"))
    capture = args.capture
    if capture is None:
        from volcap_core.synth import synthesize_capture

        t0 = time.perf_counter()
        capture = synthesize_capture(work / "capture", rig="demo_scene", seed=0, frames=args.frames).parent
        print(f"rendered demo capture in {time.perf_counter() - t0:.1f} s")
    files = sorted(p for p in capture.rglob("*.exr") if "ground_truth" not in p.parts)
    megapixels = 0.0
    import OpenEXR
    for f in files[:1]:
        with OpenEXR.File(str(f)) as exr:
            w, h = exr.header()["dataWindow"][1] + 1
            megapixels = w * h / 1e6

    bare = min(bare_decode(files) for _ in range(3))
    store = ArtifactStore(str(work / "store"))
    with prefect_test_harness(server_startup_timeout=120):
        first = run_flow(ingest_flow, store=store.url, capture_dir=str(capture))
        cached = run_flow(ingest_flow, store=store.url, capture_dir=str(capture))
    n = len(files)
    print(f"\n{n} frames of {megapixels:.3f} MP, 2-core CPU")
    print(f"{'measure':42s} {'value':>12s}")
    print(f"{'bare OpenEXR decode (frames/s)':42s} {n / bare:12.1f}")
    print(f"{'ingest flow, first run (frames/s)':42s} {n / first.wall_s:12.1f}")
    print(f"{'ratio ingest / bare decode':42s} {(n / first.wall_s) / (n / bare):12.3f}")
    print(f"{'first run wall (s)':42s} {first.wall_s:12.2f}   ({first.tasks_run} tasks run)")
    print(f"{'cached rerun wall (s)':42s} {cached.wall_s:12.2f}   ({cached.tasks_cached} cached, {cached.tasks_run} run)")
    print(f"{'cached / first':42s} {cached.wall_s / first.wall_s:12.3f}")


if __name__ == "__main__":
    main()
