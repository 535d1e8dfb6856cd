"""Cache keys see everything a task's output depends on, and nothing else (docs/tasks.md).

Per task family: changing each thing the output depends on (an input ref, a parameter, a field of
a settings object, a library release) changes the key, so a rerun recomputes; changing what only
says where data lives (the store URL, a capture folder) keeps it, so a rerun is served from the
cache. A guard refuses any task whose body reads a settings object or number from a module
global, which no key could see.
"""

from __future__ import annotations

import dataclasses
import inspect
import types
from dataclasses import replace

import pytest
from prefect import flow
from pydantic import BaseModel

import tasks.calibrate as calibrate_tasks
import tasks.enhance as enhance_tasks
import tasks.ingest as ingest_tasks
import tasks.production as production_tasks
import tasks.reconstruct as reconstruct_tasks
from flows.runtime import run_flow
from hardware.rig import load_rig
from tasks import contract
from tasks.contract import StoreCachePolicy, canonical_inputs, task_cache_key, task_identity, volcap_task
from volcap_core.calibration.colour import ColourCalibrationOptions
from volcap_core.calibration.dense import DenseOptions
from volcap_core.calibration.colour_step import ChartView
from volcap_core.calibration.static import StaticCalibrationOptions
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.capture import CameraSource, Encoding
from volcap_core.records import ArtifactRef
from volcap_core.production.presets import named_preset
from volcap_core.store import ArtifactStore

TASK_MODULES = (ingest_tasks, calibrate_tasks, reconstruct_tasks, production_tasks, enhance_tasks)
STORE, ELSEWHERE = "file:///tmp/volcap-a", "s3://bucket/volcap-b"


def ref(c: str) -> ArtifactRef:
    return ArtifactRef(digest="blake3:" + c * 64, size=10)


def all_tasks() -> list:
    found = {}
    for module in TASK_MODULES:
        for obj in vars(module).values():
            if isinstance(getattr(obj, "cache_policy", None), StoreCachePolicy):
                found[obj.cache_policy.task_name] = obj
    return [found[k] for k in sorted(found)]


def test_every_task_family_is_found():
    names = {t.cache_policy.task_name for t in all_tasks()}
    assert {"ingest-camera", "calibrate-static", "dense-points-frame", "train-segment", "render-shot"} <= names
    assert len(names) == 23


# ---------------------------------------------------------------------------------------------
# The guard: settings are parameters, never module globals read by the body
# ---------------------------------------------------------------------------------------------


def _names_read(code: types.CodeType) -> set[str]:
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):   # nested functions and lambdas
            names |= _names_read(const)
    return names


def _is_setting(value) -> bool:
    """What could change a result without changing a key: option objects and plain numbers."""
    if isinstance(value, (type, types.ModuleType, types.FunctionType)):
        return False
    if dataclasses.is_dataclass(value) or isinstance(value, BaseModel):
        return True
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def settings_read(task) -> list[str]:
    """Module globals holding settings that the task's own function (not Prefect's wrapper) reads."""
    fn = inspect.unwrap(task.fn)
    return sorted(n for n in _names_read(fn.__code__) if n in fn.__globals__ and _is_setting(fn.__globals__[n]))


@pytest.mark.parametrize("task", all_tasks(), ids=lambda t: t.cache_policy.task_name)
def test_no_task_reads_a_setting_from_a_module_global(task):
    leaks = settings_read(task)
    assert not leaks, (f"{task.cache_policy.task_name} reads module setting(s) {leaks}: make them parameters "
                       "with defaults so the cache key sees them (docs/tasks.md)")


def test_the_guard_catches_a_module_global_setting():
    """The guard above on a task written the old way (``OPTIONS`` read by the body)."""
    namespace: dict = {"volcap_task": volcap_task, "OPTIONS": DenseOptions(), "MIN_FRACTION": 0.5}
    exec(inspect.cleandoc('''
        @volcap_task(name="test-leaky", version="1")
        def leaky(store: str, frame: int) -> int:
            return int(OPTIONS.num_depths * MIN_FRACTION) + frame
    '''), namespace)
    assert settings_read(namespace["leaky"]) == ["MIN_FRACTION", "OPTIONS"]


@pytest.mark.parametrize("task", all_tasks(), ids=lambda t: t.cache_policy.task_name)
def test_every_default_has_a_key_form_and_every_library_a_release(task):
    ident = task_identity(task)     # canonicalises every default, resolves every library's release
    assert ident["version"] == task.cache_policy.version
    for lib, release in ident.get("libraries", {}).items():
        assert release and "+" not in release, (lib, release)


@pytest.mark.parametrize("task", [t for t in all_tasks() if t.cache_policy.libraries],
                         ids=lambda t: t.cache_policy.task_name)
def test_a_new_release_of_a_library_the_task_uses_changes_its_key(task, monkeypatch):
    policy = task.cache_policy
    inputs = {"x": 1}
    before = contract.cache_key(policy.task_name, policy.version, inputs, policy.locations, policy.libraries)
    for lib in policy.libraries:
        real = contract.library_version

        def bumped(m, lib=lib, real=real):
            return real(m) + ".post1" if m == lib else real(m)

        monkeypatch.setattr(contract, "library_version", bumped)
        after = contract.cache_key(policy.task_name, policy.version, inputs, policy.locations, policy.libraries)
        assert after != before, lib
        monkeypatch.setattr(contract, "library_version", real)
    # a library the task does not use is not in its key
    assert contract.cache_key(policy.task_name, policy.version, inputs, policy.locations, policy.libraries) == before


def test_the_build_label_is_not_part_of_a_release():
    """A CPU coordinator (torch 2.13.0+cpu) and a CUDA worker (+cu128) must agree on a segment's key."""
    assert "+" not in contract.library_version("torch")


# ---------------------------------------------------------------------------------------------
# Per family: each dependency misses, each location hits
# ---------------------------------------------------------------------------------------------


def assert_key_behaviour(task, base: dict, misses: dict, hits: dict):
    key = task_cache_key(task, STORE, **base)
    assert task_cache_key(task, ELSEWHERE, **base) == key, "the store URL entered the key"
    for name, change in misses.items():
        assert task_cache_key(task, STORE, **{**base, **change}) != key, f"{name} did not change the key"
    for name, change in hits.items():
        assert task_cache_key(task, STORE, **{**base, **change}) == key, f"{name} changed the key"


def test_ingest_keys():
    rig = load_rig("demo_scene")
    cam = rig.cameras[0]
    source = CameraSource(id=cam.id, path=f"cameras/{cam.id}", start_timecode="01:00:00:00")
    base = dict(capture_dir="/mnt/a/take1", camera=source, rig_camera=cam, raw_manifest=ref("a"), take_offset=0,
                frame_count=10, ocio_config=None, nan_policy="error", lens=None)
    assert_key_behaviour(
        ingest_tasks.ingest_camera, base,
        misses={"raw bytes": {"raw_manifest": ref("b")}, "nan policy": {"nan_policy": "repair"},
                "colour config": {"ocio_config": ref("c")}, "take offset": {"take_offset": 1},
                "source encoding": {"camera": source.model_copy(update={"encoding": Encoding.srgb})}},
        hits={"capture folder": {"capture_dir": "/mnt/b/other-mount"}})
    assert_key_behaviour(ingest_tasks.fingerprint_camera,
                         dict(camera_id="S001", files=["/a/000000.exr"], file_stats=[[10, 1, 1, 7]]),
                         misses={"a replaced file": {"file_stats": [[10, 2, 2, 7]]}}, hits={})


def test_calibration_keys():
    base = dict(capture=ref("a"))
    default = StaticCalibrationOptions()
    assert_key_behaviour(
        calibrate_tasks.calibrate_static, base,
        misses={"capture": {"capture": ref("b")},
                "plate frames": {"options": replace(default, plate_frames=default.plate_frames + 1)},
                "reference frame": {"options": replace(default, reference_frame=3)},
                "registration threshold": {"options": replace(default, min_registered_fraction=0.75)},
                "a nested SfM option": {"options": replace(default, sfm=replace(default.sfm,
                                                                                 **_bump_first_number(default.sfm)))},
                "the guided matching off": {"options": replace(default, guided=None)},
                "the observation threshold": {"options": replace(default, min_observations=10)},
                "unsupported cameras allowed": {"options": replace(default, allow_unregistered=True)}},
        hits={"the default, spelled out": {"options": StaticCalibrationOptions()}})
    tracking = TrackingOptions()
    assert_key_behaviour(
        calibrate_tasks.calibrate_tracking_camera, dict(capture=ref("a"), static=ref("b"), camera="T001"),
        misses={"camera": {"camera": "T002"}, "static result": {"static": ref("c")},
                "matching ratio": {"options": replace(tracking, ratio_3d=0.8)},
                "unsupported trackers allowed": {"options": replace(tracking, allow_unsupported=True)}},
        hits={"the default, spelled out": {"options": TrackingOptions()}})
    dense = DenseOptions()
    assert_key_behaviour(
        calibrate_tasks.dense_points_frame, dict(capture=ref("a"), calibration=ref("b"), frame=3),
        misses={"frame": {"frame": 4}, "scale": {"scale": 0.5}, "held-out camera": {"exclude_cameras": ["S002"]},
                "NCC threshold": {"options": replace(dense, min_ncc=0.5)},
                "sweep depth range": {"options": replace(dense, depth_max=20.0)}},
        hits={"no exclusions, spelled out": {"exclude_cameras": None}, "defaults": {"options": DenseOptions()}})
    face = ChartView(rig="face", capture=ref("a"), camera="F003", corners_px=((0, 0), (5, 0), (5, 3), (0, 3)))
    scene = ChartView(rig="scene", image=ref("b"), patches_px=((1.0, 2.0),) * 24)
    colour = ColourCalibrationOptions()
    assert_key_behaviour(
        calibrate_tasks.calibrate_colour, dict(source=face, reference=scene),
        misses={"the chart capture": {"source": face.model_copy(update={"capture": ref("c")})},
                "the chart image": {"reference": scene.model_copy(update={"image": ref("d")})},
                "a patch location": {"source": face.model_copy(update={"corners_px": ((0, 0), (5, 0), (5, 3), (0, 4))})},
                "the frame": {"source": face.model_copy(update={"frame": 1})},
                "the direction": {"source": scene, "reference": face},
                "robust rounds": {"options": replace(colour, robust_iterations=0)}},
        hits={"the defaults, spelled out": {"options": ColourCalibrationOptions()}})
    assert_key_behaviour(
        calibrate_tasks.point_cloud_sequence, dict(calibration=ref("a"), frames=[ref("b"), ref("c")]),
        misses={"budget": {"max_points_per_frame": 1000}, "seed": {"seed": 1}, "frames": {"frames": [ref("b")]}},
        hits={})


def _bump_first_number(options) -> dict:
    for f in dataclasses.fields(options):
        v = getattr(options, f.name)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return {f.name: v + 1}
    raise AssertionError(f"{type(options).__name__} has no numeric field")


def test_static_and_tracking_options_do_not_leak_into_each_other():
    """Tuning the tracking cameras does not recalibrate the static ones (and vice versa): each
    task's key holds only its own step's settings."""
    sig_static = inspect.signature(calibrate_tasks.calibrate_static.fn).parameters
    sig_tracking = inspect.signature(calibrate_tasks.calibrate_tracking_camera.fn).parameters
    assert isinstance(sig_static["options"].default, StaticCalibrationOptions)
    assert isinstance(sig_tracking["options"].default, TrackingOptions)
    assert not any(isinstance(p.default, TrackingOptions) for p in sig_static.values())


def test_reconstruction_keys():
    config = named_preset("test").train_config()
    base = dict(capture=ref("a"), calibration=ref("b"), points=ref("c"), frames=[0, 4], config=config, seed=0)
    assert_key_behaviour(
        reconstruct_tasks.train_segment_task, base,
        misses={"points": {"points": ref("d")}, "frames": {"frames": [0, 5]}, "seed": {"seed": 1},
                "steps": {"config": config.model_copy(update={"steps": config.steps + 1})},
                "held-out cameras": {"config": config.model_copy(update={"held_out_cameras": ["S003"]})},
                "requested back-end": {"config": config.model_copy(update={"backend": "torch"})},
                "MCMC cap": {"config": config.model_copy(update={"mcmc": config.mcmc.model_copy(
                    update={"cap_max": config.mcmc.cap_max + 1})})}},
        hits={"the same config rebuilt": {"config": named_preset("test").train_config()}})
    view = reconstruct_tasks.ViewSpec(K=((100.0, 0.0, 50.0), (0.0, 100.0, 50.0), (0.0, 0.0, 1.0)),
                                      world_to_camera=((1.0, 0, 0, 0), (0, 1.0, 0, 0), (0, 0, 1.0, 0), (0, 0, 0, 1.0)),
                                      width=100, height=100, time_s=0.5)
    assert_key_behaviour(reconstruct_tasks.render_views, dict(segment=ref("a"), views=[view]),
                         misses={"time": {"views": [view.model_copy(update={"time_s": 0.6})]},
                                 "near plane": {"views": [view.model_copy(update={"near_m": 0.5})]},
                                 "grids": {"grids_of": "S001"}}, hits={})


def test_enhancer_keys():
    from volcap_core.enhance.production import EnhanceSettings, PairDegradation

    pairs = dict(capture=ref("a"), actor="anna", subsequences=2, subsequence_frames=4, camera_paths=2, resolution=128)
    assert_key_behaviour(
        enhance_tasks.face_pairs, pairs,
        misses={"the capture": {"capture": ref("b")}, "the actor": {"actor": "ben"},
                "sub-sequences": {"subsequences": 3}, "frames": {"subsequence_frames": 5},
                "camera paths": {"camera_paths": 1}, "resolution": {"resolution": 64},
                "the degradation": {"degradation": PairDegradation(scale=2)}, "the window": {"window": "head"}},
        hits={"the default degradation, spelled out": {"degradation": PairDegradation()},
              "the default window, spelled out": {"window": "performer"}})
    q = named_preset("test")
    arch = q.enhancer_config()
    assert_key_behaviour(
        enhance_tasks.actor_prompt, dict(group="anna", config=arch),
        misses={"the group": {"group": "ben"}, "the text": {"text": "a woman"},
                "the architecture": {"config": arch.model_copy(update={"prompt_tokens": 9})},
                "the encoders' content": {"encoders": "/w", "encoders_fingerprint": "blake3:1"}},
        hits={"where the encoders are": {"encoders": "/elsewhere"}})
    config = q.enhancer_train_config()
    train = dict(pair_sets=[ref("a")], prompts={"anna": ref("b")}, config=config, architecture=arch)
    assert_key_behaviour(
        enhance_tasks.train_enhancer_task, train,
        misses={"the pairs": {"pair_sets": [ref("a"), ref("c")]}, "a prompt": {"prompts": {"anna": ref("c")}},
                "steps": {"config": config.model_copy(update={"steps": config.steps + 1})},
                "VAE pre-training": {"config": config.model_copy(update={"vae_steps": config.vae_steps + 1})},
                "the architecture": {"architecture": arch.model_copy(update={"train_crop": 32})},
                "the seed": {"seed": 1},
                "base weights": {"architecture": None, "base_weights": "/flux", "base_fingerprint": "blake3:1"}},
        hits={"the same config rebuilt": {"config": named_preset("test").enhancer_train_config()},
              "where the base weights are": {"base_weights": "/elsewhere"}})
    settings = q.enhance_settings()
    assert_key_behaviour(
        enhance_tasks.enhance_shot, dict(frames=ref("a"), enhancer=ref("b"), group="anna", settings=settings),
        misses={"the frames": {"frames": ref("c")}, "the enhancer": {"enhancer": ref("c")}, "the group": {"group": "ben"},
                "sampling steps": {"settings": settings.model_copy(update={"steps": settings.steps + 1})},
                "tiling": {"settings": settings.model_copy(update={"tile": 512})},
                "the flow back-end": {"settings": settings.model_copy(update={"flow": "dis"})}},
        hits={"the preset's settings rebuilt": {"settings": named_preset("test").enhance_settings()}})
    # RAFT's weights file: a location, its content pinned by its fingerprint
    raft = settings.model_copy(update={"flow": "raft"})
    assert_key_behaviour(
        enhance_tasks.enhance_shot, dict(frames=ref("a"), enhancer=ref("b"), group="anna", settings=raft,
                                         flow_weights="/w/raft.pth", flow_weights_fingerprint="blake3:1"),
        misses={"the RAFT weights' content": {"flow_weights_fingerprint": "blake3:2"},
                "RAFT's small variant": {"settings": settings.model_copy(update={"flow": "raft-small"})},
                "DIS instead": {"settings": settings.model_copy(update={"flow": "dis"}), "flow_weights": None,
                                "flow_weights_fingerprint": None}},
        hits={"where the RAFT weights are": {"flow_weights": "/elsewhere/raft_large.pth"}})
    assert enhance_tasks.enhance_shot.cache_policy.key(
        {"store": STORE, "frames": ref("a"), "enhancer": ref("b"), "group": "anna", "settings": EnhanceSettings(),
         "flow_weights": None, "flow_weights_fingerprint": None}
    ) == task_cache_key(enhance_tasks.enhance_shot, STORE, frames=ref("a"), enhancer=ref("b"), group="anna")


def test_production_keys():
    shot = {"name": "s1", "frames": [0, 4], "camera": {"preset": "orbit"}}
    assert_key_behaviour(production_tasks.render_shot, dict(performance=ref("a"), shot=shot),
                         misses={"performance": {"performance": ref("b")},
                                 "shot": {"shot": {**shot, "frames": [0, 5]}}}, hits={})


# ---------------------------------------------------------------------------------------------
# In Prefect: a changed setting reruns, a changed location is served from the cache
# ---------------------------------------------------------------------------------------------

RUNS: list[int] = []


@dataclasses.dataclass(frozen=True)
class _Gain:
    factor: int = 2


@volcap_task(name="test-settings-in-key", version="1", libraries=("numpy",))
def _gained(store: str, blob: ArtifactRef, options: _Gain = _Gain()) -> ArtifactRef:
    RUNS.append(options.factor)
    s = ArtifactStore(store)
    return s.put_bytes(s.get_bytes(blob) * options.factor)


@flow
def _gain_flow(store: str, blob: ArtifactRef, options: _Gain | None = None) -> str:
    out = _gained(store, blob) if options is None else _gained(store, blob, options)
    return out.digest


def test_prefect_reruns_on_a_changed_setting_and_serves_an_unchanged_default(prefect_api, tmp_path):
    s = ArtifactStore(str(tmp_path / "store"))
    blob = s.put_bytes(b"ab")
    RUNS.clear()
    first = run_flow(_gain_flow, store=s.url, blob=blob)
    assert RUNS == [2] and first.tasks_run == 1
    # the default spelled out is the same computation: served from the cache
    again = run_flow(_gain_flow, store=s.url, blob=blob, options=_Gain(2))
    assert (again.result, again.tasks_cached, RUNS) == (first.result, 1, [2])
    # a changed setting: recomputed
    changed = run_flow(_gain_flow, store=s.url, blob=blob, options=_Gain(3))
    assert changed.result != first.result and changed.tasks_run == 1 and RUNS == [2, 3]
