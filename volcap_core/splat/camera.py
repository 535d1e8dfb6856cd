"""The pinhole camera the splat renderer takes.

OpenCV convention throughout: camera x right, y down, z forward (looking along +z); pixel ``(u, v)``
has its centre at ``(u + 0.5, v + 0.5)`` in the intrinsics' pixel frame (gsplat's convention, also
COLMAP's). ``world_to_camera`` maps world points to that camera frame: ``x_c = R x_w + t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from volcap_core.calibration.geometry import look_at_rotation

__all__ = ["Camera", "look_at"]


def _tensor(x, dtype=torch.float32) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(dtype)
    return torch.as_tensor(np.asarray(x), dtype=dtype)


@dataclass(frozen=True)
class Camera:
    """One view.

    Attributes:
        K: ``[3, 3]`` intrinsics in pixels: ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.
        world_to_camera: ``[4, 4]`` rigid transform, OpenCV axes (x right, y down, z forward).
        width, height: image size in pixels.
        near, far: depth range in scene units (metres); Gaussians with camera-space depth
            ``z <= near`` or ``z >= far`` are culled (so nothing behind or at the camera plane is
            ever divided by its depth).
    """

    K: torch.Tensor
    world_to_camera: torch.Tensor
    width: int
    height: int
    near: float = 0.01
    far: float = 1e10

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _tensor(self.K))
        object.__setattr__(self, "world_to_camera", _tensor(self.world_to_camera))
        if self.K.shape != (3, 3) or self.world_to_camera.shape != (4, 4):
            raise ValueError(f"K must be [3,3] and world_to_camera [4,4], got "
                             f"{tuple(self.K.shape)} and {tuple(self.world_to_camera.shape)}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not 0 < self.near < self.far:
            raise ValueError(f"need 0 < near < far, got near={self.near} far={self.far}")

    @property
    def centre(self) -> torch.Tensor:
        """Camera centre in world coordinates ``[3]`` (``-Rᵀ t``)."""
        R = self.world_to_camera[:3, :3]
        return -R.T @ self.world_to_camera[:3, 3]

    def opencv_K(self) -> np.ndarray:
        """``[3, 3]`` float64 intrinsics with pixel centres at integers (OpenCV's, what depth
        buffers and projections to pixel indices round to): this camera's ``K`` (centres at +0.5,
        gsplat's convention) with ``cx, cy`` less half a pixel."""
        K = self.K.double().cpu().numpy().copy()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        return K

    def to(self, device: torch.device | str) -> "Camera":
        return replace(self, K=self.K.to(device), world_to_camera=self.world_to_camera.to(device))

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``factor`` times the resolution (intrinsics scaled about the
        pixel-corner origin, so pixel centres stay at +0.5)."""
        K = self.K.clone()
        K[:2] *= factor
        return replace(self, K=K, width=max(1, round(self.width * factor)),
                       height=max(1, round(self.height * factor)))


def look_at(eye, target, up=(0.0, 0.0, 1.0), *, fov_x_deg: float, width: int, height: int,
            near: float = 0.01, far: float = 1e10) -> Camera:
    """A camera at ``eye`` looking at ``target`` (world units), square pixels, centred principal
    point, horizontal field of view ``fov_x_deg`` degrees. ``up`` is the world direction that
    appears upward in the image (OpenCV's y axis points the other way); a camera looking along
    ``up`` or within ~2.6 degrees of it gets the fallback of
    :func:`volcap_core.calibration.geometry.look_at_rotation`, which builds the rotation."""
    eye = np.asarray(eye, dtype=np.float64)
    R = look_at_rotation(eye, target, up=up)  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    return Camera(K=K, world_to_camera=w2c, width=width, height=height, near=near, far=far)
