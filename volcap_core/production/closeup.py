"""Scoring a close-up shot against its truth: what the product delivers, beside its floors.

A synthetic capture knows what a camera at any pose would have seen (the truth renderer,
``volcap_core.production.truth``). :func:`score_closeup` compares a shot's frames (arrays) with
it, :func:`closeup_sheet_rows` draws them, and :func:`score_shot_exrs` does both from the shot's
EXR frames and the capture's ``scene.json`` (what the ``score-shot`` task runs; ``docs/shots.md``,
"Scoring a shot").

Rows (each scored by the same code on the same pixels):

* ``render``: the shot rendered over the performance;
* ``enhanced``: the detail enhancer's output (when given); its floor is the ``render`` row;
* ``empty``: an all-zero render (the empty model's; a shot renders over nothing);
* ``bicubic``: the truth area-averaged to a quarter of its resolution and brought back with
  bicubic interpolation (what upsampling a capture at a quarter of the shot's resolution would
  give at best).

Regions per frame: ``performers`` (truth alpha >= 0.5) and ``face`` (the caller's face mask, e.g.
:func:`volcap_core.synth.ground_truth.face_region`, intersected with the performers). Per row and
region: PSNR, SSIM and detail (:func:`volcap_core.splat.scoring.score_region`: display sRGB,
clamped; :func:`volcap_core.image_metrics.detail`), each the mean over frames (PSNR in dB). No
colour fit: the truth is the scene's radiance, as the render is, so an exposure error is an error.

Over the sequence, per row and for the truth itself: VBench's temporal flickering
(:func:`volcap_core.enhance.metrics.temporal_flickering` on the whole frame) and, given the shot's
backward flows, the warp error (:func:`volcap_core.enhance.metrics.warp_error` on display sRGB
RGB, restricted to the truth's performers in the later frame of each pair): the truth's own figures
are what a perfect output would score (occlusions and shading changes are not errors of the output).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from volcap_core.contact_sheet import SheetRow, contact_sheet
from volcap_core.enhance.metrics import temporal_flickering, warp_error
from volcap_core.enhance.production import read_shot_frame
from volcap_core.enhance.temporal import to_display
from volcap_core.splat.scoring import mean_region_scores, score_region
from volcap_core.synth.ground_truth import FACE_MARGIN_M, face_region

__all__ = ["BICUBIC_FACTOR", "bicubic_floor", "closeup_sheet_rows", "score_closeup", "score_shot_exrs"]

#: The bicubic floor's downsampling factor (a quarter of the shot's resolution per axis).
BICUBIC_FACTOR = 4


def _frames(name: str, frames: Sequence[np.ndarray], shape: tuple[int, ...] | None) -> list[torch.Tensor]:
    out = []
    for i, f in enumerate(frames):
        a = np.asarray(f)
        if a.ndim != 3 or a.shape[2] != 4:
            raise ValueError(f"{name} frame {i}: expected premultiplied RGBA [H, W, 4], got {a.shape}")
        if shape is not None and a.shape != shape:
            raise ValueError(f"{name} frame {i}: {a.shape[1]}x{a.shape[0]} does not match the truth's "
                             f"{shape[1]}x{shape[0]}")
        out.append(torch.from_numpy(np.nan_to_num(a.astype(np.float32), nan=0.0)))
    return out


def bicubic_floor(truth_rgba: np.ndarray, factor: int = BICUBIC_FACTOR) -> np.ndarray:
    """The truth ``[H, W, C]`` area-averaged to ``1/factor`` of its size (rounded up) and brought
    back to ``H × W`` with bicubic interpolation (``align_corners=False``). Linear values; the
    overshoot of the cubic is kept (the display encoding clamps it)."""
    t = torch.from_numpy(np.asarray(truth_rgba, np.float32)).permute(2, 0, 1)[None]
    h, w = t.shape[-2:]
    small = F.interpolate(t, size=(max(1, math.ceil(h / factor)), max(1, math.ceil(w / factor))), mode="area")
    return F.interpolate(small, size=(h, w), mode="bicubic", align_corners=False)[0].permute(1, 2, 0).numpy()


def score_closeup(truth: Sequence[np.ndarray], render: Sequence[np.ndarray], face_masks: Sequence[np.ndarray],
                  *, enhanced: Sequence[np.ndarray] | None = None, flows: Sequence[np.ndarray | None] | None = None
                  ) -> dict:
    """Score a shot's render (and enhanced render) against its truth, beside the floors.

    Args:
        truth: per shot frame, the truth ``[H, W, 4]`` premultiplied linear RGBA.
        render: per frame, the render ``[H, W, 4]`` (same layout, pixel-aligned with the truth).
        face_masks: per frame, ``[H, W]`` bool (or coverage, >= 0.5): where the faces are.
        enhanced: per frame, the enhancer's output ``[H, W, 4]``, or None.
        flows: per frame, the backward flow to the previous frame ``[H, W, 2]`` (px, x then y, as
            a render-shot frame's ``flow.x``/``flow.y``), None for the first frame and wherever the
            shot has none; warp error is over the pairs that have one.
    Returns:
        a JSON-able dict::

            {"frames": T, "width": W, "height": H,
             "rows": {row: {region: {"psnr", "ssim", "detail", "views"}, ..., "per_frame": {region:
                     {"psnr": [...], "ssim": [...], "detail": [...]}}}},
             "floors": {"render": ["empty", "bicubic"], "enhanced": ["render", "empty", "bicubic"]},
             "temporal": {row or "truth": {"flickering", "warp_error"}},
             "bicubic_factor": 4}

        ``views`` counts the frames whose region is non-empty; a figure is None when no frame has it.
    """
    if not truth:
        raise ValueError("score_closeup: no truth frames")
    n = len(truth)
    shape = np.asarray(truth[0]).shape
    truth_t = _frames("truth", truth, shape)
    if len(render) != n or len(face_masks) != n or (enhanced is not None and len(enhanced) != n):
        raise ValueError(f"score_closeup: {n} truth frames but {len(render)} render, {len(face_masks)} face masks"
                         + (f", {len(enhanced)} enhanced" if enhanced is not None else ""))
    rows: dict[str, list[torch.Tensor]] = {"render": _frames("render", render, shape)}
    if enhanced is not None:
        rows["enhanced"] = _frames("enhanced", enhanced, shape)
    rows["empty"] = [torch.zeros_like(t) for t in truth_t]
    rows["bicubic"] = [torch.from_numpy(bicubic_floor(t.numpy())) for t in truth_t]

    regions = []
    for i, (t, face) in enumerate(zip(truth_t, face_masks)):
        f = np.asarray(face)
        if f.shape != shape[:2]:
            raise ValueError(f"face mask of frame {i}: {f.shape} does not match the frames' {shape[:2]}")
        perf = t[..., 3] >= 0.5
        regions.append({"performers": perf, "face": perf & torch.from_numpy(f >= 0.5)})

    out_rows = {}
    for name, frames in rows.items():
        per = [{r: score_region(o[..., :3], t[..., :3], m) for r, m in reg.items()}
               for o, t, reg in zip(frames, truth_t, regions)]
        entry = {r: mean_region_scores([p[r] for p in per]) for r in ("performers", "face")}
        entry["per_frame"] = {r: {k: [None if getattr(p[r], k) is None else round(getattr(p[r], k), 4) for p in per]
                                  for k in ("psnr", "ssim", "detail")} for r in ("performers", "face")}
        out_rows[name] = entry

    temporal = {}
    if n >= 2:
        videos = {"truth": truth_t, **rows}
        flow_pairs = _flow_pairs(flows, n, shape) if flows is not None else []
        for name, frames in videos.items():
            video = torch.stack(frames).permute(0, 3, 1, 2)        # [T, 4, H, W]
            temporal[name] = {"flickering": round(temporal_flickering(video), 6),
                              "warp_error": _warp_error(video, truth_t, flow_pairs)}
    return {"frames": n, "width": int(shape[1]), "height": int(shape[0]), "rows": out_rows,
            "floors": {"render": ["empty", "bicubic"],
                       **({"enhanced": ["render", "empty", "bicubic"]} if enhanced is not None else {})},
            "temporal": temporal, "bicubic_factor": BICUBIC_FACTOR}


def _flow_pairs(flows: Sequence[np.ndarray | None], n: int, shape: tuple[int, ...]) -> list[tuple[int, torch.Tensor]]:
    if len(flows) != n:
        raise ValueError(f"score_closeup: {n} frames but {len(flows)} flows")
    pairs = []
    for i in range(1, n):
        if flows[i] is None:
            continue
        f = np.asarray(flows[i], np.float32)
        if f.shape != (*shape[:2], 2):
            raise ValueError(f"flow of frame {i}: expected {(*shape[:2], 2)}, got {f.shape}")
        pairs.append((i, torch.from_numpy(f).permute(2, 0, 1)))
    return pairs


def _warp_error(video: torch.Tensor, truth: Sequence[torch.Tensor], pairs: Sequence[tuple[int, torch.Tensor]]
                ) -> float | None:
    """Mean over the flowed pairs of :func:`warp_error` on the pair's display RGB, masked by the
    truth's performers in the later frame; None without flows or performers."""
    errs = []
    for i, flow in pairs:
        pair = to_display(video[i - 1:i + 1, :3])
        mask = (truth[i][..., 3] >= 0.5).float()[None, None]
        e = warp_error(pair, flow[None], mask)
        if math.isfinite(e):
            errs.append(e)
    return round(float(np.mean(errs)), 8) if errs else None


def closeup_sheet_rows(truth: Sequence[np.ndarray], render: Sequence[np.ndarray], face_masks: Sequence[np.ndarray],
                       scores: dict, *, enhanced: Sequence[np.ndarray] | None = None,
                       frame_numbers: Sequence[int] | None = None) -> list[SheetRow]:
    """Contact-sheet rows (:func:`volcap_core.contact_sheet.contact_sheet`) at the first, middle
    and last frame: per frame a row ``truth | render | error`` and, with ``enhanced``, a row
    ``truth | enhanced | error``, each labelled with its face figures from ``scores``
    (:func:`score_closeup`'s) and the face outlined. ``frame_numbers``: the shot's frame numbers
    for the labels (default 0..T-1)."""
    n = len(truth)
    if n == 0:
        raise ValueError("closeup_sheet_rows: no frames")
    numbers = list(frame_numbers) if frame_numbers is not None else list(range(n))
    pick = sorted({0, n // 2, n - 1})
    outputs = {"render": render, **({"enhanced": enhanced} if enhanced is not None else {})}
    rows = []
    for i in pick:
        t = np.asarray(truth[i], np.float32)
        face = (np.asarray(face_masks[i]) >= 0.5) & (t[..., 3] >= 0.5)
        for name, frames in outputs.items():
            pf = scores["rows"][name]["per_frame"]["face"]
            fig = (f"face PSNR {_fmt(pf['psnr'][i])} dB  SSIM {_fmt(pf['ssim'][i], 3)}  "
                   f"detail {_fmt(pf['detail'][i], 2)}")
            rows.append(SheetRow(f"frame {numbers[i]} {name}: {fig}", t[..., :3],
                                 np.asarray(frames[i], np.float32)[..., :3], face.astype(np.float32)))
    return rows


def _fmt(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def score_shot_exrs(truth: Sequence[tuple[str, bytes]], render: Sequence[tuple[str, bytes]],
                    scene: Mapping[str, Any], *, enhanced: Sequence[tuple[str, bytes]] | None = None,
                    actors: Sequence[int] | None = None, margin_m: float = FACE_MARGIN_M,
                    sheet_width: int = 1600) -> tuple[dict, np.ndarray]:
    """Score a shot's EXR frames against the truth's and draw the sheet.

    Args:
        truth: ``(name, EXR bytes)`` per shot frame, in frame order: premultiplied linear RGBA,
            cropped to a data window or whole (the truth renderer's frames,
            :mod:`volcap_core.production.truth`; read over the display window as the render's).
        render: the render-shot frames of the same names (cropped RGBA with the camera
            ``volcap.K``, ``volcap.worldToCamera``, ``volcap.time``, ``volcap.frame`` and the flow
            in their headers; :func:`volcap_core.enhance.production.read_shot_frame`).
        scene: the capture's ``ground_truth/scene.json``: the face masks are
            :func:`~volcap_core.synth.ground_truth.face_region` of ``actors`` (None: all) in each
            frame's camera at its time, grown by ``margin_m``.
        enhanced: the enhanced frames of the same names, or None.
    Returns:
        (:func:`score_closeup`'s dict plus ``"shot_frames"`` (the frames' numbers), the contact
        sheet ``uint8 [H, W, 3]``).
    """
    names = [n for n, _ in truth]
    for label, frames in (("render", render), ("enhanced", enhanced)):
        if frames is not None and [n for n, _ in frames] != names:
            raise ValueError(f"score-shot: the {label} frames ({', '.join(n for n, _ in frames)}) are not the "
                             f"truth's ({', '.join(names)})")
    truth_px, render_px, flows, faces, numbers = [], [], [], [], []
    for (name, t_bytes), (_, r_bytes) in zip(truth, render):
        header, rgba, flow = read_shot_frame(r_bytes, with_flow=True)
        try:
            _, t = read_shot_frame(t_bytes)
        except ValueError as exc:
            raise ValueError(f"truth {name}: {exc}") from None
        if t.shape[:2] != rgba.shape[:2]:
            raise ValueError(f"truth {name}: a {t.shape[1]}x{t.shape[0]} frame, the render's is "
                             f"{rgba.shape[1]}x{rgba.shape[0]} (not the same shot)")
        try:
            K = np.asarray(header["volcap.K"], np.float64).reshape(3, 3)
            w2c = np.asarray(header["volcap.worldToCamera"], np.float64).reshape(4, 4)
            time_s = float(np.asarray(header["volcap.time"]).reshape(-1)[0])
        except KeyError as exc:
            raise ValueError(f"render {name}: no {exc.args[0]} in its header (not a render-shot frame)") from None
        h, w = rgba.shape[:2]
        faces.append(face_region(scene, time_s, K, w2c, w, h, actors=actors, margin_m=margin_m))
        truth_px.append(t)
        render_px.append(rgba)
        flows.append(flow)
        numbers.append(int(header.get("volcap.frame", len(numbers))))
    enhanced_px = None if enhanced is None else [read_shot_frame(b)[1] for _, b in enhanced]
    scores = score_closeup(truth_px, render_px, faces, enhanced=enhanced_px, flows=flows)
    scores["shot_frames"] = numbers
    rows = closeup_sheet_rows(truth_px, render_px, faces, scores, enhanced=enhanced_px, frame_numbers=numbers)
    title = f"close-up: truth | {'render, enhanced' if enhanced is not None else 'render'} | error (face outlined)"
    return scores, contact_sheet(rows, title=title, max_width=sheet_width, truth_label="truth")
