"""Poly4DGS: dynamic Gaussian splats with polynomial motion (paper §"Dynamic Scene Reconstruction").

Modules, one concern each (see ``docs/poly4dgs.md``):

- :mod:`~volcap_core.splat.model` — parameters, :func:`evaluate` (slice at time t), save/load.
- :mod:`~volcap_core.splat.camera` — :class:`Camera` (OpenCV axes, pixels).
- :mod:`~volcap_core.splat.render` — :func:`render`, the one rasterization entry point, and
  :func:`render_flow` (the exact backward flow between two instants, for the enhancer).
- :mod:`~volcap_core.splat.rasterize` — the pure-PyTorch back-end (gsplat conventions).
- :mod:`~volcap_core.splat.composite_numba` — the compiled CPU compositor (back-end ``"numba"``),
  the same rules and gradients on :mod:`rasterize`'s tile bins.
- :mod:`~volcap_core.splat.grids` — per-camera exposure / black-level grids.
- :mod:`~volcap_core.splat.loss` — L1 + SSIM in unbounded sRGB, regularisers, display metrics.
- :mod:`~volcap_core.splat.mcmc` — 3DGS-MCMC relocation, growth, noise, regularisers.
- :mod:`~volcap_core.splat.train` — :func:`train_segment`.
- :mod:`~volcap_core.splat.ply` — standard 3DGS PLY export.
"""

from volcap_core.splat.camera import Camera, look_at
from volcap_core.splat.grids import ExposureGrids, apply_grids
from volcap_core.splat.model import (
                                     Gaussians3D,
                                     Poly4DGS,
                                     Poly4DGSConfig,
                                     evaluate,
                                     load_model,
                                     save_model,
)
from volcap_core.splat.ply import export_ply
from volcap_core.splat.render import gaussians_at, render, render_flow
from volcap_core.splat.train import (
                                     EvalPoint,
                                     PointsAtTime,
                                     SegmentData,
                                     TrainConfig,
                                     TrainResult,
                                     View,
                                     train_segment,
)

__all__ = [
    "Camera", "EvalPoint", "ExposureGrids", "Gaussians3D", "PointsAtTime", "Poly4DGS",
    "Poly4DGSConfig", "SegmentData", "TrainConfig", "TrainResult", "View", "apply_grids",
    "evaluate", "export_ply", "gaussians_at", "load_model", "look_at", "render", "render_flow", "save_model",
    "train_segment",
]
