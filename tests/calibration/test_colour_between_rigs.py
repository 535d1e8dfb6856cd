"""The colour calibration between the Face Rig and the Scene Rig as a task and a command: a chart
rendered in each rig (volcap_core.synth puts a ColorChecker in both stages), ingested, located in
each view (the scene view by its 24 patch centres, the face view by its four corner patches), the
3x3 matrix fitted by ``volcap calibrate-colour``, its ΔE on the synthetic charts, caching, a bad
input as a one-line error; and ``apply_colour_matrix`` on RGBA images.

One frame of one camera per rig (~5 s of rendering); the command runs twice (~15 s each).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from flows.ingest import ingest_flow
from flows.runtime import run_flow
from volcap_core.calibration.colour import (ColourCalibrationOptions, apply_colour_matrix, chart_grid_px,
                                            colour_residuals)
from volcap_core.calibration.colour_step import ChartView, ColourMatrixRecord, colour_step
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture, synthesize_face_capture

REPO = Path(__file__).resolve().parents[2]
# a frontal face camera and a scene camera that both see their rig's chart whole
FACE, SCENE = "F003", "S001"


def _projected_patches(root: Path, camera: str) -> np.ndarray:
    """The chart's patch centres in a camera at take frame 0, from the synthetic ground truth."""
    cams = json.loads((root / "ground_truth" / "cameras.json").read_text())["cameras"]
    chart = json.loads((root / "ground_truth" / "scene.json").read_text())["chart"]
    f = cams[camera]["frames"][0]
    K = np.array([[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1.0]])
    W = np.array(f["world_to_camera"])
    pc = np.array([p["centre_m"] for p in chart["patches"]]) @ W[:3, :3].T + W[:3, 3]
    return pc[:, :2] / pc[:, 2:] @ K[:2, :2].T + K[:2, 2]


@pytest.fixture(scope="module")
def rigs(prefect_api, tmp_path_factory):
    root = tmp_path_factory.mktemp("colour")
    synthesize_face_capture(root / "face", frames=1, cameras=[FACE], name="face-chart")
    synthesize_capture(root / "scene", frames=1, cameras=[SCENE], actors=1, name="scene-chart")
    store = ArtifactStore(str(root / "store")).url
    for name in ("face", "scene"):
        run_flow(ingest_flow, store=store, capture_dir=str(root / name))
    face_px, scene_px = _projected_patches(root / "face", FACE), _projected_patches(root / "scene", SCENE)
    charts = {"face": {"capture": "captures/face-chart", "camera": FACE, "frame": 0,
                       "corners_px": face_px[[0, 5, 23, 18]].round(2).tolist()},
              "scene": {"capture": "captures/scene-chart", "camera": SCENE, "frame": 0,
                        "patches_px": scene_px.round(2).tolist()}}
    (root / "charts.json").write_text(json.dumps(charts))
    return root, store, charts


def _volcap(*args: str) -> subprocess.CompletedProcess:
    from prefect.settings import PREFECT_API_URL

    env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value()}
    return subprocess.run([sys.executable, "-m", "flows.cli", *args], capture_output=True, text=True, env=env,
                          cwd=REPO, timeout=600)


def test_calibrate_colour_command_fits_the_charts_of_both_rigs(rigs):
    root, store, _ = rigs
    res = _volcap("calibrate-colour", str(root / "charts.json"), "--store", store, "--json")
    assert res.returncode == 0, res.stderr[-2000:]
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    print(res.stdout)
    assert (doc["source_rig"], doc["reference_rig"], doc["patches"]) == ("face", "scene", 24)
    assert (doc["tasks_run"], doc["tasks_failed"]) == (1, 0)
    assert "colour face -> scene" in res.stdout and "ΔE2000 mean" in res.stdout
    # measured (F003 onto S001, take frame 0, the frames as ingested: half float): ΔE2000 7.82
    # mean (9.43 max) before, 0.82 mean (2.35 max) after; what is left is the sensors' vignetting,
    # veiling glare and noise over ~9 px patches in the scene view. Bounds: 1.8x and 1.7x
    assert doc["before"]["delta_e2000_mean"] > 5
    assert doc["after"]["delta_e2000_mean"] < 1.5 and doc["after"]["delta_e2000_max"] < 4.0

    s = ArtifactStore(store)
    assert s.resolve("colour/face-to-scene").digest == doc["colour"]["digest"]
    rec = s.get_record(doc["colour"]["digest"], ColourMatrixRecord)
    assert rec.source.camera == FACE and rec.reference.corners_px is None and len(rec.delta_e2000) == 24
    # the record applied to the face view's patch colours gives the scene view's (RGBA, alpha kept)
    opts = ColourCalibrationOptions()
    from volcap_core.calibration.colour_step import chart_view_colours

    src, _ = chart_view_colours(rec.source, s.get_bytes, opts)
    ref, _ = chart_view_colours(rec.reference, s.get_bytes, opts)
    rgba = np.c_[src, np.full(len(src), 0.5)].astype(np.float32)
    mapped = apply_colour_matrix(rgba, rec)
    assert mapped.dtype == np.float32 and np.all(mapped[:, 3] == 0.5)
    assert colour_residuals(mapped[:, :3], ref)["delta_e2000_mean"] == pytest.approx(rec.after["delta_e2000_mean"],
                                                                                     abs=1e-3)

    again = _volcap("calibrate-colour", str(root / "charts.json"), "--store", store, "--json")
    assert again.returncode == 0, again.stderr[-2000:]
    doc2 = json.loads(again.stdout.strip().splitlines()[-1])
    assert (doc2["tasks_run"], doc2["tasks_cached"]) == (0, 1) and doc2["colour"] == doc["colour"]


def test_bad_chart_input_is_one_line_naming_it(rigs, tmp_path):
    root, store, charts = rigs
    bad = {**charts, "face": {**charts["face"], "camera": "F099"}}
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    res = _volcap("calibrate-colour", str(tmp_path / "bad.json"), "--store", store)
    assert res.returncode == 1
    err = res.stderr.strip().splitlines()
    assert err[-1].startswith("volcap: error:") and "F099" in err[-1] and "face-chart" in err[-1], res.stderr
    assert not any("Traceback" in line for line in err)

    # a chart off the image: too few patches sampled in both views
    off = {**charts, "scene": {**charts["scene"], "patches_px": [[1000.0 + 10 * i, 50.0] for i in range(24)]}}
    (tmp_path / "off.json").write_text(json.dumps(off))
    res = _volcap("calibrate-colour", str(tmp_path / "off.json"), "--store", store)
    assert res.returncode == 1 and "0 patches sampled in both views" in res.stderr.strip().splitlines()[-1]

    missing = _volcap("calibrate-colour", str(tmp_path / "nope.json"), "--store", store)
    assert missing.returncode == 1 and missing.stderr.strip().splitlines()[-1].startswith("volcap: error:")


def test_chart_views_are_refused_when_ambiguous(rigs):
    _, store, _ = rigs
    s = ArtifactStore(store)
    cap = s.resolve("captures/face-chart")
    both = ChartView(rig="face", capture=cap, camera=FACE, patches_px=((1.0, 2.0),) * 24,
                     corners_px=((0, 0), (5, 0), (5, 3), (0, 3)))
    with pytest.raises(CalibrationInputError, match="exactly one of patches_px, corners_px, patches_m"):
        colour_step(both, both, s.get_bytes)


def test_apply_colour_matrix_on_images():
    rng = np.random.default_rng(0)
    M = np.eye(3) + rng.normal(0, 0.05, (3, 3))
    b = np.array([0.01, -0.02, 0.005])
    img = rng.uniform(0, 1, (4, 5, 4)).astype(np.float32)
    out = apply_colour_matrix(img, M, b)
    np.testing.assert_allclose(out[..., :3], img[..., :3].astype(np.float64) @ M.T + b, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(out[..., 3], img[..., 3])
    # premultiplied colour: the offset scales with alpha, a transparent pixel stays transparent black
    img[0, 0] = 0
    pm = apply_colour_matrix(img, M, b, premultiplied=True)
    np.testing.assert_array_equal(pm[0, 0], 0)
    np.testing.assert_allclose(pm[1, 1, :3], img[1, 1, :3] @ M.T + b * img[1, 1, 3], rtol=1e-5, atol=1e-6)
    rgb = apply_colour_matrix(img[..., :3].astype(np.float64), M)
    assert rgb.shape == (4, 5, 3) and rgb.dtype == np.float64
    with pytest.raises(ValueError, match="RGB or RGBA"):
        apply_colour_matrix(np.zeros((2, 2)), M)
    # a torch image (a renderer's frame, mapped on its device): the array's values bit for bit, and
    # the array's dtype rule (float32 stays float32, float64 stays float64)
    t = apply_colour_matrix(torch.from_numpy(img), M, b, premultiplied=True)
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float32
    np.testing.assert_array_equal(t.numpy(), pm)
    # float64 out: the same values to rounding (numpy's and torch's BLAS sum the 3x3 product in their
    # own order: on an AMD EPYC the last bit differed, on the Intel machines it had not)
    t64 = apply_colour_matrix(torch.from_numpy(img[..., :3].astype(np.float64)), M)
    assert t64.dtype == torch.float64
    np.testing.assert_allclose(t64.numpy(), rgb, rtol=1e-15, atol=1e-15)
    with pytest.raises(ValueError, match="RGB or RGBA"):
        apply_colour_matrix(torch.zeros(2, 2), M)


def test_chart_grid_from_corners_is_the_projective_map():
    # a flat 4 x 6 grid seen in perspective: the four corner centres give back every centre
    K = np.array([[300.0, 0, 160], [0, 300.0, 90], [0, 0, 1]])
    a = np.radians(35)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    gy, gx = np.mgrid[0:4, 0:6]
    P = np.c_[0.05 * gx.ravel(), 0.05 * gy.ravel(), np.zeros(24)] @ R.T + [-0.1, -0.05, 1.2]
    uv = P[:, :2] / P[:, 2:] @ K[:2, :2].T + K[:2, 2]
    np.testing.assert_allclose(chart_grid_px(uv[[0, 5, 23, 18]], 4, 6), uv, atol=1e-8)
    with pytest.raises(ValueError, match="degenerate"):
        chart_grid_px(np.array([[0, 0], [1, 1], [2, 2], [3, 3.0]]), 4, 6)
