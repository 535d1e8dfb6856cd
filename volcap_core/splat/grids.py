"""Per-camera exposure and black-level grids (paper eqs. 1-3).

Each training camera has two ``[3, 32, 32]`` grids, exposure ``E`` (starts at 1) and black level
``B`` (starts at 0), per colour channel. They are upsampled to the image size by FFT zero-padding
(band-limited, periodic interpolation: exact at the grid samples, a constant grid gives a constant
image) and applied to the rasterized linear colour::

    C_adjusted = (C_rast + B↑) · E↑

They absorb what is not the scene: lens glare (an additive veil, B) and sensor/vignetting gain (E).
Novel views render without them, or with a chosen camera's.

The FFT zero-padding upsample of an ``h × w`` grid to ``H × W`` is linear and separable, so it
equals ``U_H · g · U_Wᵀ`` with fixed matrices ``U_H [H, h]`` and ``U_W [W, w]``:
:func:`upsample_grid` uses that (two small matmuls, ~10x cheaper than FFTs at 1080p, with a trivial
backward);
:func:`fft_upsample` is the FFT form, kept as the reference the matrices are tested against.
Periodicity means the right edge of the image interpolates towards the left edge (and bottom to
top), a property of the paper's FFT upsampling that we keep.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

__all__ = [
    "GRID_SIZE",
    "ExposureGrids",
    "apply_grids",
    "black_level_regulariser",
    "exposure_regulariser",
    "fft_upsample",
    "upsample_grid",
    "upsample_matrix",
]

GRID_SIZE = 32


def _resample_spectrum(X: torch.Tensor, n_out: int, dim: int) -> torch.Tensor:
    """Zero-pad (or truncate) a complex spectrum along ``dim`` from ``n_in`` to ``n_out`` bins,
    splitting an even-length Nyquist bin in two halves when upsampling (scipy.signal.resample's
    rule; without the split the result is not real and not exact at the samples)."""
    n_in = X.shape[dim]
    X = X.movedim(dim, -1)
    Y = X.new_zeros(*X.shape[:-1], n_out)
    n = min(n_in, n_out)
    nyq = n // 2 + 1
    Y[..., :nyq] = X[..., :nyq]
    if n > 2:
        Y[..., nyq - n:] = X[..., nyq - n:]
    if n % 2 == 0:
        if n_out < n_in:
            Y[..., -n // 2] += X[..., -n // 2]
        elif n_out > n_in:
            Y[..., n // 2] *= 0.5
            Y[..., n_out - n // 2] = Y[..., n // 2]
    return Y.movedim(-1, dim)


def fft_upsample(grid: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Reference FFT zero-padding resample (the paper's operation).

    Args:
        grid: ``[..., h, w]`` real.
        height, width: output size.
    Returns:
        ``[..., height, width]`` real; sample ``(i·height/h, j·width/w)`` equals ``grid[i, j]``
        whenever those are integers.
    """
    h, w = grid.shape[-2:]
    X = torch.fft.fft2(grid.to(torch.complex128 if grid.dtype == torch.float64
                               else torch.complex64))
    X = _resample_spectrum(_resample_spectrum(X, height, -2), width, -1)
    return torch.fft.ifft2(X).real.to(grid.dtype) * (height * width / (h * w))


@functools.lru_cache(maxsize=64)
def _matrix_cpu64(n_in: int, n_out: int) -> torch.Tensor:
    eye = torch.eye(n_in, dtype=torch.complex128)
    X = torch.fft.fft(eye, dim=0)                        # spectra of the unit vectors, columns
    Y = _resample_spectrum(X, n_out, 0)
    return torch.fft.ifft(Y, dim=0).real * (n_out / n_in)  # [n_out, n_in]


def upsample_matrix(n_in: int, n_out: int, *, dtype=torch.float32,
                    device: torch.device | str = "cpu") -> torch.Tensor:
    """``U [n_out, n_in]`` such that ``U @ x`` is the 1D FFT zero-padding resample of ``x``
    (computed once in float64 and cached)."""
    return _matrix_cpu64(n_in, n_out).to(device=device, dtype=dtype)


def upsample_grid(grid: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """FFT zero-padding upsample as ``U_H · g · U_Wᵀ``.

    Args:
        grid: ``[..., h, w]``.
    Returns:
        ``[..., height, width]``, equal to :func:`fft_upsample` up to rounding.
    """
    h, w = grid.shape[-2:]
    U_h = upsample_matrix(h, height, dtype=grid.dtype, device=grid.device)
    U_w = upsample_matrix(w, width, dtype=grid.dtype, device=grid.device)
    return U_h @ grid @ U_w.T


def apply_grids(rgb: torch.Tensor, exposure: torch.Tensor | None,
                black: torch.Tensor | None) -> torch.Tensor:
    """``(C_rast + B↑) · E↑`` (paper eq. 2).

    Args:
        rgb: ``[H, W, 3]`` rasterized linear colour.
        exposure: ``[3, h, w]`` exposure grid (unitless gain) or None (= 1).
        black: ``[3, h, w]`` black-level grid (linear radiance offset) or None (= 0).
    Returns:
        ``[H, W, 3]`` adjusted linear colour.
    """
    H, W = rgb.shape[:2]
    if black is not None:
        rgb = rgb + upsample_grid(black, H, W).permute(1, 2, 0)
    if exposure is not None:
        rgb = rgb * upsample_grid(exposure, H, W).permute(1, 2, 0)
    return rgb


def exposure_regulariser(exposure: torch.Tensor) -> torch.Tensor:
    """``L_exposure = (mean(E) - 1)²`` over all cameras, channels and grid cells.

    The mean of the upsampled image equals the grid mean (zero-padding keeps the DC term), so the
    grid is used directly. Args: exposure ``[..., 3, h, w]``. Returns a scalar."""
    return (exposure.mean() - 1.0) ** 2


def black_level_regulariser(black: torch.Tensor) -> torch.Tensor:
    """``L_black = -mean(B)`` of the current view's grid (rewards explaining a uniform veil with
    B rather than with floaters). Args: black ``[3, h, w]``. Returns a scalar."""
    return -black.mean()


@dataclass
class ExposureGrids:
    """Grids of a set of cameras.

    Attributes:
        camera_ids: camera id per row.
        exposure: ``[C, 3, h, w]``, starts at 1.
        black: ``[C, 3, h, w]``, starts at 0.
    """

    camera_ids: list[str]
    exposure: torch.Tensor
    black: torch.Tensor

    @classmethod
    def identity(cls, camera_ids: list[str], size: int = GRID_SIZE,
                 device: torch.device | str = "cpu") -> "ExposureGrids":
        c = len(camera_ids)
        return cls(list(camera_ids), torch.ones(c, 3, size, size, device=device),
                   torch.zeros(c, 3, size, size, device=device))

    def index(self, camera_id: str) -> int:
        return self.camera_ids.index(camera_id)

    def apply(self, rgb: torch.Tensor, camera_id: str) -> torch.Tensor:
        """Adjust ``rgb [H, W, 3]`` with camera ``camera_id``'s grids."""
        i = self.index(camera_id)
        return apply_grids(rgb, self.exposure[i], self.black[i])
