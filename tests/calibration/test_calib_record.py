"""The Calibration record: canonical JSON round trip, camera_at, the tracking-frames blob."""

from __future__ import annotations

import numpy as np
import pytest

from volcap_core.calibration.geometry import look_at_rotation, pose_matrix
from volcap_core.calibration.record import (Calibration, CameraCalibration, TrackingFrames, camera_at,
                                            decode_tracking_frames, encode_tracking_frames, matrix4,
                                            tracking_frames_ref)
from volcap_core.records import MEDIA_SAFETENSORS
from volcap_core.store import ArtifactStore


def _pose(c, look=(0.0, 0.0, 1.0)):
    R = look_at_rotation(c, look)
    return pose_matrix(R, -R @ np.asarray(c, float))


def _tracking(T=5):
    K = np.stack([np.array([1800.0 + 10 * t, 1800.0 + 10 * t, 159.5, 89.5]) for t in range(T)])
    W = np.stack([_pose((5.0, 0.1 * t, 1.8), (0.0, 0.0, 1.6)) for t in range(T)])
    return {"T1": TrackingFrames(K, W)}


def _record(blob: bytes | None) -> Calibration:
    cams = (CameraCalibration(id="S0", role="static", static=True, width=320, height=180,
                              intrinsics=(310.0, 310.0, 159.5, 89.5), world_to_camera=matrix4(_pose((4.0, -3.0, 1.3)))),
            CameraCalibration(id="T1", role="tracking-landscape", static=False, width=320, height=180,
                              quality={"focal_gain": 1.01}))
    return Calibration(capture="demo", frame_count=5, fps=24.0, reference_frame=2, stage_size_m=(4.0, 4.0, 3.5),
                       cameras=cams, tracking_frames=tracking_frames_ref(blob) if blob else None)


def test_record_round_trips_as_canonical_json():
    blob = encode_tracking_frames(_tracking())
    rec = _record(blob)
    data = rec.to_canonical_json()
    back = Calibration.from_json_bytes(data)
    assert back == rec
    assert back.to_canonical_json() == data
    assert Calibration.media_type() == "application/vnd.volcap.calibration+json"
    assert back.static_ids == ["S0"] and back.tracking_ids == ["T1"]
    assert len(data) < 4000, "the record stays JSON-small: per-frame arrays live in the blob"


def test_scene_depth_is_kept_and_a_record_without_it_is_unchanged():
    """A static camera's view of the scene (``scene_depth_m``: where its dense points sweep) round
    trips; a record made before it existed reads back with None and writes the same bytes (the
    same digest), and depths out of order are refused, naming the field."""
    rec = _record(None)
    old = rec.to_canonical_json()
    assert b"scene_depth_m" not in old
    back = Calibration.from_json_bytes(old)
    assert back.camera("S0").scene_depth_m is None and back.to_canonical_json() == old
    cams = (rec.cameras[0].model_copy(update={"scene_depth_m": (2.5, 6.0, 11.0)}),) + rec.cameras[1:]
    new = rec.model_copy(update={"cameras": cams})
    again = Calibration.from_json_bytes(new.to_canonical_json())
    assert again.camera("S0").scene_depth_m == (2.5, 6.0, 11.0)
    assert again.to_canonical_json() == new.to_canonical_json()
    with pytest.raises(ValueError, match="scene_depth_m"):
        CameraCalibration(id="S1", role="static", static=True, width=320, height=180, scene_depth_m=(6.0, 2.5, 11.0))


def test_tracking_blob_round_trip_and_ref_matches_store(tmp_path):
    frames = _tracking()
    blob = encode_tracking_frames(frames)
    assert blob == encode_tracking_frames(frames), "deterministic bytes"
    back = decode_tracking_frames(blob)
    np.testing.assert_array_equal(back["T1"].intrinsics, frames["T1"].intrinsics)
    np.testing.assert_array_equal(back["T1"].world_to_camera, frames["T1"].world_to_camera)
    store = ArtifactStore(f"file://{tmp_path}/store")
    ref = store.put_bytes(blob, MEDIA_SAFETENSORS)
    assert ref == tracking_frames_ref(blob)
    rec = _record(blob)
    assert store.get_bytes(rec.tracking_frames) == blob


def test_camera_at_static_and_tracking():
    frames = _tracking()
    rec = _record(encode_tracking_frames(frames))
    K, W, w, h = camera_at(rec, "S0", 3)
    assert (w, h) == (320, 180)
    np.testing.assert_allclose(K, [[310, 0, 159.5], [0, 310, 89.5], [0, 0, 1]])
    np.testing.assert_allclose(W, _pose((4.0, -3.0, 1.3)), atol=1e-9)
    K, W, _, _ = camera_at(rec, "T1", 4, decode_tracking_frames(encode_tracking_frames(frames)))
    assert K[0, 0] == pytest.approx(1840.0)
    np.testing.assert_allclose(W, frames["T1"].world_to_camera[4])
    with pytest.raises(ValueError, match="tracking camera"):
        camera_at(rec, "T1", 0)
    with pytest.raises(IndexError):
        camera_at(rec, "S0", 5)
    with pytest.raises(KeyError):
        camera_at(rec, "nope", 0)


def test_invalid_pose_and_arrays_are_refused():
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="rotation"):
        CameraCalibration(id="S0", role="static", static=True, width=4, height=4, intrinsics=(1, 1, 1, 1),
                          world_to_camera=tuple(map(tuple, bad)))
    with pytest.raises(ValueError, match=r"\[T, 4\]"):
        encode_tracking_frames({"T": TrackingFrames(np.zeros((3, 3)), np.zeros((3, 4, 4)))})
    with pytest.raises(ValueError, match="non-finite"):
        encode_tracking_frames({"T": TrackingFrames(np.full((1, 4), np.nan), np.zeros((1, 4, 4)))})
