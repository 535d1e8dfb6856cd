"""The demo: every stage that exists, run on the built-in synthetic capture.

the static cameras' performer masks against the synthesizer's clean plates, shadows left out (``volcap masks --plates --drop-shadows``)
→ ingest → calibrate (static cameras, tracking cameras, dense points of the frames reconstructed) →
reconstruct (Poly4DGS, one segment of the first 8 frames to the preset's Gaussian budget, on the
estimated calibration, scored on held-out cameras (the demo preset holds out one static and one tracking
camera: S004 and S010) against the empty- and untrained-model floors) → the segment's contact sheet
(footage | render | error) as ``demo/contact_sheet.png``, a held-out camera's view at the segment's
middle rendered to EXR and the Gaussians there exported as PLY; the calibration's error against the
capture's ground truth is reported; then the product (issue 27), a production on the demo capture:

- a Face Rig capture of one of the demo's actors (``demo/face_capture``: the ``demo_face`` rig, as
  many frames as the preset's Face Rig pairs need);
- a production spec (``demo/production.yaml``, rerun it with ``volcap run``): the demo capture by
  ref, the face capture by folder, that actor with both, and one close-up shot of the actor
  (:func:`closeup_shot`) with ``enhance: true``;
- the spec run by the production flow in this process, on the demo's cached ingest, calibration
  and segment (:func:`check_segment_reused` refuses a plan that would train another segment
  before anything runs): the enhancer trained on the actor's Face Rig pairs, the shot rendered and
  enhanced.

``enhancer``: the enhancer's budget, a key of :data:`ENHANCER_RUNS` (the demo preset's short
run by default; ``docs/enhancer.md``, "The demo's close-up").
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from prefect import flow, get_run_logger

from flows.ingest import ingest_flow
from flows.production import open_production, production_flow, segment_train_config
from flows.reconstruct import reconstruct_flow
from flows.truth import truth_flow
from tasks.calibrate import calibration_errors
from tasks.production import score_shot
from tasks.reconstruct import render_views
from volcap_core.capture import Capture
from volcap_core.enhance.production import EnhancerModel, PairDataset, pair_record
from volcap_core.masks import write_plate_masks
from volcap_core.segment import tracking_frames
from volcap_core.view import ViewSpec
from volcap_core.calibration.record import Calibration, camera_at
from volcap_core.production.presets import named_preset
from volcap_core.reconstruction import SegmentModel
from volcap_core.splat import export_ply, load_model
from volcap_core.store import ArtifactStore
from volcap_core.synth.synthesize import PLATES_DIR

#: The production the demo writes and runs (its journal and refs in the store are named after it).
PRODUCTION = "demo-closeup"
#: The demo actor the close-up shows and whose Face Rig capture trains the enhancer.
ACTOR_INDEX = 0
#: The close-up's lens on a 36 mm-wide sensor (a portrait lens, within issue 27's 50–85 mm) and its
#: distance from the head: the head and shoulders fill the frame (at 65 mm a 16:9 frame is 0.47 m
#: tall at 1.5 m).
CLOSEUP_FOCAL_MM = 65.0
CLOSEUP_SENSOR_MM = 36.0
CLOSEUP_DISTANCE_M = 1.5

#: The enhancer's budget (quality fields over the ``demo`` preset's). ``demo``: the preset's
#: smoke run (the tiny CPU model from random weights, 30 VAE + 20 transformer steps on 2 × 4-frame
#: sub-sequences of 128-px pairs from 2 cameras): it shows the machinery, not an enhancer that has
#: learned. ``long``: the enhancer bench's recipe (bench/bench_enhance.py FULL): the ``small()``
#: model; 3000 VAE steps at 3e-3 on 64-px crops, then 1500 at 1e-3 and 1500 at 3e-4; 12 000
#: transformer steps on 128-px crops at 1e-3 after a 50-step warm-up, a fifth of it for the last
#: third; 8 sampling steps on 128-px tiles from strength 0.4 (the demo preset's); 256-px head
#: windows at the capture's pixels, from 3 × 8-frame sub-sequences of 6 cameras (the bench's 144
#: frames): about an hour of CPU (docs/benchmarks.md, "Detail enhancer").
ENHANCER_RUNS: dict[str, dict[str, Any]] = {
    "demo": {},
    "long": dict(face_subsequences=3, face_subsequence_frames=8, face_camera_paths=6, pair_resolution=256,
                 pair_window="head", enhancer_architecture="small", enhancer_vae_steps=3000,
                 enhancer_vae_lr=3e-3, enhancer_vae_crop=64, enhancer_vae_stages=((1500, 1e-3), (1500, 3e-4)),
                 enhancer_steps=12_000, enhancer_crop=128, enhancer_lr=1e-3, enhancer_warmup_steps=50,
                 enhancer_lr_decay=((8000, 0.2),), enhancer_checkpoint_every=500, enhancer_sampling_steps=8,
                 enhancer_tile=128),
}


@flow(name="demo", persist_result=False)
def demo_flow(store: str, capture_dir: str, out_dir: str, preset: str = "demo", enhancer: str = "demo") -> dict:
    """Run the pipeline on the demo capture; returns the references a coordinator would look at.
    ``enhancer``: a key of :data:`ENHANCER_RUNS`."""
    if enhancer not in ENHANCER_RUNS:
        raise ValueError(f"unknown enhancer run {enhancer!r}: choose one of {', '.join(ENHANCER_RUNS)}")
    log = get_run_logger()
    s = ArtifactStore(store)
    plates = Path(capture_dir) / PLATES_DIR
    if plates.is_dir():
        # the static cameras' performer masks against their clean plates, as `volcap masks --plates
        # --drop-shadows` writes them (the performers' shadows on the floor left out): the capture's
        # own masks, which start each segment from the performers' visual hull and train their
        # alpha (the demo preset's mask_alpha_weight; docs/poly4dgs.md)
        write_plate_masks(capture_dir, plates=plates, drop_shadows=True)
    capture = ingest_flow(store=store, capture_dir=capture_dir)
    # The first third of the take, one segment at the preset's budget (the demo preset's 10,000
    # Gaussians a frame): at demo size a whole take spreads the Gaussians too thin per instant (each
    # lives ~1.5 frames), and a reviewer wants a legible view.
    recon = reconstruct_flow(store=store, capture=capture.digest, frames=(0, 8), preset=preset)
    seg_ref = s.resolve(recon["segments"][0]["model"]["digest"])
    seg = s.get_record(seg_ref, SegmentModel)
    calib_ref = s.resolve(recon["calibration"]["digest"])
    points_ref = s.resolve(recon["points"]["digest"])
    errors = s.get_json(calibration_errors(store, capture, calib_ref, points_ref))

    # A held-out camera (never trained on) at mid-take: the view a reviewer looks at first.
    calib = s.get_record(seg.calibration, Calibration)
    camera = seg.held_out_cameras[0] if seg.held_out_cameras else calib.cameras[0].id
    mid = (seg.frames[0] + seg.frames[1]) // 2
    K, w2c, w, h = camera_at(calib, camera, mid, tracking_frames(s.get_bytes, calib))
    [view] = render_views(store, seg_ref, [ViewSpec(K=K.tolist(), world_to_camera=w2c.tolist(), width=w, height=h,
                                                    time_s=mid / seg.fps)])
    out = Path(out_dir)
    s.get_file(view, out / f"render_{camera}_frame{mid:03d}.exr")
    sheet = out / "contact_sheet.png"
    s.get_file(seg.contact_sheet, sheet)
    summary_seg = recon["segments"][0]
    (out / f"gaussians_frame{mid:03d}.ply").write_bytes(export_ply(load_model(s.get_bytes(seg.model)), mid / seg.fps))
    s.set_ref("demo/segment", seg_ref)
    s.set_ref("demo/calibration", calib_ref)
    summary = calibration_summary(errors)
    log.info("calibration: %s", ", ".join(f"{k} {v}" for k, v in summary.items()))
    log.info("held-out PSNR %s dB (empty model %s, untrained %s); contact sheet %s",
             _r(summary_seg["held_out_psnr"]), _r(summary_seg["floor_empty_psnr"]),
             _r(summary_seg["floor_initial_psnr"]), sheet)
    keys = ("held_out_psnr", "held_out_ssim", "held_out_psnr_raw", "held_out_psnr_performers",
            "held_out_ssim_performers", "floor_empty_psnr", "floor_empty_ssim", "floor_initial_psnr",
            "floor_initial_ssim", "training_psnr", "training_ssim")
    closeup = closeup_production(store, Path(capture_dir), out, capture_ref=capture, segment_ref=seg_ref,
                                 preset=preset, enhancer=enhancer)
    return {"capture": capture.model_dump(mode="json"), "calibration": calib_ref.model_dump(mode="json"),
            "points": points_ref.model_dump(mode="json"), "calibration_errors": summary,
            "segment": seg_ref.model_dump(mode="json"),
            **{k: _r(summary_seg[k], 4) for k in keys},
            "contact_sheet": str(sheet),
            "render": str(out / f"render_{camera}_frame{mid:03d}.exr"),
            "ply": str(out / f"gaussians_frame{mid:03d}.ply"),
            "closeup": closeup}


def _r(x: float | None, digits: int = 2) -> float | None:
    return None if x is None else round(float(x), digits)


def calibration_summary(errors: dict) -> dict:
    """A few headline numbers of the calibration error table (rounded), for the demo's report."""
    out = {}
    st = errors.get("static") or {}
    if st:
        out["static_rotation_deg_mean"] = round(st["rotation_deg_mean"], 3)
        out["static_centre_pct_max"] = round(100 * st["centre_frac_max"], 2)
    tr = (errors.get("tracking") or {}).get("priors")
    if tr:
        out["tracking_focal_pct_max"] = round(tr["focal_pct_max_abs"], 2)
        out["tracking_pose_jitter_px_mean"] = round(tr["pose_jitter_px_mean"], 2)
    pts = errors.get("points") or {}
    if pts.get("median_distance_m") is not None:
        out["points_median_distance_mm"] = round(1000 * pts["median_distance_m"], 1)
    return out


# ---------------------------------------------------------------------------------------------
# The product: a close-up of a demo actor, enhanced (issue 27)
# ---------------------------------------------------------------------------------------------


def head_track(scene: Mapping[str, Any], actor: int, frames: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """From a synthetic capture's ``ground_truth/scene.json``: actor ``actor``'s head centre at each
    take index of ``frames`` (``[F, 3]`` metres, stage frame) and the direction the face looks at
    the middle one (``[3]``, horizontal unit vector: the head's local x axis, ``docs/synth.md``)."""
    actors = scene.get("actors") or []
    if not 0 <= actor < len(actors):
        raise ValueError(f"scene.json: no actor {actor} (the capture has {len(actors)})")
    by_index = {f["take_index"]: f for f in actors[actor]["frames"]}
    missing = [k for k in frames if k not in by_index]
    if missing:
        raise ValueError(f"scene.json: actor {actor} has no ground truth at take indices {missing}")
    heads = np.array([by_index[k]["head_centre_m"] for k in frames], np.float64)
    facing = np.asarray(by_index[frames[len(frames) // 2]]["head_rotation"], np.float64)[:, 0]
    facing[2] = 0.0
    norm = float(np.linalg.norm(facing))
    if norm < 1e-6:
        raise ValueError(f"scene.json: actor {actor}'s head looks straight up or down at take index "
                         f"{frames[len(frames) // 2]}: no horizontal facing to place a close-up camera")
    return heads, facing / norm


def footage_density(calib: Calibration, tracking, points: np.ndarray, frames: Sequence[int],
                    cameras: Sequence[str]) -> float:
    """Pixels per metre of the finest footage at a moving point: for each take index, the largest
    ``sqrt(fx fy) / depth`` over ``cameras`` that see ``points[i]`` (``[F, 3]`` metres) inside
    their image, then the median over the frames. Occlusion is not checked."""
    per_frame = []
    for k, p in zip(frames, points):
        best = 0.0
        for cam in cameras:
            K, w2c, w, h = camera_at(calib, cam, k, tracking)
            x = w2c[:3, :3] @ p + w2c[:3, 3]
            if x[2] <= 0:
                continue
            u, v = K[0, 0] * x[0] / x[2] + K[0, 2], K[1, 1] * x[1] / x[2] + K[1, 2]
            if 0 <= u < w and 0 <= v < h:
                best = max(best, math.sqrt(K[0, 0] * K[1, 1]) / x[2])
        per_frame.append(best)
    if not any(per_frame):
        raise ValueError(f"no camera of {', '.join(cameras)} sees the point at take indices {list(frames)}")
    return float(np.median(per_frame))


def honest_width(density_px_per_m: float, focal_mm: float, sensor_mm: float, distance_m: float,
                 multiple: int = 16) -> int:
    """The widest image (a multiple of ``multiple`` px) whose pixels at ``distance_m`` are no finer
    than ``density_px_per_m``: ``W = density · distance · sensor / focal``. Finer pixels than the
    footage's finest at the subject would draw detail no camera recorded: the render would be a
    blur by construction, and scoring it would measure the resolution, not the reconstruction."""
    return max(multiple, int(density_px_per_m * distance_m * sensor_mm / focal_mm) // multiple * multiple)


def closeup_shot(heads: np.ndarray, facing: np.ndarray, frames: tuple[int, int], fps: float, width: int,
                 actor: str, performance: str) -> dict[str, Any]:
    """A close-up shot (``docs/shots.md``) of one actor over take indices ``[frames[0], frames[1])``:
    a keyframe per frame ``CLOSEUP_DISTANCE_M`` in front of the head (``heads``: ``[F, 3]``, one
    per frame; ``facing``: the face's horizontal direction), at head height, aimed at it, a
    ``CLOSEUP_FOCAL_MM`` lens on a ``CLOSEUP_SENSOR_MM``-wide sensor, 16:9 at ``width`` px."""
    height = max(2, round(width * 9 / 16 / 2) * 2)
    keys = [{"frame": frames[0] + i, "position": [round(float(x), 5) for x in head + CLOSEUP_DISTANCE_M * facing],
             "look_at": [round(float(x), 5) for x in head], "focal_mm": CLOSEUP_FOCAL_MM}
            for i, head in enumerate(heads)]
    return {"name": "closeup", "performance": performance, "actors": [actor], "frames": list(frames), "fps": fps,
            "resolution": [width, height], "sensor_mm": CLOSEUP_SENSOR_MM, "enhance": True, "keyframes": keys}


def closeup_spec(store: str, capture_ref: str, frames: tuple[int, int], face_folder: str,
                 shot: Mapping[str, Any], quality: str | Mapping[str, Any],
                 rigs: tuple[str, str] = ("demo_scene", "demo_face"),
                 face_calibration: str | None = None) -> dict[str, Any]:
    """The demo's production spec (``docs/production-spec.md``): the demo capture by ref over
    ``frames`` (the demo segment's, so the production plans the same segment), the face capture
    by folder (relative to the spec), the shot's actor in both, one close-up shot; ``rigs``: the
    scene and face captures' rigs (built-in names or rig JSON paths); ``face_calibration``: the
    actor's ``face_calibration`` (e.g. ``ground-truth``, which Gaussian-splat pairs of the demo's
    Face Rig need: its SfM finds no matches), None: unset."""
    actor = shot["actors"][0]
    return {"format": "volcap-production/1", "name": PRODUCTION, "store": store, "quality": quality,
            "rigs": {"scene": str(rigs[0]), "face": str(rigs[1])},
            "captures": {"demo": {"ref": capture_ref, "rig": "scene", "frames": list(frames)},
                         "face": {"folder": face_folder, "rig": "face"}},
            "actors": [{"name": actor, "captures": ["demo"], "index": ACTOR_INDEX, "face_capture": "face",
                        **({"face_calibration": face_calibration} if face_calibration else {})}],
            "shots": [dict(shot)]}


def check_segment_reused(prod, seg: SegmentModel, record: Capture, spec_path: Path) -> str:
    """Before the production runs: it must plan exactly the demo's segment (its frames and the
    TrainConfig its train-segment step will train) so that the step finds the demo's trained
    model in the task cache instead of training again (~4 of the demo's minutes). Returns the
    step id; ``ValueError`` naming what differs otherwise."""
    steps = [s for s in prod.steps if s.kind == "train-segment"]
    frames = [tuple(s.parameters.frames) for s in steps]
    if frames != [tuple(seg.frames)]:
        raise ValueError(f"{spec_path}: the production plans segments {frames}, not the demo's {tuple(seg.frames)}: "
                         "it would train them anew")
    config = segment_train_config(prod.spec.quality_preset(), record, steps[0].parameters.gaussians)
    planned = config.model_dump(mode="json")
    differ = sorted(k for k in set(planned) | set(seg.config) if planned.get(k) != seg.config.get(k))
    if differ:
        raise ValueError(f"{spec_path}: the production's segment {tuple(seg.frames)} would train with a TrainConfig "
                         f"other than the demo segment's ({', '.join(differ)} differ): it would train anew")
    return steps[0].id


def enhancer_budget(quality, train_wall_s: float | None) -> str:
    """One line saying what the enhancer had, for the demo's output."""
    q = quality
    trained = f"trained in {train_wall_s:.0f} s" if train_wall_s is not None else "cached"
    vae = sum([q.enhancer_vae_steps, *(n for n, _ in q.enhancer_vae_stages)])
    window = "head-window" if q.pair_window == "head" else "square"
    line = (f"enhancer: the {q.enhancer_architecture} CPU model from random weights, {vae} VAE + "
            f"{q.enhancer_steps} transformer steps on {q.face_subsequences} x {q.face_subsequence_frames}-frame "
            f"sub-sequences of {q.pair_resolution}-px {window} Face Rig pairs ({trained})")
    if q.enhancer_steps < 1000:
        line += (": a smoke run of the machinery, not an enhancer that has learned (a CPU enhancer that learns "
                 "needs ~50 min: docs/benchmarks.md 'Detail enhancer'; volcap demo --enhancer-preset long)")
    return line


def enhancer_pairs(quality, pairs) -> str:
    """One line saying which pairs the enhancer trained on (``pairs``: its FacePairSet or
    PairDataset), for the demo's output beside :func:`enhancer_budget`'s. A PairDataset trains on
    its train split only (``load_pair_sets``), so the line counts those sequences apart."""
    line = f"enhancer pairs: {quality.pair_method}, {pairs.method}, {len(pairs.sequences)} sequence(s)"
    if isinstance(pairs, PairDataset):
        line += (f", {len(pairs.in_split('train'))} of them trained on (the train split: sub-sequence(s) "
                 f"{', '.join(map(str, pairs.split.get('train', ()))) or 'none'})")
    if quality.pair_method == "interim":
        line += ("; interim in the demo because Gaussian-splat pairs train two more Poly4DGS models per Face Rig "
                 "sub-sequence, CPU time the demo does not have")
    return line


def _is_face_capture_of(folder: Path, capture: str, actor: int, frames: int) -> bool:
    """Whether ``folder`` holds a complete Face Rig capture of actor ``actor`` of the capture named
    ``capture``, ``frames`` frames long (capture.json is written last)."""
    path = folder / "capture.json"
    if not path.is_file():
        return False
    desc = json.loads(path.read_text())
    performer = desc.get("performer") or {}
    return (performer.get("capture"), performer.get("actor"), desc.get("take", {}).get("frame_count")) == \
        (capture, actor, frames)


def closeup_production(store: str, capture_dir: Path, out: Path, *, capture_ref, segment_ref, preset: str,
                       enhancer: str, face_rig: str | Path = "demo_face",
                       quality_overrides: Mapping[str, Any] | None = None,
                       face_calibration: str | None = None) -> dict[str, Any]:
    """The demo's production (module doc): the Face Rig capture (of ``face_rig``, a built-in name
    or a rig JSON path), the spec, the production run, the truth and the scores, the frames and
    the sheet copied into ``out``. Returns paths, refs, figures and wall times.
    ``quality_overrides``: preset fields over the enhancer run's (e.g. ``pair_method``: the pairs
    bench runs it with splat and interim pairs); ``face_calibration``: the spec's, as
    :func:`closeup_spec` takes it. Both None: the demo's production."""
    from volcap_core.synth import synthesize_face_capture

    log = get_run_logger()
    s = ArtifactStore(store)
    seg = s.get_record(segment_ref, SegmentModel)
    record = s.get_record(capture_ref, Capture)
    overrides = {**ENHANCER_RUNS[enhancer], **(quality_overrides or {})}
    quality = {"preset": preset, **overrides} if overrides else preset
    q = named_preset(preset).with_overrides(**overrides)
    walls: dict[str, float] = {}

    t0 = time.perf_counter()
    face_name = "face_capture" if enhancer == "demo" else f"face_capture_{enhancer}"
    face_dir = out / face_name
    frames = q.face_subsequences * q.face_subsequence_frames
    if not _is_face_capture_of(face_dir, record.name, ACTOR_INDEX, frames):
        if face_dir.exists():   # another actor's, another length, or a run cut short: made again
            shutil.rmtree(face_dir)
        # the demo actor in the Face Rig, as many frames as the preset's Face Rig pairs take (its
        # sub-sequences end to end), with the performer masks (the pairs' alpha)
        synthesize_face_capture(face_dir, rig=face_rig, seed=0, actor_of=(capture_dir, ACTOR_INDEX),
                                frames=frames, write_depth=True)
    walls["face_capture_s"] = time.perf_counter() - t0

    a, b = seg.frames
    scene = json.loads((capture_dir / "ground_truth" / "scene.json").read_text())
    heads, facing = head_track(scene, ACTOR_INDEX, range(a, b))
    calib = s.get_record(seg.calibration, Calibration)
    density = footage_density(calib, tracking_frames(s.get_bytes, calib), heads, range(a, b), seg.grid_cameras)
    width = honest_width(density, CLOSEUP_FOCAL_MM, CLOSEUP_SENSOR_MM, CLOSEUP_DISTANCE_M)
    named = f"captures/{record.name}"
    cap_ref = named if s.resolve(named).digest == capture_ref.digest else capture_ref.digest
    shot = closeup_shot(heads, facing, (a, b), record.fps, width, actor=f"actor{ACTOR_INDEX}", performance="demo")
    spec_path = out / "production.yaml"
    # the scene capture's rig as its capture.json names it: a built-in name or a file in its folder
    scene_rig = json.loads((capture_dir / "capture.json").read_text())["rig"]
    if (capture_dir / scene_rig).is_file():
        scene_rig = str((capture_dir / scene_rig).resolve())
    spec_path.write_text(yaml.safe_dump(closeup_spec(s.url, cap_ref, (a, b), face_name, shot, quality,
                                                     rigs=(scene_rig, face_rig), face_calibration=face_calibration),
                                        sort_keys=False))
    step = check_segment_reused(open_production(spec_path), seg, record, spec_path)

    t0 = time.perf_counter()
    result = production_flow(spec=str(spec_path), segment_runs="local")
    walls["production_s"] = time.perf_counter() - t0
    reused = result["steps"][step]["segment"] == segment_ref.digest
    if not reused:
        log.warning("the production trained its own segment %s, not the demo's %s", result["steps"][step]["segment"],
                    segment_ref.digest)
    shot_out = result["shots"]["closeup"]

    # what a camera at the shot's pose would have seen, and the scores against it
    t0 = time.perf_counter()
    truth = truth_flow(spec=str(spec_path), shot="closeup")
    walls["truth_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    scored = s.get_json(score_shot(s.url, s.resolve(truth["truth"]), s.resolve(shot_out["frames"]), capture_ref,
                                   enhanced=s.resolve(shot_out["enhanced"]), actors=[ACTOR_INDEX]))
    walls["score_s"] = time.perf_counter() - t0
    sheet = out / "closeup_sheet.png"
    s.get_file(scored["contact_sheet"]["digest"], sheet)
    scores_path = out / "closeup_scores.json"
    scores_path.write_text(json.dumps(scored, indent=1, sort_keys=True))
    closeup_dir = out / "closeup"
    for what, ref in (("render", shot_out["frames"]), ("enhanced", shot_out["enhanced"]), ("truth", truth["truth"])):
        s.get_directory(ref, closeup_dir / what)
    enh = s.get_record(s.resolve(result["steps"][f"train-enhancer:actor{ACTOR_INDEX}"]["enhancer"]),
                       EnhancerModel)
    budget = enhancer_budget(q, enh.wall_s)
    pairs = enhancer_pairs(q, pair_record(enh.pair_sets[0], s.get_bytes))
    log.info("close-up: %s x %s px (the finest footage on the head: %.0f px/m), spec %s", *shot["resolution"],
             density, spec_path)
    log.info("%s", budget)
    log.info("%s", pairs)
    figures = closeup_figures(scored)
    for region in ("face", "performers"):
        log.info("close-up %s: %s", region, "; ".join(
            f"{row} {f['psnr']} dB / SSIM {f['ssim']} / detail {f['detail']}" for row, f in figures[region].items()))
    log.info("close-up sheet %s", sheet)
    return {"spec": str(spec_path), "face_capture": str(face_dir), "shot": "closeup",
            "resolution": shot["resolution"], "focal_mm": CLOSEUP_FOCAL_MM, "footage_px_per_m": round(density, 1),
            "segment_reused": reused, "sheet": str(sheet), "scores": str(scores_path),
            "frames": {what: str(closeup_dir / what) for what in ("render", "enhanced", "truth")},
            **figures,
            "enhancer_run": enhancer, "enhancer_budget": budget, "enhancer_pairs": pairs,
            "enhancer_train_s": round(enh.wall_s, 1),
            "refs": {"frames": shot_out["frames"], "enhanced": shot_out["enhanced"], "truth": truth["truth"],
                     "sheet": scored["contact_sheet"]["digest"]},
            "wall_s": {k: round(v, 1) for k, v in walls.items()}}


def closeup_figures(scores: Mapping[str, Any]) -> dict[str, Any]:
    """The headline of a ``score-shot`` result: per region (``face``, ``performers``) each row's
    PSNR (dB), SSIM and detail, the output rows (``render``, ``enhanced``) beside their floors
    (``empty``, ``bicubic``; the render is the enhanced row's floor too), and the temporal
    flickering and warp error per row and of the truth (``docs/shots.md``, "Scoring a shot")."""
    def r(x, digits):
        return None if x is None else round(float(x), digits)

    rows = scores["rows"]
    order = [k for k in ("render", "enhanced", "empty", "bicubic") if k in rows]
    out: dict[str, Any] = {region: {row: {"psnr": r(rows[row][region]["psnr"], 2),
                                          "ssim": r(rows[row][region]["ssim"], 3),
                                          "detail": r(rows[row][region]["detail"], 3)} for row in order}
                           for region in ("face", "performers")}
    out["temporal"] = {row: {"flickering": r(v["flickering"], 4), "warp_error": r(v["warp_error"], 6)}
                       for row, v in scores.get("temporal", {}).items()}
    out["floors"] = scores.get("floors", {})
    return out
