"""Compiled CPU Schur complement of the bundle adjustment (numba): the points' elimination from the
normal equations, what :func:`volcap_core.calibration.bundle._reduced_system` computes with
batched products and ``index_add_``.

Why it exists: for every ordered pair of observations of one point the torch code forms the block
``Hcp[a] Hpp⁻¹ Hcp[b]ᵀ`` ([n, n], n = 9-11 camera parameters) as a batched product of tiny matrices
(~2 µs a pair on one core) and keeps every block in memory before summing it into the reduced
camera system: a calibration's step-5 adjustment over ~300 000 pairs (the lego capture's guided
tracks) spent most of its time there, every Levenberg-Marquardt iteration. Here each pair's block
is summed into its camera pair's block of ``S`` as it is formed, nothing else is stored.

The torch code's bits: each entry of ``Hcp[a] Hpp⁻¹`` and of its product with ``Hcp[b]ᵀ`` is a
sum of three products from 0, in order (torch's batched product of 3-wide matrices computes them
so, float64, without fused multiply-adds, as numba without ``fastmath``), and the blocks are
subtracted from ``S`` in the pairs' order, as ``index_add_`` adds them. Serial: one thread writes
every block, so the bits do not depend on the thread count.

Imports numba: :mod:`volcap_core.calibration.bundle` imports it on first use, for CPU tensors,
where numba imports.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["subtract_point_blocks"]


@numba.njit(cache=True)
def _subtract(S, Hcp, Hpp_inv, oc, op, a, b, ncam):
    m_count, n, _ = Hcp.shape
    # T[m] = Hcp[m] Hpp_inv[op[m]]: [n, 3] per observation
    T = np.empty((m_count, n, 3))
    for m in range(m_count):
        p = op[m]
        for i in range(n):
            for j in range(3):
                acc = 0.0
                for k in range(3):
                    acc += Hcp[m, i, k] * Hpp_inv[p, k, j]
                T[m, i, j] = acc
    block = np.empty((n, n))
    for q in range(a.shape[0]):
        ia = a[q]
        ib = b[q]
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for k in range(3):
                    acc += T[ia, i, k] * Hcp[ib, j, k]
                block[i, j] = acc
        row = oc[ia] * ncam + oc[ib]
        for i in range(n):
            for j in range(n):
                S[row, i, j] += -block[i, j]


def subtract_point_blocks(S: np.ndarray, Hcp: np.ndarray, Hpp_inv: np.ndarray, oc: np.ndarray, op: np.ndarray,
                          a: np.ndarray, b: np.ndarray, ncam: int) -> None:
    """``S[oc[a] * ncam + oc[b]] -= Hcp[a] Hpp_inv[op[a]] Hcp[b]ᵀ`` for every pair, in place.

    Args:
        S: ``[C * C, n, n]`` float64, the reduced camera system's blocks (camera pair row-major).
        Hcp: ``[M, n, 3]`` float64, each observation's camera-point block of the normal equations.
        Hpp_inv: ``[P, 3, 3]`` float64, the inverse of each point's damped block.
        oc, op: ``[M]`` int64, each observation's camera and point.
        a, b: ``[Q]`` int64, the ordered pairs of observations of one point.
    """
    _subtract(S, np.ascontiguousarray(Hcp), np.ascontiguousarray(Hpp_inv), np.ascontiguousarray(oc, np.int64),
              np.ascontiguousarray(op, np.int64), np.ascontiguousarray(a, np.int64),
              np.ascontiguousarray(b, np.int64), int(ncam))
