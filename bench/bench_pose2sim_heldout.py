"""Pose2Sim SinglePerson with one camera held out: does a real capture's held-out view show its
performer? (issue 30; figures in ``docs/poly4dgs.md`` "Real footage" and ``docs/benchmarks.md``).

    python bench/bench_pose2sim_heldout.py --workdir W --held cam02 [--steps 250] [--gaussians 20000]
        [--fill-shell] [--mask-alpha 0.1] [--set-frozen-from F] [--no-scene-flow] [--hull-oracle] [--tag T]
        [--json out.json]
        [--sheet sheet.jpg]
        [--scale 1 --dense-scale 0.25 --gpu-prepare DIR [--gaussians-per-frame N]]

``../shared/data/real/pose2sim/Demo_SinglePerson``: 4 portrait phone cameras (1080x1920, 60 fps)
47-138 degrees apart filming a person dancing on a treadmill; its Qualisys calibration imported
(so the calibration is out of the question). Stages, each kept in the workdir and reused:

1. the capture folder (``--frames`` take frames from video frame ``--start``) with performer masks
   against each camera's background plate, the median of its whole video
   (:func:`volcap_core.masks.write_plate_masks`, ``whole_recording``), ingested into a store; the
   calibration imported;
2. dense points per frame at the training scale, the held-out camera left out
   (``dense_points_step``; ``--max-angle`` widens the sweep's triangulation angle so that a pair
   remains when cam01 or cam02 is held out);
3. training (``fit_segment``'s steps, ``train-segment``'s initial model: with the capture's masks
   it holds the performers' visual hull and drops the sweep's moving points outside the stage,
   :func:`volcap_core.reconstruction.with_performer_hull`; ``--fill-shell`` keeps the room shell's
   points no training camera sees, coloured by the median of the seen ones), then
   the scores with their floors: the whole held-out view and its performers (the capture's masks),
   each beside the empty and untrained models on the same pixels, and (outside the protocol,
   diagnostics) the raw renders' PSNR on the performers and their PSNR under a colour fit on the
   performers alone (:func:`performers_colour_fits`). ``--hull-oracle`` (a diagnostic) lets the
   held-out camera's mask carve the performers' hull too, its colours still the training views':
   the geometry a fourth silhouette would give. The trained model is kept in the workdir.

``--gpu-prepare DIR`` replaces stage 3: the same views (at ``--scale``, e.g. 1: full resolution) and
initial points (:func:`segment_inputs`), dense points at ``--dense-scale``, at a production budget,
written for ``bench/gpu_zoom_curve.py --run DIR`` on a GPU (its module doc; the command lines in
``docs/benchmarks.md``, "Pose2Sim: the held-out camera's performers").

The sheet: the first held-out frame's footage | render | error, the middle one's raw render, a
training camera, then every held-out frame's performer cropped at 1:1 of the training resolution,
as scored and raw.
~8 min a run on 2 busy cores (load 15-20; the first run adds ~6 min of masks, ingest and sweep).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.bench_dense_points import POSE2SIM_SIZES  # noqa: E402  (the repository on the path first)


def prepare(work: Path, start: int, frames: int) -> dict:
    """Stage 1 (cached in ``work/inputs.json``): capture folder with masks, ingest, calibration."""
    from bench.bench_dense_points import write_pose2sim_capture
    from flows.ingest import ingest_flow
    from flows.runtime import run_flow
    from volcap_core.masks import write_plate_masks
    from volcap_core.store import ArtifactStore

    done = work / "inputs.json"
    if done.exists():
        return json.loads(done.read_text())
    root = work / "capture"
    calib = write_pose2sim_capture(root, frames, start)
    t0 = time.perf_counter()
    write_plate_masks(root, whole_recording=True)
    masks_s = time.perf_counter() - t0
    store = ArtifactStore(str(work / "store"))
    capture = run_flow(ingest_flow, store=store.url, capture_dir=str(root)).result
    out = {"store": store.url, "capture": capture.digest, "calibration": store.put_record(calib).digest,
           "masks_s": round(masks_s, 1), "start": start, "frames": frames}
    done.write_text(json.dumps(out, indent=1))
    return out


def dense_points(inputs: dict, work: Path, held: str, scale: float, max_angle: float) -> str:
    """Stage 2: the segment's dense points without the held-out camera (cached by its arguments)."""
    from volcap_core.calibration.dense import DenseOptions
    from volcap_core.calibration.dense_points_step import dense_points_step
    from volcap_core.calibration.inputs import frame_loader
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture
    from volcap_core.pointcloud import PointCloudFrame, PointCloudSequence, encode_points
    from volcap_core.store import ArtifactStore

    key = f"points_{held}_{scale}_{max_angle}"
    cache = work / f"{key}.json"
    if cache.exists():
        return json.loads(cache.read_text())["points"]
    s = ArtifactStore(inputs["store"])
    cap = s.get_record(s.resolve(inputs["capture"]), Capture)
    calib_ref = s.resolve(inputs["calibration"])
    calib = s.get_record(calib_ref, Calibration)
    t0 = time.perf_counter()
    frames = []
    for f in range(cap.frame_count):
        d = dense_points_step(cap, calib, f, frame_loader(s.get_bytes, cap), DenseOptions(max_angle_deg=max_angle),
                              scale, exclude_cameras=[held])
        frames.append(PointCloudFrame(frame=f, time=cap.frame_time(f), count=len(d.positions),
                                      points=s.put_bytes(encode_points(d.positions, d.colours))))
        print(f"dense points frame {f}: {len(d.positions)} points", flush=True)
    ref = s.put_record(PointCloudSequence(calibration=calib_ref, frames=tuple(frames), method="plane-sweep"))
    cache.write_text(json.dumps({"points": ref.digest, "wall_s": round(time.perf_counter() - t0, 1),
                                 "counts": [p.count for p in frames]}))
    return ref.digest


def performer_box(masks, pad: int = 12) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)``: the box around the largest connected region of performer pixels
    (mask >= 0.5) over all ``masks`` [H, W] (a plate mask has specks of noise elsewhere)."""
    import numpy as np
    from scipy import ndimage

    m = np.any(np.stack([np.asarray(x) >= 0.5 for x in masks]), axis=0)
    labels, n = ndimage.label(ndimage.binary_closing(m, iterations=2))
    if n == 0:
        return 0, m.shape[0], 0, m.shape[1]
    biggest = 1 + int(np.argmax(ndimage.sum(np.ones_like(m), labels, range(1, n + 1))))
    ys, xs = np.nonzero(labels == biggest)
    h, w = m.shape
    return max(0, ys.min() - pad), min(h, ys.max() + pad + 1), max(0, xs.min() - pad), min(w, xs.max() + pad + 1)


def filled_shell(data, cap, held_out, time_s: float):
    """The room shell (``segment_init``'s last cloud) with every point, those no training camera
    sees coloured by the median of the seen ones instead of dropped (they are what a held-out
    camera sees beyond the training cameras' views: without them it renders black there)."""
    import numpy as np
    import torch

    from volcap_core import reconstruction
    from volcap_core.splat.init import colour_scan, room_shell
    from volcap_core.splat.train import PointsAtTime
    from volcap_core.stage import stage_volume

    background = reconstruction.background_views(data, cap, held_out)
    room = room_shell(np.array([v.camera.centre.double().numpy() for v in background]).reshape(-1, 3),
                      stage_volume(cap.rig.stage_size_m))
    rgb, seen = colour_scan(room, background)
    rgb[~seen] = np.median(rgb[seen], axis=0)
    print(f"room shell: {int((~seen).sum())} of {len(room)} points seen by no training camera", flush=True)
    shell = PointsAtTime(time=time_s, xyz=torch.from_numpy(room.astype(np.float32)), rgb=torch.from_numpy(rgb),
                         static=torch.ones(len(room), dtype=torch.bool))
    return reconstruction.with_footprints([shell], data, held_out)[0]


def performers_colour_fits(renders: dict, views) -> dict:
    """Diagnostics, outside the protocol: the held-out performers' PSNR (sRGB, masks >= 0.5) per
    model (``renders``: name -> the views' linear renders): ``raw`` (no colour transform), and under
    a gain/offset fitted on performer pixels only, ``cross_fitted`` on the other fold's performers
    (the protocol's folds) and ``oracle``, fitted on the view's own performers. The protocol fits the whole frame, where a
    room the training cameras never saw can pull the gain to 0; the oracle is what the best colour
    transform could score on these pixels whatever the rest of the frame, so a trained model that
    stays near the empty model's oracle is not held back by its background."""
    import numpy as np

    from volcap_core.colour import srgb_encode
    from volcap_core.image_metrics import region_psnr
    from volcap_core.splat.scoring import cross_fitted_transforms, fit_colour_transform

    truths = [v.load()[..., :3] for v in views]
    masks = [v.load_mask() >= 0.5 for v in views]

    def psnr(outputs) -> float:
        return round(float(np.mean([region_psnr(srgb_encode(o).clamp(0, 1), srgb_encode(t).clamp(0, 1), m)
                                    for o, t, m in zip(outputs, truths, masks)])), 3)

    out = {}
    for name, rs in renders.items():
        folds = cross_fitted_transforms(rs, truths, [v.camera_id for v in views], [v.frame for v in views], masks)
        own = [fit_colour_transform([r[m]], [t[m]]) for r, t, m in zip(rs, truths, masks)]
        out[name] = {"raw": psnr(rs), "cross_fitted": psnr([tf.apply(r) for tf, r in zip(folds, rs)]),
                     "oracle": psnr([tf.apply(r) for tf, r in zip(own, rs)])}
    return out


def segment_inputs(inputs: dict, points: str, args, config) -> tuple:
    """The segment's views and initial points as stage 3 trains them: ``(capture, calibration,
    SegmentData, initial points)`` at ``config``'s image scale, with ``args``' ``--fill-shell``,
    ``--clean-sweep`` and ``--hull`` applied (what ``--gpu-prepare`` writes too)."""
    from volcap_core import reconstruction
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture
    from volcap_core.pointcloud import PointCloudSequence
    from volcap_core.store import ArtifactStore

    s = ArtifactStore(inputs["store"])
    cap = s.get_record(s.resolve(inputs["capture"]), Capture)
    calib = s.get_record(s.resolve(inputs["calibration"]), Calibration)
    pts = s.get_record(s.resolve(points), PointCloudSequence)
    data = reconstruction.segment_data(cap, calib, None, (0, cap.frame_count), reconstruction.FrameCache(s.get_bytes),
                                       scale=config.image_scale)
    init = reconstruction.segment_init(s.get_bytes, cap, pts, data, config.held_out_cameras,
                                       hull_oracle_cameras=config.held_out_cameras if args.hull_oracle else (),
                                       scene_flow=config.init_scene_flow)
    if args.fill_shell:   # the room shell's points no training camera sees: the seen points' median colour
        init = list(init[:-1]) + [filled_shell(data, cap, config.held_out_cameras, init[-1].time)]
    print("initial points a cloud:", [len(p.xyz) for p in init], flush=True)
    return cap, calib, data, init


def gpu_prepare(inputs: dict, points: str, args) -> None:
    """``--gpu-prepare DIR``: the segment at ``--scale`` with the same initial points as stage 3
    (:func:`segment_inputs`), at a production budget (``bench/gpu_zoom_curve.py``'s
    :func:`demo_quality`: the production preset's Gaussians a frame and MCMC schedule stretched to
    ``--steps``; ``--gaussians-per-frame`` a CPU check's), written for ``gpu_zoom_curve.py --run``
    (:func:`write_prepared`: the rectified frames as 8-bit PNG, the capture's masks, no faces),
    with each camera's performer box (:func:`performer_box`) for the sheet's 1:1 crops."""
    import numpy as np

    from bench.gpu_zoom_curve import demo_quality, write_prepared
    from volcap_core import reconstruction
    from volcap_core.capture import Capture
    from volcap_core.store import ArtifactStore

    quality = demo_quality(args.steps, args.gaussians_per_frame).with_overrides(train_scale=args.scale)
    n = inputs["frames"]
    s = ArtifactStore(inputs["store"])
    cap = s.get_record(s.resolve(inputs["capture"]), Capture)
    width, height = max(c.width for c in cap.cameras), max(c.height for c in cap.cameras)
    [planned] = quality.with_overrides(max_segment_frames=None).plan_segments((0, n), width, height).segments[:1]
    config = quality.train_config(held_out=[args.held], max_gaussians=planned.gaussians)
    cap, calib, data, init = segment_inputs(inputs, points, args, config)
    boxes = {}
    for c in data.camera_ids:
        masks = [v.load_mask() for v in data.views if v.camera_id == c]
        if all(m is not None for m in masks):
            boxes[c] = performer_box([np.asarray(m) for m in masks], pad=max(12, round(12 * args.scale / 0.25)))
    meta = {"capture": cap.name, "capture_ref": inputs["capture"], "calibration_ref": inputs["calibration"],
            "points_ref": points, "store": inputs["store"], "frames": [0, n], "fps": cap.fps, "seed": 0,
            "held_out": [args.held], "roles": {c.id: "static" if c.static else "tracking" for c in calib.cameras},
            "gaussians": planned.gaussians, "preset": quality.model_dump(mode="json"),
            "video_frames": [inputs["start"], inputs["start"] + n], "dense_scale": args.dense_scale,
            "init": {"performer_hull": reconstruction.has_performer_mattes(data, [args.held]),
                     "fill_shell": args.fill_shell}}
    write_prepared(args.gpu_prepare, data, init, config, meta, performer_boxes=boxes)


def train(inputs: dict, points: str, args) -> dict:
    """Stage 3: train, score against the floors, draw the sheet."""
    import numpy as np
    import torch

    from volcap_core import reconstruction
    from volcap_core.contact_sheet import SheetRow, contact_sheet, encode_jpeg
    from volcap_core.production.presets import named_preset
    from volcap_core.splat import train_segment
    from volcap_core.splat.report import score_segment
    from volcap_core.splat.scoring import cross_fitted_transforms, score_views
    from volcap_core.splat.train import render_views

    overrides = {"eval_every": 0, "image_scale": args.scale}
    if args.mask_alpha:
        overrides["mask_alpha_weight"] = args.mask_alpha
    if args.set_frozen_from is not None:
        overrides["set_frozen_from"] = args.set_frozen_from or None
    if args.no_scene_flow:   # the moving Gaussians as before the demo preset's initial motion
        overrides.update(init_scene_flow=False, init_lifespan_frames=0.7)
    config = named_preset("demo").with_steps(args.steps).train_config(held_out=[args.held],
                                                                      max_gaussians=args.gaussians, **overrides)
    cap, calib, data, init = segment_inputs(inputs, points, args, config)
    n = cap.frame_count
    torch.manual_seed(0)
    t0 = time.perf_counter()
    result = train_segment(data, init, config, seed=0, device="cpu")
    wall = time.perf_counter() - t0
    roles = {c.id: "static" for c in calib.cameras}
    report = score_segment(result.model, result.grids, data, init, config, seed=0, device="cpu", roles=roles)
    out = {"held": args.held, "steps": args.steps, "gaussians": args.gaussians, "fill_shell": args.fill_shell,
           "performer_hull": reconstruction.has_performer_mattes(data, [args.held]),
           "mask_alpha": args.mask_alpha, "scale": args.scale, "train_wall_s": round(wall, 1),
           "gaussians_final": len(result.model), "held_out": {k: v.to_json() for k, v in report.held_out.items()},
           "training": report.training.to_json(), "regions": report.regions,
           "init_points": sum(len(p.xyz) for p in init)}

    # the sheet: a held-out frame whole, its raw render, a training camera, the performer cropped at 1:1
    held_views = [v for v in data.views if v.camera_id == args.held]
    renders = render_views(result.model, held_views, config, device="cpu")
    # diagnostics, outside the protocol: the performers raw and under a colour fit of their own
    from volcap_core.splat.train import frame_interval, init_model
    initial = init_model(init, config, frame_interval_s=frame_interval(data.times),
                         generator=torch.Generator().manual_seed(0))
    raw = {"trained": renders, "initial": render_views(initial, held_views, config, device="cpu"),
           "empty": [torch.zeros_like(r) for r in renders]}
    out["performers_raw_psnr"] = None
    if all(v.load_mask() is not None for v in held_views):
        fits = performers_colour_fits(raw, held_views)
        out["performers_raw_psnr"] = {k: f.pop("raw") for k, f in fits.items()}
        out["performers_colour_fit_diagnostic"] = fits
    from volcap_core.splat import save_model
    (args.workdir / f"model_{args.held}_{args.tag}.safetensors").write_bytes(save_model(result.model))
    tfs = cross_fitted_transforms(renders, [v.load()[..., :3] for v in held_views],
                                  [v.camera_id for v in held_views], [v.frame for v in held_views],
                                  [v.load_valid() for v in held_views])   # as score_segment fits them
    masks = [v.load_mask() for v in held_views]
    box = performer_box([m.numpy() for m in masks if m is not None]) if any(m is not None for m in masks) else None
    rows_full, rows_crop, rows_raw = [], [], []
    for v, r, tf, m, sc in zip(held_views, renders, tfs, masks, report.views):
        truth = v.load()[..., :3].numpy()
        out_img = tf.apply(r).detach().numpy()
        perf = "" if sc.psnr_performers is None else f", performers {sc.psnr_performers:.1f} dB"
        label = f"{v.camera_id} frame {v.frame} HELD OUT: PSNR {sc.psnr:.1f} dB{perf}"
        rows_full.append(SheetRow(label, truth, out_img, None if m is None else m.numpy()))
        if v.frame == n // 2:   # what the colour fit flattens: the render as it comes out
            rows_raw.append(SheetRow(f"{v.camera_id} frame {v.frame} HELD OUT, raw render (no colour transform, "
                                     f"outside the protocol): PSNR {sc.psnr_raw:.1f} dB", truth, r.detach().numpy(),
                                     None if m is None else m.numpy()))
        if box is not None:
            y0, y1, x0, x1 = box
            rows_crop.append(SheetRow(f"{v.camera_id} frame {v.frame} performer at 1:1", truth[y0:y1, x0:x1],
                                      out_img[y0:y1, x0:x1], m.numpy()[y0:y1, x0:x1]))
            rows_crop.append(SheetRow(f"{v.camera_id} frame {v.frame} performer at 1:1, raw render (outside the "
                                      f"protocol)", truth[y0:y1, x0:x1], r.detach().numpy()[y0:y1, x0:x1],
                                      m.numpy()[y0:y1, x0:x1]))
    train_cam = min(c for c in data.camera_ids if c != args.held)
    tv = [v for v in data.views if v.camera_id == train_cam and v.frame == n // 2][0]
    tr = result.grids.apply(render_views(result.model, [tv], config, device="cpu")[0], tv.camera_id)
    tp = score_views([tr], [tv.load()[..., :3]], ["x"], [0])[0].psnr
    rows_train = [SheetRow(f"{tv.camera_id} frame {tv.frame} training: PSNR {tp:.1f} dB", tv.load()[..., :3].numpy(),
                           tr.detach().numpy(), None if tv.load_mask() is None else tv.load_mask().numpy())]
    title = f"Pose2Sim {args.held} held out, {args.steps} steps: footage | render | error"
    if args.sheet:
        w = data.views[0].camera.width
        full = contact_sheet(rows_full[:1] + rows_raw + rows_train, title=title, max_width=3 * w + 16)
        parts = [full]
        if rows_crop:
            cw = rows_crop[0].truth.shape[1]
            parts.append(contact_sheet(rows_crop, max_width=3 * cw + 16))
        width = max(p.shape[1] for p in parts)
        pad = [np.pad(p, ((0, 0), (0, width - p.shape[1]), (0, 0)), constant_values=24) for p in parts]
        Path(args.sheet).write_bytes(encode_jpeg(np.concatenate(pad, 0), quality=90))
        out["sheet"] = args.sheet
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", type=Path, required=True)
    ap.add_argument("--held", default="cam02", choices=sorted(POSE2SIM_SIZES))
    ap.add_argument("--start", type=int, default=48, help="video frame of the take's first frame")
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--scale", type=float, default=0.25, help="training (and dense points) scale")
    ap.add_argument("--max-angle", type=float, default=70.0, help="dense points' triangulation angle limit (deg)")
    ap.add_argument("--steps", type=int, default=250)
    ap.add_argument("--gaussians", type=int, default=20000)
    ap.add_argument("--fill-shell", action="store_true", help="keep the room shell's unseen points, median-coloured")
    ap.add_argument("--mask-alpha", type=float, default=0.0, help="TrainConfig.mask_alpha_weight")
    ap.add_argument("--set-frozen-from", type=float, default=None,
                    help="TrainConfig.set_frozen_from (0: the set trains to the end; default: the demo preset's)")
    ap.add_argument("--no-scene-flow", action="store_true",
                    help="the moving Gaussians without their initial velocity, living ~1 frame (the demo preset "
                         "before 2026-11-29)")
    ap.add_argument("--hull-oracle", action="store_true",
                    help="diagnostic: the held-out camera's mask carves the performers' hull too (colours nothing)")
    ap.add_argument("--tag", default="run", help="names the saved model in the workdir")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--sheet", type=str)
    ap.add_argument("--gpu-prepare", type=Path, metavar="DIR",
                    help="instead of training: write DIR for bench/gpu_zoom_curve.py --run at --scale (a GPU's run)")
    ap.add_argument("--dense-scale", type=float, default=None,
                    help="dense points' scale (default: --scale; the GPU preparation's 0.25, the CPU runs' points)")
    ap.add_argument("--gaussians-per-frame", type=int, default=None,
                    help="--gpu-prepare: the budget a frame (default: the production preset's)")
    args = ap.parse_args(argv)
    if args.dense_scale is None:
        args.dense_scale = args.scale
    import torch

    torch.set_num_threads(args.threads)
    args.workdir.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    inputs = prepare(args.workdir, args.start, args.frames)
    points = dense_points(inputs, args.workdir, args.held, args.dense_scale, args.max_angle)
    if args.gpu_prepare:
        gpu_prepare(inputs, points, args)
        return
    out = train(inputs, points, args)
    text = json.dumps(out, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text)


if __name__ == "__main__":
    main()
