"""The close-up benchmark (issue 27): the demo's product at a size where an enhancer learns on a CPU.

    python bench/bench_closeup.py --workdir W --json out.json --sheet docs/img/closeup.png   # about an hour+
    python bench/bench_closeup.py --quick         # smoke run (< 3 min): the whole path, numbers meaningless

What runs is the demo's close-up stage (``flows/demo.py`` ``closeup_production``: a Face Rig capture
of the Scene Rig actor 0, a production spec, the production flow on the reconstruction's cached
segment, the truth, the ``score-shot`` scores and sheet) on a bigger capture, so that the figures
are about an enhancer that has learned:

* the Scene Rig capture: ``demo_scene`` with every camera's pixel grid ``render_scale`` times finer
  (``bench_enhance.scaled_rig``; the full run 2: 640×360 static and tracking cameras, as the enhancer
  bench's Face Rig), ``frames`` take frames, reconstructed as the demo reconstructs its own (the
  estimated calibration, one segment of every frame, the ``preset``'s training);
* the Face Rig capture: ``demo_face`` scaled the same way (640×360), of the Scene Rig's actor 0
  (``actor_of``): the enhancer bench's Face Rig with the Face Rig actor the Scene Rig actor;
* the enhancer: ``ENHANCER_RUNS[enhancer]`` over the preset, the full run ``long``: the enhancer
  bench's recipe through a production's preset fields (``small()``; 3000 VAE steps then its two
  lower-rate stages; 12 000 transformer steps on 128-px crops with its warm-up and rate drop; 8
  sampling steps on 128-px tiles; 256-px head windows of the Face Rig frames:
  ``docs/enhancer.md``, "The demo's close-up");
* the shot: the demo's close-up (65 mm, 1.5 m, aimed at the head), its width where its pixels on
  the head are no finer than the finest footage's (twice the demo's at twice the pixels).

Figures: the ``score-shot`` rows (render, enhanced, and the empty and bicubic floors) on the face
and the performers (PSNR, SSIM, detail), flicker and warp error per row and of the truth, and the
wall time of each stage. ``--quick``: 4 frames of the demo rig's static cameras at 320×180, the
``test`` preset and the ``demo`` enhancer run: it exercises every step, its numbers mean nothing.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

FULL = {"render_scale": 2, "frames": 8, "cameras": None, "supersample": 2, "preset": "demo", "enhancer": "long"}
QUICK = {"render_scale": 1, "frames": 4, "cameras": [f"S00{i}" for i in range(8)], "supersample": 1,
         "preset": "test", "enhancer": "demo"}


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def run(workdir: Path, settings: dict) -> dict:
    """Synthesize (or reuse) the Scene Rig capture, then reconstruct it and run the close-up
    stage in one flow run; returns the stage's result with the settings and wall times."""
    from prefect import flow

    from bench_enhance import scaled_rig
    from flows.demo import closeup_production
    from flows.ingest import ingest_flow
    from flows.reconstruct import reconstruct_flow
    from flows.runtime import run_flow
    from volcap_core.store import ArtifactStore
    from volcap_core.synth import synthesize_capture

    scale = settings["render_scale"]
    scene_rig = scaled_rig(workdir / "rigs", "demo_scene", scale)
    face_rig = scaled_rig(workdir / "rigs", "demo_face", scale)
    capture_dir = workdir / "scene"
    walls: dict[str, float] = {}
    t0 = time.perf_counter()
    if not (capture_dir / "capture.json").exists():
        _log(f"synthesizing the Scene Rig capture ({settings['frames']} frames, x{scale} pixels)")
        synthesize_capture(capture_dir, rig=str(scene_rig), seed=0, frames=settings["frames"],
                           supersample=settings["supersample"], cameras=settings["cameras"])
    walls["scene_capture_s"] = time.perf_counter() - t0
    store = ArtifactStore(str(workdir / "store")).url
    out = workdir / "out"
    out.mkdir(parents=True, exist_ok=True)

    @flow(name="bench-closeup", persist_result=False)
    def bench_closeup() -> dict:
        t = time.perf_counter()
        capture = ingest_flow(store=store, capture_dir=str(capture_dir))
        recon = reconstruct_flow(store=store, capture=capture.digest, frames=(0, settings["frames"]),
                                 preset=settings["preset"])
        segment = ArtifactStore(store).resolve(recon["segments"][0]["model"]["digest"])
        walls["reconstruct_s"] = time.perf_counter() - t
        _log(f"reconstructed: held-out {recon['segments'][0]['held_out_psnr']} dB; the close-up stage")
        return {**closeup_production(store, capture_dir, out, capture_ref=capture, segment_ref=segment,
                                     preset=settings["preset"], enhancer=settings["enhancer"], face_rig=face_rig),
                "held_out_psnr": recon["segments"][0]["held_out_psnr"]}

    t0 = time.perf_counter()
    summary = run_flow(bench_closeup)
    walls["flow_s"] = time.perf_counter() - t0
    return {**summary.result, "settings": settings, "bench_wall_s": {k: round(v, 1) for k, v in walls.items()},
            "tasks": summary.counts()}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run (< 3 min): every step, numbers meaningless")
    ap.add_argument("--workdir", type=Path, help="captures, store and outputs (kept; reused on a rerun)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--sheet", type=Path, help="copy the close-up sheet (PNG) here")
    args = ap.parse_args(argv)
    settings = dict(QUICK if args.quick else FULL)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench-closeup-"))
    t0 = time.perf_counter()
    result = run(workdir, settings)
    result["total_s"] = round(time.perf_counter() - t0, 1)
    result["machine"] = {"platform": platform.platform(), "python": platform.python_version()}
    if args.sheet:
        args.sheet.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(result["sheet"], args.sheet)
    for region in ("face", "performers"):
        _log(f"{region}: " + "; ".join(f"{row} {f['psnr']} dB / SSIM {f['ssim']} / detail {f['detail']}"
                                        for row, f in result[region].items()))
    _log("temporal (flickering, warp error): " + "; ".join(
        f"{row} {v['flickering']}, {v['warp_error']}" for row, v in result["temporal"].items()))
    _log(result["enhancer_budget"])
    _log(f"sheet {result['sheet']}; {result['total_s']} s in all ({result['bench_wall_s']}; the stage: "
         f"{result['wall_s']})")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, sort_keys=True, default=str))
    return result


if __name__ == "__main__":
    main()
