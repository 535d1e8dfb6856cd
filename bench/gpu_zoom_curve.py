"""The demo segment at a production-size budget through gsplat: detail and PSNR against time per
camera role (issue 28, "When a GPU is lent"), in three parts.

A GPU machine has no Prefect, pycolmap or OpenCV and no artifact store, so the work is split:

1. ``--prepare DIR --store S`` (here, on CPU): from a finished demo store (``demo/segment``'s
   capture and calibration, the PointCloudSequence made on that calibration) write into ``DIR``
   what training the demo segment needs, built by the library's own functions
   (:func:`volcap_core.reconstruction.segment_data`, :func:`~volcap_core.reconstruction.segment_init`):
   the footage of every (camera, frame) view as the capture stores it (half-float EXR bytes),
   each view's splat camera, the performer masks (the capture's ground truth) and the face regions
   (:func:`volcap_core.synth.ground_truth.face_region`, as ``fit_segment``'s ``head_region`` gives
   them), the initial points, the camera roles and held-out cameras (the demo preset's:
   :func:`~volcap_core.reconstruction.default_held_out`), and the quality preset: the demo preset
   with the production preset's Gaussians a frame, memory and MCMC schedule, stretched to
   ``--steps`` (:meth:`~volcap_core.production.presets.QualityPreset.with_steps`); the budget is its
   plan's (:meth:`~volcap_core.production.presets.QualityPreset.plan_segments`;
   ``--gaussians-per-frame`` replaces the production preset's Gaussians a frame: a CPU smoke
   test's tiny model).
2. ``--run DIR --out OUT --device cuda --budget-s 250`` (on the GPU machine): the segment trained by
   :func:`volcap_core.splat.train.train_segment` (the back-end its ``TrainConfig`` picks: gsplat on
   CUDA), its checkpoints (every ``steps / --evals`` steps and after the last) scored per camera
   role and view set with the region figures of ``volcap reconstruct --json``'s ``scores.regions``
   (:func:`volcap_core.splat.scoring.score_region` under the held-out protocol, composed as
   :func:`volcap_core.splat.report.score_segment` composes them; that module draws sheets with
   OpenCV, so it is not imported here, and the test holds the two equal); the empty and untrained
   models scored once on the same pixels (the floors; the untrained one is also step 0). The run
   stops early, at a scored checkpoint, when the next one would end past ``--budget-s`` seconds
   (loading and scoring included), and writes ``OUT/curve.json`` (the curve, the floors, the
   Gaussian count every few steps) and ``OUT/sheet.npz`` (the face crops of the zoom cameras,
   held out and training, at the segment's middle frame, untrained and trained).
3. ``--report OUT`` (here): the curve as a Markdown table for ``docs/benchmarks.md`` and the
   contact sheet (truth | render | error, :mod:`volcap_core.contact_sheet`) from ``OUT/sheet.npz``.

Two routes of issue 28 run through the same parts (``docs/poly4dgs.md``): ``--prepare ... --plates
DIR`` keeps the static cameras' clean plates in the folder and ``--run ... --set-steps N`` trains the
set from them first (:func:`plate_set`), then the performers alone over it (``train_segment``'s
``set_model``); ``--run ... --mcmc NAME=VALUE`` sets an MCMCConfig field over the prepared preset's
(``gradient_weight=2``: growth toward the under-fit), ``--lr NAME=VALUE`` a learning rate
(``scales=0.025``) and ``--train NAME=VALUE`` any TrainConfig field, its value JSON
(``init_lifespan_frames=1.5``; a field that reads the moving points' footprints needs a folder
prepared for a preset that reads them: ``init_model`` refuses points without them).

A real capture without ground truth (issue 30's GPU item: Pose2Sim at full resolution) is prepared
by ``bench/bench_pose2sim_heldout.py --gpu-prepare DIR``, which builds the segment and its initial
points with that bench's stages and writes them with :func:`write_prepared`: its frames rectified as
``segment_data`` gives them, as 8-bit sRGB PNG (decoded here with Pillow, no OpenCV), its own
performer masks (also the views' matte), no face regions (the figures have none), the held-out
camera named. ``--run`` and ``--report`` are the same; the sheet then shows the held-out camera
and one training camera, the whole frame at a quarter size and the performer at 1:1.

    python bench/gpu_zoom_curve.py --prepare .gpu-zoom --store /tmp/demo-base/store
    OUT=/tmp/gpu ZOOM_CURVE=.gpu-zoom PREPARED_ONLY=1 bash bench/gpu_checks.sh   # GPU; carry .gpu-zoom, .whl
    # with the demo preset's zoom points, velocities and footprints the folder is 51 MiB: over a GPU
    # call's 64 MiB with the tree and the wheels, so pack it (34.4 MiB) and carry .gpu-carry, .whl instead:
    tar cJf .gpu-carry/zoom.tar.xz .gpu-zoom
    OUT=/tmp/gpu ZOOM_CURVE=.gpu-carry/zoom.tar.xz PREPARED_ONLY=1 bash bench/gpu_checks.sh
    python bench/gpu_zoom_curve.py --report /path/to/OUT --sheet zoom_sheet.png
    python bench/bench_pose2sim_heldout.py --workdir W --held cam02 --scale 1 --dense-scale 0.25 \
        --steps 3000 --gpu-prepare .gpu-p2s   # the real capture
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

#: views of the training set whose region figures are scored (``score_segment``'s default)
TRAINING_VIEWS = 12
#: seconds kept back from the budget for writing the results
RESERVE_S = 5.0


# -------------------------------------------------------------------------------------- prepare

def _points_of(s, calibration) -> str:
    """The digest of the one PointCloudSequence record made on ``calibration`` in store ``s``."""
    from volcap_core.pointcloud import PointCloudSequence

    found = []
    for digest, info in s.iter_objects():
        if info.get("size", 0) > 1_000_000:
            continue
        data = s.get_bytes(digest, verify=False)
        if not data.startswith(b"{") or b'"method"' not in data or calibration.digest.encode() not in data:
            continue
        try:
            PointCloudSequence.model_validate_json(data)
        except ValueError:
            continue
        found.append(digest)
    if len(found) != 1:
        raise SystemExit(f"{s.url}: {len(found)} point cloud sequences on calibration {calibration.digest} "
                         "(name one with --points)")
    return found[0]


def demo_quality(steps: int, gaussians_per_frame: int | None = None):
    """The demo preset with the production preset's budget (Gaussians a frame, GPU memory) and MCMC
    schedule, stretched to ``steps``: the demo's cameras, held-out cameras and initialisation, at
    the size and schedule a production trains, the set trained to the end as a production trains it
    (the demo's ``set_frozen_from`` buys CPU steps; at a production budget it is unmeasured).
    ``gaussians_per_frame`` replaces the production preset's (a CPU smoke test's tiny model; None:
    the production's)."""
    from volcap_core.production.presets import named_preset

    demo, prod = named_preset("demo"), named_preset("production")
    return demo.with_overrides(
        train_steps=prod.train_steps, refine_start=prod.refine_start, refine_every=prod.refine_every,
        refine_stop=prod.refine_stop, eval_every=prod.eval_every, checkpoint_every=prod.checkpoint_every,
        gaussians_per_frame=gaussians_per_frame or prod.gaussians_per_frame, max_gaussians_per_segment=None,
        gpu_memory_gb=prod.gpu_memory_gb, set_frozen_from=prod.set_frozen_from).with_steps(steps)


def prepare(dst: Path, store_url: str, steps: int, *, capture: str | None = None, calibration: str | None = None,
            points: str | None = None, frames: tuple[int, int] = (0, 8), seed: int = 0,
            gaussians_per_frame: int | None = None, plates: Path | None = None) -> None:
    """Part 1 (module doc). ``gaussians_per_frame``: :func:`demo_quality`'s (None: the production
    preset's). ``plates``: a folder of the static cameras' clean background plates
    (``<camera>.exr``, as ``volcap synth --plates`` writes them beside the capture), copied into
    ``DIR/plates`` for ``--run --set-steps``: the set trained from them first."""
    from volcap_core import reconstruction
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture
    from volcap_core.pointcloud import PointCloudSequence
    from volcap_core.segment import tracking_frames
    from volcap_core.store import ArtifactStore
    from volcap_core.synth import ground_truth

    s = ArtifactStore(store_url)
    if capture is None or calibration is None:
        seg = s.get_record(s.get_ref("demo/segment"), reconstruction.SegmentModel)
        capture = capture or seg.capture.digest
        calibration = calibration or seg.calibration.digest
    cap_ref, calib_ref = s.resolve(capture), s.resolve(calibration)
    cap = s.get_record(cap_ref, Capture)
    calib = s.get_record(calib_ref, Calibration)
    pts_ref = s.resolve(points or _points_of(s, calib_ref))
    pts = s.get_record(pts_ref, PointCloudSequence)
    if pts.calibration.digest != calib_ref.digest:
        raise SystemExit(f"points {points}: made on calibration {pts.calibration.digest}, not {calib_ref.digest}")
    if cap.ground_truth is None:
        raise SystemExit(f"capture {cap.name}: no ground truth (the performer masks and faces come from it)")
    tree = s.get_tree(cap.ground_truth)
    files = ground_truth.GroundTruthFiles(cap.name, {p: e.digest for p, e in tree.items()}, s.get_bytes)
    scene = json.loads(files.read("scene.json"))
    load_mask = ground_truth.mask_loader(files)
    if load_mask is None:
        raise SystemExit(f"capture {cap.name}: its ground truth has no masks/ (synthesize with write_depth=True)")

    a, b = cap.take_range(frames)
    width = max(c.width for c in cap.cameras)
    height = max(c.height for c in cap.cameras)
    quality = demo_quality(steps, gaussians_per_frame)
    [planned] = quality.with_overrides(max_segment_frames=None).plan_segments((a, b), width, height).segments[:1]
    held = reconstruction.default_held_out(cap, calibration=calib, tracking=quality.held_out_tracking)
    config = quality.train_config(held_out=held, max_gaussians=planned.gaussians)
    data = reconstruction.segment_data(cap, calib, tracking_frames(s.get_bytes, calib), (a, b),
                                       reconstruction.FrameCache(s.get_bytes), scale=config.image_scale,
                                       load_mask=load_mask)
    if config.image_scale != 1 or any(v.valid is not None for v in data.views):
        raise SystemExit(f"capture {cap.name}: its views need resampling (scale {config.image_scale} or a "
                         "distorted lens), which needs OpenCV; the GPU run takes the footage as stored")
    t0 = time.perf_counter()
    init = reconstruction.segment_init(s.get_bytes, cap, pts, data, config.held_out_cameras,
                                       zoom_stride_px=config.init_zoom_stride_px,
                                       scene_flow=config.init_scene_flow)
    print(f"initial points: {sum(len(p.xyz) for p in init)} in {len(init)} clouds "
          f"({time.perf_counter() - t0:.1f} s)", flush=True)

    faces = {}
    for v in data.views:
        # what fit_segment's head_region gives score_segment for this view (its camera's K as it is)
        faces[(v.camera_id, v.frame)] = ground_truth.face_region(scene, v.time, v.camera.K.numpy(),
                                                                 v.camera.world_to_camera.numpy(),
                                                                 v.camera.width, v.camera.height)
    roles = {c.id: "static" if c.static else "tracking" for c in calib.cameras}
    meta = {"capture": cap.name, "capture_ref": cap_ref.digest, "calibration_ref": calib_ref.digest,
            "points_ref": pts_ref.digest,
            "store": str(store_url), "frames": [a, b], "fps": cap.fps, "seed": seed, "held_out": held,
            "roles": roles, "gaussians": planned.gaussians, "preset": quality.model_dump(mode="json")}
    write_prepared(dst, data, init, config, meta, faces=faces,
                   exr_bytes=lambda v: s.get_bytes(cap.camera(v.camera_id).frames[v.frame]))
    if plates is not None:
        from volcap_core.masks import plate_files

        files = plate_files(plates, [c for c, r in roles.items() if r == "static"])
        if not files:
            raise SystemExit(f"{plates}: no static camera's plate (<camera>.exr)")
        (dst / "plates").mkdir()
        for cam, path in files.items():
            if path.suffix.lower() != ".exr":
                raise SystemExit(f"{path}: a plate travels as the capture's half-float EXR only")
            shutil.copyfile(path, dst / "plates" / f"{cam}.exr")
        print(f"{dst}/plates: {', '.join(files)}", flush=True)


def write_prepared(dst: Path, data, init, config, meta: dict, *, faces: dict | None = None,
                   exr_bytes=None, performer_boxes: dict[str, tuple[int, int, int, int]] | None = None) -> None:
    """Write what ``--run`` loads (:class:`Prepared`) into ``dst`` (replaced): ``segment.json``
    (``meta`` and each view's camera), ``frames/``, ``masks.npz`` (each view's performer mask as
    ``View.load_mask`` gives it), ``init.safetensors`` (the initial points ``init``), and where
    they exist ``faces.npz`` (``faces``: ``(camera, frame)`` -> ``[H, W]`` bool face region),
    ``valid.npz`` (the pixels that hold footage after rectification), ``mattes.npz`` (a synthetic
    capture's own masks beside its ground truth, ``View.load_matte``: what the alpha loss trains
    toward, as the train-segment task's views carry them).

    Footage: ``exr_bytes(view)`` gives each view's half-float EXR as the capture stores it (its
    views neither resampled nor rectified); without it the views' images as ``segment_data`` gives
    them (rectified, resampled) are written as 8-bit sRGB PNG (a real capture is 8-bit video: its
    rectified frames rounded to the video's own depth, so that full-resolution footage fits the
    64 MiB a GPU call carries; decoded without OpenCV), and its masks are the capture's own (also
    the views' matte). ``performer_boxes``: camera -> ``(y0, y1, x0, x1)``, the sheet's 1:1 crop
    for a capture without face regions."""
    from volcap_core.colour import srgb_encode
    from volcap_core.contact_sheet import encode_png

    shutil.rmtree(dst, ignore_errors=True)   # another capture's files would travel
    (dst / "frames").mkdir(parents=True)
    views, masks, valid, mattes = [], {}, {}, {}
    for v in data.views:
        name = f"{v.camera_id}_{v.frame:06d}"
        if exr_bytes is not None:
            (dst / "frames" / f"{name}.exr").write_bytes(exr_bytes(v))
        else:
            codes = (srgb_encode(v.load()[..., :3].numpy()) * 255.0).round().clip(0, 255).astype(np.uint8)
            (dst / "frames" / f"{name}.png").write_bytes(encode_png(codes))
            ok = v.load_valid()
            if ok is not None:
                valid[name] = ok.numpy()
        masks[name] = v.load_mask().numpy().astype(np.float32)
        matte = v.load_matte() if exr_bytes is not None else None   # png: the masks are the capture's own
        if matte is not None:
            mattes[name] = matte.numpy().astype(np.float32)
        K, w2c = v.camera.K.numpy(), v.camera.world_to_camera.numpy()
        views.append({"camera": v.camera_id, "frame": v.frame, "time": v.time, "K": K.tolist(),
                      "world_to_camera": w2c.tolist(), "width": v.camera.width, "height": v.camera.height})
    np.savez_compressed(dst / "masks.npz", **masks)
    if faces is not None:
        np.savez_compressed(dst / "faces.npz", **{f"{c}_{f:06d}": m for (c, f), m in faces.items()})
    if valid:
        np.savez_compressed(dst / "valid.npz", **valid)
    if mattes:
        np.savez_compressed(dst / "mattes.npz", **mattes)
    (dst / "init.safetensors").write_bytes(initial_points_bytes(init, config))
    meta = dict(meta)
    if exr_bytes is None:
        meta["footage"] = "png"
    if performer_boxes is not None:
        meta["performer_boxes"] = {c: [int(x) for x in b] for c, b in performer_boxes.items()}
    meta["views"] = views
    (dst / "segment.json").write_text(json.dumps(meta, indent=1))
    size = sum(f.stat().st_size for f in dst.rglob("*") if f.is_file())
    a, b = meta["frames"]
    print(f"{dst}: {size / 2**20:.1f} MiB; {len(views)} views of {len(data.camera_ids)} cameras, frames {a}:{b}, "
          f"held out {', '.join(config.held_out_cameras)}; {meta['gaussians']} Gaussians, {config.steps} steps "
          f"(MCMC refinement {config.mcmc.refine_start}:{config.mcmc.refine_stop} every {config.mcmc.refine_every})")


def initial_points_bytes(init, config) -> bytes:
    """The initial points ``init`` (``PointsAtTime`` per cloud) as the safetensors file a prepared
    folder holds (``init.safetensors``; :func:`load_initial_points` reads it): footprints only where
    ``config`` (a TrainConfig or QualityPreset) makes ``init_model`` read them, and then the moving
    points' only (the static ones' inf: never read), floats as half where that loses nothing (the
    folder travels to a GPU within 64 MiB, wheels included)."""
    from safetensors.numpy import save as st_save

    footprints = config.init_moving_scale_px is not None or config.init_finest_level < 0
    clouds: dict[str, np.ndarray] = {}
    for i, p in enumerate(init):
        clouds[f"{i}/xyz"] = _compact(p.xyz.numpy())
        clouds[f"{i}/rgb"] = _compact(p.rgb.numpy())
        if p.static is not None:
            clouds[f"{i}/static"] = p.static.numpy().astype(np.uint8)
        if p.footprint is not None and footprints:
            foot = p.footprint.numpy().copy()
            if p.static is not None:   # init_model reads the moving points' alone: inf packs to nothing
                foot[p.static.numpy()] = np.inf
            clouds[f"{i}/footprint"] = _compact(foot)
        if p.velocity is not None:   # half precision where lossless (with_scene_flow's are)
            clouds[f"{i}/velocity"] = _compact(p.velocity.numpy())
    return st_save(clouds, {"times": json.dumps([p.time for p in init])})


def load_initial_points(path: Path) -> list:
    """:func:`initial_points_bytes`' file back as ``PointsAtTime`` (float32)."""
    from safetensors import safe_open

    from volcap_core.splat import PointsAtTime

    out = []
    with safe_open(str(path), framework="pt") as f:
        times = json.loads(f.metadata()["times"])
        keys = set(f.keys())
        for i, t in enumerate(times):
            static = f.get_tensor(f"{i}/static").bool() if f"{i}/static" in keys else None
            foot = f.get_tensor(f"{i}/footprint").float() if f"{i}/footprint" in keys else None
            vel = f.get_tensor(f"{i}/velocity").float() if f"{i}/velocity" in keys else None
            out.append(PointsAtTime(time=t, xyz=f.get_tensor(f"{i}/xyz").float(), rgb=f.get_tensor(f"{i}/rgb").float(),
                                    static=static, footprint=foot, velocity=vel))
    return out


def _compact(a: np.ndarray) -> np.ndarray:
    """``a`` (float32) as float16 where that loses nothing (colours sampled from half-float footage),
    else as it is."""
    h = a.astype(np.float16)
    return h if np.array_equal(h.astype(np.float32), a) else a


# ------------------------------------------------------------------------------------------ run

class Prepared:
    """What ``--prepare`` wrote, loaded: the segment's views (:class:`~volcap_core.splat.SegmentData`,
    footage decoded once), initial points, face regions (None for a capture without them: its
    figures have no face region), roles and the preset."""

    def __init__(self, src: Path):
        from volcap_core.production.presets import QualityPreset
        from volcap_core.splat import Camera, SegmentData, View

        path = src / "segment.json"
        if not path.is_file():
            raise SystemExit(f"{path}: missing (is {src} a folder written by --prepare?)")
        self.meta = json.loads(path.read_text())
        self.quality = QualityPreset.model_validate(self.meta["preset"])
        masks = np.load(src / "masks.npz")
        faces = np.load(src / "faces.npz") if (src / "faces.npz").is_file() else None
        valid = np.load(src / "valid.npz") if (src / "valid.npz").is_file() else None
        own_masks = self.meta.get("footage") == "png"   # a real capture's masks: its own, also the matte
        mattes = np.load(src / "mattes.npz") if (src / "mattes.npz").is_file() else None
        views = []
        self.faces = None if faces is None else {}
        for v in self.meta["views"]:
            name = f"{v['camera']}_{v['frame']:06d}"
            image = _footage(src / "frames", name)
            camera = Camera(K=torch.tensor(v["K"], dtype=torch.float32),
                            world_to_camera=torch.tensor(v["world_to_camera"], dtype=torch.float32),
                            width=v["width"], height=v["height"])
            mask = torch.from_numpy(masks[name])
            ok = torch.from_numpy(valid[name]) if valid is not None and name in valid.files else None
            matte = (mask if own_masks else torch.from_numpy(mattes[name])
                     if mattes is not None and name in mattes.files else None)
            views.append(View(v["camera"], v["frame"], v["time"], camera, image, mask, valid=ok, matte=matte))
            if faces is not None:
                self.faces[(v["camera"], v["frame"])] = faces[name]
        self.data = SegmentData(tuple(self.meta["frames"]), views)
        self.init = load_initial_points(src / "init.safetensors")
        #: camera -> its background plate ``[H, W, 3]`` linear (``--prepare --plates``), or empty
        self.plates = ({p.stem: _footage(src / "plates", p.stem) for p in sorted((src / "plates").glob("*.exr"))}
                       if (src / "plates").is_dir() else {})

    def config(self, steps: int | None = None, evals: int = 8, backend: str = "auto", mcmc: dict | None = None,
               lr: dict | None = None, train: dict | None = None):
        """The segment's TrainConfig: the preset (stretched to ``steps`` when given) at the prepared
        budget and held-out cameras, checkpoints ``evals`` times in the run (each is scored), no
        evaluation of the trainer's own (the run scores its checkpoints); ``mcmc``: MCMCConfig
        fields set as given (``--mcmc NAME=VALUE``), ``lr``: LearningRates fields (``--lr NAME=VALUE``),
        ``train``: TrainConfig fields (``--train NAME=VALUE``, validated as TrainConfig validates them)."""
        quality = self.quality if steps is None else self.quality.with_steps(steps)
        n = quality.train_steps
        config = quality.train_config(held_out=self.meta["held_out"], max_gaussians=self.meta["gaussians"],
                                      eval_every=0, checkpoint_every=max(1, n // max(1, evals)), backend=backend,
                                      **({"mcmc": dict(mcmc)} if mcmc else {}))
        if train:
            config = type(config).model_validate({**config.model_dump(), **train})
        return config.model_copy(update={"lr": config.lr.model_copy(update=lr)}) if lr else config

    def head_region(self, view) -> np.ndarray | None:
        return None if self.faces is None else self.faces[(view.camera_id, view.frame)]

    def crop_box(self, view) -> tuple[int, int, int, int]:
        """``(y0, y1, x0, x1)`` of the sheet's 1:1 crop of ``view``: around its face region (a third
        of its height beyond it) or, for a capture without faces, its camera's performer box."""
        h, w = view.camera.height, view.camera.width
        if self.faces is None:
            box = self.meta.get("performer_boxes", {}).get(view.camera_id)
            return tuple(box) if box else (0, h, 0, w)
        face = np.asarray(self.head_region(view))
        ys, xs = np.nonzero(face)
        if not len(ys):
            return 0, h, 0, w
        pad = max(4, int(ys.max() - ys.min()) // 3)
        return (max(0, ys.min() - pad), min(h, ys.max() + pad + 1), max(0, xs.min() - pad),
                min(w, xs.max() + pad + 1))


def _footage(folder: Path, name: str) -> torch.Tensor:
    """A view's footage ``[H, W, 3]`` linear float32: ``name.exr`` (half float, as a capture stores
    it) or ``name.png`` (8-bit sRGB: :func:`write_prepared`'s rectified real footage)."""
    exr, png = folder / f"{name}.exr", folder / f"{name}.png"
    if exr.is_file():
        from volcap_core.imageio.read import decode_exr

        pixels, _ = decode_exr(exr.read_bytes(), name=str(exr))
        return torch.from_numpy(np.ascontiguousarray(pixels[..., :3], dtype=np.float32))
    if not png.is_file():
        raise SystemExit(f"{folder}: no {name}.exr or {name}.png (is it a folder written by --prepare?)")
    from PIL import Image

    from volcap_core.colour import srgb_decode

    with Image.open(png) as im:
        codes = np.asarray(im.convert("RGB"))
    return torch.from_numpy(srgb_decode(codes.astype(np.float32) / 255.0))


def _pick(views, n: int) -> list:
    """At most ``n`` views spread evenly over the list, as ``score_segment`` picks its training views."""
    if len(views) <= n:
        return list(views)
    idx = np.linspace(0, len(views) - 1, n).round().astype(int)
    return [views[i] for i in sorted(set(idx.tolist()))]


class RegionScorer:
    """The figures :func:`volcap_core.splat.report.score_segment` reports (``regions``, and the
    ``held_out`` / ``training`` summaries) for a model on fixed views, the floors computed once.

    Held-out views: each model through its own cross-fitted gain/offset; training views
    (``score_segment``'s 12, spread over cameras and frames): the trained model through its grids,
    the floors through their cross-fitted gain/offset (they learned no grids).
    """

    def __init__(self, prep: Prepared, config, device, seed: int):
        from volcap_core.splat.train import frame_interval, init_model

        self.config, self.device, self.roles = config, device, prep.meta["roles"]
        held = set(config.held_out_cameras)
        self.views = {"held_out": [v for v in prep.data.views if v.camera_id in held],
                      "training": _pick([v for v in prep.data.views if v.camera_id not in held], TRAINING_VIEWS)}
        self.targets = {k: [v.load()[..., :3].to(device) for v in vs] for k, vs in self.views.items()}
        self.regions = {k: [self._view_regions(v, prep) for v in vs] for k, vs in self.views.items()}
        self.initial = init_model(prep.init, config, frame_interval_s=frame_interval(prep.data.times),
                                  generator=torch.Generator().manual_seed(seed)).to(device)
        #: floor name -> view set -> (raw renders, cross-fitted transforms)
        self.floor_renders = {name: {k: self._fit(m, k) for k in self.views}
                              for name, m in (("initial", self.initial), ("empty", None))}
        self.floors = {name: {k: [t.apply(r) for r, t in zip(*f[k])] for k in self.views}
                       for name, f in self.floor_renders.items()}

    @staticmethod
    def _view_regions(v, prep: Prepared) -> dict[str, torch.Tensor]:
        """The regions scored in ``v``: the performers and, where the capture has them, the face."""
        perf = v.load_mask() >= 0.5
        valid = v.load_valid()
        if valid is not None:
            perf = perf & valid
        if prep.faces is None:
            return {"performers": perf}
        return {"performers": perf, "face": perf & torch.as_tensor(prep.head_region(v), dtype=torch.bool)}

    def _fit(self, model, which: str) -> tuple[list[torch.Tensor], list]:
        """A model's renders of a view set and each one's cross-fitted gain/offset (its camera's,
        fitted on the other frames)."""
        from volcap_core.splat.scoring import cross_fitted_transforms
        from volcap_core.splat.train import render_views

        views = self.views[which]
        if not views:
            return [], []
        renders = render_views(model, views, self.config, device=self.device)
        return renders, cross_fitted_transforms(renders, self.targets[which], [v.camera_id for v in views],
                                                [v.frame for v in views], [v.load_valid() for v in views])

    def outputs(self, model, grids) -> dict[str, list]:
        """The trained model's outputs per view set, the figures taken on them, and
        ``"held_out_fit"``: its held-out renders and their transforms (for the raw figures)."""
        from volcap_core.splat.train import render_views

        renders = render_views(model, self.views["training"], self.config, device=self.device)
        held = self._fit(model, "held_out")
        return {"held_out": [t.apply(r) for r, t in zip(*held)], "held_out_fit": held,
                "training": [grids.apply(r, v.camera_id) for r, v in zip(renders, self.views["training"])]}

    def figures(self, outputs: dict[str, list[torch.Tensor]], *, floors: bool = False) -> dict:
        """``{"regions": view set -> role -> {"cameras", "trained": region -> figures}}`` as
        ``scores.regions`` (with ``floors``, also ``"initial"`` and ``"empty"``), per view set the
        PSNR/SSIM summary of the outputs (whole frame and performers; held out: raw and fitted),
        with ``floors`` the floors' summaries (``"floor_summaries"``: floor -> view set -> summary),
        and ``"held_out_raw"``: role -> model -> the held-out performers' figures in the raw renders."""
        from volcap_core.splat.scoring import mean_region_scores, score_region, score_views, summarise

        models = {"trained": outputs, **(self.floors if floors else {})}
        out: dict = {"regions": {}}
        for which, views in self.views.items():
            per_role: dict = {}
            for role in sorted({self.roles.get(v.camera_id, "static") for v in views}):
                idx = [i for i, v in enumerate(views) if self.roles.get(v.camera_id, "static") == role]
                per_role[role] = {"cameras": sorted({views[i].camera_id for i in idx}), **{
                    name: {region: mean_region_scores([score_region(o[which][i], self.targets[which][i],
                                                                    self.regions[which][i][region]) for i in idx])
                           for region in self.regions[which][idx[0]]} for name, o in models.items()}}
            out["regions"][which] = per_role
            if not views:
                continue
            masks, valid = [v.load_mask() for v in views], [v.load_valid() for v in views]
            summaries = {"trained": (outputs["held_out_fit"] if which == "held_out" else outputs[which])}
            if floors:   # the floors' whole-frame figures on the same views
                summaries.update({name: (r[which] if which == "held_out" else self.floors[name][which])
                                  for name, r in self.floor_renders.items()})
            for name, o in summaries.items():
                if which == "held_out":   # raw renders and their transforms: raw figures beside the fitted
                    renders, tfs = o
                    fig = summarise(score_views(renders, self.targets[which], [v.camera_id for v in views],
                                                [v.frame for v in views], masks, transforms=tfs,
                                                valid=valid)).to_json()
                else:   # through the grids (the floors through their fit): scored as it is
                    fig = summarise(score_views(o, self.targets[which], [f"{v.camera_id}#{v.frame}" for v in views],
                                                [0] * len(views), masks, valid=valid)).to_json()
                if name == "trained":
                    out[which] = fig
                else:
                    out.setdefault("floor_summaries", {}).setdefault(name, {})[which] = fig
        # the held-out performers in the raw renders (no colour transform: outside the protocol, what
        # the fitted figure flattens when the render does not correlate with the footage)
        raws = {"trained": outputs["held_out_fit"][0],
                **({name: r["held_out"][0] for name, r in self.floor_renders.items()} if floors else {})}
        held = self.views["held_out"]
        out["held_out_raw"] = {role: {name: mean_region_scores([
            score_region(r[i], self.targets["held_out"][i], self.regions["held_out"][i]["performers"])
            for i, v in enumerate(held) if self.roles.get(v.camera_id, "static") == role])
            for name, r in raws.items()} for role in sorted({self.roles.get(v.camera_id, "static") for v in held})}
        return out

    def sheet(self, outputs: dict[str, list[torch.Tensor]], model, grids, pick: list, prep: Prepared
              ) -> dict[str, np.ndarray]:
        """Crops of the views ``pick`` at 1:1 (:meth:`Prepared.crop_box`: the face, or a capture
        without faces the performer; linear float32, float16 without faces: full-resolution crops
        must come back in 16 MiB): ``<camera>/truth``, ``<camera>/face`` (bool: the region, the
        performers' without faces) and ``<camera>/initial``, ``<camera>/trained``: the model as
        scored (held-out views through the cross-fitted gain/offset; a training view through the
        grids, the untrained model's being the identity training starts from). Without faces also
        ``<camera>/trained_raw`` (a held-out view's render without its colour transform) and the
        whole frame at a quarter of the size, ``<camera>/whole/<truth|initial|trained>``."""
        from volcap_core.splat.train import render_views

        real = prep.faces is None
        out: dict[str, np.ndarray] = {}
        for v in pick:
            y0, y1, x0, x1 = prep.crop_box(v)
            region = np.asarray(prep.head_region(v)) if not real else v.load_mask().numpy() >= 0.5
            if v in self.views["held_out"]:
                i = self.views["held_out"].index(v)
                imgs = {"initial": self.floors["initial"]["held_out"][i], "trained": outputs["held_out"][i]}
                if real:
                    imgs["trained_raw"] = outputs["held_out_fit"][0][i]
            else:
                imgs = {"initial": render_views(self.initial, [v], self.config, device=self.device)[0],
                        "trained": grids.apply(render_views(model, [v], self.config, device=self.device)[0],
                                               v.camera_id)}
            dtype = np.float16 if real else np.float32
            truth = v.load()[..., :3]
            out[f"{v.camera_id}/truth"] = truth[y0:y1, x0:x1].numpy().astype(dtype)
            out[f"{v.camera_id}/face"] = region[y0:y1, x0:x1]
            for name, img in imgs.items():
                out[f"{v.camera_id}/{name}"] = img[y0:y1, x0:x1].detach().cpu().numpy().astype(dtype)
            if real:
                for name, img in (("truth", truth), ("initial", imgs["initial"]), ("trained", imgs["trained"])):
                    out[f"{v.camera_id}/whole/{name}"] = _quarter(img).astype(dtype)
        return out


def _quarter(img: torch.Tensor) -> np.ndarray:
    """``[H, W, 3]`` -> ``[H/4, W/4, 3]`` area-averaged, on the CPU."""
    x = img.detach().float().cpu().permute(2, 0, 1)[None]
    return torch.nn.functional.avg_pool2d(x, 4)[0].permute(1, 2, 0).numpy()


def sheet_views(prep: Prepared, config) -> list:
    """The views the sheet shows, at the segment's middle frame: the zoom (tracking) cameras', the
    held-out ones first, then the training ones (the demo's S010, then S008, S009, S011); on a rig
    without zoom cameras (Pose2Sim) the held-out cameras' and the first training camera's."""
    roles = prep.meta["roles"]
    mid = prep.data.frames[0] + (prep.data.frames[1] - prep.data.frames[0]) // 2
    at_mid = [v for v in prep.data.views if v.frame == mid]
    zoom = [v for v in at_mid if roles.get(v.camera_id) == "tracking"]
    held = set(config.held_out_cameras)
    if zoom:
        return [v for v in zoom if v.camera_id in held] + [v for v in zoom if v.camera_id not in held]
    return [v for v in at_mid if v.camera_id in held] + [v for v in at_mid if v.camera_id not in held][:1]


class _Stop(Exception):
    """The budget is spent: training ends at the last scored checkpoint."""


def plate_set(prep: Prepared, config, steps: int, gaussians: int, device: torch.device, seed: int):
    """The set trained once from the static training cameras' background plates (``--set-steps``;
    issue 28's route "the set trained once per capture"): the segment's static points (every
    cloud's, pooled) fitted by :func:`~volcap_core.splat.train.train_segment` to each static
    training camera's plate, as one frame at the segment's middle time (a static Gaussian's motion
    terms then get no gradient, so it stands still at every frame), with ``config``'s losses and
    schedule stretched to ``steps``, at most ``gaussians``, no performer terms (no alpha loss, a
    uniform camera schedule). Held-out cameras' plates stay out. Returns ``(set model, seconds of
    training)``."""
    from volcap_core.splat import PointsAtTime, SegmentData, View
    from volcap_core.splat.train import train_segment

    held = set(config.held_out_cameras)
    cams = [c for c in sorted(prep.plates) if c not in held and prep.meta["roles"].get(c) == "static"]
    if not cams:
        raise SystemExit("--set-steps: the prepared folder holds no training camera's plate (--prepare --plates)")
    times = sorted(prep.data.times)
    t_set = times[len(times) // 2]
    views = []
    for cam in cams:
        v = next(v for v in prep.data.views if v.camera_id == cam)
        views.append(View(cam, v.frame, t_set, v.camera, prep.plates[cam]))   # nothing scores these views
    clouds = [p for p in prep.init if p.static is not None and bool(p.static.any())]
    points = PointsAtTime(
        time=t_set, xyz=torch.cat([p.xyz[p.static] for p in clouds]), rgb=torch.cat([p.rgb[p.static] for p in clouds]),
        static=torch.ones(sum(int(p.static.sum()) for p in clouds), dtype=torch.bool),
        footprint=None if any(p.footprint is None for p in clouds) else torch.cat([p.footprint[p.static] for p in clouds]))
    set_config = prep.quality.with_steps(steps).train_config(
        held_out=[], max_gaussians=gaussians, eval_every=0, checkpoint_every=0, backend=config.backend)
    set_config = set_config.model_copy(update={"init_static_share": 1.0, "mask_alpha_weight": 0.0,
                                               "performer_view_weight": 0.0, "set_frozen_from": None})
    result = train_segment(SegmentData((views[0].frame, views[0].frame + 1), views), [points], set_config,
                           seed=seed, device=device)
    print(f"the set from {len(cams)} plates ({', '.join(cams)}): {len(result.model)} Gaussians, {steps} steps "
          f"in {result.wall_s:.1f} s", flush=True)
    return result.model, result.wall_s


def run(src: Path, out: Path, device: torch.device, budget_s: float, steps: int | None = None, evals: int = 8,
        backend: str = "auto", trace_every: int = 25, set_steps: int = 0, set_gaussians: int | None = None,
        mcmc: dict | None = None, lr: dict | None = None, train: dict | None = None) -> dict:
    """Part 2 (module doc). Returns what ``OUT/curve.json`` holds. ``set_steps`` > 0: the set is
    trained first from the folder's plates (:func:`plate_set`, at most ``set_gaussians``: default
    half the segment's budget) and the segment trains its performers alone over it
    (``train_segment``'s ``set_model``); its time is not within ``budget_s``'s training. ``mcmc``:
    MCMCConfig fields over the prepared preset's, ``lr`` LearningRates fields over TrainConfig's,
    ``train`` TrainConfig fields over the preset's (:meth:`Prepared.config`)."""
    from volcap_core.checkpoint import deterministic_torch
    from volcap_core.splat.render import resolve_backend
    from volcap_core.splat.train import _deserialise, train_segment

    t_start = time.perf_counter()

    def elapsed() -> float:
        return time.perf_counter() - t_start

    prep = Prepared(src)
    config = prep.config(steps, evals, backend, mcmc, lr, train)
    seed = int(prep.meta["seed"])
    chosen = resolve_backend(config.backend, device)
    curve: dict = {"device": str(device), "torch": torch.__version__,
                   "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
                   "backend": chosen.name, "backend_reason": chosen.reason, "capture": prep.meta["capture"],
                   "frames": prep.meta["frames"], "held_out": config.held_out_cameras, "roles": prep.meta["roles"],
                   "resolution": sorted({(v.camera.width, v.camera.height) for v in prep.data.views}),
                   "gaussians_cap": config.mcmc.cap_max, "steps": config.steps,
                   "checkpoint_every": config.checkpoint_every, "budget_s": budget_s,
                   "mcmc": config.mcmc.model_dump(), "train_config": config.model_dump(mode="json")}
    with deterministic_torch(device.type):
        t0 = time.perf_counter()
        scorer = RegionScorer(prep, config, device, seed)
        floors = scorer.figures({**scorer.floors["initial"], "held_out_fit": scorer.floor_renders["initial"]["held_out"]},
                                floors=True)
        curve["load_s"] = round(t0 - t_start, 2)
        curve["floors_s"] = round(time.perf_counter() - t0, 2)
        curve["floors"] = {which: {role: {k: r[k] for k in ("cameras", "initial", "empty")}
                                   for role, r in per_role.items()} for which, per_role in floors["regions"].items()}
        curve["floor_summaries"] = floors.get("floor_summaries", {})
        curve["floors_held_out_raw"] = {role: {k: r[k] for k in ("initial", "empty")}
                                        for role, r in floors["held_out_raw"].items()}
        points = [{"step": 0, "wall_s": 0.0, "elapsed_s": round(elapsed(), 2), "gaussians": len(scorer.initial),
                   "score_s": curve["floors_s"], "held_out": floors.get("held_out"),
                   "training": floors.get("training"), "regions": _trained_only(floors["regions"]),
                   "held_out_raw": {role: r["trained"] for role, r in floors["held_out_raw"].items()}}]
        trace: list[list] = []
        last: dict = {}
        pick = sheet_views(prep, config)
        _print_point(points[-1])

        def progress(step: int, total: int, info: dict) -> None:
            if step % trace_every == 0 or step == total:
                trace.append([step, round(info["wall_s"], 3), info["num_gaussians"], round(info["loss"], 5)])
            if elapsed() > budget_s - RESERVE_S:
                raise _Stop

        def checkpoint(blob: bytes, step: int) -> None:
            t = time.perf_counter()
            state, _, _ = _deserialise(blob, device)
            model, grids = state.model.detached(), state.grids
            outputs = scorer.outputs(model, grids)
            fig = scorer.figures(outputs)
            points.append({"step": step, "wall_s": round(state.wall_s, 3), "elapsed_s": round(elapsed(), 2),
                           "gaussians": len(model), "score_s": round(time.perf_counter() - t, 2),
                           "held_out": fig.get("held_out"), "training": fig.get("training"),
                           "regions": fig["regions"],
                           "held_out_raw": {role: r["trained"] for role, r in fig["held_out_raw"].items()}})
            last.update(model=model, grids=grids, outputs=outputs)
            _print_point(points[-1])
            # the next checkpoint, scored, would end past the budget: stop at this one
            since = points[-1]["elapsed_s"] - points[-2]["elapsed_s"]
            if step < config.steps and elapsed() + since > budget_s - RESERVE_S:
                raise _Stop

        set_model = None
        if set_steps:
            set_model, curve["set_train_s"] = plate_set(prep, config, set_steps,
                                                        set_gaussians or config.mcmc.cap_max // 2, device, seed)
            curve.update(set_steps=set_steps, set_gaussians=len(set_model))
        stopped = "steps"
        try:
            train_segment(prep.data, prep.init, config, set_model=set_model, checkpoint=checkpoint,
                          progress=progress, seed=seed, device=device)
        except _Stop:
            stopped = "budget"
        curve.update(points=points, trace=trace, stopped=stopped, elapsed_s=round(elapsed(), 2))
        # no checkpoint within the budget: no sheet (the curve says stopped at step 0)
        crops = scorer.sheet(last["outputs"], last["model"], last["grids"], pick, prep) if last else {}
    curve["sheet_step"] = points[-1]["step"]
    out.mkdir(parents=True, exist_ok=True)
    (out / "curve.json").write_text(json.dumps(curve, indent=1, default=float))
    buf = io.BytesIO()
    np.savez_compressed(buf, **crops)
    (out / "sheet.npz").write_bytes(buf.getvalue())
    print(f"{out}: curve.json ({len(points)} points, stopped by {stopped} at step {points[-1]['step']}), "
          f"sheet.npz; {elapsed():.1f} s in all", flush=True)
    return curve


def _trained_only(regions: dict) -> dict:
    return {which: {role: {k: r[k] for k in ("cameras", "trained")} for role, r in per_role.items()}
            for which, per_role in regions.items()}


def _fig(r: dict | None, key: str, digits: int) -> str:
    x = None if r is None else r.get(key)
    return "–" if x is None else f"{x:.{digits}f}"


def _print_point(p: dict) -> None:
    parts = []
    for which, per_role in p["regions"].items():
        for role, r in per_role.items():
            f = r["trained"]
            face = f" face {_fig(f['face'], 'psnr', 2)} dB det {_fig(f['face'], 'detail', 3)}" if "face" in f else ""
            parts.append(f"{which}/{role} perf {_fig(f['performers'], 'psnr', 2)} dB det "
                         f"{_fig(f['performers'], 'detail', 3)}{face}")
    held = p.get("held_out") or {}
    if held:
        parts.append(f"held-out whole {_fig(held, 'psnr', 2)} dB (raw {_fig(held, 'psnr_raw', 2)})")
    print(f"step {p['step']:>6} wall {p['wall_s']:8.1f} s elapsed {p['elapsed_s']:7.1f} s {p['gaussians']:>8} G  "
          + "; ".join(parts), flush=True)


# --------------------------------------------------------------------------------------- report

def _whole_table(curve: dict) -> None:
    """The whole-frame figures per scored step beside the floors: held out under the protocol
    (PSNR fitted / raw, performers fitted / raw) and the training views (PSNR, performers)."""
    def row(held: dict | None, raw: dict | None, training: dict | None) -> str:
        held, training = held or {}, training or {}
        perf_raw = None if not raw else _fig(raw.get("performers"), "psnr", 2)
        return (f"{_fig(held, 'psnr', 2)} / {_fig(held, 'psnr_raw', 2)} | {_fig(held, 'psnr_performers', 2)} / "
                f"{perf_raw or '–'} | {_fig(training, 'psnr', 2)} / {_fig(training, 'psnr_performers', 2)}")

    def raw_of(per_role: dict, key: str | None) -> dict | None:
        rs = [r if key is None else r.get(key) for r in per_role.values()]
        return rs[0] if len(rs) == 1 else None   # one held-out role: its figures (several: see curve.json)

    print("\n| step | train s | held-out PSNR fitted / raw | held-out performers fitted / raw | "
          "training views / performers |")
    print("|---|---|---|---|---|")
    for p in curve["points"]:
        print(f"| {p['step']} | {p['wall_s']:.1f} | "
              + row(p.get("held_out"), {"performers": raw_of(p.get("held_out_raw", {}), None)}, p.get("training")) + " |")
    for floor in ("empty", "initial"):
        f = curve["floor_summaries"].get(floor, {})
        print(f"| {floor} model (floor) | – | "
              + row(f.get("held_out"), {"performers": raw_of(curve.get("floors_held_out_raw", {}), floor)},
                    f.get("training")) + " |")


def report(out: Path, sheet: Path | None) -> None:
    """Part 3 (module doc)."""
    curve = json.loads((out / "curve.json").read_text())
    print(f"{curve['capture']} frames {curve['frames'][0]}:{curve['frames'][1]}, held out "
          f"{', '.join(curve['held_out'])}; {curve['gaussians_cap']} Gaussians cap, {curve['steps']} steps planned, "
          f"stopped by {curve['stopped']}; {curve['device']} ({curve['gpu']}), {curve['backend']}, "
          f"torch {curve['torch']}; {curve['elapsed_s']} s in all (load {curve['load_s']} s, floors {curve['floors_s']} s)")
    cols = [(which, role) for which, per_role in curve["floors"].items() for role in per_role]
    faces = any("face" in r["empty"] for per_role in curve["floors"].values() for r in per_role.values())
    head = "| step | train s | Gaussians | " + " | ".join(
        f"{which.replace('_', '-')} {role}: perf dB / detail" + (", face dB / detail" if faces else "")
        for which, role in cols) + " |"
    print(head)
    print("|" + "---|" * (3 + len(cols)))

    def cells(get) -> str:
        out = []
        for which, role in cols:
            f = get(which, role)
            face = f", {_fig(f['face'], 'psnr', 2)} / {_fig(f['face'], 'detail', 3)}" if f and "face" in f else ""
            out.append("–" if f is None else f"{_fig(f['performers'], 'psnr', 2)} / "
                       f"{_fig(f['performers'], 'detail', 3)}{face}")
        return " | ".join(out)

    for p in curve["points"]:
        print(f"| {p['step']} | {p['wall_s']:.1f} | {p['gaussians']} | "
              + cells(lambda w, r: p["regions"].get(w, {}).get(r, {}).get("trained")) + " |")
    for floor in ("empty", "initial"):
        print(f"| {floor} model (floor) | – | – | " + cells(lambda w, r: curve["floors"][w][r][floor]) + " |")
    print("cameras: " + "; ".join(f"{w} {r}: {', '.join(curve['floors'][w][r]['cameras'])}" for w, r in cols))
    if "floor_summaries" in curve:
        _whole_table(curve)
    crops = np.load(out / "sheet.npz")
    if sheet is not None and not crops.files:
        print("no sheet: the run stopped before its first checkpoint")
    elif sheet is not None:
        from volcap_core.contact_sheet import SheetRow, contact_sheet, write_sheet

        cams = sorted({k.split("/")[0] for k in crops.files}, key=lambda c: (c not in curve["held_out"], c))
        real = any("/whole/" in k for k in crops.files)   # a capture without faces: the performer
        region = "performer at 1:1" if real else "face"
        rows = []
        for cam in cams:
            role = "held out" if cam in curve["held_out"] else "training"
            mask = crops[f"{cam}/face"].astype(np.float32)
            steps = [("initial", "step 0"), ("trained", f"step {curve['sheet_step']}")]
            if real:
                rows += [SheetRow(f"{cam} ({role}) whole frame at 1/4, {label}", crops[f"{cam}/whole/truth"].astype(
                    np.float32), crops[f"{cam}/whole/{name}"].astype(np.float32)) for name, label in steps]
                if f"{cam}/trained_raw" in crops.files:
                    steps.append(("trained_raw", f"step {curve['sheet_step']}, raw render (no colour transform)"))
            for name, label in steps:
                rows.append(SheetRow(f"{cam} ({role}) {region}, {label}", crops[f"{cam}/truth"].astype(np.float32),
                                     crops[f"{cam}/{name}"].astype(np.float32), mask))
        what = "held-out and training cameras" if real else "zoom cameras' faces"
        write_sheet(sheet, contact_sheet(rows, title=f"{curve['capture']} {what}: truth | render | error"))
        print(f"sheet {sheet}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    part = ap.add_mutually_exclusive_group(required=True)
    part.add_argument("--prepare", metavar="DIR", type=Path)
    part.add_argument("--run", metavar="DIR", type=Path)
    part.add_argument("--report", metavar="OUT", type=Path)
    ap.add_argument("--store", default="/tmp/demo-base/store", help="a finished demo's store (--prepare)")
    ap.add_argument("--capture", help="capture ref (--prepare; default: demo/segment's)")
    ap.add_argument("--calibration", help="calibration ref (--prepare; default: demo/segment's)")
    ap.add_argument("--points", help="PointCloudSequence ref (--prepare; default: the one on the calibration)")
    ap.add_argument("--frames", nargs=2, type=int, default=(0, 8), metavar=("A", "B"), help="take frames [A, B)")
    ap.add_argument("--steps", type=int, default=None,
                    help="training steps: the schedule stretched to them (--prepare: default 3000; --run: the prepared)")
    ap.add_argument("--gaussians-per-frame", type=int, default=None,
                    help="--prepare: the budget a frame (default: the production preset's; small for a CPU smoke test)")
    ap.add_argument("--out", type=Path, help="where --run writes curve.json and sheet.npz")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--backend", default="auto", help="the rasterizer (auto: gsplat on CUDA)")
    ap.add_argument("--budget-s", type=float, default=250.0, help="--run stops at a scored checkpoint within this")
    ap.add_argument("--evals", type=int, default=8, help="scored checkpoints along the run")
    ap.add_argument("--sheet", type=Path, default=None, help="--report: write the face contact sheet here")
    ap.add_argument("--plates", type=Path, default=None,
                    help="--prepare: the static cameras' clean plates (<camera>.exr), kept for --set-steps")
    ap.add_argument("--set-steps", type=int, default=0,
                    help="--run: train the set from the prepared plates for this many steps first, then the "
                    "performers alone over it (0: the segment trains set and performers together)")
    ap.add_argument("--mcmc", action="append", default=[], metavar="NAME=VALUE",
                    help="--run: an MCMCConfig field over the prepared preset's (e.g. gradient_weight=2)")
    ap.add_argument("--lr", action="append", default=[], metavar="NAME=VALUE",
                    help="--run: a LearningRates field over TrainConfig's (e.g. sh0=0.01)")
    ap.add_argument("--train", action="append", default=[], metavar="NAME=VALUE",
                    help="--run: a TrainConfig field over the prepared preset's, its value JSON "
                    "(e.g. init_lifespan_frames=1.5, ssim_weight=0.4)")
    ap.add_argument("--set-gaussians", type=int, default=None,
                    help="--run --set-steps: the set's budget (default: half the segment's)")
    args = ap.parse_args(argv)
    if args.prepare:
        prepare(args.prepare, args.store, args.steps or 3000, capture=args.capture, calibration=args.calibration,
                points=args.points, frames=tuple(args.frames), gaussians_per_frame=args.gaussians_per_frame,
                plates=args.plates)
    elif args.run:
        if args.out is None:
            ap.error("--run needs --out")
        run(args.run, args.out, torch.device(args.device), args.budget_s, args.steps, args.evals, args.backend,
            set_steps=args.set_steps, set_gaussians=args.set_gaussians,
            mcmc={k: float(v) for k, v in (item.split("=", 1) for item in args.mcmc)},
            lr={k: float(v) for k, v in (item.split("=", 1) for item in args.lr)},
            train={k: json.loads(v) for k, v in (item.split("=", 1) for item in args.train)})
    else:
        report(args.report, args.sheet)


if __name__ == "__main__":
    sys.exit(main())
