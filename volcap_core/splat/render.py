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
  colours; CUDA only. gsplat is an optional dependency, imported only for CUDA tensors.
* ``"torch"`` — :mod:`volcap_core.splat.rasterize`, pure PyTorch, any device, autograd backward,
  same conventions as gsplat. Gaussians with any non-finite geometry (mean, quaternion, scale,
  opacity, or what they project to) or a non-finite colour after SH evaluation and decoding are
  culled: exactly zero contribution and zero gradient, so one NaN Gaussian cannot poison the
  image or the other parameters' gradients. Zero Gaussians render the background (alpha 0,
  depth 0), still differentiable.
* ``"auto"`` (default) — gsplat when the tensors are on CUDA and gsplat is usable, else torch.

Which back-end runs is decided by :func:`resolve_backend`, never silently:

* an explicit ``"gsplat"`` that cannot be honoured (tensors not on CUDA, gsplat not installed, its
  CUDA extension failing to load or build) raises :class:`BackendUnavailable` naming the cause,
  chained from gsplat's own exception;
* ``"auto"`` falling back to torch for CUDA tensors is logged as a WARNING with gsplat's exception
  (the pure-PyTorch rasterizer is much slower than gsplat's kernels); its other choices are
  logged at INFO. Each (back-end, reason) is logged once per process, not per render;
* the answer is a :class:`BackendChoice` (name and reason) that results record
  (:attr:`~volcap_core.splat.train.TrainResult.backend`, which the ``train-segment`` task copies
  into the ``SegmentModel`` record).

gsplat is probed once per process (:func:`probe_gsplat`, cached with its exception): the probe
imports it *and* loads its CUDA extension, since gsplat 1.5's wheel builds the extension on first
use and ``import gsplat`` succeeding says nothing about that.
"""

from __future__ import annotations

import functools
import logging
import threading
from dataclasses import dataclass
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

__all__ = [
    "Backend", "BackendChoice", "BackendName", "BackendUnavailable", "GsplatProbe",
    "gaussian_colours", "gsplat_available", "probe_gsplat", "render", "resolve_backend",
]

log = logging.getLogger(__name__)

Backend = Literal["auto", "gsplat", "torch"]
BackendName = Literal["gsplat", "torch"]

#: Longest exception summary put in a reason: a failed JIT build's message carries the whole
#: compiler log, which belongs in the traceback (chained, or logged once), not in every record.
_CAUSE_CHARS = 500


class BackendUnavailable(RuntimeError):
    """An explicitly requested back-end cannot run here; the message names the cause and
    ``__cause__`` is gsplat's own exception when it failed to import or load."""


@dataclass(frozen=True)
class BackendChoice:
    """The back-end that rasterizes, and why: what a render used and what a result records.

    Attributes:
        name: ``"gsplat"`` or ``"torch"``.
        reason: one line, e.g. ``"auto: CUDA tensors, gsplat 1.5.3"``, ``"requested"``, or
            ``"auto: CUDA tensors but gsplat is unusable (ModuleNotFoundError: No module named
            'gsplat')"``.
    """

    name: BackendName
    reason: str


@dataclass(frozen=True)
class GsplatProbe:
    """Whether gsplat can rasterize in this process.

    Attributes:
        error: what stopped it (the import's or the CUDA extension's exception), None if usable.
        version: ``gsplat.__version__`` when it imported.
    """

    error: BaseException | None
    version: str | None = None

    @property
    def usable(self) -> bool:
        return self.error is None

    @property
    def cause(self) -> str:
        """``"ExceptionType: message"`` of :attr:`error`, first line, at most 500 characters."""
        if self.error is None:
            return ""
        lines = str(self.error).strip().splitlines()
        text = type(self.error).__name__ + (f": {lines[0]}" if lines else "")
        return text if len(text) <= _CAUSE_CHARS else text[:_CAUSE_CHARS - 3] + "..."


@functools.cache
def probe_gsplat() -> GsplatProbe:
    """Import gsplat and load its CUDA extension; once per process (cached, failure included).

    Only meaningful where CUDA is: :func:`resolve_backend` calls it for CUDA tensors only.
    ``import gsplat`` alone proves little: gsplat 1.5's wheel is pure Python and loads or
    JIT-builds its CUDA extension in ``gsplat.cuda._backend`` on first use. The build can fail
    (an exception), and without a CUDA toolkit the module prints a notice and leaves the
    extension ``None``, so the first rasterization would die with an AttributeError. Loading it
    here makes either failure a reason with its cause, before any work; caching means a failed
    import is not retried per render and a build (minutes) is attempted once.
    """
    try:
        import gsplat
        from gsplat.cuda._backend import _C
    except Exception as e:  # ImportError, or a build's RuntimeError / OSError / CalledProcessError
        return GsplatProbe(e)
    version = str(getattr(gsplat, "__version__", "unknown"))
    if _C is None:
        return GsplatProbe(RuntimeError(
            "gsplat's CUDA extension did not load: no prebuilt gsplat.csrc and no CUDA toolkit "
            "(nvcc) to build it (gsplat.cuda._backend._C is None)"), version)
    return GsplatProbe(None, version)


def gsplat_available() -> bool:
    """True when CUDA is present and gsplat is usable (:func:`probe_gsplat`)."""
    return torch.cuda.is_available() and probe_gsplat().usable


# (back-end, reason) pairs already logged: one line per process per reason, not one per render
_announced: set[BackendChoice] = set()
_announced_lock = threading.Lock()


def _announce(level: int, choice: BackendChoice, exc: BaseException | None = None) -> BackendChoice:
    with _announced_lock:
        first = choice not in _announced
        _announced.add(choice)
    if first:
        # the full exception (a build failure's compiler log) once, with the warning
        log.log(level, "rasterizer back-end %r: %s", choice.name, choice.reason, exc_info=exc)
    return choice


def resolve_backend(requested: Backend, device: torch.device | str) -> BackendChoice:
    """Which back-end rasterizes tensors on ``device`` when ``requested`` is asked for, and why.

    Args:
        requested: ``"auto"``, ``"gsplat"`` or ``"torch"``.
        device: where the Gaussians' tensors are (``"cuda"`` and ``"cuda:0"`` are the same here).
    Returns:
        :class:`BackendChoice`:

        * ``"torch"``: torch, always (any device); reason ``"requested"``.
        * ``"gsplat"``: gsplat, for CUDA tensors with a usable gsplat.
        * ``"auto"``: gsplat for CUDA tensors when usable, else torch. The torch fallback for CUDA
          tensors is logged as a WARNING with gsplat's exception; the other choices at INFO;
          each once per process.
    Raises:
        BackendUnavailable: ``"gsplat"`` requested for tensors not on CUDA, or gsplat unusable
            (chained from its import/build exception).
        ValueError: an unknown ``requested``.
    """
    if requested == "torch":
        return BackendChoice("torch", "requested")
    if requested not in ("auto", "gsplat"):
        raise ValueError(f"unknown backend {requested!r}: choose 'auto', 'gsplat' or 'torch'")
    device = torch.device(device)
    if device.type != "cuda":
        if requested == "gsplat":
            why = ("" if torch.cuda.is_available() else
                   "; CUDA is not available in this process (torch.cuda.is_available() is False)")
            raise BackendUnavailable(
                f"backend 'gsplat' needs CUDA tensors, these are on {device}{why}")
        return _announce(logging.INFO, BackendChoice(
            "torch", f"auto: tensors on {device.type}, gsplat needs CUDA"))
    probe = probe_gsplat()
    if requested == "gsplat":
        if not probe.usable:
            raise BackendUnavailable("backend 'gsplat' was requested but gsplat cannot be used: "
                                     f"{probe.cause}") from probe.error
        return BackendChoice("gsplat", f"requested, gsplat {probe.version}")
    if probe.usable:
        return _announce(logging.INFO, BackendChoice(
            "gsplat", f"auto: CUDA tensors, gsplat {probe.version}"))
    # the case the resolver exists for: a GPU worker that would otherwise train on the slow
    # back-end without anyone knowing
    return _announce(logging.WARNING, BackendChoice(
        "torch", f"auto: CUDA tensors but gsplat is unusable ({probe.cause}); the pure-PyTorch "
                 "rasterizer is much slower on a GPU"), probe.error)


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
        backend: ``"auto"``, ``"gsplat"`` or ``"torch"``, resolved by :func:`resolve_backend`
            (an explicit ``"gsplat"`` that cannot run raises :class:`BackendUnavailable`).
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
    if resolve_backend(backend, gaussians.means.device).name == "gsplat":
        rgb, alpha, depth = _render_gsplat(gaussians, cam)
    else:
        rgb, alpha, depth = _render_torch(gaussians, cam, tile_size, stats)
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
    from gsplat import rasterization  # resolve_backend has loaded it (probe_gsplat)

    colours = gaussian_colours(g, cam)
    renders, alphas, _ = rasterization(
        means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities, colors=colours,
        viewmats=cam.world_to_camera[None], Ks=cam.K[None], width=cam.width, height=cam.height,
        near_plane=cam.near, far_plane=cam.far, eps2d=EPS2D, rasterize_mode="antialiased",
        render_mode="RGB+ED", packed=False)
    return renders[0, ..., :3], alphas[0], renders[0, ..., 3:4]
