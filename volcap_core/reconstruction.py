"""From stored records to Poly4DGS inputs and back: the glue the reconstruction tasks call.

A capture (scene-linear EXR frames), a calibration (cameras per frame) and dense points per frame
become :class:`~volcap_core.splat.SegmentData` and :class:`~volcap_core.splat.PointsAtTime`; a
trained segment becomes a :class:`SegmentModel` record. Training settings come from the named
presets of :mod:`volcap_core.production.presets`. Loaders are passed in, so this module never
touches a store or Prefect.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace
from collections.abc import Callable, Sequence
from threading import Lock
from typing import Any, ClassVar, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict

from volcap_core.calibration.distortion import needs_rectify, rectified_valid, rectify_frame
from volcap_core.calibration.record import Calibration, TrackingFrames, camera_at, frame_camera
from volcap_core.capture import Capture
from volcap_core.checkpoint import safetensors_bytes, safetensors_metadata
from volcap_core.imageio.read import decode_exr
from volcap_core.pointcloud import PointCloudSequence
from volcap_core.records import ArtifactRef, Record
from volcap_core.splat import Camera, ExposureGrids, PointsAtTime, SegmentData

SEGMENT_MODEL_MEDIA = "application/vnd.volcap.poly4dgs+safetensors"


class EvalSample(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    step: int
    wall_s: float
    psnr: float | None
    ssim: float | None


class SegmentModel(Record):
    """A trained segment: the Poly4DGS model for take frames [a, b) and how well it does."""

    kind: ClassVar[str] = "segment-model"
    capture: ArtifactRef
    calibration: ArtifactRef
    frames: tuple[int, int]
    fps: float
    model: ArtifactRef                 # safetensors (save_model): Gaussians + config
    grids: ArtifactRef | None = None   # safetensors: per training camera exposure/black grids
    grid_cameras: tuple[str, ...] = ()
    held_out_cameras: tuple[str, ...] = ()
    gaussians: int
    steps: int
    wall_s: float
    #: the trained model's held-out PSNR/SSIM under the protocol of ``splat.scoring``
    held_out_psnr: float | None = None
    held_out_ssim: float | None = None
    #: every figure with its floors: {"held_out": {"trained"|"initial"|"empty": Scores JSON},
    #: "training": Scores JSON} (:meth:`volcap_core.splat.report.SegmentScores.to_json`)
    scores: dict[str, Any] = {}
    contact_sheet: ArtifactRef | None = None   # PNG: footage | render | error
    history: tuple[EvalSample, ...] = ()
    config: dict[str, Any]
    #: the rasterizer that trained it and why (``TrainResult.backend``: ``config["backend"]`` is
    #: what was asked for, this is what ran); None in records written before it was kept
    backend: Literal["gsplat", "torch", "numba"] | None = None
    backend_reason: str | None = None

    @property
    def time_range(self) -> tuple[float, float]:
        """Seconds on the take's clock covered by the segment's frames."""
        return self.frames[0] / self.fps, (self.frames[1] - 1) / self.fps


def splat_camera(K: np.ndarray, world_to_camera: np.ndarray, width: int, height: int,
                 near: float | None = None) -> Camera:
    """A calibration camera (OpenCV, top-left pixel centre at 0) as a splat :class:`Camera`.

    The rasterizer puts pixel centres at +0.5 (gsplat's convention), so cx, cy shift by 0.5.
    ``near``: the near clipping plane in metres of camera depth (a view's ``ViewSpec.near_m``: what
    lies nearer is not drawn); None: the renderer's default.
    """
    K = np.array(K, dtype=np.float64, copy=True)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return Camera(K=torch.tensor(K, dtype=torch.float32),
                  world_to_camera=torch.tensor(np.asarray(world_to_camera), dtype=torch.float32),
                  width=int(width), height=int(height), **({} if near is None else {"near": float(near)}))


class FrameCache:
    """Decoded frames by digest, least recently used out first (a view is drawn many times)."""

    def __init__(self, load_bytes: Callable[[ArtifactRef], bytes], max_frames: int = 512):
        self._load = load_bytes
        self._max = max_frames
        self._frames: OrderedDict[str, torch.Tensor] = OrderedDict()
        self._lock = Lock()

    def __call__(self, ref: ArtifactRef) -> torch.Tensor:
        with self._lock:
            hit = self._frames.get(ref.digest)
            if hit is not None:
                self._frames.move_to_end(ref.digest)
                return hit
        pixels, _ = decode_exr(self._load(ref), name=ref.digest)
        img = torch.from_numpy(np.ascontiguousarray(pixels[..., :3], dtype=np.float32))
        with self._lock:
            self._frames[ref.digest] = img
            while len(self._frames) > self._max:
                self._frames.popitem(last=False)
        return img


def segment_data(capture: Capture, calibration: Calibration, tracking: dict[str, TrackingFrames] | None,
                 frames: tuple[int, int], load_frame: Callable[[ArtifactRef], torch.Tensor],
                 camera_ids: Sequence[str] | None = None, scale: float = 1.0,
                 load_mask: Callable[[str, int], np.ndarray | None] | None = None) -> SegmentData:
    """Views of take frames [a, b) of every (or the given) camera, images loaded lazily.

    ``scale`` < 1 trains at that fraction of the capture's resolution: images are area-averaged
    (what a smaller sensor of the same optics would integrate) and intrinsics scaled to match.
    ``load_mask(camera, take index)``: performer coverage ``[H, W]`` at the capture's resolution
    (a synthetic capture's ground truth), area-averaged like the images; scoring only. Without
    it, the scores use the capture's own performer masks (``CaptureCamera.masks``, imported with
    the footage) where it has them. Those masks, and never a ground truth, are also the views'
    ``matte``: what training's alpha loss reads (``TrainConfig.mask_alpha_weight``).

    A camera the calibration records with lens distortion is trained as the pinhole of its
    record's K: its frames (and masks) are rectified into it as they are loaded
    (:func:`~volcap_core.calibration.distortion.rectify_frame`, before any downscale), and its views
    carry ``valid`` (the pixels whose source lies inside the frame, after a downscale those wholly
    made of such pixels): training's loss and the scores leave the others out. A tracking camera
    with a zoom lens has a lens per frame (the tracking blob's ``distortion``): each frame is
    rectified with its own (:func:`~volcap_core.calibration.record.frame_camera`).
    """
    if not 0 < scale <= 1:
        raise ValueError(f"scale must be in (0, 1], got {scale}")
    a, b = capture.take_range(frames)
    # cameras the calibration left out (the user allowed it: too few observations) are not trained on
    ids = (list(camera_ids) if camera_ids is not None
           else [c.id for c in capture.cameras if c.id not in calibration.unregistered])
    missing = [c for c in ids if c not in {cc.id for cc in calibration.cameras}]
    if missing:
        raise ValueError(f"calibration lacks camera(s) {', '.join(missing)} of capture {capture.name}")

    tracking_ids = set(calibration.tracking_ids) & set(tracking or {})

    def camera_for(cam: str, f: int) -> Camera:
        camera = splat_camera(*camera_at(calibration, cam, f, tracking))
        return camera if scale == 1 else camera.scaled(scale)

    # the valid pixels of each static camera (one lens for the take); a tracking camera's change
    # with its zoom every frame and are recomputed with the frame (its maps are still cached then:
    # distortion.rectify_frame), not kept: 90 zoom cameras x 48 frames of 4K masks would be 36 GB
    valid_cache: dict[str, torch.Tensor | None] = {}

    def lens(cam: str, f: int):
        # the camera at that frame: a tracking camera's lens follows its zoom (record.frame_camera)
        return frame_camera(calibration, cam, f, tracking)

    def valid_of(cam: str, f: int) -> torch.Tensor | None:
        v = rectified_valid(lens(cam, f))
        if v is None:
            return None
        v = torch.from_numpy(np.asarray(v, np.float32))
        if scale != 1:
            size = camera_for(cam, f)
            v = torch.nn.functional.interpolate(v[None, None], size=(size.height, size.width), mode="area")[0, 0]
        return v >= 0.999

    def valid_for(cam: str, f: int) -> torch.Tensor | None:
        if cam in tracking_ids:
            return valid_of(cam, f)
        if cam not in valid_cache:
            valid_cache[cam] = valid_of(cam, f)
        return valid_cache[cam]

    def load_image(cam: str, f: int) -> torch.Tensor:
        image = rectify_frame(load_frame(capture.camera(cam).frames[f]), lens(cam, f))
        if scale == 1:
            return image
        size = camera_for(cam, f)
        return torch.nn.functional.interpolate(image.permute(2, 0, 1)[None], size=(size.height, size.width),
                                               mode="area")[0].permute(1, 2, 0).contiguous()

    def capture_mask(cam: str, f: int) -> np.ndarray | None:
        refs = capture.camera(cam).masks
        return None if refs is None else load_frame(refs[f])[..., 0].numpy()   # stored as one channel Y

    has_masks = any(capture.camera(c).masks is not None for c in ids)
    load_matte = capture_mask if has_masks else None
    if load_mask is None:
        load_mask = load_matte

    def in_view(load: Callable[[str, int], np.ndarray | None]) -> Callable[[str, int], torch.Tensor | None]:
        def coverage(cam: str, f: int) -> torch.Tensor | None:
            m = load(cam, f)
            if m is None:
                return None
            m = torch.from_numpy(np.asarray(rectify_frame(np.asarray(m, np.float32), lens(cam, f))))
            if scale == 1:
                return m
            size = camera_for(cam, f)
            return torch.nn.functional.interpolate(m[None, None], size=(size.height, size.width),
                                                   mode="area")[0, 0]
        return coverage

    distorted = (any(needs_rectify(calibration.camera(c)) for c in ids)
                 or any(tracking[c].distortion is not None and np.any(tracking[c].distortion)
                        for c in ids if c in tracking_ids))
    return SegmentData.build(frames=frames, camera_ids=ids, fps=capture.fps, load_image=load_image,
                             camera_for=camera_for, load_mask=in_view(load_mask) if load_mask is not None else None,
                             load_valid=valid_for if distorted else None,
                             load_matte=in_view(load_matte) if load_matte is not None else None)


def segment_points(points: PointCloudSequence, frames: tuple[int, int],
                   load_points: Callable[[ArtifactRef], tuple[np.ndarray, np.ndarray]],
                   static_scan: bytes | None = None, background: Sequence | None = None,
                   room: np.ndarray | None = None) -> list[PointsAtTime]:
    """The dense points of frames [a, b), one :class:`PointsAtTime` per frame, each point marked
    static or moving (:func:`volcap_core.splat.init.classify_static`): on the capture's lidar scan
    of the empty stage (``static_scan``, PLY bytes in the calibration's world frame) or present in
    most other frames of the segment.

    With a scan and ``background`` views (the static cameras at the segment's middle frame), the
    scan itself, coloured by those views (:func:`~volcap_core.splat.init.colour_scan`), is added
    as one more static cloud: it covers what the plane sweep finds no match on (a plain ceiling,
    the far walls), where the model would otherwise have nothing to draw. Without a scan,
    ``room`` (``[N, 3]``, :func:`~volcap_core.splat.init.room_shell`: a capture of real footage)
    stands in for it and is coloured and added the same way.
    """
    from volcap_core.calibration.lidar import LidarScan
    from volcap_core.splat.init import classify_static, colour_scan

    clouds = []
    for f in range(*frames):
        pf = points.at(f)
        xyz, rgb = load_points(pf.points)
        clouds.append((pf.time, np.asarray(xyz, np.float32), np.asarray(rgb, np.float32)))
    scan = LidarScan.from_ply_bytes(static_scan) if static_scan is not None else None
    static = classify_static([c[1] for c in clouds],
                             scan_distance=None if scan is None else scan.surface_distance)
    out = [PointsAtTime(time=t, xyz=torch.from_numpy(xyz), rgb=torch.from_numpy(rgb),
                        static=torch.from_numpy(st)) for (t, xyz, rgb), st in zip(clouds, static)]
    surface = scan.points if scan is not None else room
    if surface is not None and len(surface) and background:
        rgb, seen = colour_scan(surface, background)
        xyz = np.asarray(surface)[seen].astype(np.float32)
        mid = 0.5 * (clouds[0][0] + clouds[-1][0])
        out.append(PointsAtTime(time=mid, xyz=torch.from_numpy(xyz), rgb=torch.from_numpy(rgb[seen]),
                                static=torch.ones(len(xyz), dtype=torch.bool)))
    return out


def segment_init(load_bytes: Callable[[ArtifactRef], bytes], capture: Capture, points: PointCloudSequence,
                 data: SegmentData, held_out: Sequence[str] = (), zoom_stride_px: int | None = None,
                 hull_oracle_cameras: Sequence[str] = (), scene_flow: bool = False) -> list[PointsAtTime]:
    """What a segment's training starts from, built as the ``train-segment`` task builds it: the
    segment's dense points split static/moving, plus the capture's lidar scan coloured by the
    static training cameras (:func:`segment_points`, :func:`background_views`) or, for a capture
    without one, a room shell around those cameras coloured the same way
    (:func:`~volcap_core.splat.init.room_shell`: the floor at z = 0, walls beyond the cameras).
    Each point carries its finest training camera's pixel footprint (:func:`with_footprints`);
    ``zoom_stride_px`` (``TrainConfig.init_zoom_stride_px``) adds the zoom cameras' points
    (:func:`with_zoom_points`); ``scene_flow`` (``TrainConfig.init_scene_flow``) gives every moving
    point its velocity (:func:`with_scene_flow`). A capture with its own performer masks (its training views carry
    mattes: :func:`has_performer_mattes`) gets the performers' visual hull as each frame's moving
    points, and loses the sweep's moving points outside the stage volume
    (:func:`with_performer_hull`). Anything that must reproduce a stored segment (a resumed run, a
    check) calls this. ``hull_oracle_cameras`` is a benchmark's diagnostic that ``train-segment``
    never sets: those held-out cameras' masks carve the hull too (:func:`with_performer_hull`'s
    ``carve_only``)."""
    from volcap_core.pointcloud import decode_points

    background = background_views(data, capture, held_out)
    room = None
    if not capture.lidar:   # real footage: a room shell around the training cameras stands in for the scan
        from volcap_core.splat.init import room_shell
        from volcap_core.stage import stage_volume

        room = room_shell(np.array([v.camera.centre.double().numpy() for v in background]).reshape(-1, 3),
                          stage_volume(capture.rig.stage_size_m))
    clouds = segment_points(points, data.frames, lambda ref: decode_points(load_bytes(ref)),
                            static_scan=load_bytes(capture.lidar) if capture.lidar else None,
                            background=background, room=room)
    if has_performer_mattes(data, held_out):
        from volcap_core.stage import stage_volume

        clouds = with_performer_hull(clouds, data, held_out, stage_volume(capture.rig.stage_size_m),
                                     carve_only=hull_oracle_cameras)
    clouds = with_footprints(clouds, data, held_out)
    if zoom_stride_px is not None:
        clouds = with_zoom_points(clouds, data, held_out, zoom_stride_px)
    return with_scene_flow(clouds, data, held_out) if scene_flow else clouds


#: the radius that closes a performer mask before the hull is carved from it, as a fraction of the
#: view's shorter side (4 px at Pose2Sim's 270x480, where it closed the plate masks' torso holes)
HULL_CLOSE_FRACTION = 0.015


def has_performer_mattes(data: SegmentData, held_out: Sequence[str] = ()) -> bool:
    """Whether the capture's own performer masks (``View.matte``) reach the training views."""
    return any(v.matte is not None for v in data.views if v.camera_id not in set(held_out))


def with_performer_hull(clouds: Sequence[PointsAtTime], data: SegmentData, held_out: Sequence[str],
                        volume: tuple, *, carve_only: Sequence[str] = ()) -> list[PointsAtTime]:
    """Each frame's cloud with the performers' visual hull added as moving points and the sweep's
    moving points outside the stage ``volume`` dropped (static clouds, the scan or room shell, as
    they are).

    Why: on a sparse real rig the plane sweep puts performer points only where two cameras within
    its triangulation angle see them, and its mismatches land outside the stage; the training
    cameras' masks carve the performers wherever at least two of them see them
    (:func:`~volcap_core.splat.init.visual_hull` of the masks with their holes filled,
    :func:`~volcap_core.splat.init.filled_silhouette`), coloured by those views
    (:func:`~volcap_core.splat.init.colour_scan`). On Pose2Sim it lifted the training views'
    performers by 3.1 dB (``docs/poly4dgs.md``, "Real footage").

    Args:
        clouds: :func:`segment_points`' clouds (per frame; ``static`` set).
        data: the segment's views; the training views with a matte carve (a frame with fewer than
            two keeps its cloud as it is: one camera pins no depth).
        held_out: cameras whose masks carve nothing.
        volume: the stage volume (:func:`volcap_core.stage.stage_volume`), metres.
        carve_only: held-out cameras whose masks carve all the same, colouring nothing: a
            diagnostic (``bench/bench_pose2sim_heldout.py --hull-oracle``), the hull a held-out
            camera's silhouette would give, to tell its geometry from its appearance.
    """
    from volcap_core.splat.init import colour_scan, filled_silhouette, visual_hull

    uncoloured = set(held_out)
    held = uncoloured - set(carve_only)
    (x0, y0, z0), (x1, y1, z1) = volume
    out = []
    for p in clouds:
        views = [v for v in data.views if v.camera_id not in held and abs(v.time - p.time) < 1e-6]
        mattes = [(v, m) for v in views if (m := v.load_matte()) is not None]
        if len(mattes) < 2:   # a cloud of no frame (the static scan or room shell), or too few masks
            out.append(p)
            continue
        xyz = p.xyz.double().numpy()
        static = p.static.numpy() if p.static is not None else np.zeros(len(xyz), bool)
        inside = ((xyz >= (x0, y0, z0)) & (xyz <= (x1, y1, z1))).all(axis=1)
        keep = static | inside
        cams = []
        for v, m in mattes:
            K = v.camera.opencv_K()
            close = max(1, round(HULL_CLOSE_FRACTION * min(v.camera.width, v.camera.height)))
            cams.append((K, v.camera.world_to_camera.double().numpy(), filled_silhouette(m.numpy(), close_px=close)))
        hull = visual_hull(cams, volume)
        rgb, seen = colour_scan(hull, [v for v, _ in mattes if v.camera_id not in uncoloured])
        hull = torch.from_numpy(hull[seen].astype(np.float32))
        out.append(replace(p, xyz=torch.cat([p.xyz[torch.from_numpy(keep)], hull]),
                           rgb=torch.cat([p.rgb[torch.from_numpy(keep)], torch.from_numpy(rgb[seen]).to(p.rgb.dtype)]),
                           static=torch.cat([torch.from_numpy(static[keep]), torch.zeros(len(hull), dtype=torch.bool)]),
                           footprint=None))
    return out


def with_zoom_points(clouds: Sequence[PointsAtTime], data: SegmentData, held_out: Sequence[str], stride_px: int
                     ) -> list[PointsAtTime]:
    """Each frame's moving points joined by the points of the training cameras that resolve them
    finer than their spacing (the tracking cameras framing the faces;
    :func:`~volcap_core.splat.init.zoom_points`, every ``stride_px`` pixels, coloured by their
    footage at that frame, each at the depth the frame's other training cameras confirm by
    photo-consistency: :func:`~volcap_core.splat.init.photo_depth`). Needs :func:`with_footprints`
    first."""
    from volcap_core.splat.init import neighbour_scale, zoom_points

    held = set(held_out)
    out = []
    for p in clouds:
        moving = ~p.static.numpy() if p.static is not None else np.ones(len(p.xyz), bool)
        if not moving.any() or moving.sum() < 2:
            out.append(p)
            continue
        xyz = p.xyz.double().numpy()[moving]
        spacing = float(np.median(neighbour_scale(xyz)))
        add = []
        at = [v for v in data.views if v.camera_id not in held and abs(v.time - p.time) <= 1e-6]
        for v in at:
            K = v.camera.opencv_K()
            W = v.camera.world_to_camera.double().numpy()
            z = xyz @ W[2, :3] + W[2, 3]
            seen = z > 0.1
            if not seen.any() or float(np.median(z[seen])) / float(K[0, 0]) * stride_px > 0.5 * spacing:
                continue   # this camera resolves the performers no finer than the sweep did
            others = [(o.camera.opencv_K(), o.camera.world_to_camera.double().numpy(), o.camera.width,
                       o.camera.height, lambda o=o: o.load()[..., :3].numpy()) for o in at if o.camera_id != v.camera_id]
            add.append(zoom_points(xyz, K, W, v.load()[..., :3].numpy(), stride_px=stride_px, neighbours=others))
        if not add:
            out.append(p)
            continue
        nx = np.concatenate([a[0] for a in add]).astype(np.float32)
        out.append(replace(p, xyz=torch.cat([p.xyz, torch.from_numpy(nx)]),
                           rgb=torch.cat([p.rgb, torch.from_numpy(np.concatenate([a[1] for a in add]).astype(np.float32))]),
                           static=None if p.static is None else torch.cat([p.static, torch.zeros(len(nx), dtype=torch.bool)]),
                           footprint=torch.cat([p.footprint, torch.from_numpy(np.concatenate([a[2] for a in add])).float()])))
    return out


def with_scene_flow(clouds: Sequence[PointsAtTime], data: SegmentData, held_out: Sequence[str] = ()
                    ) -> list[PointsAtTime]:
    """Each frame's cloud with its moving points' velocity (``PointsAtTime.velocity``, m/s; the
    static points' 0): the training cameras' optical flow to the frames before and after,
    triangulated and smoothed over each point's neighbours
    (:mod:`volcap_core.splat.scene_flow`). The flows run on the views' grey sRGB, each camera's
    once per pair of frames. Clouds of no frame (the scan, the room shell) stay as they are."""
    from volcap_core.colour import srgb_encode
    from volcap_core.splat.scene_flow import FlowPair, optical_flow, point_velocities, smoothed_velocities

    held = set(held_out)
    views = {(v.camera_id, v.frame): v for v in data.views if v.camera_id not in held}
    frame_of = {round(v.time, 6): v.frame for v in data.views}
    time_of = {v.frame: v.time for v in data.views}
    grey: dict[tuple[str, int], np.ndarray] = {}
    flows: dict[tuple[str, int, int], np.ndarray] = {}

    def grey_of(cam: str, f: int) -> np.ndarray:
        if (cam, f) not in grey:
            rgb = np.clip(views[(cam, f)].load()[..., :3].numpy(), 0.0, None)
            grey[(cam, f)] = (np.clip(srgb_encode(rgb).mean(axis=2), 0, 1) * 255).round().astype(np.uint8)
        return grey[(cam, f)]

    def flow(cam: str, f: int, g: int) -> np.ndarray:
        if (cam, f, g) not in flows:
            flows[(cam, f, g)] = optical_flow(grey_of(cam, f), grey_of(cam, g))
        return flows[(cam, f, g)]

    cameras = sorted({c for c, _ in views})
    out = []
    for p in clouds:
        f = frame_of.get(round(p.time, 6))
        moving = ~p.static.numpy() if p.static is not None else np.ones(len(p.xyz), bool)
        if f is None or moving.sum() < 2:
            out.append(p)
            continue
        neighbours = []
        for g in (f - 1, f + 1):
            pairs = []
            for cam in cameras:
                a, b = views.get((cam, f)), views.get((cam, g))
                if a is None or b is None:
                    continue
                pairs.append(FlowPair(a.camera.opencv_K(), a.camera.world_to_camera.double().numpy(),
                                      b.camera.opencv_K(), b.camera.world_to_camera.double().numpy(),
                                      a.camera.width, a.camera.height, flow(cam, f, g), flow(cam, g, f)))
            if pairs:
                neighbours.append((time_of[g] - time_of[f], pairs))
        xyz = p.xyz.double().numpy()[moving]
        velocity = np.zeros((len(p.xyz), 3), np.float32)
        velocity[moving] = smoothed_velocities(xyz, point_velocities(xyz, neighbours))
        # at half precision (5e-4 relative, the estimate errs ~15 %): what a prepared segment carries
        # to a GPU in half the bytes then trains exactly as here
        out.append(replace(p, velocity=torch.from_numpy(velocity.astype(np.float16).astype(np.float32))))
    return out


def with_footprints(clouds: Sequence[PointsAtTime], data: SegmentData, held_out: Sequence[str] = ()
                    ) -> list[PointsAtTime]:
    """Each cloud with its points' finest pixel footprint over the training cameras at the
    cloud's frame (:func:`~volcap_core.splat.init.finest_footprint`; held-out cameras never count)."""
    from volcap_core.splat.init import finest_footprint

    held = set(held_out)
    out = []
    for p in clouds:
        at = min({v.time for v in data.views}, key=lambda t: abs(t - p.time))
        cams = []
        for v in data.views:
            if v.time == at and v.camera_id not in held:
                K = v.camera.opencv_K()
                cams.append((K, v.camera.world_to_camera.double().numpy(), v.camera.width, v.camera.height))
        foot = finest_footprint(p.xyz.double().numpy(), cams)
        out.append(replace(p, footprint=torch.from_numpy(foot).float()))
    return out


def background_views(data: SegmentData, capture: Capture, held_out: Sequence[str] = ()) -> list:
    """The static training cameras' views at the segment's middle frame (what colours the scan)."""
    mid = data.frames[0] + (data.frames[1] - data.frames[0]) // 2
    static = {c.id for c in capture.cameras if not capture.rig.camera(c.id).role.tracks}
    return [v for v in data.views if v.frame == mid and v.camera_id in static and v.camera_id not in held_out]


def default_held_out(capture: Capture, n: int = 1, calibration: Calibration | None = None,
                     tracking: int = 0) -> list[str]:
    """Held-out cameras when none are named: static cameras spread over the rig (never ones the
    ``calibration`` left out), at most ``n``, none when fewer than 4 static cameras exist; then
    at most ``tracking`` tracking cameras picked the same way, none when fewer than 2 exist (one
    must stay to train the close-ups: issue 28 scores a held-out tracking camera).

    On the demo rig (static S000-S007, tracking S008-S011): ``n=1, tracking=1`` gives S004 and
    S010 (the wider portrait zoom; S008, S009 and S011 frame the faces closer and train)."""
    left_out = calibration.unregistered if calibration is not None else {}
    out = []
    for count, minimum, tracks in ((n, 4, False), (tracking, 2, True)):
        ids = [c.id for c in capture.cameras
               if capture.rig.camera(c.id).role.tracks == tracks and c.id not in left_out]
        if len(ids) < minimum or count <= 0:
            continue
        step = len(ids) / count
        out += [ids[int(step * i + step / 2)] for i in range(count)]
    return out


def encode_grids(camera_ids: Sequence[str], exposure: torch.Tensor, black: torch.Tensor) -> bytes:
    """Safetensors bytes of a segment's per-camera grids (``exposure``, ``black``; the camera ids in
    the metadata)."""
    return safetensors_bytes({"exposure": exposure, "black": black}, {"cameras": ",".join(camera_ids)})


def decode_grids(data: bytes) -> ExposureGrids:
    """ExposureGrids from :func:`encode_grids` bytes."""
    from safetensors.torch import load

    t = load(data)
    return ExposureGrids(safetensors_metadata(data)["cameras"].split(","), t["exposure"], t["black"])
