"""Video cameras (MP4/MOV): decoded to scene-linear half EXR, their encoding stated and overridable,
cached on the file's digest, refused with one clear error; and the real Pose2Sim MP4s."""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from flows.ingest import ingest_flow
from flows.runtime import run_flow
from hardware.rig import RigCamera
from tasks import ingest as ingest_tasks
from tasks.contract import task_cache_key
from volcap_core import ingest
from volcap_core.digest import digest_bytes
from volcap_core.records import ArtifactRef
from volcap_core.capture import Capture, CameraSource, CaptureFolder, Encoding, IngestError, VideoEncoding
from volcap_core.colour import bt709_oetf, bt709_oetf_inverse
from volcap_core.imageio.read import decode_exr, read_exr_header
from volcap_core.store import ArtifactStore

W, H = 32, 16
#: (Y, Cb, Cr) 8-bit codes of each frame of the test video: black, white, mid grey, a red, a mix
CODES = [(16, 128, 128), (235, 128, 128), (126, 128, 128), (63, 102, 240), (180, 90, 160)]


def write_video(path: Path, codes=CODES, *, width: int = W, height: int = H, fps: int = 24,
                color_range: int | None = None, color_trc: int | None = None, faststart: bool = False) -> Path:
    """An H.264 MP4 with one flat Y'CbCr colour per frame, lossless (x264 qp 0), 4:2:0.
    ``color_range``: FFmpeg's range tag (1 limited, 2 full), none when None. ``faststart``: the
    index (moov) before the pictures, as streaming encoders write it."""
    import av

    with av.open(str(path), "w", options={"movflags": "faststart"} if faststart else {}) as out:
        stream = out.add_stream("libx264", rate=Fraction(fps))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"qp": "0", "preset": "ultrafast"}
        if color_range is not None:
            stream.codec_context.color_range = color_range
        if color_trc is not None:
            stream.codec_context.color_trc = color_trc
        for i, (y, cb, cr) in enumerate(codes):
            frame = av.VideoFrame(width, height, "yuv420p")
            for plane, value in zip(frame.planes, (y, cb, cr)):
                plane.update(bytes([value]) * (plane.line_size * plane.height))
            frame.pts = i
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def expected_linear(y: int, cb: int, cr: int, *, full: bool = False, transfer: str = "bt709") -> np.ndarray:
    """The standards by hand: range expansion, the BT.709 Y'CbCr matrix, the inverse transfer."""
    if full:
        yn, cbn, crn = y / 255.0, (cb - 128) / 255.0, (cr - 128) / 255.0
    else:
        yn, cbn, crn = (y - 16) / 219.0, (cb - 128) / 224.0, (cr - 128) / 224.0
    r = yn + 1.5748 * crn
    b = yn + 1.8556 * cbn
    g = (yn - 0.2126 * r - 0.0722 * b) / 0.7152
    v = np.array([r, g, b])
    if transfer == "srgb":
        return np.where(v < 0.04045, v / 12.92, ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4)
    return np.where(v < 0.081, v / 4.5, ((np.maximum(v, 0.081) + 0.099) / 1.099) ** (1 / 0.45))


def rig_json(sizes: dict[str, tuple[int, int]], fps: float) -> dict:
    cams = []
    for i, (cid, (w, h)) in enumerate(sizes.items()):
        cams.append({"id": cid, "role": "static", "lens": {"focal_min_mm": 14.0, "focal_max_mm": 42.0},
                     "sensor": {"width_mm": 24.0, "height_mm": 24.0 * h / w, "width_px": w, "height_px": h},
                     "mount": {"kind": "tripod", "position_m": [3.0 * np.cos(i), 3.0 * np.sin(i), 1.5],
                               "look_at_m": [0.0, 0.0, 1.0]},
                     "nominal_focal_mm": 20.0})
    return {"name": "video-rig", "kind": "scene", "fps": fps, "stage_size_m": [6.0, 8.0, 4.0], "cameras": cams,
            "lighting": {"description": "test"}}


def write_capture(root: Path, videos: dict[str, str], sizes: dict[str, tuple[int, int]], *, fps: int = 24,
                  frame_count: int = 3, camera_start: str = "00:59:59:23", extra: dict | None = None) -> Path:
    """capture.json + rig.json for video cameras ``id -> path``. The cameras start one frame before
    the take, so take index 0 is each video's frame 1."""
    (root / "rig.json").write_text(json.dumps(rig_json(sizes, fps)))
    cameras = [{"id": cid, "path": path, "start_timecode": camera_start, **(extra or {}).get(cid, {})}
               for cid, path in videos.items()]
    desc = {"format": "volcap-capture/1", "name": "video", "rig": "rig.json", "fps": fps,
            "take": {"start_timecode": "01:00:00:00", "frame_count": frame_count}, "cameras": cameras}
    (root / "capture.json").write_text(json.dumps(desc, indent=1))
    return root


@pytest.fixture
def video_capture(tmp_path: Path) -> Path:
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    write_video(root / "videos" / "cam01.mp4")
    return write_capture(root, {"V0": "videos/cam01.mp4"}, {"V0": (W, H)})


def convert(root: Path, camera_id: str = "V0"):
    """One video camera of a folder converted without Prefect: (record camera, frames [N, H, W, 3],
    their headers)."""
    folder = CaptureFolder.open(root)
    cam = folder.camera(camera_id)
    path = folder.video_info(camera_id).path
    entries = ingest.fingerprint([ingest.RawFrame(0, 0, path)])
    stored: list[bytes] = []
    rig_cam = {c.id: c for c in folder.rig.cameras}[camera_id]

    def put_ref(data: bytes) -> ArtifactRef:
        stored.append(data)
        return ArtifactRef(digest=digest_bytes(data), size=len(data))

    record = ingest.convert_video_camera(cam, rig_cam, entries, folder.offsets[camera_id], folder.frame_count,
                                         folder.fps, nan_policy="error", lens=None, put_frame=put_ref)
    pixels = np.stack([decode_exr(b)[0] for b in stored])
    return record, pixels, stored


def test_a_video_path_is_a_video_camera_and_old_entries_mean_the_same():
    cam = CameraSource(id="V0", path="videos/cam01.MP4", start_timecode="00:00:00:00")
    assert cam.encoding is Encoding.video and cam.video is None
    # a camera without video settings serialises exactly as before the field existed
    old = CameraSource(id="S0", path="S0", start_timecode="00:00:00:00")
    assert "video" not in old.model_dump(mode="json") and old.encoding is Encoding.linear
    with pytest.raises(ValueError, match="is a video file, its encoding must be 'video'"):
        CameraSource(id="V0", path="v.mov", start_timecode="00:00:00:00", encoding="srgb")
    with pytest.raises(ValueError, match="'video' settings need a video file path"):
        CameraSource(id="S0", path="S0", start_timecode="00:00:00:00", video={"range": "full"})
    with pytest.raises(ValueError, match="Extra inputs"):
        CameraSource(id="V0", path="v.mp4", start_timecode="00:00:00:00", video={"gamma": 2.2})


def test_bt709_oetf_inverse_is_the_standard_and_inverts():
    np.testing.assert_allclose(bt709_oetf(np.array([0.0, 0.01, 0.5, 1.0])),
                               [0.0, 0.045, 1.099 * 0.5 ** 0.45 - 0.099, 1.0], rtol=1e-6)
    v = np.linspace(-0.1, 1.1, 241)
    np.testing.assert_allclose(bt709_oetf(bt709_oetf_inverse(v)), v, atol=1e-6)


def test_chroma_is_upsampled_at_the_default_h273_location():
    """Chroma sample j sits on luma column 2j (co-sited) and between luma rows 2i and 2i + 1."""
    from volcap_core.imageio.video import upsample_chroma

    c = np.array([[0, 2, 4], [8, 10, 12]], np.uint8)
    np.testing.assert_array_equal(upsample_chroma(c, 4, 6), [[0, 1, 2, 3, 4, 4], [2, 3, 4, 5, 6, 6],
                                                             [6, 7, 8, 9, 10, 10], [8, 9, 10, 11, 12, 12]])


def test_video_frames_decode_to_the_standards_linear_values(video_capture, tmp_path):
    folder = CaptureFolder.open(video_capture)
    info = folder.video_info("V0")
    assert (info.width, info.height, info.frame_count, info.codec) == (W, H, len(CODES), "h264")
    assert info.tag_transfer is None and info.tag_range is None  # untagged: the defaults apply
    record, pixels, stored = convert(video_capture)
    assert record.source_encoding is Encoding.video and len(record.frames) == 3
    assert record.source_video == VideoEncoding(transfer="bt709", range="limited", matrix="bt709",
                                                primaries="bt709")
    # take index i is the video's frame i + 1 (the camera started one frame before the take)
    for i in range(3):
        want = expected_linear(*CODES[i + 1])
        np.testing.assert_allclose(pixels[i].reshape(-1, 3), np.broadcast_to(want, (H * W, 3)),
                                   atol=2e-3, rtol=2e-3)
    np.testing.assert_allclose(pixels[0], 1.0, atol=1e-3)  # Y' 235 is reference white
    # the folder reader's load: the same frame before its transfer is undone
    np.testing.assert_allclose(folder.load("V0", 2)[0, 0], bt709_oetf(expected_linear(*CODES[3])), atol=1e-4)
    (tmp_path / "f.exr").write_bytes(stored[2])
    header = read_exr_header(tmp_path / "f.exr")
    assert header["volcap.source_video"] == "cam01.mp4" and header["volcap.source_frame"] == "3"
    assert (header["volcap.source_transfer"], header["volcap.source_range"]) == ("bt709", "limited")


def test_range_and_transfer_overrides_change_the_result_as_stated(tmp_path):
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    write_video(root / "videos" / "a.mp4")
    write_capture(root, {"V0": "videos/a.mp4"}, {"V0": (W, H)},
                  extra={"V0": {"video": {"range": "full", "transfer": "srgb"}}})
    record, pixels, _ = convert(root)
    assert (record.source_video.range, record.source_video.transfer) == ("full", "srgb")
    for i in range(3):
        want = expected_linear(*CODES[i + 1], full=True, transfer="srgb")
        np.testing.assert_allclose(pixels[i][0, 0], want, atol=2e-3, rtol=2e-3)
    # white (Y' 235) is no longer 1 in full range: 235/255 through the sRGB curve
    assert abs(float(pixels[0][0, 0, 0]) - ((235 / 255 + 0.055) / 1.055) ** 2.4) < 2e-3


def test_bt2020_primaries_are_converted_to_the_working_space(tmp_path):
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    write_video(root / "videos" / "a.mp4")
    write_capture(root, {"V0": "videos/a.mp4"}, {"V0": (W, H)}, extra={"V0": {"video": {"primaries": "bt2020"}}})
    _, pixels, _ = convert(root)
    grey, red = pixels[1][0, 0], pixels[2][0, 0]
    np.testing.assert_allclose(grey, expected_linear(*CODES[2]), atol=2e-3)  # same D65 white: grey stays
    as_709 = expected_linear(*CODES[3])
    # BT.2020's red lies outside Rec.709's: in Rec.709 terms it is redder, with negative green
    assert red[0] > as_709[0] + 0.05 and red[1] < as_709[1] - 0.02


def test_the_streams_own_range_tag_is_read(tmp_path):
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    write_video(root / "videos" / "a.mp4", color_range=2)
    write_capture(root, {"V0": "videos/a.mp4"}, {"V0": (W, H)})
    assert CaptureFolder.open(root).video_info("V0").tag_range == "full"
    record, pixels, _ = convert(root)
    assert record.source_video.range == "full"
    np.testing.assert_allclose(pixels[0][0, 0], expected_linear(*CODES[1], full=True), atol=2e-3)


def test_ingest_flow_stores_video_frames_and_a_rerun_decodes_nothing(prefect_api, video_capture, tmp_path):
    store = ArtifactStore(str(tmp_path / "store")).url
    first = run_flow(ingest_flow, store=store, capture_dir=str(video_capture))
    s = ArtifactStore(store)
    capture = s.get_record(first.result, Capture)
    cam = capture.camera("V0")
    assert (cam.width, cam.height, len(cam.frames), cam.source_encoding) == (W, H, 3, Encoding.video)
    px, channels = decode_exr(s.get_bytes(cam.frames[2]))
    assert channels == ("R", "G", "B")
    np.testing.assert_allclose(px[0, 0], expected_linear(*CODES[3]), atol=2e-3, rtol=2e-3)
    again = run_flow(ingest_flow, store=store, capture_dir=str(video_capture))
    assert (again.tasks_run, again.tasks_failed) == (0, 0) and again.result == first.result


def test_a_transfer_volcap_does_not_decode_is_refused_until_the_capture_overrides_it(tmp_path):
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    write_video(root / "videos" / "a.mp4", color_trc=16)  # SMPTE ST 2084 (PQ)
    write_capture(root, {"V0": "videos/a.mp4"}, {"V0": (W, H)})
    folder = CaptureFolder.open(root)
    with pytest.raises(IngestError, match=r"camera V0: .*a\.mp4 is tagged with transfer characteristics 16 "
                                          r"\(H\.273 code\), which volcap does not decode; set \"video\": "
                                          r"\{\"transfer\": \.\.\.\}"):
        ingest.check_video(folder.camera("V0"), folder.rig.cameras[0], folder.video_info("V0"), folder.fps)
    write_capture(root, {"V0": "videos/a.mp4"}, {"V0": (W, H)}, extra={"V0": {"video": {"transfer": "bt709"}}})
    record, pixels, _ = convert(root)
    assert record.source_video.transfer == "bt709"
    np.testing.assert_allclose(pixels[0], 1.0, atol=1e-3)


def test_a_truncated_video_is_refused_naming_the_file(tmp_path):
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    path = write_video(root / "videos" / "cut.mp4", CODES * 4)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    write_capture(root, {"V0": "videos/cut.mp4"}, {"V0": (W, H)})
    with pytest.raises(IngestError, match=r"camera V0: .*cut\.mp4: not a readable video"):
        CaptureFolder.open(root).video_info("V0")


def test_a_video_cut_after_its_index_is_refused_at_the_frame_that_does_not_decode(tmp_path):
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    path = write_video(root / "videos" / "cut.mp4", CODES * 8, faststart=True)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.6)])
    write_capture(root, {"V0": "videos/cut.mp4"}, {"V0": (W, H)})
    folder = CaptureFolder.open(root)
    info = folder.video_info("V0")
    assert 0 < info.frame_count < len(CODES) * 8  # the demuxer stops where the bytes do
    entries = ingest.fingerprint([ingest.RawFrame(0, 0, info.path)])
    with pytest.raises(IngestError, match=r"camera V0: .*cut\.mp4: frame \d+ cannot be decoded"):
        ingest.convert_video_camera(folder.camera("V0"), folder.rig.cameras[0], entries, 0, info.frame_count,
                                    24.0, nan_policy="error", lens=None, put_frame=lambda data: None)


def test_a_video_shorter_than_the_take_is_refused_with_its_frame_count(tmp_path):
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    write_video(root / "videos" / "a.mp4")
    write_capture(root, {"V0": "videos/a.mp4"}, {"V0": (W, H)}, frame_count=8)
    folder = CaptureFolder.open(root)
    cam = folder.camera("V0")
    with pytest.raises(IngestError, match=r"camera V0: the take .* \(camera frames 0-4\) \(.*a\.mp4 holds 5 frames\)"):
        ingest.select_take(folder.description, cam, folder.frame_files("V0"))
    # decoding past the end names the file and the frame
    entries = ingest.fingerprint([ingest.RawFrame(0, 0, folder.video_info("V0").path)])
    rig_cam = folder.rig.cameras[0]
    with pytest.raises(IngestError, match=r"a\.mp4: the video ends after 5 frame\(s\); frame 8 is needed"):
        ingest.convert_video_camera(cam, rig_cam, entries, -1, 8, 24.0, nan_policy="error", lens=None,
                                    put_frame=lambda data: None)


def test_a_video_of_another_size_than_the_rig_camera_is_refused(tmp_path):
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    write_video(root / "videos" / "a.mp4")
    write_capture(root, {"V0": "videos/a.mp4"}, {"V0": (W, H + 2)})
    folder = CaptureFolder.open(root)
    with pytest.raises(IngestError, match=rf"camera V0: .*a\.mp4 is {W}x{H} \(h264\), the rig says {W}x{H + 2}"):
        ingest.check_video(folder.camera("V0"), folder.rig.cameras[0], folder.video_info("V0"), folder.fps)


def test_a_video_at_another_frame_rate_than_the_capture_is_refused(tmp_path):
    root = tmp_path / "capture"
    (root / "videos").mkdir(parents=True)
    write_video(root / "videos" / "a.mp4", fps=25)
    write_capture(root, {"V0": "videos/a.mp4"}, {"V0": (W, H)}, fps=24)
    folder = CaptureFolder.open(root)
    with pytest.raises(IngestError, match=r"camera V0: .*a\.mp4 runs at 25 fps, the capture at 24 fps"):
        ingest.check_video(folder.camera("V0"), folder.rig.cameras[0], folder.video_info("V0"), folder.fps)


def test_video_ingest_keys_hold_the_file_digest_frames_and_decoding():
    cam = RigCamera.model_validate(rig_json({"V0": (W, H)}, 24.0)["cameras"][0])
    source = CameraSource(id="V0", path="videos/a.mp4", start_timecode="01:00:00:00")
    def ref(c: str) -> ArtifactRef:
        return ArtifactRef(digest="blake3:" + c * 64, size=10)

    base = dict(capture_dir="/mnt/a", camera=source, rig_camera=cam, raw_manifest=ref("a"), take_offset=0,
                frame_count=3, fps=24.0, nan_policy="error", lens=None)
    key = task_cache_key(ingest_tasks.ingest_video_camera, "file:///tmp/s", **base)
    for change in ({"raw_manifest": ref("b")}, {"take_offset": -1}, {"frame_count": 4},
                   {"camera": source.model_copy(update={"video": VideoEncoding(range="full")})}):
        assert task_cache_key(ingest_tasks.ingest_video_camera, "file:///tmp/s", **{**base, **change}) != key
    assert task_cache_key(ingest_tasks.ingest_video_camera, "file:///tmp/s", **{**base, "capture_dir": "/b"}) == key


POSE2SIM = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "pose2sim" / "Demo_SinglePerson"


@pytest.mark.skipif(not POSE2SIM.is_dir(), reason=f"needs {POSE2SIM} (absent without ../shared)")
def test_the_real_pose2sim_videos_ingest(prefect_api, tmp_path):
    """Demo_SinglePerson: 4 synchronised portrait cameras at 60 fps, 100 frames each; cam01 and cam02
    were re-encoded at 1080 wide (cam02 as VP9, the one stream tagged BT.709 limited), cam03 and
    cam04 are the original 1088 wide H.264, untagged."""
    root = tmp_path / "capture"
    root.mkdir()
    videos = {f"cam0{i}": str(POSE2SIM / "videos" / f"cam0{i}.mp4") for i in range(1, 5)}
    (root / "videos").mkdir()
    for cid, path in videos.items():
        (root / "videos" / f"{cid}.mp4").symlink_to(path)
    sizes = {"cam01": (1080, 1920), "cam02": (1080, 1920), "cam03": (1088, 1920), "cam04": (1088, 1920)}
    write_capture(root, {cid: f"videos/{cid}.mp4" for cid in videos}, sizes, fps=60,
                  camera_start="01:00:00:00", frame_count=3)
    folder = CaptureFolder.open(root)
    infos = {cid: folder.video_info(cid) for cid in videos}
    assert all(i.frame_count == 100 and i.fps == 60 for i in infos.values())
    assert {cid: i.codec for cid, i in infos.items()} == {"cam01": "h264", "cam02": "vp9", "cam03": "h264",
                                                          "cam04": "h264"}
    assert (infos["cam02"].tag_transfer, infos["cam02"].tag_range) == ("bt709", "limited")
    assert infos["cam03"].tag_transfer is None and infos["cam03"].tag_range is None

    store = ArtifactStore(str(tmp_path / "store")).url
    summary = run_flow(ingest_flow, store=store, capture_dir=str(root))
    s = ArtifactStore(store)
    capture = s.get_record(summary.result, Capture)
    for cam in capture.cameras:
        assert len(cam.frames) == 3 and (cam.width, cam.height) == sizes[cam.id]
        assert cam.source_video == VideoEncoding(transfer="bt709", range="limited", matrix="bt709",
                                                 primaries="bt709")
        px, _ = decode_exr(s.get_bytes(cam.frames[1]))
        assert px.shape == (sizes[cam.id][1], sizes[cam.id][0], 3) and np.isfinite(px).all()
        lo, mean, hi = np.percentile(px, 1), float(px.mean()), np.percentile(px, 99)
        # an indoor scene exposed for the people: mid-grey average, black near 0, whites near 1
        assert -0.02 < lo < 0.1 and 0.05 < mean < 0.6 and 0.4 < hi < 1.3, (cam.id, lo, mean, hi)
