"""Render 3D Gaussians into a camera: THE entry point, one function, three back-ends.

    out = render(gaussians, camera)   # {"rgb": [H,W,3] linear, "alpha": [H,W,1], "depth": [H,W,1]}

and its companion for the detail enhancer's temporal conditioning, the exact backward flow of a
frame to the previous one (:func:`render_flow`, with :func:`gaussians_at` for the same Gaussians at
the previous frame's time).

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
* ``"numba"`` — the same rules and outputs as torch, compiled for the CPU: the projection and
  culling by the per-Gaussian kernels of :mod:`volcap_core.splat.project_numba` (forward and
  analytic backward), the survivors' colours by the per-Gaussian kernels of
  :mod:`volcap_core.splat.colour_numba` (SH and decode, analytic backward, the same non-finite
  colour rule), the same binning, composited by the per-pixel kernels of
  :mod:`volcap_core.splat.composite_numba`; the binning stays PyTorch. Faster on a
  CPU (``docs/benchmarks.md``, "Rasterizer"); float32 CPU tensors only.
* ``"auto"`` (default) — gsplat when the tensors are on CUDA and gsplat is usable; numba for
  float32 CPU tensors when numba imports; else torch (float64 renders, a GPU without gsplat, a CPU
  without numba).

Which back-end runs is decided by :func:`resolve_backend`, never silently:

* an explicit ``"gsplat"`` that cannot be honoured (tensors not on CUDA, gsplat not installed, its
  CUDA extension failing to load or build) raises :class:`BackendUnavailable` naming the cause,
  chained from gsplat's own exception; so does an explicit ``"numba"`` for tensors not on the CPU
  or a numba that does not import;
* ``"auto"`` falling back to torch for CUDA tensors is logged as a WARNING with gsplat's exception
  (the pure-PyTorch rasterizer is much slower than gsplat's kernels), and for float32 CPU tensors
  with numba's import error (slower than the compiled compositor); its other choices are
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
from volcap_core.splat.model import Gaussians3D, Poly4DGS, evaluate
from volcap_core.splat.rasterize import (
    EPS2D,
    Projected,
    TileStats,
    project_gaussians,
    rasterize_tiles,
)
from volcap_core.splat.sh import sh_to_colour

__all__ = [
    "FLOW_MIN_ALPHA", "Backend", "BackendChoice", "BackendName", "BackendUnavailable", "GsplatProbe",
    "gaussian_colours", "gaussians_at", "gsplat_available", "probe_gsplat", "render", "render_flow",
    "resolve_backend",
]

log = logging.getLogger(__name__)

Backend = Literal["auto", "gsplat", "torch", "numba"]
BackendName = Literal["gsplat", "torch", "numba"]

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
        name: ``"gsplat"``, ``"torch"`` or ``"numba"``.
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


def _numba_compositor():
    """:func:`~volcap_core.splat.composite_numba.rasterize_tiles_numba`, imported on first use:
    importing numba costs ~0.5 s, which a process that never renders on a CPU should not pay.

    Raises:
        BackendUnavailable: numba does not import (chained from its exception).
    """
    try:
        from volcap_core.splat.composite_numba import rasterize_tiles_numba
    except ImportError as e:
        raise BackendUnavailable(f"backend 'numba' was requested but numba cannot be imported: "
                                 f"{type(e).__name__}: {e}") from e
    return rasterize_tiles_numba


def _numba_projector():
    """:func:`~volcap_core.splat.project_numba.project_gaussians_numba`, imported on first use
    (numba's import cost, as :func:`_numba_compositor`; :func:`resolve_backend` has checked that
    numba imports)."""
    from volcap_core.splat.project_numba import project_gaussians_numba
    return project_gaussians_numba


def resolve_backend(requested: Backend, device: torch.device | str,
                    dtype: torch.dtype = torch.float32) -> BackendChoice:
    """Which back-end rasterizes tensors on ``device`` when ``requested`` is asked for, and why.

    Args:
        requested: ``"auto"``, ``"gsplat"``, ``"torch"`` or ``"numba"``.
        device: where the Gaussians' tensors are (``"cuda"`` and ``"cuda:0"`` are the same here).
        dtype: the Gaussians' floating type (``"auto"`` gives numba float32 only).
    Returns:
        :class:`BackendChoice`:

        * ``"torch"``: torch, always (any device); reason ``"requested"``.
        * ``"numba"``: numba, for CPU tensors; reason ``"requested"``.
        * ``"gsplat"``: gsplat, for CUDA tensors with a usable gsplat.
        * ``"auto"``: gsplat for CUDA tensors when usable; numba for float32 CPU tensors when it
          imports; else torch. The torch fallbacks (CUDA tensors without gsplat, float32 CPU
          tensors without numba) are logged as a WARNING with the exception; the other choices
          at INFO; each once per process.
    Raises:
        BackendUnavailable: ``"gsplat"`` requested for tensors not on CUDA, or gsplat unusable
            (chained from its import/build exception); ``"numba"`` requested for tensors not on
            the CPU, or numba not importable.
        ValueError: an unknown ``requested``.
    """
    if requested == "torch":
        return BackendChoice("torch", "requested")
    if requested not in ("auto", "gsplat", "numba"):
        raise ValueError(f"unknown backend {requested!r}: choose 'auto', 'gsplat', 'torch' or "
                         "'numba'")
    device = torch.device(device)
    if requested == "numba":
        if device.type != "cpu":
            raise BackendUnavailable(f"backend 'numba' composites on the CPU, these tensors are on "
                                     f"{device}")
        _numba_compositor()
        return BackendChoice("numba", "requested")
    if device.type != "cuda":
        if requested == "gsplat":
            why = ("" if torch.cuda.is_available() else
                   "; CUDA is not available in this process (torch.cuda.is_available() is False)")
            raise BackendUnavailable(
                f"backend 'gsplat' needs CUDA tensors, these are on {device}{why}")
        if device.type != "cpu" or dtype != torch.float32:
            return _announce(logging.INFO, BackendChoice(
                "torch", f"auto: {dtype} tensors on {device.type}, the compiled compositor takes float32 "
                         "CPU tensors and gsplat CUDA ones"))
        try:
            _numba_compositor()
        except BackendUnavailable as e:
            return _announce(logging.WARNING, BackendChoice(
                "torch", "auto: CPU tensors but numba cannot be imported; the pure-PyTorch compositor is "
                         "~2x slower"), e.__cause__)
        return _announce(logging.INFO, BackendChoice("numba", "auto: float32 CPU tensors, the compiled compositor"))
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
        backend: ``"auto"``, ``"gsplat"``, ``"torch"`` or ``"numba"``, resolved by
            :func:`resolve_backend` (an explicit back-end that cannot run raises
            :class:`BackendUnavailable`).
        background: ``[3]`` linear colour behind the Gaussians (default black), or an ``[H, W, 3]``
            image (another model's render: training's frozen set), added as ``(1 - alpha) · background``.
        tile_size: tile edge of the torch and numba back-ends (px).
        stats: filled with the torch or numba back-end's work counts (benchmarks).
    Returns:
        ``{"rgb": [H, W, 3] linear, "alpha": [H, W, 1] in [0, 1], "depth": [H, W, 1]}``; depth is
        the expected camera-space z of the visible Gaussians (metres; accumulated z over alpha,
        0 where nothing is drawn), gsplat's ``"RGB+ED"``.
    """
    cam = camera.to(gaussians.means.device)
    name = resolve_backend(backend, gaussians.means.device, gaussians.means.dtype).name
    if name == "gsplat":
        rgb, alpha, depth = _render_gsplat(gaussians, cam)
    else:
        rgb, alpha, depth = _render_torch(gaussians, cam, tile_size, stats, _compositor(name),
                                          _projector(name), _colourer(name))
    if background is not None:
        rgb = rgb + (1.0 - alpha) * background.to(rgb)
    return {"rgb": rgb, "alpha": alpha, "depth": depth}


def _compositor(name: BackendName):
    """The tile compositor of back-end ``"torch"`` or ``"numba"`` (same signature and outputs)."""
    return _numba_compositor() if name == "numba" else rasterize_tiles


def _projector(name: BackendName):
    """The projection of back-end ``"torch"`` or ``"numba"`` (same signature and outputs)."""
    return _numba_projector() if name == "numba" else project_gaussians


def _survivor_colours(g: Gaussians3D, cam: Camera, ids: torch.Tensor) -> torch.Tensor:
    """Back-end ``"torch"``'s colours of the Gaussians ``ids`` of ``g``: :func:`gaussian_colours`
    of their rows."""
    return gaussian_colours(g.select(ids), cam)


def _numba_survivor_colours(g: Gaussians3D, cam: Camera, ids: torch.Tensor) -> torch.Tensor:
    """Back-end ``"numba"``'s colours of the Gaussians ``ids`` of ``g``
    (:func:`~volcap_core.splat.colour_numba.survivor_colours_numba`, imported on first use as
    :func:`_numba_projector`): :func:`gaussian_colours`'s values, without gathering the rows."""
    from volcap_core.splat.colour_numba import survivor_colours_numba
    return survivor_colours_numba(g.sh, g.means, ids, cam.centre,
                                  linearise=g.colour_space != "linear")


def _colourer(name: BackendName):
    """The survivors' colours of back-end ``"torch"`` or ``"numba"`` (same signature and
    outputs)."""
    return _numba_survivor_colours if name == "numba" else _survivor_colours


def _render_torch(g: Gaussians3D, cam: Camera, tile_size: int, stats: TileStats | None,
                  composite=rasterize_tiles, project=project_gaussians,
                  colour=_survivor_colours):
    """``project`` (:func:`_projector`), the survivors' ``colour`` (:func:`_colourer`), then
    ``composite`` (:func:`_compositor`)."""
    # geometry: the projection culls (without gradient) anything non-finite or degenerate
    proj = project(g.means, g.quats, g.scales, g.opacities, cam, eps2d=EPS2D, antialiased=True)
    # colours only for the survivors: SH of culled Gaussians is never needed
    colours = colour(g, cam, proj.ids)
    finite = torch.isfinite(colours.detach()).all(-1)
    if not bool(finite.all()):
        # a non-finite colour (NaN/inf SH, or a decode overflow) is culled like a culled
        # geometry: dropped from every projected tensor and its colour recomputed without it, so
        # no graph ever holds it (0·NaN would otherwise reach its own and the others' gradients)
        keep = torch.nonzero(finite).squeeze(1)
        proj = Projected(ids=proj.ids[keep], means2d=proj.means2d[keep],
                         conics=proj.conics[keep], opacities=proj.opacities[keep],
                         depths=proj.depths[keep], radii=proj.radii[keep])
        colours = colour(g, cam, proj.ids)
    values = torch.cat([colours, proj.depths[:, None]], dim=-1)
    acc, trans = composite(proj.means2d, proj.conics, proj.opacities, proj.depths, proj.radii,
                           values, cam.width, cam.height, tile_size=tile_size, stats=stats)
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


# ------------------------------------------------------------------------------------------------
# Exact rendered flow

#: Pixels whose accumulated alpha (of Gaussians with a defined displacement) is below this get a
#: flow of exactly 0 (:func:`render_flow`): the rasterizer's own fragment threshold, 1/255, which
#: is also the shots' default crop threshold.
FLOW_MIN_ALPHA = 1.0 / 255.0


def gaussians_at(model: Poly4DGS, t: float, ids: torch.Tensor) -> Gaussians3D:
    """The model's Gaussians ``ids`` (``[M]`` int64 indices into the model, e.g.
    :attr:`Gaussians3D.ids` of :func:`~volcap_core.splat.model.evaluate` at another time) at time
    ``t`` seconds, in that order, **whatever their opacity at** ``t``.

    :func:`~volcap_core.splat.model.evaluate` itself (on those rows, without its opacity cut):
    ``evaluate`` drops a Gaussian outside its lifespan (opacity below 1/255), but its centre,
    rotation and scale are still defined there, and they say where the same Gaussian "was" in a
    frame it was invisible in (:func:`render_flow`). A Gaussian whose opacity is not even a number
    gets NaN geometry (its displacement is then undefined). Not differentiable."""
    with torch.no_grad():
        ids = ids.to(model.params["means"].device)
        sub = Poly4DGS(model.config, {k: v.detach()[ids] for k, v in model.params.items()})
        g = evaluate(sub, t, min_opacity=float("-inf"))
        if len(g) != len(ids):  # NaN opacities: keep the rows aligned with ``ids``
            def full(x: torch.Tensor) -> torch.Tensor:
                out = x.new_full((len(ids), *x.shape[1:]), float("nan"))
                out[g.ids] = x
                return out
            g = Gaussians3D(means=full(g.means), quats=full(g.quats), scales=full(g.scales),
                            opacities=full(g.opacities), sh=full(g.sh), ids=ids, colour_space=g.colour_space)
        return Gaussians3D(means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities, sh=g.sh,
                           ids=ids, colour_space=g.colour_space)


def _rotations(quats: torch.Tensor) -> torch.Tensor:
    """``[M, 3, 3]`` rotation matrices of wxyz quaternions (normalised here)."""
    q = torch.nn.functional.normalize(quats, dim=-1, eps=1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


#: A Gaussian whose first-order motion (:func:`_flow_values`) changes by more than this many px per
#: px across its footprint between two frames (a centre crossing near a camera plane, a degenerate
#: scale change) is not trusted to first order: its centre's displacement alone is used.
_FLOW_MAX_GRADIENT = 4.0


def _flow_values(cur: Gaussians3D, prev: Gaussians3D, camera: Camera, prev_camera: Camera) -> torch.Tensor:
    """Per-Gaussian values ``[M, 7]`` composited by :func:`render_flow`: ``v · (a, B, 1)`` such
    that Gaussian ``i`` moves the point it draws at pixel position ``p`` (px) by
    ``f_i(p) = a_i + B_i (p − o)`` (``o`` the image centre, which keeps ``a_i`` small), and ``v`` =
    1 where that is defined (finite, centre in front of both cameras), else 0 (the row is all
    zeros). In float64 until the end.

    ``f_i(p) = d_i + (M_i − I)(p − c_i)``: ``c_i`` the centre's projection now, ``d_i`` the
    centre's displacement (previous projection minus ``c_i``), ``M_i`` the 2×2 Jacobian of the
    previous pixel position with respect to the current one for the points of the Gaussian at the
    centre's camera depth: back-projection at depth ``z_i`` through ``camera``, the Gaussian's own
    affine motion ``X ↦ μ' + R' diag(s'/s) Rᵀ (X − μ)`` (rotation and scale change, which carry
    its density exactly), projection through ``prev_camera``. ``B_i = M_i − I`` is dropped (0)
    where an entry exceeds :data:`_FLOW_MAX_GRADIENT`."""
    f64 = torch.float64
    dev = cur.means.device
    Wc, Kc = camera.world_to_camera.to(dev, f64), camera.K.to(dev, f64)
    Wp, Kp = prev_camera.world_to_camera.to(dev, f64), prev_camera.K.to(dev, f64)
    mu, mu_p = cur.means.to(f64), prev.means.to(f64)
    xc = mu @ Wc[:3, :3].T + Wc[:3, 3]                                   # [M, 3] camera t
    yp = mu_p @ Wp[:3, :3].T + Wp[:3, 3]                                 # [M, 3] camera t-1
    z, zp = xc[:, 2], yp[:, 2]
    c = torch.stack([Kc[0, 0] * xc[:, 0] / z + Kc[0, 2], Kc[1, 1] * xc[:, 1] / z + Kc[1, 2]], -1)
    cp = torch.stack([Kp[0, 0] * yp[:, 0] / zp + Kp[0, 2], Kp[1, 1] * yp[:, 1] / zp + Kp[1, 2]], -1)
    d = cp - c
    # d(world point)/d(pixel) on the plane z_cam = z through the centre:
    # R_cᵀ · z · [[1/fx, 0], [0, 1/fy], [0, 0]]
    focal = torch.stack([Kc[0, 0], Kc[1, 1]])
    back = Wc[:2, :3].T.expand(len(mu), 3, 2) * (z[:, None, None] / focal[None, None])
    rot, rot_p = _rotations(cur.quats.to(f64)), _rotations(prev.quats.to(f64))
    ratio = prev.scales.to(f64) / cur.scales.to(f64)
    Q = (rot_p * ratio[:, None, :]) @ rot.transpose(1, 2)                # the Gaussian's own motion
    zero = torch.zeros_like(zp)
    proj = torch.stack([Kp[0, 0] / zp, zero, -Kp[0, 0] * yp[:, 0] / (zp * zp),
                        zero, Kp[1, 1] / zp, -Kp[1, 1] * yp[:, 1] / (zp * zp)], -1).reshape(-1, 2, 3)
    M = proj @ Wp[:3, :3] @ Q @ back                                     # [M, 2, 2]
    B = M - torch.eye(2, dtype=f64, device=dev)
    B = torch.where((B.abs() <= _FLOW_MAX_GRADIENT).all(-1).all(-1)[:, None, None], B, torch.zeros_like(B))
    o = torch.tensor([camera.width / 2.0, camera.height / 2.0], dtype=f64, device=dev)
    a = d - (B @ (c - o)[:, :, None])[:, :, 0]
    vals = torch.cat([a, B.reshape(-1, 4)], -1)
    valid = torch.isfinite(vals).all(-1) & (z > 0) & (zp > 0)
    vals = torch.where(valid[:, None], vals, torch.zeros_like(vals))
    return torch.cat([vals, valid[:, None].to(f64)], dim=-1).to(torch.float32)


def render_flow(gaussians: Gaussians3D, previous: Gaussians3D, camera: Camera, prev_camera: Camera, *,
                backend: Backend = "auto", tile_size: int = 8, min_alpha: float = FLOW_MIN_ALPHA
                ) -> dict[str, torch.Tensor]:
    """The exact backward flow of a render to the previous frame: where what each pixel of the
    frame rendered from ``gaussians`` into ``camera`` shows was in the previous frame's image.

    Each Gaussian ``i`` moves by its centre's 2-D displacement ``d_i = P_{t-1}(μ_i(t-1)) −
    P_t(μ_i(t))`` (px: its centre at the previous frame's time through the previous camera, minus
    its centre now through this camera), plus the first-order variation of that motion across its
    footprint (the Gaussian as an affine body: its rotation and scale change, the cameras'
    perspective; exact for a dolly or a turning Gaussian, where the centre alone is off by the
    flow's gradient times the distance to the centre): ``f_i(p) = d_i + (M_i − I)(p − c_i)``
    (:func:`_flow_values`). The ``f_i`` are alpha-composited front to back exactly like colour
    (same Gaussians, same weights ``α_i T_i`` as :func:`render`; the affine terms are composited
    as 6 channels and evaluated at each pixel centre), and normalised by the accumulated alpha:
    ``flow(p) = Σ α_i T_i f_i(p) / Σ α_i T_i``.

    Convention (:mod:`volcap_core.enhance.temporal`): **backward** flow in pixels, x then y (y
    down), ``cur(x, y) ≈ prev(x + flow_x, y + flow_y)``; pass ``flow.permute(2, 0, 1)`` to
    :func:`~volcap_core.enhance.temporal.warp`.

    Args:
        gaussians: M Gaussians of frame ``t`` (:func:`~volcap_core.splat.model.evaluate` at ``t``,
            after any selection the colour render had).
        previous: the same M Gaussians at frame ``t-1``'s time (:func:`gaussians_at` of the **same
            model** with ``gaussians.ids``; a Gaussian invisible at ``t-1``, outside its lifespan,
            still has a centre then); its means, quats and scales are used. Gaussians of another
            model have no correspondence: across a segment boundary there is no exact flow.
        camera, prev_camera: the cameras of frames ``t`` and ``t-1``.
        backend, tile_size: as :func:`render` (the gsplat back-end rasterizes the 7 flow values
            as N-channel colours, which gsplat pads to 8; numba composites them like colours).
        min_alpha: pixels whose accumulated alpha of Gaussians with a defined displacement is
            below it get flow **0** (nothing there moves; a shot frame is a render over nothing,
            so there is no background whose camera motion would matter). A displacement is
            undefined for a centre that is not in front of a camera (``z <= 0``) or not finite:
            such a Gaussian still occludes, but adds no weight to the normaliser.
    Returns:
        ``{"flow": [H, W, 2] float32 px, "alpha": [H, W, 1]}``: ``alpha`` is the accumulated alpha
        of the Gaussians with a defined displacement (the render's alpha when all have one).
        Not differentiable.
    """
    if previous.means.shape != gaussians.means.shape:
        raise ValueError(f"previous Gaussians {tuple(previous.means.shape)} must match the Gaussians "
                         f"{tuple(gaussians.means.shape)}")
    dev = gaussians.means.device
    cam, prev_cam = camera.to(dev), prev_camera.to(dev)
    prev = Gaussians3D(**{f: getattr(previous, f).to(dev)
                          for f in ("means", "quats", "scales", "opacities", "sh", "ids")},
                       colour_space=previous.colour_space)
    with torch.no_grad():
        name = resolve_backend(backend, dev, gaussians.means.dtype).name
        if name == "gsplat":
            acc = _render_flow_gsplat(gaussians, prev, cam, prev_cam)
        else:
            acc = _render_flow_torch(gaussians, prev, cam, prev_cam, tile_size, _compositor(name),
                                     _projector(name))
        h, w = acc.shape[:2]
        # pixel centres in K's frame (+0.5), relative to the image centre (_flow_values' o)
        px = torch.arange(w, device=dev, dtype=acc.dtype)[None, :] + 0.5 - w / 2.0
        py = torch.arange(h, device=dev, dtype=acc.dtype)[:, None] + 0.5 - h / 2.0
        fx = acc[..., 0] + acc[..., 2] * px + acc[..., 3] * py
        fy = acc[..., 1] + acc[..., 4] * px + acc[..., 5] * py
        weight = acc[..., 6:7]
        flow = torch.where(weight >= min_alpha, torch.stack([fx, fy], -1) / weight.clamp(min=1e-10),
                           torch.zeros_like(acc[..., :2]))
    return {"flow": flow, "alpha": weight}


def _render_flow_torch(g: Gaussians3D, prev: Gaussians3D, cam: Camera, prev_cam: Camera,
                       tile_size: int, composite=rasterize_tiles,
                       project=project_gaussians) -> torch.Tensor:
    # the survivors of _render_torch exactly: projection culling, then non-finite colours
    proj = project(g.means, g.quats, g.scales, g.opacities, cam, eps2d=EPS2D, antialiased=True)
    finite = torch.isfinite(gaussian_colours(g.select(proj.ids), cam)).all(-1)
    if not bool(finite.all()):
        keep = torch.nonzero(finite).squeeze(1)
        proj = Projected(ids=proj.ids[keep], means2d=proj.means2d[keep],
                         conics=proj.conics[keep], opacities=proj.opacities[keep],
                         depths=proj.depths[keep], radii=proj.radii[keep])
    values = _flow_values(g.select(proj.ids), prev.select(proj.ids), cam, prev_cam)
    acc, _ = composite(proj.means2d, proj.conics, proj.opacities, proj.depths, proj.radii,
                       values.to(proj.means2d.dtype), cam.width, cam.height, tile_size=tile_size)
    return acc


def _render_flow_gsplat(g: Gaussians3D, prev: Gaussians3D, cam: Camera, prev_cam: Camera) -> torch.Tensor:
    from gsplat import rasterization  # resolve_backend has loaded it (probe_gsplat)

    values = _flow_values(g, prev, cam, prev_cam)
    renders, _, _ = rasterization(
        means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities, colors=values,
        viewmats=cam.world_to_camera[None], Ks=cam.K[None], width=cam.width, height=cam.height,
        near_plane=cam.near, far_plane=cam.far, eps2d=EPS2D, rasterize_mode="antialiased",
        render_mode="RGB", packed=False)
    return renders[0]
