"""A studio's trusted calibration in as a :class:`~volcap_core.calibration.record.Calibration`
record: Qualisys XML (``.qca.txt``), a COLMAP model (text or binary) and OpenCV's K / distortion /
R|t (YAML as ``cv2.FileStorage`` writes it, or JSON).

Every importer returns a record of static cameras, each with its measured intrinsics (OpenCV
pixels: the top-left pixel's centre at (0, 0)), its lens as OpenCV's 5 or 8 ``distCoeffs`` and its
pose as ``world_to_camera`` (OpenCV axes, ``x_cam = R x + t``, metres). The world is the file's own
(a Qualisys lab's floor frame, a COLMAP model's arbitrary frame), scaled to metres; ``capture``,
``frame_count`` and ``fps`` are as given; ``reference_frame`` is 0 and ``stage_size_m``, unless
given, the footprint of the camera centres (x and y extents) by the highest centre. Each error is a
:class:`~volcap_core.calibration.errors.CalibrationInputError` naming the file and the camera.

Qualisys (conventions established by reprojection on Pose2Sim's capture, docs/calibration.md,
"Importing a studio's calibration"): ``focalLengthU/V`` and ``centerPointU/V`` are in 1/64 pixel of
the ``fov_video`` window (``left``/``top`` are subtracted, its size is ``right - left + 1`` by
``bottom - top + 1``); ``radialDistortion1..3`` and ``tangentalDistortion1..2`` are OpenCV's k1-k3,
p1, p2 as they are; ``transform`` holds ``r11..r33`` (row i, column j) whose rows are the camera's
axes in the world with the camera's y up and z backward, and ``x, y, z`` the camera centre in mm:
``R = diag(1, -1, -1) @ [r_ij]``, ``t = -R @ centre``. Inactive cameras are left out and listed in
``unregistered``.

Frames resampled after calibration: :func:`fit_to_frames` gives a camera the intrinsics of its
frames at another size: a resize (each axis to its rounded size, as a 2x downsampling) or a
uniform scale centred with padding (letterbox or pillarbox), as Pose2Sim's SinglePerson
cam01/cam02 were re-encoded (1088x1920 -> 1080x1920: scale 1080/1088, 7 px bars top and bottom).
:func:`fit_calibration` applies it to a whole record: the importers' ``frame_sizes`` and a solved
calibration reused on a resampled capture both go through it.
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path

import cv2  # noqa: F401  (before pycolmap)
import numpy as np

from volcap_core.calibration.distortion import Distortion, from_colmap_camera
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.record import Calibration, CameraCalibration, matrix4

#: Qualisys writes focal lengths and principal points in 1/64 pixel
QUALISYS_SUBPIXELS = 64.0
#: Qualisys camera axes (x right, y up, z backward) -> OpenCV's (x right, y down, z forward)
QUALISYS_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


# ------------------------------------------------------------------------------------------ shared
def _camera(source: str, cid: str, width: int, height: int, intrinsics, distortion, R, t,
            quality: Mapping[str, float] | None = None) -> CameraCalibration:
    """One static record camera from OpenCV K terms, distCoeffs and R|t (metres); an invalid value
    is an error naming ``source`` and the camera."""
    where = f"{source}: camera {cid}"
    intr = tuple(float(v) for v in intrinsics)
    if not all(math.isfinite(v) for v in intr) or intr[0] <= 0 or intr[1] <= 0:
        raise CalibrationInputError(f"{where}: focal lengths must be positive and finite, got fx, fy, cx, cy = {intr}")
    if width <= 0 or height <= 0:
        raise CalibrationInputError(f"{where}: image size must be positive, got {width}x{height}")
    try:
        dist = tuple(float(v) for v in Distortion.from_opencv(np.asarray(distortion, np.float64).reshape(-1)).opencv())
    except ValueError as exc:
        raise CalibrationInputError(f"{where}: distortion: {exc}") from None
    R = np.asarray(R, np.float64)
    t = np.asarray(t, np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise CalibrationInputError(f"{where}: rotation must be 3x3 and translation 3 finite values, "
                                    f"got {R.shape} and {t.shape}")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) <= 0:
        raise CalibrationInputError(f"{where}: the rotation is not a proper rotation "
                                    f"(R Rᵀ off the identity by {np.abs(R @ R.T - np.eye(3)).max():.2g}, "
                                    f"det {np.linalg.det(R):.4f})")
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, t
    return CameraCalibration(id=cid, role="static", static=True, width=int(width), height=int(height),
                             intrinsics=intr, distortion=dist, world_to_camera=matrix4(m),
                             quality=dict(quality or {}))


def _record(source: str, cameras: list[CameraCalibration], capture: str, frame_count: int, fps: float,
            stage_size_m, unregistered: Mapping[str, str] | None = None) -> Calibration:
    if not cameras:
        raise CalibrationInputError(f"{source}: no camera to import")
    ids = [c.id for c in cameras]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise CalibrationInputError(f"{source}: camera id(s) {', '.join(dup)} appear more than once")
    if frame_count <= 0 or not fps > 0:
        raise CalibrationInputError(f"{source}: frame_count and fps must be positive, got {frame_count} and {fps}")
    if stage_size_m is None:
        centres = np.array([-np.asarray(c.world_to_camera)[:3, :3].T @ np.asarray(c.world_to_camera)[:3, 3]
                            for c in cameras])
        ext = centres.max(0) - centres.min(0)
        stage_size_m = (max(float(ext[0]), 1e-3), max(float(ext[1]), 1e-3), max(float(centres[:, 2].max()), 1e-3))
    return Calibration(capture=capture, frame_count=int(frame_count), fps=float(fps), reference_frame=0,
                       stage_size_m=tuple(float(v) for v in stage_size_m),
                       cameras=tuple(sorted(cameras, key=lambda c: c.id)),
                       stats={"static_cameras": float(len(cameras)), "tracking_cameras": 0.0},
                       unregistered=dict(unregistered or {}))


def fit_to_frames(camera: CameraCalibration, width: int, height: int) -> CameraCalibration:
    """``camera`` for frames that are its own ``W x H`` frames resampled to ``width x height``; the
    lens (on normalized coordinates) and the pose are unchanged, the same size returns the camera
    as it is. Two resamplings, told apart by the sizes:

    - a **resize** (both axes scaled to their rounded sizes: ``s W`` and ``s H`` within a pixel of
      ``width`` and ``height``, ``s = min(width / W, height / H)``; what ``cv2.resize`` or an area
      downsampling by 2 gives): each axis by its own factor ``s_x = width / W``,
      ``s_y = height / H``, pixel edges onto pixel edges;
    - a **fit** (uniform scale ``s`` and centred padding on the other axis: letterbox or pillarbox,
      as Pose2Sim's 1088x1920 -> 1080x1920 re-encodes): ``s_x = s_y = s`` plus the padding.

    fx, fy times ``s_x``, ``s_y``; the principal point ``s (c + 0.5) - 0.5`` (OpenCV pixel centres)
    plus the padding. ``quality`` gains ``resample_scale`` (``s_x``), ``resample_scale_y`` and
    ``resample_pad_x_px`` / ``resample_pad_y_px``. A tracking camera (intrinsics per frame, in the
    tracking blob) is refused at another size."""
    W, H = camera.width, camera.height
    if (width, height) == (W, H):
        return camera
    if width <= 0 or height <= 0:
        raise CalibrationInputError(f"camera {camera.id}: frames of {width}x{height} pixels")
    if camera.intrinsics is None:
        raise CalibrationInputError(f"camera {camera.id}: a tracking camera (intrinsics per frame) cannot be "
                                    f"fitted to frames of {width}x{height} (it was calibrated at {W}x{H})")
    s = min(width / W, height / H)
    if abs(s * W - width) < 1 and abs(s * H - height) < 1:      # a resize: each axis to its rounded size
        sx, sy, pad_x, pad_y = width / W, height / H, 0.0, 0.0
    else:                                                         # a fit: uniform scale, centred
        sx = sy = s
        pad_x, pad_y = (width - s * W) / 2, (height - s * H) / 2
    fx, fy, cx, cy = camera.intrinsics
    intr = (fx * sx, fy * sy, sx * (cx + 0.5) - 0.5 + pad_x, sy * (cy + 0.5) - 0.5 + pad_y)
    q = {**camera.quality, "resample_scale": sx, "resample_scale_y": sy,
         "resample_pad_x_px": pad_x, "resample_pad_y_px": pad_y}
    return camera.model_copy(update={"width": int(width), "height": int(height), "intrinsics": intr, "quality": q})


def fit_calibration(calibration: Calibration, frame_sizes: Mapping[str, tuple[int, int]] | None, *,
                    source: str = "calibration", capture: str | None = None, frame_count: int | None = None,
                    fps: float | None = None) -> Calibration:
    """``calibration`` applied to footage of the same cameras whose frames are ``frame_sizes``
    (camera id -> (width, height); cameras not named keep their size): every camera through
    :func:`fit_to_frames`. The one path an imported record (the importers' ``frame_sizes``) and a
    solved one reused on a resampled capture (``volcap import-calibration REF --format record``)
    take. ``capture``, ``frame_count``, ``fps``: the record's, when given (the capture it is
    applied to). A size for a camera the record lacks is an error naming ``source``."""
    sizes = dict(frame_sizes or {})
    ids = [c.id for c in calibration.cameras]
    unknown = sorted(set(sizes) - set(ids))
    if unknown:
        raise CalibrationInputError(f"{source}: frame sizes given for camera(s) {', '.join(unknown)}, "
                                    f"which the calibration does not have (it has {', '.join(ids)})")
    cams = []
    for c in calibration.cameras:
        try:
            cams.append(fit_to_frames(c, *sizes[c.id]) if c.id in sizes else c)
        except CalibrationInputError as exc:
            raise CalibrationInputError(f"{source}: {exc}") from None
    update = {"cameras": tuple(cams)}
    for key, value in (("capture", capture), ("frame_count", frame_count), ("fps", fps)):
        if value is not None:
            update[key] = value
    return calibration.model_copy(update=update)


# ---------------------------------------------------------------------------------------- Qualisys
def calibration_from_qualisys(xml_bytes: bytes, capture: str, frame_count: int, fps: float, *,
                              source: str = "Qualisys XML",
                              frame_sizes: Mapping[str, tuple[int, int]] | None = None,
                              stage_size_m: tuple[float, float, float] | None = None) -> Calibration:
    """The Calibration record of a Qualisys calibration (``.qca.txt`` XML, the module docstring's
    conventions). ``source`` names the file in errors; ``frame_sizes`` (camera id -> (width,
    height)) gives cameras whose frames were resampled after calibration (:func:`fit_to_frames`)."""
    try:
        root = ET.fromstring(xml_bytes)
    except ET.ParseError as exc:
        raise CalibrationInputError(f"{source}: not XML: {exc}") from None
    nodes = root.findall("./cameras/camera")
    if not nodes:
        raise CalibrationInputError(f"{source}: no <cameras><camera> elements (is it a Qualisys calibration?)")
    cams, inactive = [], {}
    for i, node in enumerate(nodes):
        cid = node.get("serial") or f"camera{i + 1}"
        where = f"{source}: camera {cid}"
        if node.get("active", "1").strip() not in ("1", "true"):
            inactive[cid] = "inactive in the Qualisys calibration"
            continue
        if node.get("viewrotation", "0").strip() not in ("0", "0.0"):
            # a camera mounted turned by 90/180/270 degrees: its image axes are not the ones read here
            raise CalibrationInputError(f"{where}: viewrotation {node.get('viewrotation')} is not imported "
                                        "(only cameras with viewrotation 0)")
        fov, intr, tr = node.find("fov_video"), node.find("intrinsic"), node.find("transform")
        for name, el in (("fov_video", fov), ("intrinsic", intr), ("transform", tr)):
            if el is None:
                raise CalibrationInputError(f"{where}: no <{name}> element")

        def num(el, key, _where=where):
            v = el.get(key)
            try:
                x = float(v)
            except (TypeError, ValueError):
                raise CalibrationInputError(f"{_where}: <{el.tag}> {key}={v!r} is not a number") from None
            if not math.isfinite(x):
                raise CalibrationInputError(f"{_where}: <{el.tag}> {key}={v!r} is not finite")
            return x

        left, top = num(fov, "left"), num(fov, "top")
        width, height = int(round(num(fov, "right") - left + 1)), int(round(num(fov, "bottom") - top + 1))
        k = (num(intr, "focalLengthU") / QUALISYS_SUBPIXELS, num(intr, "focalLengthV") / QUALISYS_SUBPIXELS,
             num(intr, "centerPointU") / QUALISYS_SUBPIXELS - left, num(intr, "centerPointV") / QUALISYS_SUBPIXELS - top)
        dist = (num(intr, "radialDistortion1"), num(intr, "radialDistortion2"), num(intr, "tangentalDistortion1"),
                num(intr, "tangentalDistortion2"), num(intr, "radialDistortion3"))
        r = np.array([[num(tr, f"r{a}{b}") for b in "123"] for a in "123"])
        centre = np.array([num(tr, a) for a in "xyz"]) / 1000.0
        R = QUALISYS_TO_OPENCV @ r
        q = {}
        if node.get("avg-residual") is not None:
            q["qualisys_avg_residual"] = num(node, "avg-residual")
        cams.append(_camera(source, cid, width, height, k, dist, R, -R @ centre, q))
    return fit_calibration(_record(source, cams, capture, frame_count, fps, stage_size_m, inactive), frame_sizes, source=source)


# ------------------------------------------------------------------------------------------ COLMAP
def calibration_from_colmap(folder: str | Path, capture: str, frame_count: int, fps: float, *,
                            metres_per_unit: float = 1.0,
                            frame_sizes: Mapping[str, tuple[int, int]] | None = None,
                            stage_size_m: tuple[float, float, float] | None = None) -> Calibration:
    """The Calibration record of a COLMAP model folder (``cameras``/``images`` as ``.txt`` or
    ``.bin``, read by pycolmap): one camera per registered image, named by the image's file stem
    (``cam03.png`` -> ``cam03``, as :mod:`~volcap_core.calibration.colmap_export` writes them);
    COLMAP's pixel centres (+0.5) back to OpenCV's; the model's units times ``metres_per_unit``.
    Models SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV, read as a rig's
    ``colmap`` lens is (:func:`~volcap_core.calibration.distortion.from_colmap_camera`); another is an
    error naming the image, its model and why. An image without a pose is listed in ``unregistered``."""
    import pycolmap

    folder = Path(folder)
    source = str(folder)
    if not folder.is_dir():
        raise CalibrationInputError(f"{source}: not a folder (a COLMAP model folder holds cameras and images)")
    if not any((folder / f"{n}.{e}").exists() for n in ("cameras", "images") for e in ("txt", "bin")):
        raise CalibrationInputError(f"{source}: no cameras.txt/.bin or images.txt/.bin: not a COLMAP model")
    if not (metres_per_unit > 0 and math.isfinite(metres_per_unit)):
        raise CalibrationInputError(f"{source}: metres_per_unit must be positive, got {metres_per_unit}")
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises its own types for unreadable models
        raise CalibrationInputError(f"{source}: COLMAP cannot read the model: {exc}") from None
    cams, unposed = [], {}
    for image_id in sorted(rec.images):
        image = rec.images[image_id]
        cid = Path(image.name).stem
        if not image.has_pose:
            unposed[cid] = "no pose in the COLMAP model"
            continue
        cam = rec.cameras[image.camera_id]
        try:   # COLMAP's parameter order and pixel centres, read as rigs read them
            intrinsics, dist = from_colmap_camera(cam.model.name, cam.params)
        except ValueError as exc:
            raise CalibrationInputError(f"{source}: image {image.name} (camera {cid}): {exc}") from None
        m = np.asarray(image.cam_from_world().matrix(), np.float64)
        cams.append(_camera(source, cid, cam.width, cam.height, intrinsics, dist.opencv(),
                            m[:3, :3], m[:3, 3] * metres_per_unit))
    return fit_calibration(_record(source, cams, capture, frame_count, fps, stage_size_m, unposed), frame_sizes, source=source)


# ------------------------------------------------------------------------------------------ OpenCV
_KEYS = {"K": ("K", "camera_matrix", "cameraMatrix", "intrinsic", "intrinsics", "matrix"),
         "dist": ("dist", "D", "distortion", "dist_coeffs", "distCoeffs", "distortion_coefficients"),
         "R": ("R", "rotation", "rvec"),
         "t": ("t", "T", "translation", "tvec"),
         "width": ("width", "image_width"),
         "height": ("height", "image_height"),
         "size": ("size", "image_size")}


def _pick(source: str, cid: str, entry: Mapping, what: str, required: bool = True):
    for k in _KEYS[what]:
        if k in entry and entry[k] is not None:
            return entry[k]
    if required:
        raise CalibrationInputError(f"{source}: camera {cid}: no {what} (one of {', '.join(_KEYS[what])})")
    return None


def _opencv_camera(source: str, cid: str, entry: Mapping, metres_per_unit: float) -> CameraCalibration:
    where = f"{source}: camera {cid}"
    if not isinstance(entry, Mapping):
        raise CalibrationInputError(f"{where}: expected a map of K, dist, R, t, width, height")
    try:
        K = np.asarray(_pick(source, cid, entry, "K"), np.float64).reshape(3, 3)
        dist = np.asarray(_pick(source, cid, entry, "dist", required=False) or [], np.float64).reshape(-1)
        R = np.asarray(_pick(source, cid, entry, "R"), np.float64)
        t = np.asarray(_pick(source, cid, entry, "t"), np.float64).reshape(-1) * metres_per_unit
    except (TypeError, ValueError) as exc:
        raise CalibrationInputError(f"{where}: {exc}") from None
    if R.size == 3:                                   # a Rodrigues vector, as cv2.calibrateCamera returns
        R = cv2.Rodrigues(R.reshape(3, 1))[0]
    elif R.size == 9:
        R = R.reshape(3, 3)
    else:
        raise CalibrationInputError(f"{where}: R must be a 3x3 matrix or a Rodrigues 3-vector, got {R.size} values")
    size = _pick(source, cid, entry, "size", required=False)
    if size is not None:
        w, h = (int(v) for v in np.asarray(size).reshape(-1)[:2])
    else:
        w = _pick(source, cid, entry, "width")
        h = _pick(source, cid, entry, "height")
    if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or not np.allclose(K[2], (0, 0, 1)) or K[1, 0] != 0:
        raise CalibrationInputError(f"{where}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got {K.tolist()}")
    return _camera(source, cid, int(w), int(h), (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), dist, R, t)


def _opencv_entries(source: str, data) -> dict[str, Mapping]:
    if isinstance(data, Mapping) and isinstance(data.get("cameras"), Mapping):
        data = data["cameras"]
    if isinstance(data, Mapping) and isinstance(data.get("cameras"), list):
        data = {str(c.get("id", "")): c for c in data["cameras"]}
    if not isinstance(data, Mapping) or not data:
        raise CalibrationInputError(f"{source}: expected camera id -> {{K, dist, R, t, width, height}}")
    if any(k in data for k in _KEYS["K"]):           # one camera, named by the file
        return {Path(source).stem: data}
    return {str(k): v for k, v in data.items()}


def _filestorage_to_python(node):
    """A ``cv2.FileNode`` as plain Python: maps -> dicts, sequences -> lists, matrices -> lists."""
    if node.isMap() and {"rows", "cols", "data"} <= set(node.keys()):   # an !!opencv-matrix
        return node.mat().tolist()
    if node.isMap():
        return {k: _filestorage_to_python(node.getNode(k)) for k in node.keys()}
    if node.isSeq():
        return [_filestorage_to_python(node.at(i)) for i in range(node.size())]
    if node.isInt():
        return int(node.real())
    if node.isReal():
        return float(node.real())
    if node.isString():
        return node.string()
    mat = node.mat()
    return None if mat is None else mat.tolist()


def calibration_from_opencv(data: bytes, capture: str, frame_count: int, fps: float, *,
                            source: str = "OpenCV calibration", metres_per_unit: float = 1.0,
                            frame_sizes: Mapping[str, tuple[int, int]] | None = None,
                            stage_size_m: tuple[float, float, float] | None = None) -> Calibration:
    """The Calibration record of OpenCV calibrations: YAML (or XML) as ``cv2.FileStorage`` writes it,
    or JSON; either a map camera id -> ``{K, dist, R, t, width, height}`` (also under ``cameras``),
    or one camera's map (named by the file's stem). ``K`` 3x3; ``dist`` OpenCV's 4, 5, 8, 12 or 14
    ``distCoeffs`` (absent: none; thin-prism and tilt terms must be 0: ``docs/rigs.md``); ``R`` 3x3 or a Rodrigues 3-vector and ``t`` with
    ``x_cam = R x + t`` (world to camera, OpenCV axes), ``t`` in units of ``metres_per_unit``
    metres; the size as ``width``/``height`` or ``size: [w, h]`` (aliases: ``camera_matrix``,
    ``distortion_coefficients``, ``rvec``, ``tvec``, ``image_width``...)."""
    if not (metres_per_unit > 0 and math.isfinite(metres_per_unit)):
        raise CalibrationInputError(f"{source}: metres_per_unit must be positive, got {metres_per_unit}")
    text = data.decode("utf-8", errors="replace")
    if text.lstrip().startswith(("{", "[")):
        try:
            parsed = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CalibrationInputError(f"{source}: not JSON: {exc}") from None
    else:
        try:
            fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
        except cv2.error as exc:
            raise CalibrationInputError(f"{source}: OpenCV cannot read it as YAML/XML FileStorage: "
                                        f"{str(exc).strip().splitlines()[-1]}") from None
        try:
            parsed = _filestorage_to_python(fs.root())
        finally:
            fs.release()
    cams = [_opencv_camera(source, cid, entry, metres_per_unit) for cid, entry in _opencv_entries(source, parsed).items()]
    return fit_calibration(_record(source, cams, capture, frame_count, fps, stage_size_m), frame_sizes, source=source)
