"""A camera at an instant, as the renderers take it: :class:`ViewSpec`.

One small record below every layer that renders or plans views (``segment.py``'s renders, shots,
the Face Rig's camera paths), so none of them imports another for it.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

__all__ = ["ViewSpec"]


class ViewSpec(BaseModel):
    """A camera at an instant: OpenCV intrinsics (top-left pixel centre at 0) and world-to-camera."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    K: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
    world_to_camera: tuple[tuple[float, float, float, float], ...]
    width: int
    height: int
    time_s: float
