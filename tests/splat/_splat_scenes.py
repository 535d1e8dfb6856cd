"""Shared tiny scenes for the splat tests (imported by name: tests/splat is on sys.path)."""

import math

import torch

from volcap_core.splat.camera import Camera, look_at
from volcap_core.splat.model import Gaussians3D


def ring_cameras(n: int = 6, *, radius: float = 3.0, size: int = 32, fov: float = 40.0,
                 height: float = 0.6) -> list[Camera]:
    """``n`` cameras on a circle around the origin, looking at it (z up)."""
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = (radius * math.cos(a), radius * math.sin(a), height * (1 if i % 2 else -1))
        cams.append(look_at(eye, (0, 0, 0), fov_x_deg=fov, width=size, height=size))
    return cams


def random_gaussians(n: int, *, seed: int = 0, spread: float = 0.4, scale=(0.03, 0.12),
                     sh_degree: int = 1, dtype=torch.float32) -> Gaussians3D:
    g = torch.Generator().manual_seed(seed)
    K = (sh_degree + 1) ** 2
    sh = torch.randn(n, K, 3, generator=g, dtype=dtype) * 0.2
    sh[:, 0] = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) / 0.2820948
    return Gaussians3D(
        means=(torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * spread,
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=scale[0] + torch.rand(n, 3, generator=g, dtype=dtype) * (scale[1] - scale[0]),
        opacities=0.3 + 0.6 * torch.rand(n, generator=g, dtype=dtype),
        sh=sh, ids=torch.arange(n))
