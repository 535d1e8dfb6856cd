"""Train one Poly4DGS segment: :func:`train_segment`, the library half of the segment task.

    data = SegmentData.build(frames=(a, b), camera_ids=ids, fps=fps,
                             load_image=lambda cam, f: ..., camera_for=lambda cam, f: ...)
    result = train_segment(data, points, TrainConfig(held_out_cameras=["cam07"]),
                           checkpoint=lambda blob, step: store.put(blob), seed=0)

One step: pick a random training (camera, frame); slice the model at the frame's time; render
(linear); apply that camera's exposure/black-level grids; loss in unbounded sRGB (L1 + SSIM) plus
grid and MCMC regularisers; Adam with per-parameter learning rates; MCMC relocation/growth at
refine steps and SGLD noise on the means after every step.

Held-out cameras are never trained on. Evaluation (every ``eval_every`` steps and at the end)
renders them with the frozen model and scores them under :mod:`volcap_core.splat.scoring`'s
protocol (a per-camera gain/offset fitted on the camera's *other* frames only), reporting PSNR/SSIM
on the display encoding (sRGB, clamped) against the training wall time so far (evaluation and
checkpoint time excluded).

Checkpoints are safetensors bytes (tensors + JSON metadata, no pickle) holding the model, both Adam
states, the grids, the RNG state, the step and the evaluation history. ``resume_from`` continues
exactly: on CPU a resumed run ends bit-identical to an uninterrupted one with the same seed.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, model_serializer
from safetensors.torch import load as st_load

from volcap_core.checkpoint import AdamState, adam_step, safetensors_bytes, safetensors_metadata
from volcap_core.colour import srgb_encode_unbounded
from volcap_core.splat.camera import Camera
from volcap_core.splat.grids import ExposureGrids, apply_grids
from volcap_core.splat.loss import (
    grid_regularisers,
    reconstruction_loss,
)
from volcap_core.splat.mcmc import (
    MCMCConfig,
    add_gaussians,
    inject_noise,
    mcmc_regulariser,
    relocate_dead,
)
from volcap_core.splat.model import (
    Gaussians3D,
    Poly4DGS,
    Poly4DGSConfig,
    evaluate,
)
from volcap_core.splat.render import BackendChoice, render, resolve_backend
from volcap_core.splat.schedule import draw_view, view_weights
from volcap_core.splat.sh import SH_C0
from volcap_core.splat.scoring import ViewScore, score_views, summarise

__all__ = [
    "EvalPoint",
    "LearningRates",
    "PointsAtTime",
    "SegmentData",
    "TrainConfig",
    "TrainResult",
    "View",
    "evaluate_held_out",
    "frame_interval",
    "init_model",
    "performer_alpha",
    "train_segment",
]

CHECKPOINT_FORMAT = "volcap-poly4dgs-train/1"


# ----------------------------------------------------------------------------------------- data

@dataclass(frozen=True)
class View:
    """One training or evaluation image.

    Attributes:
        camera_id: the camera (a rig camera id).
        frame: take index.
        time: seconds on the take's clock (``frame / fps``), the clock of the model's ``t0``.
        camera: intrinsics/extrinsics at this frame (zoom cameras may change per frame).
        image: ``[H, W, 3]`` or ``[H, W, 4]`` linear float (RGB, or premultiplied RGBA), or a
            zero-argument callable returning it (loaded lazily, e.g. from the artifact store).
        mask: where the performers are, ``[H, W]`` in [0, 1] (a synthetic capture's ground
            truth, else the capture's own masks), a callable returning it or None; only scoring
            reads it.
        valid: which pixels hold footage, ``[H, W]`` bool, a callable returning it or None (all):
            a distorted camera's frame rectified into a pinhole has none where its rays leave the
            sensor. Training's loss and the scores leave the others out.
        matte: the capture's own performer mask (imported or computed, never a ground truth),
            ``[H, W]`` in [0, 1], a callable returning it or None: what the performers' alpha is
            trained toward (``TrainConfig.mask_alpha_weight``).
    """

    camera_id: str
    frame: int
    time: float
    camera: Camera
    image: torch.Tensor | Callable[[], torch.Tensor]
    mask: torch.Tensor | Callable[[], torch.Tensor | None] | None = None
    valid: torch.Tensor | Callable[[], torch.Tensor | None] | None = None
    matte: torch.Tensor | Callable[[], torch.Tensor | None] | None = None

    def load_valid(self) -> torch.Tensor | None:
        """``[H, W]`` bool, or None when every pixel holds footage."""
        v = self.valid() if callable(self.valid) else self.valid
        if v is None:
            return None
        v = torch.as_tensor(v).to(torch.bool)
        if tuple(v.shape) != (self.camera.height, self.camera.width):
            raise ValueError(f"view {self.camera_id}@{self.frame}: valid mask {tuple(v.shape)}, camera "
                             f"{self.camera.width}x{self.camera.height}")
        return v

    def load_mask(self) -> torch.Tensor | None:
        return self._coverage(self.mask, "mask")

    def load_matte(self) -> torch.Tensor | None:
        """``[H, W]`` float32, the capture's performer mask (:attr:`matte`), or None."""
        return self._coverage(self.matte, "matte")

    def _coverage(self, value, what: str) -> torch.Tensor | None:
        m = value() if callable(value) else value
        if m is None:
            return None
        m = torch.as_tensor(m, dtype=torch.float32).reshape(-1)
        if m.numel() != self.camera.height * self.camera.width:
            raise ValueError(f"view {self.camera_id}@{self.frame}: {what} has {m.numel()} pixels, camera "
                             f"{self.camera.width}x{self.camera.height}")
        return m.reshape(self.camera.height, self.camera.width)

    def load(self) -> torch.Tensor:
        img = self.image() if callable(self.image) else self.image
        if img.ndim != 3 or img.shape[2] not in (3, 4):
            raise ValueError(f"view {self.camera_id}@{self.frame}: image must be [H,W,3|4], "
                             f"got {tuple(img.shape)}")
        if (img.shape[0], img.shape[1]) != (self.camera.height, self.camera.width):
            raise ValueError(f"view {self.camera_id}@{self.frame}: image {tuple(img.shape[:2])} "
                             f"!= camera {(self.camera.height, self.camera.width)}")
        return img.float()


@dataclass
class SegmentData:
    """The views of frames ``[a, b)`` of a capture: one :class:`View` per (camera, frame)."""

    frames: tuple[int, int]
    views: list[View]

    @classmethod
    def build(cls, *, frames: tuple[int, int], camera_ids: Sequence[str], fps: float,
              load_image: Callable[[str, int], torch.Tensor],
              camera_for: Callable[[str, int], Camera], lazy: bool = True,
              load_mask: Callable[[str, int], torch.Tensor | None] | None = None,
              load_valid: Callable[[str, int], torch.Tensor | None] | None = None,
              load_matte: Callable[[str, int], torch.Tensor | None] | None = None) -> "SegmentData":
        """Assemble from an ingested capture and a calibration.

        Args:
            frames: ``(a, b)`` take indices, b exclusive.
            camera_ids: cameras to use (training and held-out alike).
            fps: capture frame rate; a frame's time is ``index / fps`` seconds.
            load_image: ``(camera_id, take_index) -> [H, W, 3|4]`` linear image.
            camera_for: ``(camera_id, take_index) -> Camera``.
            lazy: defer ``load_image`` until a view is used (default), else load now. A lazy
                loader runs every time its view is drawn: cache inside it (e.g. an LRU of decoded
                frames) when decoding is expensive.
            load_mask: ``(camera_id, take_index) -> [H, W]`` performer coverage or None, read
                lazily, only when views are scored.
            load_valid: ``(camera_id, take_index) -> [H, W]`` bool (pixels that hold footage) or
                None, read lazily (:attr:`View.valid`).
            load_matte: ``(camera_id, take_index) -> [H, W]`` the capture's performer mask or None,
                read lazily, only when the alpha loss trains on it (:attr:`View.matte`).
        """
        a, b = frames
        if not 0 <= a < b:
            raise ValueError(f"bad frame range [{a}, {b})")
        views = []
        for cam in camera_ids:
            for f in range(a, b):
                img = (lambda c=cam, i=f: load_image(c, i)) if lazy else load_image(cam, f)
                mask = (lambda c=cam, i=f: load_mask(c, i)) if load_mask is not None else None
                valid = (lambda c=cam, i=f: load_valid(c, i)) if load_valid is not None else None
                matte = (lambda c=cam, i=f: load_matte(c, i)) if load_matte is not None else None
                views.append(View(cam, f, f / fps, camera_for(cam, f), img, mask, valid, matte))
        return cls((a, b), views)

    @property
    def camera_ids(self) -> list[str]:
        return sorted({v.camera_id for v in self.views})

    @property
    def times(self) -> list[float]:
        return sorted({v.time for v in self.views})


@dataclass(frozen=True)
class PointsAtTime:
    """A dense point cloud of one frame: ``xyz [P, 3]`` metres, ``rgb [P, 3]`` linear colour,
    ``time`` seconds (becomes the t0 of the moving Gaussians made from it), ``static [P]`` bool
    or None: which points belong to what does not move (:func:`volcap_core.splat.init.classify_static`;
    None = all moving)."""

    time: float
    xyz: torch.Tensor
    rgb: torch.Tensor
    static: torch.Tensor | None = None
    #: ``[P]`` metres, the finest pixel footprint of a training camera that sees each point
    #: (:func:`volcap_core.splat.init.finest_footprint`), or None; read with
    #: ``TrainConfig.init_moving_scale_px``
    footprint: torch.Tensor | None = None
    #: ``[P, 3]`` m/s, each point's velocity at ``time`` (the static points' 0;
    #: :func:`volcap_core.reconstruction.with_scene_flow`), or None: the moving Gaussians made from
    #: it start with this motion instead of none
    velocity: torch.Tensor | None = None

    def _per_point(self) -> list[str]:
        """The fields with one row per point: every one but ``time``."""
        return [f.name for f in fields(self) if f.name != "time"]

    def __post_init__(self) -> None:
        n = len(self.xyz)
        for name in self._per_point():
            v = getattr(self, name)
            if v is not None and len(v) != n:
                raise ValueError(f"points at t={self.time:.4f} s: {name} has {len(v)} rows for {n} points")

    def subset(self, keep: torch.Tensor) -> "PointsAtTime":
        """These points where ``keep`` ``[P]`` (bool or indices), every per-point field with them."""
        return replace(self, **{name: None if getattr(self, name) is None else getattr(self, name)[keep]
                                for name in self._per_point()})


# --------------------------------------------------------------------------------------- config

class LearningRates(BaseModel):
    """Adam learning rates per parameter (3DGS / gsplat-MCMC values where they exist).

    ``means`` decays exponentially to ``means_final`` over the run, both times the scene scale
    (1.1 × the largest camera distance from the cameras' centroid). Higher polynomial orders use
    the rate of their order-0 parameter divided by ``time_scale^i``, so every order moves the
    Gaussian by about the same amount per step at ``|t - t0| = time_scale``.

    ``exposure`` = 1e-2 and ``black`` = 1e-3 (the paper gives no rates; they were 1e-3 and 1e-4).
    A grid only gets an image gradient when its camera is drawn, and Adam moves it by about the
    rate per draw, so 1e-3 could not absorb real gain differences: on the bench capture (10
    training cameras, relative gains 0.58-1.33, 360 steps, ~36 draws per camera) the learned
    mean E stayed in 0.976-1.020, a slope of log E against log gain of 0.048. Measured there
    (``bench/bench_poly4dgs.py --lr-exposure E --lr-black B``; held-out PSNR / SSIM, slope):
    1e-3/1e-4: 21.75 dB / 0.7518, 0.048; 1e-2/1e-3: 21.73 dB / 0.7467, 0.246 (E 0.88-1.09);
    3e-2/3e-3: 21.60 dB / 0.7358, 0.358; 1e-1/1e-2: 21.49 dB / 0.7275, 0.343 (B grows to
    0.03-0.06 on glare-free cameras whose true offset is <= 0.008: it absorbs scene light).
    1e-2/1e-3 learns 5x more of the gains at equal held-out PSNR (-0.02 dB, a tie); higher rates
    learn a little more and cost PSNR. Over a production run (30k steps, ~230 draws per camera
    with 128 cameras) 1e-2 lets E span the gains several times over.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    means: float = 1.6e-4
    means_final: float = 1.6e-6
    quats: float = 1e-3
    scales: float = 5e-3
    opacities: float = 5e-2
    log_lambdas: float = 1e-2
    t0: float = 0.0
    sh0: float = 2.5e-3
    shN: float = 2.5e-3 / 20
    exposure: float = 1e-2
    black: float = 1e-3


class TrainConfig(BaseModel):
    """Everything that shapes a segment's training. JSON-serialisable (a task's cache key)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    model: Poly4DGSConfig = Poly4DGSConfig.paper()
    steps: int = Field(30_000, ge=0)
    lr: LearningRates = LearningRates()
    mcmc: MCMCConfig = MCMCConfig()
    ssim_weight: float = 0.2
    exposure_weight: float = 10.0
    black_weight: float = 0.05
    optimise_exposure: bool = True
    optimise_black_level: bool = True
    grid_size: int = Field(32, ge=1, description="exposure/black grid cells per axis")
    image_scale: float = Field(1.0, gt=0, le=1, description="training resolution / capture resolution: "
                               "the caller loads area-downsampled images and scaled cameras")
    alpha_weight: float = Field(0.0, ge=0, description="L1 on alpha when images are RGBA")
    mask_alpha_weight: float = Field(0.0, ge=0, description="L1 between the performers' alpha (the coverage "
                                     "of the moving Gaussians, in front of the set) and the view's performer "
                                     "mask (View.matte: the capture's masks), where a view has one; 0: off")
    mask_alpha_every: int = Field(1, ge=1, description="the alpha loss on every N-th step only (its extra render "
                                  "and backward cost ~60 % of a CPU step: docs/poly4dgs.md, 'Performer masks as "
                                  "an alpha loss')")
    set_frozen_from: float | None = Field(None, gt=0, lt=1, description="from this fraction of the steps on, the "
                                          "set (the static Gaussians) stops training and each training view's "
                                          "render of it is the background the performers are composited over, so "
                                          "the remaining steps cost only the performers' Gaussians (docs/poly4dgs.md, "
                                          "'The set frozen'); None: the set trains to the end")
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    held_out_cameras: list[str] = Field(default_factory=list)
    init_opacity: float = Field(0.5, gt=0, lt=1)
    init_lifespan_frames: float = Field(0.7, gt=0,
                                        description="initial temporal σ of moving Gaussians, in frame intervals")
    init_scene_flow: bool = Field(False, description="start each moving Gaussian with its point's velocity from the "
                                  "training views' optical flow (reconstruction.with_scene_flow), so that it can "
                                  "live over several frames (init_lifespan_frames); False: no motion")
    init_max_points: int | None = Field(None, gt=0, description="thin the initial points to this")
    init_cap_fraction: float = Field(0.7, gt=0, le=1, description="initial Gaussians at most this "
                                     "fraction of mcmc.cap_max (room for growth)")
    init_static_share: float = Field(0.6, ge=0, le=1, description="share of the initial budget "
                                     "for the static pool")
    init_scale_factor: float = Field(0.5, gt=0, description="initial scale / RMS distance to the 3 "
                                     "nearest neighbours")
    init_max_scale_ratio: float = Field(4.0, gt=0, description="cap on the initial scale, × the "
                                        "median initial scale of its pool")
    init_moving_scale_px: float | None = Field(None, gt=0, description="cap on a moving Gaussian's initial "
                                               "scale, in pixel footprints of the finest training camera that "
                                               "sees its point (PointsAtTime.footprint); None: no cap")
    init_zoom_stride_px: int | None = Field(None, gt=0, description="add to each frame's moving points "
                                            "the training cameras that resolve them finer than their spacing, "
                                            "sampled every this many pixels (splat.init.zoom_points); None: off")
    init_finest_level: int = Field(0, ge=-4, le=0, description="moving points thinned on grids up to 2^-this "
                                   "times finer where a camera resolves finer (splat.init.footprint_levels)")
    performer_view_weight: float = Field(0.0, ge=0, description="camera schedule: a training view is drawn "
                                         "with probability ∝ 1 + this × the share of its pixels seeing the "
                                         "performers (splat.schedule); 0: uniform")
    time_scale_s: float | None = Field(None, gt=0, description="default: half the segment")
    checkpoint_every: int = Field(1000, ge=0)
    eval_every: int = Field(1000, ge=0, description="0: only at the end")
    eval_max_views: int = Field(24, gt=0)
    #: the rasterizer (:func:`~volcap_core.splat.render.resolve_backend`; "auto": gsplat on CUDA,
    #: the compiled compositor for float32 CPU tensors)
    backend: Literal["auto", "gsplat", "torch", "numba"] = "auto"
    tile_size: int = Field(8, ge=1)

    @model_serializer(mode="wrap")
    def _omit_off_options(self, handler):
        # at their defaults the alpha loss's, the frozen set's and the scene flow's fields are left out of the JSON:
        # configs (a train-segment key, a stored record's config) written before they existed keep
        # their bytes
        out = handler(self)
        if isinstance(out, dict):
            for name, off in _OFF_WHEN.items():
                if name in out and out[name] == off:
                    del out[name]
        return out


#: TrainConfig fields left out of its JSON at these values (added after configs were stored)
_OFF_WHEN = {"mask_alpha_weight": 0.0, "mask_alpha_every": 1, "set_frozen_from": None, "init_scene_flow": False}


@dataclass(frozen=True)
class EvalPoint:
    """Held-out quality after ``step`` optimiser steps and ``wall_s`` seconds of training."""

    step: int
    wall_s: float
    psnr: float
    ssim: float


@dataclass
class TrainResult:
    model: Poly4DGS
    grids: ExposureGrids
    history: list[EvalPoint] = field(default_factory=list)
    steps: int = 0
    wall_s: float = 0.0
    #: the rasterizer this run used and why (:func:`~volcap_core.splat.render.resolve_backend`
    #: of ``TrainConfig.backend`` on the training device); ``train_segment`` always sets it
    backend: BackendChoice | None = None


# ---------------------------------------------------------------------------------------- init

def init_model(points: Sequence[PointsAtTime], config: TrainConfig, *, frame_interval_s: float,
               generator: torch.Generator | None = None) -> Poly4DGS:
    """The untrained model of a segment (:mod:`volcap_core.splat.init`).

    Static points (``PointsAtTime.static``) of every frame are pooled into one set of Gaussians
    that live for the whole segment (centred mid-segment, λ = 0); each frame's moving points,
    isolated ones dropped, become Gaussians centred on their frame's time with temporal σ =
    ``init_lifespan_frames`` frame intervals. Both are thinned on voxel grids to
    ``init_budget(config)`` Gaussians (``init_static_share`` of it for the static pool). Colour =
    the point's colour (unbounded sRGB, or linear as it is when ``config.model.colour_space ==
    "linear"``), isotropic scale = ``init_scale_factor`` × the RMS distance to the 3 nearest
    neighbours of its pool (at most ``init_max_scale_ratio`` × the pool's median), opacity
    ``init_opacity``; no motion, or where the points carry a velocity
    (``PointsAtTime.velocity``: :func:`volcap_core.reconstruction.with_scene_flow`) that velocity.
    """
    from volcap_core.splat.init import initial_gaussians

    if not points or sum(len(p.xyz) for p in points) == 0:
        raise ValueError("no initial points: the segment's dense point clouds are empty")
    seed = int(torch.randint(2 ** 31 - 1, (1,), generator=generator)) if generator is not None else 0
    if ((config.init_moving_scale_px is not None or config.init_finest_level < 0)
            and any(p.footprint is None for p in points)):
        raise ValueError("init_moving_scale_px and init_finest_level need every initial cloud's footprint "
                         "(PointsAtTime.footprint)")
    frames = [(p.time, p.xyz.double().numpy(), p.rgb.double().numpy(),
               None if p.static is None else p.static.numpy(),
               None if p.footprint is None else p.footprint.double().numpy(),
               None if p.velocity is None else p.velocity.double().numpy()) for p in points]
    split = initial_gaussians(frames, budget=init_budget(config), static_share=config.init_static_share,
                              scale_factor=config.init_scale_factor,
                              max_scale_ratio=config.init_max_scale_ratio,
                              seed=seed, moving_scale_px=config.init_moving_scale_px,
                              finest_level=config.init_finest_level)
    if len(split.xyz) == 0:
        raise ValueError("no initial points left after dropping isolated moving points")
    rgb = torch.from_numpy(split.rgb).float()
    colour = rgb if config.model.colour_space == "linear" else srgb_encode_unbounded(rgb)
    lifespan = torch.where(torch.from_numpy(split.static), torch.tensor(float("inf")),
                           torch.tensor(config.init_lifespan_frames * frame_interval_s))
    return Poly4DGS.from_points(config.model, torch.from_numpy(split.xyz).float(), colour,
                                scales=torch.from_numpy(split.scale).float(),
                                t0=torch.from_numpy(split.t0).float(), opacity=config.init_opacity,
                                lifespan_s=lifespan,
                                velocity=None if split.velocity is None else torch.from_numpy(split.velocity).float())


def init_budget(config: TrainConfig) -> int:
    """Initial Gaussians: ``init_max_points`` but at most ``init_cap_fraction`` of MCMC's cap, so
    growth has room to act."""
    cap = config.mcmc.cap_max
    budget = max(1, int(config.init_cap_fraction * cap))
    return min(config.init_max_points or budget, budget)


def _scene_scale(cameras: Sequence[Camera]) -> float:
    centres = torch.stack([c.centre for c in cameras])
    return 1.1 * float((centres - centres.mean(0)).norm(dim=1).max().clamp(min=1e-3))


def frame_interval(times: Sequence[float]) -> float:
    """Seconds between a segment's frames (median spacing of ``times``; 1/30 for one frame)."""
    if len(times) < 2:
        return 1.0 / 30.0
    return float(np.median(np.diff(np.asarray(sorted(times)))))


def exponential_lr(lr_init: float, lr_final: float, step: int, max_steps: int) -> float:
    """Log-linear decay from ``lr_init`` at step 0 to ``lr_final`` at ``max_steps`` (3DGS's position
    schedule: 1.6e-4 -> 1.6e-6 times the scene scale), constant after."""
    if max_steps <= 0 or lr_init == lr_final:
        return lr_init
    f = min(max(step / max_steps, 0.0), 1.0)
    return float(lr_init * (lr_final / lr_init) ** f)


def learning_rates(cfg: TrainConfig, step: int, scene_scale: float, time_scale: float,
                   model: Poly4DGS) -> dict[str, float | torch.Tensor]:
    """Each parameter's learning rate at ``step``: the means' exponential decay in scene units
    (``scene_scale``, m), and the motion coefficients' order ``k`` divided by ``time_scale ** k``
    (``time_scale`` in s) so that a coefficient's step moves a Gaussian as far at every order;
    these are tensors [1, k, 1] broadcasting over the Gaussians."""
    lr = cfg.lr
    means = exponential_lr(lr.means * scene_scale, lr.means_final * scene_scale, step, cfg.steps)
    out: dict[str, float | torch.Tensor] = {
        "means": means, "quats": lr.quats, "scales": lr.scales, "opacities": lr.opacities,
        "log_lambdas": lr.log_lambdas, "t0": lr.t0, "sh0": lr.sh0, "shN": lr.shN}
    for name, base in (("means_t", means), ("quats_t", lr.quats), ("scales_t", lr.scales)):
        if name in model.params:
            n = model.params[name].shape[1]
            order = torch.arange(1, n + 1, dtype=torch.float32)
            out[name] = (base * time_scale ** -order).view(1, n, 1).to(model.params[name].device)
    return out


def _non_finite(model: Poly4DGS) -> str:
    bad = {k: int((~torch.isfinite(v.detach())).any(dim=tuple(range(1, v.ndim))).sum()) if v.ndim > 1
           else int((~torch.isfinite(v.detach())).sum()) for k, v in model.params.items()}
    return ", ".join(f"{k} in {n} Gaussian(s)" for k, n in bad.items() if n) or "none"


def _freeze_static_lifespans(model: Poly4DGS) -> None:
    """No lifespan update for Gaussians that live for ever: their log λ gradient is ~1e-19, and
    Adam (ε = 1e-15) would turn it into full-size steps that, over a long run, make the static
    set flicker out."""
    g = model.params.get("log_lambdas")
    if g is None or g.grad is None:
        return
    g.grad[~model.moving()] = 0.0


# ---------------------------------------------------------------------------------- evaluation

def render_views(model: Poly4DGS | None, views: Sequence[View], config: TrainConfig, *,
                 device: torch.device | str = "cpu") -> list[torch.Tensor]:
    """Linear renders ``[H, W, 3]`` of ``model`` for ``views`` (no grid applied); ``None`` = the
    empty model (it renders the background)."""
    bg = torch.tensor(config.background, device=device)
    out = []
    with torch.no_grad():
        for v in views:
            if model is None:
                out.append(bg.expand(v.camera.height, v.camera.width, 3).clone())
            else:
                out.append(render(evaluate(model, v.time), v.camera, backend=config.backend,
                                  background=bg, tile_size=config.tile_size)["rgb"])
    return out


def evaluate_held_out(model: Poly4DGS | None, views: Sequence[View], config: TrainConfig, *,
                      device: torch.device | str = "cpu") -> list[ViewScore]:
    """Score ``model`` on held-out ``views`` under the protocol of :mod:`volcap_core.splat.scoring`
    (per-camera gain/offset fitted on the camera's *other* frames, raw figures beside, performer
    figures where views carry masks). ``model=None`` scores the empty model (a floor)."""
    if not views:
        return []
    renders = render_views(model, views, config, device=device)
    return score_views(renders, [v.load()[..., :3].to(renders[0]) for v in views],
                       [v.camera_id for v in views], [v.frame for v in views],
                       [v.load_mask() for v in views], valid=[v.load_valid() for v in views])


def _eval_subset(views: Sequence[View], n: int) -> list[View]:
    """At most ``n`` views, spread evenly over the list (deterministic)."""
    if len(views) <= n:
        return list(views)
    idx = np.linspace(0, len(views) - 1, n).round().astype(int)
    return [views[i] for i in sorted(set(idx.tolist()))]


# ---------------------------------------------------------------------------------- checkpoints

@dataclass
class _State:
    model: Poly4DGS
    adam: AdamState
    grids: ExposureGrids
    grid_adam: AdamState
    generator: torch.Generator
    step: int
    wall_s: float
    history: list[EvalPoint]


#: The frozen set's renders kept for its training views at most (``TrainConfig.set_frozen_from``):
#: the demo segment's 72 views at 320x180 take 50 MB; a production's 4K views ~100 MB each, so
#: beyond this a view's render of the set is made again each time it is drawn
SET_RENDERS_KEPT_BYTES = 2 * 1024 ** 3


@dataclass
class _FrozenSet:
    """The set once frozen (``TrainConfig.set_frozen_from``): its Gaussians and their Adam moments
    (kept so that a checkpoint still holds the whole model and its state), and each training
    view's render of it (``[H, W, 3]`` linear, over the config's background), made on the view's
    first draw and kept within :data:`SET_RENDERS_KEPT_BYTES`: 12 bytes a pixel a training view."""

    model: Poly4DGS
    adam: AdamState
    backgrounds: dict[int, torch.Tensor] = field(default_factory=dict)


def _freeze_set(state: _State) -> _FrozenSet:
    """Split ``state``'s model in place: the performers (moving Gaussians) stay in it as the
    trained leaves, the set (static ones) goes to the returned :class:`_FrozenSet`. Each keeps
    its order, so :func:`_whole` gives the model back set first, and splitting that again (a
    checkpoint resumed after the freeze) gives the same two halves."""
    moving = state.model.moving()
    frozen = _FrozenSet(state.model.subset(~moving), AdamState(
        {k: m[~moving] for k, m in state.adam.exp_avg.items()},
        {k: v[~moving] for k, v in state.adam.exp_avg_sq.items()}, state.adam.step))
    state.model = state.model.subset(moving)
    for v in state.model.params.values():
        v.requires_grad_(True)
    state.adam = AdamState({k: m[moving] for k, m in state.adam.exp_avg.items()},
                           {k: v[moving] for k, v in state.adam.exp_avg_sq.items()}, state.adam.step)
    return frozen


def _whole(state: _State, frozen: _FrozenSet | None) -> _State:
    """``state`` with the frozen set joined back in front of the performers (model and Adam
    moments): what a checkpoint, an evaluation and the result hold."""
    if frozen is None:
        return state
    adam = AdamState({k: torch.cat([frozen.adam.exp_avg[k], m]) for k, m in state.adam.exp_avg.items()},
                     {k: torch.cat([frozen.adam.exp_avg_sq[k], v]) for k, v in state.adam.exp_avg_sq.items()},
                     state.adam.step)
    return replace(state, model=Poly4DGS.joined(frozen.model, state.model), adam=adam)


def _performers_mcmc(config: TrainConfig, n_set: int, n_performers: int) -> TrainConfig:
    """``config`` for a refine step of the performers alone (the set frozen): the segment's budget
    less the set's Gaussians, and growth by as many as the whole model's ``grow_rate`` would add,
    so freezing the set leaves the count as it would have grown (MCMC's ``moving_weight`` sends most
    of that growth to the performers anyway)."""
    m = config.mcmc
    rate = m.grow_rate * (n_set + n_performers) / max(1, n_performers)
    return config.model_copy(update={"mcmc": m.model_copy(
        update={"cap_max": max(1, m.cap_max - n_set), "grow_rate": rate})})


def _with_set(set_model: Poly4DGS, points: Sequence[PointsAtTime], config: TrainConfig, *,
              frame_interval_s: float, generator: torch.Generator) -> Poly4DGS:
    """The untrained model of a segment whose set is trained already (``train_segment``'s
    ``set_model``): ``set_model`` first, then the performers initialised from ``points``' moving
    points alone (:func:`init_model` with the whole initial budget theirs)."""
    if not bool((~set_model.moving()).all()):
        raise ValueError(f"set_model: {int(set_model.moving().sum())} of its {len(set_model)} Gaussians "
                         "have a lifespan (performers'); a set holds static Gaussians only")
    moving = [replace(p.subset(~p.static), static=None) if p.static is not None else p for p in points]
    performers = init_model([p for p in moving if len(p.xyz)], config.model_copy(update={"init_static_share": 0.0}),
                            frame_interval_s=frame_interval_s, generator=generator)
    return Poly4DGS.joined(set_model.to(performers.params["means"].device), performers)


def _serialise(state: _State, config: TrainConfig, extra: dict) -> bytes:
    tensors: dict[str, torch.Tensor] = {}
    for k, v in state.model.params.items():
        tensors[f"model/{k}"] = v.detach()
    tensors.update(state.adam.to_tensors("adam"))
    tensors["grids/exposure"] = state.grids.exposure.detach()
    tensors["grids/black"] = state.grids.black.detach()
    tensors.update(state.grid_adam.to_tensors("grid_adam"))
    tensors["rng"] = state.generator.get_state()
    tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    meta = {
        "format": CHECKPOINT_FORMAT,
        "train_config": config.model_dump_json(),
        "model_config": state.model.config.model_dump_json(),
        "state": json.dumps({
            "step": state.step, "adam_step": state.adam.step,
            "grid_adam_step": state.grid_adam.step, "wall_s": state.wall_s,
            "camera_ids": state.grids.camera_ids,
            "history": [[e.step, e.wall_s, e.psnr, e.ssim] for e in state.history],
            **extra}),
    }
    return safetensors_bytes(tensors, meta)


def _deserialise(data: bytes, device) -> tuple[_State, dict, Poly4DGSConfig]:
    meta = safetensors_metadata(data)
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"not a Poly4DGS training checkpoint (format {meta.get('format')!r})")
    info = json.loads(meta["state"])
    model_cfg = Poly4DGSConfig.model_validate_json(meta["model_config"])
    # st_load's tensors are views on read-only per-tensor buffers; training updates them in
    # place, so copy them into memory of our own
    t = {k: v.clone() for k, v in st_load(data).items()}
    names = sorted(k.split("/", 1)[1] for k in t if k.startswith("model/"))
    model = Poly4DGS(model_cfg, {k: t[f"model/{k}"].to(device).requires_grad_(True)
                                 for k in names})
    adam = AdamState.from_tensors(t, "adam", info["adam_step"], like=model.params)
    grids = ExposureGrids(info["camera_ids"], t["grids/exposure"].to(device),
                          t["grids/black"].to(device))
    gadam = AdamState.from_tensors(t, "grid_adam", info["grid_adam_step"],
                                   like={"exposure": grids.exposure, "black": grids.black})
    gen = torch.Generator()
    gen.set_state(t["rng"])
    history = [EvalPoint(int(s), float(w), float(p), float(q)) for s, w, p, q in info["history"]]
    return (_State(model, adam, grids, gadam, gen, info["step"], info["wall_s"], history), info,
            model_cfg)


# ------------------------------------------------------------------------------------- training

def performer_alpha(model: Poly4DGS, gaussians: Gaussians3D, camera: Camera, *, backend: str,
                    tile_size: int = 8) -> torch.Tensor:
    """The performers' alpha ``[H, W]``: ``Σ T_i α_i m_i`` over ``gaussians`` (``evaluate(model, t)``),
    ``m_i`` 1 for a moving Gaussian (a lifespan: ``log λ_1`` above the static value; every
    Gaussian of a model without lifespans) and 0 for the set's. That is each pixel's coverage by
    the performers *with the set in front of them occluding*, what a performer mask holds, and
    what compositing the performers over another background needs; the render's own alpha is 1
    wherever the set is. One more render of the same Gaussians, each a flat linear colour
    ``m_i``, over black."""
    moving = model.moving()[gaussians.ids].to(gaussians.sh.dtype)
    sh = torch.zeros_like(gaussians.sh)
    sh[:, 0, :] = ((moving - 0.5) / SH_C0)[:, None]     # SH DC: colour = sh0·C0 + 0.5 = m
    flat = replace(gaussians, sh=sh, colour_space="linear")
    black = torch.zeros(3, device=gaussians.means.device)
    return render(flat, camera, backend=backend, background=black, tile_size=tile_size)["rgb"][..., 0]


def step_loss(model: Poly4DGS, time: float, camera: Camera, target: torch.Tensor,
              valid: torch.Tensor | None, exposure: torch.Tensor, row: int, black: torch.Tensor,
              config: TrainConfig, *, backend: str, background: torch.Tensor,
              matte: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """The loss of one training step: the model at ``time`` rendered at ``camera``, through the
    camera's exposure and black-level grids, against its footage.

    Args:
        target: the footage [H, W, 3] or, with alpha, [H, W, 4], linear.
        valid: [H, W] bool, where the frame holds footage (a rectified lens's border does not),
            or None for everywhere.
        exposure: every training camera's exposure grid [C, Gy, Gx, 3]; ``row`` picks this one.
        black: every training camera's black-level grid [C, 3]; ``row`` picks this one.
        background: what the render is composited over: a ``[3]`` linear colour or, once the set
            is frozen (``config.set_frozen_from``), the view's ``[H, W, 3]`` render of the set.
        matte: [H, W] the view's performer mask in [0, 1], or None; with
            ``config.mask_alpha_weight`` the performers' alpha (:func:`performer_alpha`) is pulled
            toward it (L1 over the valid pixels).
    Returns:
        (scalar loss, its reported parts): L1 + SSIM (``config.ssim_weight``), the alpha terms,
        the grids' regularisers and the MCMC regulariser.
    """
    gaussians = evaluate(model, time)
    out = render(gaussians, camera, backend=backend, background=background, tile_size=config.tile_size)
    pred = apply_grids(out["rgb"], exposure[row] if config.optimise_exposure else None,
                       black[row] if config.optimise_black_level else None)
    target_rgb = target[..., :3]
    if valid is not None:
        # no footage there (a rectified lens's border): render and target are both 0 there, so
        # those pixels add no error, no gradient, and whatever the frame holds there is unseen
        v = valid.to(target.device)[..., None]
        target_rgb = torch.where(v, target_rgb, torch.zeros_like(target_rgb))
        pred = torch.where(v, pred, target_rgb)
    loss, parts = reconstruction_loss(pred, target_rgb, ssim_weight=config.ssim_weight)
    if config.alpha_weight and target.shape[2] == 4:
        loss = loss + config.alpha_weight * (out["alpha"] - target[..., 3:]).abs().mean()
    if config.mask_alpha_weight and matte is not None:
        err = (performer_alpha(model, gaussians, camera, backend=backend, tile_size=config.tile_size)
               - matte.to(target.device)).abs()
        l_matte = err[valid.to(err.device)].mean() if valid is not None else err.mean()
        loss = loss + config.mask_alpha_weight * l_matte
        parts["matte"] = float(l_matte.detach())
    reg, _ = grid_regularisers(
        exposure, black[row],
        exposure_weight=config.exposure_weight if config.optimise_exposure else 0.0,
        black_weight=config.black_weight if config.optimise_black_level else 0.0)
    return loss + reg + mcmc_regulariser(model, config.mcmc), parts


def optimiser_step(model: Poly4DGS, adam: AdamState, grid_params: dict[str, torch.Tensor],
                   grid_lrs: dict[str, float], grid_adam: AdamState,
                   lrs: dict[str, float | torch.Tensor], config: TrainConfig, step: int,
                   generator: torch.Generator, *, scene_scale: float) -> tuple[int, int]:
    """Everything after the backward pass of one step: Adam on the model (static lifespans frozen)
    and on the grids, MCMC relocation and growth on its refine steps, then MCMC's position noise.
    Returns (Gaussians relocated, Gaussians added)."""
    _freeze_static_lifespans(model)
    adam_step(model.params, lrs, adam)
    adam_step(grid_params, grid_lrs, grid_adam)
    relocated = grown = 0
    if config.mcmc.is_refine_step(step):
        relocated = relocate_dead(model, adam, config.mcmc, generator)
        grown = add_gaussians(model, adam, config.mcmc, generator)
    inject_noise(model, float(lrs["means"]), config.mcmc, generator, scene_scale=scene_scale)
    return relocated, grown



def train_segment(views: SegmentData, init_points: Sequence[PointsAtTime], config: TrainConfig,
                  *, set_model: Poly4DGS | None = None,
                  checkpoint: Callable[[bytes, int], None] | None = None,
                  resume_from: bytes | None = None, seed: int = 0,
                  progress: Callable[[int, int, dict], None] | None = None,
                  device: torch.device | str | None = None) -> TrainResult:
    """Fit a Poly4DGS model to one segment.

    Args:
        views: the segment's images and cameras (held-out cameras included; they are split off
            by ``config.held_out_cameras``).
        init_points: dense points per frame (ignored when resuming).
        config: see :class:`TrainConfig`.
        set_model: the set trained already (static Gaussians only, the same model config; e.g.
            once per capture from the static cameras' background plates), or None. Given, it is
            frozen from the first step as ``config.set_frozen_from`` freezes the segment's own
            set: each training view's render of it is the background the performers are
            composited over; the performers start from ``init_points``' moving points alone and
            have MCMC's whole budget (``config.mcmc.cap_max``) to themselves. The result and
            every checkpoint hold the whole model, the set first. Resuming, pass it again: the
            checkpoint holds its values, its presence keeps the set frozen from the first step.
        checkpoint: called as ``checkpoint(bytes, step)`` every ``config.checkpoint_every`` steps
            and after the last step; the bytes resume the run exactly.
        resume_from: checkpoint bytes to continue from (the model config must match; the rest of
            ``config`` applies from here on, e.g. a larger ``steps``).
        seed: seeds the single ``torch.Generator`` behind every random choice.
        progress: called as ``progress(step, total_steps, info)`` after every step, ``info``
            holding ``loss``, ``l1``, ``ssim``, ``num_gaussians``, ``wall_s``.
        device: where to train; default CUDA when available, else CPU.
    Returns:
        :class:`TrainResult` (model, training grids, evaluation history, the back-end used).
    Raises:
        BackendUnavailable: ``config.backend`` cannot run on ``device`` (``"gsplat"`` off CUDA or
            unusable, ``"numba"`` off the CPU); raised before any other work.
    """
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    # once, before anything else: an explicit back-end that cannot run fails here rather than
    # after initialisation, and an "auto" fallback to torch on a GPU is logged and recorded
    backend = resolve_backend(config.backend, device)
    held = set(config.held_out_cameras)
    unknown = held - set(views.camera_ids)
    if unknown:
        raise ValueError(f"held-out cameras not in the data: {sorted(unknown)}")
    train_views = [v for v in views.views if v.camera_id not in held]
    eval_views = _eval_subset([v for v in views.views if v.camera_id in held],
                              config.eval_max_views)
    if not train_views:
        raise ValueError("no training views left after holding out cameras")
    train_cams = sorted({v.camera_id for v in train_views})
    weights = view_weights(train_views, init_points, config.performer_view_weight)
    weights = None if weights is None else torch.from_numpy(weights)
    scene_scale = _scene_scale([v.camera for v in train_views])
    frame_dt = frame_interval(views.times)
    seg_len = max(views.times) - min(views.times)
    time_scale = config.time_scale_s or max(0.5 * seg_len, frame_dt)
    extra = {"scene_scale": scene_scale, "time_scale": time_scale, "seed": seed}

    if resume_from is not None:
        state, info, model_cfg = _deserialise(resume_from, device)
        if model_cfg != config.model:
            raise ValueError(f"checkpoint model config {model_cfg} != {config.model}")
        if state.grids.camera_ids != train_cams:
            raise ValueError("checkpoint was trained on other cameras")
    else:
        gen = torch.Generator().manual_seed(seed)
        if set_model is None:
            model = init_model(init_points, config, frame_interval_s=frame_dt, generator=gen).to(device)
        else:
            model = _with_set(set_model, init_points, config, frame_interval_s=frame_dt, generator=gen).to(device)
        for v in model.params.values():
            v.requires_grad_(True)
        grids = ExposureGrids.identity(train_cams, config.grid_size, device)
        state = _State(model, AdamState.zeros_like(model.params), grids,
                       AdamState.zeros_like({"exposure": grids.exposure, "black": grids.black}),
                       gen, 0, 0.0, [])
    grid_params = {"exposure": state.grids.exposure.requires_grad_(config.optimise_exposure),
                   "black": state.grids.black.requires_grad_(config.optimise_black_level)}
    grid_lrs = {"exposure": config.lr.exposure if config.optimise_exposure else 0.0,
                "black": config.lr.black if config.optimise_black_level else 0.0}
    bg = torch.tensor(config.background, device=device)
    cam_row = {c: i for i, c in enumerate(train_cams)}
    # the step at which the set stops training (TrainConfig.set_frozen_from; the first, with a set
    # trained already), and once it has
    frozen_at = (0 if set_model is not None
                 else None if config.set_frozen_from is None else max(1, round(config.set_frozen_from * config.steps)))
    frozen: _FrozenSet | None = None
    step_config = config

    def run_eval() -> None:
        if eval_views and (not state.history or state.history[-1].step != state.step):
            sc = summarise(evaluate_held_out(_whole(state, frozen).model, eval_views, config, device=device))
            state.history.append(EvalPoint(state.step, state.wall_s, sc.psnr, sc.ssim))

    def background(i: int) -> torch.Tensor:
        """What training view ``i``'s performers are composited over: the config's colour, or
        once the set is frozen, the view's render of it (kept while the kept renders stay within
        :data:`SET_RENDERS_KEPT_BYTES`, made again on each draw beyond)."""
        if frozen is None:
            return bg
        if i in frozen.backgrounds:
            return frozen.backgrounds[i]
        v = train_views[i]
        with torch.no_grad():
            image = render(evaluate(frozen.model, v.time), v.camera, backend=backend.name,
                           background=bg, tile_size=config.tile_size)["rgb"]
        kept = sum(b.numel() * b.element_size() for b in frozen.backgrounds.values())
        if kept + image.numel() * image.element_size() <= SET_RENDERS_KEPT_BYTES:
            frozen.backgrounds[i] = image
        return image

    if state.step == 0 and config.eval_every:
        run_eval()
    while state.step < config.steps:
        t_start = time.perf_counter()
        if frozen_at is not None and frozen is None and state.step >= frozen_at:
            frozen = _freeze_set(state)
        step = state.step + 1
        model = state.model
        if frozen is not None and set_model is None and config.mcmc.is_refine_step(step):
            step_config = _performers_mcmc(config, len(frozen.model), len(model))
        i = draw_view(len(train_views), weights, state.generator)
        view = train_views[i]
        target = view.load().to(device)
        lrs = learning_rates(config, step, scene_scale, time_scale, model)
        for p in (*model.params.values(), *grid_params.values()):
            p.grad = None
        row = cam_row[view.camera_id]
        loss, parts = step_loss(model, view.time, view.camera, target, view.load_valid(),
                                grid_params["exposure"], row, grid_params["black"], config,
                                backend=backend.name, background=background(i),
                                matte=view.load_matte() if config.mask_alpha_weight
                                and step % config.mask_alpha_every == 0 else None)
        if not torch.isfinite(loss.detach()):
            raise FloatingPointError(
                f"step {step}: loss is {float(loss.detach())} on view {view.camera_id}@{view.frame} "
                f"({len(model)} Gaussians; non-finite parameters: {_non_finite(model)}; target "
                f"{'finite' if bool(torch.isfinite(target).all()) else 'has NaN/Inf pixels'})")
        loss.backward()
        relocated, grown = optimiser_step(model, state.adam, grid_params, grid_lrs, state.grid_adam, lrs,
                                          step_config, step, state.generator, scene_scale=scene_scale)
        state.step = step
        state.wall_s += time.perf_counter() - t_start

        if progress is not None:
            progress(step, config.steps, {"loss": float(loss.detach()), **parts,
                                          "num_gaussians": len(model) + (len(frozen.model) if frozen else 0),
                                          "relocated": relocated,
                                          "grown": grown, "wall_s": state.wall_s})
        if config.eval_every and step % config.eval_every == 0:
            run_eval()
        if checkpoint is not None and (
                (config.checkpoint_every and step % config.checkpoint_every == 0)
                or step == config.steps):
            checkpoint(_serialise(_whole(state, frozen), config, extra), step)
    run_eval()
    final = _whole(state, frozen).model.detached()
    grids = ExposureGrids(state.grids.camera_ids, state.grids.exposure.detach().clone(),
                          state.grids.black.detach().clone())
    return TrainResult(final, grids, list(state.history), state.step, state.wall_s, backend=backend)

