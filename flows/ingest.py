"""The ingest flow: a capture folder in, a Capture record (and ``captures/<name>`` ref) out."""

from __future__ import annotations

import os
from pathlib import Path

from prefect import flow, get_run_logger, unmapped

from tasks.ingest import fingerprint_camera, ingest_camera, ingest_video_camera, record_capture
from volcap_core import ingest
from volcap_core.capture import CaptureCamera, CaptureFolder, IngestError
from volcap_core.records import MEDIA_EXR, ArtifactRef
from volcap_core.store import ArtifactStore


@flow(name="ingest", persist_result=False, log_prints=False)
def ingest_flow(store: str, capture_dir: str, nan_policy: str = "error", set_ref: bool = True) -> ArtifactRef:
    """Check the whole folder, convert every camera (fanned out), then record the capture.

    Returns the Capture record's ref; also names it ``captures/<name>`` in the store. The lidar scan
    named by ``capture.json`` is checked with the other inputs and stored with the record, and so
    are the performer masks of its masks folder (every one decoded and checked before any frame
    is converted; stored as one-channel half EXRs referenced by their camera's record).
    """
    log = get_run_logger()
    capture = CaptureFolder.open(Path(capture_dir).resolve())
    folder, desc, rig = capture.root, capture.description, capture.rig
    s = ArtifactStore(store)

    # 1. Everything that can be checked without decoding pixels, for all cameras, first.
    rig_cams, absent = ingest.match_rig(desc, rig)
    if absent:
        log.warning("rig %s cameras not in this capture: %s", rig.name, ", ".join(absent))
    recorded = {c.id: capture.frame_files(c.id) for c in desc.cameras}
    common = ingest.common_range(recorded)
    scans = {}
    for c in desc.cameras:
        scans[c.id], outside = ingest.select_take(desc, c, recorded[c.id], common)
        if outside:
            log.info("camera %s: %d recorded frame(s) outside the take left out", c.id, outside)
    lenses = {c.id: ingest.lens_for_take(desc, c, rig_cams[c.id]) for c in desc.cameras}
    for c in desc.cameras:
        if c.is_video:
            used = ingest.check_video(c, rig_cams[c.id], capture.video_info(c.id), desc.fps)
            log.info("camera %s: %s decoded as transfer %s, %s range, matrix %s, primaries %s", c.id,
                     capture.video_info(c.id).path, used.transfer, used.range, used.matrix, used.primaries)
        else:
            ingest.check_headers(c, rig_cams[c.id], scans[c.id])
    lidar_file = ingest.check_lidar(capture)
    with_masks = {c.id: n for c in desc.cameras if (n := ingest.check_masks(capture, c, rig_cams[c.id]))}
    if with_masks:
        log.info("performer masks: %d camera(s), %d masks checked", len(with_masks), sum(with_masks.values()))
    ocio_ref = None
    if desc.ocio_config:
        ocio_file = folder / desc.ocio_config
        if not ocio_file.is_file():
            raise IngestError(f"{capture.description_path}: ocio_config {ocio_file} does not exist")
        ocio_ref = s.put_file(ocio_file, "application/x-ocio", check_first=True)

    # 2. Fingerprint and convert, one task per camera (a video camera's one file, once).
    files = [[str(capture.video_info(c.id).path)] if c.is_video else [str(f.path) for f in scans[c.id]]
             for c in desc.cameras]
    stats = [[_stat(p) for p in fs] for fs in files]
    # Every fingerprint first (hashing: quick beside a conversion), then the conversions on their
    # results: handed futures, each ingest-camera run asked the API for its upstream run's state
    # (0.1-0.2 s a camera while the server records events), and a cached rerun waited for that.
    manifests = [m.result() for m in
                 fingerprint_camera.map(unmapped(store), [c.id for c in desc.cameras], files, stats)]
    images = [i for i, c in enumerate(desc.cameras) if not c.is_video]
    videos = [i for i, c in enumerate(desc.cameras) if c.is_video]

    def pick(values: list, which: list[int]) -> list:
        return [values[i] for i in which]

    cams = list(desc.cameras)
    rig_list = [rig_cams[c.id] for c in cams]
    offsets = [desc.take_offset(c) for c in cams]
    lens_list = [lenses[c.id] for c in cams]
    futures = {}
    if images:
        futures.update(zip(images, ingest_camera.map(
            unmapped(store), unmapped(str(folder)), pick(cams, images), pick(rig_list, images),
            pick(manifests, images), pick(offsets, images), unmapped(desc.take.frame_count),
            unmapped(ocio_ref), unmapped(nan_policy), pick(lens_list, images))))
    if videos:
        futures.update(zip(videos, ingest_video_camera.map(
            unmapped(store), unmapped(str(folder)), pick(cams, videos), pick(rig_list, videos),
            pick(manifests, videos), pick(offsets, videos), unmapped(desc.take.frame_count),
            unmapped(desc.fps), unmapped(nan_policy), pick(lens_list, videos))))
    cameras = [futures[i] for i in range(len(cams))]
    # the masks (checked above) are stored while the cameras convert: decoded again, not held
    masks = {c.id: _store_masks(s, capture, c.id, rig_cams[c.id].sensor.width_px, rig_cams[c.id].sensor.height_px)
             for c in cams if c.id in with_masks}

    ground_truth = None
    gt = capture.ground_truth_path
    if gt is not None:
        if not gt.is_dir():
            raise IngestError(f"{capture.description_path}: ground_truth folder {gt} does not exist")
        ground_truth = s.put_directory(gt)
    lidar = s.put_file(lidar_file, ingest.MEDIA_PLY, check_first=True) if lidar_file is not None else None

    # 3. Only when every camera converted: the record, then its name.
    capture_ref = record_capture(store, desc.name, rig, desc.fps, desc.take.start_timecode,
                                 desc.take.frame_count,
                                 [_with_masks(c.result(), masks.get(c.result().id)) for c in cameras],
                                 ground_truth, lidar, desc.performer)
    if set_ref:
        s.set_ref(f"captures/{desc.name}", capture_ref)
    log.info("capture %s: %d cameras x %d frames -> %s", desc.name, len(desc.cameras),
             desc.take.frame_count, capture_ref.digest)
    return capture_ref


def _store_masks(s: ArtifactStore, capture: CaptureFolder, camera_id: str, width: int, height: int
                 ) -> tuple[ArtifactRef, ...]:
    """A camera's performer masks, take index order, stored as :func:`volcap_core.ingest.mask_exr`s."""
    files = ingest.select_masks(capture, capture.camera(camera_id))
    return tuple(s.put_bytes(ingest.mask_exr(ingest.checked_mask(capture, camera_id, i, width, height), camera_id, i,
                                             path), MEDIA_EXR) for i, path in enumerate(files))


def _with_masks(camera: CaptureCamera, masks: tuple[ArtifactRef, ...] | None) -> CaptureCamera:
    return camera if masks is None else camera.model_copy(update={"masks": masks})


def _stat(path: str) -> list[int]:
    st = os.stat(path)
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
