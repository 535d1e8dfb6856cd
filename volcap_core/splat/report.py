"""How good a trained segment is, with its floors and a picture: :func:`score_segment`.

    report = score_segment(result.model, result.grids, data, init_points, config, seed=seed)
    report.held_out["trained"].psnr, report.held_out["empty"].psnr, report.held_out["initial"].psnr
    png = encode_png(contact_sheet(report.sheet_rows, title=...))

Held-out views are scored by :func:`volcap_core.splat.train.evaluate_held_out` (the protocol of
:mod:`volcap_core.splat.scoring`) for three models on the same views: the trained one, the empty
one (renders the background) and the untrained initial one (rebuilt from the same points, config
and seed, so it is the model training started from). Training views are rendered with their
camera's learned exposure/black-level grids and scored raw: they are the fit itself, a ceiling
rather than a measure of generalisation.

Where views carry performer masks (a synthetic capture), ``regions`` adds per camera role
(``static``, ``tracking``) and view set (held out, training) the region figures of
:func:`~volcap_core.splat.scoring.score_region` (PSNR, SSIM, detail) on the performers and on the
face (a head region from the caller, intersected with the performers), for the trained model and
its two floors on the same pixels: the held-out views under the held-out protocol (each model's
own cross-fitted gain/offset), the training views with the trained model's grids and the floors'
cross-fitted gain/offset (the floors learned no grids).

Where held-out views carry performer masks, ``alpha`` adds per camera role the **performers'
alpha** (:func:`~volcap_core.splat.train.performer_alpha`: what a shot composites the performers
with) against the mask ``M``, for the trained model and its floors: ``error`` the mean
``|A - M|`` over the valid pixels, ``on`` the mean ``A`` on the performers (``M >= 0.5``: 1 is
solid), ``spill`` the ``A`` outside them summed over the performers' pixel count (floaters,
shadows drawn as performer: 0 is clean).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from volcap_core.contact_sheet import SheetRow
from volcap_core.splat.grids import ExposureGrids
from volcap_core.splat.model import Poly4DGS, evaluate
from volcap_core.splat.scoring import (
    ColourTransform,
    Scores,
    ViewScore,
    cross_fitted_transforms,
    mean_region_scores,
    score_region,
    score_views,
    summarise,
)
from volcap_core.splat.train import (
    PointsAtTime,
    SegmentData,
    TrainConfig,
    View,
    evaluate_held_out,
    frame_interval,
    init_model,
    performer_alpha,
    render_views,
)

__all__ = ["SegmentScores", "alpha_figures", "role_regions", "score_segment", "sheet_views", "spread_views",
           "view_regions"]


@dataclass
class SegmentScores:
    """``held_out``: model name ("trained", "initial", "empty") -> :class:`Scores` on the same
    held-out views; ``training``: the trained model on training views with their grids;
    ``views``: the trained model's per-view held-out scores; ``sheet_rows``: contact-sheet rows
    (held-out and training cameras at the segment's first, middle and last frame); ``regions``:
    the region figures of the module doc (JSON-ready)."""

    held_out: dict[str, Scores]
    training: Scores
    views: list[ViewScore] = field(default_factory=list)
    sheet_rows: list[SheetRow] = field(default_factory=list)
    regions: dict = field(default_factory=dict)
    alpha: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """What :attr:`volcap_core.reconstruction.SegmentModel.scores` keeps. ``regions``: view set
        (``held_out``, ``training``) -> camera role -> model (``trained``, ``empty``, ``initial``)
        -> region (``performers``, ``face``) -> ``{psnr, ssim, detail, views}``; ``alpha``: camera
        role -> ``cameras`` and model -> ``{error, on, spill, views}`` on the held-out views (module
        doc); both empty without performer masks."""
        return {"held_out": {k: v.to_json() for k, v in self.held_out.items()},
                "training": self.training.to_json(), "regions": self.regions, "alpha": self.alpha}

    def table(self) -> list[dict]:
        """One row per model and view set: what a coordinator reads (and the Prefect table)."""
        rows = [{"views": "held-out", "model": k, **v.to_json()} for k, v in self.held_out.items()]
        rows.append({"views": "training (own grids)", "model": "trained", **self.training.to_json()})
        return rows


def spread_views(views: Sequence[View], n: int) -> list[View]:
    """At most ``n`` of ``views``, spread evenly over the list (deterministic): the training views
    :func:`score_segment` scores (``max_training_views``)."""
    if len(views) <= n:
        return list(views)
    idx = np.linspace(0, len(views) - 1, n).round().astype(int)
    return [views[i] for i in sorted(set(idx.tolist()))]


def sheet_views(views: Sequence[View], cameras: Sequence[str]) -> list[View]:
    """The views of ``cameras`` at the first, middle and last frame of the segment."""
    frames = sorted({v.frame for v in views})
    pick = sorted({frames[0], frames[len(frames) // 2], frames[-1]})
    by_key = {(v.camera_id, v.frame): v for v in views}
    return [by_key[(c, f)] for c in cameras for f in pick if (c, f) in by_key]


def score_segment(model: Poly4DGS, grids: ExposureGrids, data: SegmentData,
                  init_points: Sequence[PointsAtTime], config: TrainConfig, *, seed: int = 0,
                  max_training_views: int = 12, device: torch.device | str = "cpu",
                  roles: Mapping[str, str] | None = None,
                  head_region: Callable[[View], np.ndarray | None] | None = None) -> SegmentScores:
    """Score a trained segment against its floors (see the module doc).

    Args:
        model, grids: what :func:`~volcap_core.splat.train.train_segment` returned.
        data, init_points, config, seed: what it was trained with (the initial model is rebuilt
            from them exactly as training built it).
        max_training_views: training views scored, spread over cameras and frames.
        roles: camera id -> its role for the region figures (``"static"``, ``"tracking"``); a
            camera not in it (or ``roles=None``) counts as ``"static"``.
        head_region: view -> ``[H, W]`` bool, where the performers' heads are in that view (None:
            no head in it); without it the region figures have no ``face``.
    Returns:
        :class:`SegmentScores`.
    """
    held = set(config.held_out_cameras)
    held_views = [v for v in data.views if v.camera_id in held]
    train_views = [v for v in data.views if v.camera_id not in held]
    initial = init_model(init_points, config, frame_interval_s=frame_interval(data.times),
                         generator=torch.Generator().manual_seed(seed)).to(device)
    # the trained model's held-out renders and transforms serve its scores and its sheet rows
    held_renders = render_views(model, held_views, config, device=device)
    held_targets = [v.load()[..., :3].to(device) for v in held_views]
    held_ids, held_frames = [v.camera_id for v in held_views], [v.frame for v in held_views]
    held_valid = [v.load_valid() for v in held_views]
    tfs = cross_fitted_transforms(held_renders, held_targets, held_ids, held_frames, held_valid)
    trained_views = score_views(held_renders, held_targets, held_ids, held_frames,
                                [v.load_mask() for v in held_views], transforms=tfs, valid=held_valid)
    scored = spread_views(train_views, max_training_views)
    masks = [v.load_mask() for v in scored]
    with_regions = any(v.load_mask() is not None for v in held_views) or any(m is not None for m in masks)
    if with_regions:  # the floors' renders and transforms also serve the region figures
        floors = {name: _floor(m, held_views, config, device) for name, m in (("initial", initial), ("empty", None))}
        held_out = {"trained": summarise(trained_views),
                    **{name: summarise(f[2]) for name, f in floors.items()}}
    else:
        held_out = {"trained": summarise(trained_views),
                    "initial": summarise(evaluate_held_out(initial, held_views, config, device=device)),
                    "empty": summarise(evaluate_held_out(None, held_views, config, device=device))}

    renders = [grids.apply(r, v.camera_id)
               for r, v in zip(render_views(model, scored, config, device=device), scored)]
    targets = [v.load()[..., :3].to(device) for v in scored]
    # the grids are the training fit: scored as they are, the "fitted" figure equals the raw one
    ident = score_views(renders, targets, [f"{v.camera_id}#{v.frame}" for v in scored],
                        [0] * len(scored), masks, valid=[v.load_valid() for v in scored])
    training = summarise(ident)

    regions: dict = {}
    if with_regions:
        role_of = dict(roles or {})
        held_outputs = {"trained": [t.apply(r) for t, r in zip(tfs, held_renders)],
                        **{name: [t.apply(r) for t, r in zip(f[1], f[0])] for name, f in floors.items()}}
        train_floors = {name: _floor(m, scored, config, device) for name, m in (("initial", initial), ("empty", None))}
        train_outputs = {"trained": renders,
                         **{name: [t.apply(r) for t, r in zip(f[1], f[0])] for name, f in train_floors.items()}}
        regions = {"held_out": role_regions(held_views, held_targets, held_outputs, role_of, head_region),
                   "training": role_regions(scored, targets, train_outputs, role_of, head_region)}
        alpha = alpha_figures(held_views, {"trained": model, "initial": initial, "empty": None}, config,
                              role_of, device=device)
    else:
        alpha = {}

    rows = []
    held_cams = sorted(held)
    sheet_held = sheet_views(held_views, held_cams[:2])
    if sheet_held:
        index = {(v.camera_id, v.frame): i for i, v in enumerate(held_views)}
        score_of = {(s.camera_id, s.frame): s for s in trained_views}
        for v in sheet_held:
            i = index[(v.camera_id, v.frame)]
            sc = score_of[(v.camera_id, v.frame)]
            rows.append(_row(f"{v.camera_id} frame {v.frame} HELD-OUT  PSNR {sc.psnr:.1f} dB "
                             f"(raw {sc.psnr_raw:.1f})", v, tfs[i].apply(held_renders[i])))
    train_cams = sorted({v.camera_id for v in train_views})
    # one static and one moving (tracking) camera when both exist: their framings differ most
    pick_cams = [train_cams[0]] + ([train_cams[-1]] if len(train_cams) > 1 else [])
    for v in sheet_views(train_views, pick_cams):
        r = grids.apply(render_views(model, [v], config, device=device)[0], v.camera_id)
        p = score_views([r], [v.load()[..., :3].to(device)], ["x"], [0], valid=[v.load_valid()])[0].psnr
        rows.append(_row(f"{v.camera_id} frame {v.frame} training  PSNR {p:.1f} dB", v, r))
    return SegmentScores(held_out, training, trained_views, rows, regions, alpha)


def _floor(model: Poly4DGS | None, views: Sequence[View], config: TrainConfig, device
           ) -> tuple[list[torch.Tensor], list[ColourTransform], list[ViewScore]]:
    """A floor model's renders of ``views``, their cross-fitted transforms and its scores: what
    :func:`~volcap_core.splat.train.evaluate_held_out` computes, with the renders kept."""
    if not views:
        return [], [], []
    renders = render_views(model, views, config, device=device)
    targets = [v.load()[..., :3].to(renders[0]) for v in views]
    ids, frames, valid = [v.camera_id for v in views], [v.frame for v in views], [v.load_valid() for v in views]
    tfs = cross_fitted_transforms(renders, targets, ids, frames, valid)
    return renders, tfs, score_views(renders, targets, ids, frames, [v.load_mask() for v in views],
                                     transforms=tfs, valid=valid)


def view_regions(view: View, head_region: Callable[[View], np.ndarray | None] | None) -> dict | None:
    """The regions :func:`role_regions` scores in ``view``: ``performers`` (its performer mask >= 0.5,
    within its valid pixels) and, with ``head_region``, ``face`` (the performers within the heads;
    empty where ``head_region`` gives None), each ``[H, W]`` bool; None without a performer mask."""
    m = view.load_mask()
    if m is None:
        return None
    perf = m >= 0.5
    valid = view.load_valid()
    if valid is not None:
        perf = perf & valid.to(perf.device)
    regions = {"performers": perf}
    if head_region is not None:
        head = head_region(view)
        regions["face"] = perf & torch.as_tensor(head, dtype=torch.bool).to(perf.device) \
            if head is not None else torch.zeros_like(perf)
    return regions


def role_regions(views: Sequence[View], targets: Sequence[torch.Tensor], outputs: Mapping[str, Sequence[torch.Tensor]],
                 role_of: Mapping[str, str], head_region: Callable[[View], np.ndarray | None] | None) -> dict:
    """One view set's ``regions`` (see :meth:`SegmentScores.to_json`): role -> ``cameras`` and model
    -> region -> mean figures (:func:`mean_region_scores`) over ``views``.

    Args:
        views: the views scored; those without a performer mask are left out.
        targets: ``[H, W, 3]`` linear footage of each view.
        outputs: model name -> ``[H, W, 3]`` linear output per view, already through the model's
            colour transform (held out: its cross-fitted gain/offset; training: its grids).
        role_of: camera id -> ``"static"`` or ``"tracking"`` (absent: ``"static"``).
        head_region: view -> ``[H, W]`` bool where the heads are (None: no head in it); None: no
            ``face`` region.
    """
    per_view = [view_regions(v, head_region) for v in views]
    out: dict = {}
    for role in sorted({role_of.get(v.camera_id, "static") for v in views}):
        idx = [i for i, v in enumerate(views) if role_of.get(v.camera_id, "static") == role and per_view[i]]
        if not idx:
            continue
        names = list(per_view[idx[0]])
        out[role] = {"cameras": sorted({views[i].camera_id for i in idx}), **{
            model: {region: mean_region_scores([score_region(outputs[model][i], targets[i], per_view[i][region])
                                                for i in idx]) for region in names}
            for model in outputs}}
    return out


def alpha_figures(views: Sequence[View], models: Mapping[str, Poly4DGS | None], config: TrainConfig,
                  role_of: Mapping[str, str], *, device: torch.device | str = "cpu") -> dict:
    """The performers' alpha of each of ``models`` (None: the empty model, alpha 0) on ``views``
    against their performer masks (the module doc's ``error``, ``on``, ``spill``, each the mean over
    the views), per camera role (absent from ``role_of``: ``"static"``): role -> ``cameras`` and
    model -> ``{error, on, spill, views}``. Views without a mask, or without performers in it, are
    left out."""
    masked = []
    for v in views:
        m = v.load_mask()
        if m is None:
            continue
        ok = v.load_valid()
        ok = torch.ones_like(m, dtype=torch.bool) if ok is None else ok.to(m.device)
        if bool(((m >= 0.5) & ok).any()):
            masked.append((v, m.to(device), ok.to(device)))
    out: dict = {}
    for role in sorted({role_of.get(v.camera_id, "static") for v, _, _ in masked}):
        mine = [x for x in masked if role_of.get(x[0].camera_id, "static") == role]
        out[role] = {"cameras": sorted({v.camera_id for v, _, _ in mine})}
        for name, model in models.items():
            figs = []
            for v, m, ok in mine:
                if model is None:
                    a = torch.zeros_like(m)
                else:
                    with torch.no_grad():
                        a = performer_alpha(model, evaluate(model, v.time), v.camera, backend=config.backend,
                                            tile_size=config.tile_size).to(m)
                on = (m >= 0.5) & ok
                figs.append(((a - m).abs()[ok].mean(), a[on].mean(), a[~on & ok].sum() / on.sum()))
            f = torch.tensor(figs, dtype=torch.float64).mean(0).tolist()
            out[role][name] = {"error": round(f[0], 4), "on": round(f[1], 4), "spill": round(f[2], 4),
                               "views": len(figs)}
    return out


def _row(label: str, view: View, output: torch.Tensor) -> SheetRow:
    m = view.load_mask()
    return SheetRow(label, view.load()[..., :3].detach().cpu().numpy(),
                    output.detach().cpu().numpy(), None if m is None else m.cpu().numpy())
