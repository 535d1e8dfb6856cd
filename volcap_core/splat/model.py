"""Poly4DGS: 3D Gaussians whose properties are polynomials of time (paper §"Poly4DGS").

For a Gaussian with temporal centre ``t0`` and ``dt = t - t0`` (seconds)::

    μ_t = Σ_{i=0..n_μ} μ_i dt^i                       mean, metres
    q_t = normalise(Σ_{i=0..n_q} q_i dt^i)            rotation, wxyz quaternion
    s_t = exp(Σ_{i=0..n_s} s_i dt^i)                  scale, metres (polynomial in log-scale)
    o_t = o_0 · exp(-½ Σ_{i=1..n_o} λ_i dt^{2i})      opacity, λ_i >= 0
    c(d) = SH(sh, d) + 0.5                            colour, unbounded sRGB, constant in time
                                                      (``colour_space="linear"``: linear radiance)

Degrees are configuration (:class:`Poly4DGSConfig`): the paper's default is
``(n_μ, n_q, n_s, n_o) = (2, 1, 0, 2)``; ``(1, 0, 0, 1)`` is the 4D-Rotor sliced baseline;
``(0, 0, 0, 0)`` is static 3DGS (train it on one frame). A degree of 0 creates no temporal tensor
and no compute for that property; a model with all degrees 0 has no ``t0`` either.

Parameter tensors (``Poly4DGS.params``, names as in gsplat where they exist; N Gaussians):

====================  ======================  ==============================================
name                  shape                   meaning
====================  ======================  ==============================================
``means``             ``[N, 3]``              μ_0 (metres)
``means_t``           ``[N, n_μ, 3]``         μ_1..μ_n (metres / s^i)
``quats``             ``[N, 4]``              q_0, wxyz, unnormalised
``quats_t``           ``[N, n_q, 4]``         q_1..q_n (1 / s^i)
``scales``            ``[N, 3]``              s_0 = log scale (log metres)
``scales_t``          ``[N, n_s, 3]``         s_1..s_n (1 / s^i)
``opacities``         ``[N]``                 logit(o_0)
``log_lambdas``       ``[N, n_o]``            log λ_1..λ_n (λ_i in 1 / s^(2i)); exp keeps λ >= 0
                                              and makes Adam steps relative (λ spans decades)
``t0``                ``[N]``                 temporal centre (seconds, the take's clock)
``sh0``               ``[N, 1, 3]``           SH DC coefficient
``shN``               ``[N, K-1, 3]``         higher SH bands, K = (sh_degree + 1)²
====================  ======================  ==============================================

Numerical guards (why each exists is in ``docs/poly4dgs.md``): ``|dt|`` is clamped to
:data:`MAX_ABS_DT`; the opacity envelope is evaluated in log space with each term capped;
log-scales are clamped to ``[LOG_SCALE_MIN, LOG_SCALE_MAX]``; quaternions are normalised with a
floor on the norm.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_serializer
from safetensors.torch import load as st_load

from volcap_core.checkpoint import safetensors_bytes, safetensors_metadata
from volcap_core.splat.sh import num_sh_bases

__all__ = [
    "ALPHA_MIN",
    "ColourSpace",
    "Gaussians3D",
    "Poly4DGS",
    "Poly4DGSConfig",
    "evaluate",
    "load_model",
    "opacity_envelope",
    "save_model",
]

#: Opacity below which a Gaussian at time t is dropped before rasterization (gsplat's alpha
#: threshold: such a Gaussian cannot produce a fragment the rasterizer keeps).
ALPHA_MIN = 1.0 / 255.0
#: |t - t0| is clamped to this many seconds (11.6 days) so dt^i never overflows float32.
MAX_ABS_DT = 1e6
#: Log-scale clamp: 9e-14 m .. 22 km. Beyond it covariances overflow float32 in projection.
LOG_SCALE_MIN, LOG_SCALE_MAX = -30.0, 10.0
#: Each opacity-envelope term λ_i dt^(2i) is capped at exp(80) ≈ 5.5e34 (float32-safe sum).
_LOG_TERM_CAP = 80.0
#: log λ of a Gaussian that lives for the whole segment (static set): λ = e^-40, so λ·dt² < 1e-14
#: for any |dt| < 1 day; an exact zero would put log λ at -inf, whose Adam update is NaN
STATIC_LOG_LAMBDA = -40.0
MODEL_FORMAT = "volcap-poly4dgs/1"

#: What the SH colour ``c(d) = SH(d) + 0.5`` of a Gaussian is. ``"srgb_unbounded"`` (the paper's
#: choice): unbounded sRGB, linearised before rasterization. ``"linear"``: linear radiance,
#: rasterized as is (the paper's "training in linear colour space" ablation). The loss is the same
#: (unbounded sRGB of the linear render) either way.
ColourSpace = Literal["srgb_unbounded", "linear"]


class Poly4DGSConfig(BaseModel):
    """Polynomial degrees per property and the SH degree. JSON-serialisable, immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    mean_degree: int = Field(2, ge=0, le=8, description="n_μ")
    quat_degree: int = Field(1, ge=0, le=8, description="n_q")
    scale_degree: int = Field(0, ge=0, le=8, description="n_s")
    opacity_degree: int = Field(2, ge=0, le=6, description="n_o (terms λ_1..λ_n of dt^2i)")
    sh_degree: int = Field(3, ge=0, le=3)
    colour_space: ColourSpace = Field("srgb_unbounded",
                                      description="what the SH colours are (see ColourSpace)")

    @model_serializer(mode="wrap")
    def _omit_default_colour_space(self, handler):
        # The default is left out of the JSON so configs (a task's cache key) and saved models
        # written before the field existed stay byte-identical; a missing field reads back as it.
        out = handler(self)
        if self.colour_space == "srgb_unbounded":
            out.pop("colour_space", None)
        return out

    @classmethod
    def paper(cls, sh_degree: int = 3) -> "Poly4DGSConfig":
        """(n_μ, n_q, n_s, n_o) = (2, 1, 0, 2): the paper's choice."""
        return cls(mean_degree=2, quat_degree=1, scale_degree=0, opacity_degree=2,
                   sh_degree=sh_degree)

    @classmethod
    def rotor4d(cls, sh_degree: int = 3) -> "Poly4DGSConfig":
        """(1, 0, 0, 1): a sliced 4D Gaussian (4D-Rotor baseline)."""
        return cls(mean_degree=1, quat_degree=0, scale_degree=0, opacity_degree=1,
                   sh_degree=sh_degree)

    @classmethod
    def static(cls, sh_degree: int = 3) -> "Poly4DGSConfig":
        """(0, 0, 0, 0): per-frame static 3DGS, no temporal opacity."""
        return cls(mean_degree=0, quat_degree=0, scale_degree=0, opacity_degree=0,
                   sh_degree=sh_degree)

    @property
    def temporal(self) -> bool:
        return max(self.mean_degree, self.quat_degree, self.scale_degree, self.opacity_degree) > 0

    def param_shapes(self) -> dict[str, tuple[int, ...]]:
        """Trailing shape (after N) of each parameter tensor this config creates."""
        shapes: dict[str, tuple[int, ...]] = {"means": (3,), "quats": (4,), "scales": (3,),
                                              "opacities": (), "sh0": (1, 3)}
        if self.mean_degree:
            shapes["means_t"] = (self.mean_degree, 3)
        if self.quat_degree:
            shapes["quats_t"] = (self.quat_degree, 4)
        if self.scale_degree:
            shapes["scales_t"] = (self.scale_degree, 3)
        if self.opacity_degree:
            shapes["log_lambdas"] = (self.opacity_degree,)
        if self.temporal:
            shapes["t0"] = ()
        if self.sh_degree:
            shapes["shN"] = (num_sh_bases(self.sh_degree) - 1, 3)
        return shapes


@dataclass
class Gaussians3D:
    """Plain 3D Gaussians at one instant (what a 3DGS rasterizer takes). M Gaussians.

    Attributes:
        means: ``[M, 3]`` world positions (metres).
        quats: ``[M, 4]`` unit quaternions, wxyz.
        scales: ``[M, 3]`` standard deviations along the rotated axes (metres), > 0.
        opacities: ``[M]`` in ``[0, 1]``.
        sh: ``[M, K, 3]`` SH coefficients of the colour (unbounded sRGB unless
            ``colour_space`` says ``"linear"``).
        ids: ``[M]`` int64 index of each Gaussian in the model it came from.
        colour_space: what ``SH + 0.5`` is (:data:`ColourSpace`); the renderer linearises
            ``"srgb_unbounded"`` colours and rasterizes ``"linear"`` ones as they are.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    ids: torch.Tensor
    colour_space: ColourSpace = "srgb_unbounded"

    def __len__(self) -> int:
        return self.means.shape[0]

    def select(self, index: torch.Tensor) -> "Gaussians3D":
        """Subset by an index or boolean mask ``[M]`` (differentiable)."""
        return Gaussians3D(**{f.name: getattr(self, f.name)[index] for f in fields(self)
                              if f.name != "colour_space"}, colour_space=self.colour_space)


class Poly4DGS:
    """A Poly4DGS model: its config and its parameter tensors (a plain dict, see module doc).

    The trainer makes the tensors leaves with ``requires_grad``; everything else treats the model
    as data. Construct with :meth:`from_points` or :func:`load_model`.
    """

    def __init__(self, config: Poly4DGSConfig, params: dict[str, torch.Tensor]):
        shapes = config.param_shapes()
        if set(params) != set(shapes):
            raise ValueError(f"parameters {sorted(params)} do not match config {sorted(shapes)}")
        n = params["means"].shape[0]
        for name, trailing in shapes.items():
            if tuple(params[name].shape) != (n, *trailing):
                raise ValueError(f"{name}: shape {tuple(params[name].shape)}, expected "
                                 f"{(n, *trailing)}")
        self.config = config
        self.params = params

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @classmethod
    def from_points(cls, config: Poly4DGSConfig, xyz: torch.Tensor, colour: torch.Tensor, *,
                    scales: torch.Tensor, t0: torch.Tensor | None = None,
                    opacity: float = 0.5, lifespan_s: float | torch.Tensor = 1.0,
                    velocity: torch.Tensor | None = None) -> "Poly4DGS":
        """One isotropic Gaussian per point, no motion (or ``velocity``).

        Args:
            xyz: ``[N, 3]`` positions (metres).
            colour: ``[N, 3]`` colours in ``config.colour_space`` (unbounded sRGB by default:
                encode linear point colours first).
            scales: ``[N]`` or ``[N, 3]`` initial standard deviations (metres), > 0.
            t0: ``[N]`` temporal centres (seconds); required when the config is temporal.
            opacity: initial o_0 in (0, 1).
            lifespan_s: initial temporal standard deviation σ_t (seconds), one for all or ``[N]``:
                λ_1 = 1/σ_t², and λ_i = 0.01 / σ_t^(2i) for i >= 2 (a near-Gaussian envelope the
                optimiser reshapes). ``inf`` = lives for ever (what does not move): log λ =
                :data:`STATIC_LOG_LAMBDA`.
            velocity: ``[N, 3]`` m/s at ``t0``, the first-order mean coefficient μ_1 (needs
                ``mean_degree`` >= 1); None: 0.
        """
        n = xyz.shape[0]
        dev, dt = xyz.device, torch.float32
        scales = scales.to(dt)
        if scales.ndim == 1:
            scales = scales[:, None].expand(n, 3)
        p: dict[str, torch.Tensor] = {
            "means": xyz.to(dt).clone(),
            "quats": torch.tensor([1.0, 0, 0, 0], device=dev).repeat(n, 1),
            "scales": torch.log(scales.clamp(min=math.exp(LOG_SCALE_MIN))).clone(),
            "opacities": torch.full((n,), math.log(opacity / (1 - opacity)), device=dev),
            "sh0": ((colour.to(dt) - 0.5) / 0.28209479177387814)[:, None, :].clone(),
        }
        c = config
        if c.mean_degree:
            p["means_t"] = torch.zeros(n, c.mean_degree, 3, device=dev)
            if velocity is not None:
                p["means_t"][:, 0] = velocity.to(dev, dt).reshape(n, 3)
        elif velocity is not None:
            raise ValueError("a velocity needs mean_degree >= 1")
        if c.quat_degree:
            p["quats_t"] = torch.zeros(n, c.quat_degree, 4, device=dev)
        if c.scale_degree:
            p["scales_t"] = torch.zeros(n, c.scale_degree, 3, device=dev)
        if c.opacity_degree:
            i = torch.arange(1, c.opacity_degree + 1, device=dev, dtype=dt)
            life = torch.as_tensor(lifespan_s, dtype=dt, device=dev).expand(n)
            log_lam = (-2 * i[None] * torch.log(life.clamp(min=1e-9))[:, None]
                       + torch.where(i > 1, math.log(0.01), 0.0)[None])
            p["log_lambdas"] = torch.where(torch.isinf(life)[:, None],
                                           torch.full_like(log_lam, STATIC_LOG_LAMBDA), log_lam)
        if c.temporal:
            if t0 is None:
                raise ValueError("a temporal config needs t0 per point")
            p["t0"] = t0.to(dev, dt).reshape(n).clone()
        if c.sh_degree:
            p["shN"] = torch.zeros(n, num_sh_bases(c.sh_degree) - 1, 3, device=dev)
        return cls(config, p)

    def detached(self) -> "Poly4DGS":
        """A copy with plain (no-grad) cloned tensors."""
        return Poly4DGS(self.config, {k: v.detach().clone() for k, v in self.params.items()})

    def to(self, device: torch.device | str) -> "Poly4DGS":
        return Poly4DGS(self.config, {k: v.to(device) for k, v in self.params.items()})

    def moving(self) -> torch.Tensor:
        """``[N]`` bool: the Gaussians with a lifespan (``log λ_1`` above the static value: the
        performers') rather than the set's, which live for the whole segment. Every Gaussian of a
        model without lifespans counts as moving."""
        lam = self.params.get("log_lambdas")
        if lam is None:
            return torch.ones(len(self), dtype=torch.bool, device=self.params["means"].device)
        return lam.detach()[:, 0] > STATIC_LOG_LAMBDA + 10.0

    def subset(self, keep: torch.Tensor) -> "Poly4DGS":
        """The Gaussians ``keep`` (``[N]`` bool or indices), as plain (no-grad) copies."""
        return Poly4DGS(self.config, {k: v.detach()[keep].clone() for k, v in self.params.items()})

    @staticmethod
    def joined(first: "Poly4DGS", second: "Poly4DGS") -> "Poly4DGS":
        """One model holding ``first``'s Gaussians, then ``second``'s (the same config; plain
        copies)."""
        if first.config != second.config:
            raise ValueError(f"joining models of different configs: {first.config} and {second.config}")
        return Poly4DGS(first.config, {k: torch.cat([first.params[k].detach(), second.params[k].detach()])
                                       for k in first.params})


def _powers(dt: torch.Tensor, degree: int) -> torch.Tensor:
    """``[N, degree]`` with column i-1 = dt^i."""
    return torch.cumprod(dt[:, None].expand(-1, degree), dim=1)


def opacity_envelope(log_o0: torch.Tensor, log_lambdas: torch.Tensor | None,
                     dt: torch.Tensor) -> torch.Tensor:
    """``o_t = o_0 · exp(-½ Σ_i λ_i dt^(2i))``, evaluated in log space.

    Args:
        log_o0: ``[N]`` log of the peak opacity (``logsigmoid`` of the stored logit).
        log_lambdas: ``[N, n_o]`` log λ_i, or None (no temporal opacity).
        dt: ``[N]`` seconds from the temporal centre.
    Returns:
        ``[N]`` opacity in ``[0, 1]``. Each term is ``exp(log λ_i + 2i log|dt|)`` capped at
        ``exp(80)``: finite for λ up to 1e8 and |dt| up to :data:`MAX_ABS_DT`, and a Gaussian far
        outside its lifespan gets opacity exactly 0 with zero (not NaN) gradient.
    """
    if log_lambdas is None or log_lambdas.shape[1] == 0:
        return log_o0.exp()
    n_o = log_lambdas.shape[1]
    two_i = 2.0 * torch.arange(1, n_o + 1, device=dt.device, dtype=dt.dtype)
    # |dt| floored at 1e-30 so log|dt| and its gradient stay finite at dt == 0 (the term is 0 there)
    log_abs_dt = dt.abs().clamp(min=1e-30).log()
    log_terms = (log_lambdas + two_i * log_abs_dt[:, None]).clamp(max=_LOG_TERM_CAP)
    return (log_o0 - 0.5 * log_terms.exp().sum(dim=1)).exp()


@functools.cache
def _numba_slicer():
    """:func:`~volcap_core.splat.evaluate_numba.slice_poly4dgs_numba`, imported on first use
    (numba's import costs ~0.5 s; a GPU machine has no numba), or None where numba does not
    import."""
    try:
        from volcap_core.splat.evaluate_numba import slice_poly4dgs_numba
    except ImportError:
        return None
    return slice_poly4dgs_numba


def evaluate(model: Poly4DGS, t: float, *, min_opacity: float = ALPHA_MIN) -> Gaussians3D:
    """Slice the model at time ``t`` (seconds): the 3D Gaussians a rasterizer takes.

    Gaussians whose opacity at ``t`` is below ``min_opacity`` are dropped (they would not produce
    a single kept fragment), and their polynomials are not evaluated at all.

    float32 CPU parameters are sliced by the compiled kernels of
    :mod:`volcap_core.splat.evaluate_numba` when numba imports (the same values within float32
    rounding, an analytic backward); CUDA, float64 or no numba: the PyTorch ops below.

    Args:
        model: the model; gradients flow to its parameters.
        t: time in seconds on the take's clock (same clock as ``t0``).
        min_opacity: drop threshold, default 1/255.
    Returns:
        :class:`Gaussians3D` with M <= N Gaussians; ``ids`` maps them back into the model.
    """
    p, c = model.params, model.config
    slicer = _numba_slicer() if all(v.dtype == torch.float32 and v.device.type == "cpu"
                                    for v in p.values()) else None
    if slicer is not None:
        means, quats, scales, opacities, sh, ids = slicer(
            p, t, min_opacity, max_abs_dt=MAX_ABS_DT, log_term_cap=_LOG_TERM_CAP,
            log_scale_min=LOG_SCALE_MIN, log_scale_max=LOG_SCALE_MAX)
        return Gaussians3D(means=means, quats=quats, scales=scales, opacities=opacities, sh=sh,
                           ids=ids, colour_space=c.colour_space)
    n = len(model)
    dev = p["means"].device
    if c.temporal:
        dt_all = (t - p["t0"]).clamp(-MAX_ABS_DT, MAX_ABS_DT)
    else:
        dt_all = torch.zeros(n, device=dev)
    log_o0 = torch.nn.functional.logsigmoid(p["opacities"])
    opac_all = opacity_envelope(log_o0, p.get("log_lambdas"), dt_all)
    with torch.no_grad():
        ids = torch.nonzero(opac_all >= min_opacity).squeeze(1)
    dt = dt_all[ids]

    def poly(name: str, degree: int) -> torch.Tensor:
        value = p[name][ids]
        if degree:
            coeffs = p[name + "_t"][ids]                   # [M, degree, D]
            value = value + (coeffs * _powers(dt, degree)[:, :, None]).sum(dim=1)
        return value

    means = poly("means", c.mean_degree)
    quats = torch.nn.functional.normalize(poly("quats", c.quat_degree), dim=-1, eps=1e-8)
    scales = poly("scales", c.scale_degree).clamp(LOG_SCALE_MIN, LOG_SCALE_MAX).exp()
    sh = p["sh0"][ids]
    if c.sh_degree:
        sh = torch.cat([sh, p["shN"][ids]], dim=1)
    return Gaussians3D(means=means, quats=quats, scales=scales, opacities=opac_all[ids], sh=sh,
                       ids=ids, colour_space=c.colour_space)


def save_model(model: Poly4DGS) -> bytes:
    """Serialise to safetensors bytes; the config travels as JSON in the header metadata
    (``volcap.config``), so one artifact holds the whole model. No pickle. The same model gives
    the same bytes in any process (:func:`~volcap_core.checkpoint.safetensors_bytes`)."""
    tensors = {k: v.detach().contiguous().cpu() for k, v in model.params.items()}
    meta = {"format": MODEL_FORMAT, "volcap.config": model.config.model_dump_json()}
    return safetensors_bytes(tensors, meta)


def load_model(data: bytes, device: torch.device | str = "cpu") -> Poly4DGS:
    """Inverse of :func:`save_model`."""
    meta = safetensors_metadata(data)
    if meta.get("format") != MODEL_FORMAT:
        raise ValueError(f"not a Poly4DGS model (format {meta.get('format')!r})")
    config = Poly4DGSConfig.model_validate_json(meta["volcap.config"])
    tensors = st_load(data)  # views on read-only buffers: own the memory (writable, aligned)
    return Poly4DGS(config, {k: v.to(device).clone() for k, v in tensors.items()})
