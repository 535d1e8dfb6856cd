"""Turning scene-linear frames into the 8-bit images that feature detectors and matchers want."""

from __future__ import annotations

import numpy as np

from volcap_core.colour import srgb_encode


def exposure_normalise(linear: np.ndarray, percentile: float = 99.0, target: float = 0.9) -> np.ndarray:
    """Scale a linear image [H, W, C] so its ``percentile`` luminance lands at ``target``.

    Cameras of a rig differ in gain (the synthetic sensors by up to ±60 %); SIFT is invariant to
    affine intensity changes but not to clipping, so every image is first brought to a common level.
    """
    img = np.asarray(linear, np.float32)
    lum = luminance(img) if img.ndim == 3 else img
    p = float(np.percentile(lum, percentile))
    return img * (target / p) if p > 1e-8 else img


def luminance(linear: np.ndarray) -> np.ndarray:
    """Rec.709 luminance of a linear RGB(A) image [H, W, C>=3] -> [H, W]."""
    img = np.asarray(linear, np.float32)
    return img[..., 0] * 0.2126 + img[..., 1] * 0.7152 + img[..., 2] * 0.0722


def to_uint8_gray(linear: np.ndarray, normalise: bool = True) -> np.ndarray:
    """Linear RGB(A) [H, W, C] or gray [H, W] -> display-referred sRGB gray uint8 [H, W]."""
    img = np.asarray(linear, np.float32)
    if normalise:
        img = exposure_normalise(img)
    g = luminance(img) if img.ndim == 3 else img
    enc = srgb_encode(np.clip(g, 0.0, 1.0))
    return np.ascontiguousarray(np.round(enc * 255.0).astype(np.uint8))
