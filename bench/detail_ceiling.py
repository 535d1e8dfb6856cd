"""The detail ceiling of noisy footage: what a perfect, noise-free model scores (issue 28).

Issue 28's detail figure is the performers' (and faces') gradient energy of the render over the
footage's (:func:`volcap_core.image_metrics.detail`). A synthetic capture's footage carries its
sensor's read and shot noise (:mod:`volcap_core.synth.sensor`), and that noise is part of the
footage's gradient energy: a model that matched the scene exactly renders the camera's expected
values, the **noise-free recording**, and scores below 1. This bench measures how far below.

For each view scored, the noise-free recording of the same camera at the same take index
(:func:`volcap_core.synth.truth.capture_recording`: the capture's own renderer through the
capture's true camera, sampled as the footage was, then the camera's sensor without noise) is
scored against the footage with the code that scores a render in ``volcap reconstruct --json``'s
``scores.regions`` (:func:`volcap_core.splat.report.role_regions`: display sRGB, the ground-truth
performer masks, the face regions of :func:`volcap_core.synth.ground_truth.face_region` through the
calibration's camera, :func:`~volcap_core.splat.scoring.score_region`), under the same protocol:
a held-out camera's output through its cross-fitted gain/offset
(:func:`~volcap_core.splat.scoring.cross_fitted_transforms`), a training camera's as it is (a
perfect model's exposure grids reproduce the camera's exposure: the recording already has it).

Two checks say the noise-free recording is right before its figures are read as the ceiling:

* its PSNR against the footage is the noise's: the noise model predicts, per region, the display
  MSE ``mean(slope(x)² · (read² + shot · S))`` (``x`` the recording, ``S`` its signal above black,
  ``slope`` the sRGB curve's derivative: the noise is small enough to be carried linearly), and
  with it the ceiling itself, ``E / (E + N)`` (``E`` the recording's gradient energy, ``N`` the
  noise's expected one: ``Σ`` over the differences counted of the two pixels' display variances);
* the noise-free recording with noise drawn afresh from the sensor's law (a second recording of
  the same instant) scores detail ~1 against the footage, and PSNR 3 dB below the prediction (two
  independent noises).

Views: by default those ``score_segment`` scores, so that the ceiling divides its figures view for
view: every view of the held-out cameras (the demo preset's: S004 and S010) and the training views
it spreads over cameras and frames (:func:`~volcap_core.splat.report.spread_views`, 12); and per
camera, every camera at ``--frames`` (0, 4, 7). The views must hold the footage as stored (no
rectification, full resolution): the recording is rendered at the footage's pixels.

    python bench/detail_ceiling.py                         # the demo's store, segment 0:8
    python bench/detail_ceiling.py --store /tmp/demo-base/store --json ceiling.json

About 30 s for the demo on the shared 2 cores (12 cameras at 320x180: 28 views scored, 36 per camera).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from volcap_core.colour import srgb_encode_and_slope  # noqa: E402
from volcap_core.splat.report import role_regions, spread_views, view_regions  # noqa: E402
from volcap_core.splat.scoring import cross_fitted_transforms  # noqa: E402
from volcap_core.splat.train import View  # noqa: E402
from volcap_core.synth.sensor import SensorModel  # noqa: E402
from volcap_core.synth.truth import capture_recording, capture_sensor  # noqa: E402

#: the demo's store, capture and segment (``volcap demo``)
DEMO_STORE = "/tmp/demo-base/store"
DEMO_CAPTURE = "captures/synth-demo_scene-s0"
DEMO_SEGMENT = (0, 8)
#: the per-camera table's frames
FRAMES = (0, 4, 7)
#: training views ``score_segment`` scores (its ``max_training_views``)
TRAINING_VIEWS = 12

HeadRegion = Callable[[View], np.ndarray | None]


class Segment:
    """A segment of a synthetic capture in a store, as ``volcap reconstruct`` scores it: its views
    (:func:`volcap_core.reconstruction.segment_data` with the ground-truth performer masks, full
    resolution), the camera roles, the held-out cameras, the face regions, and the capture's world
    and ``cameras.json`` (what renders its noise-free recordings)."""

    def __init__(self, store: str, capture: str = DEMO_CAPTURE, calibration: str | None = None,
                 frames: tuple[int, int] = DEMO_SEGMENT, held_out: Sequence[str] | None = None):
        from volcap_core import reconstruction
        from volcap_core.calibration.record import Calibration
        from volcap_core.capture import Capture
        from volcap_core.production.presets import named_preset
        from volcap_core.segment import tracking_frames
        from volcap_core.store import ArtifactStore
        from volcap_core.synth import ground_truth
        from volcap_core.synth.truth import truth_world

        s = ArtifactStore(store)
        cap = s.get_record(s.resolve(capture), Capture)
        if calibration is None:
            seg = s.get_record(s.get_ref("demo/segment"), reconstruction.SegmentModel)
            calibration = seg.calibration.digest
        calib = s.get_record(s.resolve(calibration), Calibration)
        if calib.capture != cap.name:
            raise SystemExit(f"calibration {calibration} is of capture {calib.capture!r}, not {cap.name!r}")
        if cap.ground_truth is None:
            raise SystemExit(f"capture {cap.name}: no ground truth (not a synthetic capture: no noise-free recording)")
        tree = s.get_tree(cap.ground_truth)
        files = ground_truth.GroundTruthFiles(cap.name, {p: e.digest for p, e in tree.items()}, s.get_bytes)
        load_mask = ground_truth.mask_loader(files)
        if load_mask is None:
            raise SystemExit(f"capture {cap.name}: its ground truth has no masks/ (synthesize with --depth)")
        self.name = cap.name
        self.scene = json.loads(files.read("scene.json"))
        self.cameras = json.loads(files.read("cameras.json"))
        self.world = truth_world(files, cap.rig)
        self.data = reconstruction.segment_data(cap, calib, tracking_frames(s.get_bytes, calib), frames,
                                                reconstruction.FrameCache(s.get_bytes), load_mask=load_mask)
        demo = named_preset("demo")
        self.held_out = list(held_out) if held_out is not None else \
            reconstruction.default_held_out(cap, calibration=calib, tracking=demo.held_out_tracking)
        self.roles = {c.id: "static" if c.static else "tracking" for c in calib.cameras}

    def head_region(self, view: View) -> np.ndarray:
        """What ``fit_segment``'s ``head_region`` gives ``score_segment`` for ``view``."""
        from volcap_core.synth.ground_truth import face_region

        cam = view.camera
        return face_region(self.scene, view.time, cam.K.numpy(), cam.world_to_camera.numpy(), cam.width, cam.height)

    def scored_views(self) -> list[View]:
        """The views ``score_segment`` scores: the held-out cameras' all, then its training ones."""
        held = set(self.held_out)
        return [v for v in self.data.views if v.camera_id in held] + \
            spread_views([v for v in self.data.views if v.camera_id not in held], TRAINING_VIEWS)

    def views_at(self, frames: Sequence[int]) -> list[View]:
        """Every camera's views at take indices ``frames`` (those in the segment)."""
        return [v for v in self.data.views if v.frame in set(frames)]


def recordings(views: Sequence[View], world, cameras: Mapping, *, supersample: int = 2, seed: int = 1
               ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Per view, its camera's noise-free recording at its take index and the same with noise drawn
    afresh (a generator seeded by ``seed``, the camera and the frame: not the footage's), both
    ``[H, W, 3]`` linear float32 (:func:`~volcap_core.synth.truth.capture_recording`;
    ``supersample``: the capture's). A view whose pixels are not the footage's as recorded
    (rectified, or another size) is refused by name."""
    noise_free, redrawn = [], []
    for v in views:
        gt = cameras["cameras"].get(v.camera_id)
        if gt is None:
            raise SystemExit(f"view {v.camera_id}@{v.frame}: the ground truth has no camera {v.camera_id}")
        if v.load_valid() is not None or (v.camera.width, v.camera.height) != (gt["width"], gt["height"]):
            raise SystemExit(f"view {v.camera_id}@{v.frame}: its pixels are resampled (rectified or rescaled); "
                             "the noise-free recording is rendered at the footage's own pixels")
        rng = np.random.default_rng([seed, zlib.crc32(v.camera_id.encode()), v.frame])
        noise_free.append(torch.from_numpy(capture_recording(world, cameras, v.camera_id, v.frame,
                                                             supersample=supersample)))
        redrawn.append(torch.from_numpy(capture_recording(world, cameras, v.camera_id, v.frame,
                                                          supersample=supersample, noise=rng)))
    return noise_free, redrawn


def protocol_outputs(views: Sequence[View], footage: Sequence[torch.Tensor], outputs: Sequence[torch.Tensor],
                     held_out: Sequence[str]) -> list[torch.Tensor]:
    """``outputs`` as ``score_segment`` scores a model's: a held-out camera's through the gain/offset
    cross-fitted on its other frames, a training camera's as they are (its grids are the fit)."""
    held = set(held_out)
    idx = [i for i, v in enumerate(views) if v.camera_id in held]
    out = list(outputs)
    if idx:
        tfs = cross_fitted_transforms([outputs[i] for i in idx], [footage[i] for i in idx],
                                      [views[i].camera_id for i in idx], [views[i].frame for i in idx],
                                      [views[i].load_valid() for i in idx])
        for i, tf in zip(idx, tfs):
            out[i] = tf.apply(outputs[i])
    return out


def predicted(view: View, noise_free: torch.Tensor, sensor: SensorModel, region: torch.Tensor
              ) -> tuple[float | None, float | None]:
    """What the sensor's noise model predicts on ``region`` of ``view`` for the noise-free recording
    against the footage (module doc): ``(PSNR dB, detail)``; None where the region is empty (the
    PSNR also where the sensor has no noise)."""
    if not bool(region.any()):
        return None, None
    x = noise_free.double()
    enc, slope = srgb_encode_and_slope(x)
    signal = (x - torch.tensor(sensor.black, dtype=torch.float64)).clamp(min=0)
    var = slope ** 2 * (sensor.read_noise ** 2 + sensor.shot_noise * signal)      # display variance [H, W, 3]
    mse = float(var[region].mean())
    m = region
    mx, my = (m[:, 1:] & m[:, :-1])[..., None], (m[1:] & m[:-1])[..., None]
    e_signal = float((((enc[:, 1:] - enc[:, :-1]) ** 2) * mx).sum() + (((enc[1:] - enc[:-1]) ** 2) * my).sum())
    e_noise = float(((var[:, 1:] + var[:, :-1]) * mx).sum() + ((var[1:] + var[:-1]) * my).sum())
    psnr = 10.0 * np.log10(1.0 / mse) if mse > 0 else None
    total = e_signal + e_noise
    return psnr, (e_signal / total if total > 0 else None)


def ceiling(views: Sequence[View], footage: Sequence[torch.Tensor], noise_free: Sequence[torch.Tensor],
            redrawn: Sequence[torch.Tensor], roles: Mapping[str, str], held_out: Sequence[str],
            sensors: Mapping[str, SensorModel], head_region: HeadRegion | None) -> dict:
    """The figures of ``views``: view set (``held_out``, ``training``) -> role -> ``cameras`` and
    model -> region -> figures, as ``scores.regions`` (:func:`~volcap_core.splat.report.role_regions`)
    for the models ``noise_free`` (the ceiling) and ``redrawn`` (the check: detail ~1), each
    through the protocol (:func:`protocol_outputs`), and ``predicted``: region -> the noise model's
    ``psnr`` and ``detail`` (:func:`predicted`, means over the views as the figures')."""
    outs = {"noise_free": protocol_outputs(views, footage, noise_free, held_out),
            "redrawn": protocol_outputs(views, footage, redrawn, held_out)}
    held = set(held_out)
    result: dict = {}
    for which, in_set in (("held_out", lambda c: c in held), ("training", lambda c: c not in held)):
        idx = [i for i, v in enumerate(views) if in_set(v.camera_id)]
        if not idx:
            continue
        sub = [views[i] for i in idx]
        per_role = role_regions(sub, [footage[i] for i in idx], {k: [o[i] for i in idx] for k, o in outs.items()},
                                roles, head_region)
        for role, r in per_role.items():
            preds: dict[str, list] = {}
            for i in idx:
                if roles.get(views[i].camera_id, "static") != role:
                    continue
                for name, region in (view_regions(views[i], head_region) or {}).items():
                    preds.setdefault(name, []).append(predicted(views[i], noise_free[i], sensors[views[i].camera_id],
                                                                region))
            r["predicted"] = {name: {"psnr": _mean([p[0] for p in ps]), "detail": _mean([p[1] for p in ps])}
                              for name, ps in preds.items()}
        result[which] = per_role
    return result


def _mean(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return round(float(np.mean(vals)), 4) if vals else None


def measure(seg: Segment, views: Sequence[View], *, supersample: int = 2, seed: int = 1) -> dict:
    """:func:`ceiling` of ``views`` of ``seg`` (footage loaded, recordings rendered here)."""
    footage = [v.load()[..., :3] for v in views]
    noise_free, redrawn = recordings(views, seg.world, seg.cameras, supersample=supersample, seed=seed)
    sensors = {c: capture_sensor(seg.cameras, c) for c in {v.camera_id for v in views}}
    return ceiling(views, footage, noise_free, redrawn, seg.roles, seg.held_out, sensors, seg.head_region)


def run(store: str = DEMO_STORE, capture: str = DEMO_CAPTURE, calibration: str | None = None,
        segment: tuple[int, int] = DEMO_SEGMENT, frames: Sequence[int] = FRAMES, held_out: Sequence[str] | None = None,
        supersample: int = 2, seed: int = 1) -> dict:
    """The bench (module doc): ``scored`` (``score_segment``'s views) and ``cameras`` (each camera at
    ``frames``: camera -> :func:`ceiling` of its views)."""
    t0 = time.perf_counter()
    seg = Segment(store, capture, calibration, segment, held_out)
    out = {"store": store, "capture": seg.name, "segment": list(seg.data.frames), "held_out": seg.held_out,
           "supersample": supersample, "frames": list(frames),
           "scored": measure(seg, seg.scored_views(), supersample=supersample, seed=seed), "cameras": {}}
    at = seg.views_at(frames)
    for cam in seg.data.camera_ids:
        views = [v for v in at if v.camera_id == cam]
        if views:
            out["cameras"][cam] = measure(seg, views, supersample=supersample, seed=seed)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    return out


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def table(result: dict) -> list[str]:
    """Markdown: per view set and role, then per camera, the noise-free recording's PSNR and detail
    on the performers and faces, the noise model's predictions, and the redrawn check's detail."""
    head = ("| {what} | views | performers PSNR (predicted) | **performers detail** (predicted) | redrawn detail "
            "| faces PSNR (predicted) | **faces detail** (predicted) | redrawn detail |")
    rule = "|---|---|---|---|---|---|---|---|"

    def row(label: str, r: dict) -> str:
        cells = [label, str(r["noise_free"]["performers"]["views"])]
        for region in ("performers", "face"):
            nf, rd, pr = r["noise_free"].get(region), r["redrawn"].get(region), r["predicted"].get(region)
            if nf is None:
                cells += ["-", "-", "-"]
                continue
            cells += [f"{_fmt(nf['psnr'], '.1f')} ({_fmt(pr['psnr'], '.1f')})",
                      f"**{_fmt(nf['detail'], '.3f')}** ({_fmt(pr['detail'], '.3f')})", _fmt(rd["detail"], ".3f")]
        return "| " + " | ".join(cells) + " |"

    lines = [head.format(what="views scored (view set, role)"), rule]
    for which in ("training", "held_out"):
        for role, r in result["scored"].get(which, {}).items():
            lines.append(row(f"{which.replace('_', '-')} {role} ({', '.join(r['cameras'])})", r))
    lines += ["", head.format(what=f"camera (frames {', '.join(map(str, result['frames']))})"), rule]
    for cam, per_set in result["cameras"].items():
        for which, per_role in per_set.items():
            for role, r in per_role.items():
                lines.append(row(f"{cam} ({'held-out' if which == 'held_out' else 'training'} {role})", r))
    return lines


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--store", default=DEMO_STORE, help="the store (read only; default: the demo's)")
    p.add_argument("--capture", default=DEMO_CAPTURE, help="capture ref name or digest")
    p.add_argument("--calibration", default=None, help="calibration ref or digest (default: demo/segment's)")
    p.add_argument("--segment", type=int, nargs=2, default=list(DEMO_SEGMENT), metavar=("A", "B"),
                   help="take frames [A, B) of the segment")
    p.add_argument("--frames", type=int, nargs="+", default=list(FRAMES), help="frames of the per-camera table")
    p.add_argument("--held-out", nargs="+", default=None, help="held-out cameras (default: the demo preset's)")
    p.add_argument("--supersample", type=int, default=2, help="the capture's samples per pixel side (volcap synth: 2)")
    p.add_argument("--seed", type=int, default=1, help="the redrawn noise's seed")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = p.parse_args(argv)
    result = run(a.store, a.capture, a.calibration, tuple(a.segment), a.frames, a.held_out, a.supersample, a.seed)
    print(f"{result['capture']} frames {result['segment'][0]}:{result['segment'][1]}, held out "
          f"{', '.join(result['held_out'])}: the noise-free recording against the footage ({result['wall_s']} s)")
    print("\n".join(table(result)))
    if a.json is not None:
        a.json.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
