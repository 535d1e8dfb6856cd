"""What a camera does to scene radiance, and what its lens encoder reports.

Recorded value of pixel (x, y), channel c (documented in ``docs/synthetic-capture.md``)::

    I = gain * channel_gain[c] * V(x, y) * G[L](x, y, c) + black[c] + noise
    G[L] = (1 - glare) * L + glare * (L * gaussian(sigma_px))        zoom (tracking) cameras only
    V(x, y) = (1 - k * r^2) * (1 + gx * xn + gy * yn)
    xn = (x - (W-1)/2) / (W/2),  yn = (y - (H-1)/2) / (H/2),  r^2 = (xn^2 W^2 + yn^2 H^2) / (W^2 + H^2)
    noise ~ N(0, read^2 + shot * max(S, 0)), S = the noiseless signal before ``+ black``
            (independent per pixel, channel and frame)

Lens encoder reading of a tracking camera at one of its frames::

    focal_reading = focal_true * (1 + gain_error) + offset_mm + N(0, (noise_rel * focal_true)^2)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np


@functools.lru_cache(maxsize=8)
def _vignette(width: int, height: int, k: float, gradient: tuple[float, float]) -> np.ndarray:
    xn = (np.arange(width) - (width - 1) / 2) / (width / 2)
    yn = (np.arange(height) - (height - 1) / 2) / (height / 2)
    r2 = (xn[None, :] ** 2 * width ** 2 + yn[:, None] ** 2 * height ** 2) / (width ** 2 + height ** 2)
    g = 1 + gradient[0] * xn[None, :] + gradient[1] * yn[:, None]
    v = ((1 - k * r2) * g).astype(np.float32)
    v.flags.writeable = False
    return v


@dataclass(frozen=True)
class SensorModel:
    gain: float
    channel_gain: tuple[float, float, float]
    black: tuple[float, float, float]
    vignette_k: float
    gradient: tuple[float, float]
    glare: float            # 0 for static cameras
    glare_sigma_frac: float  # sigma as a fraction of max(W, H)
    read_noise: float
    shot_noise: float

    @staticmethod
    def random(rng: np.random.Generator, zoom: bool) -> "SensorModel":
        return SensorModel(
            gain=float(np.exp(rng.uniform(np.log(0.6), np.log(1.6)))),
            channel_gain=tuple(float(x) for x in rng.uniform(0.94, 1.06, 3)),
            black=tuple(float(x) for x in rng.uniform(0.002, 0.012, 3)),
            vignette_k=float(rng.uniform(0.08, 0.3)),
            gradient=tuple(float(x) for x in rng.uniform(-0.05, 0.05, 2)),
            glare=float(rng.uniform(0.01, 0.04)) if zoom else 0.0,
            glare_sigma_frac=0.15,
            read_noise=0.0015,
            shot_noise=0.0004)

    def vignette(self, width: int, height: int) -> np.ndarray:
        return _vignette(width, height, self.vignette_k, self.gradient)

    def veiling_glare(self, rad: np.ndarray) -> np.ndarray:
        if self.glare <= 0:
            return rad
        h, w = rad.shape[:2]
        sigma = self.glare_sigma_frac * max(w, h)
        f = max(1, int(sigma // 8))                        # blur a reduced copy: it is smooth anyway
        small = cv2.resize(rad, (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA)
        blurred = cv2.GaussianBlur(small, (0, 0), sigma / f, borderType=cv2.BORDER_REFLECT)
        blurred = cv2.resize(blurred, (w, h), interpolation=cv2.INTER_LINEAR)
        return (1 - self.glare) * rad + self.glare * blurred

    def apply(self, rad: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """Radiance ``rad`` (H, W, 3) → the recorded values (H, W, 3) float32 (module doc).
        ``rng=None``: without the noise (the expected recorded value: signal + black)."""
        h, w = rad.shape[:2]
        sig = self.veiling_glare(rad) * (self.gain * self.vignette(w, h))[..., None] \
            * np.asarray(self.channel_gain, np.float32)
        out = sig + np.asarray(self.black, np.float32)
        if rng is not None:
            std = np.sqrt(self.read_noise ** 2 + self.shot_noise * np.maximum(sig, 0))
            out = out + std * rng.standard_normal(sig.shape, np.float32)
        return out.astype(np.float32)

    @staticmethod
    def from_json(d: dict) -> "SensorModel":
        """The inverse of :meth:`to_json` (a camera's ``photometric`` in ``ground_truth/cameras.json``)."""
        return SensorModel(gain=float(d["gain"]), channel_gain=tuple(float(x) for x in d["channel_gain"]),
                           black=tuple(float(x) for x in d["black_offset"]), vignette_k=float(d["vignette_k"]),
                           gradient=tuple(float(x) for x in d["vignette_gradient"]),
                           glare=float(d["glare_fraction"]), glare_sigma_frac=float(d["glare_sigma_px_per_max_side"]),
                           read_noise=float(d["read_noise"]), shot_noise=float(d["shot_noise"]))

    def to_json(self) -> dict:
        return {"gain": self.gain, "channel_gain": list(self.channel_gain), "black_offset": list(self.black),
                "vignette_k": self.vignette_k, "vignette_gradient": list(self.gradient),
                "glare_fraction": self.glare, "glare_sigma_px_per_max_side": self.glare_sigma_frac,
                "read_noise": self.read_noise, "shot_noise": self.shot_noise}


@dataclass(frozen=True)
class EncoderModel:
    gain_error: float
    offset_mm: float
    noise_rel: float = 0.002
    focus_noise_rel: float = 0.02

    @staticmethod
    def random(rng: np.random.Generator, focal_min_mm: float) -> "EncoderModel":
        return EncoderModel(gain_error=float(rng.normal(0, 0.01)),
                            offset_mm=float(rng.normal(0, 0.01 * focal_min_mm)))

    def read(self, rng: np.random.Generator, focal_mm: float, focus_m: float) -> tuple[float, float]:
        f = focal_mm * (1 + self.gain_error) + self.offset_mm + rng.normal(0, self.noise_rel * focal_mm)
        d = focus_m * (1 + rng.normal(0, self.focus_noise_rel))
        return round(float(f), 4), round(float(max(d, 0.1)), 4)

    def to_json(self) -> dict:
        return {"gain_error": self.gain_error, "offset_mm": self.offset_mm, "noise_rel": self.noise_rel,
                "focus_noise_rel": self.focus_noise_rel,
                "model": "reading = focal_true*(1+gain_error) + offset_mm + N(0, (noise_rel*focal_true)^2)"}


def smooth_zoom(t: float, period_s: float, phase: float, depth: float = 0.15) -> float:
    """Smooth multiplicative zoom modulation exp(depth * sin(2 pi t / period + phase))."""
    return math.exp(depth * math.sin(2 * math.pi * t / period_s + phase))
