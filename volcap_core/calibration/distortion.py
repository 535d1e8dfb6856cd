"""Lens distortion in the models COLMAP and OpenCV share, on normalized image coordinates.

A camera maps a point ``X_cam = (X, Y, Z)`` (OpenCV axes) to the normalized coordinates
``x = X / Z, y = Y / Z``, distorts them, and applies the pinhole intrinsics::

    r² = x² + y²
    radial = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
    x_d = x radial + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y radial + p1 (r² + 2 y²) + 2 p2 x y
    u = fx x_d + cx,   v = fy y_d + cy          (OpenCV pixels: top-left pixel centre at (0, 0))

Models (names as COLMAP's ``CameraModelId``; parameters in COLMAP's order, which is also the order
of OpenCV's ``distCoeffs`` vector ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tauX, tauY]]]])``;
the missing ones are 0; OpenCV's thin-prism and tilt terms are not applied and read only as zeros,
:meth:`Distortion.from_opencv`):

=================  =================================  ==================================
model              params                             OpenCV distCoeffs
=================  =================================  ==================================
``PINHOLE``        ()                                 (0, 0, 0, 0, 0)
``SIMPLE_RADIAL``  (k,)                               (k, 0, 0, 0, 0)
``RADIAL``         (k1, k2)                           (k1, k2, 0, 0, 0)
``OPENCV``         (k1, k2, p1, p2)                   (k1, k2, p1, p2, 0)
``FULL_OPENCV``    (k1, k2, p1, p2, k3, k4, k5, k6)   (k1, k2, p1, p2, k3, k4, k5, k6)
=================  =================================  ==================================

COLMAP's ``SIMPLE_RADIAL`` and ``RADIAL`` cameras have one focal (``f, cx, cy, k...``):
:func:`colmap_camera` writes them only for square pixels and falls back to the exact equivalent
``OPENCV`` camera (``fx, fy, cx, cy, k1, k2, p1, p2``) otherwise. COLMAP's pixel centres are at
+0.5 (:data:`hardware.lens_models.COLMAP_PIXEL_OFFSET`); :func:`colmap_camera` adds it.

:meth:`Distortion.undistort` inverts the model by Newton's method with the analytic 2x2 Jacobian,
started at the distorted point: for |k1| ≤ 0.3 over a 16:9 image at ~50-75° of horizontal field of
view it converges in 3-6 iterations to a residual below 1e-13 in normalized coordinates (1e-10 px
at a focal of 1000 px); ``iterations`` (20) caps it. Outside the radius where the model stops being
monotonic (barrel distortion folds back: ``d r_d / d r <= 0``) there is no inverse; such points come
back as the last iterate and :meth:`Distortion.undistort_converged` says which.

Images: :func:`undistort_maps` / :func:`undistort_image` resample a distorted image into a pinhole
image (``cv2.initUndistortRectifyMap`` + ``cv2.remap``, bilinear by default); pixels whose ray falls
outside the source image are black (``cv2.BORDER_CONSTANT``), and :func:`undistort_valid_mask` says
which.

Footage after calibration: :func:`rectify_frame` resamples a frame of a calibrated camera (a
``Calibration`` record's camera: its ``intrinsics`` and ``distortion``) into the pinhole with the
*same* fx, fy, cx, cy and size and no distortion, so the record's ``K`` (``record.camera_at``) is
the pinhole of the rectified frame. Every reader of footage after calibration (dense points,
training and scoring, the ground truth's depth and masks) goes through it; a camera without
distortion comes back untouched. A tracking camera with a zoom lens has a lens per frame (the
tracking-frames blob's ``distortion``): rectify frame t with
``record.frame_camera(calibration, id, t, tracking)``, which carries that frame's intrinsics and
lens. :func:`rectified_valid` says which rectified pixels have their
whole bilinear footprint inside the source frame; the others are 0 in the rectified frame and
training's loss and the scores leave them out (``splat.train.View.valid``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np

from hardware.lens_models import COLMAP_PIXEL_OFFSET, DISTORTION_MODELS, colmap_intrinsics, opencv_distortion

#: COLMAP cameras that carry one focal (f, cx, cy, ...) for these models
_COLMAP_SINGLE_FOCAL = {"SIMPLE_RADIAL": "SIMPLE_RADIAL", "RADIAL": "RADIAL", "PINHOLE": "SIMPLE_PINHOLE"}


class PinholeLike(Protocol):
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@dataclass(frozen=True)
class Distortion:
    """A lens distortion: ``model`` (a key of :data:`DISTORTION_MODELS`) and its ``params`` in that model's
    order. ``Distortion.none()`` is the pinhole (no distortion)."""

    model: str = "PINHOLE"
    params: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        model = str(self.model).upper()
        if model not in DISTORTION_MODELS:
            raise ValueError(f"unknown distortion model {self.model!r}: one of {', '.join(DISTORTION_MODELS)}")
        params = tuple(float(p) for p in self.params)
        if len(params) != len(DISTORTION_MODELS[model]):
            raise ValueError(f"distortion model {model} takes {len(DISTORTION_MODELS[model])} parameters "
                             f"({', '.join(DISTORTION_MODELS[model]) or 'none'}), got {len(params)}")
        if not all(np.isfinite(params)):
            raise ValueError(f"distortion model {model}: non-finite parameters {params}")
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "params", params)

    # ------------------------------------------------------------------ construction / conversion
    @staticmethod
    def none() -> "Distortion":
        return Distortion("PINHOLE", ())

    @staticmethod
    def from_opencv(coeffs) -> "Distortion":
        """OpenCV's ``distCoeffs`` as ``cv2.calibrateCamera`` writes them (4, 5, 8, 12 or 14
        values, or none; any shape) -> the smallest model that holds them exactly
        (``hardware.lens_models.opencv_distortion``). Thin-prism (s1..s4) and tilt (tauX, tauY)
        terms are accepted as zeros; a non-zero one is refused by name (``ValueError``)."""
        model, params = opencv_distortion(np.asarray(coeffs, np.float64).reshape(-1).tolist())
        return Distortion(model, params)

    @property
    def is_none(self) -> bool:
        return not any(self.params)

    @property
    def coefficients(self) -> dict[str, float]:
        """Every coefficient of the full model by name (k1..k6, p1, p2), zeros where absent."""
        k1, k2, p1, p2, k3, k4, k5, k6 = self.opencv_full()
        return {"k1": k1, "k2": k2, "p1": p1, "p2": p2, "k3": k3, "k4": k4, "k5": k5, "k6": k6}

    def opencv_full(self) -> tuple[float, ...]:
        """The 8 coefficients (k1, k2, p1, p2, k3, k4, k5, k6) of the full model."""
        p = self.params
        if self.model == "PINHOLE":
            c = ()
        elif self.model in ("SIMPLE_RADIAL", "RADIAL"):
            c = p + (0.0,) * (2 - len(p)) + (0.0, 0.0)
        else:
            c = p
        return tuple(float(v) for v in (c + (0.0,) * (8 - len(c))))

    def opencv(self) -> np.ndarray:
        """OpenCV's ``distCoeffs``: 5 values (k1, k2, p1, p2, k3), 8 for ``FULL_OPENCV`` with a
        rational term."""
        c = self.opencv_full()
        return np.asarray(c if any(c[5:]) else c[:5], np.float64)

    def as_model(self, model: str) -> "Distortion":
        """The same distortion in a more general model (``RADIAL`` -> ``OPENCV``...); a coefficient
        the target cannot hold is an error."""
        model = model.upper()
        c = self.opencv_full()
        k1, k2, p1, p2, k3, k4, k5, k6 = c
        names = DISTORTION_MODELS.get(model)
        if names is None:
            raise ValueError(f"unknown distortion model {model!r}")
        full = dict(zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), c))
        full["k"] = k1
        target = Distortion(model, tuple(full[n] for n in names))
        if target.opencv_full() != c:
            raise ValueError(f"distortion {self.model} {self.params} does not fit model {model}")
        return target

    # ------------------------------------------------------------------ the model
    def distort(self, xy) -> np.ndarray:
        """Undistorted normalized coordinates [N, 2] -> distorted normalized coordinates [N, 2]."""
        xy = np.asarray(xy, np.float64)
        if self.is_none:
            return xy.copy()
        k1, k2, p1, p2, k3, k4, k5, k6 = self.opencv_full()
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def jacobian(self, xy) -> np.ndarray:
        """d distort / d xy [N, 2, 2] at undistorted normalized coordinates [N, 2]."""
        xy = np.asarray(xy, np.float64)
        k1, k2, p1, p2, k3, k4, k5, k6 = self.opencv_full()
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        A = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        B = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dA = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        dB = k4 + r2 * (2 * k5 + 3 * k6 * r2)
        rad = A / B
        drad = (dA * B - A * dB) / (B * B)          # d radial / d r²
        J = np.empty(xy.shape[:-1] + (2, 2))
        J[..., 0, 0] = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
        J[..., 0, 1] = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
        J[..., 1, 0] = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
        J[..., 1, 1] = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
        return J

    def undistort(self, xy_d, iterations: int = 20, tol: float = 1e-14) -> np.ndarray:
        """Distorted normalized coordinates [N, 2] -> undistorted [N, 2] (Newton, see the module
        docstring for its accuracy). ``tol``: stop when every step is below it."""
        return self._undistort(xy_d, iterations, tol)[0]

    def undistort_converged(self, xy_d, iterations: int = 20, tol: float = 1e-14,
                            residual: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
        """``(undistorted [N, 2], converged [N] bool)``: converged = the point re-distorts to within
        ``residual`` (normalized) of the input and the model is locally invertible there."""
        xy, ok = self._undistort(xy_d, iterations, tol)
        return xy, ok & (np.abs(self.distort(xy) - np.asarray(xy_d, np.float64)).max(axis=-1) <= residual)

    def _undistort(self, xy_d, iterations: int, tol: float) -> tuple[np.ndarray, np.ndarray]:
        target = np.asarray(xy_d, np.float64)
        if self.is_none:
            return target.copy(), np.ones(target.shape[:-1], bool)
        xy = target.copy()
        for _ in range(iterations):
            J = self.jacobian(xy)
            r = self.distort(xy) - target
            det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
            safe = np.where(np.abs(det) > 1e-12, det, 1.0)
            dx = (J[..., 1, 1] * r[..., 0] - J[..., 0, 1] * r[..., 1]) / safe
            dy = (-J[..., 1, 0] * r[..., 0] + J[..., 0, 0] * r[..., 1]) / safe
            step = np.stack([dx, dy], axis=-1)
            step = np.where((np.abs(det) > 1e-12)[..., None], step, 0.0)
            xy = xy - step
            if not np.isfinite(xy).all() or np.abs(step).max(initial=0.0) < tol:
                break
        J = self.jacobian(xy)
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        return xy, np.isfinite(xy).all(axis=-1) & (det > 0)

    # ------------------------------------------------------------------ pixels
    def distort_pixels(self, K, uv) -> np.ndarray:
        """Pixels of the pinhole camera ``K`` [3, 3] [N, 2] -> pixels of the distorted camera with
        the same ``K``."""
        K = np.asarray(K, np.float64)
        uv = np.asarray(uv, np.float64)
        xy = (uv - K[:2, 2]) / np.diag(K)[:2]
        return self.distort(xy) * np.diag(K)[:2] + K[:2, 2]

    def undistort_pixels(self, K, uv, K_out=None) -> np.ndarray:
        """Pixels of the distorted camera ``K`` [N, 2] -> pixels of the pinhole camera ``K_out``
        (default ``K``)."""
        K = np.asarray(K, np.float64)
        K_out = K if K_out is None else np.asarray(K_out, np.float64)
        uv = np.asarray(uv, np.float64)
        xy = self.undistort((uv - K[:2, 2]) / np.diag(K)[:2])
        return xy * np.diag(K_out)[:2] + K_out[:2, 2]

    # ------------------------------------------------------------------ serialisation
    def to_json(self) -> dict:
        return {"model": self.model, "params": list(self.params)}

    @staticmethod
    def from_json(d: dict | None) -> "Distortion":
        if not d:
            return Distortion.none()
        return Distortion(d["model"], tuple(d.get("params", ())))


def _K(intr) -> np.ndarray:
    if hasattr(intr, "fx"):
        return np.array([[intr.fx, 0.0, intr.cx], [0.0, intr.fy, intr.cy], [0.0, 0.0, 1.0]])
    return np.asarray(intr, np.float64)


def colmap_camera(fx: float, fy: float, cx: float, cy: float, distortion: Distortion = Distortion.none()
                  ) -> tuple[str, list[float]]:
    """``(COLMAP camera model name, params)`` for OpenCV-pixel intrinsics and a distortion: the
    distortion's own model when COLMAP has it with these focals (one focal for ``SIMPLE_RADIAL`` /
    ``RADIAL`` / ``SIMPLE_PINHOLE``), else ``PINHOLE`` / ``OPENCV`` / ``FULL_OPENCV``. ``cx, cy``
    get COLMAP's +0.5."""

    ccx, ccy = cx + COLMAP_PIXEL_OFFSET, cy + COLMAP_PIXEL_OFFSET
    square = abs(fx - fy) < 1e-9
    m = distortion.model
    if square and m in _COLMAP_SINGLE_FOCAL:
        return _COLMAP_SINGLE_FOCAL[m], [float(fx), float(ccx), float(ccy), *distortion.params]
    if m == "PINHOLE":
        return "PINHOLE", [float(fx), float(fy), float(ccx), float(ccy)]
    d = distortion if m in ("OPENCV", "FULL_OPENCV") else distortion.as_model("OPENCV")
    return d.model, [float(fx), float(fy), float(ccx), float(ccy), *d.params]


def from_colmap_camera(model_name: str, params) -> tuple[tuple[float, float, float, float], Distortion]:
    """A COLMAP camera (model name, params in COLMAP's order and pixels) -> ``((fx, fy, cx, cy)
    OpenCV pixels, Distortion)``: the inverse of :func:`colmap_camera`, and the reading of any
    COLMAP camera volcap can apply (``hardware.lens_models.colmap_intrinsics``; fisheye and the
    other models are refused by name)."""
    intrinsics, model, rest = colmap_intrinsics(model_name, [float(v) for v in params])
    return intrinsics, Distortion(model, rest)


def undistort_maps(intrinsics: PinholeLike, distortion: Distortion, out_intrinsics: PinholeLike | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (``map_x``, ``map_y`` float32 [H_out, W_out]) that resample an image of the
    distorted camera ``intrinsics`` into the pinhole camera ``out_intrinsics`` (default: the same
    fx, fy, cx, cy and size): output pixel ``p`` reads the source at ``K D(K_out⁻¹ p)``."""
    import cv2

    out = intrinsics if out_intrinsics is None else out_intrinsics
    return cv2.initUndistortRectifyMap(_K(intrinsics), distortion.opencv(), None, _K(out),
                                       (int(out.width), int(out.height)), cv2.CV_32FC1)


def undistort_valid_mask(intrinsics: PinholeLike, distortion: Distortion,
                         out_intrinsics: PinholeLike | None = None, margin_px: float = 0.0) -> np.ndarray:
    """[H_out, W_out] bool: output pixels whose source lies inside the distorted image (by
    ``margin_px``), i.e. those :func:`undistort_image` does not fill with black."""
    mx, my = undistort_maps(intrinsics, distortion, out_intrinsics)
    lo = -0.5 + margin_px
    return (mx >= lo) & (my >= lo) & (mx <= intrinsics.width - 0.5 - margin_px) & \
        (my <= intrinsics.height - 0.5 - margin_px)


def undistort_image(image: np.ndarray, intrinsics: PinholeLike, distortion: Distortion,
                    out_intrinsics: PinholeLike | None = None, *, interpolation: int | None = None,
                    maps: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """A distorted image [H, W(, C)] -> the pinhole image of ``out_intrinsics`` (default: the same
    K and size). Bilinear (``cv2.INTER_LINEAR``) unless ``interpolation`` says otherwise; outside the
    source: 0. ``maps`` reuses :func:`undistort_maps`'s result."""
    import cv2

    if distortion.is_none and (out_intrinsics is None or np.allclose(_K(out_intrinsics), _K(intrinsics))) \
            and (out_intrinsics is None or (out_intrinsics.width, out_intrinsics.height)
                 == (intrinsics.width, intrinsics.height)):
        return np.array(image, copy=True)
    mx, my = maps if maps is not None else undistort_maps(intrinsics, distortion, out_intrinsics)
    interp = cv2.INTER_LINEAR if interpolation is None else interpolation
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] > 4:      # cv2.remap handles up to 4 channels at once
        return np.stack([cv2.remap(np.ascontiguousarray(img[..., c]), mx, my, interp,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                         for c in range(img.shape[2])], axis=-1)
    return cv2.remap(img, mx, my, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


# ---------------------------------------------------------------------------------------------
# Frames of calibrated cameras
# ---------------------------------------------------------------------------------------------


class _Pinhole(NamedTuple):
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


def record_distortion(camera: Any) -> Distortion:
    """The :class:`Distortion` of a ``Calibration`` record's camera (its OpenCV ``distortion``
    ``(k1, k2, p1, p2, k3)``; none for a pinhole). A tracking camera's lens follows its zoom: pass
    that frame's camera, ``record.frame_camera(calibration, id, frame, tracking)``."""
    return Distortion.from_opencv(tuple(getattr(camera, "distortion", None) or ()))


def needs_rectify(camera: Any) -> bool:
    """Whether a record camera's frames must be resampled before a pinhole reads them."""
    return not record_distortion(camera).is_none


def _compute_rectify_maps(intr: _Pinhole, coeffs: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = Distortion.from_opencv(coeffs)
    mx, my = undistort_maps(intr, d, intr)
    # the whole bilinear footprint inside the source: [0, W - 1] x [0, H - 1]
    valid = (mx >= 0) & (my >= 0) & (mx <= intr.width - 1) & (my <= intr.height - 1)
    for a in (mx, my, valid):
        a.setflags(write=False)
    return mx, my, valid


# Two caches of maps (map_x, map_y, valid: ~75 MB at 3840x2160). A static camera has one lens for
# the whole take: its maps are kept (up to 128 cameras). A tracking camera's lens follows its zoom,
# so each of its frames has maps of its own (4 320 of them for 90 zoom cameras over a 48-frame
# segment): sharing the static cache, training's random draws of views evicted every static
# camera's maps and rebuilt maps on nearly every load (0.14-0.2 s at 4K), and the cache pinned
# ~9.5 GB. Per-frame lenses therefore get a small cache of their own: the maps of the last few
# frames, enough for a frame's image, mask and valid pixels loaded one after the other.
_rectify_maps = functools.lru_cache(maxsize=128)(_compute_rectify_maps)
_frame_rectify_maps = functools.lru_cache(maxsize=4)(_compute_rectify_maps)


def _maps_of(camera: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if camera.intrinsics is None:
        raise ValueError(f"camera {camera.id}: a distortion without intrinsics")
    fx, fy, cx, cy = (float(v) for v in camera.intrinsics)
    coeffs = tuple(float(v) for v in camera.distortion)
    cache = _rectify_maps if getattr(camera, "static", True) else _frame_rectify_maps
    return cache(_Pinhole(fx, fy, cx, cy, int(camera.width), int(camera.height)), coeffs)


def rectified_valid(camera: Any) -> np.ndarray | None:
    """[H, W] bool (read-only): the pixels of ``camera``'s rectified frames (:func:`rectify_frame`)
    whose bilinear footprint lies wholly inside the source frame; None for a camera without
    distortion (every pixel valid)."""
    if not needs_rectify(camera):
        return None
    return _maps_of(camera)[2]


def rectify_frame(pixels, camera: Any, *, interpolation: int | None = None):
    """A frame of a calibrated camera (``camera``: a ``Calibration`` record's camera, with its
    ``intrinsics``, ``distortion``, ``width`` and ``height``) [H, W(, C)] -> the same frame seen by
    the pinhole with the record's fx, fy, cx, cy and no distortion. Bilinear (``interpolation``
    otherwise); pixels outside :func:`rectified_valid` are 0. A camera without distortion gets
    ``pixels`` back as they are (the same object). numpy arrays and torch tensors (CPU) both;
    the maps are computed once per static camera (cached); a tracking camera's (``static``
    False: one frame's lens, ``record.frame_camera``) are kept only for the last few frames."""
    if not needs_rectify(camera):
        return pixels
    import cv2

    tensor = None
    if not isinstance(pixels, np.ndarray):
        import torch

        if isinstance(pixels, torch.Tensor):
            tensor = pixels
            pixels = pixels.detach().cpu().numpy()
    img = np.asarray(pixels)
    if img.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"camera {camera.id}: frame is {img.shape[1]}x{img.shape[0]}, the calibration says "
                         f"{camera.width}x{camera.height}")
    mx, my, valid = _maps_of(camera)
    interp = cv2.INTER_LINEAR if interpolation is None else interpolation
    src = np.ascontiguousarray(img)
    if src.dtype == np.float16:
        src = src.astype(np.float32)
    if src.ndim == 3 and src.shape[2] > 4:
        out = np.stack([cv2.remap(np.ascontiguousarray(src[..., c]), mx, my, interp,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                        for c in range(src.shape[2])], axis=-1)
    else:
        out = cv2.remap(src, mx, my, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if out.ndim < img.ndim:              # cv2 drops a trailing channel axis of 1
        out = out[..., None]
    out[~valid] = 0
    out = out.astype(img.dtype, copy=False)
    if tensor is not None:
        import torch

        return torch.from_numpy(out).to(tensor.device)
    return out
