"""Ground truth of a synthetic capture as pipeline records: the cameras as a :class:`Calibration`,
dense per-frame points from the true depth maps, the performer masks, and the actors' face
regions in any camera (:func:`face_region`: the head ellipsoid of ``scene.json`` cast into the
camera's pixels, what the close-up scores measure on).

Evaluation and the reconstruction tests use these to separate Poly4DGS's errors from calibration's
(the Poly4DGS issue trains on them until estimated calibration is available). Formats:
``docs/synthetic-capture.md``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from volcap_core.calibration.distortion import Distortion
from volcap_core.calibration.record import (
    Calibration,
    CameraCalibration,
    TrackingFrames,
    encode_tracking_frames,
    matrix4,
    tracking_frames_ref,
)
from volcap_core.synth.geometry import intersect_ellipsoid

#: How far (metres) the face region grows the head ellipsoid by default: the nose (2.4 cm past
#: the head's front at the synthetic actor's scale 1) and the ears' silhouette stay inside.
FACE_MARGIN_M = 0.03


def calibration(cameras_json: dict, capture_name: str, camera_ids: Sequence[str],
                stage_size_m: tuple[float, float, float]) -> tuple[Calibration, bytes | None]:
    """``ground_truth/cameras.json`` → a :class:`Calibration` (``stats["ground_truth"] = 1``) and the
    tracking cameras' per-frame blob (None without tracking cameras). The caller stores the blob
    and sets ``tracking_frames`` to its ref (``Calibration.model_copy``)."""
    n = int(cameras_json["frame_count"])
    cams, tracking = [], {}
    for cid in camera_ids:
        try:
            gt = cameras_json["cameras"][cid]
        except KeyError:
            raise ValueError(f"ground truth has no camera {cid!r}") from None
        frames = sorted(gt["frames"], key=lambda f: f["take_index"])
        if len(frames) != n:
            raise ValueError(f"ground truth camera {cid}: {len(frames)} frames, expected {n}")
        intr = np.array([[f["fx"], f["fy"], f["cx"], f["cy"]] for f in frames], np.float64)
        w2c = np.array([f["world_to_camera"] for f in frames], np.float64)
        static = gt["role"] == "static"
        if static:
            extra = {}
            if frames[0].get("distortion"):
                coeffs = Distortion.from_json(frames[0]["distortion"]).opencv()
                if len(coeffs) != 5:
                    raise ValueError(f"ground truth camera {cid}: a rational distortion (k4-k6) does not fit "
                                     f"the Calibration record's (k1, k2, p1, p2, k3)")
                extra["distortion"] = tuple(float(v) for v in coeffs)
            cams.append(CameraCalibration(id=cid, role=gt["role"], static=True, width=gt["width"],
                                          height=gt["height"], intrinsics=tuple(intr[0]),
                                          world_to_camera=matrix4(w2c[0]), **extra))
        else:
            cams.append(CameraCalibration(id=cid, role=gt["role"], static=False, width=gt["width"],
                                          height=gt["height"]))
            dist = None
            if any(f.get("distortion") for f in frames):      # a zoom lens: each frame's lens at its focal
                coeffs = [Distortion.from_json(f.get("distortion")).opencv_full() for f in frames]
                dist = np.asarray(coeffs, np.float64)
                dist = dist if np.any(dist[:, 5:]) else dist[:, :5]
            tracking[cid] = TrackingFrames(intr, w2c, dist)
    blob = encode_tracking_frames(tracking) if tracking else None
    record = Calibration(capture=capture_name, frame_count=n, fps=float(cameras_json["fps"]), reference_frame=n // 2,
                         stage_size_m=tuple(stage_size_m), cameras=tuple(cams),
                         tracking_frames=tracking_frames_ref(blob) if blob else None,
                         stats={"ground_truth": 1.0})
    return record, blob


def backproject_depth(depth: np.ndarray, image: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray,
                      stride: int = 1, distortion: Distortion | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixels with finite positive depth → (xyz [N, 3] world metres, rgb [N, 3] linear).

    ``depth`` [H, W] is the distance along the optical axis (camera z); ``image`` [H, W, >=3].
    ``distortion``: the camera's lens (the depth map and image are its own, distorted pixels): a
    pixel's ray is its undistorted normalized coordinates.
    """
    h, w = depth.shape
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    z = depth[v, u]
    ok = np.isfinite(z) & (z > 0)
    ui, vi, z = u[ok], v[ok], z[ok].astype(np.float64)
    xn = (ui - K[0, 2]) / K[0, 0]
    yn = (vi - K[1, 2]) / K[1, 1]
    if distortion is not None and not distortion.is_none:
        xy = distortion.undistort(np.stack([xn, yn], axis=-1))
        xn, yn = xy[:, 0], xy[:, 1]
    x, y = xn * z, yn * z
    cam = np.stack([x, y, z], axis=-1)
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    world = (cam - t) @ R  # R^T (x - t), as row vectors
    return world.astype(np.float32), np.asarray(image[vi, ui, :3], np.float32)


def subsample(xyz: np.ndarray, rgb: np.ndarray, budget: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``budget`` points, chosen uniformly at random (deterministic by seed)."""
    if len(xyz) <= budget:
        return xyz, rgb
    idx = np.sort(np.random.default_rng(seed).choice(len(xyz), size=budget, replace=False))
    return xyz[idx], rgb[idx]


def performer_mask(exr_bytes: bytes) -> np.ndarray:
    """A ``ground_truth/masks/<camera>/<take index>.exr`` file's bytes → the performer coverage
    [H, W] float32 in [0, 1]: the fraction of the pixel where an actor is the visible surface
    (1 = only actor, 0 = only set). Restrict image metrics to the performers with it (e.g. ``> 0.5``,
    or as a weight)."""
    from volcap_core.imageio.read import decode_exr_native  # OpenImageIO: only code reading EXRs imports it

    pixels, channels = decode_exr_native(exr_bytes, "performer mask")
    if pixels.ndim != 3 or pixels.shape[-1] != 1:
        raise ValueError(f"performer mask: expected one channel, got {channels}")
    return np.clip(pixels[..., 0].astype(np.float32), 0.0, 1.0)


class GroundTruthFiles:
    """A synthetic capture's ground-truth tree (``docs/synthetic-capture.md``), read by path.

    ``digests``: path -> digest of each file (the stored tree); ``get_bytes(digest)`` reads one.
    """

    def __init__(self, capture_name: str, digests: dict[str, str], get_bytes):
        self.capture_name, self._digests, self._get = capture_name, digests, get_bytes

    def __contains__(self, path: str) -> bool:
        return path in self._digests

    def has_folder(self, folder: str) -> bool:
        return any(p.startswith(folder.rstrip("/") + "/") for p in self._digests)

    def read(self, path: str) -> bytes:
        if path not in self._digests:
            raise ValueError(f"capture {self.capture_name}: ground truth has no {path}"
                             + (" (synthesize with write_depth=True for depth maps and masks)"
                                if path.startswith(("depth/", "masks/")) else ""))
        return self._get(self._digests[path])


def depth_points(files: GroundTruthFiles, camera_ids: Sequence[str], frame: int, load_image, camera_at_frame,
                 budget: int, seed: int, distortion_of=None) -> tuple[np.ndarray, np.ndarray]:
    """One frame's dense points from the true depth maps of ``camera_ids``, coloured by their
    images, at most ``budget`` (uniformly, seeded by ``seed + frame``).

    ``load_image(camera, frame)`` -> linear RGB [H, W, 3]; ``camera_at_frame(camera, frame)`` ->
    (K [3, 3], world_to_camera [4, 4]); ``distortion_of(camera, frame)`` -> its lens at that frame
    (a tracking camera's follows its zoom), a
    :class:`~volcap_core.calibration.distortion.Distortion` (None: pinholes; the depth maps and
    frames are in each camera's own pixels). Returns xyz [N, 3], rgb [N, 3] float32.
    """
    from volcap_core.imageio.read import decode_exr_native

    xyz_all, rgb_all = [], []
    for cam in camera_ids:
        depth, _ = decode_exr_native(files.read(f"depth/{cam}/{frame:06d}.exr"))
        K, w2c = camera_at_frame(cam, frame)
        xyz, rgb = backproject_depth(depth[..., 0].astype(np.float32), load_image(cam, frame), K, w2c,
                                     distortion=distortion_of(cam, frame) if distortion_of is not None else None)
        xyz_all.append(xyz)
        rgb_all.append(rgb)
    return subsample(np.concatenate(xyz_all), np.concatenate(rgb_all), budget, seed + frame)


def mask_loader(files: GroundTruthFiles):
    """``load(camera, take index) -> [H, W] performer coverage or None`` from the ground truth's
    ``masks/``; None when the capture was synthesized without them."""
    if not files.has_folder("masks"):
        return None

    def load(cam: str, frame: int) -> np.ndarray | None:
        path = f"masks/{cam}/{frame:06d}.exr"
        return performer_mask(files.read(path)) if path in files else None

    return load


def head_at(actor: Mapping, time_s: float) -> dict:
    """An actor's head prim (``scene.json`` ``parts`` entry named ``head``: ``centre_m``,
    ``rotation`` (columns: the ellipsoid's axes), ``semi_axes_m``) at ``time_s`` on the take's
    clock: the centre interpolated linearly between the two take frames around it, the rotation
    and semi-axes of the nearer one; held before the first and after the last frame."""
    frames = actor.get("frames") or []
    if not frames:
        raise ValueError(f"scene.json actor {actor.get('index')}: no frames")
    times = np.array([float(f["time_s"]) for f in frames])
    j = int(np.searchsorted(times, time_s))
    lo, hi = max(j - 1, 0), min(j, len(frames) - 1)
    u = 0.0 if hi == lo else float(np.clip((time_s - times[lo]) / (times[hi] - times[lo]), 0.0, 1.0))

    def head(k: int) -> Mapping:
        for p in frames[k].get("parts") or ():
            if p.get("name") == "head" and p.get("kind") == "ellipsoid":
                return p
        raise ValueError(f"scene.json actor {actor.get('index')} take frame {frames[k].get('take_index')}: "
                         f"no 'head' ellipsoid in its parts")

    a, b = head(lo), head(hi)
    near = a if u < 0.5 else b
    centre = (1.0 - u) * np.asarray(a["centre_m"], np.float64) + u * np.asarray(b["centre_m"], np.float64)
    return {"name": "head", "kind": "ellipsoid", "centre_m": centre.tolist(),
            "rotation": np.asarray(near["rotation"], np.float64).tolist(),
            "semi_axes_m": np.asarray(near["semi_axes_m"], np.float64).tolist()}


def head_region(head: Mapping, K: np.ndarray, world_to_camera: np.ndarray, width: int, height: int, *,
                margin_m: float = 0.0) -> np.ndarray:
    """Where a head ellipsoid is in a pinhole camera's image: ``[height, width]`` bool, True at the
    pixels whose centre's ray (OpenCV pixel centres, top-left at (0, 0)) meets the ellipsoid
    grown by ``margin_m`` along each semi-axis. Occlusion is not considered (intersect with a
    coverage mask for what is visible: :func:`face_region`).

    Args:
        head: a :func:`head_at` prim (``centre_m``, ``rotation``, ``semi_axes_m``; metres, world).
        K: ``[3, 3]`` intrinsics (pixels); world_to_camera: ``[4, 4]`` OpenCV axes.
        width, height: the image size (pixels).
    """
    K = np.asarray(K, np.float64)
    w2c = np.asarray(world_to_camera, np.float64)
    if K.shape != (3, 3) or w2c.shape != (4, 4):
        raise ValueError(f"head_region: K must be [3, 3] and world_to_camera [4, 4], got {K.shape} and {w2c.shape}")
    centre = np.asarray(head["centre_m"], np.float64)
    R_head = np.asarray(head["rotation"], np.float64)
    semi = np.asarray(head["semi_axes_m"], np.float64) + float(margin_m)
    out = np.zeros((int(height), int(width)), bool)
    R, t = w2c[:3, :3], w2c[:3, 3]
    # the pixels to test: the projection of the ellipsoid's bounding box (it contains the
    # ellipsoid's when every corner is in front of the camera; else every pixel)
    corners = centre + (np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * semi) @ R_head.T
    cam = corners @ R.T + t
    if np.all(cam[:, 2] > 1e-6):
        uv = (cam @ K.T)[:, :2] / cam[:, 2:3]
        x0, y0 = np.floor(uv.min(0)).astype(int)
        x1, y1 = np.ceil(uv.max(0)).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width - 1), min(y1, height - 1)
        if x1 < x0 or y1 < y0:
            return out
    else:
        x0, y0, x1, y1 = 0, 0, width - 1, height - 1
    v, u = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], axis=-1)
    rays = rays_cam @ R                                       # Rᵀ d, as row vectors
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    origin = -R.T @ t
    hit = np.isfinite(intersect_ellipsoid(origin.astype(np.float32), rays.astype(np.float32), centre, R_head, semi))
    out[y0:y1 + 1, x0:x1 + 1] = hit
    return out


def face_region(scene: Mapping, time_s: float, K: np.ndarray, world_to_camera: np.ndarray, width: int,
                height: int, *, coverage: np.ndarray | None = None, actors: Iterable[int] | None = None,
                margin_m: float = FACE_MARGIN_M) -> np.ndarray:
    """The performers' faces in a camera at ``time_s``: ``[height, width]`` bool, the union of the
    actors' :func:`head_region` (grown by ``margin_m``) and, given the performers' ``coverage``
    ``[H, W]`` (a ground-truth mask or a truth render's alpha), only where it is >= 0.5: the head
    pixels where a performer is the visible surface.

    Args:
        scene: ``ground_truth/scene.json`` (its ``actors``).
        time_s: seconds on the take's clock (take frame ``k`` is at ``k / fps``).
        K, world_to_camera, width, height: the camera (pinhole, OpenCV axes).
        actors: indices of the actors whose faces count (None: every actor).
    """
    wanted = None if actors is None else {int(a) for a in actors}
    region = np.zeros((int(height), int(width)), bool)
    for actor in scene.get("actors") or ():
        if wanted is None or int(actor["index"]) in wanted:
            region |= head_region(head_at(actor, time_s), K, world_to_camera, width, height, margin_m=margin_m)
    if coverage is not None:
        c = np.asarray(coverage)
        if c.shape != region.shape:
            raise ValueError(f"face_region: coverage {c.shape} does not match the camera's {region.shape}")
        region &= c >= 0.5
    return region
