"""Ingest tasks: fingerprint a camera's raw files, convert them, record the capture."""

from __future__ import annotations

import tempfile
from pathlib import Path

from hardware.rig import Rig, RigCamera
from tasks.contract import volcap_task
from volcap_core import ingest
from volcap_core.capture import CameraSource, Capture, CaptureCamera, LensSample, Performer
from volcap_core.records import MEDIA_EXR, ArtifactRef
from volcap_core.store import ArtifactStore

RAW_MANIFEST_MEDIA = "application/vnd.volcap.raw-manifest+json"
#: a converted frame's bytes depend on the decoder (OpenImageIO), the colour conversion
#: (OpenColorIO, numpy) and the encoder's compression (OpenEXR)
INGEST_LIBRARIES = ("OpenImageIO", "PyOpenColorIO", "OpenEXR", "numpy")
#: a converted video frame's bytes depend on the decoder (PyAV's FFmpeg), the transfer function
#: (torch), primaries (OpenColorIO) and the encoder (OpenEXR)
VIDEO_INGEST_LIBRARIES = ("av", "torch", "PyOpenColorIO", "OpenEXR", "numpy")


@volcap_task(name="fingerprint-camera", version="1")
def fingerprint_camera(store: str, camera_id: str, files: list[str], file_stats: list[list[int]]) -> ArtifactRef:
    """BLAKE3 of a camera's raw files, as a manifest object.

    Keyed on the files' paths and (size, mtime_ns, ctime_ns, inode): an untouched folder is not
    re-read on a rerun, while replacing a file (which always changes its ctime) re-hashes it.
    """
    from volcap_core.ingest import RawFrame

    frames = [RawFrame(take_index=i, camera_frame=-1, path=Path(p)) for i, p in enumerate(files)]
    entries = ingest.fingerprint(frames)
    return ArtifactStore(store).put_json(ingest.raw_manifest_json(camera_id, entries), RAW_MANIFEST_MEDIA)


@volcap_task(name="ingest-camera", version="3", locations=("capture_dir",), libraries=INGEST_LIBRARIES)
def ingest_camera(store: str, capture_dir: str, camera: CameraSource, rig_camera: RigCamera,
                  raw_manifest: ArtifactRef, take_offset: int, frame_count: int,
                  ocio_config: ArtifactRef | None, nan_policy: str,
                  lens: list[LensSample] | None) -> CaptureCamera:
    """Convert one camera's frames to scene-linear half EXR in the store.

    The key holds the raw files' manifest (``raw_manifest``: each file's digest and its path), not
    the folder parameter (``capture_dir``): the same files ingested again are a cache hit; the same
    bytes under another path are converted again (the manifest names the path).
    Version 2: frames are display-window sized, converted to the working primaries from the
    files' ``chromaticities``, taken from the part/view the camera chooses, and say so in
    their headers and the CaptureCamera record.
    """
    s = ArtifactStore(store)
    ocio_path = None
    if ocio_config is not None:
        # Pin the config by content: copy the stored bytes out rather than trusting the folder.
        ocio_path = s.get_file(ocio_config, Path(tempfile.gettempdir()) / "volcap-ocio" / f"{ocio_config.hex}.ocio")
    return ingest.convert_camera(camera, rig_camera, ingest.parse_raw_manifest(s.get_bytes(raw_manifest)),
                                 take_offset, frame_count, ocio_config=ocio_path, nan_policy=nan_policy, lens=lens,
                                 put_frame=lambda data: s.put_bytes(data, MEDIA_EXR))


@volcap_task(name="ingest-video-camera", version="1", locations=("capture_dir",), libraries=VIDEO_INGEST_LIBRARIES)
def ingest_video_camera(store: str, capture_dir: str, camera: CameraSource, rig_camera: RigCamera,
                        raw_manifest: ArtifactRef, take_offset: int, frame_count: int, fps: float,
                        nan_policy: str, lens: list[LensSample] | None) -> CaptureCamera:
    """Decode one video camera's take to scene-linear half EXR in the store.

    The key holds the video file's digest (``raw_manifest``), the camera's decoding settings
    (``camera.video``), which frames (``take_offset``, ``frame_count``) and the decoder's release:
    an unchanged video at the same path is not decoded again (the manifest names the path).
    """
    s = ArtifactStore(store)
    return ingest.convert_video_camera(camera, rig_camera, ingest.parse_raw_manifest(s.get_bytes(raw_manifest)),
                                       take_offset, frame_count, fps, nan_policy=nan_policy, lens=lens,
                                       put_frame=lambda data: s.put_bytes(data, MEDIA_EXR))


@volcap_task(name="record-capture", version="3")
def record_capture(store: str, name: str, rig: Rig, fps: float, start_timecode: str, frame_count: int,
                   cameras: list[CaptureCamera], ground_truth: ArtifactRef | None,
                   lidar: ArtifactRef | None = None, performer: Performer | None = None) -> ArtifactRef:
    """Assemble and store the Capture record (only once every camera converted).

    ``lidar``: the stored lidar scan (PLY) of the static stage, the calibration's input (version 2:
    the record gained the field). ``performer``: whose actor the capture films, as its
    capture.json says (version 3: the record gained the field; a record without one keeps its
    bytes)."""
    capture = Capture(name=name, rig=rig, fps=fps, start_timecode=start_timecode, frame_count=frame_count,
                      cameras=tuple(cameras), ground_truth=ground_truth, lidar=lidar, performer=performer)
    return ArtifactStore(store).put_record(capture)
