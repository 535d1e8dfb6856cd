"""A camera at an instant, as the renderers take it: :class:`ViewSpec`.

One small record below every layer that renders or plans views (``segment.py``'s renders, shots,
the Face Rig's camera paths), so none of them imports another for it.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, model_serializer, model_validator

__all__ = ["ViewSpec"]


class ViewSpec(BaseModel):
    """A camera at an instant: OpenCV intrinsics (top-left pixel centre at 0) and world-to-camera.

    ``near_m``: the near clipping plane (metres of camera depth): what lies nearer is not drawn.
    None: the renderer's default (:class:`~volcap_core.splat.camera.Camera`'s). The Face Rig's
    camera paths set it so that nothing between the path camera and the head is drawn
    (``docs/enhancer.md``, "Camera paths"); :func:`~volcap_core.splat_pairs.render_path` and the
    ``render-views`` task honour it (through ``reconstruction.splat_camera``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    K: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
    world_to_camera: tuple[tuple[float, float, float, float], ...]
    width: int
    height: int
    time_s: float
    near_m: float | None = None

    @model_validator(mode="after")
    def _check(self) -> "ViewSpec":
        if self.near_m is not None and not 0 < self.near_m < float("inf"):
            raise ValueError(f"view at {self.time_s} s: near_m must be a positive finite depth, got {self.near_m}")
        return self

    @model_serializer(mode="wrap")
    def _without_unset_near(self, handler):
        # a view without a near plane serialises as it did before the field existed, so the cache
        # keys of everything that renders such views (render-views, shots) stay what they were
        data = handler(self)
        if isinstance(data, dict) and data.get("near_m", 0) is None:
            del data["near_m"]
        return data
