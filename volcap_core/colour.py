"""Colour transfer functions (torch, differentiable).

Two families of IEC 61966-2-1 (sRGB) piecewise curves, and the ITU-R BT.709 OETF pair
(:func:`bt709_oetf` / :func:`bt709_oetf_inverse`) that video footage is decoded with:

* :func:`srgb_encode` / :func:`srgb_decode` — the standard display transfer function on its domain
  ``[0, 1]``. Inputs outside ``[0, 1]`` are clamped first (zero gradient there): this is the pair
  for display images and 8/16-bit files.
* :func:`srgb_encode_unbounded` / :func:`srgb_decode_unbounded` — the same curve extended to the
  whole real line, used for training (the Poly4DGS paper stores Gaussian colours in *unbounded*
  sRGB and linearises them before rasterization, "f_srgb^-1 operates in R+ without clamping").

  - Above 1 the power segment simply continues (HDR values stay HDR: ``decode(107.1) ≈ 65504``).
  - Below 0 the *linear* segment continues: ``encode(x) = 12.92 x`` and ``decode(y) = y / 12.92``
    for every ``x <= 0.0031308`` / ``y < 0.04045``. Chosen over an odd extension because the
    curve is then smooth (constant slope) across 0, monotone, exactly invertible, and has finite,
    non-zero gradients everywhere, including exactly 0. Negative linear values do occur (SH colours
    are unconstrained; ringing in the exposure grids) and must neither explode nor get stuck.

Names follow colour-science: ``decode`` = EOTF (encoded -> linear), ``encode`` = inverse EOTF.

All functions accept a torch tensor (any shape, any floating dtype; float16/bfloat16 are computed
in float32 and cast back) or a numpy array (returned as a numpy array), so ingest can call
``srgb_decode(torch.from_numpy(x))`` or ``srgb_decode(x)`` alike. Integer inputs are refused: divide
by the maximum code value (255, 65535) first.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeVar

import numpy as np

if TYPE_CHECKING:
    import torch

__all__ = [
    "SRGB_DECODE_BREAK",
    "SRGB_ENCODE_BREAK",
    "srgb_decode",
    "srgb_decode_unbounded",
    "srgb_encode",
    "srgb_encode_and_slope",
    "srgb_encode_unbounded",
    "bt709_oetf",
    "bt709_oetf_inverse",
]

#: Break point of the encoded curve: encoded values at or below it are on the linear segment.
SRGB_DECODE_BREAK = 0.04045
#: Break point of the linear curve: ``0.04045 / 12.92`` to the precision IEC 61966-2-1 states.
SRGB_ENCODE_BREAK = 0.0031308
_SLOPE = 12.92
_A = 0.055
_GAMMA = 2.4

# torch is imported where a curve is evaluated, not here: ingest and the command line import this
# module on paths (a cached rerun, header checks) that never touch a pixel, and torch costs seconds.
T = TypeVar("T", "torch.Tensor", np.ndarray)


def _as_float_tensor(x: T) -> tuple[torch.Tensor, torch.dtype, bool]:
    import torch

    is_numpy = isinstance(x, np.ndarray)
    t = torch.from_numpy(np.asarray(x)) if is_numpy else x
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"expected a torch.Tensor or numpy.ndarray, got {type(x).__name__}")
    if not t.is_floating_point():
        raise TypeError(f"sRGB transfer needs floating values in [0, 1] (got {t.dtype}); "
                        "divide integer codes by 255 or 65535 first")
    out_dtype = t.dtype
    if t.dtype in (torch.float16, torch.bfloat16):
        t = t.float()  # pow in half precision loses ~3 digits and has no CPU kernel on some builds
    return t, out_dtype, is_numpy


def _back(t: torch.Tensor, dtype: torch.dtype, is_numpy: bool):
    t = t.to(dtype)
    return t.numpy() if is_numpy else t


def _encode(linear: torch.Tensor) -> torch.Tensor:
    # Clamping the power branch's input keeps pow away from 0, where d/dx x^(1/2.4) is infinite:
    # torch.where would otherwise route 0 * inf = NaN into the gradient of the unused branch.
    import torch

    power = (1.0 + _A) * linear.clamp(min=SRGB_ENCODE_BREAK).pow(1.0 / _GAMMA) - _A
    return torch.where(linear <= SRGB_ENCODE_BREAK, _SLOPE * linear, power)


def _decode(encoded: torch.Tensor) -> torch.Tensor:
    import torch

    power = ((encoded.clamp(min=SRGB_DECODE_BREAK) + _A) / (1.0 + _A)).pow(_GAMMA)
    # Strict '<' as colour-science does: at exactly 0.04045 the two segments differ by 2e-9 and the
    # reference takes the power segment there.
    return torch.where(encoded < SRGB_DECODE_BREAK, encoded / _SLOPE, power)


def srgb_encode_unbounded(linear: T) -> T:
    """Linear light -> unbounded sRGB, on all of R (linear segment continued below 0).

    Args:
        linear: scene-linear values, any shape ``[...]``, any real value (HDR allowed).
    Returns:
        encoded values, same shape and dtype; ``[0, 1] -> [0, 1]``, ``65504 -> ~107.1``.
    """
    t, dtype, is_numpy = _as_float_tensor(linear)
    return _back(_encode(t), dtype, is_numpy)


def srgb_decode_unbounded(encoded: T) -> T:
    """Unbounded sRGB -> linear light: exact inverse of :func:`srgb_encode_unbounded` on all of R.

    Args:
        encoded: unbounded sRGB values ``[...]`` (e.g. Gaussian colours evaluated from SH).
    Returns:
        scene-linear values, same shape and dtype; negative inputs map to ``x / 12.92``.
    """
    t, dtype, is_numpy = _as_float_tensor(encoded)
    return _back(_decode(t), dtype, is_numpy)


def srgb_encode(linear: T) -> T:
    """IEC 61966-2-1 inverse EOTF: linear ``[0, 1]`` -> display sRGB ``[0, 1]``.

    Inputs are clamped to ``[0, 1]`` (the standard's domain); use :func:`srgb_encode_unbounded`
    where out-of-range values must survive.

    Args:
        linear: linear values ``[...]``.
    Returns:
        encoded values ``[...]`` in ``[0, 1]``, same dtype (numpy in, numpy out).
    """
    t, dtype, is_numpy = _as_float_tensor(linear)
    return _back(_encode(t.clamp(0.0, 1.0)), dtype, is_numpy)


def srgb_encode_and_slope(linear: "torch.Tensor") -> tuple["torch.Tensor", "torch.Tensor"]:
    """:func:`srgb_encode` and its derivative in one pass, for fits that need both (a Gauss-Newton
    step costs one evaluation of the curve instead of autograd's forward and backward).

    Args:
        linear: linear values ``[...]``, a floating torch tensor.
    Returns:
        ``(encoded [...], slope [...])``: the clamped encoding, and ``d encoded / d linear``, which is
        0 outside ``(0, 1)`` (where the clamp holds the encoding still), 12.92 on the linear segment.
    """
    import torch

    x = linear.clamp(0.0, 1.0)
    xp = x.clamp(min=SRGB_ENCODE_BREAK)
    p = xp.pow(1.0 / _GAMMA)
    low = x <= SRGB_ENCODE_BREAK
    encoded = torch.where(low, _SLOPE * x, (1.0 + _A) * p - _A)
    slope = torch.where(low, torch.full_like(x, _SLOPE), (1.0 + _A) / _GAMMA * p / xp)
    return encoded, slope * ((linear > 0.0) & (linear < 1.0))


def srgb_decode(encoded: T) -> T:
    """IEC 61966-2-1 EOTF: display sRGB ``[0, 1]`` -> linear ``[0, 1]`` (inverse of
    :func:`srgb_encode` on ``[0, 1]``; inputs are clamped to ``[0, 1]``).

    Args:
        encoded: sRGB-encoded values ``[...]``, e.g. 8-bit codes divided by 255.
    Returns:
        linear values ``[...]`` in ``[0, 1]``, same dtype (numpy in, numpy out).
    """
    t, dtype, is_numpy = _as_float_tensor(encoded)
    return _back(_decode(t.clamp(0.0, 1.0)), dtype, is_numpy)


#: ITU-R BT.709-6 item 1.2: ``V = 4.5 L`` for ``L < 0.018``, ``V = 1.099 L^0.45 - 0.099`` above.
BT709_LINEAR_BREAK = 0.018
#: the encoded value at the break, ``4.5 * 0.018``: the inverse's linear segment ends here
BT709_ENCODED_BREAK = 0.081
_BT709_SLOPE = 4.5
_BT709_ALPHA = 1.099
_BT709_BETA = 0.099
_BT709_EXPONENT = 0.45


def bt709_oetf(linear: T) -> T:
    """ITU-R BT.709 opto-electronic transfer function: scene-linear ``L`` -> video signal ``V``.

    Extended to all of R as :func:`srgb_encode_unbounded` is: the linear segment continues below 0
    (limited-range video carries foot-room below black), the power segment above 1 (head-room).

    Args:
        linear: scene-linear values ``[...]`` (1.0 = the camera's reference white).
    Returns:
        ``V`` ``[...]``, same dtype (numpy in, numpy out); ``0 -> 0``, ``1 -> 1``, ``0.01 -> 0.045``.
    """
    import torch

    t, dtype, is_numpy = _as_float_tensor(linear)
    power = _BT709_ALPHA * t.clamp(min=BT709_LINEAR_BREAK).pow(_BT709_EXPONENT) - _BT709_BETA
    return _back(torch.where(t < BT709_LINEAR_BREAK, _BT709_SLOPE * t, power), dtype, is_numpy)


def bt709_oetf_inverse(encoded: T) -> T:
    """Inverse of the BT.709 OETF: video signal ``V`` (R', G' or B' in ``[0, 1]`` at nominal black
    and white) -> scene-linear ``L``. This is what "linear light" means for camera video: the
    light the camera saw, relative to its reference white, not the display light of BT.1886.

    Unbounded like :func:`bt709_oetf`: ``V < 0`` -> ``V / 4.5``; ``V > 1`` follows the power segment.

    Args:
        encoded: signal values ``[...]`` (e.g. limited-range codes expanded: ``(Y - 16) / 219``).
    Returns:
        scene-linear values ``[...]``, same dtype (numpy in, numpy out); ``0.045 -> 0.01``, ``1 -> 1``.
    """
    import torch

    t, dtype, is_numpy = _as_float_tensor(encoded)
    power = ((t.clamp(min=BT709_ENCODED_BREAK) + _BT709_BETA) / _BT709_ALPHA).pow(1.0 / _BT709_EXPONENT)
    return _back(torch.where(t < BT709_ENCODED_BREAK, t / _BT709_SLOPE, power), dtype, is_numpy)
