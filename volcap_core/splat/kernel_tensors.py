"""The tensors the compiled CPU kernels (``splat/*_numba.py``) take: the check that they are
float32 on the CPU, and their numpy views.

One concept shared by the compiled compositor, projection, slice, colours and noise, so each says
the same thing about a wrong tensor and none copies what it need not: a kernel reads and writes
numpy arrays that share the tensors' memory (contiguous tensors are not copied).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

__all__ = ["as_arrays", "require_float32_cpu"]


def require_float32_cpu(what: str, tensors: Mapping[str, torch.Tensor]) -> None:
    """Raise ``ValueError`` naming the first of ``tensors`` (name -> tensor) that is not float32
    on the CPU: ``"the numba {what} take(s) float32 CPU tensors: {name} is {dtype} on {device}"``."""
    for name, t in tensors.items():
        if t.dtype != torch.float32 or t.device.type != "cpu":
            raise ValueError(f"the numba {what} takes float32 CPU tensors: {name} is {t.dtype} on {t.device}")


def as_arrays(*tensors: torch.Tensor) -> list[np.ndarray]:
    """Contiguous numpy views of ``tensors`` (detached; copied only where not contiguous)."""
    return [t.detach().contiguous().numpy() for t in tensors]
