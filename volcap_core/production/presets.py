"""Named quality presets: the one table that ``volcap reconstruct --preset`` and a production
spec's ``quality:`` both read.

A :class:`QualityPreset` holds every knob a quality level sets:

- the training schedule (steps, exposure grid, evaluation, checkpoints, MCMC refinement), the
  training resolution and SH degree: :meth:`QualityPreset.train_config` turns them into the
  :class:`~volcap_core.splat.TrainConfig` of a segment;
- the segment budget (Gaussians per frame, the per-segment cap, the longest segment, the overlap):
  :meth:`QualityPreset.plan_segments` is the one segmenter
  (:func:`volcap_core.production.segments.plan_segments` with the preset's budget), so
  ``volcap reconstruct`` and a production split the same frames of the same capture alike;
- what only a production uses: the dense-point matching resolution and the Face Rig / enhancer
  sizes.

A spec overrides single fields (``quality: {preset: production, train_steps: 20000}``:
:meth:`QualityPreset.with_overrides`); ``volcap reconstruct --steps N`` stretches the preset's
schedule to ``N`` steps instead (:meth:`QualityPreset.with_steps`). Table and rationale:
``docs/production-spec.md`` ("Quality presets").
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from volcap_core.enhance.model import EnhancerConfig
from volcap_core.enhance.production import EnhanceSettings
from volcap_core.enhance.training import EnhancerTrainConfig
from volcap_core.production.segments import DEFAULT_OVERLAP, GIB, SegmentBudget, SegmentPlan, plan_segments
from volcap_core.splat.mcmc import MCMCConfig
from volcap_core.splat.model import Poly4DGSConfig
from volcap_core.splat.train import TrainConfig

__all__ = ["DEGREES", "ENHANCER_TRAINING_FIELDS", "ENHANCING_FIELDS", "PRESETS", "TRAINING_FIELDS",
           "QualityPreset", "named_preset"]

#: Model degrees by name (paper Table 1 baselines).
DEGREES = {"poly4dgs": Poly4DGSConfig.paper, "rotor4d": Poly4DGSConfig.rotor4d, "static": Poly4DGSConfig.static}

#: The preset fields that shape a segment's TrainConfig (a train-segment step carries them).
TRAINING_FIELDS = ("train_steps", "grid_size", "eval_every", "eval_max_views", "checkpoint_every",
                   "refine_start", "refine_every", "refine_stop", "train_scale", "sh_degree", "held_out_tracking",
                   "init_static_share", "init_zoom_stride_px", "init_finest_level", "init_moving_scale_px",
                   "init_scene_flow", "init_lifespan_frames",
                   "performer_view_weight", "moving_weight", "opacity_reg", "mask_alpha_weight", "mask_alpha_every",
                   "set_frozen_from")

#: The preset fields that shape the enhancer's training (a train-enhancer step carries them).
ENHANCER_TRAINING_FIELDS = ("enhancer_architecture", "enhancer_weights", "enhancer_steps", "enhancer_finetune",
                            "enhancer_frozen_dtype", "enhancer_lora_rank", "enhancer_lr", "enhancer_batch", "enhancer_crop",
                            "enhancer_vae_steps", "enhancer_checkpoint_every", "enhancer_warmup_steps",
                            "enhancer_lr_decay", "enhancer_vae_lr", "enhancer_vae_crop", "enhancer_vae_stages")
#: The preset fields that shape a shot's enhancement (an enhance-shot step carries them).
ENHANCING_FIELDS = ("enhancer_sampling_steps", "enhancer_strength", "enhancer_tile", "enhancer_vae_tiling",
                    "enhancer_flow", "enhancer_flow_weights")

_TRAIN = TrainConfig.model_fields
_MCMC = MCMCConfig.model_fields


class QualityPreset(BaseModel):
    """Every knob a quality level sets (module doc). Schedule fields left out take
    :class:`~volcap_core.splat.TrainConfig`'s and :class:`~volcap_core.splat.mcmc.MCMCConfig`'s
    defaults (the paper's schedule for 30k steps)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    # -- training
    train_steps: int = Field(gt=0, description="Poly4DGS optimisation steps per segment")
    grid_size: int = Field(_TRAIN["grid_size"].default, ge=1, description="exposure/black grid cells per axis")
    eval_every: int = Field(_TRAIN["eval_every"].default, ge=0, description="held-out evaluation every N steps "
                            "(0: only at the end)")
    eval_max_views: int = Field(_TRAIN["eval_max_views"].default, gt=0)
    checkpoint_every: int = Field(_TRAIN["checkpoint_every"].default, ge=0)
    refine_start: int = Field(_MCMC["refine_start"].default, ge=0, description="first MCMC refinement step")
    refine_every: int = Field(_MCMC["refine_every"].default, gt=0)
    refine_stop: int = Field(_MCMC["refine_stop"].default, ge=0, description="no refinement from this step on")
    train_scale: float = Field(1.0, gt=0, le=1, description="training resolution / capture")
    sh_degree: int = Field(3, ge=0, le=3)
    # -- where the Gaussians go (issue 28: the performers at the tracking cameras' resolution;
    #    docs/poly4dgs.md "Performers at the tracking cameras' resolution")
    init_static_share: float = Field(_TRAIN["init_static_share"].default, ge=0, le=1,
                                     description="share of the initial budget for the static pool")
    init_zoom_stride_px: int | None = Field(_TRAIN["init_zoom_stride_px"].default, gt=0,
                                            description="the zoom cameras' points every N pixels (None: off)")
    init_finest_level: int = Field(_TRAIN["init_finest_level"].default, ge=-4, le=0,
                                   description="moving points thinned up to 2^-N times finer where a camera resolves finer")
    init_moving_scale_px: float | None = Field(_TRAIN["init_moving_scale_px"].default, gt=0,
                                               description="moving Gaussians' initial scale cap, in finest footprints")
    init_scene_flow: bool = Field(_TRAIN["init_scene_flow"].default,
                                  description="moving Gaussians start with their points' velocity (optical flow, triangulated)")
    init_lifespan_frames: float = Field(_TRAIN["init_lifespan_frames"].default, gt=0,
                                        description="moving Gaussians' initial temporal σ, in frame intervals")
    performer_view_weight: float = Field(_TRAIN["performer_view_weight"].default, ge=0,
                                         description="camera schedule weight of the views' performer coverage")
    moving_weight: float = Field(_MCMC["moving_weight"].default, gt=0,
                                 description="MCMC relocation/growth weight of moving Gaussians")
    opacity_reg: float = Field(_MCMC["opacity_reg"].default, ge=0,
                               description="MCMC's opacity regulariser weight (3DGS-MCMC's 0.01)")
    # -- the performers' alpha (what a shot composites) against the capture's own masks, where it has
    #    them (docs/poly4dgs.md "Performer masks as an alpha loss"); a capture without masks trains as before
    mask_alpha_weight: float = Field(_TRAIN["mask_alpha_weight"].default, ge=0,
                                     description="L1 weight of the performers' alpha against the capture's masks (0: off)")
    mask_alpha_every: int = Field(_TRAIN["mask_alpha_every"].default, ge=1,
                                  description="the alpha loss on every N-th training step only")
    # -- the set frozen for the last part of the run, its render the performers' background
    #    (docs/poly4dgs.md "The set frozen"); None: the set trains to the end
    set_frozen_from: float | None = Field(_TRAIN["set_frozen_from"].default, gt=0, lt=1,
                                          description="fraction of the steps after which only the performers train")
    # -- segments
    held_out_tracking: int = Field(0, ge=0, description="tracking cameras held out of every segment for "
                                   "scoring, beside one static camera (reconstruction.default_held_out); the "
                                   "demo holds one out (issue 28 scores a held-out zoom view), a production none "
                                   "(every close-up camera trains)")
    gaussians_per_frame: int = Field(gt=0, description="Gaussians a segment needs per frame")
    max_gaussians_per_segment: int | None = Field(None, gt=0)
    gpu_memory_gb: float | None = Field(None, gt=0, description="GPU a segment must fit (GiB)")
    max_segment_frames: int | None = Field(None, gt=0, description="cap on segment length")
    overlap: int = Field(DEFAULT_OVERLAP, ge=0, description="frames shared by neighbours")
    # -- productions only
    dense_scale: float = Field(1.0, gt=0, le=1, description="dense-point matching resolution / capture")
    face_subsequences: int = Field(60, gt=0, description="Face Rig sub-sequences per actor")
    face_subsequence_frames: int = Field(8, gt=0)
    face_camera_paths: int = Field(60, gt=0, description="camera paths per sub-sequence")
    face_hq_gaussians_per_frame: int = Field(1_000_000, gt=0)
    face_lq_gaussians: tuple[int, int] = (50_000, 200_000)
    pair_resolution: int = Field(4096, gt=0, description="square LQ/HQ pair renders (px)")
    pair_window: Literal["performer", "head"] = Field(
        "performer", description="interim pairs' crop: performer (the largest square on the performer, resized to "
                                 "pair_resolution) or head (a pair_resolution square over the head at the capture's "
                                 "own pixels, the enhancer bench's window)")
    pair_method: Literal["splat", "interim"] = Field(
        "splat", description="splat: the paper's pairs, HQ and LQ Poly4DGS models of Face Rig sub-sequences "
                             "rendered along camera paths (the facerig_pairs flow); interim: degraded Face Rig "
                             "frames (docs/enhancer.md)")
    enhancer_steps: int = Field(20_000, gt=0, description="enhancer training steps")
    # -- the detail enhancer (docs/enhancer.md)
    enhancer_architecture: Literal["tiny", "small", "flux-dev"] = Field(
        "flux-dev", description="tiny: the CPU smoke-test model, random weights; small: a CPU model wide enough "
                                "to learn (docs/benchmarks.md 'Detail enhancer'), random weights; flux-dev: "
                                "FLUX.1-dev from enhancer_weights")
    enhancer_weights: str | None = Field(None, description="local FLUX.1 directory (transformer/, vae/, text "
                                         "encoders optional); relative paths are relative to the spec file")
    enhancer_finetune: Literal["lora", "full"] = "lora"
    enhancer_frozen_dtype: Literal["float32", "bfloat16"] = Field(
        "bfloat16", description="dtype of the weights training does not change (FLUX.1's transformer: 48 GB in float32)")
    enhancer_lora_rank: int = Field(16, ge=1)
    enhancer_lr: float = Field(1e-4, gt=0)
    enhancer_batch: int = Field(1, ge=1)
    enhancer_crop: int = Field(1024, ge=16, description="training crop side (px)")
    enhancer_vae_steps: int = Field(0, ge=0, description="VAE pre-training steps (the tiny model's VAE is random)")
    enhancer_checkpoint_every: int = Field(500, ge=0)
    enhancer_warmup_steps: int = Field(0, ge=0, description="linear warm-up of the transformer's rate (steps)")
    enhancer_lr_decay: tuple[tuple[int, float], ...] = Field(
        (), description="(step, factor) pairs: from that step on the rate is enhancer_lr times factor")
    enhancer_vae_lr: float = Field(1e-3, gt=0, description="VAE pre-training rate")
    enhancer_vae_crop: int | None = Field(None, ge=8, description="VAE pre-training crop (px); null: enhancer_crop")
    enhancer_vae_stages: tuple[tuple[int, float], ...] = Field(
        (), description="(steps, rate) stages continuing the VAE pre-training at lower rates")
    enhancer_sampling_steps: int = Field(28, ge=1, description="Euler steps per frame")
    enhancer_strength: float = Field(1.0, gt=0, le=1, description="fraction of the sampler's noise levels run, starting from the noised LQ (1: from pure noise, as Flux samples)")
    enhancer_tile: int | None = Field(1024, ge=16, description="latent tile (px, multiple of 16); null: whole frame")
    enhancer_vae_tiling: bool = Field(True, description="the VAE's own tiling for large frames")
    enhancer_flow: Literal["rendered", "dis", "zero", "raft", "raft-small"] = Field(
        "rendered", description="flow between consecutive LQ frames: rendered (the shot renderer's exact flow, "
                                "DIS where a frame has none), dis, zero, raft / raft-small (torchvision's RAFT "
                                "from enhancer_flow_weights)")
    enhancer_flow_weights: str | None = Field(None, description="local RAFT weights file (torchvision raft_large / "
                                              "raft_small state dict) for enhancer_flow raft / raft-small; relative "
                                              "paths are relative to the spec file")

    @model_validator(mode="after")
    def _cap(self) -> "QualityPreset":
        if self.max_gaussians_per_segment is None and self.gpu_memory_gb is None:
            raise ValueError("set max_gaussians_per_segment or gpu_memory_gb (or both)")
        if self.enhancer_tile is not None and self.enhancer_tile % 16:
            raise ValueError(f"enhancer_tile must be a multiple of 16 px, got {self.enhancer_tile}")
        raft = self.enhancer_flow in ("raft", "raft-small")
        if raft and self.enhancer_flow_weights is None:
            raise ValueError(f"enhancer_flow {self.enhancer_flow} needs enhancer_flow_weights: a local RAFT weights "
                             "file (docs/enhancer.md)")
        if self.enhancer_flow_weights is not None and not raft:
            raise ValueError(f"enhancer_flow_weights is set but enhancer_flow is {self.enhancer_flow}: RAFT weights "
                             "are for raft / raft-small")
        if self.enhancer_crop % 16:
            raise ValueError(f"enhancer_crop must be a multiple of 16 px, got {self.enhancer_crop}")
        lo, hi = self.face_lq_gaussians
        if not 0 < lo <= hi:
            raise ValueError(f"face_lq_gaussians must be 0 < low <= high, got {[lo, hi]}")
        try:   # the enhancer's schedules are checked with the preset, not when its task starts
            self.enhancer_train_config()
        except ValidationError as e:
            raise ValueError("; ".join(str(err.get("ctx", {}).get("error", err["msg"])) for err in e.errors())) from None
        return self

    def with_overrides(self, **fields: Any) -> "QualityPreset":
        """This preset with single fields replaced, validated (a spec's ``quality:`` overrides)."""
        return QualityPreset.model_validate({**self.model_dump(), **fields})

    def with_steps(self, steps: int) -> "QualityPreset":
        """This preset trained for ``steps`` steps instead, its schedule stretched to match:
        evaluation, checkpoints and MCMC refinement at the same fractions of the run (an
        evaluation interval of 0, "only at the end", stays 0)."""
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        stretch = steps / self.train_steps

        def scaled(value: int) -> int:
            return max(1, round(value * stretch))

        return self.with_overrides(
            train_steps=steps,
            eval_every=scaled(self.eval_every) if self.eval_every else 0,
            checkpoint_every=scaled(self.checkpoint_every) if self.checkpoint_every else 0,
            refine_start=scaled(self.refine_start), refine_every=scaled(self.refine_every),
            refine_stop=scaled(self.refine_stop))

    def training(self) -> dict[str, Any]:
        """The fields of :data:`TRAINING_FIELDS` by name."""
        return {name: getattr(self, name) for name in TRAINING_FIELDS}

    def enhancer_training(self) -> dict[str, Any]:
        """The fields of :data:`ENHANCER_TRAINING_FIELDS` by name."""
        return {name: getattr(self, name) for name in ENHANCER_TRAINING_FIELDS}

    def enhancing(self) -> dict[str, Any]:
        """The fields of :data:`ENHANCING_FIELDS` by name."""
        return {name: getattr(self, name) for name in ENHANCING_FIELDS}

    def enhancer_config(self) -> EnhancerConfig:
        """The :class:`~volcap_core.enhance.model.EnhancerConfig` of the architecture (the tiny
        model's training crop is the preset's)."""
        if self.enhancer_architecture in ("tiny", "small"):
            cpu = EnhancerConfig.tiny() if self.enhancer_architecture == "tiny" else EnhancerConfig.small()
            return cpu.model_copy(update={"train_crop": self.enhancer_crop})
        return EnhancerConfig.flux_dev()

    def enhancer_train_config(self) -> EnhancerTrainConfig:
        """The :class:`~volcap_core.enhance.training.EnhancerTrainConfig` of the enhancer's training."""
        return EnhancerTrainConfig(steps=self.enhancer_steps, lr=self.enhancer_lr, batch=self.enhancer_batch,
                                   crop=self.enhancer_crop, finetune=self.enhancer_finetune,
                                   lora_rank=self.enhancer_lora_rank, vae_steps=self.enhancer_vae_steps,
                                   checkpoint_every=self.enhancer_checkpoint_every,
                                   frozen_dtype=self.enhancer_frozen_dtype, warmup_steps=self.enhancer_warmup_steps,
                                   lr_decay=self.enhancer_lr_decay, vae_lr=self.enhancer_vae_lr,
                                   vae_crop=self.enhancer_vae_crop, vae_stages=self.enhancer_vae_stages)

    def enhance_settings(self) -> EnhanceSettings:
        """The :class:`~volcap_core.enhance.production.EnhanceSettings` of a shot's enhancement."""
        return EnhanceSettings(steps=self.enhancer_sampling_steps, strength=self.enhancer_strength,
                               tile=self.enhancer_tile, vae_tiling=self.enhancer_vae_tiling, flow=self.enhancer_flow)

    def train_config(self, *, degrees: str = "poly4dgs", held_out: Sequence[str] = (),
                     max_gaussians: int | None = None, **overrides: Any) -> TrainConfig:
        """The :class:`~volcap_core.splat.TrainConfig` of a segment trained at this quality.

        ``degrees``: a key of :data:`DEGREES` (at the preset's SH degree). ``held_out``: cameras
        never trained on. ``max_gaussians``: the Gaussian budget (MCMC's cap, and the initial
        points are thinned to it); None keeps TrainConfig's. ``overrides``: TrainConfig fields set
        as given (a partial ``mcmc`` dict merges into the preset's refinement schedule).
        """
        if degrees not in DEGREES:
            raise ValueError(f"unknown model degrees {degrees!r}: choose one of {', '.join(DEGREES)}")
        mcmc: dict[str, Any] = {"refine_start": self.refine_start, "refine_every": self.refine_every,
                                "refine_stop": self.refine_stop, "moving_weight": self.moving_weight,
                                "opacity_reg": self.opacity_reg}
        if isinstance(overrides.get("mcmc"), dict):
            mcmc.update(overrides.pop("mcmc"))
        values: dict[str, Any] = {
            "steps": self.train_steps, "grid_size": self.grid_size, "eval_every": self.eval_every,
            "eval_max_views": self.eval_max_views, "checkpoint_every": self.checkpoint_every,
            "image_scale": self.train_scale, "model": DEGREES[degrees](sh_degree=self.sh_degree),
            "held_out_cameras": list(held_out), "init_static_share": self.init_static_share,
            "init_zoom_stride_px": self.init_zoom_stride_px, "init_finest_level": self.init_finest_level,
            "init_moving_scale_px": self.init_moving_scale_px, "performer_view_weight": self.performer_view_weight,
            "init_scene_flow": self.init_scene_flow, "init_lifespan_frames": self.init_lifespan_frames,
            "mask_alpha_weight": self.mask_alpha_weight, "mask_alpha_every": self.mask_alpha_every,
            "set_frozen_from": self.set_frozen_from}
        if max_gaussians is not None:
            mcmc["cap_max"] = max_gaussians
            values["init_max_points"] = max_gaussians
        values["mcmc"] = MCMCConfig(**{**MCMCConfig().model_dump(), **mcmc})
        values.update(overrides)
        return TrainConfig(**values)

    def segment_budget(self, width: int, height: int) -> SegmentBudget:
        """The segment budget for a capture whose largest image is ``width × height`` pixels (the
        memory estimate is at the training resolution, ``train_scale`` of that, for the paper's
        model at the preset's SH degree)."""
        return SegmentBudget(
            gaussians_per_frame=self.gaussians_per_frame, max_gaussians=self.max_gaussians_per_segment,
            gpu_memory_bytes=int(self.gpu_memory_gb * GIB) if self.gpu_memory_gb else None,
            width=max(1, round(width * self.train_scale)), height=max(1, round(height * self.train_scale)),
            config=Poly4DGSConfig.paper(sh_degree=self.sh_degree))

    def plan_segments(self, frames: tuple[int, int], width: int, height: int) -> SegmentPlan:
        """Take indices ``[frames[0], frames[1])`` in segments of this preset's budget, at most
        ``max_segment_frames`` long, neighbours sharing ``overlap`` frames
        (:func:`~volcap_core.production.segments.plan_segments`)."""
        return plan_segments(frames, self.segment_budget(width, height), overlap=self.overlap,
                             max_length=self.max_segment_frames)


#: Face Rig and enhancer sizes of the presets that run on a CPU: the tiny enhancer (random weights,
#: its VAE pre-trained first), full fine-tuning on 64-px crops of 4 sequences of 128-px pairs, 4
#: sampling steps over whole frames, started from the noised LQ (strength 0.4: a CPU-sized model
#: enhances the LQ rather than drawing a face from noise), on interim pairs (degraded Face Rig
#: frames: the demo's Face Rig capture cannot be calibrated, docs/enhancer.md). Why and what it costs:
#: docs/benchmarks.md "Detail enhancer", docs/enhancer.md "Cost on a CPU"
_CPU_FACE = dict(face_subsequences=2, face_subsequence_frames=4, face_camera_paths=2,
                 face_hq_gaussians_per_frame=2_000, face_lq_gaussians=(200, 500), pair_resolution=128,
                 pair_method="interim",
                 enhancer_architecture="tiny", enhancer_steps=20, enhancer_finetune="full", enhancer_lr=1e-3,
                 enhancer_frozen_dtype="float32",
                 enhancer_crop=64, enhancer_vae_steps=30, enhancer_checkpoint_every=10,
                 enhancer_sampling_steps=4, enhancer_strength=0.4, enhancer_tile=None, enhancer_vae_tiling=False)

PRESETS: dict[str, QualityPreset] = {
    # CI and laptops: 20 steps at full resolution, tiny segments (the reconstruct tests' schedule;
    # production tests override train_scale/sh_degree for speed)
    "test": QualityPreset(train_steps=20, grid_size=4, eval_every=0, eval_max_views=2, checkpoint_every=10,
                          refine_start=5, refine_every=5, refine_stop=15,
                          gaussians_per_frame=500, max_gaussians_per_segment=8_000, max_segment_frames=8,
                          overlap=2, dense_scale=0.5, **_CPU_FACE),
    # the built-in demo on 2 CPU cores: the schedule and the Gaussian budget (10,000 a frame, one
    # 8-frame segment) that fit its time target; the measurements: docs/poly4dgs.md "The demo".
    # 1640 steps since the compiled CPU training step (projection, slice, colours, Adam, all cores for
    # the compositing): ~3.7 min of training on 2 quiet cores, issue 28's ~4 minutes; the 820-step
    # schedule doubled (820 steps before, 550 before the compiled compositor); 1340 since the initial
    # motion (below), that schedule stretched. Issue 28's route since 2026-11-28 (docs/poly4dgs.md, "The zoom
    # points' depth"): the zoom cameras' own points every 2 px at a photo-consistent depth, views
    # drawn by their performer coverage (1.5) and MCMC growing the moving Gaussians 4x as readily.
    # Where the capture has masks (the demo's: against its clean plates), the performers' alpha
    # trained toward them on every 4th step (docs/poly4dgs.md, "Performer masks as an alpha loss").
    # The set frozen halfway through 2030 steps (the same time) was measured on two seeds and left
    # off: the zoom cameras' faces +10 % detail, the held-out static performers -0.5 dB
    # (docs/poly4dgs.md, "The set frozen"). Since 2026-11-29 the moving Gaussians start with their
    # points' velocity (the training views' optical flow, triangulated) and live ~3 frames, so each
    # frame sees ~3 frames' Gaussians; a step then costs ~1.2x, so 1340 steps (the 1640-step
    # schedule's time): the close-up's face +0.8 dB, the zoom cameras' performers +0.9 dB and +19 %
    # detail (docs/poly4dgs.md, "The performers' initial motion"). Since 2026-11-29 (later) where a
    # camera resolves a moving point finer than the frame's 90th-percentile footprint, the point is
    # thinned on a grid up to 8x finer and its Gaussian starts at most 2 of that camera's pixels wide:
    # the zoom cameras' faces got ~1,260 Gaussians 2 px wide where they had ~660 at 6 px, and their
    # eyes, brows and hair drawn (docs/poly4dgs.md, "The faces' Gaussians at the zoom cameras' pixels").
    # Since 2026-11-29 (third) MCMC's opacity regulariser at 0.001 instead of 3DGS-MCMC's 0.01: a face's
    # small Gaussians, drawn on few steps, no longer kept translucent; the zoom cameras' detail 0.327 ->
    # 0.382 and the close-up's face +0.62 dB in the same training time ("What holds the eyes back")
    "demo": QualityPreset(train_steps=1340, grid_size=8, eval_every=268, eval_max_views=4, checkpoint_every=268,
                          refine_start=243, refine_every=243, refine_stop=1217,
                          gaussians_per_frame=10_000, max_gaussians_per_segment=80_000, overlap=2,
                          held_out_tracking=1, init_zoom_stride_px=2, performer_view_weight=1.5, moving_weight=4.0,
                          mask_alpha_weight=1.0, mask_alpha_every=4, init_scene_flow=True, init_lifespan_frames=3.0,
                          init_finest_level=-3, init_moving_scale_px=2.0, opacity_reg=0.001, **_CPU_FACE),
    # dailies: half resolution, short training, one 24 GB GPU per segment
    "preview": QualityPreset(train_steps=3_000, eval_every=500, checkpoint_every=500,
                             refine_start=300, refine_every=100, refine_stop=2_500,
                             train_scale=0.5, sh_degree=1,
                             gaussians_per_frame=20_000, gpu_memory_gb=24, max_segment_frames=48, overlap=2,
                             face_subsequences=12, face_camera_paths=12,
                             face_hq_gaussians_per_frame=250_000, face_lq_gaussians=(20_000, 50_000),
                             pair_resolution=1024, enhancer_steps=2_000, enhancer_crop=512,
                             enhancer_checkpoint_every=200),
    # final: the paper's settings and schedule, an 80 GB GPU per segment, at most 5 s (24 fps) per segment
    "production": QualityPreset(train_steps=30_000, gaussians_per_frame=100_000, gpu_memory_gb=80,
                                max_segment_frames=120, overlap=3),
}


def named_preset(name: str) -> QualityPreset:
    """The preset called ``name``; ``ValueError`` naming the known ones otherwise."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}: choose one of {', '.join(PRESETS)}")
    return PRESETS[name]
