"""Procedural textures (seeded), mip-mapped bilinear sampling, calibration patterns, colour chart.

Texture maps hold *linear* values (albedo, or radiance where a flat surface's lighting is baked in).
A map of shape (rows, cols, 3) covers ``rows * texel_m`` by ``cols * texel_m`` metres; texel (i, j)
covers v in [i, i+1) * texel_m and u in [j, j+1) * texel_m.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

# ColorChecker Classic, sRGB 8-bit (BabelColor averages, D65), row-major from dark skin to black.
COLORCHECKER_NAMES = (
    "dark skin", "light skin", "blue sky", "foliage", "blue flower", "bluish green",
    "orange", "purplish blue", "moderate red", "purple", "yellow green", "orange yellow",
    "blue", "green", "red", "yellow", "magenta", "cyan",
    "white 9.5", "neutral 8", "neutral 6.5", "neutral 5", "neutral 3.5", "black 2")
COLORCHECKER_SRGB8 = np.array([
    (115, 82, 68), (194, 150, 130), (98, 122, 157), (87, 108, 67), (133, 128, 177), (103, 189, 170),
    (214, 126, 44), (80, 91, 166), (193, 90, 99), (94, 60, 108), (157, 188, 64), (224, 163, 46),
    (56, 61, 150), (70, 148, 73), (175, 54, 60), (231, 199, 31), (187, 86, 149), (8, 133, 161),
    (243, 243, 242), (200, 200, 200), (160, 160, 160), (122, 122, 121), (85, 85, 85), (52, 52, 52)],
    np.float64)


def srgb_to_linear(x):
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def colorchecker_linear() -> np.ndarray:
    """(24, 3) linear Rec.709 reflectances of the 24 patches."""
    return srgb_to_linear(COLORCHECKER_SRGB8 / 255.0)


class Texture:
    """A mip-mapped texture sampled bilinearly in metres, the level picked from the footprint."""

    def __init__(self, image: np.ndarray, texel_m: float, wrap: bool | tuple[bool, bool] = False,
                 levels: int = 6):
        img = np.ascontiguousarray(image, np.float32)
        self.texel_m = float(texel_m)
        self.wrap = wrap  # one flag for both axes, or (wrap in u, wrap in v)
        self.levels = [img]
        while len(self.levels) < levels and min(self.levels[-1].shape[:2]) >= 8:
            prev = self.levels[-1]
            h, w = (prev.shape[0] + 1) // 2, (prev.shape[1] + 1) // 2
            self.levels.append(cv2.resize(prev, (w, h), interpolation=cv2.INTER_AREA))

    @property
    def size_m(self) -> tuple[float, float]:
        h, w = self.levels[0].shape[:2]
        return (w * self.texel_m, h * self.texel_m)

    def sample(self, u, v, footprint=None) -> np.ndarray:
        """Bilinear lookup at (u, v) metres (arrays of one shape) -> (..., 3)."""
        u = np.asarray(u, np.float32)
        v = np.asarray(v, np.float32)
        shape = u.shape
        u, v = u.reshape(-1), v.reshape(-1)
        if footprint is None or len(self.levels) == 1:
            return self._bilinear(0, u, v).reshape(shape + (3,))
        fp = np.asarray(footprint, np.float32).reshape(-1)
        lvl = np.clip(np.floor(np.log2(np.maximum(fp, 1e-9) / self.texel_m) + 0.5),
                      0, len(self.levels) - 1).astype(np.int8)
        present = np.flatnonzero(np.bincount(lvl, minlength=len(self.levels)))
        if len(present) == 1:
            return self._bilinear(int(present[0]), u, v).reshape(shape + (3,))
        out = np.empty((u.size, 3), np.float32)
        for level in present:
            m = lvl == level
            out[m] = self._bilinear(int(level), u[m], v[m])
        return out.reshape(shape + (3,))

    def _bilinear(self, level, u, v):
        """cv2.remap does the bilinear lookups (about 20x faster than numpy gathers)."""
        img = self.levels[level]
        h, w = img.shape[:2]
        h0, w0 = self.levels[0].shape[:2]
        x = u * np.float32(w / (w0 * self.texel_m)) - np.float32(0.5)
        y = v * np.float32(h / (h0 * self.texel_m)) - np.float32(0.5)
        wu, wv = self.wrap if isinstance(self.wrap, tuple) else (self.wrap, self.wrap)
        if wu or wv:
            x = np.mod(x, w) if wu else np.clip(x, 0, w - 1)
            y = np.mod(y, h) if wv else np.clip(y, 0, h - 1)
            border = cv2.BORDER_WRAP
        else:
            border = cv2.BORDER_REPLICATE
        n = x.size
        if n == 0:
            return np.zeros((0, 3), np.float32)
        cols = 1024 if n > 1024 else n
        rows = -(-n // cols)
        pad = rows * cols - n
        if pad:
            x = np.concatenate([x, np.zeros(pad, np.float32)])
            y = np.concatenate([y, np.zeros(pad, np.float32)])
        out = cv2.remap(img, x.reshape(rows, cols).astype(np.float32), y.reshape(rows, cols).astype(np.float32),
                        cv2.INTER_LINEAR, borderMode=border)
        return out.reshape(-1, 3)[:n]


# --------------------------------------------------------------------------- generators

def value_noise(rng: np.random.Generator, rows: int, cols: int, cell_px: float, octaves: int = 4,
                persistence: float = 0.55, wrap: bool = False) -> np.ndarray:
    """Fractal value noise in about [-1, 1], (rows, cols) float32; the coarsest cell is ``cell_px``."""
    out = np.zeros((rows, cols), np.float32)
    amp, total = 1.0, 0.0
    cell = float(cell_px)
    for _ in range(octaves):
        if cell < 1.5:
            break
        gh, gw = max(2, int(math.ceil(rows / cell)) + 2), max(2, int(math.ceil(cols / cell)) + 2)
        grid = rng.uniform(-1, 1, (gh, gw)).astype(np.float32)
        if wrap:
            gh, gw = max(2, int(round(rows / cell))), max(2, int(round(cols / cell)))
            grid = rng.uniform(-1, 1, (gh, gw)).astype(np.float32)
            grid = np.pad(grid, 2, mode="wrap")
            up = cv2.resize(grid, ((gw + 4) * cols // gw, (gh + 4) * rows // gh),
                            interpolation=cv2.INTER_CUBIC)
            oy, ox = 2 * rows // gh, 2 * cols // gw
            layer = up[oy:oy + rows, ox:ox + cols]
            layer = np.pad(layer, ((0, rows - layer.shape[0]), (0, cols - layer.shape[1])), mode="edge")
        else:
            up = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
            layer = up[:rows, :cols]
        out += amp * layer
        total += amp
        amp *= persistence
        cell /= 2.0
    return out / max(total, 1e-9)


def random_palette(rng: np.random.Generator, n: int, lo: float = 0.04, hi: float = 0.8) -> np.ndarray:
    """n random linear reflectances, varied hue and lightness."""
    light = np.exp(rng.uniform(np.log(lo), np.log(hi), n))
    tint = rng.uniform(0.35, 1.0, (n, 3))
    tint /= tint.max(axis=1, keepdims=True)
    return (light[:, None] * tint).astype(np.float32)


def draw_shapes(img: np.ndarray, rng: np.random.Generator, count: int, size_px: tuple[float, float],
                palette: np.ndarray) -> None:
    """Scatter random discs, rotated rectangles, strokes and rings (in place)."""
    rows, cols = img.shape[:2]
    lo, hi = math.log(size_px[0]), math.log(size_px[1])
    kinds = rng.integers(0, 4, count)
    sizes = np.exp(rng.uniform(lo, hi, count))
    xs = rng.uniform(0, cols, count)
    ys = rng.uniform(0, rows, count)
    angs = rng.uniform(0, math.pi, count)
    aspects = rng.uniform(0.2, 1.0, count)
    cols_idx = rng.integers(0, len(palette), count)
    for k in range(count):
        color = tuple(float(c) for c in palette[cols_idx[k]])
        s, x, y = sizes[k], xs[k], ys[k]
        if kinds[k] == 0:
            cv2.circle(img, (int(x), int(y)), max(1, int(s / 2)), color, -1)
        elif kinds[k] == 1:
            rect = ((float(x), float(y)), (float(s), float(s * aspects[k])), float(np.degrees(angs[k])))
            cv2.fillPoly(img, [cv2.boxPoints(rect).astype(np.int32)], color)
        elif kinds[k] == 2:
            dx, dy = s * math.cos(angs[k]), s * math.sin(angs[k])
            cv2.line(img, (int(x - dx), int(y - dy)), (int(x + dx), int(y + dy)), color,
                     max(1, int(s * 0.12 * aspects[k])))
        else:
            cv2.circle(img, (int(x), int(y)), max(2, int(s / 2)), color, max(1, int(s * 0.12)))


def surface_texture(rng: np.random.Generator, width_m: float, height_m: float, texel_m: float,
                    base: np.ndarray, shapes_per_m2: float = 30.0, contrast: float = 0.45,
                    size_m: tuple[float, float] = (0.03, 0.5), palette_size: int = 24) -> np.ndarray:
    """A non-repetitive, feature-rich albedo map: coloured fractal noise plus scattered shapes."""
    rows, cols = max(8, int(round(height_m / texel_m))), max(8, int(round(width_m / texel_m)))
    n1 = value_noise(rng, rows, cols, cell_px=1.2 / texel_m, octaves=6)
    n2 = value_noise(rng, rows, cols, cell_px=0.35 / texel_m, octaves=3)
    img = np.empty((rows, cols, 3), np.float32)
    base = np.asarray(base, np.float32)
    for ch in range(3):
        img[..., ch] = base[ch] * (1 + contrast * n1 + 0.1 * contrast * n2 * (ch - 1))
    palette = random_palette(rng, palette_size)
    count = int(shapes_per_m2 * width_m * height_m)
    draw_shapes(img, rng, count, (size_m[0] / texel_m, size_m[1] / texel_m), palette)
    grain = value_noise(rng, rows, cols, cell_px=3.0, octaves=2)
    img *= (1 + 0.12 * grain)[..., None]
    # soften the texel staircase of the (non-antialiased) shapes when zoom cameras magnify it
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    return np.clip(img, 0.01, 0.95)


def aruco_cells(marker_id: int, dictionary: int = cv2.aruco.DICT_4X4_50) -> np.ndarray:
    """(n+2, n+2) array of 0/1 cells of an ArUco marker including its black border; row 0 = top."""
    d = cv2.aruco.getPredefinedDictionary(dictionary)
    n = d.markerSize + 2
    img = cv2.aruco.generateImageMarker(d, marker_id, n)
    return (img > 127).astype(np.float32)


def checker_cells(cols: int, rows: int) -> np.ndarray:
    """(rows, cols) checkerboard, top-left square black."""
    return ((np.arange(rows)[:, None] + np.arange(cols)[None, :]) % 2).astype(np.float32)


def chart_texture(patch_m: float, gap_m: float, texel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A 6 x 4 ColorChecker on a black frame: albedo map (row index = b / texel) and patch centres in chart
    coordinates (a, b) metres from the bottom-left corner (a right, b up), (24, 2)."""
    cols, rows = 6, 4
    w = cols * patch_m + (cols + 1) * gap_m
    h = rows * patch_m + (rows + 1) * gap_m
    nx, ny = int(round(w / texel_m)), int(round(h / texel_m))
    img = np.full((ny, nx, 3), 0.02, np.float32)   # black frame
    refl = colorchecker_linear().astype(np.float32)
    centres = []
    for k in range(24):
        r, c = divmod(k, cols)
        a0 = gap_m + c * (patch_m + gap_m)
        b_top = h - (gap_m + r * (patch_m + gap_m))     # row 0 at the top
        j0, j1 = int(round(a0 / texel_m)), int(round((a0 + patch_m) / texel_m))
        i0, i1 = int(round((b_top - patch_m) / texel_m)), int(round(b_top / texel_m))
        img[i0:i1, j0:j1] = refl[k]
        centres.append((a0 + patch_m / 2, b_top - patch_m / 2))
    # indices above are already b / texel_m (rows increase upwards with b): no flip
    return img, np.array(centres)
