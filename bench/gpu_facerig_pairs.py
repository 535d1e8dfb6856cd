"""The Face Rig pair stages' time and peak GPU memory at the paper's sizes through gsplat (issue 29,
"Time and memory per stage ... when a GPU is lent, at 1024² or more on gsplat"), in three parts.

A GPU machine has no Prefect, pycolmap, OpenCV or artifact store, so the work is split as
``bench/gpu_zoom_curve.py`` splits it:

1. ``--prepare DIR`` (here, on CPU): one Face Rig sub-sequence (``--frames``, the paper's 8) of an
   ingested Face Rig capture read from a store (read only: nothing is written there), with what its
   two pair models' training and their renders need, built by the functions the ``facerig_pairs``
   flow's tasks call: the ground-truth calibration (``ground_truth.calibration``, as
   ``ground-truth-calibration``; the flow's ``face_calibration: ground-truth``), the views
   (:func:`volcap_core.reconstruction.segment_data`) and their footage as the capture stores it
   (half-float EXR bytes), the dense points from true depth
   (``ground_truth.depth_points``, as ``ground-truth-points``, every camera but the held-out one)
   made into the initial points as ``train-segment`` makes them
   (:func:`~volcap_core.reconstruction.segment_init`), the held-out cameras
   (:func:`~volcap_core.reconstruction.default_held_out`), the production preset (its
   ``face_hq_gaussians_per_frame``, ``face_lq_gaussians`` and TrainConfig), the LQ count drawn as
   the flow draws it (:func:`volcap_core.splat_pairs.lq_gaussians_per_frame`), camera paths
   (:func:`~volcap_core.production.face_paths.face_camera_paths`, seeded, around the head
   :func:`~volcap_core.production.face_paths.head_from_model` finds in the dense points of each
   frame: the flow's ``face-paths`` looks in the HQ model, which does not exist yet here) at each
   render size, and the Face Rig -> Scene Rig colour matrix
   (:func:`~volcap_core.calibration.colour_step.colour_step`, the ``calibrate-colour`` task's, on
   the synthetic chart of each rig, its patch centres projected through each capture's true camera).
   ``--cameras`` keeps the footage of a few cameras (one view trains each step, so the step's cost
   does not depend on how many cameras there are) and ``--points-per-frame`` fewer points than the
   flow's (which takes ``face_hq_gaussians_per_frame`` a frame): both keep the folder small enough
   to travel (<= 40 MiB); the models grow to their budget by MCMC (below).
2. ``--run DIR --out OUT --device cuda --budget-s 150`` (on the GPU machine): per stage the wall
   time and the peak GPU memory (``torch.cuda.max_memory_allocated``, reset between stages):
   ``train-lq``, ``train-hq``: :func:`volcap_core.splat.train.train_segment` with the production
   preset's TrainConfig at the model's budget (Gaussians a frame × frames), except that MCMC grows
   the model to that budget in its first refinement steps (refinement every step, growth
   ``grow_rate`` enough to reach the cap) instead of over the schedule's thousands of steps; then
   ``--lq-steps`` / ``--hq-steps`` ordinary steps, timed one by one (their median and spread after
   a few of warm-up): the cost of a step at the budget, not a converged model. ``render-<model>-<px>``:
   the trained models rendered along the first camera path at each render size (all its frames at
   1024 px and below, its first ``--large-frames`` above: at 4096² a frame's EXR encode takes
   seconds of CPU) by :func:`volcap_core.splat_pairs.render_path`, per frame the render (with the
   copy to the host), the colour matrix (:func:`~volcap_core.calibration.colour.apply_colour_matrix`
   on the device, as ``render_path`` applies it before the copy, between two CUDA synchronisations),
   the EXR encode (:func:`~volcap_core.splat_pairs.encode_pair_frame`: 16-bit half RGBA, the
   pairs' writer), then the path's frames encoded again together on the host's threads
   (:func:`~volcap_core.splat_pairs.encode_frames`, as ``render-pairs`` encodes them: the wall
   time against the one-by-one sum), and, for the LQ, its exact flow (``render_path(...,
   flow=True)`` over the path with the colour matrix, less the frames' render and colour time) and
   the flow EXR encodes (:func:`~volcap_core.splat_pairs.encode_flow_frame`, one by one, then
   together on the threads). It stops before a stage or frame that the time left cannot hold
   (``--budget-s``, loading counted), writing what it has after every stage:
   ``OUT/facerig_pairs.json`` and ``OUT/facerig_pairs.log``, nothing else (the EXRs' sizes are
   recorded, not the EXRs).
3. ``--report OUT`` (here): a Markdown table for ``docs/benchmarks.md``.
4. ``--encode-check PX`` (anywhere): whether the pair EXR encodes gain from host threads
   (:func:`encode_check`).

    python bench/gpu_facerig_pairs.py --prepare .gpu-pairs
    timeout 180 python3 bench/gpu_facerig_pairs.py --run .gpu-pairs --out $OUT/pairs --device cuda --budget-s 150
    python bench/gpu_facerig_pairs.py --report OUT/pairs
    nice python bench/gpu_facerig_pairs.py --encode-check 4096
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.gpu_zoom_curve import initial_points_bytes, load_initial_points  # noqa: E402  (the repository on the path first)

#: the background Face Rig pairs bench's store and its Face Rig / Scene Rig captures (640×360)
STORE = "/work/pairsbench-w/store"
FACE_CAPTURE = "captures/synth-demo_face_x2-s0"
SCENE_CAPTURE = "captures/synth-demo_scene_x2-s0"
#: the chart views of the colour matrix: a frontal Face Rig camera and a Scene Rig camera that both
#: see their rig's chart whole at take frame 0 (tests/calibration/test_colour_between_rigs.py's)
CHART_CAMERAS = ("F003", "S001")
#: seconds kept back from the budget for writing the results
RESERVE_S = 3.0
#: above this many pixels a side the run renders only a path's first LARGE_FRAMES frames: at 4096²
#: a frame's EXR encode (OpenEXR on the CPU) takes seconds, and the budget must hold both models
#: and the flow
LARGE, LARGE_FRAMES = 1024, 4
#: the ordinary steps after growth not counted in the step statistics (warm-up)
WARMUP_STEPS = 3
JSON_NAME, LOG_NAME = "facerig_pairs.json", "facerig_pairs.log"


# -------------------------------------------------------------------------------------- prepare

def _chart_patches_px(cameras_json: dict, chart: dict, camera: str, frame: int = 0) -> list[list[float]]:
    """The synthetic chart's patch centres (``scene.json`` ``chart.patches[].centre_m``) in pixels
    of ``camera`` at take frame ``frame``, through its true camera (``cameras.json``)."""
    f = cameras_json["cameras"][camera]["frames"][frame]
    K = np.array([[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1.0]])
    w2c = np.array(f["world_to_camera"])
    pc = np.array([p["centre_m"] for p in chart["patches"]]) @ w2c[:3, :3].T + w2c[:3, 3]
    return (pc[:, :2] / pc[:, 2:] @ K[:2, :2].T + K[:2, 2]).round(2).tolist()


def _colour_matrix(s, face_ref, scene_ref):
    """The Face Rig -> Scene Rig ColourMatrixRecord of the two synthetic captures' charts."""
    from volcap_core.calibration.colour_step import ChartView, colour_step
    from volcap_core.capture import Capture
    from volcap_core.synth import ground_truth

    views = []
    for rig, ref, cam in (("face", face_ref, CHART_CAMERAS[0]), ("scene", scene_ref, CHART_CAMERAS[1])):
        cap = s.get_record(ref, Capture)
        tree = s.get_tree(cap.ground_truth)
        files = ground_truth.GroundTruthFiles(cap.name, {p: e.digest for p, e in tree.items()}, s.get_bytes)
        chart = json.loads(files.read("scene.json"))["chart"]
        patches = _chart_patches_px(json.loads(files.read("cameras.json")), chart, cam)
        views.append(ChartView(rig=rig, capture=ref, camera=cam, frame=0, patches_px=tuple(map(tuple, patches))))
    return colour_step(views[0], views[1], s.get_bytes)


def prepare(dst: Path, store_url: str = STORE, *, capture: str = FACE_CAPTURE, scene: str = SCENE_CAPTURE,
            frames: tuple[int, int] = (0, 8), cameras: list[str] | None = None, points_per_frame: int = 40_000,
            paths: int = 3, sizes: tuple[int, ...] = (1024, 4096), preset: str = "production",
            overrides: dict | None = None, seed: int = 0) -> dict:
    """Part 1 (module doc). ``cameras``: the cameras whose footage travels (None: all; the held-out
    ones are always kept: training checks they exist). ``overrides``: QualityPreset fields (a CPU
    test's tiny budgets). Returns what ``DIR/pairs.json`` holds."""
    from volcap_core import reconstruction
    from volcap_core.calibration.distortion import record_distortion
    from volcap_core.calibration.record import camera_at, frame_camera
    from volcap_core.capture import Capture
    from volcap_core.pointcloud import POINTS_MEDIA, PointCloudFrame, PointCloudSequence, encode_points
    from volcap_core.production.face_paths import face_camera_paths, head_from_model
    from volcap_core.production.presets import named_preset
    from volcap_core.segment import tracking_frames
    from volcap_core.splat_pairs import lq_gaussians_per_frame
    from volcap_core.store import ArtifactStore
    from volcap_core.synth import ground_truth

    t0 = time.perf_counter()
    s = ArtifactStore(store_url)            # read only: every put goes to the scratch store below
    cap_ref, scene_ref = s.resolve(capture), s.resolve(scene)
    cap = s.get_record(cap_ref, Capture)
    if cap.ground_truth is None:
        raise SystemExit(f"capture {cap.name}: no ground truth (its calibration and points come from it)")
    quality = named_preset(preset).with_overrides(**(overrides or {}))
    tree = s.get_tree(cap.ground_truth)
    files = ground_truth.GroundTruthFiles(cap.name, {p: e.digest for p, e in tree.items()}, s.get_bytes)
    calib, blob = ground_truth.calibration(json.loads(files.read("cameras.json")), cap.name,
                                           [c.id for c in cap.cameras], cap.rig.stage_size_m)
    if blob is not None:
        raise SystemExit(f"capture {cap.name}: tracking cameras; a Face Rig's are static")
    held = reconstruction.default_held_out(cap, calibration=calib, tracking=quality.held_out_tracking)
    a, b = cap.take_range(frames)
    keep = sorted(set(cameras or [c.id for c in cap.cameras]) | set(held))
    data = reconstruction.segment_data(cap, calib, tracking_frames(s.get_bytes, calib), (a, b),
                                       reconstruction.FrameCache(s.get_bytes), camera_ids=keep)
    if any(v.valid is not None for v in data.views):
        raise SystemExit(f"capture {cap.name}: distorted lenses need rectifying (OpenCV): not on the GPU machine")

    # the dense points of the window's frames from true depth, every camera but the held-out ones
    # (ground-truth-points), into a scratch store; then the initial points as train-segment makes them
    point_cams = [c.id for c in cap.cameras if c.id not in set(held)]
    with tempfile.TemporaryDirectory(prefix="gpu-pairs-") as tmp:
        scratch = ArtifactStore(str(Path(tmp) / "store"))
        pframes, heads = [], []
        around = np.median([c.mount.look_at_m for c in cap.rig.cameras], axis=0)
        for f in range(a, b):
            xyz, rgb = ground_truth.depth_points(
                files, point_cams, f, lambda cam, k: _decode(s, cap, cam, k),
                lambda cam, k: camera_at(calib, cam, k, None)[:2], points_per_frame, seed,
                distortion_of=lambda cam, k: record_distortion(frame_camera(calib, cam, k, None)))
            heads.append(head_from_model(torch.from_numpy(xyz), torch.ones(len(xyz)), around_m=around))
            pframes.append(PointCloudFrame(frame=f, time=cap.frame_time(f), count=len(xyz),
                                           points=scratch.put_bytes(encode_points(xyz, rgb), POINTS_MEDIA)))
        pts = PointCloudSequence(calibration=scratch.put_record(calib), frames=tuple(pframes),
                                 method=f"ground-truth depth, {points_per_frame} per frame")

        def load(ref):
            return scratch.get_bytes(ref) if scratch.exists(ref) else s.get_bytes(ref)

        init = reconstruction.segment_init(load, cap, pts, data, held)
    colour = _colour_matrix(s, cap_ref, scene_ref)

    times = [cap.frame_time(f) for f in range(a, b)]
    centres = np.stack([h.centre_m for h in heads])
    radius = float(np.median([h.radius_m for h in heads]))
    drawn = {str(px): [{"views": [v.model_dump(mode="json") for v in p.views], "params": p.params}
                       for p in face_camera_paths(centres, radius, times, paths, width=px, height=px, seed=seed)]
             for px in sizes}
    lq = lq_gaussians_per_frame(quality.face_lq_gaussians, seed, 0)

    shutil.rmtree(dst, ignore_errors=True)
    (dst / "frames").mkdir(parents=True)
    views = []
    for v in data.views:
        name = f"{v.camera_id}_{v.frame:06d}"
        (dst / "frames" / f"{name}.exr").write_bytes(s.get_bytes(cap.camera(v.camera_id).frames[v.frame]))
        views.append({"camera": v.camera_id, "frame": v.frame, "time": v.time, "K": v.camera.K.tolist(),
                      "world_to_camera": v.camera.world_to_camera.tolist(), "width": v.camera.width,
                      "height": v.camera.height})
    (dst / "init.safetensors").write_bytes(initial_points_bytes(init, quality))
    meta = {"capture": cap.name, "capture_ref": cap_ref.digest, "scene_ref": scene_ref.digest, "store": str(store_url),
            "frames": [a, b], "fps": cap.fps, "seed": seed, "held_out": held, "cameras": keep,
            "points_per_frame": points_per_frame, "point_cameras": point_cams,
            "initial_points": int(sum(len(p.xyz) for p in init)),
            "hq_gaussians_per_frame": quality.face_hq_gaussians_per_frame, "lq_range": list(quality.face_lq_gaussians),
            "lq_gaussians_per_frame": lq, "preset_name": preset, "preset": quality.model_dump(mode="json"),
            "head": {"centres_m": centres.tolist(), "radius_m": radius},
            "colour": colour.model_dump(mode="json"), "paths": drawn, "views": views}
    (dst / "pairs.json").write_text(json.dumps(meta, indent=1))
    size = sum(f.stat().st_size for f in dst.rglob("*") if f.is_file())
    print(f"{dst}: {size / 2**20:.1f} MiB in {time.perf_counter() - t0:.0f} s; {cap.name} frames {a}:{b}, "
          f"{len(views)} views of {', '.join(keep)} (held out {', '.join(held)}), "
          f"{meta['initial_points']} initial points; HQ {quality.face_hq_gaussians_per_frame} a frame, "
          f"LQ {lq} a frame (range {list(quality.face_lq_gaussians)}); {paths} path(s) at {list(sizes)} px; "
          f"colour matrix ΔE2000 {colour.before['delta_e2000_mean']:.2f} -> "
          f"{colour.after['delta_e2000_mean']:.2f}", flush=True)
    return meta


def _decode(s, cap, cam: str, k: int) -> np.ndarray:
    from volcap_core.imageio.read import decode_exr

    return decode_exr(s.get_bytes(cap.camera(cam).frames[k]))[0]


# ------------------------------------------------------------------------------------------ run

class Prepared:
    """What ``--prepare`` wrote, loaded: the sub-sequence's views (footage decoded once), the
    initial points, the preset, the paths per render size and the colour matrix."""

    def __init__(self, src: Path):
        from volcap_core.calibration.colour_step import ColourMatrixRecord
        from volcap_core.imageio.read import decode_exr
        from volcap_core.production.presets import QualityPreset
        from volcap_core.splat import Camera, SegmentData, View
        from volcap_core.view import ViewSpec

        path = src / "pairs.json"
        if not path.is_file():
            raise SystemExit(f"{path}: missing (is {src} a folder written by --prepare?)")
        self.meta = json.loads(path.read_text())
        self.quality = QualityPreset.model_validate(self.meta["preset"])
        self.colour = ColourMatrixRecord.model_validate(self.meta["colour"])
        self.paths = {int(px): [[ViewSpec.model_validate(v) for v in p["views"]] for p in drawn]
                      for px, drawn in self.meta["paths"].items()}
        views = []
        for v in self.meta["views"]:
            exr = src / "frames" / f"{v['camera']}_{v['frame']:06d}.exr"
            pixels, _ = decode_exr(exr.read_bytes(), name=str(exr))
            image = torch.from_numpy(np.ascontiguousarray(pixels[..., :3], dtype=np.float32))
            camera = Camera(K=torch.tensor(v["K"], dtype=torch.float32),
                            world_to_camera=torch.tensor(v["world_to_camera"], dtype=torch.float32),
                            width=v["width"], height=v["height"])
            views.append(View(v["camera"], v["frame"], v["time"], camera, image))
        self.data = SegmentData(tuple(self.meta["frames"]), views)
        self.init = load_initial_points(src / "init.safetensors")

    def config(self, per_frame: int, steps: int, backend: str = "auto"):
        """The production preset's TrainConfig at ``per_frame`` × frames Gaussians (the flow's
        ``face_model_jobs`` budget), ``steps`` long, no evaluation or checkpoint, MCMC growing the
        initial model to the cap in its first refinement steps (every step from step 1, doubling
        at most) instead of over the schedule. Returns ``(config, growth steps)``."""
        from volcap_core.splat.train import init_budget

        frames = self.meta["frames"][1] - self.meta["frames"][0]
        cap = per_frame * frames
        base = self.quality.train_config(held_out=self.meta["held_out"], max_gaussians=cap)
        start = min(init_budget(base), self.meta["initial_points"])
        growth = max(0, int(np.ceil(np.log2(max(1.0, cap / max(1, start)))))) + 1
        config = self.quality.train_config(
            held_out=self.meta["held_out"], max_gaussians=cap, eval_every=0, checkpoint_every=0, steps=growth + steps,
            backend=backend, mcmc={"refine_start": 1, "refine_every": 1, "refine_stop": growth + 1, "grow_rate": 1.0})
        return config, growth


class _Stop(Exception):
    """The budget is spent."""


class Run:
    """Part 2's state: the clock, the log and the figures written after every stage."""

    def __init__(self, out: Path, device: torch.device, budget_s: float):
        self.t0 = time.perf_counter()
        self.out, self.device, self.budget_s = out, device, budget_s
        out.mkdir(parents=True, exist_ok=True)
        self.log_file = open(out / LOG_NAME, "w")
        self.figures: dict = {"device": str(device), "torch": torch.__version__, "budget_s": budget_s,
                              "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
                              "stages": {}, "skipped": []}

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def left(self) -> float:
        return self.budget_s - RESERVE_S - self.elapsed()

    def log(self, msg: str) -> None:
        line = f"[{self.elapsed():7.1f} s] {msg}"
        print(line, flush=True)
        self.log_file.write(line + "\n")
        self.log_file.flush()

    def sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def reset_memory(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(self.device)

    def allocated_gib(self) -> float | None:
        """GPU memory held now (models kept for later stages count in a stage's peak)."""
        return round(torch.cuda.memory_allocated(self.device) / 2**30, 3) if self.device.type == "cuda" else None

    def peak_gib(self) -> float | None:
        return round(torch.cuda.max_memory_allocated(self.device) / 2**30, 3) if self.device.type == "cuda" else None

    def write(self) -> None:
        self.figures["elapsed_s"] = round(self.elapsed(), 2)
        (self.out / JSON_NAME).write_text(json.dumps(self.figures, indent=1, default=float))

    def skip(self, what: str, why: str) -> None:
        self.figures["skipped"].append(f"{what}: {why}")
        self.log(f"skipped {what}: {why}")


def _spread(xs: list[float]) -> dict:
    """Median, mean, standard deviation, 10th and 90th percentile, min, max, count (seconds)."""
    if not xs:
        return {"n": 0}
    q = np.percentile(xs, [10, 90])
    return {"n": len(xs), "median": round(statistics.median(xs), 5), "mean": round(statistics.fmean(xs), 5),
            "std": round(statistics.pstdev(xs), 5), "p10": round(float(q[0]), 5), "p90": round(float(q[1]), 5),
            "min": round(min(xs), 5), "max": round(max(xs), 5)}


def train_stage(r: Run, prep: Prepared, label: str, per_frame: int, steps: int, backend: str):
    """One pair model trained (module doc); its figures under ``stages[train-<label>]``. Returns the
    model, or None when the budget stopped it."""
    from volcap_core.splat.render import resolve_backend
    from volcap_core.splat.train import train_segment

    config, growth = prep.config(per_frame, steps, backend)
    stage = {"gaussians_per_frame": per_frame, "cap": config.mcmc.cap_max, "growth_steps": growth,
             "timed_steps": steps, "steps": config.steps, "backend": resolve_backend(config.backend, r.device).name,
             "resolution": sorted({(v.camera.width, v.camera.height) for v in prep.data.views}),
             "train_views": sum(v.camera_id not in set(config.held_out_cameras) for v in prep.data.views)}
    r.figures["stages"][f"train-{label}"] = stage
    r.reset_memory()
    stage["resident_gib"] = r.allocated_gib()
    marks: list[tuple[int, float, int]] = []
    start = time.perf_counter()

    def progress(step: int, total: int, info: dict) -> None:   # info's loss is a float: the step has synced
        marks.append((step, time.perf_counter(), int(info["num_gaussians"])))
        if r.left() < 0:
            raise _Stop

    r.log(f"train-{label}: cap {config.mcmc.cap_max} ({per_frame} a frame), {growth} growth + {steps} timed steps, "
          f"{stage['backend']}")
    try:
        result = train_segment(prep.data, prep.init, config, seed=int(prep.meta["seed"]), progress=progress,
                               device=r.device)
    except _Stop:
        result = None
    r.sync()
    wall = time.perf_counter() - start
    durations = [(s, t - marks[i - 1][1], n) for i, (s, t, n) in enumerate(marks) if i > 0]
    timed = [d for s, d, n in durations if s > growth + WARMUP_STEPS]
    stage.update({"wall_s": round(wall, 2), "peak_gpu_gib": r.peak_gib(), "steps_done": len(marks),
                  "first_step_s": round(marks[0][1] - start, 3) if marks else None,
                  "growth_s": round(sum(d for s, d, n in durations if s <= growth), 3),
                  "gaussians": marks[-1][2] if marks else None,
                  "gaussians_after_growth": next((n for s, t, n in marks if s == growth), None),
                  "step_s": _spread(timed), "stopped": result is None})
    r.log(f"train-{label}: {len(marks)} steps in {wall:.1f} s (first step with initialisation "
          f"{stage['first_step_s']} s), {stage['gaussians']} Gaussians, step {stage['step_s'].get('median')} s median "
          f"(std {stage['step_s'].get('std')}, n {stage['step_s']['n']}), peak {stage['peak_gpu_gib']} GiB")
    r.write()
    return None if result is None else result.model


def render_stage(r: Run, prep: Prepared, label: str, model, px: int, flow: bool, max_frames: int | None = None
                 ) -> None:
    """``model`` along the first camera path at ``px``² (its first ``max_frames`` frames; None: all;
    module doc); figures under ``stages[render-<label>-<px>]``."""
    from volcap_core.calibration.colour import apply_colour_matrix
    from volcap_core.splat_pairs import encode_flow_frame, encode_frames, encode_pair_frame, host_threads, render_path

    path = prep.paths[px][0]
    views = path[:max_frames]
    name = f"render-{label}-{px}"
    stage = {"px": px, "frames": len(views), "path_frames": len(path), "gaussians": len(model), "per_frame": []}
    r.figures["stages"][name] = stage
    r.reset_memory()
    stage["resident_gib"] = r.allocated_gib()
    start = time.perf_counter()
    frames, attributes = [], []
    for k, view in enumerate(views):
        est = max((sum(f[key] for key in ("render_s", "colour_s", "encode_s")) for f in stage["per_frame"]),
                  default=0.0)
        if r.left() < 1.5 * est:
            r.skip(f"{name} frames {k}-{len(views) - 1}", f"{r.left():.1f} s left, a frame took {est:.2f} s")
            break
        t = time.perf_counter()
        raw, _ = render_path(model, [view])
        t1 = time.perf_counter()
        # the colour matrix as render_path applies it: on the device, before the copy (the raw
        # frame goes back there untimed, so the render and the colour are timed apart)
        on_device = torch.from_numpy(raw[0]).to(r.device)
        r.sync()
        tc = time.perf_counter()
        mapped = apply_colour_matrix(on_device, prep.colour, premultiplied=True)
        r.sync()
        t2 = time.perf_counter()
        rgba = mapped.cpu().numpy()
        del on_device, mapped
        attributes.append({"volcap.pair": label, "volcap.sequence": "s000-p000",
                           "volcap.frame": int(prep.meta["frames"][0] + k)})
        te = time.perf_counter()
        exr = encode_pair_frame(rgba, view, attributes[-1])
        t3 = time.perf_counter()
        frames.append(rgba)
        stage["per_frame"].append({"render_s": round(t1 - t, 4), "colour_s": round(t2 - tc, 4),
                                   "encode_s": round(t3 - te, 4), "exr_bytes": len(exr),
                                   "alpha_mean": round(float(rgba[..., 3].mean()), 4)})
    threads = host_threads()
    serial = sum(f["encode_s"] for f in stage["per_frame"])
    if frames and r.left() < 1.5 * serial:
        r.skip(f"{name} encodes on {threads} threads", f"{r.left():.1f} s left, one by one they took {serial:.2f} s")
    elif frames:
        t = time.perf_counter()
        list(encode_frames(encode_pair_frame, frames, views, attributes))
        stage["threaded_encode"] = {"threads": threads, "frames": len(frames), "s": round(time.perf_counter() - t, 4),
                                    "one_by_one_s": round(serial, 4)}
    if flow and len(frames) == len(views) > 1:
        render_total = sum(f["render_s"] + f["colour_s"] for f in stage["per_frame"])
        if r.left() < 2.5 * render_total:
            r.skip(f"{name} flow", f"{r.left():.1f} s left, the path's renders took {render_total:.2f} s")
        else:
            t = time.perf_counter()
            rgba, flows = render_path(model, views, colour=prep.colour, flow=True)
            t1 = time.perf_counter()
            flow_attributes = [{"volcap.sequence": "s000-p000", "volcap.frame": int(prep.meta["frames"][0] + i + 1)}
                               for i in range(len(flows))]
            encodes, sizes = [], []
            for f, a in zip(flows, flow_attributes):
                if r.left() < 0:
                    r.skip(f"{name} flow encodes {len(sizes)}-{len(flows) - 1}", "budget")
                    break
                te = time.perf_counter()
                sizes.append(len(encode_flow_frame(f, a)))
                encodes.append(time.perf_counter() - te)
            stage["flow"] = {"path_with_flow_s": round(t1 - t, 4),
                             "flow_s_per_pair": round(max(0.0, (t1 - t) - render_total) / len(flows), 4),
                             "encode_s": _spread(encodes), "exr_bytes": sizes,
                             "mean_abs_px": round(float(np.abs(flows).mean()), 4),
                             "max_diff_to_per_frame_renders": max(float(np.abs(x - y).max())
                                                                  for x, y in zip(rgba, frames))}
            if len(encodes) == len(flows) and r.left() > 1.5 * sum(encodes):
                t = time.perf_counter()
                list(encode_frames(encode_flow_frame, flows, flow_attributes))
                stage["flow"]["threaded_encode"] = {"threads": threads, "frames": len(flows),
                                                    "s": round(time.perf_counter() - t, 4),
                                                    "one_by_one_s": round(sum(encodes), 4)}
    stage.update({"wall_s": round(time.perf_counter() - start, 2), "peak_gpu_gib": r.peak_gib(),
                  "render_s": _spread([f["render_s"] for f in stage["per_frame"]]),
                  "colour_s": _spread([f["colour_s"] for f in stage["per_frame"]]),
                  "encode_s": _spread([f["encode_s"] for f in stage["per_frame"]])})
    fl = stage.get("flow", {})
    te = stage.get("threaded_encode")
    r.log(f"{name}: {len(stage['per_frame'])} frames in {stage['wall_s']} s, "
          f"render {stage['render_s'].get('median')} s, "
          f"colour {stage['colour_s'].get('median')} s, EXR {stage['encode_s'].get('median')} s a frame"
          + (f" ({te['frames']} on {te['threads']} threads: {te['s']} s)" if te else "")
          + (f"; flow {fl['flow_s_per_pair']} s a pair, its EXR {fl['encode_s'].get('median')} s" if fl else "")
          + f"; peak {stage['peak_gpu_gib']} GiB")
    r.write()


def _guarded(r: Run, name: str, stage, *args):
    """``stage(*args)``; an error (a GPU out of memory ...) is recorded in the stage's figures and
    the run goes on with the next stage (None returned)."""
    try:
        return stage(*args)
    except Exception as exc:
        r.figures["stages"].setdefault(name, {})["error"] = f"{type(exc).__name__}: {str(exc)[:500]}"
        r.log(f"{name}: {type(exc).__name__}: {str(exc)[:500]}")
        r.write()
        if r.device.type == "cuda":
            torch.cuda.empty_cache()
        return None


def run(src: Path, out: Path, device: torch.device, budget_s: float, *, hq_steps: int = 20, lq_steps: int = 40,
        backend: str = "auto", sizes: tuple[int, ...] | None = None, large_frames: int | None = LARGE_FRAMES) -> dict:
    """Part 2 (module doc); above :data:`LARGE` px only the paths' first ``large_frames`` frames
    (None: all). Returns what ``OUT/facerig_pairs.json`` holds."""
    from volcap_core.checkpoint import deterministic_torch

    r = Run(out, device, budget_s)
    try:
        prep = Prepared(src)
        r.figures.update({k: prep.meta[k] for k in ("capture", "frames", "held_out", "cameras", "initial_points",
                                                    "hq_gaussians_per_frame", "lq_range", "lq_gaussians_per_frame",
                                                    "preset_name")})
        r.figures["load_s"] = round(r.elapsed(), 2)
        r.log(f"loaded {src}: {len(prep.data.views)} views, {prep.meta['initial_points']} initial points")
        if device.type == "cuda":
            t = time.perf_counter()
            from volcap_core.splat.render import resolve_backend

            chosen = resolve_backend(backend, device)
            version = None
            if chosen.name == "gsplat":   # the extension built or loaded here, not inside a step
                import importlib
                import importlib.metadata

                importlib.import_module("gsplat.cuda._backend")._C
                version = importlib.metadata.version("gsplat")
            r.figures["backend"] = {"name": chosen.name, "reason": chosen.reason, "version": version,
                                    "load_s": round(time.perf_counter() - t, 2)}
            r.log(f"back-end {chosen.name} ({chosen.reason}) in {r.figures['backend']['load_s']} s")
        models = {}
        for label, per_frame, steps in (("lq", prep.meta["lq_gaussians_per_frame"], lq_steps),
                                        ("hq", prep.meta["hq_gaussians_per_frame"], hq_steps)):
            if r.left() <= 0:
                r.skip(f"train-{label}", "budget")
                continue
            with deterministic_torch(device.type):   # as fit_segment trains (on CUDA: nothing changes)
                models[label] = _guarded(r, f"train-{label}", train_stage, r, prep, label, per_frame, steps, backend)
            if models[label] is None:
                r.skip(f"renders of {label}", "its training did not finish")
        for px in sizes or sorted(prep.paths):
            for label in ("lq", "hq"):
                if models.get(label) is None:
                    continue
                if r.left() <= 0:
                    r.skip(f"render-{label}-{px}", "budget")
                    continue
                _guarded(r, f"render-{label}-{px}", render_stage, r, prep, label, models[label], px, label == "lq",
                         large_frames if px > LARGE else None)
    except Exception as exc:   # what finished is written, with the error
        r.figures["error"] = f"{type(exc).__name__}: {exc}"
        r.log(f"error: {r.figures['error']}")
        r.write()
        raise
    r.write()
    r.log(f"{out / JSON_NAME}: {len(r.figures['stages'])} stages, {len(r.figures['skipped'])} skipped")
    return r.figures


# --------------------------------------------------------------------------------------- report

def report(out: Path) -> str:
    """Part 3 (module doc): the figures as a Markdown table (printed and returned)."""
    f = json.loads((out / JSON_NAME).read_text())
    lines = [f"{f.get('capture')} frames {f.get('frames')}, held out {f.get('held_out')}; {f.get('device')} "
             f"({f.get('gpu')}), torch {f.get('torch')}, back-end {f.get('backend', {}).get('name', '-')}; "
             f"{f.get('elapsed_s')} s of a {f.get('budget_s')} s budget (loading {f.get('load_s')} s)", "",
             "| stage | size | wall s | per step / frame (median, std) | peak GPU GiB (of it held before) |",
             "|---|---|---|---|---|"]

    def ms(sp: dict | None) -> str:
        if not sp or not sp.get("n"):
            return "–"
        return f"{1000 * sp['median']:.1f} ms ({1000 * sp['std']:.1f}, n {sp['n']})"

    def threaded(te: dict | None) -> str:
        if not te:
            return ""
        return (f", {te['frames']} EXRs on {te['threads']} threads {te['s']:.2f} s "
                f"(one by one {te['one_by_one_s']:.2f} s)")

    for name, s in f["stages"].items():
        gib = "–" if s.get("peak_gpu_gib") is None else f"{s['peak_gpu_gib']:.2f} ({s.get('resident_gib', 0):.2f})"
        if name.startswith("train-"):
            size = (f"{s['gaussians']} Gaussians ({s['gaussians_per_frame']} a frame), "
                    f"{'×'.join(map(str, s['resolution'][0]))} views")
            what = (f"step {ms(s.get('step_s'))}; {s.get('growth_steps')} growth steps {s.get('growth_s')} s, "
                    f"first step with init {s.get('first_step_s')} s"
                    + (", stopped by the budget" if s.get("stopped") else ""))
        else:
            size = f"{s['px']}², {len(s['per_frame'])} of {s['path_frames']} frames, {s['gaussians']} Gaussians"
            what = f"render {ms(s.get('render_s'))}, colour {ms(s.get('colour_s'))}, EXR {ms(s.get('encode_s'))}"
            if s.get("per_frame"):
                what += f" ({np.mean([p['exr_bytes'] for p in s['per_frame']]) / 2**20:.1f} MiB)"
            what += threaded(s.get("threaded_encode"))
            if "flow" in s:
                fl = s["flow"]
                what += (f"; flow {1000 * fl['flow_s_per_pair']:.1f} ms a pair, its EXR {ms(fl['encode_s'])}"
                         + threaded(fl.get("threaded_encode")))
        lines.append(f"| {name} | {size} | {s.get('wall_s', '–')} | {what} | {gib} |")
    if f.get("skipped"):
        lines += ["", "Skipped: " + "; ".join(f["skipped"])]
    if f.get("error"):
        lines += ["", f"Error: {f['error']}"]
    text = "\n".join(lines)
    print(text)
    return text


# ------------------------------------------------------------------------------- encode check

def _python_rate_beside(work) -> float:
    """Iterations a second of a Python loop in this thread while ``work()`` runs in another."""
    import threading

    done = threading.Event()

    def run():
        work()
        done.set()

    n, t = 0, time.perf_counter()
    threading.Thread(target=run).start()
    while not done.is_set():
        n += 1
    return n / (time.perf_counter() - t)


def encode_check(px: int, frames: int = 4, workers: int | None = None, repeats: int = 3) -> dict:
    """Part 4 (any machine, no GPU, no prepared folder): whether a path's pair EXRs encode faster
    on host threads at ``px``². ``frames`` encodes (:func:`~volcap_core.splat_pairs.encode_pair_frame`
    of a synthetic premultiplied frame: a disc of smooth colour with 2 % noise, which compresses
    worse than a render) one by one and through :func:`~volcap_core.splat_pairs.encode_frames` on
    ``workers`` threads (None: the host's); beside them a control that runs side by side whenever
    cores are free (sha256 of as many bytes: it releases the GIL), which tells a shared machine's
    busy cores from a binding that holds the GIL; and the GIL itself: a Python loop's speed while
    one encode runs in another thread, against while sha256 (releases it), ``sum(range)`` (holds
    it) and a sleep run (telling only when an encode and a sha256 take much longer than the
    interpreter's 5-ms switch interval: 2048² and more). Prints and returns the figures."""
    import hashlib

    from volcap_core.splat_pairs import encode_frames, encode_pair_frame, host_threads
    from volcap_core.view import ViewSpec

    workers = host_threads() if workers is None else workers
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:px, :px].astype(np.float32) / px
    alpha = ((xx - 0.5) ** 2 + (yy - 0.5) ** 2 < 0.16).astype(np.float32)[..., None]
    images = [np.concatenate([(np.stack([0.7 * xx, 0.5 * yy, xx * yy], -1)
                               + rng.normal(0, 0.02, (px, px, 3)).astype(np.float32)) * alpha, alpha], -1)
              for _ in range(frames)]
    view = ViewSpec(K=((float(px), 0.0, px / 2), (0.0, float(px), px / 2), (0.0, 0.0, 1.0)),
                    world_to_camera=tuple(tuple(float(i == j) for j in range(4)) for i in range(4)),
                    width=px, height=px, time_s=0.0)
    views, attributes = [view] * frames, [{"volcap.frame": k} for k in range(frames)]
    blobs = [np.random.default_rng(k).bytes(px * px * 8) for k in range(frames)]
    sha = lambda b: hashlib.sha256(b).digest()  # noqa: E731

    def timed(fn) -> float:
        t = time.perf_counter()
        fn()
        return time.perf_counter() - t

    encode_pair_frame(images[0], view, attributes[0])          # warm-up (imports, allocator)
    rounds = []
    for _ in range(repeats):   # each round's four timings back to back: a shared machine's load drifts
        rounds.append({
            "encode_one_by_one_s": timed(lambda: list(encode_frames(encode_pair_frame, images, views, attributes,
                                                                    workers=1))),
            "encode_threads_s": timed(lambda: list(encode_frames(encode_pair_frame, images, views, attributes,
                                                                 workers=workers))),
            "sha256_one_by_one_s": timed(lambda: [sha(b) for b in blobs]),
            "sha256_threads_s": timed(lambda: list(encode_frames(sha, blobs, workers=workers)))})
    f = {"px": px, "frames": frames, "workers": workers, "rounds": rounds,
         **{k: statistics.median(r[k] for r in rounds) for k in rounds[0]},
         **{f"{work}_speedup": round(statistics.median(r[f"{work}_one_by_one_s"] / r[f"{work}_threads_s"]
                                                       for r in rounds), 2) for work in ("encode", "sha256")}}
    idle = _python_rate_beside(lambda: time.sleep(0.5))
    f["python_loop_beside"] = {name: round(_python_rate_beside(work) / idle, 2) for name, work in (
        ("encode", lambda: encode_pair_frame(images[0], view, attributes[0])), ("sha256", lambda: sha(blobs[0])),
        ("sum_range", lambda: sum(range(30_000_000))))}
    print(f"{px}², medians of {repeats} rounds: {frames} half RGBA encodes one by one "
          f"{f['encode_one_by_one_s']:.3f} s, on {workers} threads {f['encode_threads_s']:.3f} s "
          f"({f['encode_speedup']}x); control: sha256 of {frames} × {len(blobs[0]) / 2**20:.1f} MiB one by one "
          f"{f['sha256_one_by_one_s']:.3f} s, on {workers} threads "
          f"{f['sha256_threads_s']:.3f} s ({f['sha256_speedup']}x); a Python loop runs at "
          + ", ".join(f"{v:.0%} beside {k}" for k, v in f["python_loop_beside"].items())
          + " (of its speed beside a sleep)", flush=True)
    return f


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    part = ap.add_mutually_exclusive_group(required=True)
    part.add_argument("--prepare", metavar="DIR", type=Path)
    part.add_argument("--run", metavar="DIR", type=Path)
    part.add_argument("--report", metavar="OUT", type=Path)
    part.add_argument("--encode-check", metavar="PX", type=int,
                      help="whether a path's EXR encodes gain from the host's threads at PX² (no GPU)")
    ap.add_argument("--repeats", type=int, default=3, help="--encode-check: rounds (medians reported)")
    ap.add_argument("--store", default=STORE, help="--prepare: the store holding the captures (read only)")
    ap.add_argument("--capture", default=FACE_CAPTURE, help="--prepare: the Face Rig capture (ref name or digest)")
    ap.add_argument("--scene", default=SCENE_CAPTURE, help="--prepare: the Scene Rig capture (the colour matrix's)")
    ap.add_argument("--frames", nargs=2, type=int, default=(0, 8), metavar=("A", "B"), help="take frames [A, B)")
    ap.add_argument("--cameras", nargs="*", default=["F000", "F002", "F004", "F006"],
                    help="--prepare: the cameras whose footage travels (the held-out ones are added)")
    ap.add_argument("--points-per-frame", type=int, default=40_000, help="--prepare: dense points a frame")
    ap.add_argument("--paths", type=int, default=3, help="--prepare: camera paths drawn")
    ap.add_argument("--sizes", nargs="*", type=int, default=None,
                    help="render sizes (px, square): --prepare draws paths at them (default 1024 4096); "
                         "--run renders at them (default: the prepared)")
    ap.add_argument("--preset", default="production", help="--prepare: the quality preset")
    ap.add_argument("--override", action="append", default=[], metavar="FIELD=JSON",
                    help="--prepare: a preset field, e.g. face_hq_gaussians_per_frame=2000 (a CPU test)")
    ap.add_argument("--out", type=Path, help="--run: where facerig_pairs.json and .log go")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--backend", default="auto", help="--run: the rasterizer (auto: gsplat on CUDA)")
    ap.add_argument("--budget-s", type=float, default=150.0, help="--run: stop within this many seconds")
    ap.add_argument("--large-frames", type=int, default=LARGE_FRAMES,
                    help=f"--run: frames of a path rendered above {LARGE} px (0: all)")
    ap.add_argument("--hq-steps", type=int, default=20, help="--run: timed HQ steps after growth")
    ap.add_argument("--lq-steps", type=int, default=40, help="--run: timed LQ steps after growth")
    args = ap.parse_args(argv)
    if args.prepare:
        overrides = {k: json.loads(v) for k, v in (o.split("=", 1) for o in args.override)}
        prepare(args.prepare, args.store, capture=args.capture, scene=args.scene, frames=tuple(args.frames),
                cameras=args.cameras or None, points_per_frame=args.points_per_frame, paths=args.paths,
                sizes=tuple(args.sizes or (1024, 4096)), preset=args.preset, overrides=overrides)
    elif args.run:
        if args.out is None:
            ap.error("--run needs --out")
        run(args.run, args.out, torch.device(args.device), args.budget_s, hq_steps=args.hq_steps,
            lq_steps=args.lq_steps, backend=args.backend, sizes=tuple(args.sizes) if args.sizes else None,
            large_frames=args.large_frames or None)
    elif args.report:
        report(args.report)
    else:
        encode_check(args.encode_check, repeats=args.repeats)


if __name__ == "__main__":
    sys.exit(main())
