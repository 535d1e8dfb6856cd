"""Render 3D Gaussians into a camera: THE entry point, one function, two back-ends.

    out = render(gaussians, camera)   # {"rgb": [H,W,3] linear, "alpha": [H,W,1], "depth": [H,W,1]}

Colour path (paper eq. 1): each Gaussian's SH is evaluated at the direction from the camera
centre, giving an *unbounded sRGB* colour; that is linearised with
:func:`~volcap_core.colour.srgb_decode_unbounded` (no clamp) and the linear colours are
rasterized (a model with ``colour_space="linear"`` stores linear colours: no decode).
Exposure/black-level grids are applied by the caller (:mod:`volcap_core.splat.grids`): novel
views render without them.

Back-ends:

* ``"gsplat"`` — ``gsplat.rasterization(..., rasterize_mode="antialiased")`` with the precomputed
  colours; CUDA only. gsplat is an optional dependency, imported only when used.
* ``"torch"`` — :mod:`volcap_core.splat.rasterize`, pure PyTorch, any device, autograd backward,
  same conventions as gsplat. Gaussians with any non-finite geometry (mean, quaternion, scale,
  opacity, or what they project to) or a non-finite colour after SH evaluation and decoding are
  culled: exactly zero contribution and zero gradient, so one NaN Gaussian cannot poison the
  image or the other parameters' gradients. Zero Gaussians render the background (alpha 0,
  depth 0), still differentiable.
* ``"auto"`` (default) — gsplat when the tensors are on CUDA and gsplat imports, else torch.
"""

from __future__ import annotations

import functools
from typing import Literal

import torch

from volcap_core.colour import srgb_decode_unbounded
from volcap_core.splat.camera import Camera
from volcap_core.splat.model import Gaussians3D
from volcap_core.splat.rasterize import (
    EPS2D,
    Projected,
    TileStats,
    project_gaussians,
    rasterize_tiles,
)
from volcap_core.splat.sh import sh_to_colour

__all__ = ["Backend", "gsplat_available", "gaussian_colours", "render"]

Backend = Literal["auto", "gsplat", "torch"]


@functools.cache
def gsplat_available() -> bool:
    """True when CUDA is present and ``gsplat`` imports."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # ImportError, or a broken CUDA extension build
        return False
    return True


def gaussian_colours(gaussians: Gaussians3D, camera: Camera) -> torch.Tensor:
    """Linear colours ``[M, 3]`` of the Gaussians seen from ``camera``: SH evaluated at the
    direction camera centre -> Gaussian (unbounded sRGB), then linearised without clamping; with
    ``colour_space="linear"`` the SH colour is already linear and is returned as is."""
    dirs = gaussians.means - camera.centre.to(gaussians.means)
    colour = sh_to_colour(gaussians.sh, dirs)
    if gaussians.colour_space == "linear":
        return colour
    return srgb_decode_unbounded(colour)


def render(gaussians: Gaussians3D, camera: Camera, *, backend: Backend = "auto",
           background: torch.Tensor | None = None, tile_size: int = 8,
           stats: TileStats | None = None) -> dict[str, torch.Tensor]:
    """Rasterize ``gaussians`` into ``camera``.

    Args:
        gaussians: M Gaussians at one instant (:func:`volcap_core.splat.model.evaluate`).
        camera: the view (OpenCV axes, pixels).
        backend: ``"auto"``, ``"gsplat"`` or ``"torch"`` (see module doc).
        background: ``[3]`` linear colour behind the Gaussians (default black), added as
            ``(1 - alpha) · background``.
        tile_size: tile edge of the torch back-end (px).
        stats: filled with the torch back-end's work counts (benchmarks).
    Returns:
        ``{"rgb": [H, W, 3] linear, "alpha": [H, W, 1] in [0, 1], "depth": [H, W, 1]}``; depth is
        the expected camera-space z of the visible Gaussians (metres; accumulated z over alpha,
        0 where nothing is drawn), gsplat's ``"RGB+ED"``.
    """
    cam = camera.to(gaussians.means.device)
    if backend == "auto":
        backend = "gsplat" if gaussians.means.is_cuda and gsplat_available() else "torch"
    if backend == "gsplat":
        rgb, alpha, depth = _render_gsplat(gaussians, cam)
    elif backend == "torch":
        rgb, alpha, depth = _render_torch(gaussians, cam, tile_size, stats)
    else:
        raise ValueError(f"unknown backend {backend!r}")
    if background is not None:
        rgb = rgb + (1.0 - alpha) * background.to(rgb)
    return {"rgb": rgb, "alpha": alpha, "depth": depth}


def _render_torch(g: Gaussians3D, cam: Camera, tile_size: int, stats: TileStats | None):
    # geometry: project_gaussians culls (without gradient) anything non-finite or degenerate
    proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, cam, eps2d=EPS2D,
                             antialiased=True)
    # colours only for the survivors: SH of culled Gaussians is never needed
    colours = gaussian_colours(g.select(proj.ids), cam)
    finite = torch.isfinite(colours.detach()).all(-1)
    if not bool(finite.all()):
        # a non-finite colour (NaN/inf SH, or a decode overflow) is culled like a culled
        # geometry: dropped from every projected tensor and its colour recomputed without it, so
        # no graph ever holds it (0·NaN would otherwise reach its own and the others' gradients)
        keep = torch.nonzero(finite).squeeze(1)
        proj = Projected(ids=proj.ids[keep], means2d=proj.means2d[keep],
                         conics=proj.conics[keep], opacities=proj.opacities[keep],
                         depths=proj.depths[keep], radii=proj.radii[keep])
        colours = gaussian_colours(g.select(proj.ids), cam)
    values = torch.cat([colours, proj.depths[:, None]], dim=-1)
    acc, trans = rasterize_tiles(proj.means2d, proj.conics, proj.opacities, proj.depths,
                                 proj.radii, values, cam.width, cam.height, tile_size=tile_size,
                                 stats=stats)
    alpha = (1.0 - trans)[..., None]
    depth = acc[..., 3:4] / alpha.clamp(min=1e-10)
    return acc[..., :3], alpha, depth


def _render_gsplat(g: Gaussians3D, cam: Camera):
    if not gsplat_available():
        raise RuntimeError("backend 'gsplat' needs CUDA and the gsplat package")
    from gsplat import rasterization

    colours = gaussian_colours(g, cam)
    renders, alphas, _ = rasterization(
        means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities, colors=colours,
        viewmats=cam.world_to_camera[None], Ks=cam.K[None], width=cam.width, height=cam.height,
        near_plane=cam.near, far_plane=cam.far, eps2d=EPS2D, rasterize_mode="antialiased",
        render_mode="RGB+ED", packed=False)
    return renders[0, ..., :3], alphas[0], renders[0, ..., 3:4]
