"""The production flow in one process (what CI and laptops run): plan, run, rerun, explain.

A capture of six of the demo rig's static cameras only (so: no tracking stage; the static solve,
most of the test's time, grows with the cameras), four frames, one shot
over them with a quality that makes two overlapping segments.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from flows.production import open_production, plan_production, production_flow
from flows.runtime import run_flow
from volcap_core.imageio.read import decode_exr_native
from volcap_core.production.performance import Performance
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture

STATIC = [f"S00{i}" for i in range(6)]


@pytest.fixture(scope="module")
def static_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("prod")
    return synthesize_capture(root / "cap", rig="demo_scene", seed=0, frames=4, supersample=1,
                              cameras=STATIC).parent


def _shot(**kw):
    shot = {"name": "orbit", "performance": "demo", "frames": [0, 4], "fps": 24, "resolution": [64, 36],
            "sensor_mm": 36,
            "keyframes": [{"frame": 0, "position": [5.0, -2.0, 1.8], "look_at": [0.0, 0.0, 1.0], "focal_mm": 24},
                          {"frame": 3, "position": [5.0, 2.0, 1.8], "look_at": [0.0, 0.0, 1.0], "focal_mm": 28}]}
    shot.update(kw)
    return shot


def _write_spec(path, capture, store, train_steps=20, shots=None):
    spec = {"format": "volcap-production/1", "name": "flow-test", "store": store,
            # at a quarter of the resolution, SH degree 0, as the other production tests: what this
            # test checks (the plan, the steps run, their outputs, the cache) does not depend on it,
            # and the segments train and are scored on a sixteenth of the pixels
            "quality": {"preset": "test", "max_segment_frames": 3, "overlap": 1, "train_steps": train_steps,
                        "train_scale": 0.25, "sh_degree": 0},
            "captures": {"demo": {"folder": str(capture)},
                         "unused": {"folder": str(path.parent / "no-such-folder")}},
            "shots": shots or [_shot()]}
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


@pytest.mark.slow
def test_production_runs_plans_and_explains(prefect_api, static_capture, tmp_path):
    store = ArtifactStore(str(tmp_path / "store")).url
    spec = _write_spec(tmp_path / "spec.yaml", static_capture, store)

    before = plan_production(open_production(spec))
    kinds = [p.step.kind for p in before]
    # only what the shot needs: no tracking stage (no tracking camera), nothing for "unused"
    assert kinds == ["ingest", "calibrate-static", "dense-points", "train-segment", "dense-points",
                     "train-segment", "render-shot"]
    assert all(p.status == "to-run" for p in before)
    assert before[0].reason == "never run" and before[1].reason == "after ingest:demo, which is to run"

    first = run_flow(production_flow, spec=str(spec))
    out = first.result
    assert out["segment_runs"] == "local" and first.tasks_failed == 0
    s = ArtifactStore(store)
    frames = s.get_tree(out["shots"]["orbit"]["frames"])
    assert sorted(frames) == [f"{f:06d}.exr" for f in range(4)]
    # (after 20 steps the Gaussians are still large blobs filling the stage volume, so the crop to
    # the performers cannot show at this budget: test_production_shot tests it on a built model)
    pixels, _ = decode_exr_native(s.get_bytes(frames["000002.exr"].digest))
    # RGBA, then flow.x/flow.y on frames with an exact flow to the previous one (docs/shots.md)
    assert pixels.shape[-1] in (4, 6)
    rgba = pixels[..., :4]
    assert np.isfinite(rgba).all() and rgba[..., 3].max() > 0.5
    perf = s.get_record(out["shots"]["orbit"]["performance"], Performance)
    assert [seg.frames for seg in perf.segments] == [(0, 3), (2, 4)]
    assert s.get_ref("productions/flow-test/shots/orbit").digest == out["shots"]["orbit"]["frames"]
    assert not any("tracking" in t for t in out["steps"])
    # dense points are kept whole (training thins them to the segment's budget after the
    # static/moving split has seen every point), not cut to gaussians_per_frame first
    from volcap_core.pointcloud import PointCloudSequence

    pts = s.get_record(out["steps"]["dense-points:demo:000000-000003"]["points"], PointCloudSequence)
    assert min(f.count for f in pts.frames) > open_production(spec).spec.quality_preset().gaussians_per_frame

    # rerun: nothing computed, same artifacts; the plan agrees
    again = run_flow(production_flow, spec=str(spec))
    assert again.tasks_run == 0 and again.result["steps"] == out["steps"]
    assert {p.status for p in plan_production(open_production(spec))} == {"cached"}

    # a quality change: the plan names the parameter, and only training and rendering re-run
    spec2 = _write_spec(tmp_path / "spec2.yaml", static_capture, store, train_steps=25)
    changed = {p.step.id: p for p in plan_production(open_production(spec2))}
    assert changed["ingest:demo"].status == "cached"
    assert changed["dense-points:demo:000000-000003"].status == "cached"
    assert changed["train-segment:demo:000000-000003"].reason == "parameter train_steps changed"
    assert changed["render-shot:orbit"].reason.startswith("after train-segment:demo:")

    # an output gone from the store (gc, a wiped bucket) is seen by the plan
    s.fs.rm_file(s._object_path(out["shots"]["orbit"]["frames"]))
    gone = {p.step.id: p for p in plan_production(open_production(spec))}
    assert gone["render-shot:orbit"].reason == "output missing from the store"


def test_an_enhanced_shot_is_planned_after_its_render_and_the_enhancer(prefect_api, static_capture, tmp_path):
    """(It runs end to end in test_enhanced_shot.py.)"""
    store = ArtifactStore(str(tmp_path / "store")).url
    spec = yaml.safe_load(_write_spec(tmp_path / "spec.yaml", static_capture, store).read_text())
    spec["captures"]["face"] = {"folder": str(static_capture)}
    spec["actors"] = [{"name": "anna", "captures": ["demo"], "face_capture": "face"}]
    spec["shots"] = [_shot(name="cu", enhance=True)]
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(spec))
    planned = {p.step.id: p for p in plan_production(open_production(tmp_path / "spec.yaml"))}
    assert planned["face-pairs:anna"].reason == "after ingest:face, which is to run"
    assert planned["train-enhancer:anna"].reason == "after face-pairs:anna, which is to run"
    assert planned["enhance-shot:cu"].reason == "after render-shot:cu, which is to run"
    assert not ArtifactStore(store).list_refs()


def test_a_needed_capture_that_cannot_be_read_is_named(prefect_api, tmp_path):
    spec = {"format": "volcap-production/1", "name": "bad", "store": str(tmp_path / "store"),
            "quality": "test", "captures": {"demo": {"folder": str(tmp_path / "missing")}},
            "shots": [_shot()]}
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(spec))
    with pytest.raises(ValueError, match=r"captures\.demo: .*missing"):
        open_production(tmp_path / "spec.yaml")


def test_store_credentials_come_from_a_secret_block_and_the_environment_wins(prefect_api, monkeypatch):
    from prefect.blocks.system import Secret

    from flows.store_credentials import store_credentials_from_block

    Secret(value='{"AWS_ACCESS_KEY_ID": "from-block", "AWS_SECRET_ACCESS_KEY": "s3cr3t"}').save(
        "volcap-test-store", overwrite=True)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "placeholder")  # recorded, so teardown restores it
    monkeypatch.delenv("AWS_SECRET_ACCESS_KEY")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "from-env")
    monkeypatch.setenv("VOLCAP_STORE_SECRET", "volcap-test-store")
    assert store_credentials_from_block() == ["AWS_SECRET_ACCESS_KEY"]
    import os

    assert os.environ["AWS_ACCESS_KEY_ID"] == "from-env" and os.environ["AWS_SECRET_ACCESS_KEY"] == "s3cr3t"
    Secret(value='{"PATH": "/evil"}').save("volcap-test-bad", overwrite=True)
    monkeypatch.setenv("VOLCAP_STORE_SECRET", "volcap-test-bad")
    with pytest.raises(ValueError, match="unexpected keys PATH"):
        store_credentials_from_block()
    monkeypatch.setenv("VOLCAP_STORE_SECRET", "no-such-block")
    with pytest.raises(ValueError, match="no such Secret block"):
        store_credentials_from_block()
