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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from volcap_core.contact_sheet import SheetRow
from volcap_core.splat.grids import ExposureGrids
from volcap_core.splat.model import Poly4DGS
from volcap_core.splat.scoring import Scores, ViewScore, cross_fitted_transforms, score_views, summarise
from volcap_core.splat.train import (
    PointsAtTime,
    SegmentData,
    TrainConfig,
    View,
    evaluate_held_out,
    frame_interval,
    init_model,
    render_views,
)

__all__ = ["SegmentScores", "score_segment", "sheet_views"]


@dataclass
class SegmentScores:
    """``held_out``: model name ("trained", "initial", "empty") -> :class:`Scores` on the same
    held-out views; ``training``: the trained model on training views with their grids;
    ``views``: the trained model's per-view held-out scores; ``sheet_rows``: contact-sheet rows
    (held-out and training cameras at the segment's first, middle and last frame)."""

    held_out: dict[str, Scores]
    training: Scores
    views: list[ViewScore] = field(default_factory=list)
    sheet_rows: list[SheetRow] = field(default_factory=list)

    def to_json(self) -> dict:
        """What :attr:`volcap_core.reconstruction.SegmentModel.scores` keeps."""
        return {"held_out": {k: v.to_json() for k, v in self.held_out.items()},
                "training": self.training.to_json()}

    def table(self) -> list[dict]:
        """One row per model and view set: what a coordinator reads (and the Prefect table)."""
        rows = [{"views": "held-out", "model": k, **v.to_json()} for k, v in self.held_out.items()]
        rows.append({"views": "training (own grids)", "model": "trained", **self.training.to_json()})
        return rows


def _spread(views: Sequence[View], n: int) -> list[View]:
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
                  max_training_views: int = 12, device: torch.device | str = "cpu") -> SegmentScores:
    """Score a trained segment against its floors (see the module doc).

    Args:
        model, grids: what :func:`~volcap_core.splat.train.train_segment` returned.
        data, init_points, config, seed: what it was trained with (the initial model is rebuilt
            from them exactly as training built it).
        max_training_views: training views scored, spread over cameras and frames.
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
    held_out = {"trained": summarise(trained_views),
                "initial": summarise(evaluate_held_out(initial, held_views, config, device=device)),
                "empty": summarise(evaluate_held_out(None, held_views, config, device=device))}

    scored = _spread(train_views, max_training_views)
    renders = [grids.apply(r, v.camera_id)
               for r, v in zip(render_views(model, scored, config, device=device), scored)]
    targets = [v.load()[..., :3].to(device) for v in scored]
    masks = [v.load_mask() for v in scored]
    # the grids are the training fit: scored as they are, the "fitted" figure equals the raw one
    ident = score_views(renders, targets, [f"{v.camera_id}#{v.frame}" for v in scored],
                        [0] * len(scored), masks, valid=[v.load_valid() for v in scored])
    training = summarise(ident)

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
    return SegmentScores(held_out, training, trained_views, rows)


def _row(label: str, view: View, output: torch.Tensor) -> SheetRow:
    m = view.load_mask()
    return SheetRow(label, view.load()[..., :3].detach().cpu().numpy(),
                    output.detach().cpu().numpy(), None if m is None else m.cpu().numpy())
