"""Export one frame's calibration and points as a COLMAP model (text or binary) that
``pycolmap.Reconstruction(path)`` reads back: ``cameras``, ``images``, ``points3D`` (plus COLMAP 4's
``rigs`` and ``frames``, one trivial rig and frame per camera).

Cameras are ``PINHOLE`` (fx, fy, cx, cy) with COLMAP's pixel convention (OpenCV + 0.5), or, for a
camera with lens distortion (a 5th element of its tuple, a
:class:`~volcap_core.calibration.distortion.Distortion`), ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1,
p2) / ``FULL_OPENCV`` when k3 is set: the model of the camera's own (distorted) frames; image names
are ``<camera id>.png`` unless given. Points carry their colour (sRGB-encoded 8-bit from linear) and,
when observations are given, their tracks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import cv2  # noqa: F401  (before pycolmap)
import numpy as np
import pycolmap

from hardware.lens_models import COLMAP_PIXEL_OFFSET
from volcap_core.calibration.distortion import Distortion
from volcap_core.calibration.record import Calibration, TrackingFrames, camera_at, frame_camera
from volcap_core.colour import srgb_encode

Camera = tuple   # (K [3, 3], world_to_camera [4, 4], width, height[, Distortion])


def cameras_at(calibration: Calibration, frame: int,
               tracking: Mapping[str, TrackingFrames] | None = None) -> dict[str, Camera]:
    """Every camera of a calibration at one take index (tracking cameras need the decoded blob);
    a camera with distortion in the record (a tracking camera's: that frame's lens) gets it as a 5th
    element."""
    out = {}
    for cam in calibration.cameras:
        if not cam.static and tracking is None:
            continue
        out[cam.id] = camera_at(calibration, cam.id, frame, tracking)
        dist = frame_camera(calibration, cam.id, frame, tracking).distortion
        if any(dist):
            out[cam.id] = (*out[cam.id], Distortion.from_opencv(dist))
    return out


def _colmap_model(K: np.ndarray, w: int, h: int, dist: Distortion | None, camera_id: int) -> pycolmap.Camera:
    if dist is None or dist.is_none:
        return pycolmap.Camera(model="PINHOLE", width=int(w), height=int(h),
                               params=[K[0, 0], K[1, 1], K[0, 2] + COLMAP_PIXEL_OFFSET, K[1, 2] + COLMAP_PIXEL_OFFSET],
                               camera_id=camera_id)
    d = dist if dist.model == "FULL_OPENCV" else dist.as_model("FULL_OPENCV" if any(dist.opencv_full()[4:]) else "OPENCV")
    params = [K[0, 0], K[1, 1], K[0, 2] + COLMAP_PIXEL_OFFSET, K[1, 2] + COLMAP_PIXEL_OFFSET, *d.params]
    return pycolmap.Camera(model=d.model, width=int(w), height=int(h), params=params, camera_id=camera_id)


def build_reconstruction(cameras: Mapping[str, Camera], points: np.ndarray | None = None,
                         colours: np.ndarray | None = None, *,
                         observations: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                         image_names: Mapping[str, str] | None = None) -> pycolmap.Reconstruction:
    """A pycolmap reconstruction. ``points`` [N, 3] metres; ``colours`` [N, 3] linear float (or uint8);
    ``observations`` = (point index [M], camera id index into ``sorted(cameras)`` [M], OpenCV xy
    [M, 2])."""
    rec = pycolmap.Reconstruction()
    ids = sorted(cameras)
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    if colours is None:
        cols = np.full((len(pts), 3), 128, np.uint8)
    elif np.asarray(colours).dtype == np.uint8:
        cols = np.asarray(colours, np.uint8).reshape(-1, 3)
    else:
        cols = np.round(255 * srgb_encode(np.clip(np.asarray(colours, np.float32), 0, 1))).astype(np.uint8)
    per_cam_xy: dict[int, list] = {i: [] for i in range(len(ids))}
    per_cam_pt: dict[int, list] = {i: [] for i in range(len(ids))}
    if observations is not None:
        op, oc, oxy = observations
        for p, c, xy in zip(np.asarray(op), np.asarray(oc), np.asarray(oxy, np.float64)):
            per_cam_xy[int(c)].append(xy + COLMAP_PIXEL_OFFSET)
            per_cam_pt[int(c)].append(int(p))
    for i, cid in enumerate(ids):
        K, w2c, w, h, *rest = cameras[cid]
        cam = _colmap_model(np.asarray(K, np.float64), w, h, rest[0] if rest else None, i + 1)
        rec.add_camera_with_trivial_rig(cam)
        kp = np.asarray(per_cam_xy[i], np.float64).reshape(-1, 2)
        name = (image_names or {}).get(cid, f"{cid}.png")
        img = pycolmap.Image(name=name, keypoints=kp, camera_id=i + 1, image_id=i + 1)
        m = np.asarray(w2c, np.float64)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(m[:3, :4]))
    tracks: dict[int, list] = {}
    for i in range(len(ids)):
        for k, p in enumerate(per_cam_pt[i]):
            tracks.setdefault(p, []).append(pycolmap.TrackElement(i + 1, k))
    for p in range(len(pts)):
        pid = rec.add_point3D(pts[p], pycolmap.Track(), cols[p])
        for el in tracks.get(p, []):
            rec.add_observation(pid, el)
    return rec


def export_colmap(out_dir: str | Path, cameras: Mapping[str, Camera], points: np.ndarray | None = None,
                  colours: np.ndarray | None = None, *, binary: bool = False,
                  observations: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                  image_names: Mapping[str, str] | None = None) -> Path:
    """Write a COLMAP model folder (``binary``: ``*.bin``, else ``*.txt``); returns the folder."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rec = build_reconstruction(cameras, points, colours, observations=observations, image_names=image_names)
    if binary:
        rec.write_binary(str(out))
    else:
        rec.write_text(str(out))
    return out
