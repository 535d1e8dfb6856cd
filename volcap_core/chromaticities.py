"""Colour primaries: volcap's working space, and footage converted into it from the primaries its
EXR ``chromaticities`` attribute declares.

The working space
-----------------
Scene-linear with ITU-R BT.709 / IEC 61966-2-1 (sRGB) primaries and a D65 white
(:data:`WORKING_CHROMATICITIES`): what ``srgb`` footage decodes to, what an OCIO config's
``scene_linear`` role must name (``docs/capture-layout.md``), what calibration and reconstruction
treat as linear Rec.709, and what every EXR volcap writes declares in its ``chromaticities``
attribute (:func:`volcap_core.imageio.write.encode_exr` writes it by default). An EXR without the
attribute is Rec.709/D65 by the OpenEXR specification, so it needs no conversion.

Conversion
----------
``RGB_file → XYZ → (chromatic adaptation) → RGB_working``, one 3×3 matrix applied by OpenColorIO
(a ``MatrixTransform``). ``RGB → XYZ`` is the usual normalised primary matrix: the primaries'
chromaticities scaled so that RGB (1, 1, 1) is the white point at Y = 1 (OpenEXR's ``RGBtoXYZ``).
The adaptation is **Bradford** (von Kries scaling in the Bradford cone space): the method OpenEXR's
own ACES reader (``ImfAcesFile``) uses, and the one behind OpenColorIO's studio config's
``ACES2065-1 → Linear Rec.709 (sRGB)`` matrix, which :func:`to_working_matrix` reproduces.

Which white is adapted from D65:

* the file's ``adoptedNeutral`` when it has one (OpenEXR: "the (x, y) that should be considered
  neutral during colour rendering");
* else the white of its ``chromaticities``;
* except CIE XYZ itself (primaries on the X, Y, Z axes and white E, so ``RGB → XYZ`` is the
  identity): such pixels are tristimulus values with no white of their own, converted to the
  working space without adaptation, as DCDM X'Y'Z' is (SMPTE ST 428) and as the openexr-images
  ``Chromaticities/XYZ.exr`` was made (it holds the unadapted XYZ of ``Rec709.exr``).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

__all__ = [
    "Chromaticities",
    "REC709_D65",
    "WORKING_CHROMATICITIES",
    "EXR_DEFAULT_CHROMATICITIES",
    "CIE_XYZ",
    "SAME_TOLERANCE",
    "same_chromaticities",
    "needs_conversion",
    "rgb_to_xyz_matrix",
    "bradford_matrix",
    "to_working_matrix",
    "convert_to_working",
]


class Chromaticities(NamedTuple):
    """CIE 1931 (x, y) of the red, green and blue primaries and the white, in the order of the
    EXR ``chromaticities`` attribute (8 numbers)."""

    red_x: float
    red_y: float
    green_x: float
    green_y: float
    blue_x: float
    blue_y: float
    white_x: float
    white_y: float

    @property
    def white(self) -> tuple[float, float]:
        return (self.white_x, self.white_y)

    def __str__(self) -> str:
        r, g, b = (self.red_x, self.red_y), (self.green_x, self.green_y), (self.blue_x, self.blue_y)
        return f"red {_xy(r)}, green {_xy(g)}, blue {_xy(b)}, white {_xy(self.white)}"


def _xy(p: tuple[float, float]) -> str:
    return f"({p[0]:.4g}, {p[1]:.4g})"


#: ITU-R BT.709 primaries, D65 white (CIE 1931 2°, the 4-digit values of the standards).
REC709_D65 = Chromaticities(0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)
#: volcap's working space (see the module docstring).
WORKING_CHROMATICITIES = REC709_D65
#: What an EXR without a ``chromaticities`` attribute is in (the OpenEXR specification's default).
EXR_DEFAULT_CHROMATICITIES = REC709_D65
#: CIE XYZ as an RGB space: primaries on the axes, equal-energy white (OpenEXR's convention).
CIE_XYZ = Chromaticities(1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0 / 3.0, 1.0 / 3.0)
#: Two sets of chromaticities within this of each other (every coordinate) are the same space:
#: float32 storage and the 4- vs 5-digit D65 in circulation (0.3127 vs 0.31271) differ by < 1e-4,
#: while distinct standard gamuts differ by > 1e-2.
SAME_TOLERANCE = 2e-4

#: Bradford cone-response matrix (XYZ → LMS), as in ImfAcesFile and Lindbloom.
_BRADFORD = np.array([[0.8951, 0.2664, -0.1614],
                      [-0.7502, 1.7135, 0.0367],
                      [0.0389, -0.0685, 1.0296]])


def same_chromaticities(a: tuple[float, ...], b: tuple[float, ...], tol: float = SAME_TOLERANCE) -> bool:
    return len(a) == len(b) and all(abs(x - y) <= tol for x, y in zip(a, b))


def _close_xy(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return same_chromaticities(a, b)


def needs_conversion(chromaticities: Chromaticities | None,
                     adopted_neutral: tuple[float, float] | None = None) -> bool:
    """Whether footage declaring these needs converting to the working space (None: the EXR
    default, Rec.709/D65, needs nothing)."""
    if chromaticities is None and adopted_neutral is None:
        return False
    c = chromaticities or EXR_DEFAULT_CHROMATICITIES
    neutral = adopted_neutral or c.white
    return not (same_chromaticities(c, WORKING_CHROMATICITIES)
                and _close_xy(neutral, WORKING_CHROMATICITIES.white))


def _white_xyz(xy: tuple[float, float], what: str) -> np.ndarray:
    """(x, y) → XYZ at Y = 1, [3]."""
    x, y = (float(v) for v in xy)
    if not (np.isfinite(x) and np.isfinite(y)) or y <= 0.0 or x < 0.0 or x + y > 1.0:
        raise ValueError(f"{what} ({x:.4g}, {y:.4g}) is not a physical white (needs y > 0, x >= 0, x + y <= 1)")
    return np.array([x / y, 1.0, (1.0 - x - y) / y])


def rgb_to_xyz_matrix(c: Chromaticities) -> np.ndarray:
    """[3, 3] float64 taking linear RGB in ``c``'s primaries to CIE XYZ, RGB (1,1,1) → white at Y = 1.

    Raises ValueError when ``c`` defines no RGB space: non-finite numbers, collinear primaries,
    a white that is not physical or lies outside the primaries' triangle (a primary would be
    scaled by a negative amount).
    """
    values = np.array(c, dtype=np.float64)
    if not np.isfinite(values).all():
        raise ValueError(f"chromaticities {tuple(c)} hold NaN or Inf")
    xs, ys = values[0:6:2], values[1:6:2]
    # columns: each primary's (x, y, z = 1 - x - y); y = 0 is allowed (CIE XYZ's own blue)
    primaries = np.stack([xs, ys, 1.0 - xs - ys])
    if abs(np.linalg.det(primaries)) < 1e-9:
        raise ValueError(f"chromaticities ({c}) have collinear primaries: they span no RGB space")
    scale = np.linalg.solve(primaries, _white_xyz(c.white, "the white point"))
    if (scale <= 0).any():
        raise ValueError(f"chromaticities ({c}) put the white outside the primaries' triangle")
    return primaries * scale


def bradford_matrix(source_white: tuple[float, float], target_white: tuple[float, float]) -> np.ndarray:
    """[3, 3] float64 Bradford chromatic adaptation of XYZ from ``source_white`` to ``target_white``
    ((x, y) each): a source-white surface comes out at the target white, luminance kept."""
    src = _BRADFORD @ _white_xyz(source_white, "the adopted white")
    dst = _BRADFORD @ _white_xyz(target_white, "the target white")
    return np.linalg.solve(_BRADFORD, np.diag(dst / src) @ _BRADFORD)


def _is_cie_xyz(c: Chromaticities) -> bool:
    return same_chromaticities(c, CIE_XYZ)


def to_working_matrix(c: Chromaticities, adopted_neutral: tuple[float, float] | None = None) -> np.ndarray:
    """[3, 3] float64 taking linear RGB in ``c`` to the working space (see the module docstring for
    the adaptation). Raises ValueError when ``c`` or ``adopted_neutral`` define no conversion."""
    to_xyz = rgb_to_xyz_matrix(c)
    from_xyz = np.linalg.inv(rgb_to_xyz_matrix(WORKING_CHROMATICITIES))
    if adopted_neutral is not None:
        neutral: tuple[float, float] | None = adopted_neutral
    elif _is_cie_xyz(c):
        neutral = None  # tristimulus values: nothing to adapt from
    else:
        neutral = c.white
    if neutral is None or _close_xy(neutral, WORKING_CHROMATICITIES.white):
        return from_xyz @ to_xyz
    return from_xyz @ bradford_matrix(neutral, WORKING_CHROMATICITIES.white) @ to_xyz


@functools.lru_cache(maxsize=32)
def _ocio_processor(c: Chromaticities, adopted_neutral: tuple[float, float] | None):
    """An OpenColorIO CPU processor applying :func:`to_working_matrix` (cached: a camera's frames
    share their chromaticities, so each frame costs only the pixel pass)."""
    import PyOpenColorIO as ocio

    m = to_working_matrix(c, adopted_neutral)
    m44 = np.eye(4)
    m44[:3, :3] = m
    transform = ocio.MatrixTransform(matrix=[float(v) for v in m44.ravel()])
    return ocio.Config.CreateRaw().getProcessor(transform).getDefaultCPUProcessor()


def convert_to_working(rgb: np.ndarray, c: Chromaticities,
                       adopted_neutral: tuple[float, float] | None = None) -> np.ndarray:
    """Linear RGB ``[..., 3]`` in ``c`` → a new float32 array ``[..., 3]`` in the working space,
    through OpenColorIO. Raises ValueError when the conversion is undefined (bad chromaticities)."""
    out = np.ascontiguousarray(rgb, dtype=np.float32)
    if np.may_share_memory(out, rgb):  # OCIO converts in place: never in the caller's array
        out = out.copy()
    if out.shape[-1] != 3:
        raise ValueError(f"expected [..., 3] RGB, got shape {out.shape}")
    if out.size:
        _ocio_processor(Chromaticities(*(float(v) for v in c)),
                        None if adopted_neutral is None else (float(adopted_neutral[0]), float(adopted_neutral[1]))
                        ).applyRGB(out)
    return out
