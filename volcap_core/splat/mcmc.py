"""3DGS-MCMC (Kheradmand et al. 2024) for Poly4DGS, in torch (the position noise of float32 CPU
models in one compiled pass: :mod:`volcap_core.splat.mcmc_numba`).

What it does, with the defaults of :class:`MCMCConfig` (gsplat's ``MCMCStrategy`` values):

* **Relocation** every ``refine_every`` = 100 steps in ``[refine_start, refine_stop)``: Gaussians
  whose peak opacity ``o_0 < min_opacity`` (0.005) are dead; each is moved onto a live Gaussian
  sampled with probability ∝ ``o_0``. A live Gaussian sampled k times is split into N = k + 1
  (capped at 51) identical Gaussians whose composite matches the original:
  ``o_new = 1 - (1 - o)^(1/N)`` and ``s_new = o / D · s`` with
  ``D = Σ_{k<N} C(N, k+1) (-1)^k o_new^(k+1) / sqrt(k+1)`` (computed in float64: the alternating
  sum cancels badly in float32). All polynomial coefficients (motion, rotation, log-scale, temporal
  opacity, t0, SH) are copied; the Adam moments of the source and the destinations are reset.
* **Growth** at the same steps: ``grow_rate`` = 5% more Gaussians, sampled the same way, up to
  ``cap_max``.
* **SGLD noise** after every optimiser step:
  ``Δμ_0 = lr_μ · noise_lr · σ(-100 (o_0 - 0.005)) · Σ η / s²``
  with ``Σ = R diag(s_0)² Rᵀ`` (metres²), ``η ~ N(0, I)``, ``noise_lr = 5e5`` and ``s`` the scene
  scale (metres; ``lr_μ`` already includes it): nearly transparent Gaussians explore, opaque ones
  stay put. The ``/ s²`` makes the displacement relative to the scene equal to gsplat's in its
  normalised (scale ~1) world, for which ``noise_lr`` was tuned (derivation in
  :func:`inject_noise`).
* **Sampling toward the under-fit** (``gradient_weight`` > 0; ours, issue 28's "densification
  that responds to the under-fit regions of zoom views"): a source's weight ``o_0`` is multiplied
  by ``1 + gradient_weight · r / mean(r)``, ``r`` its means' RMS gradient as Adam's second moment
  holds it (an average over the last ~1/(1-β2) steps, at no cost): where the loss still pulls
  Gaussians, splits and copies go, as 3DGS's densification by gradient sends them. A 3D gradient
  is a pixel error times the camera's focal length over depth, so a zoom camera's under-fit face
  weighs most. A Gaussian whose moments were reset (just relocated or grown) weighs ``o_0``.
* **Nothing to sample from**: relocation and growth sample live Gaussians with a finite,
  positive ``o_0``; when there is none (all opacities underflowed to 0, or non-finite) they do
  nothing and return 0.
* **Regularisers** added to the loss: ``opacity_reg · mean(o_0) + scale_reg · mean(exp(s_0))``,
  0.01 each, pushing unused Gaussians towards death (and so relocation).

All randomness comes from the ``torch.Generator`` passed in (checkpointed by the trainer).
"""

from __future__ import annotations

import functools
import math

import torch
from pydantic import BaseModel, ConfigDict, Field, model_serializer

from volcap_core.checkpoint import AdamState
from volcap_core.splat.model import LOG_SCALE_MAX, LOG_SCALE_MIN, Poly4DGS
from volcap_core.splat.rasterize import quat_scale_to_covar

__all__ = ["MCMCConfig", "add_gaussians", "inject_noise", "mcmc_regulariser", "relocate_dead",
           "relocation_opacity_scale"]


class MCMCConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    cap_max: int = Field(1_000_000, gt=0, description="most Gaussians growth may reach")
    refine_start: int = Field(500, ge=0)
    refine_stop: int = Field(25_000, ge=0)
    refine_every: int = Field(100, gt=0)
    min_opacity: float = Field(0.005, gt=0, lt=1, description="o_0 below this is dead")
    grow_rate: float = Field(0.05, ge=0)
    noise_lr: float = Field(5e5, ge=0)
    opacity_reg: float = Field(0.01, ge=0)
    scale_reg: float = Field(0.01, ge=0)
    max_ratio: int = Field(51, ge=2, description="cap on N, the split count of one Gaussian")
    moving_weight: float = Field(1.0, gt=0, description="relocation and growth sample a moving Gaussian "
                                 "(finite lifespan) with this times the weight of a static one of the same "
                                 "opacity: > 1 spends the budget on the performers first")
    gradient_weight: float = Field(0.0, ge=0, description="relocation and growth sample a Gaussian with its "
                                   "opacity times 1 + this × its means' RMS gradient over the mean one (Adam's "
                                   "second moment): > 0 sends the budget where the loss still pulls; 0: off")

    @model_serializer(mode="wrap")
    def _omit_off_options(self, handler):
        # off, the field is left out of the JSON: configs (a train-segment key, a stored record's
        # config) written before it existed keep their bytes
        out = handler(self)
        if isinstance(out, dict) and out.get("gradient_weight") == 0.0:
            del out["gradient_weight"]
        return out

    def is_refine_step(self, step: int) -> bool:
        """True after optimiser step ``step`` (1-based) when relocation and growth run."""
        return self.refine_start <= step < self.refine_stop and step % self.refine_every == 0


@functools.lru_cache(maxsize=4)
def _binomials(n_max: int) -> torch.Tensor:
    """``[n_max + 1, n_max + 1]`` float64 table, ``C(n, k)``."""
    t = torch.zeros(n_max + 1, n_max + 1, dtype=torch.float64)
    for n in range(n_max + 1):
        for k in range(n + 1):
            t[n, k] = math.comb(n, k)
    return t


def relocation_opacity_scale(opacities: torch.Tensor, scales: torch.Tensor, ratios: torch.Tensor,
                             *, max_ratio: int = 51) -> tuple[torch.Tensor, torch.Tensor]:
    """Opacity and scale of each of N copies so that N copies composite like the original.

    Args:
        opacities: ``[M]`` original opacities in (0, 1).
        scales: ``[M, 3]`` original scales (metres).
        ratios: ``[M]`` int N >= 1 (clamped to ``max_ratio``).
    Returns:
        ``(o_new [M], s_new [M, 3])`` in the input dtype; N = 1 returns the inputs unchanged.
    """
    n = ratios.clamp(1, max_ratio).to(torch.float64)
    o = opacities.to(torch.float64)
    o_new = 1.0 - (1.0 - o) ** (1.0 / n)
    k = torch.arange(max_ratio, dtype=torch.float64, device=o.device)           # [R]
    binom = _binomials(max_ratio).to(o.device)[n.long()][:, 1:]                    # C(N, k+1)
    terms = binom * (-1.0) ** k * o_new[:, None] ** (k + 1) / torch.sqrt(k + 1)
    terms = torch.where(k[None] < n[:, None], terms, 0.0)
    denom = terms.sum(dim=1)
    coef = o / denom
    return o_new.to(opacities.dtype), (coef[:, None] * scales.to(torch.float64)).to(scales.dtype)


def _sampleable(model: Poly4DGS) -> torch.Tensor:
    """``[N]`` bool: Gaussians that may be sampled as a source, i.e. whose opacity logit is finite
    and whose ``o_0`` is finite and > 0 (an ``o_0`` underflowed to 0 has nothing to give; a NaN or
    ±inf one must never be copied)."""
    logit = model.params["opacities"].detach()
    o0 = torch.sigmoid(logit)
    return torch.isfinite(logit) & torch.isfinite(o0) & (o0 > 0)


def _sample_by_opacity(o0: torch.Tensor, candidates: torch.Tensor, n: int,
                       generator: torch.Generator) -> torch.Tensor | None:
    """``n`` indices drawn from ``candidates`` with probability ∝ ``o0``; None when the weights
    do not sum to a positive finite number (nothing alive to sample from): no 0/0 and no
    ``torch.multinomial`` error, and no draw is taken from ``generator`` then."""
    # sampled on the CPU with the (CPU) generator whatever the device: one RNG stream to checkpoint
    probs = o0[candidates].detach().to("cpu", torch.float64)
    probs = torch.where(torch.isfinite(probs) & (probs > 0), probs, 0.0)
    total = float(probs.sum())
    if n <= 0 or not (0.0 < total < math.inf):
        return None
    pick = torch.multinomial(probs / total, n, replacement=True, generator=generator)
    return candidates[pick.to(candidates.device)]


def _source_weight(model: Poly4DGS, o0: torch.Tensor, cfg: MCMCConfig,
                   adam: AdamState | None = None) -> torch.Tensor:
    """``[N]`` sampling weight of each Gaussian as a relocation/growth source: ``o_0``, times
    ``cfg.moving_weight`` for the moving ones (a lifespan: ``log λ_1`` above the static value),
    times ``1 + cfg.gradient_weight · r / mean(r)`` with ``r`` the means' RMS gradient from
    ``adam`` (module doc). At ``moving_weight`` 1 (or a model without lifespans) and
    ``gradient_weight`` 0 (or no Adam state) it is ``o0`` itself: the draws of every run before
    the weights existed."""
    w = o0
    if cfg.moving_weight != 1.0 and "log_lambdas" in model.params:
        w = torch.where(model.moving(), w * cfg.moving_weight, w)
    if cfg.gradient_weight and adam is not None and "means" in adam.exp_avg_sq:
        r = adam.exp_avg_sq["means"].detach().sum(dim=1).sqrt()
        ok = torch.isfinite(r)
        mean = float(r[ok].mean()) if bool(ok.any()) else 0.0
        if mean > 0.0:
            w = w * (1.0 + cfg.gradient_weight * torch.where(ok, r, 0.0) / mean)
    return w


@torch.no_grad()
def _split_into(model: Poly4DGS, sampled: torch.Tensor, cfg: MCMCConfig) -> None:
    """Set the opacity and scale of each sampled Gaussian to its share of the split."""
    p = model.params
    ratios = torch.bincount(sampled, minlength=len(model))[sampled] + 1
    o0 = torch.sigmoid(p["opacities"][sampled])
    s0 = torch.exp(p["scales"][sampled])
    o_new, s_new = relocation_opacity_scale(o0, s0, ratios, max_ratio=cfg.max_ratio)
    eps = torch.finfo(torch.float32).eps
    o_new = o_new.clamp(min=cfg.min_opacity, max=1.0 - eps)
    p["opacities"][sampled] = torch.logit(o_new)
    # shift the whole log-scale polynomial: s_t scales by the same factor at every t
    p["scales"][sampled] = torch.log(s_new).clamp(LOG_SCALE_MIN, LOG_SCALE_MAX)


@torch.no_grad()
def relocate_dead(model: Poly4DGS, adam: AdamState | None, cfg: MCMCConfig,
                  generator: torch.Generator) -> int:
    """Move dead Gaussians (``o_0 < min_opacity``) onto live ones sampled by opacity.

    A Gaussian whose ``o_0`` is NaN counts as dead (it is overwritten by a live copy). Only live,
    finite Gaussians are sampled (:func:`_sampleable`); when there is none (every opacity dead or
    underflowed to 0, or non-finite) nothing changes and 0 is returned.

    Modifies ``model.params`` (in place) and ``adam`` moments. Returns the number relocated.
    """
    p = model.params
    o0 = torch.sigmoid(p["opacities"])
    dead = ~(o0 >= cfg.min_opacity)                    # NaN is dead too
    n_dead = int(dead.sum())
    live = torch.nonzero(~dead & _sampleable(model)).squeeze(1)
    if n_dead == 0 or len(live) == 0:
        return 0
    dead_idx = torch.nonzero(dead).squeeze(1)
    sampled = _sample_by_opacity(_source_weight(model, o0, cfg, adam), live, n_dead, generator)
    if sampled is None:
        return 0
    _split_into(model, sampled, cfg)
    for t in p.values():
        t[dead_idx] = t[sampled]
    if adam is not None:
        for moments in (adam.exp_avg, adam.exp_avg_sq):
            for name in p:
                moments[name][sampled] = 0
                moments[name][dead_idx] = 0
    return n_dead


@torch.no_grad()
def add_gaussians(model: Poly4DGS, adam: AdamState | None, cfg: MCMCConfig,
                  generator: torch.Generator) -> int:
    """Grow by ``grow_rate`` (up to ``cap_max``): sampled Gaussians split, the copies are appended.

    Only finite Gaussians with ``o_0 > 0`` are sampled (:func:`_sampleable`); when there is none
    (every opacity underflowed to 0, or non-finite) nothing changes and 0 is returned.

    Replaces the tensors of ``model.params`` (new leaves, same ``requires_grad``) and extends the
    Adam moments with zeros. Returns the number added.
    """
    n = len(model)
    n_new = max(0, min(cfg.cap_max, int((1.0 + cfg.grow_rate) * n)) - n)
    if n_new == 0:
        return 0
    p = model.params
    o0 = torch.sigmoid(p["opacities"])
    sampled = _sample_by_opacity(_source_weight(model, o0, cfg, adam), torch.nonzero(_sampleable(model)).squeeze(1),
                                 n_new, generator)
    if sampled is None:
        return 0
    _split_into(model, sampled, cfg)
    for name, t in list(p.items()):
        grown = torch.cat([t.detach(), t.detach()[sampled]]).requires_grad_(t.requires_grad)
        p[name] = grown
    if adam is not None:
        for moments in (adam.exp_avg, adam.exp_avg_sq):
            for name in p:
                m = moments[name]
                m[sampled] = 0
                moments[name] = torch.cat([m, m.new_zeros((n_new, *m.shape[1:]))])
    return n_new


@torch.no_grad()
def inject_noise(model: Poly4DGS, lr_means: float, cfg: MCMCConfig,
                 generator: torch.Generator, *, scene_scale: float = 1.0) -> None:
    """SGLD exploration of μ_0, in place:
    ``Δμ_0 = lr_means · noise_lr · σ(-100 (o_0 - min_opacity)) · Σ η / scene_scale²``.

    Why ``/ s²`` (``s = scene_scale``, metres): gsplat's ``noise_lr = 5e5`` is tuned for a scene
    normalised to scale ~1. Normalising ours, ``x' = x / s``, gives ``Σ' = Σ / s²`` and a means
    learning rate ``lr' = lr_means / s`` (the trainer passes ``lr_means`` already multiplied by
    ``s``). gsplat's step in that world is ``Δ' = lr' · noise_lr · gate · Σ' η``; in metres
    ``Δ = s Δ' = s · (lr_means / s) · noise_lr · gate · (Σ / s²) η
    = lr_means · noise_lr · gate · Σ η / s²``. So the displacement relative to the scene is
    gsplat's, whatever unit the scene is in: scaling the scene (means, scales) by ``k`` with
    ``lr_means`` and ``scene_scale`` scaled by ``k`` scales the noise by exactly ``k``. Without
    it (``s = 1`` on a scene in metres) the noise is ``s²`` times too strong relative to the
    scene (~40-50x on a ~7 m stage).

    Args:
        model: the model; ``params["means"]`` is modified.
        lr_means: learning rate of the means this step (metres, scene scale included).
        cfg: ``noise_lr``, ``min_opacity``.
        generator: the RNG of ``η``.
        scene_scale: the scene's scale ``s`` (metres), the one ``lr_means`` was multiplied by.

    float32 CPU Gaussians move by the compiled kernel of :mod:`volcap_core.splat.mcmc_numba`
    where numba imports (covariance, product and move fused in one pass, the same bits as the
    torch code here, which moves every other model: CUDA, float64, no numba).
    """
    if cfg.noise_lr <= 0 or lr_means <= 0:
        return
    if not (scene_scale > 0 and math.isfinite(scene_scale)):
        raise ValueError(f"scene_scale must be positive and finite, got {scene_scale}")
    p = model.params
    o0 = torch.sigmoid(p["opacities"])
    gate = torch.sigmoid(-100.0 * (o0 - cfg.min_opacity))
    scales = torch.exp(p["scales"].clamp(LOG_SCALE_MIN, LOG_SCALE_MAX))
    eta = torch.randn(p["means"].shape, generator=generator,
                      dtype=p["means"].dtype).to(p["means"].device)
    step = lr_means * cfg.noise_lr / (scene_scale * scene_scale)
    gated_step = gate * step
    compiled = _compiled_noise() if p["means"].device.type == "cpu" else None
    if compiled is not None and compiled.takes(p["means"], p["quats"], scales, eta, gated_step):
        compiled.add_position_noise(p["means"], p["quats"], scales, eta, gated_step)
        return
    cov = quat_scale_to_covar(p["quats"], scales)
    noise = (cov @ (eta * gated_step[:, None])[..., None])[..., 0]
    p["means"].add_(noise)


@functools.cache
def _compiled_noise():
    """:mod:`volcap_core.splat.mcmc_numba`, imported on first use (importing numba costs ~0.5 s,
    which a process that never trains on a CPU should not pay); None where numba does not import."""
    try:
        from volcap_core.splat import mcmc_numba
    except ImportError:
        return None
    return mcmc_numba


def mcmc_regulariser(model: Poly4DGS, cfg: MCMCConfig) -> torch.Tensor:
    """``opacity_reg · mean(o_0) + scale_reg · mean(exp(s_0))`` (differentiable scalar)."""
    p = model.params
    loss = p["means"].new_zeros(())
    if cfg.opacity_reg:
        loss = loss + cfg.opacity_reg * torch.sigmoid(p["opacities"]).mean()
    if cfg.scale_reg:
        loss = loss + cfg.scale_reg * torch.exp(p["scales"].clamp(LOG_SCALE_MIN,
                                                                  LOG_SCALE_MAX)).mean()
    return loss
