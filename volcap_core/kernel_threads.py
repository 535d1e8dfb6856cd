"""The thread count of volcap's compiled CPU kernels (numba), and the scope that runs them on it.

One concept: these kernels give the same bits on any number of threads (each output is written by
one thread, every sum runs in a fixed order), so unlike torch they may use every core while a
reproducible training keeps torch on one thread. Used by the splat kernels (the compositor
:mod:`volcap_core.splat.composite_numba` and its neighbours) and the calibration's guided matching
(:mod:`volcap_core.calibration.guided_numba`); a module at the bottom of ``volcap_core`` so any
layer's compiled kernels can share it. Imports numba: import it only where numba is used.
"""

from __future__ import annotations

import contextlib

import numba
import torch

__all__ = ["kernel_threads", "kernel_threads_scope"]


def kernel_threads() -> int:
    """The compiled kernels' thread count: ``NUMBA_NUM_THREADS`` (numba's own setting, all cores
    unless the environment caps it), whatever torch's.

    Why not torch's count: reproducible CPU training runs torch on one thread (the processes'
    ``OMP_NUM_THREADS=1``, ``volcap_core.checkpoint.deterministic_torch``), which leaves the other
    cores idle; these kernels give the same bits on any number of threads (each output written by
    one thread, every sum in a fixed order), so they take the cores back without breaking
    bit-identical resumption. A process sharing its machine (a worker per core) sets
    ``NUMBA_NUM_THREADS``.
    """
    return max(1, int(numba.config.NUMBA_NUM_THREADS))


@contextlib.contextmanager
def kernel_threads_scope():
    """Run the compiled kernels inside on :func:`kernel_threads` threads (numba's setting is per
    calling thread) and leave torch's own setting as it was.

    The restore matters: numba's OpenMP threading layer shares torch's OpenMP runtime, and
    starting its thread pool or widening it sets that runtime's thread count for torch too, which
    every later torch op would then use (on a shared 2-core machine a 1-thread caller's projection
    and binning ran ~20× slower after the first numba call), and a one-thread training would no
    longer be reproducible.
    """
    n = torch.get_num_threads()
    numba.set_num_threads(kernel_threads())
    try:
        yield
    finally:
        torch.set_num_threads(n)
