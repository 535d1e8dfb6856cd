"""The demo's close-up at 1080p on the gsplat back-end (issue 27, "When a GPU is lent"), in three parts.

A GPU machine has no Prefect, pycolmap or OpenCV, and cannot rebuild the synthetic world the truth
is rendered from, so the work is split:

1. ``--prepare DIR`` (here, on CPU): from a finished demo (its store and output folder) export into
   ``DIR/gpu`` what the GPU needs: the close-up shot's JSON with its resolution raised (same path,
   same focal length in mm), the production's performance record and its segment models' bytes, the
   stage volume, the demo's trained enhancer (its safetensors and record) and the production's
   enhance settings (the ``enhance-shot`` step's parameters). The truth frames at the raised
   resolution (:func:`volcap_core.production.truth.render_truth_frames`) and the capture's
   ``scene.json`` go to ``DIR/truth`` and ``DIR/scene.json``: only the scoring reads them.
2. ``--run DIR --out OUT --device cuda`` (on the GPU machine; carry ``DIR/gpu`` only): every shot
   frame rendered through the gsplat back-end (:func:`volcap_core.production.shot.render_shot_frame`,
   with the exact flow), one frame through the torch back-end for the time, the frames enhanced as the
   production's ``enhance-shot`` task does (:func:`volcap_core.enhance.production.enhance_shot_frames`)
   with the model on ``--device``; each stage timed per frame. ``OUT``: ``closeup_exrs.tar``
   (``render/``, ``enhanced/``: the first frames, as many as ``--max-mib`` holds) in parts of
   15 MiB (``closeup_exrs.tar.00``, ...) and ``timings.json``.
3. ``--score DIR OUT`` (here): render and enhanced scored against the truth
   (:func:`volcap_core.production.closeup.score_shot_exrs`: face and performers beside the empty and
   bicubic floors), the sheet PNG and the scores JSON written to ``DIR/score``, a table printed.

    python bench/gpu_closeup.py --prepare .gpu --store /tmp/d1/store --demo /tmp/d1/demo
    OUT=/tmp/gpu GPU_CLOSEUP=.gpu bash bench/gpu_checks.sh      # on the GPU machine, carry .gpu/gpu
    python bench/gpu_closeup.py --score .gpu /path/to/OUT
"""

from __future__ import annotations

import argparse
import functools
import io
import json
import shutil
import sys
import tarfile
import time
from pathlib import Path

import torch

CLOSEUP = "closeup"
#: the size of each part of the returned tar (a device call brings back files of at most 16 MiB)
PART_BYTES = 15 * 2**20


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def prepare(dst: Path, store_url: str, demo: Path, width: int, height: int, frames: int | None,
            supersample: int) -> None:
    """Part 1 (module doc)."""
    from volcap_core.capture import Capture
    from volcap_core.enhance.production import EnhancerModel
    from volcap_core.production.performance import Performance
    from volcap_core.production.shot import load_shot
    from volcap_core.production.spec import load_spec
    from volcap_core.production.truth import render_truth_frames, truth_world_of
    from volcap_core.stage import stage_volume
    from volcap_core.store import ArtifactStore

    spec_path = demo / "production.yaml"
    if not spec_path.is_file():
        raise SystemExit(f"{spec_path}: no production spec (is {demo} a finished demo's output folder?)")
    spec = load_spec(spec_path)
    shots = {sh.name: sh for sh in spec.shots}
    if CLOSEUP not in shots:
        raise SystemExit(f"{spec_path}: no shot named {CLOSEUP!r}")
    shot_json = dict(shots[CLOSEUP].model_dump(mode="json"), resolution=[width, height])
    if frames is not None:  # a shorter run (the CPU check): the first frames, the same camera path
        a, b = shot_json["frames"]
        shot_json["frames"] = [a, min(b, a + frames)]
    shot = load_shot(shot_json, where=f"{spec_path} shot {CLOSEUP}")
    s = ArtifactStore(store_url)
    perf = s.get_record(s.resolve(f"productions/{spec.name}/performances/{CLOSEUP}"), Performance)
    capture = s.get_record(perf.capture, Capture)
    enh = s.get_record(s.resolve(f"productions/{spec.name}/enhancer"), EnhancerModel)
    # the production's enhance-shot call: its settings and prompt group (flows/production.py)
    settings = spec.quality_preset().enhance_settings()

    for old in (dst / "gpu", dst / "truth"):  # another demo's files would travel or be scored
        shutil.rmtree(old, ignore_errors=True)
    gpu = dst / "gpu"
    (gpu / "models").mkdir(parents=True, exist_ok=True)
    for seg in perf.segments:
        (gpu / "models" / f"{seg.model.digest.split(':')[-1]}.safetensors").write_bytes(s.get_bytes(seg.model))
    (gpu / "performance.json").write_text(perf.model_dump_json(indent=1))
    (gpu / "shot.json").write_text(json.dumps(shot_json, indent=1))
    (gpu / "stage.json").write_text(json.dumps(stage_volume(capture.rig.stage_size_m)))
    (gpu / "enhancer.safetensors").write_bytes(s.get_bytes(enh.model))
    (gpu / "enhancer.json").write_text(enh.model_dump_json(indent=1))
    enhance = {"settings": settings.model_dump(mode="json"), "group": shot.actors[0], "model_digest": enh.model.digest}
    (gpu / "enhance.json").write_text(json.dumps(enhance, indent=1))

    tree = s.get_tree(capture.ground_truth)
    (dst / "scene.json").write_bytes(s.get_bytes(tree["scene.json"].digest))
    (dst / "truth").mkdir(exist_ok=True)
    world = truth_world_of(s, capture)
    t0 = time.perf_counter()
    for name, exr in render_truth_frames(shot, world, supersample=supersample):
        (dst / "truth" / name).write_bytes(exr)
        print(f"truth {name} ({time.perf_counter() - t0:.1f} s)", flush=True)
        t0 = time.perf_counter()
    size = sum(f.stat().st_size for f in gpu.rglob("*") if f.is_file())
    print(f"{gpu}: {size / 2**20:.1f} MiB for the GPU; truth {dst / 'truth'}: "
          f"{sum(f.stat().st_size for f in (dst / 'truth').iterdir()) / 2**20:.1f} MiB (stays here)")


class _NoDis:
    """The DIS fallback where OpenCV is absent (the GPU machine): a single-segment shot's frames
    all carry the renderer's exact flow, so it is never called; if one is, it says why."""

    def __call__(self, prev, cur):
        raise RuntimeError("a frame without rendered flow needs OpenCV's DIS, which is not installed here")


def run(src: Path, out: Path, device: torch.device, backend_name: str, compare_backend: str | None,
        max_mib: float) -> None:
    """Part 2 (module doc)."""
    from volcap_core.enhance.model import enhancer_from_bytes
    from volcap_core.enhance.production import EnhanceSettings, enhance_shot_frames
    from volcap_core.production.performance import Performance
    from volcap_core.production.shot import load_shot, render_shot_frame
    from volcap_core.splat import load_model

    gpu = src / "gpu"
    shot = load_shot(json.loads((gpu / "shot.json").read_text()), where=str(gpu / "shot.json"))
    perf = Performance.model_validate_json((gpu / "performance.json").read_text())
    lo, hi = json.loads((gpu / "stage.json").read_text())
    stage = (tuple(lo), tuple(hi))
    enhance = json.loads((gpu / "enhance.json").read_text())
    settings = EnhanceSettings(**enhance["settings"])

    @functools.lru_cache(maxsize=4)
    def model_of(ref):
        return load_model((gpu / "models" / f"{ref.digest.split(':')[-1]}.safetensors").read_bytes(), device)

    timings: dict = {"device": str(device), "torch": torch.__version__, "backend": backend_name,
                     "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
                     "resolution": list(shot.resolution), "frames": list(shot.frames),
                     "enhance_settings": settings.model_dump(), "render_s": {}, "enhance_s": {}}

    def render(frame: int, backend: str) -> tuple[bytes, float]:
        _sync(device)
        t0 = time.perf_counter()
        exr = render_shot_frame(shot, perf, model_of, frame, backend=backend, device=device, stage=stage)
        _sync(device)
        return exr, time.perf_counter() - t0

    t0 = time.perf_counter()
    for seg in perf.segments:
        model_of(seg.model)
    timings["load_models_s"] = round(time.perf_counter() - t0, 3)
    rendered: list[tuple[str, bytes]] = []
    for f in shot.frame_numbers():
        exr, dt = render(f, backend_name)
        rendered.append((f"{f:06d}.exr", exr))
        timings["render_s"][str(f)] = round(dt, 4)
        print(f"render {backend_name} frame {f}: {dt:.3f} s", flush=True)
    if compare_backend:  # the same frame again through each back-end, warm: the second frame (it has flow)
        f = shot.frames[0] + min(1, len(shot.frame_numbers()) - 1)
        _, warm = render(f, backend_name)
        _, dt = render(f, compare_backend)
        timings["compare"] = {"frame": f, f"{backend_name}_s": round(warm, 4), f"{compare_backend}_s": round(dt, 4)}
        print(f"frame {f}: {backend_name} {warm:.3f} s, {compare_backend} {dt:.3f} s", flush=True)

    t0 = time.perf_counter()
    model = enhancer_from_bytes((gpu / "enhancer.safetensors").read_bytes(), device=device)
    timings["load_enhancer_s"] = round(time.perf_counter() - t0, 3)
    try:
        from volcap_core.enhance.temporal import DisFlow
        backend = DisFlow()
    except ImportError:
        backend = _NoDis()
    enhanced: list[tuple[str, bytes]] = []
    _sync(device)
    t0 = time.perf_counter()
    for name, data in enhance_shot_frames(model, rendered, settings, group=enhance["group"],
                                          model_digest=enhance["model_digest"], flow_backend=backend, shot=shot.name):
        _sync(device)
        dt = time.perf_counter() - t0
        enhanced.append((name, data))
        timings["enhance_s"][str(int(name.split(".")[0]))] = round(dt, 4)
        print(f"enhance {name}: {dt:.3f} s", flush=True)
        t0 = time.perf_counter()

    # a device call brings back at most 8 files of 16 MiB: the tar in parts of PART_BYTES, joined
    # again by --score; the frames (render and enhanced) as far as they fit in max_mib, in order
    kept, total = 0, 0
    for (_, r), (_, e) in zip(rendered, enhanced):
        if total + len(r) + len(e) + 2048 > max_mib * 2**20:
            break
        kept, total = kept + 1, total + len(r) + len(e) + 2048
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for kind, frames in (("render", rendered), ("enhanced", enhanced)):
            for name, data in frames[:kept]:
                info = tarfile.TarInfo(f"{kind}/{name}")
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
    out.mkdir(parents=True, exist_ok=True)
    data = buf.getvalue()
    parts = [data[i:i + PART_BYTES] for i in range(0, len(data), PART_BYTES)]
    for i, part in enumerate(parts):
        (out / f"closeup_exrs.tar.{i:02d}").write_bytes(part)
    timings["frame_bytes"] = {"render": [len(b) for _, b in rendered], "enhanced": [len(b) for _, b in enhanced]}
    timings["returned_frames"] = [name for name, _ in rendered[:kept]]
    timings["tar_parts"] = len(parts)
    (out / "timings.json").write_text(json.dumps(timings, indent=1))
    print(f"{out}: {kept} of {len(rendered)} frames in closeup_exrs.tar.00-{len(parts) - 1:02d} "
          f"({len(data) / 2**20:.1f} MiB), timings.json", flush=True)


def score(src: Path, out: Path) -> None:
    """Part 3 (module doc)."""
    from flows.demo import closeup_figures
    from volcap_core.contact_sheet import encode_png
    from volcap_core.production.closeup import score_shot_exrs

    frames: dict[str, list[tuple[str, bytes]]] = {"render": [], "enhanced": []}
    parts = sorted(out.glob("closeup_exrs.tar.[0-9][0-9]"))
    timings = json.loads((out / "timings.json").read_text())
    if len(parts) != timings["tar_parts"]:
        raise SystemExit(f"{out}: {len(parts)} closeup_exrs.tar parts, timings.json says {timings['tar_parts']}")
    with tarfile.open(fileobj=io.BytesIO(b"".join(p.read_bytes() for p in parts))) as tar:
        for m in sorted(tar.getmembers(), key=lambda m: m.name):
            kind, name = m.name.split("/", 1)
            if kind in frames:
                frames[kind].append((name, tar.extractfile(m).read()))
    names = timings["returned_frames"]
    truth = [(n, (src / "truth" / n).read_bytes()) for n in names]
    shot = json.loads((src / "gpu" / "shot.json").read_text())
    actors = [int(a.removeprefix("actor")) for a in shot["actors"]]
    scene = json.loads((src / "scene.json").read_text())
    scores, sheet = score_shot_exrs(truth, frames["render"], scene, enhanced=frames["enhanced"], actors=actors)
    dst = src / "score"
    dst.mkdir(exist_ok=True)
    (dst / "closeup_sheet.png").write_bytes(encode_png(sheet))
    figures = closeup_figures(scores)
    (dst / "closeup_scores.json").write_text(json.dumps({"figures": figures, "scores": scores, "timings": timings},
                                                        indent=1, sort_keys=True, default=float))
    w, h = timings["resolution"]
    print(f"close-up {w}x{h}, shot frames {timings['frames']}, scored {len(names)} ({names[0]}-{names[-1]}), "
          f"{timings['device']} ({timings['gpu']})")
    print(f"{'region':<11}{'row':<10}{'PSNR dB':>9}{'SSIM':>7}{'detail':>8}")
    for region in ("face", "performers"):
        for row, f in figures[region].items():
            print(f"{region:<11}{row:<10}{f['psnr']:>9}{f['ssim']:>7}{f['detail']:>8}")
    for row, t in figures["temporal"].items():
        print(f"temporal {row:<10} flickering {t['flickering']}  warp error {t['warp_error']}")
    r, e = timings["render_s"], timings["enhance_s"]
    print(f"render ({timings['backend']}) s/frame: {', '.join(f'{v:.3f}' for v in r.values())}; "
          f"enhance s/frame: {', '.join(f'{v:.3f}' for v in e.values())}")
    if "compare" in timings:
        print(f"one frame: {timings['compare']}")
    print(f"sheet {dst / 'closeup_sheet.png'}, scores {dst / 'closeup_scores.json'}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    part = ap.add_mutually_exclusive_group(required=True)
    part.add_argument("--prepare", metavar="DIR", type=Path)
    part.add_argument("--run", metavar="DIR", type=Path)
    part.add_argument("--score", nargs=2, metavar=("DIR", "OUT"), type=Path)
    ap.add_argument("--store", default="/tmp/d1/store", help="the demo's store (--prepare)")
    ap.add_argument("--demo", type=Path, default=Path("/tmp/d1/demo"), help="the demo's output folder (--prepare)")
    ap.add_argument("--resolution", nargs=2, type=int, default=(1920, 1080), metavar=("W", "H"))
    ap.add_argument("--frames", type=int, default=None, help="only the shot's first N frames (--prepare)")
    ap.add_argument("--supersample", type=int, default=2, help="the truth's samples per pixel per axis")
    ap.add_argument("--out", type=Path, help="where --run writes: the tar parts and timings.json")
    ap.add_argument("--max-mib", type=float, default=75.0,
                    help="the most EXR bytes --run returns (5 parts): frames beyond are timed, not returned")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--backend", default="gsplat", help="the renderer's back-end (gsplat needs CUDA)")
    ap.add_argument("--compare", default="torch", help="the back-end one frame is also timed with ('' for none)")
    args = ap.parse_args(argv)
    if args.prepare:
        prepare(args.prepare, args.store, args.demo, *args.resolution, args.frames, args.supersample)
    elif args.run:
        if args.out is None:
            ap.error("--run needs --out")
        run(args.run, args.out, torch.device(args.device), args.backend, args.compare or None,
            args.max_mib)
    else:
        score(*args.score)


if __name__ == "__main__":
    sys.exit(main())
