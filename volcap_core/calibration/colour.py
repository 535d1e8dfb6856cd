"""Colour calibration between cameras and rigs from a colour chart, in linear light.

A camera's chart patch colours ``src`` [N, 3] (linear RGB) are mapped to a reference's ``ref`` [N, 3]
(another camera, the Face Rig, or the chart's published values) by an affine map
``ref ≈ src @ M.T + b`` (3x3 matrix + offset), fitted by (optionally robust, weighted) least squares.
The residual is reported as a colour difference in CIELAB: ΔE*ab (CIE76) and ΔE2000, from linear
Rec.709/sRGB primaries through CIE XYZ (D65). Colours are normalised to a white level first so ΔE
is about chromaticity and relative lightness, not absolute exposure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

#: linear Rec.709 / sRGB (D65) -> CIE XYZ (IEC 61966-2-1)
RGB_TO_XYZ = np.array([[0.4124564, 0.3575761, 0.1804375],
                       [0.2126729, 0.7151522, 0.0721750],
                       [0.0193339, 0.1191920, 0.9503041]])
D65_WHITE = RGB_TO_XYZ @ np.ones(3)


@dataclass(frozen=True)
class ColourCalibrationOptions:
    """Settings of the chart colour calibration between two rigs (task ``calibrate-colour``)."""

    #: fit an offset (black-level difference) besides the 3x3 matrix
    offset: bool = True
    #: Cauchy re-weighting rounds against a glared, shadowed or mislocated patch
    robust_iterations: int = 2
    #: each patch's colour is the mean over a square of this fraction of the patch (or, for patch
    #: centres in pixels, of the distance to the nearest patch), centred on it
    window_fraction: float = 0.5
    #: patches seen in both views the fit needs (a ColorChecker has 24)
    min_patches: int = 12


def fit_colour_matrix(src: np.ndarray, ref: np.ndarray, *, offset: bool = True,
                      weights: np.ndarray | None = None, robust_iterations: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ``M`` [3, 3] and ``b`` [3] with ``ref ≈ src @ M.T + b`` (``b = 0`` without offset).

    ``robust_iterations`` > 0 re-weights with Cauchy weights (scale: 1.4826 MAD of the residual norms)
    so a shadowed or clipped patch does not bend the fit.
    """
    src = np.asarray(src, np.float64).reshape(-1, 3)
    ref = np.asarray(ref, np.float64).reshape(-1, 3)
    if len(src) != len(ref):
        raise ValueError(f"{len(src)} source colours for {len(ref)} reference colours")
    need = 4 if offset else 3
    if len(src) < need:
        raise ValueError(f"an affine colour fit needs >= {need} patches, got {len(src)}")
    A = np.c_[src, np.ones(len(src))] if offset else src
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    X = None
    for it in range(robust_iterations + 1):
        sw = np.sqrt(w)[:, None]
        X, *_ = np.linalg.lstsq(A * sw, ref * sw, rcond=None)
        if it < robust_iterations:
            r = np.linalg.norm(A @ X - ref, axis=1)
            s = max(1.4826 * np.median(r), 1e-9)
            w = (np.ones(len(src)) if weights is None else np.asarray(weights)) / (1 + (r / (2 * s)) ** 2)
    M = X[:3].T
    b = X[3] if offset else np.zeros(3)
    return M, b


def apply_colour_matrix(image: np.ndarray | torch.Tensor, M, b: np.ndarray | None = None, *,
                        premultiplied: bool = False) -> np.ndarray | torch.Tensor:
    """``rgb @ M.T + b`` (linear) on an RGB [..., 3] or RGBA [..., 4] image or colour array.

    ``M``: a [3, 3] matrix, or a colour-matrix record (anything with ``matrix`` and ``offset``, e.g.
    :class:`volcap_core.calibration.colour_step.ColourMatrixRecord`; then ``b`` must be None). Alpha is
    passed through unchanged; with ``premultiplied`` (colour already multiplied by alpha, as a
    Gaussian renderer's RGBA is) the offset is scaled by alpha, so a transparent pixel stays 0.
    float32 out for float32 / half images, else float64.

    ``image`` a numpy array, or a torch tensor mapped where it lies (a renderer's frame on its GPU,
    before the copy to the host, which a numpy map of a 4096² frame made the bottleneck) and
    returned there. Both go through the one formula below in float64, so an image's float32 result
    is the same either way (on the CPU bit for bit: a pair frame's EXR bytes do not depend on
    where its colour was mapped; ``tests/enhance/test_splat_pairs.py``).

    This is what makes a Face Rig render comparable with a Scene Rig one: a pair renderer applies the
    ``calibrate-colour`` record to the rig it maps (its ``source_rig``) before pairing the images.
    """
    if hasattr(M, "matrix"):
        if b is not None:
            raise ValueError("give either a colour-matrix record or a matrix and offset, not both")
        M, b = M.matrix, M.offset
    M = np.asarray(M, np.float64)
    if M.shape != (3, 3):
        raise ValueError(f"colour matrix must be 3x3, got {M.shape}")
    tensor = isinstance(image, torch.Tensor)
    image = image if tensor else np.asarray(image)
    if image.shape[-1] not in (3, 4):
        raise ValueError(f"expected RGB or RGBA in the last axis, got shape {tuple(image.shape)}")
    off = None if b is None else np.asarray(b, np.float64)
    if tensor:
        x = image.to(torch.float64)
        dtype = torch.float32 if image.dtype in (torch.float32, torch.float16, torch.bfloat16) else torch.float64
        M, join = torch.tensor(M, device=x.device), torch.cat
        off = None if off is None else torch.tensor(off, device=x.device)
    else:
        x = image.astype(np.float64, copy=False)
        dtype, join = np.float32 if image.dtype in (np.float32, np.float16) else np.float64, np.concatenate
    out = x[..., :3] @ M.T
    if off is not None:
        out = out + (off * x[..., 3:4] if premultiplied and x.shape[-1] == 4 else off)
    if x.shape[-1] == 4:
        out = join([out, x[..., 3:4]], -1)
    return out.to(dtype) if tensor else out.astype(dtype, copy=False)


def linear_rgb_to_lab(rgb: np.ndarray, white: float = 1.0) -> np.ndarray:
    """Linear sRGB [..., 3] -> CIELAB (D65), with ``white`` the linear level of reference white."""
    xyz = np.asarray(rgb, np.float64) / white @ RGB_TO_XYZ.T / D65_WHITE
    d = 6 / 29
    f = np.where(xyz > d ** 3, np.cbrt(np.maximum(xyz, 0)), xyz / (3 * d * d) + 4 / 29)
    L = 116 * f[..., 1] - 16
    a = 500 * (f[..., 0] - f[..., 1])
    bb = 200 * (f[..., 1] - f[..., 2])
    return np.stack([L, a, bb], -1)


def delta_e76(lab1: np.ndarray, lab2: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.asarray(lab1) - np.asarray(lab2), axis=-1)


def delta_e2000(lab1: np.ndarray, lab2: np.ndarray) -> np.ndarray:
    """CIEDE2000 (Sharma, Wu & Dalal 2005), kL = kC = kH = 1."""
    L1, a1, b1 = np.moveaxis(np.asarray(lab1, np.float64), -1, 0)
    L2, a2, b2 = np.moveaxis(np.asarray(lab2, np.float64), -1, 0)
    C1, C2 = np.hypot(a1, b1), np.hypot(a2, b2)
    Cm = (C1 + C2) / 2
    G = 0.5 * (1 - np.sqrt(Cm ** 7 / (Cm ** 7 + 25 ** 7)))
    a1p, a2p = (1 + G) * a1, (1 + G) * a2
    C1p, C2p = np.hypot(a1p, b1), np.hypot(a2p, b2)
    h1p = np.degrees(np.arctan2(b1, a1p)) % 360
    h2p = np.degrees(np.arctan2(b2, a2p)) % 360
    dLp = L2 - L1
    dCp = C2p - C1p
    dhp = h2p - h1p
    dhp = np.where(dhp > 180, dhp - 360, np.where(dhp < -180, dhp + 360, dhp))
    dhp = np.where(C1p * C2p == 0, 0, dhp)
    dHp = 2 * np.sqrt(C1p * C2p) * np.sin(np.radians(dhp / 2))
    Lpm = (L1 + L2) / 2
    Cpm = (C1p + C2p) / 2
    hsum = h1p + h2p
    hpm = np.where(np.abs(h1p - h2p) > 180, np.where(hsum < 360, (hsum + 360) / 2, (hsum - 360) / 2), hsum / 2)
    hpm = np.where(C1p * C2p == 0, hsum, hpm)
    Tt = (1 - 0.17 * np.cos(np.radians(hpm - 30)) + 0.24 * np.cos(np.radians(2 * hpm))
          + 0.32 * np.cos(np.radians(3 * hpm + 6)) - 0.20 * np.cos(np.radians(4 * hpm - 63)))
    dtheta = 30 * np.exp(-(((hpm - 275) / 25) ** 2))
    Rc = 2 * np.sqrt(Cpm ** 7 / (Cpm ** 7 + 25 ** 7))
    Sl = 1 + 0.015 * (Lpm - 50) ** 2 / np.sqrt(20 + (Lpm - 50) ** 2)
    Sc = 1 + 0.045 * Cpm
    Sh = 1 + 0.015 * Cpm * Tt
    Rt = -np.sin(np.radians(2 * dtheta)) * Rc
    return np.sqrt((dLp / Sl) ** 2 + (dCp / Sc) ** 2 + (dHp / Sh) ** 2 + Rt * (dCp / Sc) * (dHp / Sh))


def colour_residuals(src: np.ndarray, ref: np.ndarray, M: np.ndarray | None = None, b: np.ndarray | None = None,
                     white: float | None = None) -> dict:
    """ΔE76 and ΔE2000 (mean, max, per patch) between ``ref`` and ``src`` mapped by ``(M, b)``
    (identity when None). ``white``: linear level of reference white (default: the brightest
    reference patch's luminance, so ΔE is independent of exposure)."""
    src = np.asarray(src, np.float64)
    ref = np.asarray(ref, np.float64)
    mapped = src if M is None else apply_colour_matrix(src, M, b)
    if white is None:
        white = float((ref @ RGB_TO_XYZ[1]).max())
    l1 = linear_rgb_to_lab(mapped, white)
    l2 = linear_rgb_to_lab(ref, white)
    e76 = delta_e76(l1, l2)
    e00 = delta_e2000(l1, l2)
    return {"delta_e76_mean": float(e76.mean()), "delta_e76_max": float(e76.max()),
            "delta_e2000_mean": float(e00.mean()), "delta_e2000_max": float(e00.max()),
            "delta_e2000": e00.tolist()}


def calibrate_colour(src: np.ndarray, ref: np.ndarray, *, offset: bool = True, robust_iterations: int = 2) -> dict:
    """Fit ``src`` patches onto ``ref`` patches; return ``matrix`` [3, 3], ``offset`` [3] and the
    residual ΔE before and after (see :func:`colour_residuals`)."""
    M, b = fit_colour_matrix(src, ref, offset=offset, robust_iterations=robust_iterations)
    return {"matrix": M, "offset": b, "before": colour_residuals(src, ref), "after": colour_residuals(src, ref, M, b)}


def sample_patches(image: np.ndarray, centres_px: np.ndarray, radius_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean linear colour [N, 3] of square windows (half size ``radius_px``) around OpenCV pixel
    centres [N, 2], and a validity mask [N] (window inside the image, at least 4 pixels)."""
    img = np.asarray(image, np.float64)[..., :3]
    h, w = img.shape[:2]
    out = np.zeros((len(centres_px), 3))
    ok = np.zeros(len(centres_px), bool)
    r = max(0.5, float(radius_px))
    for i, (x, y) in enumerate(np.asarray(centres_px, np.float64)):
        x0, x1 = int(np.ceil(x - r)), int(np.floor(x + r)) + 1
        y0, y1 = int(np.ceil(y - r)), int(np.floor(y + r)) + 1
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h or (x1 - x0) * (y1 - y0) < 4:
            continue
        out[i] = img[y0:y1, x0:x1].reshape(-1, 3).mean(0)
        ok[i] = True
    return out, ok


def chart_patches_in_view(image: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray,
                          patch_centres_m: np.ndarray, patch_size_m: float, fraction: float = 0.5
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Sample a chart's patches in a calibrated view: project the patch centres (stage frame, [N, 3])
    and average a window of ``fraction`` of the patch's projected size. Returns colours [N, 3] and a
    mask [N] (in front, inside, at least 4 px)."""
    P = np.asarray(patch_centres_m, np.float64)
    pc = P @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = pc[:, 2]
    uv = pc[:, :2] / np.maximum(z, 1e-9)[:, None] @ K[:2, :2].T + K[:2, 2]
    radius = 0.5 * fraction * patch_size_m * K[0, 0] / np.maximum(z, 1e-9)
    cols = np.zeros((len(P), 3))
    ok = np.zeros(len(P), bool)
    for i in range(len(P)):
        if z[i] <= 0:
            continue
        c, m = sample_patches(image, uv[i:i + 1], radius[i])
        cols[i], ok[i] = c[0], m[0] and radius[i] >= 1.0
    return cols, ok


def chart_grid_px(corners_px: np.ndarray, rows: int = 4, cols: int = 6) -> np.ndarray:
    """Patch centres [rows * cols, 2] (row-major, as a ColorChecker's patches are numbered) of a
    flat chart from the centres of its four corner patches, in the order first patch (row 0, col 0),
    end of the first row, last patch, start of the last row: the projective map of the chart plane
    (exact for a pinhole view of a flat chart)."""
    c = np.asarray(corners_px, np.float64).reshape(4, 2)
    if rows < 2 or cols < 2:
        raise ValueError(f"a chart grid needs at least 2 x 2 patches, got {rows} x {cols}")
    src = np.array([[0, 0], [cols - 1, 0], [cols - 1, rows - 1], [0, rows - 1]], np.float64)
    extent = max(float(np.ptp(c, axis=0).max()), 1e-12)
    for i, j, k in ((0, 1, 2), (1, 2, 3), (2, 3, 0), (3, 0, 1)):
        area = abs(np.cross(c[j] - c[i], c[k] - c[i])) / 2
        if area < 1e-3 * extent ** 2:
            raise ValueError("the four chart corners are degenerate (three of them collinear or repeated)")
    A = []
    for (x, y), (u, v) in zip(src, c):
        A.append([x, y, 1, 0, 0, 0, -u * x, -u * y, -u])
        A.append([0, 0, 0, x, y, 1, -v * x, -v * y, -v])
    _, _, vt = np.linalg.svd(np.asarray(A))
    H = vt[-1].reshape(3, 3)
    gy, gx = np.mgrid[0:rows, 0:cols]
    g = np.c_[gx.ravel(), gy.ravel(), np.ones(rows * cols)] @ H.T
    return g[:, :2] / g[:, 2:3]


def grid_spacing_px(centres_px: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Per patch [rows * cols], the smaller distance to its row and column neighbours (px)."""
    g = np.asarray(centres_px, np.float64).reshape(rows, cols, 2)
    dx = np.linalg.norm(np.diff(g, axis=1), axis=-1)
    dy = np.linalg.norm(np.diff(g, axis=0), axis=-1)
    hx = np.minimum(np.pad(dx, ((0, 0), (1, 0)), constant_values=np.inf), np.pad(dx, ((0, 0), (0, 1)), constant_values=np.inf))
    hy = np.minimum(np.pad(dy, ((1, 0), (0, 0)), constant_values=np.inf), np.pad(dy, ((0, 1), (0, 0)), constant_values=np.inf))
    return np.minimum(hx, hy).ravel()
