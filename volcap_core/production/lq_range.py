"""The LQ range: how many Gaussians a Scene Rig reconstruction spends on an actor's head and
shoulders, frame by frame; its minimum and maximum bound the Face Rig's low-quality models.

The paper draws each LQ Face Rig model's Gaussian count "from 50,000 to 200,000 ... the minimum
and maximum number of Gaussians left when cropping the upper-body of actors in the Scene Rig
reconstructions", so that the enhancer learns to repair what a Scene Rig close-up will show.
:func:`upper_body_gaussian_counts` counts, for one actor, the Gaussians of a Scene Rig segment
model that are alive at each frame's time and whose centre is then inside the actor's upper-body
region (:class:`UpperBody`: a capsule hanging from the head position); :func:`lq_range` takes the
minimum and maximum over frames (and actors, segments).

Alive is what the renderer draws: :func:`volcap_core.splat.model.evaluate` at the frame's time
keeps the Gaussians whose opacity there (peak opacity × the temporal envelope, the lifespan) is
at least ``min_opacity``, by default :data:`~volcap_core.splat.model.ALPHA_MIN` (1/255: below it
a Gaussian cannot leave a fragment), and moves each to where it is at that time.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from volcap_core.splat.model import ALPHA_MIN, Poly4DGS, evaluate
from volcap_core.synth.ground_truth import head_at

__all__ = ["LQRange", "UpperBody", "ground_truth_heads", "lq_range", "upper_body_gaussian_counts"]


@dataclass(frozen=True)
class UpperBody:
    """An actor's head and shoulders around a head position: the points within ``radius_m`` of the
    segment from the head position down ``drop_m`` along ``-up`` (a capsule; metres, world).

    The defaults take in a standing adult's whole head (crown ~0.12 m above its centre, the
    synthetic actors' head semi-axes 0.08-0.115 m) and the shoulders (their tops ~0.2 m below the
    head centre, ~0.2 m to each side), and stop above the chest's middle: what a head-and-shoulders
    close-up frames."""

    radius_m: float = 0.25
    drop_m: float = 0.3
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        if not (0 < self.radius_m < math.inf and 0 <= self.drop_m < math.inf):
            raise ValueError(f"upper body: radius_m {self.radius_m} must be > 0 and drop_m {self.drop_m} >= 0")
        if not 0 < np.linalg.norm(self.up) < math.inf:
            raise ValueError(f"upper body: up {list(self.up)} must be a finite non-zero vector")

    def contains(self, points: torch.Tensor, head_m) -> torch.Tensor:
        """``points`` ``[N, 3]`` (metres) → ``[N]`` bool: inside the region of the head at
        ``head_m`` ``[3]``."""
        up = torch.tensor(self.up, dtype=points.dtype, device=points.device)
        up = up / up.norm()
        top = torch.as_tensor(np.asarray(head_m, np.float64), dtype=points.dtype, device=points.device)
        rel = points - top
        # the nearest point of the axis [top - drop·up, top]: its distance below the head, clamped
        below = (-(rel @ up)).clamp(0.0, self.drop_m)
        return (rel + below[:, None] * up).norm(dim=1) <= self.radius_m


def upper_body_gaussian_counts(models: Poly4DGS | Sequence[Poly4DGS], head_positions_m, times_s, *,
                               region: UpperBody | None = None, min_opacity: float = ALPHA_MIN) -> np.ndarray:
    """One actor's upper-body Gaussians of a Scene Rig reconstruction, per frame.

    Args:
        models: the segment model, or one model per frame (the segment that owns each frame: a
            performance's models differ across segments).
        head_positions_m: ``[F, 3]`` the actor's head centre at each frame (metres, world).
        times_s: ``[F]`` the frames' times (seconds on the take's clock, the models' clock).
        region: the upper body around each head position (default :class:`UpperBody`).
        min_opacity: a Gaussian counts at a time when its opacity there is at least this.
    Returns:
        ``[F]`` int64 counts.
    """
    region = region or UpperBody()
    heads = np.asarray(head_positions_m, np.float64)
    times = np.asarray(times_s, np.float64).reshape(-1)
    if heads.shape != (len(times), 3) or not np.all(np.isfinite(heads)):
        raise ValueError(f"upper-body counts: head_positions_m must be finite [{len(times)}, 3] "
                         f"(one per frame time), got shape {heads.shape}")
    per_frame = [models] * len(times) if isinstance(models, Poly4DGS) else list(models)
    if len(per_frame) != len(times):
        raise ValueError(f"upper-body counts: {len(per_frame)} models for {len(times)} frame times "
                         "(give one model, or one per frame)")
    counts = np.zeros(len(times), np.int64)
    with torch.no_grad():
        for i, (model, head, t) in enumerate(zip(per_frame, heads, times)):
            alive = evaluate(model, float(t), min_opacity=min_opacity)
            counts[i] = int(region.contains(alive.means, head).sum())
    return counts


@dataclass(frozen=True)
class LQRange:
    """The LQ range: ``low`` and ``high`` Gaussian counts (the minimum and maximum of the upper-body
    counts over every frame of every actor and segment measured) and ``frames``, how many counts
    they were taken over."""

    low: int
    high: int
    frames: int

    def to_json(self) -> dict:
        return {"low": self.low, "high": self.high, "frames": self.frames}


def lq_range(counts: np.ndarray | Iterable[np.ndarray]) -> LQRange:
    """The minimum and maximum of upper-body counts (:func:`upper_body_gaussian_counts`' arrays:
    one, or several: actors, segments). ``ValueError`` when there is no count."""
    if isinstance(counts, np.ndarray):
        counts = [counts]
    flat = np.concatenate([np.asarray(c, np.int64).reshape(-1) for c in counts] or [np.zeros(0, np.int64)])
    if flat.size == 0:
        raise ValueError("LQ range: no upper-body counts to take it from")
    return LQRange(low=int(flat.min()), high=int(flat.max()), frames=int(flat.size))


def ground_truth_heads(scene: Mapping, actor: int | None, times_s, *, where: str = "scene.json") -> np.ndarray:
    """A synthetic capture's true head centre of actor ``actor`` (``scene.json`` ``actors`` index;
    None: the capture's only actor) at each of ``times_s`` (seconds on the take's clock):
    ``[F, 3]`` metres (:func:`~volcap_core.synth.ground_truth.head_at`). The head positions a
    production measures the LQ range with where its Scene Rig capture is synthetic: a real capture
    has no head track yet. ``ValueError`` naming ``where`` for an actor it does not hold, or None
    where it holds several."""
    actors = scene.get("actors") or []
    if actor is None:
        if len(actors) != 1:
            raise ValueError(f"{where}: the ground truth holds {len(actors)} actors: say which one "
                             "(the production spec's actors[].index)")
        actor = 0
    if not 0 <= actor < len(actors):
        raise ValueError(f"{where}: no actor {actor} in the ground truth (it holds {len(actors)})")
    return np.array([head_at(actors[actor], float(t))["centre_m"] for t in np.asarray(times_s, np.float64).reshape(-1)],
                    np.float64).reshape(-1, 3)
