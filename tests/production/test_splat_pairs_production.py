"""Gaussian-splat face pairs in a production (issue 29): the face capture's calibration from the
spec, the LQ range measured in the actor's Scene Rig segments, and the whole enhancer half end to end.

Fast: planning on hand-made facts (well under 1 s each) and the ground-truth head positions.
Slow: a small production (a synthetic Scene Rig capture of the demo rig's 8 static cameras, 2
frames, and a Face Rig capture of its actor 0, 4 cameras, 4 frames, calibrated by its ground truth)
runs face-pairs (splat, the LQ range measured) -> train-enhancer -> enhance-shot, then again fully
cached.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from flows.production import Production, open_production, plan_production, production_flow, step_fingerprint
from volcap_core.capture import Performer
from volcap_core.production.lq_range import ground_truth_heads
from volcap_core.production.spec import CaptureInfo, SpecError, needed_steps, parse_spec
from volcap_core.store import ArtifactStore
from volcap_core.synth.ground_truth import head_at

SHOT = {"name": "cu", "performance": "take", "frames": [0, 4], "fps": 24, "resolution": [64, 36],
        "sensor_mm": 36, "enhance": True,
        "keyframes": [{"frame": 0, "position": [5.0, -2.0, 1.8], "look_at": [0.0, 0.0, 1.5], "focal_mm": 50}]}
SPLAT = {"preset": "test", "pair_method": "splat"}


def spec_data(quality=SPLAT, **anna) -> dict:
    return {"format": "volcap-production/1", "name": "p", "quality": quality,
            "captures": {"take": {"ref": "captures/take"}, "face": {"ref": "captures/face"}},
            "actors": [{"name": "anna", "captures": ["take"], "face_capture": "face", **anna}], "shots": [SHOT]}


def facts(scene_truth: bool | None = True, face_truth: bool | None = True, performer_actor: int | None = 1):
    performer = Performer(capture="take-name", actor=performer_actor) if performer_actor is not None else None
    return {"take": CaptureInfo(has_tracking_cameras=False, fps=24, frame_count=8, width=320, height=180,
                                name="take-name", ground_truth=scene_truth),
            "face": CaptureInfo(has_tracking_cameras=False, fps=24, frame_count=8, width=320, height=180,
                                name="face", performer=performer, ground_truth=face_truth)}


def plan(data: dict, info: dict) -> dict:
    return {s.id: s for s in needed_steps(parse_spec(data), info)}


# ---------------------------------------------------------------------------------------------
# The face capture's calibration


def test_face_calibration_is_planned_as_the_spec_gives_it():
    steps = plan(spec_data(face_calibration="ground-truth"), facts())
    assert steps["face-pairs:anna"].parameters.calibration == "ground-truth"
    assert steps["face-pairs:anna"].parameters.as_json()["calibration"] == "ground-truth"
    ref = plan(spec_data(face_calibration="imported-calibrations/face"), facts())["face-pairs:anna"]
    assert ref.parameters.calibration == "imported-calibrations/face"
    unset = plan(spec_data(), facts())["face-pairs:anna"].parameters
    assert unset.calibration is None and "calibration" not in unset.as_json()    # SfM, as before the field


def test_ground_truth_on_a_real_face_capture_is_refused_in_one_line_before_anything_runs():
    with pytest.raises(ValueError) as info:
        needed_steps(parse_spec(spec_data(face_calibration="ground-truth")), facts(face_truth=False))
    assert str(info.value).startswith("actors[0].face_calibration: ground-truth, but actor 'anna''s face "
                                      "capture 'face' carries no ground truth (only synthetic captures do)")
    assert "\n" not in str(info.value)


def test_a_face_calibration_without_a_face_capture_is_a_spec_error():
    data = spec_data(face_calibration="ground-truth")
    del data["actors"][0]["face_capture"]
    data["shots"] = []
    with pytest.raises(SpecError, match=r"actors\[0\].face_calibration: set, but actor 'anna' has no face_capture"):
        parse_spec(data)


def test_a_face_calibration_ref_missing_from_the_store_is_refused_before_anything_runs(tmp_path):
    store = ArtifactStore(str(tmp_path / "store")).url
    spec = parse_spec(spec_data(face_calibration="imported-calibrations/face"))
    prod = Production(spec=spec, spec_dir=tmp_path, store=store, steps=needed_steps(spec, facts()))
    with pytest.raises(ValueError, match=r"^p: actors\[0\].face_calibration: 'imported-calibrations/face' is "
                                         r"not in store .*volcap import-calibration"):
        prod.check_enhancer()
    # present: its digest is in the step's fingerprint (a ref moved to another calibration re-runs it)
    s = ArtifactStore(store)
    ref = s.put_json({"stand-in": "any stored object: the fingerprint reads the digest the name gives"})
    s.set_ref("imported-calibrations/face", ref)
    prod.check_enhancer()
    step = next(st for st in prod.steps if st.id == "face-pairs:anna")
    done = {i: {"segment": ref} for i in step.inputs}
    assert step_fingerprint(prod, step, done)["face_calibration"] == ref.digest


# ---------------------------------------------------------------------------------------------
# The LQ range: measured in the actor's segments, or the preset's


def test_splat_pairs_measure_the_lq_range_in_the_actor_s_synthetic_segments_and_run_after_them():
    steps = plan(spec_data(face_calibration="ground-truth"), facts(performer_actor=1))
    pairs = steps["face-pairs:anna"]
    segments = [i for i in steps if i.startswith("train-segment:take:")]
    assert segments and [i for i in pairs.inputs if i.startswith("train-segment:")] == segments
    order = list(steps)
    assert max(order.index(i) for i in segments) < order.index("face-pairs:anna")
    assert pairs.parameters.lq_range == "measured"
    assert pairs.parameters.actor_index == 1                     # the face capture's performer
    assert plan(spec_data(index=1), facts(performer_actor=None))["face-pairs:anna"].parameters.actor_index == 1
    # no performer, no index: the capture's only actor (the task refuses a capture of several)
    assert plan(spec_data(), facts(performer_actor=None))["face-pairs:anna"].parameters.actor_index is None


def test_without_head_positions_the_preset_s_lq_range_stands_and_interim_plans_are_unchanged():
    real = plan(spec_data(), facts(scene_truth=False))["face-pairs:anna"]
    assert real.parameters.lq_range == "preset" and real.parameters.actor_index is None
    assert not any(i.startswith("train-segment:") for i in real.inputs)
    assert {"lq_range", "actor_index"}.isdisjoint(real.parameters.as_json())
    interim = plan(spec_data(quality="test", face_calibration="ground-truth"), facts())["face-pairs:anna"]
    assert interim.inputs == () and interim.parameters.as_json() == {
        "actor": "anna", "face_capture": "face", "subsequences": 2, "subsequence_frames": 4, "camera_paths": 2,
        "hq_gaussians_per_frame": 2000, "lq_gaussians": [200, 500], "resolution": 128, "window": "performer"}


def test_ground_truth_heads_are_the_scene_s_head_prims_and_the_actor_must_be_known():
    def actor(i, x):
        return {"index": i, "frames": [{"take_index": k, "time_s": k / 24, "parts": [
            {"name": "head", "kind": "ellipsoid", "centre_m": [x + k, 0.0, 1.6], "rotation": np.eye(3).tolist(),
             "semi_axes_m": [0.1, 0.08, 0.12]}]} for k in range(3)]}

    scene = {"actors": [actor(0, 0.0), actor(1, 5.0)]}
    times = [0.0, 1 / 48, 2 / 24]
    heads = ground_truth_heads(scene, 1, times)
    assert heads.shape == (3, 3)
    np.testing.assert_allclose(heads, [head_at(scene["actors"][1], t)["centre_m"] for t in times])
    np.testing.assert_allclose(heads[:, 0], [5.0, 5.5, 7.0])
    with pytest.raises(ValueError, match=r"^capture c: the ground truth holds 2 actors: say which one"):
        ground_truth_heads(scene, None, times, where="capture c")
    with pytest.raises(ValueError, match=r"no actor 2 in the ground truth \(it holds 2\)"):
        ground_truth_heads(scene, 2, times)
    np.testing.assert_allclose(ground_truth_heads({"actors": [actor(0, 1.0)]}, None, [0.0]), [[1.0, 0.0, 1.6]])


# ---------------------------------------------------------------------------------------------
# End to end (slow): face-pairs (splat) -> train-enhancer -> enhance-shot, and a rerun cached

STATIC = [f"S00{i}" for i in range(8)]
FACE_CAMS = ["F000", "F002", "F004", "F006"]     # four static Face Rig cameras: one held out of every model


def _production_spec(path, scene, face, store):
    spec = {"format": "volcap-production/1", "name": "gs-pairs", "store": store,
            # the test preset's schedule, cut down (10 steps at half resolution), with the paper's pairs: two
            # 2-frame sub-sequences of the face take, two 64 px paths each, 1 000-Gaussian HQ models (each
            # model's scoring, its floors' colour fits per view, costs most: views are what cost)
            "quality": {"preset": "test", "max_segment_frames": 4, "overlap": 1, "train_steps": 10,
                        "train_scale": 0.5, "sh_degree": 0, "pair_method": "splat", "face_camera_paths": 2,
                        "face_subsequence_frames": 2, "face_hq_gaussians_per_frame": 1000, "pair_resolution": 64},
            "captures": {"scene": {"folder": str(scene)}, "face": {"folder": str(face)}},
            "actors": [{"name": "anna", "captures": ["scene"], "face_capture": "face",
                        "face_calibration": "ground-truth"}],
            "shots": [{**SHOT, "performance": "scene", "frames": [0, 2],
                       "keyframes": [{"frame": 0, "position": [5.0, -2.0, 1.8], "look_at": [0.0, 0.0, 1.0],
                                      "focal_mm": 24}]}]}
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


@pytest.mark.slow
def test_a_production_trains_its_enhancer_on_splat_pairs_with_the_measured_lq_range(prefect_api, tmp_path):
    import json

    from flows.runtime import run_flow
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture
    from volcap_core.enhance.production import SPLAT_PAIRS, EnhancerModel, PairDataset
    from volcap_core.production.lq_range import lq_range, upper_body_gaussian_counts
    from volcap_core.reconstruction import SegmentModel
    from volcap_core.splat import load_model
    from volcap_core.synth import synthesize_capture, synthesize_face_capture

    scene = synthesize_capture(tmp_path / "scene", rig="demo_scene", seed=0, frames=2, supersample=1,
                               cameras=STATIC).parent
    face = synthesize_face_capture(tmp_path / "face", frames=4, supersample=1, cameras=FACE_CAMS, write_depth=True,
                                   actor_of=(scene, 0)).parent
    store = ArtifactStore(str(tmp_path / "store")).url
    spec = _production_spec(tmp_path / "spec.yaml", scene, face, store)

    before = {p.step.id: p for p in plan_production(open_production(spec))}
    pairs_step = before["face-pairs:anna"].step
    segments = [i for i in before if i.startswith("train-segment:scene:")]
    assert [i for i in pairs_step.inputs if i.startswith("train-segment:")] == segments == ["train-segment:scene:000000-000002"]
    p = pairs_step.parameters
    assert (p.method, p.calibration, p.lq_range, p.actor_index) == ("splat", "ground-truth", "measured", 0)

    first = run_flow(production_flow, spec=str(spec))
    assert first.tasks_failed == 0
    out = first.result
    s = ArtifactStore(store)
    ds = s.get_record(out["steps"]["face-pairs:anna"]["pairs"], PairDataset)
    assert ds.method == SPLAT_PAIRS and ds.actor == "anna" and ds.resolution == 64
    assert s.get_record(ds.calibration, Calibration).stats.get("ground_truth") == 1.0   # no SfM on the Face Rig
    # the LQ range is actor 0's upper-body Gaussians in the scene segment, per frame, min and max, recorded measured
    assert ds.lq_range_source == "measured"
    measurement = s.get_json(ds.parameters["lq_measurement"])
    seg = s.get_record(out["steps"][segments[0]]["segment"], SegmentModel)
    cap = s.get_record(seg.capture, Capture)
    truth = json.loads(s.get_bytes(s.get_tree(cap.ground_truth)["scene.json"].digest))
    times = [cap.frame_time(f) for f in range(0, 2)]
    counts = upper_body_gaussian_counts(load_model(s.get_bytes(seg.model)),
                                        [head_at(truth["actors"][0], t)["centre_m"] for t in times], times)
    want = lq_range(counts)
    assert ds.lq_range == (want.low, want.high) == (measurement["low"], measurement["high"])
    assert 0 < want.low <= want.high < seg.gaussians and measurement["frames"] == 2
    assert all(want.low <= q.lq_gaussians <= want.high and q.hq_gaussians == 1000 for q in ds.sequences)
    assert len(ds.sequences) == 2 * 2
    # the enhancer trained on the dataset, and the close-up enhanced with it
    model = s.get_record(out["steps"]["train-enhancer:anna"]["enhancer"], EnhancerModel)
    assert [r.digest for r in model.pair_sets] == [out["steps"]["face-pairs:anna"]["pairs"]] and model.groups == ("anna",)
    enhanced = s.get_tree(out["shots"]["cu"]["enhanced"])
    assert sorted(enhanced) == [f"{f:06d}.exr" for f in range(2)]

    again = run_flow(production_flow, spec=str(spec))
    assert again.tasks_run == 0 and again.result["steps"] == out["steps"]
    assert {p.status for p in plan_production(open_production(spec))} == {"cached"}


def test_the_demo_says_which_pairs_its_enhancer_trained_on():
    from types import SimpleNamespace

    from flows.demo import ENHANCER_RUNS, enhancer_pairs
    from tasks.enhance import INTERIM_PAIRS
    from volcap_core.enhance.production import SPLAT_PAIRS
    from volcap_core.production.presets import named_preset

    demo = named_preset("demo").with_overrides(**ENHANCER_RUNS["demo"])
    line = enhancer_pairs(demo, SimpleNamespace(method=INTERIM_PAIRS, sequences=[0] * 4))
    assert line.startswith(f"enhancer pairs: interim, {INTERIM_PAIRS}, 4 sequence(s); interim in the demo because")
    splat = enhancer_pairs(demo.with_overrides(pair_method="splat"), SimpleNamespace(method=SPLAT_PAIRS, sequences=[0]))
    assert splat == f"enhancer pairs: splat, {SPLAT_PAIRS}, 1 sequence(s)" and "\n" not in line


def test_the_demo_counts_the_pair_datasets_training_split_apart():
    """A PairDataset trains its enhancer on its train split only: the demo's line says how many of
    its sequences that is (the full bench's 18 sequences trained 6)."""
    from flows.demo import enhancer_pairs
    from volcap_core.enhance.production import SPLAT_PAIRS, PairDataset, SplatPairSequence, split_subsequences
    from volcap_core.production.presets import named_preset
    from volcap_core.records import ArtifactRef

    ref = ArtifactRef(digest="blake3:" + "c" * 64, size=1)
    seqs = tuple(SplatPairSequence(name=f"s{i:03d}-p{p:03d}", subsequence=i, path=p, frames=(0, 1), width=8, height=8,
                                   lq=(ref, ref), hq=(ref, ref), flow=(ref,), path_params={}, lq_gaussians=1,
                                   hq_gaussians=2, lq_model=ref, hq_model=ref) for i in range(3) for p in range(2))
    split = split_subsequences(3, seed=0)
    ds = PairDataset(actor="anna", group="anna", capture=ref, calibration=ref, colour=None, method=SPLAT_PAIRS,
                     lq_range=(1, 2), lq_range_source="preset", resolution=8, parameters={}, split=split, sequences=seqs)
    line = enhancer_pairs(named_preset("test").with_overrides(pair_method="splat"), ds)
    [train] = split["train"]
    assert line == (f"enhancer pairs: splat, {SPLAT_PAIRS}, 6 sequence(s), 2 of them trained on "
                    f"(the train split: sub-sequence(s) {train})")
