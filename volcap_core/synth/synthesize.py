"""Write complete synthetic capture folders (layout of ``volcap_core.capture``) with ground truth."""

from __future__ import annotations

import json
import math
import shutil
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from hardware.lens_models import DISTORTION_MODELS
from hardware.rig import CameraRole, Rig, RigCamera, ZoomIntrinsics, load_rig, rig_file
from volcap_core.calibration.distortion import Distortion
from volcap_core.calibration.geometry import look_at_rotation
from volcap_core.capture import (CameraSource, CaptureDescription, CaptureFolder, Encoding, IngestError, LensSample,
                                 Performer, Take, frames_to_timecode, timecode_to_frames)
from volcap_core.synth import io as sio
from volcap_core.synth.actors import HEAD_CENTRE_HEIGHT, Actor
from volcap_core.synth.geometry import PinholeCamera
from volcap_core.synth.render import World, background, render
from volcap_core.synth.sensor import EncoderModel, SensorModel, smooth_zoom
from volcap_core.synth.stage import build_face_stage, build_room_stage

TAKE_START = "01:00:00:00"
FRAMES_DIR = "frames"
GT_DIR = "ground_truth"
SCENE_FORMAT = "volcap-synth-scene/1"
#: how much larger a Face Rig actor's expressions are than a Scene Rig actor's (``Actor.expressive``)
FACE_EXPRESSIVE = 1.6
#: the rig's lidar scan of the static set, a capture input (calibration reads it); the same bytes are
#: kept in ground_truth/lidar.ply for evaluation
LIDAR_FILE = "lidar.ply"
#: the static cameras' clean plates (``plates=True``): ``plates/<camera id>.exr``, what
#: ``volcap masks --plates`` reads (not a capture input: ingest does not read the folder)
PLATES_DIR = "plates"
Progress = Callable[[int, int], None]

#: a static camera with measured intrinsics in the rig (a lens calibration) is rendered with the
#: rig's values plus the error of a good lens calibration (1 sigma): focal 0.2 % (fy/fx kept),
#: principal point 0.3 px, k1 and k2 0.002, p1 and p2 0.0001, k3..k6 0 (drawn from their own random
#: stream: the camera's pose, noise and everything else are those of the same rig without them)
LENS_CALIBRATION_ERROR = {"focal_rel": 0.002, "centre_px": 0.3, "k": 0.002, "p": 0.0001}
#: a tracking camera whose rig carries a zoom lens table (``zoom_intrinsics``) is rendered through
#: that table plus, at every sample, the error of a good calibration at that zoom (1 sigma, drawn
#: per sample from the camera's "lens" stream): the radial distortion at the image corner 0.05 % of
#: its radius (k1 += N(0, 0.0005) / r² with r the corner's normalized radius at that focal; k2 and
#: the higher terms 0), the tangential shift there 0.002 % (p += N(0, 0.00002) / r), the principal
#: point (when the table has one) 0.3 px. Each frame's lens is the true table at its true focal.
ZOOM_CALIBRATION_ERROR = {"corner": 0.0005, "tangential": 0.00002, "centre_px": 0.3}


def _rng(seed: int, *keys) -> np.random.Generator:
    """An independent stream per (seed, purpose...): adding a camera never changes another's noise."""
    ints = [int(seed)] + [k if isinstance(k, int) else zlib.crc32(str(k).encode()) for k in keys]
    return np.random.default_rng(ints)


# --------------------------------------------------------------------------- cameras over time

@dataclass
class CameraPlan:
    cam: RigCamera
    pre_roll: int                  # frames recorded before the take start
    sensor: SensorModel
    encoder: EncoderModel | None
    position: np.ndarray           # true optical centre (fixed)
    cx: float
    cy: float
    static: PinholeCamera | None = None
    static_focal_mm: float = 0.0
    actor: int = 0
    mode: str = "head"             # head | full | upper | lower
    extent_m: float = 0.55
    lag_s: float = 0.06
    zoom_period_s: float = 3.0
    zoom_phase: float = 0.0
    wobble: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    #: a tracking camera's true zoom lens (its table in the rig, ``Rig.zoom_intrinsics``: its own or
    #: its lens group's, plus a calibration's error)
    zoom: ZoomIntrinsics | None = None

    @property
    def tracks(self) -> bool:
        return self.static is None


MODE_TARGET = {"full": (0.95, 2.3), "upper": (1.3, 1.1), "lower": (0.5, 1.15)}


def _target(world: World, actor: int, mode: str, t: float) -> np.ndarray:
    a = world.actors[actor]
    if mode == "head":
        return a.head(t)[0]
    root, _ = a.root(t)
    return root + np.array([0.0, 0.0, MODE_TARGET[mode][0] * a.scale])


def camera_at(plan: CameraPlan, world: World, t: float) -> tuple[PinholeCamera, float, float]:
    """The true camera at time t, its focal length (mm) and focus distance (m)."""
    s = plan.cam.sensor
    if not plan.tracks:
        tgt = _target(world, 0, "head", t) if world.actors else plan.position + plan.static.R[2]
        return plan.static, plan.static_focal_mm, float(np.linalg.norm(tgt - plan.position))
    target = _target(world, plan.actor, plan.mode, t)
    aim = _target(world, plan.actor, plan.mode, t - plan.lag_s)
    dist = float(np.linalg.norm(aim - plan.position))
    # small smooth servo error, perpendicular to the line of sight
    R0 = look_at_rotation(plan.position, aim)
    w1, w2, p1, p2 = plan.wobble
    err = 0.006 * dist * (math.sin(2 * math.pi * w1 * t + p1) * R0[0] + math.sin(2 * math.pi * w2 * t + p2) * R0[1])
    R = look_at_rotation(plan.position, aim + err)
    f_mm = s.height_mm * dist / plan.extent_m * smooth_zoom(t, plan.zoom_period_s, plan.zoom_phase)
    f_mm = float(np.clip(f_mm, plan.cam.lens.focal_min_mm, plan.cam.lens.focal_max_mm))
    f_px = s.focal_px(f_mm)
    cx, cy, dist = plan.cx, plan.cy, Distortion.none()
    if plan.zoom is not None:           # the lens at this frame's (true) focal
        lens = plan.zoom.at(f_mm)
        dist = Distortion(plan.zoom.model, lens.params)
        if lens.cx is not None:
            cx, cy = lens.cx, lens.cy
    cam = PinholeCamera(s.width_px, s.height_px, f_px, f_px, cx, cy, R, -R @ plan.position, dist)
    return cam, f_mm, float(np.linalg.norm(target - plan.position))


def _plans(rig: Rig, seed: int, actor_centres: list[tuple[float, float]], cameras: Sequence[str] | None,
           lens_error: Mapping[str, float] = LENS_CALIBRATION_ERROR) -> list[CameraPlan]:
    n_actors = len(actor_centres)
    chosen = [c for c in rig.cameras if cameras is None or c.id in cameras]
    if cameras is not None and len(chosen) != len(set(cameras)):
        missing = sorted(set(cameras) - {c.id for c in chosen})
        raise ValueError(f"rig {rig.name} has no camera(s) {missing}")
    # one static and one tracking camera (when there are) start a few frames before the take
    pre: dict[str, int] = {}
    r = _rng(seed, "pre-roll")
    statics = [c.id for c in chosen if not c.role.tracks]
    trackers = [c.id for c in chosen if c.role.tracks]
    for group in (statics, trackers):
        if group and len(chosen) > 1:
            pre[group[int(r.integers(len(group)))]] = int(r.integers(2, 5))
    plans = []
    n_portrait = 0
    for cam in chosen:
        r = _rng(seed, "camera", cam.id)
        s = cam.sensor
        pos = np.asarray(cam.mount.position_m) + r.normal(0, 0.015, 3)
        cx = (s.width_px - 1) / 2 + r.normal(0, 0.003 * s.width_px)
        cy = (s.height_px - 1) / 2 + r.normal(0, 0.003 * s.height_px)
        sensor = SensorModel.random(_rng(seed, "sensor", cam.id), zoom=cam.role.tracks)
        plan = CameraPlan(cam, pre.get(cam.id, 0), sensor, None, pos, float(cx), float(cy))
        if cam.role is CameraRole.static:
            look = np.asarray(cam.mount.look_at_m)
            look = look + r.normal(0, 0.005 * np.linalg.norm(look - pos), 3)
            f_mm = float(np.clip(cam.nominal_focal_mm * (1 + r.normal(0, 0.01)),
                                 cam.lens.focal_min_mm, cam.lens.focal_max_mm))
            f_px = s.focal_px(f_mm)
            fy_px, dist = f_px, Distortion.none()
            roll = cam.mount.roll_deg + r.normal(0, 0.3)
            measured = rig.measured_intrinsics(cam.id)
            if measured is not None:
                f_px, fy_px, cx, cy, dist = _true_lens(measured, _rng(seed, "lens", cam.id), lens_error)
                plan.cx, plan.cy = cx, cy
                f_mm = f_px * s.width_mm / s.width_px
            plan.static = PinholeCamera.looking_at(s.width_px, s.height_px, f_px, fy_px, cx, cy, pos, look,
                                                   roll, dist)
            plan.static_focal_mm = f_mm
        else:
            if n_actors == 0:
                raise ValueError(f"tracking camera {cam.id} needs an actor to follow")
            plan.encoder = EncoderModel.random(_rng(seed, "encoder", cam.id), cam.lens.focal_min_mm)
            # follow the actor whose walking loop is nearest; portrait cameras cycle through
            # full-body, upper-body and lower-body framings
            plan.actor = int(np.argmin([np.linalg.norm(np.asarray(c) - pos[:2]) for c in actor_centres]))
            if cam.role is CameraRole.tracking_landscape:
                plan.mode, plan.extent_m = "head", 0.55
            else:
                plan.mode = ("full", "upper", "lower")[n_portrait % 3]
                plan.extent_m = MODE_TARGET[plan.mode][1]
                n_portrait += 1
            plan.lag_s = float(r.uniform(0.03, 0.09))
            plan.zoom_period_s = float(r.uniform(2.0, 4.0))
            plan.zoom_phase = float(r.uniform(0, 2 * math.pi))
            plan.wobble = (float(r.uniform(0.3, 0.8)), float(r.uniform(0.3, 0.8)),
                           float(r.uniform(0, 6.3)), float(r.uniform(0, 6.3)))
            table = rig.zoom_intrinsics(cam.id)      # its own or its lens group's: each unit errs on its own
            if table is not None:
                plan.zoom = _true_zoom(table, s, _rng(seed, "lens", cam.id))
        plans.append(plan)
    return plans


def _true_lens(m, r: np.random.Generator, e: Mapping[str, float] = LENS_CALIBRATION_ERROR
               ) -> tuple[float, float, float, float, Distortion]:
    """The true lens of a camera whose rig carries measured intrinsics ``m``: the measured values
    plus the lens calibration's error ``e`` (1 sigma, the keys of :data:`LENS_CALIBRATION_ERROR`)."""
    scale = 1 + r.normal(0, e["focal_rel"])
    cx = m.cx + r.normal(0, e["centre_px"])
    cy = m.cy + r.normal(0, e["centre_px"])
    d = Distortion(m.model, tuple(m.params))
    full = np.asarray(d.opencv_full())
    full[[0, 1]] += r.normal(0, e["k"], 2)
    full[[2, 3]] += r.normal(0, e["p"], 2)
    names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    coeff = dict(zip(names, full))
    coeff["k"] = coeff["k1"]
    # the model keeps its own parameters (a RADIAL lens stays RADIAL: its error is in k1, k2 only)
    params = tuple(float(coeff[n]) for n in DISTORTION_MODELS[d.model])
    return float(m.fx * scale), float(m.fy * scale), float(cx), float(cy), Distortion(d.model, params)


def _true_zoom(z: ZoomIntrinsics, sensor, r: np.random.Generator) -> ZoomIntrinsics:
    """The true zoom lens of a tracking camera whose rig carries the table ``z``: each sample plus
    :data:`ZOOM_CALIBRATION_ERROR` (its own draw per sample)."""
    e = ZOOM_CALIBRATION_ERROR
    h2 = (sensor.width_mm / 2) ** 2 + (sensor.height_mm / 2) ** 2
    names = DISTORTION_MODELS[z.model]
    samples = []
    for smp in z.samples:
        r2 = h2 / smp.focal_mm ** 2           # the image corner's normalized radius, squared
        full = np.asarray(Distortion(z.model, smp.params).opencv_full())
        full[0] += r.normal(0, e["corner"]) / r2
        full[[2, 3]] += r.normal(0, e["tangential"], 2) / np.sqrt(r2)
        coeff = dict(zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), full))
        coeff["k"] = coeff["k1"]
        # the model keeps its own parameters (a RADIAL lens has no tangential error)
        upd = {"params": tuple(float(coeff[n]) for n in names)}
        if smp.cx is not None:
            upd.update(cx=float(smp.cx + r.normal(0, e["centre_px"])), cy=float(smp.cy + r.normal(0, e["centre_px"])))
        samples.append(smp.model_copy(update=upd))
    return z.model_copy(update={"samples": tuple(samples)})


# --------------------------------------------------------------------------- actors

def _scene_actors(stage_size_m: Sequence[float], seed: int, n: int) -> list[Actor]:
    """The ``n`` walking actors of a Scene Rig capture of ``seed`` on a stage ``stage_size_m``
    (x, y, z metres): the same arguments draw the same people on the same loops."""
    sx, sy, _ = stage_size_m
    r0 = 0.3 * min(sx, sy)
    actors = []
    for i in range(n):
        r = _rng(seed, "actor", i)
        if n == 1:
            centre, radii = (0.0, 0.0), (0.55 * r0, 0.45 * r0)
        else:
            ang = 2 * math.pi * i / n + math.pi / 2
            centre = (0.65 * r0 * math.cos(ang), 0.65 * r0 * math.sin(ang))
            radii = (0.38 * r0, 0.3 * r0)
        actors.append(Actor.random(i, r, centre, radii, walking=True))
    return actors


def _face_actor(seed: int) -> Actor:
    """A Face Rig capture's own actor (one drawn for it, in no Scene Rig capture), scaled so the
    head is at about 1.7 m."""
    a = Actor.random(0, _rng(seed, "face-actor"), (0.0, 0.0), (0.0, 0.0), walking=False, expressive=FACE_EXPRESSIVE)
    a.scale = 1.7 / HEAD_CENTRE_HEIGHT * float(_rng(seed, "face-scale").uniform(0.99, 1.01))
    return a


def _face_rig_head_height(rig: Rig) -> float:
    """Where a Face Rig's cameras look, as a height (metres): the median z of their ``look_at_m``."""
    return float(np.median([c.mount.look_at_m[2] for c in rig.cameras]))


def _face_performer(source: Mapping[str, Any], seed: int) -> Actor:
    """A Face Rig capture's actor when it films a Scene Rig capture's actor: actor
    ``source["actor"]`` of the scene capture ``source`` describes (its seed, stage size and actor
    count rebuild it), the same person at the same scale, standing at the Face Rig's centre facing
    +x on a riser that puts the rest head centre at ``source["head_height_m"]``, with a
    performance of its own drawn from the face capture's ``seed`` (larger expressions and head
    turns than when walking)."""
    scene = _scene_actors(source["stage_size_m"], int(source["seed"]), int(source["actors"]))[int(source["actor"])]
    riser = float(source["head_height_m"]) - HEAD_CENTRE_HEIGHT * scene.scale
    return scene.restaged(0, _rng(seed, "face-performance"), (0.0, 0.0), expressive=FACE_EXPRESSIVE, riser_m=riser)


def _actor_frame(a: Actor, k: int, t: float) -> dict:
    """scene.json's record of actor ``a`` at take index ``k`` (time ``t`` seconds)."""
    root, yaw = a.root(t)
    prims = a.pose(t)
    head = next(p for p in prims if p.name == "head")
    return {"take_index": k, "time_s": round(t, 6), "root_m": np.round(root, 6).tolist(),
            "yaw_rad": round(yaw, 6), "head_centre_m": np.round(head.centre, 6).tolist(),
            "head_rotation": np.round(head.R, 6).tolist(),
            "expression": {k2: round(v, 6) for k2, v in head.expression.items()},
            "parts": [p.to_json() for p in prims]}


def _mismatch(recorded: Any, rebuilt: Any, path: str = "") -> str | None:
    """The first place (a JSON path) where two scene.json values differ (numbers beyond 1e-6),
    None when they agree."""
    if isinstance(recorded, dict) and isinstance(rebuilt, dict):
        for k in sorted(set(recorded) | set(rebuilt)):
            if k not in recorded or k not in rebuilt:
                return f"{path}.{k}" + (" is not recorded" if k not in recorded else " is recorded, not rebuilt")
            where = _mismatch(recorded[k], rebuilt[k], f"{path}.{k}")
            if where:
                return where
        return None
    if isinstance(recorded, list) and isinstance(rebuilt, list):
        if len(recorded) != len(rebuilt):
            return f"{path} has {len(recorded)} entries recorded, {len(rebuilt)} rebuilt"
        for i, (a, b) in enumerate(zip(recorded, rebuilt)):
            where = _mismatch(a, b, f"{path}[{i}]")
            if where:
                return where
        return None
    numbers = (int, float)
    if isinstance(recorded, numbers) and isinstance(rebuilt, numbers) and not isinstance(recorded, bool):
        return None if abs(recorded - rebuilt) <= 1e-6 else f"{path} is {recorded} recorded, {rebuilt} rebuilt"
    return None if recorded == rebuilt else f"{path} is {recorded!r} recorded, {rebuilt!r} rebuilt"


def scene_actors_of(scene_json: Path | str | Mapping[str, Any]) -> list[Actor]:
    """The actors of a synthetic capture, rebuilt from its ``ground_truth/scene.json`` (a path or
    the parsed file) and checked against what that file records.

    A Scene Rig capture's actors are drawn from (seed, stage size, actor count); a Face Rig
    capture's actor is its own (from its seed) or, when scene.json names a ``performer``, that
    Scene Rig actor restaged (:func:`synthesize_face_capture` ``actor_of``). Every rebuilt actor
    must describe itself as recorded (scale, colours, path, riser) and pose its parts, head and
    expression at take index 0 as recorded; ``ValueError`` naming the file, the actor and the
    first value that differs otherwise (a capture synthesized by another version of volcap).
    Returns the actors in scene.json's order; each one's ``index`` is its place in that list."""
    where = str(scene_json) if isinstance(scene_json, (str, Path)) else "scene.json"
    if isinstance(scene_json, (str, Path)):
        try:
            d = json.loads(Path(scene_json).read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"{where}: cannot read a synthetic scene description: {exc}") from None
    else:
        d = dict(scene_json)
    if not isinstance(d, dict) or d.get("format") != SCENE_FORMAT:
        raise ValueError(f"{where}: not a synthetic scene description (format "
                         f"{d.get('format') if isinstance(d, dict) else None!r}, expected {SCENE_FORMAT!r})")
    recorded = d.get("actors") or []
    seed, kind = int(d["seed"]), d["kind"]
    if kind == "scene":
        actors = _scene_actors(d["stage"]["size_m"], seed, len(recorded))
        how = f"seed {seed}, stage {d['stage']['size_m']} m, {len(recorded)} actor(s)"
    elif kind == "face" and d.get("performer") is not None:
        src = d["performer"]
        actors = [_face_performer(src, seed)]
        how = f"actor {src['actor']} of capture {src['capture']!r} (seed {src['seed']}), face seed {seed}"
    elif kind == "face":
        actors = [_face_actor(seed)]
        how = f"face seed {seed}"
    else:
        raise ValueError(f"{where}: unknown capture kind {kind!r} (scene or face)")
    if len(actors) != len(recorded):
        raise ValueError(f"{where}: records {len(recorded)} actor(s), a {kind} capture has {len(actors)}")
    for i, (a, rec) in enumerate(zip(actors, recorded)):
        rebuilt = a.describe()
        described = {k: v for k, v in rec.items() if k != "frames"}
        if rec.get("frames"):
            described["frames"] = rec["frames"][:1]
            f0 = rec["frames"][0]
            rebuilt["frames"] = [_actor_frame(a, int(f0["take_index"]), float(f0["time_s"]))]
        diff = _mismatch(described, rebuilt, f"actors[{i}]")
        if diff is not None:
            raise ValueError(f"{where}: actor {i} rebuilt from ({how}) does not match what the file records: "
                             f"{diff} (a capture synthesized by another version of volcap?)")
    return actors


def _performer_source(actor_of: tuple[str | Path, int]) -> dict[str, Any]:
    """What a Face Rig capture records of the Scene Rig actor it films (scene.json's
    ``performer``, less the head height): the scene capture's name and the actor's index, and
    what rebuilds that actor (its seed, rig, stage size, actor count). The scene capture's actors
    are rebuilt and checked first (:func:`scene_actors_of`); ``ValueError`` naming the folder
    when it is not a synthetic Scene Rig capture or has no such actor."""
    folder, index = actor_of
    folder = Path(folder)
    try:
        capture = CaptureFolder.open(folder)
    except IngestError as exc:
        raise ValueError(f"actor_of: {exc}") from None
    gt = capture.ground_truth_path
    scene_file = gt / "scene.json" if gt is not None else None
    if scene_file is None or not scene_file.is_file():
        raise ValueError(f"actor_of: {folder} is not a synthetic capture (no {scene_file or 'ground_truth folder'}): "
                         "its actors cannot be rebuilt")
    d = json.loads(scene_file.read_text())
    if d.get("kind") != "scene":
        raise ValueError(f"actor_of: {folder} is a {d.get('kind')} capture, not a Scene Rig capture")
    actors = scene_actors_of(scene_file)
    if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(actors):
        raise ValueError(f"actor_of: capture {capture.name} ({folder}) has actors 0..{len(actors) - 1}, no actor {index!r}")
    return {"capture": capture.name, "actor": index, "seed": int(d["seed"]), "rig": d["rig"],
            "stage_size_m": list(d["stage"]["size_m"]), "actors": len(actors)}


# --------------------------------------------------------------------------- the writer

def _render_camera(plan: CameraPlan, world: World, fps: float, frames: int, seed: int, ss: int,
                   cam_dir: Path, depth_dir: Path | None, tick, mask_dir: Path | None = None,
                   plate: Path | None = None) -> dict:
    """Render and write all of one camera's frames (and, for take frames, the depth maps and performer
    masks when their folders are given; for a static camera its clean plate at ``plate`` when
    given); return its ground truth and encoder samples."""
    cache = background(world, plan.static, ss) if not plan.tracks else None
    if plate is not None and cache is not None:
        # the set without the actors (nor their contact shadows) at the take's first instant, from
        # the frames' own set render, through the sensor with a noise stream of its own: a clean
        # plate as a studio shoots one before the take
        empty = World(world.stage, [])
        rad = render(empty, camera_at(plan, empty, 0.0)[0], 0.0, ss, cache=cache, bg_ss=1)[0]
        sio.write_exr(plate, plan.sensor.apply(rad, _rng(seed, "plate", plan.cam.id)))
    bg_ss = 1   # moving cameras: the set at one sample per pixel (mip-filtered), actors at ss
    gt_frames, samples = [], []
    enc_rng = _rng(seed, "encoder-noise", plan.cam.id)
    for n in range(plan.pre_roll + frames):
        k = n - plan.pre_roll
        t = k / fps
        cam, f_mm, focus = camera_at(plan, world, t)
        # pre-roll frames (k < 0) have no ground-truth maps: no mask to compute
        want_mask = mask_dir is not None and k >= 0
        rad, depth, *mask = render(world, cam, t, ss, cache=cache, bg_ss=bg_ss,
                                   want_depth=depth_dir is not None, want_mask=want_mask)
        img = plan.sensor.apply(rad, _rng(seed, "noise", plan.cam.id, n))
        sio.write_exr(cam_dir / f"{n:06d}.exr", img)
        if plan.encoder is not None:
            fr, fo = plan.encoder.read(enc_rng, f_mm, focus)
            samples.append(LensSample(frame=n, focal_mm=fr, focus_m=fo))
        if k >= 0:
            gt_frames.append({"take_index": k, "frame": n, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                              "cy": cam.cy, "focal_mm": f_mm, "focus_m": round(focus, 6),
                              "world_to_camera": np.round(cam.world_to_camera, 9).tolist()})
            if not cam.distortion.is_none:       # (absent for pinholes: their files stay as they were)
                gt_frames[-1]["distortion"] = cam.distortion.to_json()
            if depth_dir is not None:
                sio.write_exr(depth_dir / f"{k:06d}.exr", depth, half=False)
            if want_mask:
                # coverage j / ss^2 (exact in half for ss = 1, 2, 4); one channel "Z" like depth
                sio.write_exr(mask_dir / f"{k:06d}.exr", mask[0], half=True)
        tick()
    return {"frames": gt_frames, "samples": samples}


def _synthesize(out_dir: Path, rig_name: str | Path, seed: int, frames: int, kind: str, n_actors: int,
                ss: int, cameras: Sequence[str] | None, write_depth: bool, lidar_spacing_m: float,
                progress: Progress | None, name: str | None, lidar: bool = True,
                lens_error: Mapping[str, float] = LENS_CALIBRATION_ERROR,
                performer: Mapping[str, Any] | None = None, plates: bool = False) -> Path:
    if frames < 1:
        raise ValueError("frames must be >= 1")
    if ss < 1:
        raise ValueError("supersample must be >= 1")
    rig = load_rig(rig_name)
    if rig.kind != kind:
        raise ValueError(f"rig {rig.name} is a {rig.kind} rig; this synthesizer needs a {kind} rig "
                         f"(synthesize_{'face_' if rig.kind == 'face' else ''}capture renders it)")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # a rerun into the same folder replaces what a previous synthesis wrote (and nothing else)
    for old in (out_dir / "capture.json", out_dir / "rig.json", out_dir / LIDAR_FILE):
        old.unlink(missing_ok=True)
    for old in (out_dir / FRAMES_DIR, out_dir / GT_DIR, out_dir / PLATES_DIR):
        if old.is_dir():
            shutil.rmtree(old)
    rig_ref = rig.name
    source_file = rig_file(rig_name)
    if source_file is not None:
        shutil.copyfile(source_file, out_dir / "rig.json")
        rig_ref = "rig.json"
    if performer is not None:
        performer = {**performer, "head_height_m": round(_face_rig_head_height(rig), 6)}
    if kind == "face":
        actors = [_face_performer(performer, seed) if performer is not None else _face_actor(seed)]
    else:
        actors = _scene_actors(rig.stage_size_m, seed, n_actors)
    stage = _stage(rig, kind, seed)
    world = World(stage, actors)
    plans = _plans(rig, seed, [a.path_centre for a in actors], cameras, lens_error)
    fps = rig.fps
    total = sum(p.pre_roll + frames for p in plans)
    done = 0

    def tick():
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    gt_dir = out_dir / GT_DIR
    gt_dir.mkdir(exist_ok=True)
    take_tc = timecode_to_frames(TAKE_START, fps)
    sources, gt_cams = [], {}
    for plan in plans:
        cid = plan.cam.id
        cam_dir = out_dir / FRAMES_DIR / cid
        cam_dir.mkdir(parents=True, exist_ok=True)
        depth_dir = mask_dir = None
        if write_depth:
            depth_dir = gt_dir / "depth" / cid
            depth_dir.mkdir(parents=True, exist_ok=True)
            mask_dir = gt_dir / "masks" / cid
            mask_dir.mkdir(parents=True, exist_ok=True)
        plate = None
        if plates and not plan.tracks:
            (out_dir / PLATES_DIR).mkdir(exist_ok=True)
            plate = out_dir / PLATES_DIR / f"{cid}.exr"
        res = _render_camera(plan, world, fps, frames, seed, ss, cam_dir, depth_dir, tick, mask_dir, plate)
        sources.append(CameraSource(
            id=cid, path=f"{FRAMES_DIR}/{cid}", start_timecode=frames_to_timecode(take_tc - plan.pre_roll, fps),
            encoding=Encoding.linear, lens_encoder=res["samples"] or None))
        gt_cams[cid] = {
            "role": plan.cam.role.value, "width": plan.cam.sensor.width_px, "height": plan.cam.sensor.height_px,
            "sensor_mm": [plan.cam.sensor.width_mm, plan.cam.sensor.height_mm],
            "take_offset": -plan.pre_roll, "centre_m": np.round(plan.position, 9).tolist(),
            "photometric": plan.sensor.to_json(),
            "encoder": plan.encoder.to_json() if plan.encoder else None,
            "tracking": ({"actor": plan.actor, "target": plan.mode, "framing_extent_m": plan.extent_m,
                          "lag_s": plan.lag_s} if plan.tracks else None),
            "frames": res["frames"]}
        if plan.zoom is not None:   # the true zoom lens table (each frame's 'distortion' is it at that focal)
            gt_cams[cid]["zoom_lens"] = plan.zoom.model_dump(mode="json")
    desc = CaptureDescription(
        name=name or f"synth-{rig.name}-s{seed}", rig=rig_ref, fps=fps,
        take=Take(start_timecode=TAKE_START, frame_count=frames), cameras=sources, ground_truth=GT_DIR,
        lidar=LIDAR_FILE if lidar else None,
        performer=Performer(capture=performer["capture"], actor=performer["actor"]) if performer else None)
    # ground truth
    convention = ("world: metres, z up, origin at the stage centre on the floor. world_to_camera: 4x4, "
                  "OpenCV camera axes (x right, y down, z forward). Pixels: OpenCV, centre of the "
                  "top-left pixel at (0, 0) (COLMAP: +0.5). Pinhole, no distortion. frames[i] is take "
                  "index i; 'frame' is the camera's own frame number.")
    if any((p.static is not None and not p.static.distortion.is_none) or p.zoom is not None for p in plans):
        convention = convention.replace(
            "Pinhole, no distortion.", "Pinhole unless a frame has 'distortion' {model, params} (COLMAP's model "
            "names and parameter order, OpenCV's equations on normalized coordinates; the images are rendered "
            "through it exactly, per ray).")
    sio.write_json(gt_dir / "cameras.json", {
        "format": "volcap-synth-cameras/1",
        "convention": convention,
        "fps": fps, "take_start_timecode": TAKE_START, "frame_count": frames, "cameras": gt_cams})
    scene_gt = {
        "format": SCENE_FORMAT, "seed": seed, "rig": rig.name, "kind": kind,
        "units": "metres, seconds; world z up, origin at the stage centre on the floor; colours linear Rec.709",
        "stage": {"size_m": list(stage.stage_size_m), "set": stage.background.describe()},
        "lighting": stage.lighting.to_json(), "emitters": stage.emitters,
        "chart": stage.chart, "targets": stage.targets, "props": stage.props,
        "actors": []}
    if performer is not None:   # whose actor this is, and what rebuilds it (scene_actors_of)
        scene_gt["performer"] = dict(performer)
    for a in actors:
        d = a.describe()
        d["frames"] = [_actor_frame(a, k, k / fps) for k in range(frames)]
        scene_gt["actors"].append(d)
    sio.write_json(gt_dir / "scene.json", scene_gt)
    pts, nrm = stage.lidar(_rng(seed, "lidar"), lidar_spacing_m)
    sio.write_ply(gt_dir / "lidar.ply", pts, nrm,
                  comment="volcap synthetic lidar scan of the static set, world frame, metres")
    if lidar:   # without: the capture has no scan (ground truth keeps it, for evaluation only)
        shutil.copyfile(gt_dir / "lidar.ply", out_dir / LIDAR_FILE)
    sio.write_json(out_dir / "capture.json", desc.model_dump(mode="json", exclude_none=True))
    return out_dir / "capture.json"


def synthesize_capture(out_dir: Path, rig: str = "demo_scene", seed: int = 0, frames: int = 24, *,
                       progress: Progress | None = None, actors: int = 2, supersample: int = 2,
                       cameras: Sequence[str] | None = None, write_depth: bool = False,
                       lidar_spacing_m: float = 0.05, name: str | None = None, lidar: bool = True,
                       lens_calibration_error: Mapping[str, float] | None = None, plates: bool = False) -> Path:
    """Render a Scene Rig capture of ``actors`` walking, talking actors; returns capture.json's path.

    ``rig``: a built-in rig name or a rig JSON file (copied into the capture). ``cameras`` renders a
    subset of the rig (tests; the static cameras alone make a capture without tracking cameras).
    ``supersample``: ss x ss samples per pixel. ``write_depth``: also write
    ground-truth depth maps and performer masks per camera and take frame (``ground_truth/depth/``,
    ``ground_truth/masks/``). ``lidar=False``: a capture without a lidar scan (no ``lidar.ply`` input,
    none in capture.json; ``ground_truth/lidar.ply`` is still written, for evaluation).
    ``lens_calibration_error``: for a rig whose static cameras carry measured intrinsics, how far
    (1 sigma) each unit's true lens is from them, in the keys of :data:`LENS_CALIBRATION_ERROR`
    (the default; ``centre_px`` in the rig's pixels). ``plates``: also write each static camera's
    clean plate, ``plates/<camera id>.exr`` (:data:`PLATES_DIR`: the empty set through its sensor,
    what ``volcap masks --plates`` computes the performer masks against). Same arguments, same bytes.
    """
    if not 1 <= actors <= 3:
        raise ValueError("actors must be 1, 2 or 3")
    error = dict(LENS_CALIBRATION_ERROR)
    if lens_calibration_error is not None:
        unknown = set(lens_calibration_error) - set(error)
        if unknown:
            raise ValueError(f"lens_calibration_error: unknown keys {sorted(unknown)}; known: {sorted(error)}")
        error.update(lens_calibration_error)
    return _synthesize(Path(out_dir), rig, seed, frames, "scene", actors, supersample, cameras, write_depth,
                       lidar_spacing_m, progress, name, lidar, error, plates=plates)


def synthesize_face_capture(out_dir: Path, rig: str = "demo_face", seed: int = 0, frames: int = 48, *,
                            progress: Progress | None = None, supersample: int = 2,
                            cameras: Sequence[str] | None = None, write_depth: bool = False,
                            lidar_spacing_m: float = 0.03, name: str | None = None,
                            actor_of: tuple[str | Path, int] | None = None) -> Path:
    """Render a Face Rig capture: one actor's head making expressions; returns capture.json's path.

    ``actor_of=(scene_capture_dir, n)``: the actor is actor ``n`` of that synthetic Scene Rig
    capture (its ``ground_truth/scene.json`` rebuilds and checks it): the same person (scale,
    colours, textures, freckles) on a riser at the rig's centre facing +x, the rest head centre
    where the rig's cameras look (the median height of their ``look_at_m``), with its own performance from
    ``seed``. capture.json then records ``performer: {capture, actor}`` and scene.json a
    ``performer`` block. ``ValueError`` (one line, naming the folder) for a folder that is not a
    synthetic Scene Rig capture or has no actor ``n``. Without it: the capture's own actor, the
    same bytes as before the option existed."""
    performer = _performer_source(actor_of) if actor_of is not None else None
    return _synthesize(Path(out_dir), rig, seed, frames, "face", 1, supersample, cameras, write_depth,
                       lidar_spacing_m, progress, name, performer=performer)


def synthetic_world(scene: Mapping, rig: Rig | None = None) -> World:
    """The World (set + actors) of a synthetic capture, rebuilt from its ``ground_truth/scene.json``
    (parsed): the set from the same seeded stream as :func:`_synthesize`, the actors from
    :func:`scene_actors_of` (which checks them against the file, a Face Rig capture of a Scene Rig
    actor included), so it renders the capture's truth from any camera at any time. ``rig``: the
    capture's rig (a capture folder's or store record's: a rig file is not found by name); None
    loads the built-in rig ``scene["rig"]``."""
    rig = load_rig(scene["rig"]) if rig is None else rig
    if rig.name != scene["rig"]:
        raise ValueError(f"scene.json was rendered with rig {scene['rig']!r}, not {rig.name!r}")
    if scene["kind"] not in ("scene", "face"):
        raise ValueError(f"scene.json: unknown kind {scene['kind']!r} (scene or face)")
    return World(_stage(rig, scene["kind"], int(scene["seed"])), scene_actors_of(scene))


def _stage(rig: Rig, kind: str, seed: int):
    """The set of a ``kind`` ("scene" or "face") capture from its seed: the one stream that both
    the synthesizer and the rebuilt world draw it from."""
    return (build_face_stage if kind == "face" else build_room_stage)(rig, _rng(seed, "stage"))
