"""Poly4DGS on a synthetic capture: held-out error against training time, and the paper's Table 1.

    python bench/bench_poly4dgs.py            # 160x90, 360 steps (~10 min, see "Time")
    python bench/bench_poly4dgs.py --quick    # smoke run (~50 s): tiny, numbers meaningless
    python bench/bench_poly4dgs.py --downsample 1 --steps 720 --json out.json \\
        --plot docs/img/poly4dgs_error_vs_time.png --sheet docs/img/poly4dgs_contact_sheet.jpg
                                              # the documented run (docs/benchmarks.md, ~30 min)

Scene: ``synthesize_capture(rig="demo_scene", seed=0, frames=N, write_depth=True)`` read back from
its files (:mod:`poly4dgs_data`): 12 cameras (8 static, 4 zoom/tracking with veiling glare), each
with its own gain, black offset and vignetting. Held out (never trained on, never used for the
initial points): two static cameras (S002, S005) and the tracking camera the demo preset holds
out (``QualityPreset.held_out_tracking`` through ``reconstruction.default_held_out``, the rule
the demo's flow uses: S010, the wider portrait zoom; S008, S009 and S011 frame the faces closer
and train), so the figures say how a zoom view the model never saw is drawn (issue 28).

Initial points, as production builds them (``docs/poly4dgs.md`` "Initialisation"): the training
cameras' ground-truth depth, back-projected per frame (``P`` points per frame), goes through
:func:`volcap_core.reconstruction.segment_points`, the reconstruction task's own function. Each
point is static (within 5 cm of the capture's lidar scan ``ground_truth/lidar.ply``, or
persistent over the segment) or moving, and the scan, coloured by the static training cameras at
the middle frame, is appended as one more static cloud. :func:`volcap_core.splat.train.init_model`
then thins the static pool (one Gaussian for the whole segment) and each frame's moving points on
voxel grids to ``init_budget`` = 70 % of MCMC's cap. The cap is ``N·P / 0.7`` (the library's
``init_cap_fraction`` rule), so every run starts from at most N·P Gaussians and growth (5 % per
refine step, 6 refine steps) acts.

Runs (one seed each, same step budget S):

=================  ==============================================================================
full               Poly4DGS, paper degrees (n_μ, n_q, n_s, n_o) = (2, 1, 0, 2), all components
rotor4d            degrees (1, 0, 0, 1): the sliced 4D-Rotor Gaussian, same training otherwise
per_frame          one static 3DGS (degrees 0) per frame, S / N steps each, on that frame's points
                   (static ones too) plus the coloured scan, cap P / 0.7 each
no_black           w/o black-level grids (training)
no_exposure        w/o exposure grids (training)
sparse             w/o dense points: 2 % of each frame's dense points (classification kept) and
                   *no scan* (the scan is dense points too); same cap as full, so MCMC may grow
linear_storage     SH colours stored as linear radiance (no sRGB decode before rasterization)
=================  ==============================================================================

Evaluation: the library's held-out protocol (:mod:`volcap_core.splat.scoring`, what the
``train-segment`` task reports), the same for every run and every snapshot. All held-out views
are rendered (3 cameras × N frames; per-frame GS renders each view with its frame's model) and
scored by :func:`~volcap_core.splat.scoring.score_views`: each held-out camera gets a gain and an
offset per channel in linear light, **fitted on the camera's other frames** (two folds by frame
parity), never on the view scored. Figures are on the display encoding (sRGB clamped to [0, 1]),
means over the views:

* ``PSNR``, ``SSIM``: with that cross-fitted transform;
* ``raw PSNR``: no transform at all;
* ``performers PSNR / SSIM``: over the pixels where the synthetic capture's ground-truth
  performer mask (``ground_truth/masks``, area-downsampled like the images) is >= 0.5, the SSIM
  map averaged there;
* **floors** on the same views by the same code: ``empty`` (renders the background, zeros; the
  fitted offsets can still draw each camera's mean colour; one per run, as it does not depend on
  the method) and ``initial`` (the method's untrained model, rebuilt from the same points, config
  and seed as training built it; it is also the step-0 point of every curve). A figure is worth
  what it stands above its floors;
* **region figures per camera role** of every run's end and of both its floors on the same
  pixels (:class:`Evaluation`): what ``score_segment`` reports as ``regions``, by its own function
  (:func:`volcap_core.splat.report.role_regions`) on its views: per view set (held out; the 12
  training views it scores) and role (static, tracking), PSNR, SSIM and detail (the output's
  gradient energy over the footage's, ``image_metrics.detail``) on the ``performers`` (mask >=
  0.5) and the ``face`` (the performers within the actors' heads of ``ground_truth/scene.json``,
  ``synth.ground_truth.face_region``). Held-out views after each model's cross-fitted
  gain/offset, training views after the trained model's learned grids (the floors, which learned
  none, after their cross-fitted gain/offset).

The full run is also scored by :func:`volcap_core.splat.report.score_segment`, as the task does
(its held-out figures and region figures must equal the bench's; a warning says when not): its
training views with their learned grids (the fit itself: a ceiling, not generalisation) and a
contact sheet (footage | render | error for the held-out cameras, the tracking one added to
``score_segment``'s two, and a static and a tracking training camera at the first, middle and
last frame), written to ``--sheet`` (default ``docs/img/poly4dgs_contact_sheet.jpg``; none with ``--quick``
unless given).

Snapshots come from ``train_segment``'s checkpoints; time on the x-axis is training time only
(``wall_s``: evaluation and checkpointing excluded), and the process CPU time over the same steps
(``cpu_s``), which other jobs on a shared machine inflate less (it still moved ~15 % between
identical runs on the 2-core development machine).

Default settings (``Settings.full``): 6 frames, images box-downsampled 2x to 160x90 (90x160
portrait), P = 5000 dense points per frame (at most 30 000 initial Gaussians, cap 42 858), 360
steps per run (per-frame: 60 per frame), 3DGS-MCMC relocation and growth 6 times per run
(``mcmc_for``), SH degree 3. Curves (the initial model + 4 snapshots) for ``--curves`` (default:
full, rotor4d, per_frame, linear_storage), the initial model and the end only for the rest. Also
printed: what each run's exposure and black-level grids learned against the synthetic cameras'
true gain and black offset.

Time, on the shared 2-core development machine: at these defaults, with S002 and S005 held out
only (load average 1.5-2), the full run alone took 87 s (71 s wall / 68 s CPU of training, the
rest scoring, the report and the sheet) and all seven runs should take about 8-10 min (an
estimate, not measured as a whole); the held-out tracking camera adds half again to every
evaluation. The documented run (``--downsample 1 --steps 720``, ``docs/benchmarks.md``) took
1883 s at load 2.0-6.6 with the tracking camera held out and the region figures; ``--quick``
about 50 s. Runs single-threaded (``torch.set_num_threads(1)``; see ``--threads``). Writes the PNG (two panels:
PSNR against wall-clock and against CPU seconds, the empty floor dotted; needs matplotlib, the
``bench`` extra, else skipped with a warning) and, with ``--json``, every number.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import platform
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load as st_load

sys.path.insert(0, str(Path(__file__).resolve().parent))

from poly4dgs_data import (  # noqa: E402
    BenchScene,
    InitPoints,
    load_scene,
    production_points,
    subsample_points,
)

from volcap_core import reconstruction  # noqa: E402
from volcap_core.capture import CaptureFolder  # noqa: E402
from volcap_core.contact_sheet import SheetRow, contact_sheet, write_sheet  # noqa: E402
from volcap_core.production.presets import named_preset  # noqa: E402
from volcap_core.splat.grids import ExposureGrids  # noqa: E402
from volcap_core.splat.mcmc import MCMCConfig  # noqa: E402
from volcap_core.splat.model import STATIC_LOG_LAMBDA, Poly4DGS, Poly4DGSConfig  # noqa: E402
from volcap_core.splat.report import role_regions, score_segment, sheet_views, spread_views  # noqa: E402
from volcap_core.splat.scoring import (  # noqa: E402
    ColourTransform,
    Scores,
    cross_fitted_transforms,
    score_views,
    summarise,
)
from volcap_core.splat.train import (  # noqa: E402
    LearningRates,
    PointsAtTime,
    SegmentData,
    TrainConfig,
    View,
    frame_interval,
    init_budget,
    init_model,
    render_views,
    train_segment,
)
from volcap_core.synth import synthesize_capture  # noqa: E402

HELD_OUT_STATIC = ["S002", "S005"]
#: the preset whose held-out tracking cameras the bench holds out too (issue 28: the demo's S010)
TRACKING_PRESET = "demo"
TRAINING_VIEWS = 12   # training views scored, as score_segment's default max_training_views
ROLES = ("static", "tracking")
REGIONS = ("performers", "face")
METHODS = ["full", "rotor4d", "per_frame", "no_black", "no_exposure", "sparse", "linear_storage"]
CURVE_METHODS = ("full", "rotor4d", "per_frame", "linear_storage")
LABELS = {
    "full": "Full (Poly4DGS, degrees 2,1,0,2)",
    "rotor4d": "4D-Rotor degrees (1,0,0,1)",
    "per_frame": "per-frame GS (static 3DGS per frame)",
    "no_black": "w/o black level",
    "no_exposure": "w/o exposure opt.",
    "sparse": "w/o dense points (2% of the points, no scan)",
    "linear_storage": "linear colour storage",
}
PAPER = {  # Table 1 of the paper (PSNR, SSIM, LPIPS); linear storage: "about 5 dB" below
    "full": (27.29, 0.9752, 0.0160), "no_black": (24.11, 0.9576, 0.0200),
    "no_exposure": (25.50, 0.9718, 0.0161), "sparse": (25.31, 0.9576, 0.0288),
    "per_frame": (26.11, 0.9697, 0.0204), "rotor4d": (27.08, 0.9730, 0.0171),
}
DEFAULT_PLOT = Path("docs/img/poly4dgs_error_vs_time.png")
DEFAULT_SHEET = Path("docs/img/poly4dgs_contact_sheet.jpg")
SHEET_WIDTH = 1000


# ------------------------------------------------------------------------------------ settings

@dataclass(frozen=True)
class Settings:
    frames: int
    downsample: int
    points_per_frame: int          # dense points per frame; N·P initial Gaussians
    steps: int
    snapshots: int                 # evaluation points along the curves (plus step 0)
    sparse_fraction: float = 0.02
    sh_degree: int = 3
    seed: int = 0
    lr_exposure: float | None = None   # None: the library's LearningRates default
    lr_black: float | None = None

    @classmethod
    def full(cls) -> "Settings":
        return cls(frames=6, downsample=2, points_per_frame=5000, steps=360, snapshots=4)

    @classmethod
    def quick(cls) -> "Settings":
        return cls(frames=2, downsample=4, points_per_frame=1500, steps=40, snapshots=2,
                   sh_degree=1)


def cap_for(initial: int) -> int:
    """MCMC's cap for ``initial`` starting Gaussians under the library's rule
    (``init_budget`` = ``init_cap_fraction`` × cap, 0.7 by default): room for growth."""
    fraction = TrainConfig.model_fields["init_cap_fraction"].default
    cap = math.ceil(initial / fraction)
    while int(fraction * cap) < initial:   # float rounding: never start below ``initial``
        cap += 1
    return cap


def mcmc_for(steps: int, cap: int) -> MCMCConfig:
    """3DGS-MCMC scaled to a short run: relocation (and 5 % growth up to ``cap``) 6 times."""
    every = max(2, steps // 8)
    return MCMCConfig(refine_start=2 * every, refine_every=every, refine_stop=steps, cap_max=cap)


# ---------------------------------------------------------------------------------- evaluation

FIGURES = ("psnr", "ssim", "psnr_raw", "ssim_raw", "psnr_performers", "ssim_performers")

ModelOrFrames = Poly4DGS | dict[float, Poly4DGS] | None


def held_out_cameras(capture_dir: Path) -> list[str]:
    """The bench's held-out cameras: the static S002 and S005 (Table 1's since the first run),
    then the tracking cameras :data:`TRACKING_PRESET` holds out, picked by the rule the demo's
    flow uses (``reconstruction.default_held_out``, ``QualityPreset.held_out_tracking``): S010
    on the demo rig, the wider portrait zoom; S008, S009 and S011 frame the faces closer and
    train."""
    from types import SimpleNamespace

    folder = CaptureFolder.open(capture_dir)
    # default_held_out reads a capture's camera ids and rig: the folder's, before any ingest
    capture = SimpleNamespace(rig=folder.rig, cameras=[SimpleNamespace(id=c) for c in folder.camera_ids])
    tracking = reconstruction.default_held_out(
        capture, n=0, tracking=named_preset(TRACKING_PRESET).held_out_tracking)
    return HELD_OUT_STATIC + [c for c in tracking if c not in HELD_OUT_STATIC]


def renders_of(model: ModelOrFrames, views: list[View], cfg: TrainConfig) -> list[torch.Tensor]:
    """Linear renders of ``views``: a model, ``None`` (the empty model) or ``{time: model}``
    (per-frame GS: every view rendered by its frame's model)."""
    if isinstance(model, dict):
        return [render_views(model[v.time], [v], cfg)[0] for v in views]
    return render_views(model, views, cfg)


class Evaluation:
    """The views every run is scored on and the figures taken on them, by the library's code.

    * Held-out views (every frame of the held-out cameras): the held-out protocol
      (:mod:`volcap_core.splat.scoring`: renders, each camera's gain/offset cross-fitted on its
      other frames, :func:`score_views`), what ``score_segment`` reports as ``held_out``.
    * Region figures per camera role (:func:`volcap_core.splat.report.role_regions`, the function
      ``score_segment`` computes its ``regions`` with): on the held-out views and on
      ``score_segment``'s training views (:func:`spread_views`, 12), for a trained model and its
      floors (its untrained model and the empty one) on the same pixels. Held out: each model
      after its own cross-fitted gain/offset; training: the trained model after its learned
      grids, the floors after their cross-fitted gain/offset; faces from the synthetic ground
      truth (:meth:`BenchScene.head_region`).
    """

    def __init__(self, scene: BenchScene, cfg: TrainConfig):
        held = set(scene.held_out)
        self.scene = scene
        self.held = [v for v in scene.data.views if v.camera_id in held]
        self.training = spread_views([v for v in scene.data.views if v.camera_id not in held],
                                     TRAINING_VIEWS)
        self.targets = {"held_out": [v.load()[..., :3] for v in self.held],
                        "training": [v.load()[..., :3] for v in self.training]}
        empty_scores, self.empty_held = self.held_out(None, cfg)
        self.empty = figures(empty_scores)
        self.empty_training = self.fitted(None, "training", cfg)[1]

    def fitted(self, model: ModelOrFrames, which: str, cfg: TrainConfig
               ) -> tuple[list[torch.Tensor], list[torch.Tensor], list[ColourTransform]]:
        """``model``'s renders of a view set (``"held_out"``, ``"training"``), the same through
        each view's cross-fitted gain/offset, and those transforms."""
        views = self.held if which == "held_out" else self.training
        renders = renders_of(model, views, cfg)
        tfs = cross_fitted_transforms(renders, self.targets[which], [v.camera_id for v in views],
                                      [v.frame for v in views], [v.load_valid() for v in views])
        return renders, [t.apply(r) for t, r in zip(tfs, renders)], tfs

    def held_out(self, model: ModelOrFrames, cfg: TrainConfig) -> tuple[Scores, list[torch.Tensor]]:
        """The held-out protocol's figures of ``model`` and its outputs (after the transforms)."""
        renders, outputs, tfs = self.fitted(model, "held_out", cfg)
        v = self.held
        scores = score_views(renders, self.targets["held_out"], [x.camera_id for x in v],
                             [x.frame for x in v], [x.load_mask() for x in v], transforms=tfs,
                             valid=[x.load_valid() for x in v])
        return summarise(scores), outputs

    def trained_training(self, model: ModelOrFrames, grids: ExposureGrids | dict[float, ExposureGrids],
                         cfg: TrainConfig) -> list[torch.Tensor]:
        """The trained model's outputs on the training views through its learned grids (per-frame
        GS: each frame's model through that frame's grids)."""
        renders = renders_of(model, self.training, cfg)
        return [(grids[v.time] if isinstance(grids, dict) else grids).apply(r, v.camera_id)
                for r, v in zip(renders, self.training)]

    def regions(self, trained: dict[str, list[torch.Tensor]], initial: ModelOrFrames,
                initial_held: list[torch.Tensor], cfg: TrainConfig) -> dict:
        """``score_segment``'s ``regions``: view set -> role -> ``cameras`` and model (trained,
        initial, empty) -> region -> ``{psnr, ssim, detail, views}``. ``trained``: the trained
        model's outputs per view set; ``initial_held``: the untrained model's held-out outputs."""
        outputs = {"held_out": {"trained": trained["held_out"], "initial": initial_held,
                                "empty": self.empty_held},
                   "training": {"trained": trained["training"],
                                "initial": self.fitted(initial, "training", cfg)[1],
                                "empty": self.empty_training}}
        return {which: role_regions(self.held if which == "held_out" else self.training,
                                    self.targets[which], outputs[which], self.scene.roles,
                                    self.scene.head_region)
                for which in ("held_out", "training")}


def figures(sc: Scores) -> dict:
    return {k: getattr(sc, k) for k in FIGURES}


def fmt(x: float | None, digits: int = 2) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def initial_model(points: list[PointsAtTime], cfg: TrainConfig, data: SegmentData,
                  seed: int) -> Poly4DGS:
    """The model ``train_segment(data, points, cfg, seed=seed)`` starts from, rebuilt the way it
    (and ``score_segment``) builds it."""
    return init_model(points, cfg, frame_interval_s=frame_interval(data.times),
                      generator=torch.Generator().manual_seed(seed))


def static_count(model: Poly4DGS) -> int:
    """Gaussians that live for the whole segment (0 for a static config: no lifespan)."""
    lam = model.params.get("log_lambdas")
    return 0 if lam is None else int((lam.detach()[:, 0] <= STATIC_LOG_LAMBDA + 10.0).sum())


# ------------------------------------------------------------------------------------ training

@dataclass
class Snapshot:
    step: int
    wall_s: float
    cpu_s: float
    model: Poly4DGS


@dataclass
class RunLog:
    snapshots: list[Snapshot] = field(default_factory=list)
    cpu_excluded: float = 0.0
    cpu_at_step: float = 0.0
    cpu_start: float = 0.0


def _model_from_checkpoint(blob: bytes) -> tuple[Poly4DGS, dict]:
    n = int.from_bytes(blob[:8], "little")
    meta = json.loads(blob[8:8 + n])["__metadata__"]
    cfg = Poly4DGSConfig.model_validate_json(meta["model_config"])
    t = st_load(blob)
    params = {k[6:]: v.clone() for k, v in t.items() if k.startswith("model/")}
    return Poly4DGS(cfg, params), json.loads(meta["state"])


def train_with_snapshots(data: SegmentData, points: list[PointsAtTime], cfg: TrainConfig,
                         *, seed: int) -> tuple[RunLog, Poly4DGS, ExposureGrids]:
    """``train_segment`` with checkpoints every ``cfg.checkpoint_every`` steps (and after the last
    step) turned into model snapshots; CPU time of the steps is tracked beside the trainer's wall
    time (the CPU spent in checkpointing is excluded, as the trainer excludes its wall time)."""
    log = RunLog()

    def progress(step, total, info):
        log.cpu_at_step = time.process_time()

    def checkpoint(blob: bytes, step: int):
        model, state = _model_from_checkpoint(blob)
        train_cpu = log.cpu_at_step - log.cpu_start - log.cpu_excluded
        log.snapshots.append(Snapshot(step, float(state["wall_s"]), train_cpu, model))
        log.cpu_excluded += time.process_time() - log.cpu_at_step

    log.cpu_start = time.process_time()
    result = train_segment(data, points, cfg, checkpoint=checkpoint, progress=progress, seed=seed,
                           device="cpu")
    return log, result.model, result.grids


def base_config(s: Settings, *, model: Poly4DGSConfig, steps: int, cap: int,
                checkpoint_every: int, **kw) -> TrainConfig:
    """Training config of a run: the library's defaults (initialisation included) but for the
    model, the step count, the MCMC schedule and cap, and the CPU rasterizer. Held-out cameras
    are not in the training data (``held_out_cameras=[]``: the trainer evaluates nothing)."""
    lr = {k: v for k, v in (("exposure", s.lr_exposure), ("black", s.lr_black)) if v is not None}
    return TrainConfig(model=model, steps=steps, mcmc=mcmc_for(steps, cap), held_out_cameras=[],
                       eval_every=0, checkpoint_every=checkpoint_every, backend="torch",
                       lr=LearningRates(**lr), **kw)


@dataclass
class MethodResult:
    name: str
    curve: list[dict]            # step, wall_s, cpu_s + FIGURES; step 0 = the initial model
    with_curve: bool
    gaussians: int
    init_gaussians: int
    init_static: int             # of init_gaussians, living the whole segment
    cap: int
    steps: int
    grids: dict[str, dict] = field(default_factory=dict)   # camera -> learned mean E, B
    training: dict | None = None  # full: training views with their grids (score_segment)
    #: score_segment's ``regions`` of the end: view set -> role -> cameras, model -> region -> figures
    regions: dict = field(default_factory=dict)

    @property
    def final(self) -> dict:
        return self.curve[-1]

    @property
    def initial(self) -> dict:
        return self.curve[0]


def _point(step: int, wall: float, cpu: float, sc: Scores) -> dict:
    return dict(step=step, wall_s=wall, cpu_s=cpu, **figures(sc))


def _print_point(name: str, c: dict, n: int | None = None) -> None:
    extra = f"  N {n}" if n is not None else ""
    print(f"  {name:15s} step {c['step']:5d}  wall {c['wall_s']:7.1f} s  cpu {c['cpu_s']:7.1f} s  "
          f"PSNR {fmt(c['psnr']):>6s}  SSIM {fmt(c['ssim'], 4)}  raw {fmt(c['psnr_raw']):>6s}  "
          f"performers {fmt(c['psnr_performers']):>6s} / {fmt(c['ssim_performers'], 4)}{extra}",
          flush=True)


def run_method(name: str, scene: BenchScene, init: InitPoints, s: Settings, ev: Evaluation, *,
               with_curve: bool, sheet: Path | None = None, sheet_title: str = "") -> MethodResult:
    """Train ``name`` (see the module doc) and score it on the held-out views: its initial model
    (step 0), ``s.snapshots`` points along the run when ``with_curve``, and the end; the region
    figures per camera role of the end and its floors (:meth:`Evaluation.regions`). ``full`` is
    also scored by ``score_segment`` (training views; the contact sheet, written to ``sheet``)."""
    train_views = [v for v in scene.data.views if v.camera_id not in scene.held_out]
    cap = cap_for(s.frames * s.points_per_frame)
    model = Poly4DGSConfig.paper(sh_degree=s.sh_degree)
    extra: dict = {}
    points = init.all
    if name == "rotor4d":
        model = Poly4DGSConfig.rotor4d(sh_degree=s.sh_degree)
    elif name == "no_black":
        extra["optimise_black_level"] = False
    elif name == "no_exposure":
        extra["optimise_exposure"] = False
    elif name == "sparse":
        points = subsample_points(init.frames, s.sparse_fraction, seed=s.seed)   # no scan
    elif name == "linear_storage":
        model = model.model_copy(update={"colour_space": "linear"})
    elif name == "per_frame":
        return _run_per_frame(scene, init, s, ev, train_views, with_curve=with_curve)
    elif name != "full":
        raise ValueError(name)

    every = s.steps // s.snapshots if with_curve else 0
    cfg = base_config(s, model=model, steps=s.steps, cap=cap, checkpoint_every=every, **extra)
    data = SegmentData(scene.frames, train_views)
    initial = initial_model(points, cfg, data, s.seed)
    sc, initial_held = ev.held_out(initial, cfg)
    curve = [_point(0, 0.0, 0.0, sc)]
    _print_point(name, curve[0], len(initial))
    log, final, grids = train_with_snapshots(data, points, cfg, seed=s.seed)
    for snap in log.snapshots:   # the last one is the final model (checkpointed after step S)
        sc, held = ev.held_out(snap.model, cfg)
        curve.append(_point(snap.step, snap.wall_s, snap.cpu_s, sc))
        _print_point(name, curve[-1], len(snap.model))
    learned = {c: {"exposure": float(grids.exposure[i].mean()),
                   "black": float(grids.black[i].mean())} for i, c in enumerate(grids.camera_ids)}
    regions = ev.regions({"held_out": held, "training": ev.trained_training(final, grids, cfg)},
                         initial, initial_held, cfg)
    _print_regions(regions)
    result = MethodResult(name, curve, with_curve, len(final), len(initial), static_count(initial),
                          cap, s.steps, learned, regions=regions)
    if name == "full":
        result.training = _report(final, grids, scene, points, cfg, s, ev, result, held, sheet,
                                  sheet_title)
    return result


def _report(final: Poly4DGS, grids: ExposureGrids, scene: BenchScene,
            points: list[PointsAtTime], cfg: TrainConfig, s: Settings, ev: Evaluation,
            result: MethodResult, held_outputs: list[torch.Tensor], sheet: Path | None,
            title: str) -> dict:
    """``score_segment`` on the full run, as the train-segment task calls it (camera roles and
    face regions included): its held-out figures and its ``regions`` must be the bench's (same
    protocol, same initial model, same functions); returns the training-view ceiling and writes
    the contact sheet, with the held-out tracking cameras' rows added after the held-out static
    ones (``score_segment`` draws the first two held-out cameras only)."""
    cfg_task = cfg.model_copy(update={"held_out_cameras": list(scene.held_out)})
    report = score_segment(final, grids, SegmentData(scene.frames, scene.data.views), points,
                           cfg_task, seed=s.seed, roles=scene.roles,
                           head_region=scene.head_region)
    for key, point in (("trained", result.final), ("initial", result.initial)):
        got = report.held_out[key]
        if not math.isclose(got.psnr, point["psnr"], abs_tol=1e-3):
            print(f"  WARNING: score_segment's {key} PSNR {got.psnr:.4f} != the bench's "
                  f"{point['psnr']:.4f}", flush=True)
    if report.regions != result.regions:
        print("  WARNING: score_segment's region figures differ from the bench's", flush=True)
    tr = report.training
    print(f"  full on its training views (learned grids, raw; {tr.views} views): PSNR "
          f"{fmt(tr.psnr)}  SSIM {fmt(tr.ssim, 4)}  performers {fmt(tr.psnr_performers)} / "
          f"{fmt(tr.ssim_performers, 4)}", flush=True)
    if sheet is not None:
        rows = list(report.sheet_rows)
        drawn = sorted(scene.held_out)[:2]
        extra_cams = [c for c in scene.held_out if c not in drawn]
        index = {(v.camera_id, v.frame): i for i, v in enumerate(ev.held)}
        score_of = {(x.camera_id, x.frame): x for x in report.views}
        added = []
        for v in sheet_views(ev.held, extra_cams):
            sc = score_of[(v.camera_id, v.frame)]
            m = v.load_mask()
            added.append(SheetRow(
                f"{v.camera_id} frame {v.frame} HELD-OUT {scene.roles[v.camera_id]}  PSNR "
                f"{sc.psnr:.1f} dB (raw {sc.psnr_raw:.1f})", v.load()[..., :3].numpy(),
                held_outputs[index[(v.camera_id, v.frame)]].numpy(),
                None if m is None else m.numpy()))
        at = len(sheet_views(ev.held, drawn))
        rows[at:at] = added
        sheet.parent.mkdir(parents=True, exist_ok=True)
        # panels ~2x the 160x90 images (the library's 1600 px default: 3x); 4 MB at 1000 px
        write_sheet(sheet, contact_sheet(rows, title=title, max_width=SHEET_WIDTH))
        print(f"  contact sheet: {sheet}", flush=True)
    return {"views": tr.views, **figures(tr)}


def _run_per_frame(scene: BenchScene, init: InitPoints, s: Settings, ev: Evaluation, train_views,
                   *, with_curve: bool) -> MethodResult:
    """One static model per frame, S / N steps each (the same total step budget), on that frame's
    points plus the coloured scan, cap P / 0.7 each. Curve point k sums every frame's time up to
    its k-th snapshot and scores all frames' models together (each view by its frame's model,
    a training view through its frame's grids)."""
    steps = max(1, s.steps // s.frames)
    every = steps // s.snapshots if with_curve else 0
    model = Poly4DGSConfig.static(sh_degree=s.sh_degree)
    cap = cap_for(s.points_per_frame)
    scan = [init.scan] if init.scan is not None else []
    logs: dict[float, RunLog] = {}
    inits: dict[float, Poly4DGS] = {}
    finals: dict[float, Poly4DGS] = {}
    grids: dict[float, ExposureGrids] = {}
    cfg = base_config(s, model=model, steps=steps, cap=cap, checkpoint_every=every)
    for i, f in enumerate(range(*scene.frames)):
        pts = [init.frames[i]] + scan
        data = SegmentData((f, f + 1), [v for v in train_views if v.frame == f])
        t = init.frames[i].time
        inits[t] = initial_model(pts, cfg, data, s.seed + i)
        logs[t], finals[t], grids[t] = train_with_snapshots(data, pts, cfg, seed=s.seed + i)
    sc, initial_held = ev.held_out(inits, cfg)
    curve = [_point(0, 0.0, 0.0, sc)]
    _print_point("per_frame", curve[0], sum(len(m) for m in inits.values()))
    n_snap = min(len(lg.snapshots) for lg in logs.values())
    held = None
    for k in range(n_snap):
        snaps = {t: lg.snapshots[k] for t, lg in logs.items()}
        sc, held = ev.held_out({t: sn.model for t, sn in snaps.items()}, cfg)
        curve.append(_point(sum(sn.step for sn in snaps.values()),
                            sum(sn.wall_s for sn in snaps.values()),
                            sum(sn.cpu_s for sn in snaps.values()), sc))
        _print_point("per_frame", curve[-1], sum(len(sn.model) for sn in snaps.values()))
    if held is None or n_snap < max(len(lg.snapshots) for lg in logs.values()):
        held = ev.held_out(finals, cfg)[1]   # the curve stopped short of every frame's end
    regions = ev.regions({"held_out": held, "training": ev.trained_training(finals, grids, cfg)},
                         inits, initial_held, cfg)
    _print_regions(regions)
    return MethodResult("per_frame", curve, with_curve, sum(len(m) for m in finals.values()),
                        sum(len(m) for m in inits.values()), 0, cap * s.frames, steps * s.frames,
                        regions=regions)


def _cell(r: dict | None) -> str:
    """``PSNR / SSIM / detail`` of one region figure (``—`` where the region is empty)."""
    if r is None or not r.get("views"):
        return "—"
    return f"{fmt(r['psnr'])} / {fmt(r['ssim'], 3)} / {fmt(r['detail'], 3)}"


def _print_regions(regions: dict) -> None:
    for which, per_role in regions.items():
        for role, r in per_role.items():
            print(f"  {which:8s} {role:8s} ({', '.join(r['cameras'])}): " + "  ".join(
                f"{region} {_cell(r['trained'].get(region))} (empty {_cell(r['empty'].get(region))}, "
                f"initial {_cell(r['initial'].get(region))})" for region in REGIONS), flush=True)


# ------------------------------------------------------------------------------------- reports

def psnr_at_budgets(curve: list[dict], budgets: list[float], key: str) -> list[float | None]:
    """Best PSNR among the snapshots reached within each time budget (None: none yet)."""
    out = []
    for b in budgets:
        ok = [c["psnr"] for c in curve if c[key] <= b + 1e-9]
        out.append(max(ok) if ok else None)
    return out


def print_tables(results: dict[str, MethodResult], empty: dict, s: Settings) -> str:
    lines = []
    lines.append("Error against training time (held-out views; step 0 = the untrained initial "
                 "model; PSNR dB)")
    lines.append("| method | step | wall s | CPU s | PSNR | SSIM | raw PSNR | performers PSNR | "
                 "performers SSIM |")
    lines.append("|---|---|---|---|---|---|---|---|---|")
    for name in METHODS:
        if name in results and results[name].with_curve:
            for c in results[name].curve:
                lines.append(f"| {name} | {c['step']} | {c['wall_s']:.1f} | {c['cpu_s']:.1f} | "
                             f"{fmt(c['psnr'])} | {fmt(c['ssim'], 4)} | {fmt(c['psnr_raw'])} | "
                             f"{fmt(c['psnr_performers'])} | {fmt(c['ssim_performers'], 4)} |")
    curves = [results[n] for n in METHODS if n in results and results[n].with_curve]
    if curves:
        longest = max(r.final["wall_s"] for r in curves)
        budgets = [round(longest * f, 1) for f in (0.25, 0.5, 0.75, 1.0)]
        lines.append("")
        lines.append("Best held-out PSNR reached within a wall-time budget "
                     "(0 s: the initial model)")
        lines.append("| method | " + " | ".join(f"<= {b:g} s" for b in budgets) + " |")
        lines.append("|---|" + "---|" * len(budgets))
        for r in curves:
            vals = psnr_at_budgets(r.curve, budgets, "wall_s")
            lines.append(f"| {r.name} | " + " | ".join(fmt(v) for v in vals) + " |")
    lines.append("")
    lines.append("Floors on the same held-out views, same protocol (empty: renders the background; "
                 "initial: the method's untrained model)")
    lines.append("| model | PSNR | SSIM | raw PSNR | raw SSIM | performers PSNR | performers SSIM "
                 "| Gaussians |")
    lines.append("|---|---|---|---|---|---|---|---|")
    rows = [("empty", empty, "0")] + [
        (f"initial: {n}", results[n].initial,
         f"{results[n].init_gaussians}" + (f" ({results[n].init_static} static)"
                                           if results[n].init_static else ""))
        for n in METHODS if n in results]
    for label, c, n in rows:
        lines.append(f"| {label} | {fmt(c['psnr'])} | {fmt(c['ssim'], 4)} | {fmt(c['psnr_raw'])} | "
                     f"{fmt(c['ssim_raw'], 4)} | {fmt(c['psnr_performers'])} | "
                     f"{fmt(c['ssim_performers'], 4)} | {n} |")
    lines.append("")
    lines.append(f"Table 1 on the synthetic capture ({s.frames} frames, {s.steps} steps; held-out "
                 f"PSNR dB with a per-camera gain/offset fitted on the camera's other frames)")
    lines.append("| method | PSNR | SSIM | raw PSNR | performers PSNR / SSIM | Δ vs full | "
                 "paper PSNR | paper Δ | floors empty / initial | Gaussians (init → end, cap) | "
                 "train wall s | train CPU s |")
    lines.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
    full = results.get("full")
    for name in METHODS:
        if name not in results:
            continue
        r = results[name]
        f = r.final
        d = f"{f['psnr'] - full.final['psnr']:+.2f}" if full and name != "full" else "—"
        if name in PAPER:
            pp = f"{PAPER[name][0]:.2f}"
            pd = "—" if name == "full" else f"{PAPER[name][0] - PAPER['full'][0]:+.2f}"
        elif name == "linear_storage":
            pp, pd = "—", "≈ −5"
        else:
            pp = pd = "—"
        lines.append(f"| {LABELS[name]} | {fmt(f['psnr'])} | {fmt(f['ssim'], 4)} | "
                     f"{fmt(f['psnr_raw'])} | {fmt(f['psnr_performers'])} / "
                     f"{fmt(f['ssim_performers'], 4)} | {d} | {pp} | {pd} | "
                     f"{fmt(empty['psnr'])} / {fmt(r.initial['psnr'])} | "
                     f"{r.init_gaussians} → {r.gaussians}, {r.cap} | {f['wall_s']:.0f} | "
                     f"{f['cpu_s']:.0f} |")
    if full is not None and full.training is not None:
        t = full.training
        lines.append("")
        lines.append(f"Ceiling: the full run on {t['views']} of its training views with their "
                     f"learned grids (raw): PSNR {fmt(t['psnr'])}, SSIM {fmt(t['ssim'], 4)}, "
                     f"performers {fmt(t['psnr_performers'])} / {fmt(t['ssim_performers'], 4)}")
    lines += ["", *region_table(results)]
    text = "\n".join(lines)
    print(text)
    return text


def region_table(results: dict[str, MethodResult]) -> list[str]:
    """Table 1's region figures per camera role (``score_segment``'s ``regions``): one column per
    view set, role and region, one row per method and per floor on the same pixels."""
    first = next((r for n, r in results.items() if r.regions), None)
    if first is None:
        return []
    cols = [(which, role, region) for which in ("held_out", "training") for role in ROLES
            for region in REGIONS if role in first.regions.get(which, {})]
    head = [f"{'held-out' if w == 'held_out' else 'training'} {role} "
            f"({', '.join(first.regions[w][role]['cameras'])}) {region}" for w, role, region in cols]

    def row(label: str, r: MethodResult, model: str) -> str:
        return f"| {label} | " + " | ".join(
            _cell(r.regions.get(w, {}).get(role, {}).get(model, {}).get(region))
            for w, role, region in cols) + " |"

    lines = ["Region figures per camera role (PSNR dB / SSIM / detail: the output's gradient energy "
             "over the footage's; held out after each model's cross-fitted gain/offset, training "
             "views after the trained model's grids and the floors' cross-fitted gain/offset; "
             "performers = ground-truth mask >= 0.5, face = the performers within the heads)",
             "| model | " + " | ".join(head) + " |", "|---|" + "---|" * len(cols),
             row("floor: empty", first, "empty")]
    for name in METHODS:
        if name in results and results[name].regions:
            r = results[name]
            lines.append(row(LABELS[name], r, "trained"))
            lines.append(row(f"floor: untrained {name}", r, "initial"))
    return lines


def grid_table(results: dict[str, MethodResult], scene: BenchScene) -> str:
    """What the training cameras' grids learned against the synthetic camera's truth: relative
    gain (gain × mean channel gain, over the training cameras' geometric mean) and black offset.
    The model's brightness is arbitrary, so E can only match the gains up to one common factor."""
    rows = [r for r in results.values() if r.grids]
    if not rows:
        return ""
    cams = scene.train_cameras
    g = {c: scene.photometric[c]["gain"] * float(np.mean(scene.photometric[c]["channel_gain"]))
         for c in cams}
    gm = math.exp(np.mean([math.log(v) for v in g.values()]))
    shown = rows[:1]
    lines = ["Learned grids (mean over cells and channels) against the truth",
             "| camera | role | true rel. gain | true black | glare | "
             + " | ".join(f"E {r.name} | B {r.name}" for r in shown) + " |",
             "|---|---|---|---|---|" + "---|---|" * len(shown)]
    for c in cams:
        ph = scene.photometric[c]
        cells = " | ".join(f"{r.grids[c]['exposure']:.3f} | {r.grids[c]['black']:+.4f}"
                           for r in shown)
        lines.append(f"| {c} | {ph['role']} | {g[c] / gm:.3f} | "
                     f"{float(np.mean(ph['black_offset'])):.4f} | {ph['glare_fraction']:.3f} | "
                     f"{cells} |")
    lines.append("")
    lines.append("slope of log E against log(true gain) over the training cameras "
                 "(1: E absorbs the gains, 0: E does not move); E and B ranges:")
    for r in rows:
        x = np.log([g[c] for c in cams])
        y = np.log([max(r.grids[c]["exposure"], 1e-6) for c in cams])
        slope = float(np.polyfit(x, y, 1)[0])
        es = [r.grids[c]["exposure"] for c in cams]
        bs = [r.grids[c]["black"] for c in cams]
        lines.append(f"  {r.name:15s} slope {slope:+.3f}  E {min(es):.3f}..{max(es):.3f}  "
                     f"B {min(bs):+.4f}..{max(bs):+.4f}")
    return "\n".join(lines)


def plot(results: dict[str, MethodResult], empty: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    styles = {"full": ("C0", "o-"), "rotor4d": ("C1", "s-"), "per_frame": ("C2", "^-"),
              "linear_storage": ("C3", "D--")}
    markers = {"no_black": "x", "no_exposure": "+", "sparse": "v", "linear_storage": "D",
               "full": "o", "rotor4d": "s", "per_frame": "^"}
    for ax, key, xlabel in ((axes[0], "wall_s", "training wall-clock time (s)"),
                            (axes[1], "cpu_s", "training CPU time (s, one thread)")):
        ax.axhline(empty["psnr"], color="0.5", ls=":", lw=1,
                   label=f"floor: empty model ({empty['psnr']:.1f} dB)")
        for name in METHODS:
            if name not in results:
                continue
            r = results[name]
            if r.with_curve:
                c = r.curve
                colour, style = styles.get(name, (None, ".--"))
                ax.plot([p[key] for p in c], [p["psnr"] for p in c], style, color=colour,
                        label=LABELS[name] + " (step 0: initial model)")
            else:
                f = r.final
                ax.plot([f[key]], [f["psnr"]], markers.get(name, "."), color="0.3", markersize=7,
                        label=LABELS[name] + " (end)")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("held-out PSNR (dB, sRGB; gain/offset from other frames)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------- main

HELP_DESCRIPTION = """\
Poly4DGS on a synthetic capture: held-out error against training time (with the empty and
untrained floors), and the paper's Table 1 with its ablations, under the library's held-out
protocol (volcap_core.splat.scoring), with score_segment's region figures per camera role
(performers and face: PSNR, SSIM, detail; held-out S002, S005 and the tracking S010). Initial points as production builds them
(reconstruction.segment_points: lidar scan + persistence, the coloured scan appended).
Defaults: 6 frames at 160x90, 5000 points per frame, 360 steps per run (8-10 min on
2 lightly loaded cores).
"""

HELP_EPILOG = """\
columns: PSNR/SSIM = held-out views with a per-camera gain/offset fitted on the camera's OTHER
frames; raw PSNR = no transform; performers = pixels where the ground-truth performer mask >= 0.5;
floors = the empty model (background only) and the method's untrained initial model, scored the
same way on the same views (the initial model is also step 0 of each curve); Gaussians = initial ->
end, and MCMC's cap (initial count / 0.7); times = training only (evaluation excluded).
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=HELP_DESCRIPTION,
        epilog=HELP_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="smoke run (~50 s): 2 frames at 80x45, 40 steps; numbers meaningless")
    ap.add_argument("--frames", type=int, help="frames in the segment (default 6; quick 2)")
    ap.add_argument("--steps", type=int, help="optimiser steps per run, per-frame GS splits them "
                    "over its frames (default 360; quick 40)")
    ap.add_argument("--downsample", type=int, help="image downsampling factor, 320x180 / d "
                    "(default 2; quick 4)")
    ap.add_argument("--points-per-frame", type=int, help="dense points per frame; the runs start "
                    "from frames x this many Gaussians (default 5000; quick 1500)")
    ap.add_argument("--snapshots", type=int, help="evaluation points along each curve, besides "
                    "the initial model (default 4; quick 2)")
    ap.add_argument("--lr-exposure", type=float, help="exposure-grid learning rate "
                    "(default: the library's)")
    ap.add_argument("--lr-black", type=float, help="black-level-grid learning rate "
                    "(default: the library's)")
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=METHODS)
    ap.add_argument("--curves", nargs="*", choices=METHODS, default=list(CURVE_METHODS),
                    help="methods evaluated along the run (the others at their initial model and "
                    "at the end only)")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    ap.add_argument("--capture", type=Path, help="reuse/keep the synthetic capture here (it needs "
                    "at least --frames frames, written with depth and masks)")
    ap.add_argument("--json", type=Path, help="write every number here")
    ap.add_argument("--plot", type=Path, help=f"PSNR-vs-time PNG (default: none with --quick, "
                    f"{DEFAULT_PLOT} otherwise)")
    ap.add_argument("--sheet", type=Path, help=f"contact sheet PNG of the full run (default: none "
                    f"with --quick, {DEFAULT_SHEET} otherwise)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    s = Settings.quick() if args.quick else Settings.full()
    over = {k: getattr(args, k) for k in ("frames", "steps", "downsample", "points_per_frame",
                                          "snapshots", "lr_exposure", "lr_black")
            if getattr(args, k) is not None}
    s = Settings(**{**s.__dict__, **over})
    t_all = time.perf_counter()
    print(f"settings: {s}  threads={torch.get_num_threads()}  load average "
          f"{os.getloadavg()[0]:.2f}", flush=True)

    with tempfile.TemporaryDirectory(prefix="bench-poly4dgs-") as tmp:
        cap_dir = args.capture or Path(tmp) / "capture"
        t0 = time.perf_counter()
        if not (cap_dir / "capture.json").exists():
            synthesize_capture(cap_dir, rig="demo_scene", seed=0, frames=s.frames,
                               write_depth=True)
        t_synth = time.perf_counter() - t0
        t0 = time.perf_counter()
        held_out = held_out_cameras(cap_dir)
        scene = load_scene(cap_dir, frames=(0, s.frames), held_out=held_out,
                           downsample=s.downsample, points_per_frame=s.points_per_frame,
                           seed=s.seed)
        t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    init = production_points(scene)
    t_points = time.perf_counter() - t0
    v0 = scene.data.views[0]
    held_views = [v for v in scene.data.views if v.camera_id in scene.held_out]
    n_masks = sum(v.mask is not None for v in held_views)
    cap = cap_for(s.frames * s.points_per_frame)
    print(f"capture: {t_synth:.1f} s to synthesize, {t_load:.1f} s to read; "
          f"{len(scene.train_cameras)} training + {len(scene.held_out)} held-out cameras "
          f"({', '.join(f'{c} {scene.roles[c]}' for c in scene.held_out)}) × "
          f"{s.frames} frames at {v0.camera.width}x{v0.camera.height} (and portrait); "
          f"performer masks on {n_masks}/{len(held_views)} held-out views", flush=True)
    print(f"initial points ({t_points:.1f} s, reconstruction.segment_points): {init.summary()}; "
          f"runs start from {s.frames * s.points_per_frame} Gaussians, MCMC cap {cap}", flush=True)

    # the empty floor: the same for every method (background only, no Gaussian)
    empty_cfg = base_config(s, model=Poly4DGSConfig.paper(sh_degree=s.sh_degree), steps=s.steps,
                            cap=cap, checkpoint_every=0)
    assert init_budget(empty_cfg) >= s.frames * s.points_per_frame
    ev = Evaluation(scene, empty_cfg)
    empty = ev.empty
    print(f"floor: empty model  PSNR {fmt(empty['psnr'])}  SSIM {fmt(empty['ssim'], 4)}  raw "
          f"{fmt(empty['psnr_raw'])}  performers {fmt(empty['psnr_performers'])} / "
          f"{fmt(empty['ssim_performers'], 4)}", flush=True)

    sheet_path = args.sheet or (None if args.quick else DEFAULT_SHEET)
    plot_path = args.plot or (None if args.quick else DEFAULT_PLOT)
    if plot_path is not None and importlib.util.find_spec("matplotlib") is None:
        print(f"WARNING: matplotlib is not installed (pip install -e '.[bench]'): no plot "
              f"({plot_path}); everything else runs", flush=True)
        plot_path = None
    sheet_title = (f"Poly4DGS full, synthetic demo_scene frames 0:{s.frames}, "
                   f"{v0.camera.width}x{v0.camera.height}, {s.steps} steps: "
                   f"footage | render | error")
    results: dict[str, MethodResult] = {}
    loads = [os.getloadavg()[0]]
    for name in args.methods:
        t0 = time.perf_counter()
        print(f"{name}:", flush=True)
        results[name] = run_method(name, scene, init, s, ev, with_curve=name in args.curves,
                                   sheet=sheet_path, sheet_title=sheet_title)
        loads.append(os.getloadavg()[0])
        print(f"  ({time.perf_counter() - t0:.0f} s with evaluation)", flush=True)
    total = time.perf_counter() - t_all
    tables = print_tables(results, empty, s)
    grids = grid_table(results, scene)
    print("\n" + grids)
    text = tables + "\n\n" + grids
    print(f"\ntotal {total:.0f} s; load average (1 min) sampled between runs: "
          f"{min(loads):.2f}-{max(loads):.2f}")

    if plot_path is not None:
        plot(results, empty, plot_path,
             f"Poly4DGS on synthetic demo_scene: {s.frames} frames, "
             f"{v0.camera.width}x{v0.camera.height}, {s.steps} steps, held-out "
             f"{'+'.join(scene.held_out)} (gain/offset fitted on other frames); 1 thread, shared 2-core "
             f"Xeon")
        print(f"plot: {plot_path}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({
            "settings": s.__dict__, "threads": torch.get_num_threads(),
            "protocol": "volcap_core.splat.scoring (per-camera gain/offset fitted on other frames)",
            "machine": {"cpu": platform.processor() or platform.machine(),
                        "cpus": os.cpu_count(), "load_avg_1min": loads},
            "total_s": total, "capture_s": t_synth, "points": init.summary(),
            "floors": {"empty": empty,
                       "initial": {n: r.initial for n, r in results.items()}},
            "results": {n: {k: v for k, v in asdict(r).items() if k != "name"}
                        for n, r in results.items()},
            "tables": text}, indent=1))
    if not all(math.isfinite(r.final["psnr"]) for r in results.values()):
        print("non-finite PSNR", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
