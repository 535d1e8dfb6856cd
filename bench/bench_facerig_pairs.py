"""The Face Rig pairs benchmark (issue 29): Gaussian-splat pairs of a Scene Rig actor, checked, timed,
and the enhancer trained on them beside the one trained on interim pairs.

    python bench/bench_facerig_pairs.py --workdir W --json W/facerig_pairs.json \\
        --sheet docs/img/facerig_pairs.png                 # hours on a CPU; a rerun resumes
    python bench/bench_facerig_pairs.py --quick            # smoke run (< 4 min), numbers meaningless

Stages, in order (each a cached volcap flow or task: a rerun with the same ``--workdir`` recomputes
nothing that finished; the JSON is written after every stage, ``finished`` listing them):

``scene``
    the Scene Rig capture (``demo_scene``, every camera's pixels ``render_scale`` times finer:
    ``bench_enhance.scaled_rig``), ingested and reconstructed as the demo reconstructs its own (the
    estimated calibration, one segment of every frame, the ``preset``'s training).
``pairs``
    the Face Rig capture of the Scene Rig's actor 0 (``synthesize_face_capture(actor_of=...)``,
    ``demo_face`` scaled the same way, as many frames as the pairs' sub-sequences end to end), the
    LQ range measured in the scene segment (``lq-range``), and the ``facerig_pairs`` flow with the
    capture's ground-truth calibration (a spec's ``face_calibration: ground-truth``) exactly as the
    splat production below calls it (so that production finds it cached); then ``lq_counts``
    further LQ models of sub-sequence 0 at counts spread over the range. Time and peak memory per
    task kind (models = ``train-segment``, paths = ``face-paths``, renders = ``render-pairs``,
    dataset = ``pair-dataset``).
``checks``
    on the pairs (nothing trained; recomputed on every run, from the store):
    the LQ worse than the HQ on the Face Rig's held-out camera(s) (the cameras the pair models were
    not trained on: ``reconstruction.default_held_out``): each model's held-out PSNR / SSIM, whole
    frame and face region, against that camera's footage as ``train-segment`` scores them
    (``splat.scoring``), beside the empty model's on the same pixels, for the HQ and every LQ count;
    the LQ's rendered flow against zero flow and OpenCV DIS (``enhance.metrics.warp_error``, over
    the pixels the LQ draws whose samples all three flows keep inside the previous frame:
    :func:`flow_warp_errors`; on the LQ frames and on the HQ frames, as ``tests/enhance/
    test_splat_pairs.py`` checks it); the detail of the LQ pair renders (``image_metrics.detail``,
    LQ over HQ on the HQ's silhouette, display sRGB) beside the Scene Rig's (the scene segment's
    held-out face detail against its footage, and the close-up render's face detail against the
    truth once a production ran); a contact sheet of pairs (``--sheet``).
``enhancer-splat``, ``enhancer-interim``
    the demo's close-up production (``flows/demo.py`` ``closeup_production``) twice, with
    ``pair_method`` splat and interim, the same enhancer run (``ENHANCER_RUNS[enhancer]``), each
    scored by ``score-shot`` against the truth beside the unenhanced render. The longest stage.

Sizes: the full run: the demo preset, ``render_scale`` 2 (640×360 cameras: every Scene Rig camera,
the Face Rig's 8), 8 take frames, the ``long`` enhancer run (3 Face Rig sub-sequences of 8 frames, 6
paths each at 256 px), HQ models of 20 000 Gaussians a frame or ``HQ_OVER_LQ`` times the measured
LQ high end if more, 3 LQ counts. ``--quick``: the test preset on 320×180 cameras (the demo rig's 8
static cameras, 4 take frames; Face Rig cameras F000, F002, F004, F006), 2 sub-sequences of 4
frames, 2 paths each at 64 px, HQ 2 000 Gaussians a frame, the tiny enhancer (``demo`` run): every
stage, numbers meaningless.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

FULL = {"render_scale": 2, "frames": 8, "cameras": None, "supersample": 2, "face_cameras": None, "preset": "demo",
        "enhancer": "long", "overrides": {"face_hq_gaussians_per_frame": 20_000}, "lq_counts": 3,
        "sheet_sequences": 6}
QUICK = {"render_scale": 1, "frames": 4, "cameras": [f"S00{i}" for i in range(8)], "supersample": 1,
         "face_cameras": ["F000", "F002", "F004", "F006"], "preset": "test", "enhancer": "demo",
         "overrides": {"face_camera_paths": 2, "pair_resolution": 64, "face_hq_gaussians_per_frame": 2_000},
         "lq_counts": 3, "sheet_sequences": 4}
#: the Scene Rig actor the Face Rig captures and the close-up shows (the demo's)
ACTOR_INDEX = 0
#: the HQ model's Gaussians a frame are at least this many times the measured LQ range's high end
#: (the paper's 1 M against 50-200 k: 5 to 20 times), above the settings' floor
HQ_OVER_LQ = 5
#: the stages in order
STAGES = ("scene", "pairs", "checks", "enhancer-splat", "enhancer-interim")


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


class RssSampler:
    """The process's resident memory (``VmRSS``), sampled every ``period_s`` in a thread, so that a
    stage's peak can be read off the samples inside its time window (``peak_mb``)."""

    def __init__(self, period_s: float = 0.25):
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(period_s,), daemon=True)
        self._thread.start()

    @staticmethod
    def rss_mb() -> float:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        return float("nan")

    def _run(self, period_s: float) -> None:
        while not self._stop.is_set():
            self.samples.append((time.time(), self.rss_mb()))
            self._stop.wait(period_s)

    def peak_mb(self, windows: list[tuple[float, float]]) -> float | None:
        """The largest sample inside any of ``windows`` (epoch seconds), None when none falls there."""
        inside = [mb for t, mb in list(self.samples) if any(a <= t <= b for a, b in windows)]
        return round(max(inside), 1) if inside else None

    def stop(self) -> None:
        self._stop.set()


def task_kinds(flow_run_id: str, sampler: RssSampler) -> dict[str, Any]:
    """Per task name (``train-segment``, ``face-paths``, ...) of a flow run and its sub-flows: how
    many task runs, their summed wall time, and the process's peak RSS while any of them ran (the
    map fans tasks out in threads: a peak can include a concurrent task of another kind)."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId

    from flows.runtime import flow_run_family

    with get_client(sync_client=True) as client:
        runs = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=flow_run_family(flow_run_id))))
    out: dict[str, Any] = {}
    for r in runs:
        if r.start_time is None or r.end_time is None:
            continue
        kind = re.sub(r"-[0-9a-f]{3}$", "", r.name)           # Prefect names a run <task>-<3 hex>
        k = out.setdefault(kind, {"runs": 0, "wall_s": 0.0, "windows": []})
        k["runs"] += 1
        k["wall_s"] += (r.end_time - r.start_time).total_seconds()
        k["windows"].append((r.start_time.timestamp(), r.end_time.timestamp()))
    return {kind: {"runs": k["runs"], "wall_s": round(k["wall_s"], 1), "peak_rss_mb": sampler.peak_mb(k["windows"])}
            for kind, k in sorted(out.items())}


# ---------------------------------------------------------------------------------------------
# Stages


def scene_stage(workdir: Path, store: str, settings: dict) -> dict[str, Any]:
    """The Scene Rig capture, ingested and reconstructed (one segment of every frame)."""
    from bench_enhance import scaled_rig
    from flows.ingest import ingest_flow
    from flows.reconstruct import reconstruct_flow
    from volcap_core.store import ArtifactStore
    from volcap_core.synth import synthesize_capture

    capture_dir = workdir / "scene"
    if not (capture_dir / "capture.json").exists():
        _log(f"synthesizing the Scene Rig capture ({settings['frames']} frames, x{settings['render_scale']} pixels)")
        synthesize_capture(capture_dir, rig=str(scaled_rig(workdir / "rigs", "demo_scene", settings["render_scale"])),
                           seed=0, frames=settings["frames"], supersample=settings["supersample"],
                           cameras=settings["cameras"])
    capture = ingest_flow(store=store, capture_dir=str(capture_dir))
    recon = reconstruct_flow(store=store, capture=capture.digest, frames=(0, settings["frames"]),
                             preset=settings["preset"])
    segment = ArtifactStore(store).resolve(recon["segments"][0]["model"]["digest"])
    return {"capture": capture.digest, "segment": segment.digest, "held_out_psnr": recon["segments"][0]["held_out_psnr"]}


def closeup_out(workdir: Path, method: str) -> Path:
    return workdir / f"closeup-{method}"


def face_capture_dir(workdir: Path, method: str, enhancer: str) -> Path:
    """Where ``closeup_production`` looks for (and else makes) its Face Rig capture."""
    return closeup_out(workdir, method) / ("face_capture" if enhancer == "demo" else f"face_capture_{enhancer}")


def overrides(settings: dict, method: str, hq: int | None = None) -> dict[str, Any]:
    """The preset fields both productions and the pairs stage run with: the settings' over the
    enhancer run's, ``pair_method`` and the HQ count (``hq``; None: the settings')."""
    return {**settings["overrides"], "pair_method": method,
            **({"face_hq_gaussians_per_frame": hq} if hq is not None else {})}


def quality(settings: dict, method: str, hq: int | None = None):
    from flows.demo import ENHANCER_RUNS
    from volcap_core.production.presets import named_preset

    return named_preset(settings["preset"]).with_overrides(**{**ENHANCER_RUNS[settings["enhancer"]],
                                                              **overrides(settings, method, hq)})


def pairs_stage(workdir: Path, store: str, settings: dict, scene: dict) -> dict[str, Any]:
    """The Face Rig capture, the measured LQ range, the pair dataset, and the extra LQ models."""
    import numpy as np

    from bench_enhance import scaled_rig
    from flows.facerig_pairs import facerig_pairs_flow
    from flows.ingest import ingest_flow
    from tasks.facerig import measured_lq_range
    from tasks.reconstruct import train_segment_task
    from volcap_core.reconstruction import SegmentModel
    from volcap_core.store import ArtifactStore
    from volcap_core.synth import synthesize_face_capture

    s = ArtifactStore(store)
    q = quality(settings, "splat")
    face_dir = face_capture_dir(workdir, "splat", settings["enhancer"])
    frames = q.face_subsequences * q.face_subsequence_frames
    if not (face_dir / "capture.json").exists():
        _log(f"synthesizing the Face Rig capture of Scene Rig actor {ACTOR_INDEX} ({frames} frames)")
        # as closeup_production makes it, so that the production reuses it
        synthesize_face_capture(face_dir, rig=str(scaled_rig(workdir / "rigs", "demo_face", settings["render_scale"])),
                                seed=0, actor_of=(workdir / "scene", ACTOR_INDEX), frames=frames, write_depth=True,
                                cameras=settings["face_cameras"])
    face = ingest_flow(store=store, capture_dir=str(face_dir))
    seg_ref = s.resolve(scene["segment"])
    seg = s.get_record(seg_ref, SegmentModel)
    measurement = measured_lq_range(store, [seg_ref], [list(seg.frames)], ACTOR_INDEX)
    measured = s.get_json(measurement)
    lq_range = (measured["low"], measured["high"])
    hq = max(q.face_hq_gaussians_per_frame, -(-HQ_OVER_LQ * lq_range[1] // 1000) * 1000)
    q = quality(settings, "splat", hq)
    _log(f"LQ range measured in the scene segment: {lq_range[0]}-{lq_range[1]} Gaussians a frame; HQ {hq}; the pairs")
    out = facerig_pairs_flow(store=store, capture=face.digest, actor=f"actor{ACTOR_INDEX}", quality=q,
                             ground_truth=True, lq_range=lq_range, lq_range_source="measured",
                             lq_measurement=measurement.digest)
    # more LQ counts of sub-sequence 0, spread over the range, trained as the flow trains its own
    first = out["subsequences"][0]
    held = s.get_record(first["hq"], SegmentModel).held_out_cameras
    counts = sorted({int(round(n)) for n in np.linspace(lq_range[0], lq_range[1], settings["lq_counts"])})
    window = first["frames"]
    extra = {}
    for n in counts:
        _log(f"LQ model of sub-sequence 0 at {n} Gaussians a frame")
        extra[n] = train_segment_task(store, face, out["calibration"], out["points"], [window[0], window[-1] + 1],
                                      q.train_config(held_out=list(held), max_gaussians=n * len(window)), 0).digest
    return {"face_capture": face.digest, "lq_range": list(lq_range), "hq_gaussians_per_frame": hq, "lq_measurement": measurement.digest,
            "dataset": out["dataset"].digest, "sequences": out["sequences"],
            "subsequences": [{"frames": x["frames"], "hq": x["hq"].digest, "lq": x["lq"].digest,
                              "lq_gaussians": x["lq_gaussians"]} for x in out["subsequences"]],
            "lq_models_subsequence_0": {str(n): d for n, d in extra.items()}}


def held_out_figures(seg) -> dict[str, Any]:
    """A trained segment's held-out scores beside the empty model's on the same pixels: whole frame
    (PSNR, SSIM) and, per camera role, the face region (PSNR, SSIM, detail)."""
    h = seg.scores.get("held_out", {})
    out = {"cameras": list(seg.held_out_cameras), "gaussians": seg.gaussians,
           "psnr": h.get("trained", {}).get("psnr"), "ssim": h.get("trained", {}).get("ssim"),
           "empty_psnr": h.get("empty", {}).get("psnr"), "empty_ssim": h.get("empty", {}).get("ssim")}
    for role, models in seg.scores.get("regions", {}).get("held_out", {}).items():
        face = {m: models.get(m, {}).get("face") or {} for m in ("trained", "empty")}
        out[f"face_{role}"] = {"psnr": face["trained"].get("psnr"), "ssim": face["trained"].get("ssim"),
                               "detail": face["trained"].get("detail"), "empty_psnr": face["empty"].get("psnr"),
                               "empty_ssim": face["empty"].get("ssim")}
    return out


def _mean(xs):
    import numpy as np

    xs = [x for x in xs if x is not None and np.isfinite(x)]
    return round(float(np.mean(xs)), 6) if xs else None


#: the flows the check compares, by name (module doc)
FLOWS = ("rendered", "zero", "dis")


def flow_warp_errors(frames, flows: dict[str, Any], drawn) -> dict[str, float | None]:
    """Each flow's ``enhance.metrics.warp_error`` of ``frames`` (``[T, C, H, W]``; ``flows[name]``:
    ``[T - 1, 2, H, W]`` backward flows) over **one set of pixels**: those ``drawn`` (``[T - 1, 1,
    H, W]``) whose sample every flow keeps inside frame ``t - 1``. ``warp_error`` alone scores each
    flow on its own in-frame pixels, so a flow that sends most pixels out of the frame is scored
    on the few it keeps while the others are scored on all of them. Also ``in_frame_<name>``: the
    fraction of the drawn pixels each flow keeps in frame, and ``scored``: the fraction scored."""
    import torch

    from volcap_core.enhance.metrics import warp_error
    from volcap_core.enhance.temporal import in_frame

    inside = {name: torch.stack([in_frame(f) for f in flow]) for name, flow in flows.items()}
    common = drawn.float()
    for m in inside.values():
        common = common * m
    total = float(drawn.sum())
    out: dict[str, float | None] = {name: warp_error(frames, flow, common) for name, flow in flows.items()}
    for name, m in inside.items():
        out[f"in_frame_{name}"] = round(float((m * drawn).sum()) / total, 4) if total else None
    out["scored"] = round(float(common.sum()) / total, 4) if total else None
    return out


def flow_checks(ds, get_bytes) -> list[dict[str, Any]]:
    """Per sequence of the pair dataset ``ds``: :func:`flow_warp_errors` of the LQ's rendered flow,
    zero flow and OpenCV DIS (run on the LQ frames) over the pixels the LQ draws, on the LQ frames
    (``lq``) and on the HQ frames (``hq``, what training warps)."""
    import torch

    from volcap_core.enhance.production import decode_splat_pair_sequence
    from volcap_core.enhance.temporal import DisFlow

    dis = DisFlow()
    out = []
    for q in ds.sequences:
        p = decode_splat_pair_sequence(q, get_bytes)
        drawn = (p.lq[1:, 3:4] > 0.5).float()
        flows = {"rendered": p.flow, "zero": torch.zeros_like(p.flow),
                 "dis": torch.stack([dis(p.lq[t, :3], p.lq[t + 1, :3]) for t in range(len(p) - 1)])}
        out.append({"sequence": q.name, "path_params": q.path_params,
                    **{what: flow_warp_errors(frames, flows, drawn) for what, frames in (("lq", p.lq), ("hq", p.hq))}})
    return out


def flow_summary(flows: list[dict[str, Any]], what: str) -> dict[str, Any]:
    """The means over the sequences of :func:`flow_checks` (``what``: "lq" or "hq") and on how many
    the rendered flow has the lower error."""
    out = {m: _mean([f[what][m] for f in flows]) for m in FLOWS + ("in_frame_rendered", "scored")}
    out["rendered_below_zero"] = f"{sum(f[what]['rendered'] < f[what]['zero'] for f in flows)}/{len(flows)}"
    out["rendered_below_dis"] = f"{sum(f[what]['rendered'] < f[what]['dis'] for f in flows)}/{len(flows)}"
    return out


def checks_stage(store: str, settings: dict, scene: dict, pairs: dict, sheet: Path | None,
                 closeups: dict[str, Any]) -> dict[str, Any]:
    """The checks on the pairs (module doc): held-out gap per LQ count, the flow, detail, the sheet."""
    from volcap_core.colour import srgb_encode
    from volcap_core.contact_sheet import SheetRow, contact_sheet, write_sheet
    from volcap_core.enhance.production import PairDataset, decode_splat_pair_sequence
    from volcap_core.enhance.temporal import in_frame, warp
    from volcap_core.image_metrics import detail
    from volcap_core.reconstruction import SegmentModel
    from volcap_core.store import ArtifactStore

    s = ArtifactStore(store)
    seg = lambda digest: s.get_record(s.resolve(digest), SegmentModel)  # noqa: E731
    first = pairs["subsequences"][0]
    held = {"hq": {"gaussians_per_frame": pairs["hq_gaussians_per_frame"],
                   **held_out_figures(seg(first["hq"]))},
            "lq": [{"gaussians_per_frame": int(n), **held_out_figures(seg(d))}
                   for n, d in sorted(pairs["lq_models_subsequence_0"].items(), key=lambda kv: int(kv[0]))]}
    for m in held["lq"]:        # the LQ's shortfall against the HQ on the same held-out pixels
        m["psnr_gap_to_hq_db"] = _gap(held["hq"].get("psnr"), m.get("psnr"))
        m["face_psnr_gap_to_hq_db"] = _gap(_face(held["hq"]).get("psnr"), _face(m).get("psnr"))
    held["every_subsequence"] = [{"frames": x["frames"], "hq": held_out_figures(seg(x["hq"])),
                                  "lq": {"gaussians_per_frame": x["lq_gaussians"], **held_out_figures(seg(x["lq"]))}}
                                 for x in pairs["subsequences"]]

    ds = s.get_record(s.resolve(pairs["dataset"]), PairDataset)
    flows = flow_checks(ds, s.get_bytes)
    details, rows = [], []
    for k, q in enumerate(ds.sequences):
        p = decode_splat_pair_sequence(q, s.get_bytes)
        for t in range(len(p)):
            mask = p.hq[t, 3] > 0.5
            if mask.sum() > 16:
                details.append(detail(srgb_encode(p.lq[t, :3].permute(1, 2, 0)), srgb_encode(p.hq[t, :3].permute(1, 2, 0)),
                                      mask))
        if k < settings["sheet_sequences"]:
            t = len(p) // 2
            hq, lq = (x[t, :3].permute(1, 2, 0).numpy() for x in (p.hq, p.lq))
            rows.append(SheetRow(f"{q.name} frame {q.frames[t]}: HQ ({q.hq_gaussians}/frame) | LQ "
                                 f"({q.lq_gaussians}/frame) | LQ-HQ error", hq, lq, p.hq[t, 3].numpy()))
            moved = warp(p.hq[t - 1, :3], p.flow[t - 1]).permute(1, 2, 0).numpy()
            drawn = p.lq[t, 3] > 0.5
            lost = float((in_frame(p.flow[t - 1])[0] < 0.5)[drawn].float().mean()) if drawn.any() else 0.0
            rows.append(SheetRow(f"{q.name} flow: HQ frame {q.frames[t]} | HQ frame {q.frames[t - 1]} warped by the "
                                 f"LQ's rendered flow (black: sampled outside the frame, {lost:.0%} of the LQ's pixels) "
                                 "| warp error", hq, moved, p.lq[t, 3].numpy()))

    scene_seg = held_out_figures(seg(scene["segment"]))
    detail_side = {"lq_pairs_vs_hq": _mean(details), "lq_pair_frames": len(details),
                   "lq_models_held_out_face_vs_footage": {
                       str(x["gaussians_per_frame"]): _face_detail(x) for x in held["lq"]},
                   "hq_model_held_out_face_vs_footage": _face_detail(held["hq"]),
                   "scene_segment_held_out_face_vs_footage": _face_detail(scene_seg),
                   "closeup_render_face_vs_truth": {m: c["face"]["render"]["detail"] for m, c in closeups.items()}}
    result = {"held_out": held, "flow": {"lq_frames": flow_summary(flows, "lq"), "hq_frames": flow_summary(flows, "hq"),
                                        "sequences": flows},
              "detail": detail_side, "scene_segment_held_out": scene_seg,
              "dataset": {"sequences": len(ds.sequences), "split": ds.split, "lq_range": list(ds.lq_range),
                          "lq_range_source": ds.lq_range_source, "resolution": ds.resolution}}
    if sheet is not None and rows:
        sheet.parent.mkdir(parents=True, exist_ok=True)
        write_sheet(sheet, contact_sheet(rows, title=f"Face Rig pairs of actor {ACTOR_INDEX}: LQ range "
                                         f"{list(ds.lq_range)} ({ds.lq_range_source})", truth_label="HQ"))
        result["sheet"] = str(sheet)
    return result


def _gap(hq: float | None, lq: float | None) -> float | None:
    return None if hq is None or lq is None else round(hq - lq, 3)


def _face(figures: dict) -> dict:
    """The face-region figures of :func:`held_out_figures`' first camera role ({} without masks)."""
    return next((v for k, v in figures.items() if k.startswith("face_") and isinstance(v, dict)), {})


def _face_detail(figures: dict) -> float | None:
    """The face-region detail of :func:`held_out_figures`' first camera role that has one."""
    for key, v in figures.items():
        if key.startswith("face_") and isinstance(v, dict) and v.get("detail") is not None:
            return round(float(v["detail"]), 4)
    return None


def enhancer_stage(workdir: Path, store: str, settings: dict, scene: dict, pairs: dict, method: str) -> dict[str, Any]:
    """The close-up production with ``method`` pairs, scored against the truth (``closeup_production``)."""
    from bench_enhance import scaled_rig
    from flows.demo import closeup_production
    from volcap_core.store import ArtifactStore

    s = ArtifactStore(store)
    out = closeup_out(workdir, method)
    out.mkdir(parents=True, exist_ok=True)
    face_dir = face_capture_dir(workdir, method, settings["enhancer"])
    shared = face_capture_dir(workdir, "splat", settings["enhancer"])
    if method != "splat" and not face_dir.exists() and (shared / "capture.json").exists():
        shutil.copytree(shared, face_dir)          # the same Face Rig capture, not synthesized twice
    result = closeup_production(store, workdir / "scene", out, capture_ref=s.resolve(scene["capture"]),
                                segment_ref=s.resolve(scene["segment"]), preset=settings["preset"],
                                enhancer=settings["enhancer"],
                                face_rig=scaled_rig(workdir / "rigs", "demo_face", settings["render_scale"]),
                                quality_overrides=overrides(settings, method, pairs["hq_gaussians_per_frame"]),
                                face_calibration="ground-truth" if method == "splat" else None)
    return result


# ---------------------------------------------------------------------------------------------
# The run


def run(workdir: Path, settings: dict, json_path: Path, sheet: Path | None, stop_after: str | None) -> dict:
    """Every stage in order, each in its own flow run; the JSON rewritten after each."""
    from prefect import flow

    from flows.runtime import run_flow
    from volcap_core.store import ArtifactStore

    workdir.mkdir(parents=True, exist_ok=True)
    store = ArtifactStore(str(workdir / "store")).url
    previous = json.loads(json_path.read_text()) if json_path.exists() else {}
    # an earlier run's figures stay until this run redoes their stage (a --stop-after rerun keeps the rest)
    result: dict[str, Any] = {**previous, "settings": settings, "workdir": str(workdir), "finished": [],
                              "stages": previous.get("stages", {}),
                              "machine": {"platform": platform.platform(), "python": platform.python_version()}}
    sampler = RssSampler()
    outputs: dict[str, Any] = {}

    def stage(name: str, fn, *args) -> Any:
        @flow(name=f"bench-facerig-pairs-{name}", persist_result=False)
        def one() -> Any:
            return fn(*args)

        _log(f"stage {name}")
        t0, e0 = time.perf_counter(), time.time()
        summary = run_flow(one)
        wall = time.perf_counter() - t0
        timing = {"wall_s": round(wall, 1), **{k: summary.counts()[k] for k in ("tasks_run", "tasks_cached")},
                  "peak_rss_mb": sampler.peak_mb([(e0, time.time())]),
                  "by_task": task_kinds(summary.flow_run_id, sampler)}
        old = result["stages"].get(name)
        if old and summary.tasks_run == 0 and old.get("tasks_run", 0) > 0:
            result["stages"][name] = {**old, "rerun": timing}    # the computing run's figures stand
        else:
            result["stages"][name] = timing
        result[name] = summary.result
        result["finished"].append(name)
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(result, indent=1, sort_keys=True, default=str))
        _log(f"stage {name} done: {summary.line()}")
        return summary.result

    try:
        outputs["scene"] = stage("scene", scene_stage, workdir, store, settings)
        outputs["pairs"] = stage("pairs", pairs_stage, workdir, store, settings, outputs["scene"])
        result["checks"] = _timed_checks(store, settings, outputs, sheet, {}, sampler, result, json_path)
        report_checks(result)
        if stop_after in ("pairs", "checks"):
            return result
        closeups = {}
        for method in ("splat", "interim"):
            closeups[method] = stage(f"enhancer-{method}", enhancer_stage, workdir, store, settings,
                                     outputs["scene"], outputs["pairs"], method)
            report_closeup(method, closeups[method])
        # the close-up render's face detail joins the detail comparison
        result["checks"] = _timed_checks(store, settings, outputs, sheet, closeups, sampler, result, json_path)
        result["enhancer_comparison"] = comparison(closeups)
        json_path.write_text(json.dumps(result, indent=1, sort_keys=True, default=str))
    finally:
        sampler.stop()
    return result


def _timed_checks(store, settings, outputs, sheet, closeups, sampler, result, json_path) -> dict:
    t0, e0 = time.perf_counter(), time.time()
    checks = checks_stage(store, settings, outputs["scene"], outputs["pairs"], sheet, closeups)
    result["stages"]["checks"] = {"wall_s": round(time.perf_counter() - t0, 1),
                                  "peak_rss_mb": sampler.peak_mb([(e0, time.time())])}
    result["checks"] = checks
    if "checks" not in result["finished"]:
        result["finished"].append("checks")
    json_path.write_text(json.dumps(result, indent=1, sort_keys=True, default=str))
    return checks


def comparison(closeups: dict[str, Any]) -> dict[str, Any]:
    """Face and performer rows of both productions side by side: the render (the same in both:
    one shot, one segment), the enhanced frames of each pair method, and the floors."""
    out: dict[str, Any] = {}
    for region in ("face", "performers"):
        rows = {f"enhanced ({m})": c[region]["enhanced"] for m, c in closeups.items() if "enhanced" in c[region]}
        any_c = next(iter(closeups.values()))
        out[region] = {"render": any_c[region]["render"], **rows,
                       **{k: any_c[region][k] for k in ("empty", "bicubic") if k in any_c[region]}}
    out["temporal"] = {m: c["temporal"] for m, c in closeups.items()}
    out["enhancer"] = {m: {"budget": c["enhancer_budget"], "pairs": c["enhancer_pairs"],
                           "train_s": c["enhancer_train_s"], "sheet": c["sheet"]} for m, c in closeups.items()}
    return out


def report_checks(result: dict) -> None:
    c = result["checks"]
    h = c["held_out"]

    def line(m: dict) -> str:
        face = _face(m)
        return (f"{m['psnr']} dB / SSIM {m['ssim']} (empty {m['empty_psnr']} dB); face {face.get('psnr')} dB "
                f"(empty {face.get('empty_psnr')}), detail {face.get('detail')}")

    _log(f"held out ({', '.join(h['hq']['cameras'])}), sub-sequence 0: HQ {h['hq']['gaussians_per_frame']}/frame "
         f"{line(h['hq'])}")
    for m in h["lq"]:
        _log(f"held out, sub-sequence 0: LQ {m['gaussians_per_frame']}/frame {line(m)}; below the HQ by "
             f"{m['psnr_gap_to_hq_db']} dB, face {m['face_psnr_gap_to_hq_db']} dB")
    for what in ("lq_frames", "hq_frames"):
        f = c["flow"][what]
        _log(f"flow, warp error on the {what.replace('_', ' ')}: rendered {f['rendered']}, zero {f['zero']}, DIS "
             f"{f['dis']} (rendered below zero in {f['rendered_below_zero']}, below DIS in {f['rendered_below_dis']}; "
             f"scored on {f['scored']} of the drawn pixels, the rendered flow keeping {f['in_frame_rendered']} in frame)")
    d = c["detail"]
    _log(f"detail: LQ pairs / HQ {d['lq_pairs_vs_hq']} over {d['lq_pair_frames']} frames; held-out face vs footage: "
         f"LQ models {d['lq_models_held_out_face_vs_footage']}, HQ {d['hq_model_held_out_face_vs_footage']}, "
         f"Scene Rig segment {d['scene_segment_held_out_face_vs_footage']}; close-up render vs truth "
         f"{d['closeup_render_face_vs_truth'] or '(after the enhancer stages)'}")
    if "sheet" in c:
        _log(f"sheet {c['sheet']}")


def report_closeup(method: str, r: dict) -> None:
    for region in ("face", "performers"):
        _log(f"{method} {region}: " + "; ".join(f"{row} {f['psnr']} dB / SSIM {f['ssim']} / detail {f['detail']}"
                                                 for row, f in r[region].items()))
    _log(f"{method}: {r['enhancer_pairs']}; {r['enhancer_budget']}")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run (< 4 min): every stage, numbers meaningless")
    ap.add_argument("--workdir", type=Path, help="captures, store and outputs (kept; a rerun resumes from them)")
    ap.add_argument("--json", type=Path, help="the figures (default: WORKDIR/facerig_pairs.json), after every stage")
    ap.add_argument("--sheet", type=Path, help="the contact sheet of pairs (PNG)")
    ap.add_argument("--stop-after", choices=("pairs", "checks"), help="skip the enhancer comparison")
    args = ap.parse_args(argv)
    settings = dict(QUICK if args.quick else FULL)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench-facerig-pairs-"))
    json_path = args.json or workdir / "facerig_pairs.json"
    t0 = time.perf_counter()
    result = run(workdir, settings, json_path, args.sheet, args.stop_after)
    result["total_s"] = round(time.perf_counter() - t0, 1)
    json_path.write_text(json.dumps(result, indent=1, sort_keys=True, default=str))
    _log(f"stages finished: {', '.join(result['finished'])}; {result['total_s']} s; figures {json_path}")
    return result


if __name__ == "__main__":
    main()
