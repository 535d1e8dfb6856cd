"""The calibration options of `volcap calibrate` and `volcap reconstruct` reach the calibration they
run: `--allow-unregistered`, `--known-distance CAM_A,CAM_B,METRES` and `--known-points FILE.json`
(issue 13). In-process and without a Prefect server: the command's flow call is intercepted (CLI ->
flow parameters), and the flows' bodies run until they call ``calibrate_capture`` (flow ->
calibration settings), so both commands are checked to ask for the same cached calibration. A few
seconds once the modules are imported (~20 s on the shared 2-core machine).
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import pytest
from typer.testing import CliRunner

import flows.calibrate as calibrate_flows
import flows.cli as cli
import flows.reconstruct as reconstruct_flows
from hardware.rig import load_rig
from tasks.calibrate import calibrate_static
from tasks.contract import task_cache_key
from volcap_core.calibration.scale import KnownPoints
from volcap_core.calibration.sfm import StaticSfmOptions
from volcap_core.calibration.static import StaticCalibrationOptions
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.capture import Capture, CaptureCamera
from volcap_core.store import ArtifactStore

MARKS = {"points": {"A": {"S001": [100.0, 120.0], "S002": [140.5, 118.0]},
                    "B": {"S002": [200.0, 130.0], "S003": [180.0, 125.0]}}, "distance_m": 2.5}


class _Summary:
    result = {"segments": [], "calibration": {"digest": "blake3:c"}, "points": {"digest": "blake3:p"},
              "unregistered": {}, "errors": None, "stage_frame": None}

    def counts(self) -> dict:
        return {}


@pytest.fixture
def flow_calls(monkeypatch):
    """The parameters each command would start its flow with."""
    calls: list[dict] = []

    def fake_run(flow, **params):
        calls.append({"flow": flow.name, **params})
        return _Summary()

    monkeypatch.setattr(cli, "_run", fake_run)
    monkeypatch.setattr(cli, "start_api_early", lambda: None)
    monkeypatch.setattr(cli, "_open", lambda url: None)
    return calls


def _invoke(*args: str):
    return CliRunner().invoke(cli.app, list(args))


def test_reconstruct_passes_the_calibration_options_to_its_flow(flow_calls, tmp_path):
    marks = tmp_path / "marks.json"
    marks.write_text(json.dumps(MARKS))
    assert _invoke("reconstruct", "captures/x", "--out", str(tmp_path)).exit_code == 0
    assert not {"allow_unregistered", "known_distance", "known_points"} & set(flow_calls[-1])   # the flow's defaults
    res = _invoke("reconstruct", "captures/x", "--allow-unregistered", "--out", str(tmp_path))
    assert res.exit_code == 0, res.output
    assert flow_calls[-1]["flow"] == "reconstruct" and flow_calls[-1]["allow_unregistered"] is True
    res = _invoke("reconstruct", "captures/x", "--known-distance", "S001,S004,5.5", "--out", str(tmp_path))
    assert res.exit_code == 0 and flow_calls[-1]["known_distance"] == ("S001", "S004", 5.5)
    res = _invoke("reconstruct", "captures/x", "--known-points", str(marks), "--allow-unregistered",
                  "--out", str(tmp_path))
    assert res.exit_code == 0 and flow_calls[-1]["known_points"] == MARKS and flow_calls[-1]["allow_unregistered"]
    res = _invoke("calibrate", "captures/x", "--known-points", str(marks))
    assert res.exit_code == 0, res.output
    assert flow_calls[-1]["flow"] == "calibrate" and flow_calls[-1]["known_points"] == MARKS
    assert flow_calls[-1]["known_distance"] is None
    # a sparse rig's SfM pair threshold (docs/calibration.md): passed only when given
    assert "min_pair_inliers" not in flow_calls[-1]
    res = _invoke("calibrate", "captures/x", "--min-pair-inliers", "20")
    assert res.exit_code == 0 and flow_calls[-1]["min_pair_inliers"] == 20, res.output
    res = _invoke("reconstruct", "captures/x", "--min-pair-inliers", "20", "--out", str(tmp_path))
    assert res.exit_code == 0 and flow_calls[-1]["min_pair_inliers"] == 20, res.output
    assert _invoke("calibrate", "captures/x", "--min-pair-inliers", "3").exit_code == 2


def test_reconstruct_passes_the_mask_alpha_loss_to_its_flow(flow_calls, tmp_path):
    """`--mask-alpha WEIGHT[:EVERY]` (the alpha loss on the capture's own masks, not a calibration
    option, checked here with the same interception): parsed, passed, refused when malformed."""
    assert _invoke("reconstruct", "captures/x", "--out", str(tmp_path)).exit_code == 0
    assert flow_calls[-1]["mask_alpha"] is None
    for given, parsed in (("1", (1.0, 1)), ("0.5:4", (0.5, 4))):
        res = _invoke("reconstruct", "captures/x", "--mask-alpha", given, "--out", str(tmp_path))
        assert res.exit_code == 0 and flow_calls[-1]["mask_alpha"] == parsed, res.output
    calls = len(flow_calls)
    for bad in ("x", "1:0", "-1", "1:2.5"):
        res = _invoke("reconstruct", "captures/x", "--mask-alpha", bad, "--out", str(tmp_path))
        assert res.exit_code == 2 and "--mask-alpha" in res.output, (bad, res.output)
    assert len(flow_calls) == calls


def test_reconstruct_passes_the_frozen_sets_fraction_to_its_flow(flow_calls, tmp_path):
    """`--set-frozen-from F` (0: off): passed as given, the preset's when omitted, refused outside [0, 0.99]."""
    assert _invoke("reconstruct", "captures/x", "--out", str(tmp_path)).exit_code == 0
    assert flow_calls[-1]["set_frozen_from"] is None
    for given in ("0", "0.3"):
        res = _invoke("reconstruct", "captures/x", "--set-frozen-from", given, "--out", str(tmp_path))
        assert res.exit_code == 0 and flow_calls[-1]["set_frozen_from"] == float(given), res.output
    for bad in ("1", "-0.1", "x"):
        res = _invoke("reconstruct", "captures/x", "--set-frozen-from", bad, "--out", str(tmp_path))
        assert res.exit_code == 2 and "--set-frozen-from" in res.output, (bad, res.output)


def test_conflicting_or_bad_options_are_refused_before_any_flow(flow_calls, tmp_path):
    marks = tmp_path / "marks.json"
    marks.write_text(json.dumps(MARKS))
    # a given calibration (or the ground truth) runs none: its options would be silently ignored
    for extra in (["--calibration", "calibrations/x"], ["--ground-truth"]):
        res = _invoke("reconstruct", "captures/x", "--allow-unregistered", *extra)
        assert res.exit_code == 2 and "--allow-unregistered" in res.output, res.output
    res = _invoke("calibrate", "captures/x", "--known-distance", "S001,S002,3", "--known-points", str(marks))
    assert res.exit_code == 2 and "not both" in res.output
    res = _invoke("calibrate", "captures/x", "--known-distance", "S001,3")
    assert res.exit_code == 2 and "CAM_A,CAM_B,METRES" in res.output
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**MARKS, "points": {**MARKS["points"], "A": {"S001": [1.0, 2.0]}}}))
    res = _invoke("calibrate", "captures/x", "--known-points", str(bad))
    assert isinstance(res.exception, cli.CommandError)
    assert str(res.exception) == f"{bad}: point A is marked in 1 camera(s) (S001); it needs at least two"
    # a file that is not JSON, or is missing, is named (the same check for every JSON option)
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    for opt, path in (("--known-points", broken), ("--colour-charts", broken), ("--known-points", tmp_path / "no.json")):
        res = _invoke("calibrate", "captures/x", opt, str(path))
        assert isinstance(res.exception, cli.CommandError), res.output
        assert str(res.exception).startswith(f"{path}: not a readable JSON file"), res.exception
    assert flow_calls == []


def test_help_lists_the_options():
    for cmd, opts in (("reconstruct", ("--allow-unregistered", "--known-distance", "--known-points", "--min-pair-inliers")),
                      ("calibrate", ("--allow-unregistered", "--known-distance", "--known-points", "--min-pair-inliers"))):
        res = CliRunner().invoke(cli.app, [cmd, "--help"], terminal_width=200)
        assert res.exit_code == 0 and all(o in res.output for o in opts), res.output


# -- the flows: the same options give the same calibration settings from either command -------


class _Stop(Exception):
    pass


@pytest.fixture
def capture_store(tmp_path):
    rig = load_rig("demo_scene")
    cams = tuple(CaptureCamera(id=c, width=320, height=180, channels=("R", "G", "B"), source_encoding="linear",
                               frames=()) for c in ("S001", "S002", "S003"))
    s = ArtifactStore(str(tmp_path / "store"))
    ref = s.put_record(Capture(name="opts", rig=rig, fps=24.0, start_timecode="01:00:00:00", frame_count=4,
                               cameras=cams))
    s.set_ref("captures/opts", ref)
    return s.url, ref


@pytest.fixture
def calibrations(monkeypatch):
    """(static options, known points) each flow asks ``calibrate_capture`` for; the flow stops there."""
    asked: list[tuple] = []

    def fake(store, capture, static_options=None, known_points=None, tracking_options=None):
        asked.append((static_options, known_points, tracking_options))
        raise _Stop

    for module in (calibrate_flows, reconstruct_flows):
        monkeypatch.setattr(module, "calibrate_capture", fake)
        monkeypatch.setattr(module, "get_run_logger", lambda: logging.getLogger("test"))
    return asked


@pytest.mark.parametrize("options", [{}, {"allow_unregistered": True},
                                     {"known_distance": ("S001", "S003", 4.0)}, {"known_points": MARKS},
                                     {"allow_unregistered": True, "known_points": MARKS},
                                     {"allow_unregistered": True, "min_pair_inliers": 20}])
def test_calibrate_and_reconstruct_ask_for_the_same_calibration(capture_store, calibrations, options):
    store, ref = capture_store
    with pytest.raises(_Stop):
        calibrate_flows.calibrate_flow.fn(store=store, capture="captures/opts", **options)
    with pytest.raises(_Stop):
        reconstruct_flows.reconstruct_flow.fn(store=store, capture="captures/opts", preset="test", **options)
    (static_c, known_c, tracking_c), (static_r, known_r, tracking_r) = calibrations
    assert static_c == static_r and known_c == known_r and tracking_c == tracking_r
    if not options:   # nothing given: the task's defaults, the key of `calibrate_static(store, capture)`
        assert static_r is None and known_r is None
    # the tracking cameras: their defaults' key, or an unsupported one left out as a static one is
    assert tracking_r == (TrackingOptions(allow_unsupported=True) if options.get("allow_unregistered") else None)
    if options.get("allow_unregistered") and "min_pair_inliers" not in options:
        assert static_r == StaticCalibrationOptions(allow_unregistered=True)
    if "min_pair_inliers" in options:
        assert static_r == StaticCalibrationOptions(allow_unregistered=True,
                                                    sfm=replace(StaticSfmOptions(), min_pair_inliers=20))
    if "known_points" in options:
        assert known_r == KnownPoints.model_validate(MARKS)
    keys = {task_cache_key(calibrate_static, store, capture=ref,
                           **({} if s is None else {"options": s}), **({} if k is None else {"known_points": k}))
            for s, k, _ in calibrations}
    assert len(keys) == 1


def test_reconstruct_refuses_calibration_options_it_would_not_use(capture_store, calibrations):
    store, _ = capture_store
    with pytest.raises(ValueError, match="allow_unregistered: settings of the calibration reconstruct runs itself"):
        reconstruct_flows.reconstruct_flow.fn(store=store, capture="captures/opts", calibration="calibrations/x",
                                              allow_unregistered=True)
    with pytest.raises(ValueError, match="known_points.*the ground truth"):
        reconstruct_flows.reconstruct_flow.fn(store=store, capture="captures/opts", ground_truth=True,
                                              known_points=MARKS)
    assert calibrations == []


def test_known_points_are_in_the_static_calibrations_cache_key(capture_store):
    store, ref = capture_store
    marks = KnownPoints.model_validate(MARKS)
    none = task_cache_key(calibrate_static, store, capture=ref)
    given = task_cache_key(calibrate_static, store, capture=ref, known_points=marks)
    longer = task_cache_key(calibrate_static, store, capture=ref,
                            known_points=marks.model_copy(update={"distance_m": 2.6}))
    moved = dict(MARKS, points={**MARKS["points"], "A": {**MARKS["points"]["A"], "S001": [101.0, 120.0]}})
    clicked = task_cache_key(calibrate_static, store, capture=ref, known_points=KnownPoints.model_validate(moved))
    assert len({none, given, longer, clicked}) == 4
    assert task_cache_key(calibrate_static, store, capture=ref, known_points=None) == none


def test_calibrate_prints_where_the_scale_came_from(flow_calls, monkeypatch, tmp_path):
    frame = {"scale_source": 2.0, "mount_residual_rms_m": 0.0193, "mount_residual_max_m": 0.0262,
             "known_points_distance_m": 3.0, "known_points_triangulated_m": 3.0048, "known_points_sigma_m": 0.0135,
             "known_points_scale": 0.99841, "known_points_residual_max_m": 0.0, "known_points_distances": 1.0}
    monkeypatch.setattr(_Summary, "result", {**_Summary.result, "stage_frame": frame})
    marks = tmp_path / "marks.json"
    marks.write_text(json.dumps(MARKS))
    res = _invoke("calibrate", "captures/x", "--known-points", str(marks))
    assert res.exit_code == 0, res.output
    assert ("no lidar scan: stage frame and scale from the known distance between scene points; camera centres "
            "1.9 cm rms (max 2.6 cm) from their mounts") in res.output
    assert "known points: 3.000 m measured, 3.005 m ± 13.5 mm triangulated; scaled by 0.99841" in res.output
