"""bench/detail_ceiling.py: a camera's noise-free recording scores detail below 1 on its noisy
footage, as the sensor's noise model predicts, and 1 on footage recorded without noise.

Two tiny demo_scene captures of a static and a tracking camera (2 frames, 2×2 samples a pixel), one
as synthesized and one synthesized with its sensors' noise set to 0; their views built as
``segment_data`` builds a store's (the ground-truth cameras as splat cameras, the performer masks),
scored through the bench's functions with S009 held out (its cross-fitted gain/offset); and the
recordings against whole frames. About 12 s on the shared 2 cores."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from tests.gpu_machine import load_bench
from volcap_core.reconstruction import splat_camera
from volcap_core.splat.train import View
from volcap_core.synth import synthesize_capture
from volcap_core.synth.ground_truth import face_region, performer_mask
from volcap_core.synth.io import read_exr
from volcap_core.synth.sensor import SensorModel
from volcap_core.synth.truth import capture_camera, capture_recording, capture_sensor, truth_world_from_folder

CAMERAS = ["S000", "S009"]   # a static camera, a tracking one framing a head
ROLES = {"S000": "static", "S009": "tracking"}
HELD_OUT = ["S009"]
FRAMES = 2
#: samples a pixel side, as `volcap synth` (a tracking camera samples its set at 1: the recording must too)
SUPERSAMPLE = 2

bench = load_bench("detail_ceiling")


def _capture(root, noise: bool):
    with pytest.MonkeyPatch.context() as mp:
        if not noise:   # the same sensors (same draws), their read and shot noise 0
            random = SensorModel.random
            mp.setattr(SensorModel, "random", staticmethod(
                lambda rng, zoom: dataclasses.replace(random(rng, zoom), read_noise=0.0, shot_noise=0.0)))
        synthesize_capture(root, rig="demo_scene", seed=3, frames=FRAMES, supersample=SUPERSAMPLE, cameras=CAMERAS,
                           write_depth=True)
    return root


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    return _capture(tmp_path_factory.mktemp("ceiling") / "noisy", noise=True)


@pytest.fixture(scope="module")
def noiseless(tmp_path_factory):
    return _capture(tmp_path_factory.mktemp("ceiling") / "noiseless", noise=False)


def _figures(root) -> dict:
    """The bench's figures of every view of the capture folder ``root``."""
    cams = json.loads((root / "ground_truth" / "cameras.json").read_text())
    scene = json.loads((root / "ground_truth" / "scene.json").read_text())
    views = []
    for cid in CAMERAS:
        offset = cams["cameras"][cid]["take_offset"]
        for k in range(FRAMES):
            pin = capture_camera(cams, cid, k)
            image = torch.from_numpy(read_exr(root / "frames" / cid / f"{k - offset:06d}.exr")[..., :3].copy())
            mask = performer_mask((root / "ground_truth" / "masks" / cid / f"{k:06d}.exr").read_bytes())
            views.append(View(cid, k, k / cams["fps"], splat_camera(pin.K, pin.world_to_camera, pin.width, pin.height),
                              image, torch.from_numpy(mask.astype("float32"))))

    def head(v: View):
        c = v.camera
        return face_region(scene, v.time, c.K.numpy(), c.world_to_camera.numpy(), c.width, c.height)

    noise_free, redrawn = bench.recordings(views, truth_world_from_folder(root), cams, supersample=SUPERSAMPLE)
    sensors = {c: capture_sensor(cams, c) for c in CAMERAS}
    return bench.ceiling(views, [v.load()[..., :3] for v in views], noise_free, redrawn, ROLES, HELD_OUT,
                         sensors, head)


def _each(figures: dict):
    """(view set, role, per-role figures) of both cameras."""
    assert figures["held_out"]["tracking"]["cameras"] == ["S009"]
    assert figures["training"]["static"]["cameras"] == ["S000"]
    yield "held_out", "tracking", figures["held_out"]["tracking"]
    yield "training", "static", figures["training"]["static"]


def test_a_noise_free_recording_scores_below_1_on_noisy_footage_as_the_noise_model_predicts(noisy):
    figures = _figures(noisy)
    print(json.dumps(figures, indent=1))
    for which, role, r in _each(figures):
        for region in ("performers", "face"):
            nf, pred, rd = r["noise_free"][region], r["predicted"][region], r["redrawn"][region]
            assert nf["views"] == FRAMES, (which, region)
            # the footage's noise adds gradient energy the recording has not: the ceiling is below 1
            assert nf["detail"] < 0.97, (which, role, region, nf)
            # by as much as the noise model says (its PSNR is the noise's, its detail E / (E + N)):
            # the prediction is the expectation, a region of a few thousand values draws within 1-2 %
            assert abs(nf["psnr"] - pred["psnr"]) < 0.3, (which, role, region, nf, pred)
            assert abs(nf["detail"] - pred["detail"]) < 0.04, (which, role, region, nf, pred)
            # a second recording of the same instant has the footage's energy, and twice the noise
            assert abs(rd["detail"] - 1) < 0.1, (which, role, region, rd)
            assert abs(rd["psnr"] - (pred["psnr"] - 3.01)) < 0.5, (which, role, region, rd, pred)


def test_a_noise_free_recording_scores_1_on_footage_recorded_without_noise(noiseless):
    figures = _figures(noiseless)
    for which, role, r in _each(figures):
        for region in ("performers", "face"):
            nf = r["noise_free"][region]
            # what is left is the footage's half-float storage (relative steps of 2^-11, ~5e-4; in
            # display sRGB a few 1e-4 beside gradients of ~1e-2) and, held out, a gain/offset fitted
            # on the other frame (identity to the fit's tolerance): both far below 1 %
            assert abs(nf["detail"] - 1) < 0.01, (which, role, region, nf)
            assert nf["psnr"] > 55, (which, role, region, nf)


def test_a_capture_cameras_recording_is_its_footage_less_the_noise(noisy, noiseless):
    """``capture_recording`` over whole frames (the set too, which the regions above barely see)."""
    for root, noise in ((noisy, True), (noiseless, False)):
        cams = json.loads((root / "ground_truth" / "cameras.json").read_text())
        world = truth_world_from_folder(root)
        for cid in CAMERAS:
            k = 1
            frame = read_exr(root / "frames" / cid / f"{k - cams['cameras'][cid]['take_offset']:06d}.exr")[..., :3]
            rec = capture_recording(world, cams, cid, k, supersample=SUPERSAMPLE)
            if noise:   # the residual is the sensor's noise: variance read² + shot·S a value
                s = capture_sensor(cams, cid)
                var = s.read_noise ** 2 + s.shot_noise * np.maximum(rec - np.asarray(s.black, np.float32), 0)
                z2 = float(((frame - rec) ** 2 / var).mean())
                assert 0.95 < z2 < 1.05, (cid, z2)
            else:       # the same values, to the footage's half-float rounding (2^-11 relative)
                np.testing.assert_allclose(frame, rec, rtol=2 ** -10, atol=1e-7, err_msg=cid)
