"""Laplacian pyramids in torch with OpenCV's ``pyrDown``/``pyrUp`` convention, and the paper's
low-frequency swap.

Convention (the same numbers as ``cv2.pyrDown`` / ``cv2.pyrUp`` on float32, tested against OpenCV):

* ``pyr_down``: 5-tap binomial filter ``[1, 4, 6, 4, 1] / 16`` along each axis, ``BORDER_REFLECT_101``
  (``dcb|abcd|cba``), keep the even rows and columns: a ``W × H`` image becomes
  ``(W + 1) // 2 × (H + 1) // 2``.
* ``pyr_up(x, (h, w))``: insert zeros at the odd positions of a ``2W × 2H`` grid, filter with
  ``[1, 4, 6, 4, 1] / 8`` along each axis (reflect-101 on the enlarged grid), crop to the explicit
  size of the finer level (``h ∈ {2H - 1, 2H}``). Computed in polyphase form (even outputs
  ``(s[i-1] + 6 s[i] + s[i+1]) / 8``, odd outputs ``(s[i] + s[i+1]) / 2``; on the source, reflect-101
  on the first side and edge replication on the last side, which is what reflect-101 on the
  zero-stuffed grid amounts to), so no ``4×`` zero-stuffed tensor is allocated.

Level counting: ``laplacian_pyramid(x, levels)`` does ``levels`` ``pyr_down`` steps and returns
``levels + 1`` tensors: ``levels`` band-pass (detail) levels, finest first, and the low-pass residual
last. With ``levels = 5`` (the paper's "5-level Laplacian pyramid") a 3840×2160 frame has a
**120×68** lowest level (3840→1920→960→480→240→120, 2160→1080→540→270→135→68), the size the paper
states; :func:`pyramid_sizes` gives the sizes without allocating anything.

Tensors are ``[..., H, W]`` (any leading dims: ``[C, H, W]`` or ``[B, C, H, W]``), floating point;
filtering is done in the input dtype (float32: same values as OpenCV to float rounding). The work
is memory-bound and elementwise: seconds on one CPU thread for a 4K frame, trivial on a GPU
(``docs/enhancer.md``).
"""

from __future__ import annotations

import torch

__all__ = ["laplacian_pyramid", "lowpass", "pyr_down", "pyr_up", "pyramid_sizes", "reconstruct", "swap_low_frequency"]


def pyramid_sizes(height: int, width: int, levels: int) -> list[tuple[int, int]]:
    """``(h, w)`` of every level of a ``levels``-step pyramid of an ``height × width`` image, finest
    first (``levels + 1`` entries; the last is the low-pass residual)."""
    if height < 1 or width < 1:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    if levels < 0:
        raise ValueError(f"levels must be >= 0, got {levels}")
    sizes = [(height, width)]
    for _ in range(levels):
        h, w = sizes[-1]
        sizes.append(((h + 1) // 2, (w + 1) // 2))
    return sizes


def _reflect101(n: int, pad: int, device: torch.device) -> torch.Tensor:
    """Indices ``-pad .. n + pad - 1`` mapped into ``[0, n)`` with OpenCV's BORDER_REFLECT_101
    (a length-1 axis maps everything to 0, as ``cv::borderInterpolate`` does)."""
    i = torch.arange(-pad, n + pad, device=device)
    if n == 1:
        return torch.zeros_like(i)
    period = 2 * (n - 1)
    i = torch.remainder(i, period)
    return torch.where(i >= n, period - i, i)


def _check(x: torch.Tensor) -> None:
    if not isinstance(x, torch.Tensor) or x.ndim < 2:
        raise ValueError("expected a tensor [..., H, W]")
    if not x.is_floating_point():
        raise TypeError(f"expected a floating-point tensor, got {x.dtype}")


def _down_axis(x: torch.Tensor, dim: int) -> torch.Tensor:
    n = x.shape[dim]
    p = x.index_select(dim, _reflect101(n, 2, x.device))  # length n + 4
    m = (n + 1) // 2
    # output j is centred on source 2j, i.e. on padded index 2j + 2: taps at 2j .. 2j + 4
    every_other = (slice(None),) * dim + (slice(None, None, 2),)

    def tap(k: int) -> torch.Tensor:
        return p.narrow(dim, k, 2 * m - 1)[every_other]

    return (tap(0) + tap(4) + 4.0 * (tap(1) + tap(3)) + 6.0 * tap(2)) * (1.0 / 16.0)


def pyr_down(x: torch.Tensor) -> torch.Tensor:
    """``cv2.pyrDown``: blur with ``[1,4,6,4,1]/16`` (reflect-101), keep even rows/columns.
    ``[..., H, W] -> [..., (H+1)//2, (W+1)//2]``."""
    _check(x)
    return _down_axis(_down_axis(x, x.ndim - 1), x.ndim - 2)


def _up_axis(x: torch.Tensor, dim: int, out: int) -> torch.Tensor:
    n = x.shape[dim]
    if out not in (2 * n - 1, 2 * n):
        raise ValueError(f"pyr_up: an axis of {n} px goes to {2 * n - 1} or {2 * n} px, not {out}")
    first = x.narrow(dim, 1 if n > 1 else 0, 1)    # reflect-101 on the first side
    last = x.narrow(dim, n - 1, 1)                  # edge replication on the last side
    p = torch.cat([first, x, last], dim)            # p[i + 1] = s[i], i = -1 .. n
    prev, cur, nxt = p.narrow(dim, 0, n), p.narrow(dim, 1, n), p.narrow(dim, 2, n)
    even = (prev + nxt + 6.0 * cur) * 0.125
    odd = (cur + nxt) * 0.5
    y = torch.stack([even, odd], dim + 1).flatten(dim, dim + 1)
    return y.narrow(dim, 0, out) if out != 2 * n else y


def pyr_up(x: torch.Tensor, size: tuple[int, int] | None = None) -> torch.Tensor:
    """``cv2.pyrUp(x, dstsize=(w, h))`` with ``size = (h, w)`` (default ``(2H, 2W)``); each output
    axis must be ``2n - 1`` or ``2n`` for an input axis of ``n``."""
    _check(x)
    h, w = size if size is not None else (2 * x.shape[-2], 2 * x.shape[-1])
    return _up_axis(_up_axis(x, x.ndim - 1, int(w)), x.ndim - 2, int(h))


def laplacian_pyramid(img: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """``levels`` band-pass levels ``L_k = G_k - pyr_up(G_{k+1}, size(G_k))`` (finest first) and the
    low-pass residual ``G_levels`` last: ``levels + 1`` tensors ``[..., h_k, w_k]``
    (sizes as :func:`pyramid_sizes`)."""
    _check(img)
    if levels < 0:
        raise ValueError(f"levels must be >= 0, got {levels}")
    pyr, g = [], img
    for _ in range(levels):
        low = pyr_down(g)
        pyr.append(g - pyr_up(low, (g.shape[-2], g.shape[-1])))
        g = low
    pyr.append(g)
    return pyr


def reconstruct(pyr: list[torch.Tensor]) -> torch.Tensor:
    """Inverse of :func:`laplacian_pyramid`: ``G_k = L_k + pyr_up(G_{k+1}, size(L_k))`` from the
    residual up; exact to float rounding."""
    if not pyr:
        raise ValueError("empty pyramid")
    g = pyr[-1]
    for band in reversed(pyr[:-1]):
        g = band + pyr_up(g, (band.shape[-2], band.shape[-1]))
    return g


def lowpass(img: torch.Tensor, levels: int) -> torch.Tensor:
    """The residual (lowest) level of a ``levels``-step pyramid: ``levels`` × :func:`pyr_down`."""
    _check(img)
    for _ in range(levels):
        img = pyr_down(img)
    return img


def swap_low_frequency(output: torch.Tensor, lq: torch.Tensor, levels: int = 5) -> torch.Tensor:
    """The paper's low-frequency stabilisation: the ``levels``-step Laplacian pyramid of ``output``
    with its lowest level (``120×68`` at 3840×2160 for ``levels = 5``) replaced by that of ``lq``,
    reconstructed. ``output``, ``lq``: ``[..., C, H, W]``, same shape. High frequencies (the band-pass
    levels) come from ``output``; global intensity and colour (the residual) from ``lq``."""
    if output.shape != lq.shape:
        raise ValueError(f"shape mismatch: output {tuple(output.shape)} vs lq {tuple(lq.shape)}")
    # reconstruct(bands(output) + [low(lq)]) = output + expand(low(lq) - low(output)) since the
    # reconstruction is linear and reconstruct(laplacian_pyramid(output)) = output: the same result
    # (to float rounding) without building the band-pass levels (at 4K, ~5x less work).
    _check(output)
    sizes = pyramid_sizes(output.shape[-2], output.shape[-1], levels)
    change = lowpass(lq.to(output.dtype), levels) - lowpass(output, levels)
    for size in reversed(sizes[:-1]):
        change = pyr_up(change, size)
    return output + change
