"""The Face Rig's Gaussian-splat pairs: an HQ and an LQ Poly4DGS model of one Face Rig
sub-sequence rendered along the same camera path (the paper's "Training Data Generation";
``docs/enhancer.md``, "Gaussian-splat pairs").

Both models are ordinary segment models (``train-segment`` trains them on the Face Rig capture,
HQ at the preset's ``face_hq_gaussians_per_frame``, LQ at a count drawn from the LQ range by
:func:`lq_gaussians_per_frame`). :func:`render_path` renders one of them along a path's views
(the same cameras at the same times for both, so LQ and HQ frames are pixel-aligned) as linear
premultiplied RGBA with the Face Rig -> Scene Rig colour matrix applied, and, for the LQ, the
exact backward flow of each frame to the previous one
(:func:`~volcap_core.splat.render.render_flow`: the same Gaussians at the previous frame's time
through the previous camera). :func:`encode_pair_frame` / :func:`encode_flow_frame` write them
as EXR, :func:`encode_frames` a path's frames on several host threads.
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from volcap_core import reconstruction
from volcap_core.calibration.colour import apply_colour_matrix
from volcap_core.imageio.write import encode_exr
from volcap_core.view import ViewSpec
from volcap_core.splat import evaluate, render
from volcap_core.splat.model import Poly4DGS
from volcap_core.splat.render import Backend, gaussians_at, render_flow

__all__ = ["FLOW_CHANNELS", "encode_flow_frame", "encode_frames", "encode_pair_frame", "host_threads",
           "lq_gaussians_per_frame", "render_path"]

#: the channels of a flow frame (the render-shot frames' names, ``docs/shots.md``)
FLOW_CHANNELS = ("flow.x", "flow.y")


def lq_gaussians_per_frame(lq_range: tuple[int, int], seed: int, subsequence: int) -> int:
    """The LQ model's Gaussians per frame for sub-sequence ``subsequence``: uniform over the
    integers of ``[low, high]`` (inclusive), drawn from a generator seeded by ``seed`` and the
    sub-sequence, so each sub-sequence's draw is the same whatever the others are."""
    lo, hi = (int(v) for v in lq_range)
    if not 0 < lo <= hi:
        raise ValueError(f"LQ range must be 0 < low <= high, got {[lo, hi]}")
    return int(np.random.default_rng(zlib.crc32(f"lq/{seed}/{subsequence}".encode())).integers(lo, hi + 1))


def _camera(view: ViewSpec, device: torch.device):
    """The splat camera of ``view``, with its near plane when it has one (the renderer's default else)."""
    return reconstruction.splat_camera(np.asarray(view.K), np.asarray(view.world_to_camera), view.width, view.height,
                                       near=view.near_m).to(device)


def render_path(model: Poly4DGS, views: Sequence[ViewSpec], *, colour=None, flow: bool = False,
                backend: Backend = "auto") -> tuple[np.ndarray, np.ndarray | None]:
    """``model`` rendered from each view at its time: ``rgba [T, H, W, 4]`` float32, linear, RGB
    premultiplied by alpha (the renderer's), with ``colour`` applied (a colour-matrix record or
    ``(M, b)``, :func:`~volcap_core.calibration.colour.apply_colour_matrix` on premultiplied RGBA:
    the Face Rig's colour onto the Scene Rig's; None: unchanged). With ``flow``: also ``[T - 1, H,
    W, 2]`` float32, the exact backward flow of frame ``t`` to frame ``t - 1`` (px, x then y,
    ``cur(x, y) ≈ prev(x + fx, y + fy)``; 0 where the frame is empty), else None. A view's
    ``near_m`` is its camera's near plane for the colour and the flow alike (``Camera.near``, which
    both back-ends cull by): the Gaussians nearer than it at that frame are neither drawn nor
    counted in its flow. Runs on the model's device, the colour matrix too, frame by frame before
    its copy into the returned array (at 4096² a host-side matrix took longer than the render); the
    host holds the returned arrays and one frame in flight, nothing more."""
    if not views:
        raise ValueError("a camera path needs at least one view")
    sizes = {(v.width, v.height) for v in views}
    if len(sizes) != 1:
        raise ValueError(f"the views of a path must share one size, got {sorted(sizes)}")
    (w, h), = sizes
    matrix, offset = (colour, None) if colour is None or hasattr(colour, "matrix") else colour
    device = model.params["means"].device
    rgba = np.empty((len(views), h, w, 4), np.float32)
    flows = np.zeros((len(views) - 1 if flow else 0, h, w, 2), np.float32)
    with torch.no_grad():
        prev = None
        for t, view in enumerate(views):
            cam = _camera(view, device)
            g = evaluate(model, view.time_s)
            out = render(g, cam, backend=backend)
            frame = torch.cat([out["rgb"], out["alpha"]], dim=-1).float()
            if colour is not None:
                frame = apply_colour_matrix(frame, matrix, offset, premultiplied=True)
            torch.from_numpy(rgba[t]).copy_(frame)
            if flow and prev is not None:
                prev_view, prev_cam = prev
                f = render_flow(g, gaussians_at(model, prev_view.time_s, g.ids), cam, prev_cam, backend=backend)
                torch.from_numpy(flows[t - 1]).copy_(f["flow"].float())
            prev = (view, cam)
    return rgba, flows if flow else None


def host_threads() -> int:
    """The CPUs this process may run on: how many EXR encodes :func:`encode_frames` runs at once."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def encode_frames(encode: Callable[..., bytes], *per_frame: Sequence, workers: int | None = None
                  ) -> Iterator[bytes]:
    """``encode`` (:func:`encode_pair_frame`, :func:`encode_flow_frame`) of each frame's arguments
    (``per_frame``: one sequence per argument, zipped), yielded in the frames' order, run on
    ``workers`` host threads at once (None: :func:`host_threads`; 1: one after the other, in the caller's thread).
    OpenEXR compresses with the GIL released, so a path's encodes, seconds each at 4096², run side
    by side on as many cores (``docs/benchmarks.md``, "Face Rig pairs on a GPU"). Each encode in
    flight holds a half copy of its frame besides the caller's arrays."""
    workers = host_threads() if workers is None else workers
    if workers <= 1:
        yield from map(encode, *per_frame)
        return
    with ThreadPoolExecutor(workers, thread_name_prefix="exr-encode") as pool:
        yield from pool.map(encode, *per_frame)


def encode_pair_frame(rgba: np.ndarray, view: ViewSpec, attributes: dict[str, str | int | float]) -> bytes:
    """A pair frame ``[H, W, 4]`` as a half-float RGBA EXR, its camera (``volcap.K``,
    ``volcap.world_to_camera``, OpenCV; ``volcap.near_m`` when the view has a near plane) and time
    (``volcap.time_s``) in the header beside ``attributes`` (``volcap.pair`` ...)."""
    attrs = {"volcap.time_s": float(view.time_s), "volcap.K": json.dumps([list(r) for r in view.K]),
             "volcap.world_to_camera": json.dumps([list(r) for r in view.world_to_camera]),
             **({} if view.near_m is None else {"volcap.near_m": float(view.near_m)}), **attributes}
    return encode_exr(np.asarray(rgba, np.float32), ("R", "G", "B", "A"), pixel_type="half", attributes=attrs)


def encode_flow_frame(flow: np.ndarray, attributes: dict[str, str | int | float] | None = None) -> bytes:
    """A backward flow ``[H, W, 2]`` (px) as a float EXR with channels :data:`FLOW_CHANNELS`."""
    return encode_exr(np.asarray(flow, np.float32), FLOW_CHANNELS, pixel_type="float", attributes=attributes or {})
