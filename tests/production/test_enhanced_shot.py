"""Enhanced shots in the production flow: face pairs, actor prompts, the enhancer, enhanced frames.

The end-to-end test runs a tiny spec in one process: one capture of six of the demo rig's static
cameras (four frames; the static solve grows with the cameras) that also stands for the actor's
Face Rig capture (so its ingest and calibration are shared), two shots over it, one with
``enhance: true``; the tiny enhancer of the ``test`` preset.
"""

from __future__ import annotations

import io

import numpy as np
import OpenEXR
import pytest
import torch
import yaml

from flows.production import open_production, plan_production, production_flow
from flows.runtime import run_flow
from volcap_core.enhance.production import (EnhanceSettings, EnhancerModel, FacePairSet, decode_pair_sequence,
                                            encode_enhanced_frame, encode_pair_sequence, enhance_shot_frames,
                                            face_windows, head_window, read_shot_frame, square_window)
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture

STATIC = [f"S00{i}" for i in range(6)]


def _exr(data: bytes) -> tuple[dict, np.ndarray]:
    f = OpenEXR.File(io.BytesIO(data))
    return dict(f.header()), f.channels()["RGBA"].pixels


def _shot(**kw):
    shot = {"name": "orbit", "performance": "demo", "frames": [0, 4], "fps": 24, "resolution": [64, 36],
            "sensor_mm": 36,
            "keyframes": [{"frame": 0, "position": [5.0, -2.0, 1.8], "look_at": [0.0, 0.0, 1.0], "focal_mm": 24},
                          {"frame": 3, "position": [5.0, 2.0, 1.8], "look_at": [0.0, 0.0, 1.0], "focal_mm": 28}]}
    shot.update(kw)
    return shot


# ---------------------------------------------------------------------------------------------
# Fast: the pair-set artifact, the windows, the EXR


def test_a_pair_sequence_round_trips_as_half_float_with_its_group():
    g = torch.Generator().manual_seed(0)
    lq, hq = torch.rand(3, 4, 16, 24, generator=g), torch.rand(3, 4, 16, 24, generator=g) * 3
    flow = torch.randn(2, 2, 16, 24, generator=g)
    data = encode_pair_sequence(lq, hq, flow, {"camera": "F001"})
    assert data == encode_pair_sequence(lq, hq, flow, {"camera": "F001"})     # same tensors, same bytes
    ps = decode_pair_sequence(data, "anna/w000-F001", group="anna")
    assert ps.lq.dtype == torch.float32 and ps.lq.shape == (3, 4, 16, 24) and ps.name == "anna/w000-F001"
    assert torch.equal(ps.lq, lq.half().float()) and torch.equal(ps.hq, hq.half().float())
    assert torch.equal(ps.flow, flow) and ps.group == "anna"
    assert decode_pair_sequence(encode_pair_sequence(lq, hq)).flow is None
    with pytest.raises(ValueError, match="not a pair sequence"):
        from volcap_core.checkpoint import safetensors_bytes

        decode_pair_sequence(safetensors_bytes({"x": lq}, {"format": "other"}))


def test_face_windows_spread_over_the_take_and_square_crops_follow_the_performer():
    assert face_windows(20, 3, 4) == [[0, 1, 2, 3], [8, 9, 10, 11], [16, 17, 18, 19]]
    assert face_windows(4, 2, 4) == [[0, 1, 2, 3]]           # one window fits: no duplicate
    assert face_windows(3, 2, 8) == [[0, 1, 2]]              # a short take: all of it
    alpha = np.zeros((40, 100), np.float32)
    alpha[10:20, 80:90] = 1.0
    assert square_window(alpha) == (0, 60, 40)               # centred on the performer, inside the frame
    assert square_window(np.zeros((40, 100), np.float32)) == (0, 30, 40)


def test_a_head_window_holds_the_head_at_the_capture_pixels_over_every_frame():
    # a performer whose head top is at row 30 in frame 0 and row 24 in frame 1, centred on column 70
    alpha = np.zeros((2, 120, 160), np.float32)
    alpha[0, 30:120, 60:80] = 1.0
    alpha[1, 24:120, 62:78] = 1.0
    assert head_window(alpha, 64) == (8, 38)                # 16 px above the highest head top, centred
    assert head_window(alpha, 64, below_top=0) == (24, 38)
    assert head_window(alpha[:, :40], 40) == (0, 50)        # clamped inside the frame
    assert head_window(np.zeros((1, 120, 160), np.float32), 64) == (28, 48)   # nobody: the centre


def test_head_window_pairs_are_cut_at_the_capture_pixels_and_performer_ones_resized():
    """``pair_window: head`` cuts the HQ of each pair out of the frames without resampling (the
    enhancer bench's pairs); ``performer`` resizes the largest square on the performer."""
    from types import SimpleNamespace

    from volcap_core.enhance.production import PairDegradation, face_pairs_from_capture
    from volcap_core.imageio.write import encode_exr

    rng = np.random.default_rng(0)
    frames, blobs = [], {}
    for f in range(4):
        px = np.zeros((96, 160, 4), np.float32)
        px[..., :3] = rng.uniform(0.1, 1.0, (96, 160, 3)).astype(np.float16)     # exact in half
        px[30:, 70:100, 3] = 1.0                                                # head top at row 30
        frames.append(px)
        blobs[f"F000/{f}"] = encode_exr(px)
    cam = SimpleNamespace(id="F000", frames=[f"F000/{f}" for f in range(4)])
    capture = SimpleNamespace(name="face", cameras=[cam], frame_count=4)
    kw = dict(subsequences=1, subsequence_frames=4, camera_paths=1, degradation=PairDegradation())
    [(name, camera, take, pairs)] = face_pairs_from_capture(capture, blobs.__getitem__, resolution=64,
                                                             window="head", **kw)
    assert (camera, take, tuple(pairs.hq.shape)) == ("F000", [0, 1, 2, 3], (4, 4, 64, 64))
    y0, x0 = 14, 52                                       # 16 px above the head top, centred on columns 70-99
    want = torch.from_numpy(np.stack(frames)[:, y0:y0 + 64, x0:x0 + 64]).permute(0, 3, 1, 2)
    want = torch.cat([want[:, :3] * want[:, 3:], want[:, 3:]], dim=1)     # premultiplied by the coverage
    assert torch.equal(pairs.hq, want)
    [(*_, resized)] = face_pairs_from_capture(capture, blobs.__getitem__, resolution=64, window="performer", **kw)
    assert tuple(resized.hq.shape) == (4, 4, 64, 64) and not torch.equal(resized.hq, want)


def test_the_long_demo_enhancer_trains_with_the_enhancer_bench_recipe():
    """``volcap demo --enhancer-preset long`` (and bench/bench_closeup.py) promise the enhancer
    bench's recipe through a production's preset fields: the same EnhancerTrainConfig as the
    bench builds from its FULL settings, apart from checkpoints (which do not change training)."""
    import importlib.util
    from pathlib import Path

    from flows.demo import ENHANCER_RUNS
    from volcap_core.enhance.training import EnhancerTrainConfig
    from volcap_core.production.presets import named_preset

    path = Path(__file__).resolve().parents[2] / "bench" / "bench_enhance.py"
    spec = importlib.util.spec_from_file_location("bench_enhance", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    s = bench.FULL
    q = named_preset("demo").with_overrides(**ENHANCER_RUNS["long"])
    want = EnhancerTrainConfig(steps=s["steps"], lr=s["lr"], warmup_steps=min(50, s["steps"] // 10),
                               lr_decay=((max(1, round(s["steps"] * s["lr_decay_at"])), s["lr_decay"]),),
                               batch=s["batch"], crop=s["crop"], finetune="full", vae_steps=s["vae_steps"],
                               vae_lr=s["vae_lr"], vae_batch=s["vae_batch"], vae_crop=s["vae_crop"],
                               vae_stages=tuple(tuple(x) for x in s["vae_stages"]), seed=0)
    got = q.enhancer_train_config().model_copy(update={"checkpoint_every": want.checkpoint_every})
    assert got == want
    assert (q.pair_window, q.pair_resolution, q.enhancer_architecture) == ("head", s["size"], "small")
    assert (q.enhancer_sampling_steps, q.enhancer_strength, q.enhancer_tile) == (s["sample_steps"], s["strength"],
                                                                                s["crop"])
    assert q.face_subsequences * q.face_subsequence_frames == s["frames"]


def _shot_frame(rgba: np.ndarray, window=(2, 3, 9, 7), *, frame: int = 3, flow: np.ndarray | None = None) -> bytes:
    """A frame as render-shot writes it: a cropped data window, metadata of every type, and the
    exact flow ``[H, W, 2]`` in ``flow.x``/``flow.y`` when given."""
    x0, y0, x1, y1 = window
    h, w = rgba.shape[:2]
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "dataWindow": (np.array([x0, y0], np.int32), np.array([x1, y1], np.int32)),
              "displayWindow": (np.array([0, 0], np.int32), np.array([w - 1, h - 1], np.int32)),
              "volcap.shot": "cu", "volcap.frame": frame, "volcap.time": np.array([0.125]),
              "volcap.K": np.eye(3), "volcap.empty": 0}
    crop = rgba[y0:y1 + 1, x0:x1 + 1].astype(np.float16)
    planes = {c: np.ascontiguousarray(crop[..., i]) for i, c in enumerate("RGBA")}
    if flow is not None:
        for i, c in enumerate(("flow.x", "flow.y")):
            planes[c] = np.ascontiguousarray(flow[y0:y1 + 1, x0:x1 + 1, i].astype(np.float16))
    buf = io.BytesIO()
    OpenEXR.File(header, planes).write(buf)
    return buf.getvalue()


def test_an_enhanced_frame_keeps_the_render_header_and_crop():
    rgba = np.zeros((12, 16, 4), np.float32)
    rgba[3:8, 2:10] = [0.5, 0.25, 0.125, 1.0]
    header, full = read_shot_frame(_shot_frame(rgba))
    assert full.shape == (12, 16, 4) and np.array_equal(full, rgba)       # placed in the display window
    out = encode_enhanced_frame(full * 2, header, {"volcap.enhanced": 1, "volcap.enhancer": "blake3:x",
                                                   "volcap.gain": 0.5})
    h2, px = _exr(out)
    assert px.dtype == np.float16 and px.shape == (5, 8, 4)
    assert np.array_equal(px.astype(np.float32), (rgba * 2)[3:8, 2:10])
    assert [tuple(v) for v in h2["dataWindow"]] == [(2, 3), (9, 7)]
    assert h2["volcap.shot"] == "cu" and h2["volcap.frame"] == 3 and float(h2["volcap.time"][0]) == 0.125
    assert np.array_equal(h2["volcap.K"], np.eye(3)) and h2["volcap.enhanced"] == 1
    assert h2["volcap.enhancer"] == "blake3:x" and float(h2["volcap.gain"][0]) == 0.5
    with pytest.raises(ValueError, match="display window"):
        encode_enhanced_frame(full[:4], header, {})


def test_shot_frames_are_enhanced_in_order_with_alpha_in_range():
    from volcap_core.enhance.model import EnhancerConfig, build_enhancer

    model = build_enhancer(EnhancerConfig.tiny(), seed=0)
    frames = []
    for t in range(3):
        rgba = np.zeros((20, 24, 4), np.float32)
        rgba[4 + t:14 + t, 5:15] = [0.4, 0.3, 0.2, 1.0]
        frames.append((f"{t:06d}.exr", _shot_frame(rgba, (3, 2, 18, 17))))
    settings = EnhanceSettings(steps=2, tile=None, vae_tiling=False)
    out = list(enhance_shot_frames(model, frames, settings, group="anna", model_digest="blake3:m"))
    assert [n for n, _ in out] == [n for n, _ in frames]
    for t, (_, data) in enumerate(out):
        header, px = _exr(data)
        a = px[..., 3].astype(np.float32)
        assert np.isfinite(px.astype(np.float32)).all() and a.min() >= 0 and a.max() <= 1
        assert px[..., :3].min() >= 0
        assert header["volcap.enhanceSeed"] == t and header["volcap.lqFrame"] == f"{t:06d}.exr"
    again = list(enhance_shot_frames(model, frames, settings, group="anna", model_digest="blake3:m"))
    assert again == out                                                # deterministic


def test_the_rendered_flow_is_read_and_used_and_dis_only_where_a_frame_has_none(monkeypatch):
    """``flow="rendered"`` (the default) conditions a frame on the exact flow it carries, without
    running DIS; a frame without flow (a segment boundary) falls back to DIS; the header says which."""
    import volcap_core.enhance.temporal as temporal
    from volcap_core.enhance.model import EnhancerConfig, build_enhancer
    from volcap_core.production.shot import FLOW_CHANNELS

    assert FLOW_CHANNELS == ("flow.x", "flow.y") and EnhanceSettings().flow == "rendered"
    window = (3, 2, 18, 17)
    frames, shifts = [], [None, (-1.0, 0.5), (-1.0, 0.5), None]           # frame 3: across a boundary
    for t, shift in enumerate(shifts):
        rgba = np.zeros((20, 24, 4), np.float32)
        rgba[4 + t:14 + t, 5:15] = [0.4, 0.3, 0.2, 1.0]
        flow = None if shift is None else np.broadcast_to(np.float32(shift), (20, 24, 2)).copy()
        frames.append((f"{t:06d}.exr", _shot_frame(rgba, window, frame=t, flow=flow)))
    header, full, flow = read_shot_frame(frames[1][1], with_flow=True)
    inside = np.zeros((20, 24), bool)
    inside[2:18, 3:19] = True
    assert np.array_equal(flow[inside], np.broadcast_to(np.float32([-1.0, 0.5]), (inside.sum(), 2)))
    assert not flow[~inside].any() and read_shot_frame(frames[0][1], with_flow=True)[2] is None
    assert len(read_shot_frame(frames[1][1])) == 2                         # the RGBA reader as before

    dis_calls, seen = [], []

    class CountingDis:
        def __init__(self, *args, **kwargs):
            pass

        def __call__(self, prev, cur):
            dis_calls.append(tuple(cur.shape))
            return torch.zeros(2, *cur.shape[-2:])

    condition = temporal.temporal_condition

    def spy(prev_output, prev_lq, cur_lq, flow, **kw):
        seen.append(flow)
        return condition(prev_output, prev_lq, cur_lq, flow, **kw)

    monkeypatch.setattr(temporal, "DisFlow", CountingDis)
    monkeypatch.setattr(temporal, "temporal_condition", spy)
    model = build_enhancer(EnhancerConfig.tiny(), seed=0)

    def run(**kw):
        dis_calls.clear()
        seen.clear()
        out = list(enhance_shot_frames(model, frames, EnhanceSettings(steps=1, tile=None, vae_tiling=False, **kw),
                                       group="anna", model_digest="blake3:m"))
        return [_exr(data)[0]["volcap.enhanceFlow"] for _, data in out]

    assert run() == ["none", "rendered", "rendered", "dis"]
    assert len(dis_calls) == 1 and isinstance(seen[2], CountingDis)         # DIS for frame 3 only
    for f in seen[:2]:
        assert isinstance(f, torch.Tensor) and f.shape == (2, 20, 24)
        assert torch.equal(f[:, 5, 10], torch.tensor([-1.0, 0.5]))
    assert run(flow="dis") == ["none", "dis", "dis", "dis"] and len(dis_calls) == 3
    assert run(flow="zero") == ["none", "zero", "zero", "zero"] and seen == [None] * 3 and not dis_calls


# ---------------------------------------------------------------------------------------------
# RAFT as a shot's flow: selected by the settings, its weights file a location


def _no_torchvision(monkeypatch):
    import sys

    for name in ("torchvision", "torchvision.models", "torchvision.models.optical_flow"):
        monkeypatch.setitem(sys.modules, name, None)                      # import raises ImportError


def test_raft_is_a_flow_setting_and_refused_clearly_before_any_frame(tmp_path, monkeypatch):
    """``flow="raft"`` without weights, with a missing file, a file changed since it was
    fingerprinted, or without torchvision: an error naming the shot (and the file), raised before
    the first frame is even read."""
    from pydantic import ValidationError

    from volcap_core.enhance.production import directory_fingerprint, shot_flow_backend
    from volcap_core.enhance.temporal import FlowUnavailable

    assert EnhanceSettings(flow="raft").flow == "raft" and EnhanceSettings(flow="raft-small").flow == "raft-small"
    with pytest.raises(ValidationError):
        EnhanceSettings(flow="raft-large")
    raft = EnhanceSettings(flow="raft")
    with pytest.raises(ValueError, match=r"^shot cu: flow 'raft' needs a local RAFT weights file .*raft_large.*"
                                         r"set flow_weights"):
        shot_flow_backend(raft, None, shot="cu")
    missing = tmp_path / "missing.pth"
    with pytest.raises(FileNotFoundError, match=rf"^shot cu: flow 'raft': no RAFT weights file at {missing}$"):
        shot_flow_backend(raft, missing, shot="cu")
    weights = tmp_path / "raft.pth"
    weights.write_bytes(b"not a state dict")
    pinned = directory_fingerprint(weights)
    weights.write_bytes(b"other weights, longer")
    with pytest.raises(ValueError, match=rf"^shot cu: flow 'raft': the RAFT weights file {weights} changed"):
        shot_flow_backend(raft, weights, shot="cu", fingerprint=pinned)
    _no_torchvision(monkeypatch)
    with pytest.raises(FlowUnavailable, match=r"^shot cu: flow 'raft-small' needs torchvision, which is not "
                                              r"installed here: install .*pip install torchvision.*raft\.pth"):
        shot_flow_backend(EnhanceSettings(flow="raft-small"), weights, shot="cu",
                          fingerprint=directory_fingerprint(weights))

    read = []

    def frames():
        read.append(1)
        yield "000000.exr", b""

    shot_frames = enhance_shot_frames(None, frames(), raft, group="anna", model_digest="blake3:m", shot="cu")
    with pytest.raises(ValueError, match="^shot cu: flow 'raft' needs a local RAFT weights file"):
        next(shot_frames)
    assert not read                                                       # refused before the first frame


def test_raft_selection_hands_raft_flow_the_weights_and_is_used_for_every_frame(tmp_path, monkeypatch):
    """The back-end selection builds RaftFlow from the weights file (large or small), wraps a file
    that does not load, and enhance_shot_frames conditions every frame after the first through it
    (even one carrying rendered flow), recorded as ``raft``. RAFT itself is not run here: it needs
    torchvision (a stand-in records how it was built and returns zero flow)."""
    import sys
    import types

    import volcap_core.enhance.temporal as temporal
    from volcap_core.enhance.model import EnhancerConfig, build_enhancer
    from volcap_core.enhance.production import shot_flow_backend

    model = build_enhancer(EnhancerConfig.tiny(), seed=0)                # diffusers imported before the stand-in
    for name in ("torchvision", "torchvision.models", "torchvision.models.optical_flow"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))    # only the import check passes
    built, calls = [], []

    class RecordingRaft:
        def __init__(self, weights_path, *, small=False, device="cpu", **kw):
            if weights_path.name == "bad.pth":
                raise RuntimeError("Error(s) in loading state_dict for RAFT")
            built.append((weights_path, small, device))

        def __call__(self, prev, cur):
            calls.append(tuple(cur.shape))
            return torch.zeros(2, *cur.shape[-2:])

    monkeypatch.setattr(temporal, "RaftFlow", RecordingRaft)
    weights = tmp_path / "raft.pth"
    weights.write_bytes(b"weights")
    assert isinstance(shot_flow_backend(EnhanceSettings(flow="raft"), str(weights), shot="cu"), RecordingRaft)
    assert isinstance(shot_flow_backend(EnhanceSettings(flow="raft-small"), weights, shot="cu"), RecordingRaft)
    assert built == [(weights, False, "cpu"), (weights, True, "cpu")]
    assert isinstance(shot_flow_backend(EnhanceSettings(), None, shot="cu"), temporal.DisFlow)
    assert isinstance(shot_flow_backend(EnhanceSettings(flow="dis"), None, shot="cu"), temporal.DisFlow)
    assert shot_flow_backend(EnhanceSettings(flow="zero"), None, shot="cu") is None
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"weights")
    with pytest.raises(temporal.FlowUnavailable, match=rf"^shot cu: flow 'raft': the RAFT weights file {bad} does "
                                                       r"not load into torchvision's raft_large: Error\(s\) in loading"):
        shot_flow_backend(EnhanceSettings(flow="raft"), bad, shot="cu")

    frames = []
    for t in range(3):
        rgba = np.zeros((20, 24, 4), np.float32)
        rgba[4 + t:14 + t, 5:15] = [0.4, 0.3, 0.2, 1.0]
        flow = None if t == 0 else np.zeros((20, 24, 2), np.float32)
        frames.append((f"{t:06d}.exr", _shot_frame(rgba, (3, 2, 18, 17), frame=t, flow=flow)))
    settings = EnhanceSettings(steps=1, tile=None, vae_tiling=False, flow="raft")
    backend = shot_flow_backend(settings, weights, shot="cu")
    out = list(enhance_shot_frames(model, frames, settings, group="anna", model_digest="blake3:m",
                                   flow_backend=backend))
    assert [_exr(data)[0]["volcap.enhanceFlow"] for _, data in out] == ["none", "raft", "raft"]
    assert calls == [(3, 20, 24)] * 2                                    # RGB of each later frame


def test_the_enhance_shot_task_refuses_raft_before_anything_is_stored(prefect_api, tmp_path, monkeypatch):
    from prefect import flow

    from tasks.enhance import enhance_shot
    from volcap_core.enhance.production import directory_fingerprint
    from volcap_core.records import MEDIA_EXR

    s = ArtifactStore(str(tmp_path / "store"))
    rgba = np.zeros((12, 16, 4), np.float32)
    tree = s.put_tree({f"{t:06d}.exr": s.put_bytes(_shot_frame(rgba, frame=t), MEDIA_EXR) for t in range(2)})
    before = {d for d, _ in s.iter_objects()}
    enhancer = ArtifactStore(str(tmp_path / "other")).put_bytes(b"no enhancer needed to refuse")

    @flow
    def one(**kw):
        return enhance_shot(s.url, tree, enhancer, "anna", **kw)

    raft = EnhanceSettings(flow="raft", steps=1, tile=None)
    with pytest.raises(ValueError, match="^shot cu: flow 'raft' needs a local RAFT weights file"):
        run_flow(one, settings=raft)
    missing = tmp_path / "raft.pth"
    with pytest.raises(FileNotFoundError, match=rf"^shot cu: flow 'raft': no RAFT weights file at {missing}$"):
        run_flow(one, settings=raft, flow_weights=str(missing), flow_weights_fingerprint="blake3:0")
    missing.write_bytes(b"weights")
    with pytest.raises(ValueError, match="^shot cu: flow_weights .* without flow_weights_fingerprint"):
        run_flow(one, settings=raft, flow_weights=str(missing))
    with pytest.raises(ValueError, match="^shot cu: flow_weights .* given but settings.flow is 'rendered'"):
        run_flow(one, settings=EnhanceSettings(), flow_weights=str(missing),
                 flow_weights_fingerprint=directory_fingerprint(missing))
    _no_torchvision(monkeypatch)
    with pytest.raises(RuntimeError, match="^shot cu: flow 'raft' needs torchvision"):
        run_flow(one, settings=raft, flow_weights=str(missing), flow_weights_fingerprint=directory_fingerprint(missing))
    assert {d for d, _ in s.iter_objects()} == before                   # nothing enhanced, nothing stored


# ---------------------------------------------------------------------------------------------
# End to end


@pytest.fixture(scope="module")
def static_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("enh")
    return synthesize_capture(root / "cap", rig="demo_scene", seed=0, frames=4, supersample=1,
                              cameras=STATIC).parent


def _spec(path, capture, store, **quality):
    spec = {"format": "volcap-production/1", "name": "enh-test", "store": store,
            # a quarter of the resolution, SH degree 0: the segment is only the render the enhancer
            # takes, nothing here checks its quality
            "quality": {"preset": "test", "max_segment_frames": 4, "overlap": 1, "train_steps": 10,
                        "train_scale": 0.25, "sh_degree": 0, **quality},
            "captures": {"demo": {"folder": str(capture)}, "face": {"folder": str(capture)}},
            "actors": [{"name": "anna", "captures": ["demo"], "face_capture": "face"}],
            "shots": [_shot(name="wide"), _shot(name="cu", enhance=True)]}
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def test_a_flux_enhancer_without_its_weights_is_refused_before_anything_runs(prefect_api, static_capture,
                                                                              tmp_path):
    store = ArtifactStore(str(tmp_path / "store")).url
    spec = _spec(tmp_path / "spec.yaml", static_capture, store, enhancer_architecture="flux-dev",
                 enhancer_weights=str(tmp_path / "no-flux"))
    with pytest.raises(ValueError, match=r"enhancer_weights .*no-flux: no such directory"):
        open_production(spec)
    with pytest.raises(ValueError, match="enhancer_weights"):
        run_flow(production_flow, spec=str(spec))
    assert not ArtifactStore(store).list_refs()
    # without an enhanced shot the weights do not matter
    only_wide = open_production(spec, shots=["wide"])
    assert not {"face-pairs", "train-enhancer", "enhance-shot"} & {st.kind for st in only_wide.steps}


def test_volcap_plan_names_a_missing_flux_directory_in_one_line(static_capture, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    spec = _spec(tmp_path / "spec.yaml", static_capture, str(tmp_path / "store"),
                 enhancer_architecture="flux-dev", enhancer_weights="weights/FLUX.1-dev")
    res = subprocess.run([sys.executable, "-m", "flows.cli", "plan", str(spec)], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[2], timeout=600)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 1 and len(lines) == 1, res.stderr[-3000:]
    assert lines[0] == (f"volcap: error: {spec}: quality.enhancer_weights {tmp_path / 'weights/FLUX.1-dev'}: no "
                        "such directory (a local FLUX.1 checkpoint directory with transformer/ and vae/; "
                        "docs/enhancer.md)")


def test_a_raft_flow_in_a_spec_is_checked_before_anything_runs(static_capture, tmp_path, monkeypatch):
    """``quality.enhancer_flow: raft`` needs ``enhancer_flow_weights`` (a file relative to the spec),
    and torchvision, checked when the production opens; the step's fingerprint holds the file's."""
    import sys
    import types

    from flows.production import step_fingerprint
    from volcap_core.enhance.production import directory_fingerprint
    from volcap_core.production.presets import named_preset

    with pytest.raises(ValueError, match="enhancer_flow raft needs enhancer_flow_weights"):
        named_preset("test").with_overrides(enhancer_flow="raft")
    with pytest.raises(ValueError, match="enhancer_flow_weights is set but enhancer_flow is rendered"):
        named_preset("test").with_overrides(enhancer_flow_weights="raft.pth")
    store = ArtifactStore(str(tmp_path / "store")).url
    spec = _spec(tmp_path / "spec.yaml", static_capture, store, enhancer_flow="raft",
                 enhancer_flow_weights="weights/raft.pth")
    weights = tmp_path / "weights" / "raft.pth"
    with pytest.raises(ValueError, match=rf"^{spec}: quality.enhancer_flow raft: no RAFT weights file at {weights}$"):
        open_production(spec)
    weights.parent.mkdir()
    weights.write_bytes(b"weights")
    with monkeypatch.context() as m:
        _no_torchvision(m)
        with pytest.raises(ValueError, match=rf"^{spec}: quality.enhancer_flow raft needs torchvision"):
            open_production(spec)
    assert open_production(spec, shots=["wide"])          # without an enhanced shot RAFT does not matter
    for name in ("torchvision", "torchvision.models", "torchvision.models.optical_flow"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))    # the import check passes
    prod = open_production(spec)
    assert prod.enhancer_flow_weights() == weights and prod.spec.quality_preset().enhance_settings().flow == "raft"
    step = next(st for st in prod.steps if st.kind == "enhance-shot")
    assert step.parameters.enhancer_flow == "raft"
    done = {i: {"out": ArtifactStore(store).put_bytes(i.encode())} for i in step.inputs}
    assert step_fingerprint(prod, step, done)["flow_weights"] == directory_fingerprint(weights)


@pytest.mark.slow
def test_an_enhanced_shot_runs_end_to_end_and_reruns_cached(prefect_api, static_capture, tmp_path):
    store = ArtifactStore(str(tmp_path / "store")).url
    spec = _spec(tmp_path / "spec.yaml", static_capture, store)

    before = {p.step.id: p for p in plan_production(open_production(spec))}
    assert [k for k in before if k.split(":")[0] in ("face-pairs", "train-enhancer", "enhance-shot")] == [
        "face-pairs:anna", "train-enhancer:anna", "enhance-shot:cu"]
    assert before["enhance-shot:cu"].reason == "after render-shot:cu, which is to run"
    assert "enhance-shot:wide" not in before

    first = run_flow(production_flow, spec=str(spec))
    out = first.result
    assert first.tasks_failed == 0
    s = ArtifactStore(store)
    assert set(out["shots"]) == {"wide", "cu"} and "enhanced" not in out["shots"]["wide"]
    assert s.get_ref("productions/enh-test/enhanced/cu").digest == out["shots"]["cu"]["enhanced"]
    lq_tree = s.get_tree(out["shots"]["cu"]["frames"])
    enh_tree = s.get_tree(out["shots"]["cu"]["enhanced"])
    assert sorted(enh_tree) == sorted(lq_tree) == [f"{f:06d}.exr" for f in range(4)]
    model = s.get_record(out["steps"]["train-enhancer:anna"]["enhancer"], EnhancerModel)
    assert model.steps == 20 and model.groups == ("anna",) and len(model.losses) == 20
    pairs = s.get_record(out["steps"]["face-pairs:anna"]["pairs"], FacePairSet)
    q = open_production(spec).spec.quality_preset()
    # the plan's face-pairs parameters: windows x cameras, frames per window, square resolution
    assert len(pairs.sequences) == q.face_camera_paths * 1          # a 4-frame take holds one 4-frame window
    assert {(sq.width, sq.height, len(sq.frames)) for sq in pairs.sequences} == {(128, 128, 4)}
    assert "interim" in pairs.method
    for name in sorted(lq_tree):
        lq_header, lq_px = _exr(s.get_bytes(lq_tree[name].digest))
        header, px = _exr(s.get_bytes(enh_tree[name].digest))
        assert px.dtype == np.float16 and px.shape == lq_px.shape
        a = px[..., 3].astype(np.float32)
        assert np.isfinite(px.astype(np.float32)).all() and 0 <= a.min() and a.max() <= 1
        for key, value in lq_header.items():                       # the shot's metadata, untouched
            if key.startswith("volcap.") or key in ("dataWindow", "displayWindow", "worldToCamera"):
                assert np.array_equal(np.asarray(header[key]), np.asarray(value)), key
        assert header["volcap.enhanced"] == 1 and header["volcap.enhancer"] == model.model.digest
        # the render carries its exact flow from the second frame on (one segment), and it was used
        has_flow = {"flow.x", "flow.y"} <= set(OpenEXR.File(io.BytesIO(s.get_bytes(lq_tree[name].digest))).channels())
        assert has_flow == (name != "000000.exr"), name
        assert header["volcap.enhanceFlow"] == ("none" if name == "000000.exr" else "rendered"), name
    # the un-enhanced shot is the render alone: no enhancement ran on it
    assert out["steps"]["render-shot:wide"]["frames"] == out["shots"]["wide"]["frames"]
    assert "enhance-shot:wide" not in out["steps"]
    assert [r for r in s.list_refs() if r.startswith("productions/enh-test/enhanced/")] == [
        "productions/enh-test/enhanced/cu"]

    again = run_flow(production_flow, spec=str(spec))
    assert again.tasks_run == 0 and again.result["steps"] == out["steps"]
    assert {p.status for p in plan_production(open_production(spec))} == {"cached"}

    # a sampling change re-runs only the enhancement, and the plan says why
    spec2 = _spec(tmp_path / "spec2.yaml", static_capture, store, enhancer_sampling_steps=3)
    changed = {p.step.id: p for p in plan_production(open_production(spec2))}
    assert changed["train-enhancer:anna"].status == "cached"
    assert changed["enhance-shot:cu"].reason == "parameter enhancer_sampling_steps changed"
