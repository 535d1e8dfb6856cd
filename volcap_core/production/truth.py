"""The truth of a shot of a synthetic capture: what its camera would have seen, frame by frame.

A synthetic capture knows its world (:mod:`volcap_core.synth.truth`), so a shot over it
(:class:`~volcap_core.production.shot.Shot`) has a truth at every frame: the world rendered by the
synthetic renderer through :func:`~volcap_core.production.shot.camera_at` at
:meth:`~volcap_core.production.shot.Shot.time_at`. Scene radiance, no sensor model (a shot camera
is virtual: no gain, vignette, glare, black level or noise), a pinhole like every shot camera.

Each truth frame is encoded exactly as the shot's render frames are
(:func:`~volcap_core.production.shot.encode_shot_exr`): RGBA half float, linear, premultiplied, the
display window the full frame, the data window the crop of the truth's own alpha (``shot.crop``),
the same camera header, plus ``volcap.truth`` and ``volcap.truthSupersample``. A ``content: stage``
shot's truth is the performers over nothing (its alpha: their coverage); ``content: all`` the whole
set, alpha 1. Read a truth frame and a render frame of the same shot frame with
:func:`volcap_core.enhance.production.read_shot_frame` (each over its display window): the two
arrays are then pixel for pixel the same camera's (``docs/shots.md``, "Truth").
"""

from __future__ import annotations

from collections.abc import Iterator

from volcap_core.capture import Capture
from volcap_core.production.shot import Shot, camera_at, encode_shot_exr
from volcap_core.splat.camera import Camera
from volcap_core.store import ArtifactStore
from volcap_core.synth.geometry import PinholeCamera
from volcap_core.synth.ground_truth import GroundTruthFiles
from volcap_core.synth.render import World
from volcap_core.synth.truth import render_truth, truth_world

__all__ = ["TRUTH_KIND", "render_truth_frame", "render_truth_frames", "shot_pinhole", "truth_world_of"]

#: ``volcap.truth`` of a truth frame: what its pixels are
TRUTH_KIND = "synthetic radiance, no sensor"


def truth_world_of(store: ArtifactStore, capture: Capture) -> World:
    """The world of an ingested synthetic ``capture`` from its ground-truth tree in ``store``
    (a cluster worker has no capture folder); ``ValueError`` ``capture X has no synthetic ground
    truth (...)`` for any other capture."""
    if capture.ground_truth is None:
        raise ValueError(f"capture {capture.name} has no synthetic ground truth (its record carries no "
                         "ground_truth tree): the truth is rendered only for synthetic captures (volcap synth)")
    tree = store.get_tree(capture.ground_truth)
    files = GroundTruthFiles(capture.name, {p: e.digest for p, e in tree.items()}, store.get_bytes)
    return truth_world(files, capture.rig)


def shot_pinhole(camera: Camera) -> PinholeCamera:
    """A shot's :class:`~volcap_core.splat.camera.Camera` (pixel centres at +0.5) as the synthetic
    renderer's :class:`~volcap_core.synth.geometry.PinholeCamera` (pixel centres at 0): the same rays."""
    K = camera.K.detach().cpu().double().numpy()
    w2c = camera.world_to_camera.detach().cpu().double().numpy()
    return PinholeCamera(camera.width, camera.height, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) - 0.5,
                         float(K[1, 2]) - 0.5, w2c[:3, :3], w2c[:3, 3])


def render_truth_frame(shot: Shot, world: World, frame: int, *, supersample: int = 2) -> bytes:
    """The truth of shot frame ``frame`` as the EXR bytes of a render frame (module doc), rendered
    at ``supersample`` x ``supersample`` samples per pixel (set and performers alike). No near/far
    clipping: everything in front of the camera is drawn."""
    a, b = shot.frames
    if not a <= frame < b:
        raise ValueError(f"shot {shot.name}: frame {frame} is outside its frames [{a}, {b})")
    camera = camera_at(shot, frame)
    truth = render_truth(world, shot_pinhole(camera), shot.time_at(frame), content=shot.content,
                         supersample=supersample)
    return encode_shot_exr(truth.rgba, camera, shot, frame,
                           extra={"content": shot.content, "truth": TRUTH_KIND, "truthSupersample": int(supersample)})


def render_truth_frames(shot: Shot, world: World, *, supersample: int = 2) -> Iterator[tuple[str, bytes]]:
    """Every frame of ``shot`` in order: (``<frame:06d>.exr``, :func:`render_truth_frame`), the
    names of the shot's render frames."""
    for f in shot.frame_numbers():
        yield f"{f:06d}.exr", render_truth_frame(shot, world, f, supersample=supersample)
