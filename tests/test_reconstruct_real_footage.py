"""A small real capture reconstructs into views that look like their footage (issue 30; skipped
without ../shared): Pose2Sim SinglePerson, cameras cam01, cam02 (the pair the plane sweep matches)
and cam04 held out, 2 frames, ingested from the MP4s as a user's capture folder, the studio's
Qualisys calibration (so the calibration is out of the question), trained at 1/8 size (135x240).

What it checks (docs/poly4dgs.md, "Real footage"): without a lidar scan the initial model is the
sweep's points plus the room shell (``splat.init.room_shell``) coloured by the training cameras, so
the untrained model already draws the held-out view's room (before: the sweep's points alone, a
black frame with dots, raw PSNR about 1 dB over the empty model's), and the training views come out
like their footage. ~65 s on 2 busy cores (ingest of 1080x1920 frames, 80 steps), marked slow.
"""

from __future__ import annotations

import json

import pytest
import torch

from tests.calibration.test_pose2sim_calibration import SINGLE, SIZES, _rig

CAMERAS = ["cam01", "cam02", "cam04"]
HELD = "cam04"


@pytest.fixture(scope="module")
def real_capture(prefect_api, tmp_path_factory):
    from flows.ingest import ingest_flow
    from flows.runtime import run_flow
    from volcap_core.calibration.importers import calibration_from_qualisys
    from volcap_core.store import ArtifactStore

    if not SINGLE.is_dir():
        pytest.skip(f"needs {SINGLE} (absent without ../shared)")
    imported = calibration_from_qualisys((SINGLE / "calibration" / "Calib.qca.txt").read_bytes(), "pose2sim", 100,
                                         60.0, frame_sizes=SIZES)
    root = tmp_path_factory.mktemp("real") / "pose2sim"
    (root / "videos").mkdir(parents=True)
    for cid in CAMERAS:
        (root / "videos" / f"{cid}.mp4").symlink_to(SINGLE / "videos" / f"{cid}.mp4")
    rig = _rig(imported)
    rig["cameras"] = [c for c in rig["cameras"] if c["id"] in CAMERAS]
    (root / "rig.json").write_text(json.dumps(rig))
    (root / "capture.json").write_text(json.dumps({
        "format": "volcap-capture/1", "name": "pose2sim", "rig": "rig.json", "fps": 60,
        "take": {"start_timecode": "01:00:00:48", "frame_count": 2},
        "cameras": [{"id": c, "path": f"videos/{c}.mp4", "start_timecode": "01:00:00:00"} for c in CAMERAS]}))
    store = ArtifactStore(str(tmp_path_factory.mktemp("realstore") / "store"))
    capture = run_flow(ingest_flow, store=store.url, capture_dir=str(root)).result
    return store, capture, imported


@pytest.mark.slow
def test_a_real_capture_trains_views_like_its_footage(real_capture):
    from volcap_core.calibration.dense_points_step import dense_points_step
    from volcap_core.capture import Capture
    from volcap_core.imageio.read import decode_exr
    from volcap_core.pointcloud import PointCloudFrame, PointCloudSequence, encode_points
    from volcap_core.production.presets import named_preset
    from volcap_core.segment import fit_segment

    store, capture_ref, imported = real_capture
    cap = store.get_record(capture_ref, Capture)
    calib_ref = store.put_record(imported)

    def load(cam: str, f: int):
        return decode_exr(store.get_bytes(cap.camera(cam).frames[f]))[0][..., :3]

    frames = []
    for f in range(2):   # the sweep at 1/4 size, without the held-out camera (it must not feed the model)
        d = dense_points_step(cap, imported, f, load, scale=0.25, exclude_cameras=[HELD])
        frames.append(PointCloudFrame(frame=f, time=cap.frame_time(f), count=len(d.positions),
                                      points=store.put_bytes(encode_points(d.positions, d.colours))))
    points = PointCloudSequence(calibration=calib_ref, frames=tuple(frames), method="plane-sweep")
    config = named_preset("demo").with_steps(80).train_config(held_out=[HELD], max_gaussians=8000, image_scale=0.125,
                                                             eval_every=0)
    torch.manual_seed(0)
    fitted = fit_segment(cap, capture_ref, imported, calib_ref, points, (0, 2), config, 0,
                         get_bytes=store.get_bytes, put_bytes=store.put_bytes, device="cpu")
    held, training = fitted.report.held_out, fitted.report.training
    print({k: (v.psnr_raw, v.psnr) for k, v in held.items()}, "training", training.psnr)
    # measured here (2026-11-27): untrained held-out raw 12.18 dB against the empty model's 5.30,
    # training views 23.50 dB; before the shell 6.10 and 12.54 (this test failed). The held-out
    # view's gain/offset-fitted figure stays at the floor (13.65 against 13.60 empty, 13.69
    # untrained): one training camera sees cam04's side (docs/poly4dgs.md, "Real footage"), so
    # it is printed, not asserted.
    # the untrained model draws the held-out camera's room (the shell, coloured by the others)
    assert held["initial"].psnr_raw >= held["empty"].psnr_raw + 4.0
    # the training views look like their footage
    assert training.psnr >= 20.0
