"""Lens models as studios write them, mapped onto the distortion volcap applies.

volcap applies one lens model (``volcap_core.calibration.distortion.Distortion``): a pinhole with
OpenCV's radial (k1-k6, rational) and tangential (p1, p2) distortion on normalized coordinates,
held as one of :data:`DISTORTION_MODELS` (COLMAP's names) with its parameters in COLMAP's order.
Calibrations arrive in two other forms, and this module maps each onto that one, exactly, or
refuses it with the reason:

- **OpenCV's** ``distCoeffs`` vector as ``cv2.calibrateCamera`` writes it, of 4, 5, 8, 12 or 14
  values (:data:`OPENCV_COEFFICIENTS`: ``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tauX tauY]]]]``;
  0 values: no distortion): :func:`opencv_distortion`. The thin-prism terms ``s1..s4`` and the
  sensor tilt ``tauX, tauY`` are not applied by volcap: zero ones are accepted (OpenCV writes them
  as zeros when its flags leave them out), a non-zero one is refused by name.
- **COLMAP's** cameras (a ``cameras.txt`` line's model and parameters, pixel centres at +0.5:
  :data:`COLMAP_PIXEL_OFFSET`): :func:`colmap_intrinsics`. The models volcap can apply are
  :data:`COLMAP_MODELS`; the fisheye, division, FOV and other models are refused by name
  (:data:`COLMAP_REFUSED`, with why).

This is the bottom layer (no numpy, no OpenCV), so the rig's models (``hardware.rig``) and the
calibration library (``volcap_core.calibration.distortion``) read lenses the same way.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

#: lens distortion models (COLMAP's names) -> their parameters in COLMAP's (and OpenCV's) order: the
#: models a rig's lens is held in and the calibration applies
DISTORTION_MODELS: dict[str, tuple[str, ...]] = {
    "PINHOLE": (),
    "SIMPLE_RADIAL": ("k",),
    "RADIAL": ("k1", "k2"),
    "OPENCV": ("k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}

#: OpenCV's ``distCoeffs`` in its order (``cv::calibrateCamera``'s documentation)
OPENCV_COEFFICIENTS: tuple[str, ...] = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
                                        "s1", "s2", "s3", "s4", "tauX", "tauY")
#: the lengths OpenCV writes: 4 (k1 k2 p1 p2), 5 (+k3), 8 (+k4 k5 k6, rational), 12 (+s1..s4,
#: thin prism), 14 (+tauX tauY, tilted sensor); 0: no distortion
OPENCV_LENGTHS: tuple[int, ...] = (0, 4, 5, 8, 12, 14)
#: the terms volcap does not apply, and what they are
_NOT_APPLIED = {"s1": "thin prism", "s2": "thin prism", "s3": "thin prism", "s4": "thin prism",
                "tauX": "sensor tilt", "tauY": "sensor tilt"}

#: COLMAP pixel coordinates = OpenCV pixel coordinates + 0.5 (COLMAP: the top-left pixel's corner at
#: (0, 0), OpenCV: its centre); the one definition, for rigs and the calibration alike
COLMAP_PIXEL_OFFSET = 0.5

#: COLMAP camera models volcap applies -> (their parameters in COLMAP's order, the distortion model
#: of :data:`DISTORTION_MODELS` they map onto). ``f``: one focal for both axes.
COLMAP_MODELS: dict[str, tuple[tuple[str, ...], str]] = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), "PINHOLE"),
    "PINHOLE": (("fx", "fy", "cx", "cy"), "PINHOLE"),
    "SIMPLE_RADIAL": (("f", "cx", "cy", "k"), "SIMPLE_RADIAL"),
    "RADIAL": (("f", "cx", "cy", "k1", "k2"), "RADIAL"),
    "OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), "OPENCV"),
    "FULL_OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), "FULL_OPENCV"),
}
_FISHEYE = "a fisheye (equidistant) projection, not a pinhole with distortion"
#: COLMAP camera models volcap refuses, and why
COLMAP_REFUSED: dict[str, str] = {
    "OPENCV_FISHEYE": _FISHEYE, "SIMPLE_RADIAL_FISHEYE": _FISHEYE, "RADIAL_FISHEYE": _FISHEYE,
    "THIN_PRISM_FISHEYE": _FISHEYE, "RAD_TAN_THIN_PRISM_FISHEYE": _FISHEYE, "SIMPLE_FISHEYE": _FISHEYE,
    "FISHEYE": _FISHEYE,
    "FOV": "the FOV (arctangent) distortion model",
    "SIMPLE_DIVISION": "the division distortion model", "DIVISION": "the division distortion model",
    "EUCM": "the extended unified (omnidirectional) camera model",
    "EQUIRECTANGULAR": "a spherical (equirectangular) projection",
}


def _finite(values: Sequence[float], what: str) -> tuple[float, ...]:
    if isinstance(values, (str, bytes)):
        raise ValueError(f"{what}: expected a list of numbers, got {values!r}")
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected a list of numbers, got {values!r}") from None
    bad = [v for v in out if not math.isfinite(v)]
    if bad:
        raise ValueError(f"{what}: non-finite values {bad}")
    return out


def opencv_distortion(coeffs: Sequence[float], model: str | None = None) -> tuple[str, tuple[float, ...]]:
    """OpenCV's ``distCoeffs`` (4, 5, 8, 12 or 14 values, or none) -> ``(model, params)``: in
    ``model`` (one of :data:`DISTORTION_MODELS`) when given, else the smallest model that holds
    them exactly (``(k1, k2, p1, p2, k3)`` with ``k3 == 0`` is ``OPENCV``; with ``p1 == p2 == 0``
    too, ``RADIAL``...).

    Raises ``ValueError`` for another length, a non-finite value, a non-zero thin-prism
    (``s1..s4``) or tilt (``tauX``, ``tauY``) term (naming the term), or a non-zero term
    ``model`` does not hold."""
    c = _finite(coeffs, "OpenCV distortion coefficients")
    if len(c) not in OPENCV_LENGTHS:
        raise ValueError(f"OpenCV distortion has 4, 5, 8, 12 or 14 coefficients "
                         f"({' '.join(OPENCV_COEFFICIENTS)}), got {len(c)}")
    for name, value in zip(OPENCV_COEFFICIENTS[8:], c[8:]):
        if value != 0.0:
            raise ValueError(f"OpenCV distortion term {name} = {value:g} ({_NOT_APPLIED[name]}) is not applied by "
                             f"volcap (it applies k1-k6, p1, p2): calibrate without it, or give it as 0")
    full = dict(zip(OPENCV_COEFFICIENTS[:8], (c + (0.0,) * 8)[:8]))
    full["k"] = full["k1"]
    if model is None:
        model = smallest_model(full)
    names = DISTORTION_MODELS.get(model)
    if names is None:
        raise ValueError(f"unknown distortion model {model!r}: one of {', '.join(DISTORTION_MODELS)}")
    dropped = [n for n in OPENCV_COEFFICIENTS[:8] if full[n] and n not in names and not (n == "k1" and "k" in names)]
    if dropped:
        raise ValueError(f"distortion model {model} has no {', '.join(dropped)}: these OpenCV coefficients need "
                         f"{smallest_model(full)}")
    return model, tuple(full[n] for n in names)


def smallest_model(coefficients: dict[str, float]) -> str:
    """The smallest of :data:`DISTORTION_MODELS` whose parameters hold every non-zero one of
    ``coefficients`` (OpenCV's names, k1..k6, p1, p2; absent ones are 0)."""
    def nonzero(*names: str) -> bool:
        return any(coefficients.get(n, 0.0) for n in names)

    if nonzero("k3", "k4", "k5", "k6"):
        return "FULL_OPENCV"
    if nonzero("p1", "p2"):
        return "OPENCV"
    if nonzero("k2"):
        return "RADIAL"
    if nonzero("k1"):
        return "SIMPLE_RADIAL"
    return "PINHOLE"


def colmap_intrinsics(model: str, params: Sequence[float]
                      ) -> tuple[tuple[float, float, float, float], str, tuple[float, ...]]:
    """A COLMAP camera (its model name, e.g. ``"SIMPLE_RADIAL"`` or pycolmap's
    ``"CameraModelId.SIMPLE_RADIAL"``, and its parameters in COLMAP's order, COLMAP's pixels) ->
    ``((fx, fy, cx, cy) in OpenCV pixels, distortion model, distortion params)``.

    Raises ``ValueError`` naming the model for one volcap cannot apply (:data:`COLMAP_REFUSED`,
    and unknown names) and for the wrong number of parameters."""
    name = str(model).split(".")[-1].upper()
    if name not in COLMAP_MODELS:
        why = COLMAP_REFUSED.get(name, "not a COLMAP camera model")
        raise ValueError(f"COLMAP camera model {name} is not supported: {why}; volcap applies "
                         f"{', '.join(COLMAP_MODELS)}")
    names, distortion = COLMAP_MODELS[name]
    p = _finite(params, f"COLMAP camera model {name}")
    if len(p) != len(names):
        raise ValueError(f"COLMAP camera model {name} takes {len(names)} parameters ({', '.join(names)}), "
                         f"got {len(p)}")
    if names[0] == "f":
        fx = fy = p[0]
        cx, cy, rest = p[1], p[2], p[3:]
    else:
        fx, fy, cx, cy, rest = p[0], p[1], p[2], p[3], p[4:]
    return (fx, fy, cx - COLMAP_PIXEL_OFFSET, cy - COLMAP_PIXEL_OFFSET), distortion, rest
