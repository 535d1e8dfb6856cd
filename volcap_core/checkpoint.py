"""Training state that comes back bit for bit: what Poly4DGS segment training (``splat``) and
Detail Enhancer training (``enhance``) share to store their tensors and resume exactly.

One concept, three parts, each needed for "a resumed run ends with the bytes of an uninterrupted
one" and for "the same tensors make the same artifact digest":

- **bytes** — :func:`safetensors_bytes` writes safetensors whose bytes depend only on the tensors
  and the metadata; :func:`safetensors_metadata` reads the metadata back. Models, grids, prompts,
  pair sequences and training checkpoints are all stored so (no pickle).
- **optimiser state** — :class:`AdamState` and :func:`adam_step`, a functional Adam whose whole
  state is two dicts of tensors and a step count, so it goes into a checkpoint as tensors
  (:meth:`AdamState.to_tensors`, :meth:`AdamState.from_tensors`).
- **execution** — :func:`deterministic_torch`, the CPU setting under which the same inputs give the
  same bits.

It sits at the bottom of ``volcap_core`` (it imports nothing of it), so both ``splat`` and
``enhance`` import it downward and neither reaches into the other. Why each part is built as it is,
and what was measured, is in ``docs/poly4dgs.md`` ("Reproducibility").
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch

__all__ = ["AdamState", "adam_step", "deterministic_torch", "safetensors_bytes", "safetensors_metadata"]


# ------------------------------------------------------------------------------------------ bytes

#: torch dtype -> safetensors name, in the order of safetensors' ``Dtype`` enum (it lays tensors
#: out by that order, largest first, then by name)
_ST_DTYPES = {torch.bool: "BOOL", torch.uint8: "U8", torch.int8: "I8", torch.int16: "I16",
              torch.float16: "F16", torch.bfloat16: "BF16", torch.int32: "I32",
              torch.float32: "F32", torch.float64: "F64", torch.int64: "I64"}
_ST_RANK = {d: i for i, d in enumerate(_ST_DTYPES)}


def safetensors_bytes(tensors: Mapping[str, torch.Tensor],
                      metadata: Mapping[str, str] | None = None) -> bytes:
    """Safetensors bytes that depend only on the tensors and the metadata (readable by
    ``safetensors.torch.load``).

    Why not ``safetensors.torch.save``: it keeps the metadata in a Rust ``HashMap``, whose
    iteration order is randomised per map, so the same tensors with two metadata keys came out
    in one of two byte orders; a content-addressed store then sees two different artifacts. Here
    the header is JSON with sorted keys; tensors are laid out as safetensors does (by its dtype
    order, largest first, then by name, so every tensor is aligned); the header is space-padded
    to a multiple of 8 bytes. With at most one metadata key the bytes equal
    ``safetensors.torch.save``'s (tested).
    """
    items = []
    for name, t in tensors.items():
        if t.dtype not in _ST_DTYPES:
            raise ValueError(f"{name}: dtype {t.dtype} not supported")
        items.append((name, t.detach().to("cpu").contiguous()))
    items.sort(key=lambda kv: (-_ST_RANK[kv[1].dtype], kv[0]))
    header: dict = {}
    if metadata:
        header["__metadata__"] = {str(k): str(v) for k, v in sorted(metadata.items())}
    chunks, offset = [], 0
    for name, t in items:
        raw = t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b""
        header[name] = {"dtype": _ST_DTYPES[t.dtype], "shape": list(t.shape),
                        "data_offsets": [offset, offset + len(raw)]}
        chunks.append(raw)
        offset += len(raw)
    head = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    head += b" " * (-len(head) % 8)
    return len(head).to_bytes(8, "little") + head + b"".join(chunks)


def safetensors_metadata(data: bytes) -> dict[str, str]:
    """The ``__metadata__`` of safetensors bytes (8-byte little-endian header length, JSON);
    ``{}`` when there is none. Reads the header only."""
    if len(data) < 8:
        raise ValueError("truncated safetensors data")
    n = int.from_bytes(data[:8], "little")
    if n > len(data) - 8:
        raise ValueError("truncated safetensors header")
    return json.loads(data[8:8 + n]).get("__metadata__", {}) or {}


# ------------------------------------------------------------------------------- optimiser state

@dataclass
class AdamState:
    """First and second moments per parameter name (same shapes as the parameters), and the
    number of steps taken (one count for all: every group steps together).

    Why not ``torch.optim.Adam``: Poly4DGS's MCMC relocation resets the moments of individual
    Gaussians and growth appends rows, which with torch's optimizer means reaching into
    ``optimizer.state`` keyed by tensor identity; checkpoints must be safetensors (no pickle); and
    learning rates are a pure function of the step (no scheduler state). Here the state is plain
    tensors and an int."""

    exp_avg: dict[str, torch.Tensor] = field(default_factory=dict)
    exp_avg_sq: dict[str, torch.Tensor] = field(default_factory=dict)
    step: int = 0

    @classmethod
    def zeros_like(cls, params: Mapping[str, torch.Tensor]) -> "AdamState":
        return cls({k: torch.zeros_like(v) for k, v in params.items()},
                   {k: torch.zeros_like(v) for k, v in params.items()}, 0)

    def to_tensors(self, prefix: str) -> dict[str, torch.Tensor]:
        """The moments as checkpoint tensors: ``{prefix}/m/{name}`` and ``{prefix}/v/{name}``
        (the step count is the caller's to store, in the checkpoint's metadata)."""
        out = {f"{prefix}/m/{k}": v for k, v in self.exp_avg.items()}
        out.update({f"{prefix}/v/{k}": v for k, v in self.exp_avg_sq.items()})
        return out

    @classmethod
    def from_tensors(cls, tensors: Mapping[str, torch.Tensor], prefix: str, step: int,
                     like: Mapping[str, torch.Tensor]) -> "AdamState":
        """Inverse of :meth:`to_tensors` for the parameters ``like`` (their names; each moment goes
        to its parameter's device). The moments are copies: safetensors' loaded tensors are views
        on read-only buffers, and :func:`adam_step` updates moments in place."""
        def moments(kind: str) -> dict[str, torch.Tensor]:
            return {k: tensors[f"{prefix}/{kind}/{k}"].to(p.device, copy=True) for k, p in like.items()}

        return cls(moments("m"), moments("v"), int(step))


@functools.cache
def _compiled_adam():
    """:mod:`volcap_core.adam_numba`, imported on first use (importing numba costs ~0.5 s, which a
    process that never trains on a CPU should not pay); None where numba does not import."""
    try:
        from volcap_core import adam_numba
    except ImportError:
        return None
    return adam_numba


@torch.no_grad()
def adam_step(params: Mapping[str, torch.Tensor], lrs: Mapping[str, float | torch.Tensor],
              state: AdamState, *, betas: tuple[float, float] = (0.9, 0.999),
              eps: float = 1e-15) -> None:
    """One Adam update in place on every ``params[name]`` that has a ``.grad`` and a learning
    rate ``lrs[name]``: a float (0 or absent = frozen) or a tensor broadcastable to the parameter
    (e.g. ``[1, n, 1]``: one rate per polynomial order). Exactly ``torch.optim.Adam``'s update
    (bias-corrected, ``eps`` added to the corrected ``sqrt(v)``). ``eps = 1e-15`` as in 3DGS
    (Gaussian parameters have tiny gradients; a larger eps would silently lower their learning
    rate); the enhancer passes 1e-8.

    float32 CPU parameters (contiguous, as their grads and moments) are updated by the compiled
    kernels of :mod:`volcap_core.adam_numba` where numba imports: two fused passes per parameter
    around torch's square root, the same bits as the torch code below, which updates every other
    parameter (CUDA, float64, no numba, a CPU without AVX2)."""
    state.step += 1
    b1, b2 = betas
    bc1 = 1.0 - b1 ** state.step
    bc2 = 1.0 - b2 ** state.step
    for name, p in params.items():
        lr = lrs.get(name, 0.0)
        if p.grad is None or (not isinstance(lr, torch.Tensor) and lr <= 0.0):
            continue
        g = p.grad
        m, v = state.exp_avg[name], state.exp_avg_sq[name]
        compiled = _compiled_adam() if p.device.type == "cpu" else None
        if compiled is not None and compiled.takes(p, g, m, v, lr):
            compiled.adam_update(p, g, m, v, lr, betas=betas, bc1=bc1, bc2=bc2, eps=eps)
            continue
        m.mul_(b1).add_(g, alpha=1.0 - b1)
        v.mul_(b2).addcmul_(g, g, value=1.0 - b2)
        denom = (v / bc2).sqrt_().add_(eps)
        if isinstance(lr, torch.Tensor):
            p.sub_(m / denom * (lr / bc1))
        else:
            p.addcdiv_(m, denom, value=-lr / bc1)


# ------------------------------------------------------------------------------------- execution

@contextmanager
def deterministic_torch(device: str = "cpu"):
    """Reproducible CPU training: one intra-op thread while training (restored after).

    With two intra-op threads the same seed ended with different Gaussians in two runs (the order
    of multi-threaded accumulations), which breaks bit-identical resumption from a checkpoint.
    ``torch.use_deterministic_algorithms`` also fixes it, at many times the cost of a step; one
    thread is deterministic and, on a busy 2-core machine, no slower. On CUDA nothing changes
    (bit-identity is promised on CPU only).

    Safe with concurrently mapped tasks in one process: with torch's OpenMP back-end the intra-op
    thread count is per calling thread (checked: a thread kept 1 while another thread switched
    ``torch.set_num_threads`` between 2 and 1 a hundred times), so a task restoring its setting on
    exit does not change the count of a task still training in another thread; a new thread
    starts from the last value set anywhere, and this context sets its own before training.
    """
    if device != "cpu":
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)
