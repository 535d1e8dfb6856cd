"""The camera schedule: which training view each step draws.

Uniform by default (every (camera, frame) alike, the 3DGS recipe). With a performer weight, a
view is drawn with probability ∝ ``1 + performer_weight · coverage``, ``coverage`` being the share
of its pixels that see the performers (the segment's moving initial points at the view's frame,
splatted at their own spacing). A tracking camera framing a face sees performers in most of its
pixels, a wide static camera in a few per cent: the views that hold the performers' detail are
drawn more often, and the set, which every static camera sees, still gets its share
(``docs/poly4dgs.md``, "Performers at the tracking cameras' resolution").
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

__all__ = ["moving_coverage", "view_weights", "draw_view"]


def moving_coverage(K: np.ndarray, world_to_camera: np.ndarray, width: int, height: int,
                    xyz: np.ndarray) -> float:
    """Share of a camera's pixels (0..1) that see the points ``xyz [P, 3]`` (metres), each splatted
    over about its distance to its neighbours (so a sparse cloud covers its surface, not dots).

    ``K`` 3×3 OpenCV (top-left pixel centre at 0), ``world_to_camera`` 4×4.
    """
    from volcap_core.calibration.lidar import depth_buffer
    from volcap_core.splat.init import neighbour_scale

    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    if len(xyz) == 0:
        return 0.0
    z = xyz @ world_to_camera[:3, 2] + world_to_camera[2, 3]
    front = z > 0.1
    if not front.any():
        return 0.0
    spacing_px = neighbour_scale(xyz)[front] * float(K[0, 0]) / z[front]
    splat = int(min(32, max(1, math.ceil(0.5 * float(np.median(spacing_px))))))
    zbuf = depth_buffer(K, world_to_camera, width, height, xyz, splat_px=splat)
    return float(np.isfinite(zbuf).mean())


def view_weights(views: Sequence, points: Sequence, performer_weight: float) -> np.ndarray | None:
    """``[V]`` draw weights of training ``views`` (:class:`~volcap_core.splat.train.View`), or None
    for the uniform schedule (``performer_weight == 0``).

    ``points``: the segment's :class:`~volcap_core.splat.train.PointsAtTime`; a view's performers
    are the moving points (``static`` False, or all points of a cloud without ``static``) of the
    cloud nearest its time.
    """
    if performer_weight <= 0:
        return None
    clouds = [(p.time, p.xyz.numpy() if p.static is None else p.xyz.numpy()[~p.static.numpy()])
              for p in points if p.static is None or not bool(p.static.all())]
    if not clouds:
        raise ValueError("a performer-weighted camera schedule needs the segment's moving points; "
                         "none of its initial clouds has any")
    out = np.empty(len(views))
    for i, v in enumerate(views):
        _, xyz = min(clouds, key=lambda c: abs(c[0] - v.time))
        K = v.camera.opencv_K()
        cover = moving_coverage(K, v.camera.world_to_camera.double().numpy(), v.camera.width, v.camera.height, xyz)
        out[i] = 1.0 + performer_weight * cover
    return out


def draw_view(n: int, weights: torch.Tensor | None, generator: torch.Generator) -> int:
    """Index of the view a step trains on: uniform (``torch.randint``, the draw of every run before
    weights existed, so a uniform schedule reproduces them) or ∝ ``weights [n]`` (float64)."""
    if weights is None:
        return int(torch.randint(n, (1,), generator=generator))
    return int(torch.multinomial(weights, 1, generator=generator))
