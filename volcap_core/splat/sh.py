"""Real spherical harmonics, the 3DGS / gsplat basis and sign convention (degrees 0..3).

A Gaussian's colour seen along unit direction ``d`` (from the camera centre to the Gaussian) is
``c(d) = Σ_k sh[k] · Y_k(d) + 0.5``. In Poly4DGS that colour is *unbounded sRGB* (see
:mod:`volcap_core.colour`); it is linearised before rasterization, never clamped.
"""

from __future__ import annotations

import torch

__all__ = ["SH_C0", "num_sh_bases", "rgb_to_sh0", "sh_to_colour"]

SH_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
       0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of coefficients ``K = (degree + 1)²`` per colour channel."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in [0, {MAX_SH_DEGREE}], got {degree}")
    return (degree + 1) ** 2


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient ``[..., 3]`` giving the view-independent colour ``rgb`` ``[..., 3]``."""
    return (rgb - 0.5) / SH_C0


def sh_to_colour(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH colours.

    Args:
        sh: ``[N, K, 3]`` coefficients, ``K = (degree + 1)²`` with degree in 0..3.
        dirs: ``[N, 3]`` viewing directions (camera centre -> Gaussian), any length; normalised here
            with a floor on the norm so a zero direction gives the DC colour, not NaN.
    Returns:
        ``[N, 3]`` colours (``+ 0.5`` included, no clamp).
    """
    K = sh.shape[-2]
    if K == 1:
        return SH_C0 * sh[:, 0] + 0.5
    if K not in (4, 9, 16):
        raise ValueError(f"unsupported number of SH coefficients {K}")
    d = torch.nn.functional.normalize(dirs, dim=-1, eps=1e-12)
    x, y, z = d.unbind(-1)
    basis = [torch.full_like(x, SH_C0), -_C1 * y, _C1 * z, -_C1 * x]
    if K > 4:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy), _C2[3] * xz,
                  _C2[4] * (xx - yy)]
    if K > 9:
        basis += [_C3[0] * y * (3 * xx - yy), _C3[1] * xy * z, _C3[2] * y * (4 * zz - xx - yy),
                  _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                  _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    # one contraction (not K slices of sh): its backward is one product, not K scatters
    return torch.einsum("nk,nkc->nc", torch.stack(basis, dim=-1), sh) + 0.5
