"""Compiled CPU assembly of the bundle adjustment's normal equations (numba): the per-observation
blocks summed into the cameras' and points' blocks, and the points' elimination (Schur complement),
what :func:`volcap_core.calibration.bundle._reduced_system` computes with batched products and
``index_add_``.

Why it exists: the torch code forms every observation's ``JcᵀJc``, ``JpᵀJp``, ``JcᵀJp`` and, for every
ordered pair of observations of one point, the block ``Hcp[a] Hpp⁻¹ Hcp[b]ᵀ`` ([n, n], n = 9-11
camera parameters), each as a batched product of tiny float64 matrices (~1-2 µs a matrix on one
core, transposed operands copied first), and keeps them all in memory before summing them: a
calibration's step-5 adjustment (the lego capture's ~58 000 guided observations, ~300 000 pairs)
spent most of every Levenberg-Marquardt iteration there. Here each block is summed where it
belongs as it is formed.

The torch code's bits: each entry of a product is a sum of its two (observation blocks) or three
(point blocks) products from 0, in order (torch's batched product of such small matrices computes
them so, float64, without fused multiply-adds, as numba without ``fastmath``), and the blocks are
added in the observations' (pairs') order, as ``index_add_`` adds them. Serial: one thread writes
every block, so the bits do not depend on the thread count.

Imports numba: :mod:`volcap_core.calibration.bundle` imports it on first use, for CPU tensors,
where numba imports.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["add_observation_blocks", "subtract_point_blocks"]


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


@numba.njit(cache=True, inline="always")
def _dot2(a0, a1, b0, b1):
    """``a·b`` of two 2-vectors as torch's small batched product sums it: from 0, in order."""
    acc = 0.0
    acc += a0 * b0
    acc += a1 * b1
    return acc


@numba.njit(cache=True)
def _observations(Jc, Jp, rw, oc, op, Hcc, gc, Hpp, gp, Hcp):
    m_count, _, n = Jc.shape
    for m in range(m_count):
        c = oc[m]
        p = op[m]
        for i in range(n):
            for j in range(n):
                Hcc[c, i, j] += _dot2(Jc[m, 0, i], Jc[m, 1, i], Jc[m, 0, j], Jc[m, 1, j])
            gc[c, i] += _dot2(Jc[m, 0, i], Jc[m, 1, i], rw[m, 0], rw[m, 1])
            for j in range(3):
                Hcp[m, i, j] = _dot2(Jc[m, 0, i], Jc[m, 1, i], Jp[m, 0, j], Jp[m, 1, j])
        for i in range(3):
            for j in range(3):
                Hpp[p, i, j] += _dot2(Jp[m, 0, i], Jp[m, 1, i], Jp[m, 0, j], Jp[m, 1, j])
            gp[p, i] += _dot2(Jp[m, 0, i], Jp[m, 1, i], rw[m, 0], rw[m, 1])


def add_observation_blocks(Jc: np.ndarray, Jp: np.ndarray, rw: np.ndarray, oc: np.ndarray, op: np.ndarray,
                           Hcc: np.ndarray, gc: np.ndarray, Hpp: np.ndarray, gp: np.ndarray) -> np.ndarray:
    """Each observation's weighted blocks added into the cameras' and points' blocks, in place:
    ``Hcc[oc] += JcᵀJc``, ``gc[oc] += Jcᵀ rw``, ``Hpp[op] += JpᵀJp``, ``gp[op] += Jpᵀ rw``.

    Args:
        Jc: ``[M, 2, n]`` float64, the weighted residuals' derivatives by the camera parameters.
        Jp: ``[M, 2, 3]`` float64, by the point.
        rw: ``[M, 2]`` float64, the weighted residuals.
        oc, op: ``[M]`` int64, each observation's camera and point.
        Hcc ``[C, n, n]``, gc ``[C, n]``, Hpp ``[P, 3, 3]``, gp ``[P, 3]``: float64, added into.
    Returns:
        ``Hcp [M, n, 3]`` float64, each observation's ``JcᵀJp``.
    """
    Hcp = np.empty((Jc.shape[0], Jc.shape[2], 3))
    _observations(np.ascontiguousarray(Jc), np.ascontiguousarray(Jp), np.ascontiguousarray(rw),
                  np.ascontiguousarray(oc, np.int64), np.ascontiguousarray(op, np.int64), Hcc, gc, Hpp, gp, Hcp)
    return Hcp
