"""The truth of a synthetic capture for any camera at any time.

A synthetic capture (``docs/synthetic-capture.md``) is made by an analytic world: a seeded set and
seeded actors. Its ``ground_truth/scene.json`` records what rebuilds that world (seed, rig, kind,
actor count); :func:`truth_world` rebuilds it (through
:func:`~volcap_core.synth.synthesize.synthetic_world`) and checks the rebuild against the file (the
actors' description and every part of every actor at take index 0), so a capture made by another
synthesizer is refused instead of scored against the wrong truth. :func:`render_truth` then renders
it with the capture's own renderer (:func:`~volcap_core.synth.render.render`) through any pinhole
(or distorted) :class:`~volcap_core.synth.geometry.PinholeCamera` at any time:

- ``content="stage"``: the performers alone over nothing, premultiplied: ``rgb`` is the box filter
  of the radiance of the sub-samples that hit an actor (0 elsewhere) and ``alpha`` their fraction.
  Nothing of the set is drawn and nothing of it hides a performer;
- ``content="all"``: the whole world (set, props, targets, chart, performers), opaque; ``alpha``
  is the performers' coverage with occlusion (as ``ground_truth/masks/``).

The truth is scene radiance: no sensor (gain, vignette, glare, black level, noise), as a virtual
camera would see the stage. A capture camera's recorded values without noise are
``SensorModel.from_json(photometric).apply(radiance, None)``
(:class:`~volcap_core.synth.sensor.SensorModel`; ``photometric`` from ``ground_truth/cameras.json``).
:func:`capture_recording` composes them for a capture camera at a take index, sampled as the
synthesizer sampled its footage: the camera's **noise-free recording** (the expected value of
each footage pixel), or the same with noise drawn afresh from the camera's own noise model.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from hardware.rig import Rig
from volcap_core.calibration.distortion import Distortion
from volcap_core.capture import CaptureFolder
from volcap_core.synth.geometry import PinholeCamera
from volcap_core.synth.ground_truth import GroundTruthFiles
from volcap_core.synth.render import World, draw_prims, performer_coverage, render
from volcap_core.synth.sensor import SensorModel
from volcap_core.synth.synthesize import synthetic_world

__all__ = ["SCENE_FILE", "Truth", "capture_camera", "capture_recording", "capture_sensor", "render_truth",
           "truth_world", "truth_world_from_folder"]

#: the ground-truth file the world is rebuilt from
SCENE_FILE = "scene.json"


def _no_truth(capture: str, why: str) -> ValueError:
    return ValueError(f"capture {capture} has no synthetic ground truth ({why}): the truth is rendered only "
                      "for synthetic captures (volcap synth)")


def truth_world(files: GroundTruthFiles, rig: Rig) -> World:
    """The world of a synthetic capture from its stored ground truth (``files``: the tree
    ``Capture.ground_truth`` names; ``rig``: the capture's), its actors checked against the file."""
    if SCENE_FILE not in files:
        raise _no_truth(files.capture_name, "its ground truth has no scene.json")
    scene = json.loads(files.read(SCENE_FILE))
    return _rebuilt(scene, rig, files.capture_name)


def truth_world_from_folder(capture_dir: str | Path) -> World:
    """The world of the synthetic capture folder ``capture_dir`` (its ``ground_truth/scene.json``
    and rig), its actors checked against the file."""
    folder = CaptureFolder.open(Path(capture_dir))
    name = folder.description.name
    gt = folder.ground_truth_path
    if gt is None:
        raise _no_truth(name, f"{folder.description_path} names no ground_truth folder")
    if not (gt / SCENE_FILE).is_file():
        raise _no_truth(name, f"no {gt / SCENE_FILE}")
    scene = json.loads((gt / SCENE_FILE).read_text())
    return _rebuilt(scene, folder.rig, name)


def _rebuilt(scene: Mapping[str, Any], rig: Rig, capture: str) -> World:
    """:func:`~volcap_core.synth.synthesize.synthetic_world`, its errors naming the capture."""
    try:
        return synthetic_world(scene, rig)
    except ValueError as exc:
        raise ValueError(f"capture {capture}: the world rebuilt from ground_truth/scene.json: {exc}") from None


@dataclass(frozen=True)
class Truth:
    """One truth image.

    ``rgb`` ``[H, W, 3]`` float32: linear Rec.709 scene radiance (no sensor), box-filtered over
    the pixel's sub-samples; for ``content="stage"`` premultiplied by ``alpha`` (the performers over
    nothing). ``alpha`` ``[H, W]`` float32 in [0, 1]: the fraction of the pixel's sub-samples whose
    visible surface is a performer (multiples of 1/ss²). ``content``: what was rendered."""

    rgb: np.ndarray
    alpha: np.ndarray
    content: Literal["stage", "all"] = "stage"

    @property
    def rgba(self) -> np.ndarray:
        """``[H, W, 4]`` float32: premultiplied RGBA for ``stage``; for ``all`` alpha 1 (the set is
        opaque everywhere: a plate), the performers' coverage being in :attr:`alpha` only."""
        a = self.alpha if self.content == "stage" else np.ones_like(self.alpha)
        return np.concatenate([self.rgb, a[..., None]], axis=-1).astype(np.float32)


def render_truth(world: World, camera: PinholeCamera, t: float, *, content: Literal["stage", "all"] = "stage",
                 supersample: int = 2, set_supersample: int | None = None) -> Truth:
    """The truth seen by ``camera`` at ``t`` seconds on the take's clock (take index / fps).

    ``supersample``: ss x ss samples per pixel (the capture's footage used 2). ``content``: ``stage``
    (the performers over nothing) or ``all`` (module doc). ``set_supersample`` (``all`` only): the
    set's samples per pixel side, dividing ``supersample`` (None: ``supersample``; the capture's
    tracking cameras used 1, its static cameras ``supersample``: give the same to reproduce a
    capture camera's footage exactly). Cost: the performers' screen area at ss² samples (``stage``),
    plus the whole set (``all``)."""
    ss = int(supersample)
    if ss < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    if content == "all":
        rad, _, mask = render(world, camera, t, ss, bg_ss=set_supersample, want_mask=True)
        return Truth(rad, mask, "all")
    if content != "stage":
        raise ValueError(f"content must be 'stage' or 'all', got {content!r}")
    dirs = camera.ray_directions(ss)
    tbuf = np.full(dirs.shape[:2], np.inf, np.float32)
    rad = np.zeros((*dirs.shape[:2], 3), np.float32)
    idx = draw_prims(world, camera, dirs, ss, tbuf, rad, world.prims(t))
    rgb = rad if ss == 1 else cv2.resize(rad, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return Truth(rgb.astype(np.float32), performer_coverage(idx, ss), "stage")


def capture_camera(cameras: Mapping[str, Any], camera_id: str, take_index: int) -> PinholeCamera:
    """Camera ``camera_id`` of ``ground_truth/cameras.json`` (parsed) at ``take_index``: its true
    intrinsics, pose and lens distortion (a capture camera's truth renders its footage's pixels)."""
    try:
        cam = cameras["cameras"][camera_id]
    except KeyError:
        raise ValueError(f"ground truth has no camera {camera_id!r} "
                         f"(it has {', '.join(sorted(cameras['cameras']))})") from None
    frames = {f["take_index"]: f for f in cam["frames"]}
    if take_index not in frames:
        raise ValueError(f"ground truth camera {camera_id}: no take index {take_index} "
                         f"(0..{len(frames) - 1})")
    f = frames[take_index]
    w2c = np.asarray(f["world_to_camera"], np.float64)
    return PinholeCamera(int(cam["width"]), int(cam["height"]), float(f["fx"]), float(f["fy"]), float(f["cx"]),
                         float(f["cy"]), w2c[:3, :3], w2c[:3, 3], Distortion.from_json(f.get("distortion")))


def capture_sensor(cameras: Mapping[str, Any], camera_id: str) -> SensorModel:
    """The sensor of camera ``camera_id`` of ``ground_truth/cameras.json`` (parsed): its
    ``photometric`` (gain, vignette, glare, black level, read and shot noise)."""
    try:
        cam = cameras["cameras"][camera_id]
    except KeyError:
        raise ValueError(f"ground truth has no camera {camera_id!r} "
                         f"(it has {', '.join(sorted(cameras['cameras']))})") from None
    if "photometric" not in cam:
        raise ValueError(f"ground truth camera {camera_id}: no 'photometric' (its sensor is not recorded)")
    return SensorModel.from_json(cam["photometric"])


def capture_recording(world: World, cameras: Mapping[str, Any], camera_id: str, take_index: int, *,
                      supersample: int = 2, noise: np.random.Generator | None = None) -> np.ndarray:
    """What capture camera ``camera_id`` records at ``take_index``: ``[H, W, 3]`` float32, the
    footage's values (linear, black level included).

    The world seen through the camera's true lens and pose (:func:`capture_camera`) at
    ``take_index / fps`` seconds, ``content="all"``, sampled as the synthesizer sampled the footage
    (``supersample`` per pixel side, the capture's: ``volcap synth`` uses 2; the set at that rate for
    a static camera, at 1 for a tracking one), then through the camera's sensor
    (:func:`capture_sensor`). ``noise=None``: the **noise-free recording**, the expected value of
    each footage pixel (what a model that matched the scene exactly and learned the camera's
    exposure would render); a generator: noise drawn from it with the sensor's own law (read and
    shot noise; a fresh draw, independent of the footage's unless given its generator)."""
    sensor = capture_sensor(cameras, camera_id)   # refuses a camera the ground truth lacks
    tracks = cameras["cameras"][camera_id].get("tracking") is not None
    truth = render_truth(world, capture_camera(cameras, camera_id, take_index), take_index / float(cameras["fps"]),
                         content="all", supersample=supersample, set_supersample=1 if tracks else None)
    return sensor.apply(truth.rgb, noise)
