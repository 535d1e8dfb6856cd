"""Compiled CPU scores of the guided patch search (numba): the normalised cross-correlation of each
anchor's template with the other camera's image at every shift of the search grid, what
:func:`volcap_core.calibration.guided._match_patches` computes with ``_sample`` and ``_ncc``.

Why it exists: the torch code materialises every shifted template, ``[anchors, shifts, Q]``
bilinear samples (512 × 169 × 81 floats a chunk), then makes several passes over them to centre,
multiply and reduce: memory-bound, ~0.7 ms an anchor and camera on one core, which made the
matching most of a no-scan calibration's step 5. Here each score is one pass over the template's
``Q`` pixels, four image reads a pixel, and nothing is stored but the score.

The same scores to float32 rounding, not the same bits: the template is centred once (the mean of
the shifted samples then cancels from the cross term), the sums run in float64 and the sampled
window's variance is ``Σv² - (Σv)²/Q``; the bilinear sample is ``grid_sample``'s (``border``
padding: the position clamped to ``[0, W - 1]``, ``align_corners=False`` with the caller's
pixel-centre convention). Each anchor's scores are written by one thread and sum in a fixed order,
so they do not depend on the thread count (:mod:`volcap_core.kernel_threads`).

Imports numba: :mod:`volcap_core.calibration.guided` imports it on first use, where numba imports.
"""

from __future__ import annotations

import numba
import numpy as np

from volcap_core.kernel_threads import kernel_threads_scope

__all__ = ["shifted_ncc"]


@numba.njit(cache=True)
def _axis_taps(p, steps, size, lo, hi, frac):
    """The bilinear taps along one axis of a position ``p`` under every shift: the shifted
    position clamped to ``[0, size - 1]`` (``grid_sample``'s border padding), its lower and upper
    pixel (``lo``, ``hi``) and its fraction ``frac`` past ``lo``, written into the arrays given."""
    for j in range(steps.shape[0]):
        x = min(max(np.float64(p + steps[j]), 0.0), size - 1.0)
        lo[j] = int(x)                 # x >= 0: truncation is the floor
        hi[j] = min(lo[j] + 1, size - 1)
        frac[j] = x - lo[j]


@numba.njit(cache=True, parallel=True)
def _scores(image, template, warped, steps, out):
    """``out [n, S, S]``: NCC of each template with its window at every (y, x) shift. Per template
    pixel the image is interpolated along x once for each row the y shifts reach, then along y for
    each shift: a bilinear sample ``top + (bottom - top) fy`` with ``top = a + (b - a) fx``, the
    same arithmetic as one sample at a time, a quarter of the image reads."""
    H, W = image.shape
    n, q = template.shape
    ns = steps.shape[0]
    rows_max = int(np.ceil(steps[ns - 1] - steps[0])) + 3
    for i in numba.prange(n):
        mean = 0.0
        for k in range(q):
            mean += template[i, k]
        mean /= q
        centred = np.empty(q)
        tnorm2 = 0.0
        for k in range(q):
            centred[k] = template[i, k] - mean
            tnorm2 += centred[k] * centred[k]
        sv = np.zeros((ns, ns))
        svv = np.zeros((ns, ns))
        stv = np.zeros((ns, ns))
        x0 = np.empty(ns, np.int64)
        x1 = np.empty(ns, np.int64)
        fx = np.empty(ns)
        y0 = np.empty(ns, np.int64)
        y1 = np.empty(ns, np.int64)
        fy = np.empty(ns)
        row = np.empty((rows_max, ns))
        for k in range(q):
            _axis_taps(warped[i, k, 0], steps, W, x0, x1, fx)
            _axis_taps(warped[i, k, 1], steps, H, y0, y1, fy)
            r0 = y0[0]
            for r in range(y1[ns - 1] - r0 + 1):
                for jx in range(ns):
                    a = np.float64(image[r0 + r, x0[jx]])
                    row[r, jx] = a + (np.float64(image[r0 + r, x1[jx]]) - a) * fx[jx]
            c = centred[k]
            for jy in range(ns):
                t0 = y0[jy] - r0
                t1 = y1[jy] - r0
                for jx in range(ns):
                    top = row[t0, jx]
                    v = top + (row[t1, jx] - top) * fy[jy]
                    sv[jy, jx] += v
                    svv[jy, jx] += v * v
                    stv[jy, jx] += c * v
        tnorm = np.sqrt(tnorm2)
        for jy in range(ns):
            for jx in range(ns):
                vnorm = np.sqrt(max(svv[jy, jx] - sv[jy, jx] * sv[jy, jx] / q, 0.0))
                out[i, jy, jx] = stv[jy, jx] / (tnorm * vnorm + 1e-6)


def shifted_ncc(image: np.ndarray, template: np.ndarray, warped: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """NCC of each template with the image under every shift of the search grid.

    Args:
        image: ``[H, W]`` float32 (log luminance).
        template: ``[n, Q]`` float32, each anchor's values at its own camera.
        warped: ``[n, Q, 2]`` float32, the template's pixels mapped into this camera (OpenCV px).
        steps: ``[S]`` float32, the grid's shifts along each axis (px).
    Returns:
        ``[n, S, S]`` float32 scores, indexed ``[anchor, y shift, x shift]``.
    """
    image = np.ascontiguousarray(image, np.float32)
    template = np.ascontiguousarray(template, np.float32)
    warped = np.ascontiguousarray(warped, np.float32)
    steps = np.ascontiguousarray(steps, np.float32)
    out = np.empty((len(template), len(steps), len(steps)), np.float32)
    if len(template):
        with kernel_threads_scope():
            _scores(image, template, warped, steps, out)
    return out
