"""The Detail Enhancer in a production: stored pair sets, face pairs from an ingested capture,
stored enhancers and enhanced shot frames.

What the ``face-pairs``, ``actor-prompt``, ``train-enhancer`` and ``enhance-shot`` tasks
(``tasks/enhance.py``) and the Face Rig pair tasks (``tasks/facerig.py``) call. Bytes move through
``get_bytes(ref)`` / ``put_bytes(data, media)`` callables, so nothing here touches a store or Prefect.

**Gaussian-splat pairs** (the paper's): a :class:`PairDataset` of :class:`SplatPairSequence` s,
LQ/HQ Poly4DGS renders of an actor's Face Rig sub-sequences along camera paths with the LQ's exact
flow (``flows/facerig_pairs.py``), split by sub-sequence (:func:`split_subsequences`).
:func:`load_pair_sets` is the one loader training reads pairs with (a dataset's train split).

**Interim pairs** (``pair_method: interim``, the CPU presets'): an actor's pairs made from the
actor's *ingested* Face Rig capture frames (:func:`face_pairs_from_capture`): HQ = the frames (RGB premultiplied by the
ground-truth performer coverage where the capture has it), LQ =
:func:`~volcap_core.enhance.pairs.make_degraded_pairs` of them. The plan's face-pairs parameters
are honoured this way: ``subsequences`` windows of ``subsequence_frames`` consecutive take frames,
spread evenly over the take; ``camera_paths`` cameras per window (real cameras stand for the
rendered camera paths; consecutive windows take the next cameras, so every camera is used); each
frame cropped to the largest square centred on the performer and resized to ``resolution`` px
(or, with the ``head`` window, a ``resolution``-px square over the head at the capture's pixels).
The LQ/HQ Gaussian budgets of the plan (``lq_gaussians``, ``hq_gaussians_per_frame``) have no
meaning for degraded frames and are only recorded.
"""

from __future__ import annotations

import io
import json
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any, ClassVar, Literal

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field

from volcap_core.checkpoint import safetensors_bytes, safetensors_metadata
from volcap_core.records import ArtifactRef, Record

__all__ = [
    "ENHANCED_FRAME_ATTRIBUTES",
    "EnhanceSettings",
    "EnhancerModel",
    "FacePairSet",
    "PairDataset",
    "PairDegradation",
    "PairSequence",
    "SPLAT_PAIRS",
    "SplatPairSequence",
    "check_flux_directory",
    "check_raft_weights",
    "decode_pair_sequence",
    "decode_splat_pair_sequence",
    "directory_fingerprint",
    "encode_enhanced_frame",
    "encode_pair_sequence",
    "enhance_shot_frames",
    "face_pairs_from_capture",
    "face_windows",
    "has_text_encoders",
    "head_window",
    "load_pair_sets",
    "pair_record",
    "read_shot_frame",
    "shot_flow_backend",
    "split_subsequences",
    "square_window",
]

PAIR_SEQUENCE_FORMAT = "volcap-pair-sequence/1"
GetBytes = Callable[[ArtifactRef], bytes]
PutBytes = Callable[[bytes, str], ArtifactRef]


# ------------------------------------------------------------------------------------ records


class PairDegradation(BaseModel):
    """The interim LQ: :func:`~volcap_core.enhance.pairs.make_degraded_pairs`'s settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    scale: int = Field(4, ge=1)
    blur_sigma: float = Field(0.6, ge=0)
    noise_sigma: float = Field(0.03, ge=0)
    splat_sigma: float = Field(1.0, ge=0)
    seed: int = 0


class PairSequence(BaseModel):
    """One stored LQ/HQ sequence of a :class:`FacePairSet`: ``data`` holds ``lq`` and ``hq``
    ``[T, 4, H, W]`` half float (and ``flow [T-1, 2, H, W]`` float32 when exact flow exists)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str
    camera: str
    frames: tuple[int, ...]
    width: int
    height: int
    data: ArtifactRef


class FacePairSet(Record):
    """An actor's LQ/HQ pair sequences (the ``face-pairs`` task's output)."""

    kind: ClassVar[str] = "face-pair-set"
    actor: str
    #: the prompt group the pairs train (the actor's name)
    group: str
    capture: ArtifactRef
    #: how the pairs were made ("degraded capture frames (interim)" until the pair dataset lands)
    method: str
    parameters: dict[str, Any]
    sequences: tuple[PairSequence, ...]


#: the method string of a :class:`PairDataset` (the paper's pairs; the interim ones say INTERIM_PAIRS)
SPLAT_PAIRS = "Gaussian-splat renders of HQ and LQ Poly4DGS models of Face Rig sub-sequences along camera paths"

#: the splits of a :class:`PairDataset`, by sub-sequence
SPLITS = ("train", "validation", "test")


class SplatPairSequence(Record):
    """One rendered pair sequence of a :class:`PairDataset`: the HQ and LQ models of sub-sequence
    ``subsequence`` (take indices ``frames``) rendered along camera path ``path`` at ``width`` ×
    ``height``. ``lq``, ``hq``: one half-float RGBA EXR per frame (linear, premultiplied, the
    Face Rig -> Scene Rig colour matrix applied); ``flow``: the LQ's exact backward flow of frame
    ``t`` to ``t - 1`` for ``t >= 1`` (float EXR, channels ``flow.x``, ``flow.y``, px), ``T - 1`` of
    them. ``path_params``: the camera path's parameters; ``lq_gaussians`` / ``hq_gaussians``: the
    models' Gaussian budgets (per frame) and ``lq_model`` / ``hq_model`` their SegmentModel refs."""

    kind: ClassVar[str] = "splat-pair-sequence"
    name: str
    subsequence: int
    path: int
    frames: tuple[int, ...]
    width: int
    height: int
    lq: tuple[ArtifactRef, ...]
    hq: tuple[ArtifactRef, ...]
    flow: tuple[ArtifactRef, ...]
    path_params: dict[str, Any]
    lq_gaussians: int
    hq_gaussians: int
    lq_model: ArtifactRef
    hq_model: ArtifactRef


class PairDataset(Record):
    """An actor's Face Rig pair dataset (the ``facerig_pairs`` flow's output, ``docs/enhancer.md``,
    "Gaussian-splat pairs"): the rendered sequences, the actor and its prompt group, how the LQ
    count was chosen (``lq_range`` and where it came from, ``lq_range_source``: "preset" or
    "measured") and the split by sub-sequence: ``split[name]`` lists the sub-sequence indices of
    ``train``, ``validation`` and ``test`` (disjoint; every sequence of a sub-sequence is in its
    split, so no test sub-sequence reaches training)."""

    kind: ClassVar[str] = "pair-dataset"
    actor: str
    group: str
    capture: ArtifactRef
    calibration: ArtifactRef
    colour: ArtifactRef | None
    method: str
    lq_range: tuple[int, int]
    lq_range_source: str
    resolution: int
    parameters: dict[str, Any]
    split: dict[str, tuple[int, ...]]
    sequences: tuple[SplatPairSequence, ...]

    def in_split(self, split: str) -> list[SplatPairSequence]:
        """The sequences of the sub-sequences of ``split`` (``train``, ``validation``, ``test``)."""
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r} (known: {', '.join(SPLITS)})")
        chosen = set(self.split.get(split, ()))
        return [q for q in self.sequences if q.subsequence in chosen]


class EnhancerModel(Record):
    """A trained enhancer (the ``train-enhancer`` task's output): the weights
    (:func:`~volcap_core.enhance.model.enhancer_to_bytes`) and how they were trained."""

    kind: ClassVar[str] = "enhancer-model"
    model: ArtifactRef
    config: dict[str, Any]
    train_config: dict[str, Any]
    groups: tuple[str, ...]
    pair_sets: tuple[ArtifactRef, ...]
    steps: int
    wall_s: float
    losses: tuple[float, ...]
    base: str = Field(description="'random' or the base weights' fingerprint")


class EnhanceSettings(BaseModel):
    """How a shot is enhanced (the ``enhance-shot`` task's settings; part of its key).

    ``steps``: Euler sampling steps; ``strength``: the fraction of them run, starting from the noised
    LQ (:func:`~volcap_core.enhance.inference.enhance_frame`; 1: from pure noise);
    ``seed``: frame ``t`` is sampled from noise seeded ``seed + t``;
    ``tile``/``overlap``: latent tiling in px (None: the whole frame in one pass);
    ``vae_tiling``: the VAE's own tiling for frames larger than its tile (needed at 4K, a waste on
    small frames with the tiny model, whose VAE tile is 64 px); ``flow``: the flow between
    consecutive LQ frames: ``rendered`` (default: the exact flow the shot renderer wrote into the
    frame, channels ``flow.x``/``flow.y``, and OpenCV DIS for a frame without it: across a segment
    boundary, or frames not rendered by render-shot v3+), ``dis`` (always DIS), ``zero``, or
    ``raft`` / ``raft-small`` (always torchvision's RAFT large / small, from a local weights file
    that reaches the task as its ``flow_weights`` location and ``flow_weights_fingerprint``, never
    in these settings; :func:`shot_flow_backend`); ``temporal``/``lowfreq_swap``: the ablation
    switches of :func:`~volcap_core.enhance.inference.enhance_frame`."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    steps: int = Field(28, ge=1)
    strength: float = Field(1.0, gt=0, le=1)
    seed: int = 0
    tile: int | None = Field(1024, ge=16)
    overlap: int | None = Field(None, ge=0)
    vae_tiling: bool = True
    flow: Literal["rendered", "dis", "zero", "raft", "raft-small"] = "rendered"
    temporal: bool = True
    lowfreq_swap: bool = True


# ------------------------------------------------------------------------- pair-set artifacts


def encode_pair_sequence(lq: torch.Tensor, hq: torch.Tensor, flow: torch.Tensor | None = None,
                         meta: Mapping[str, Any] | None = None) -> bytes:
    """Safetensors bytes of one pair sequence: ``lq``, ``hq`` ``[T, 4, H, W]`` as half float
    (finite values clamped to +-65504, as the EXRs are), ``flow`` float32; ``meta`` (JSON) in
    the metadata. Same tensors, same bytes."""

    def half(x: torch.Tensor) -> torch.Tensor:
        return x.detach().float().clamp(-65504.0, 65504.0).half().contiguous().cpu()

    if lq.ndim != 4 or lq.shape[1] != 4 or hq.shape != lq.shape:
        raise ValueError(f"lq and hq must be [T, 4, H, W] of one shape, got {tuple(lq.shape)}, {tuple(hq.shape)}")
    tensors = {"lq": half(lq), "hq": half(hq)}
    if flow is not None:
        tensors["flow"] = flow.detach().float().contiguous().cpu()
    return safetensors_bytes(tensors, {"format": PAIR_SEQUENCE_FORMAT,
                                       "meta": json.dumps(dict(meta or {}), sort_keys=True)})


def decode_pair_sequence(data: bytes, name: str = "", group: str | None = None):
    """Inverse of :func:`encode_pair_sequence`: a :class:`~volcap_core.enhance.pairs.PairSet`
    (float32 tensors) with ``group`` set (the prompt group training reads)."""
    from safetensors.torch import load as st_load

    from volcap_core.enhance.pairs import PairSet

    meta = safetensors_metadata(data)
    if meta.get("format") != PAIR_SEQUENCE_FORMAT:
        raise ValueError(f"not a pair sequence (format {meta.get('format')!r})")
    t = st_load(data)
    ps = PairSet(lq=t["lq"].float(), hq=t["hq"].float(), flow=t["flow"].float() if "flow" in t else None,
                 name=name)
    if group is not None:
        ps.group = group  # read by training (getattr(seq, "group")); PairSet is not slotted
    return ps


def pair_record(ref: ArtifactRef, get_bytes: GetBytes) -> "FacePairSet | PairDataset":
    """The pair record ``ref`` names: a :class:`PairDataset` (Gaussian-splat pairs) or a
    :class:`FacePairSet` (interim pairs), by its media type (a ref without one, e.g. a bare
    digest: whichever of the two its JSON is); ``ValueError`` naming the digest otherwise."""
    models = [m for m in (PairDataset, FacePairSet) if ref.media_type == m.media_type()] or [PairDataset, FacePairSet]
    data = get_bytes(ref)
    for model in models:
        try:
            return model.from_json_bytes(data)
        except ValueError:
            if len(models) == 1:
                raise
    raise ValueError(f"{ref.digest}: not a pair set ({ref.media_type}; expected a {PairDataset.kind} or a "
                     f"{FacePairSet.kind} record)")


def decode_splat_pair_sequence(seq: SplatPairSequence, get_bytes: GetBytes, name: str = "",
                               group: str | None = None):
    """A :class:`SplatPairSequence` as a :class:`~volcap_core.enhance.pairs.PairSet` (float32
    ``[T, 4, H, W]`` LQ and HQ, ``[T - 1, 2, H, W]`` flow) with ``group`` set."""
    from volcap_core.enhance.pairs import PairSet
    from volcap_core.imageio.read import decode_exr_native

    def frames(refs: Sequence[ArtifactRef], what: str, channels: tuple[str, ...]) -> torch.Tensor:
        out = []
        for k, ref in enumerate(refs):
            where = f"pair sequence {seq.name}: {what} frame {k}"
            px, names = decode_exr_native(get_bytes(ref), name=where)
            missing = [c for c in channels if c not in names]
            if missing or px.shape[:2] != (seq.height, seq.width):
                raise ValueError(f"{where}: {px.shape[1]}x{px.shape[0]} with channels {', '.join(names)}, expected "
                                 f"{seq.width}x{seq.height} with {', '.join(channels)}")
            px = np.stack([px[..., names.index(c)] for c in channels], axis=-1)
            out.append(torch.from_numpy(np.ascontiguousarray(px, np.float32)).permute(2, 0, 1))
        return torch.stack(out)

    lq, hq = frames(seq.lq, "LQ", tuple("RGBA")), frames(seq.hq, "HQ", tuple("RGBA"))
    flow = frames(seq.flow, "flow", ("flow.x", "flow.y")) if seq.flow else None
    ps = PairSet(lq=lq, hq=hq, flow=flow, name=name or seq.name)
    if group is not None:
        ps.group = group
    return ps


def load_pair_sets(sets: Iterable["FacePairSet | PairDataset"], get_bytes: GetBytes, split: str = "train") -> list:
    """Every sequence of ``sets`` as :class:`~volcap_core.enhance.pairs.PairSet` s, each carrying
    its set's prompt group, in order: all of a :class:`FacePairSet` (interim pairs have no split),
    the sequences of ``split``'s sub-sequences of a :class:`PairDataset`. The one loader
    ``train-enhancer`` reads pairs with."""
    out = []
    for s in sets:
        if isinstance(s, PairDataset):
            out += [decode_splat_pair_sequence(q, get_bytes, f"{s.actor}/{q.name}", s.group) for q in s.in_split(split)]
        else:
            out += [decode_pair_sequence(get_bytes(q.data), f"{s.actor}/{q.name}", s.group) for q in s.sequences]
    return out


def split_subsequences(count: int, seed: int, validation: float = 0.1, test: float = 0.1) -> dict[str, tuple[int, ...]]:
    """A seeded split of sub-sequences ``0 .. count - 1`` into ``train``, ``validation`` and
    ``test`` (disjoint, sorted): ``round(count * test)`` test sub-sequences, at least one when
    ``test > 0`` and ``count >= 2``; likewise validation when ``count >= 3``; the rest train (at
    least one). Sub-sequences are drawn by a permutation seeded ``seed`` (numpy's PCG64)."""
    if count < 1:
        raise ValueError(f"a split needs at least one sub-sequence, got {count}")
    if not (0 <= validation < 1 and 0 <= test < 1 and validation + test < 1):
        raise ValueError(f"split fractions must be in [0, 1) and sum below 1, got validation {validation}, test {test}")
    n_test = max(1, round(count * test)) if test > 0 and count >= 2 else 0
    n_val = max(1, round(count * validation)) if validation > 0 and count >= 3 else 0
    while count - n_test - n_val < 1:
        n_val, n_test = (n_val - 1, n_test) if n_val >= n_test else (n_val, n_test - 1)
    order = np.random.default_rng(seed).permutation(count).tolist()
    return {"train": tuple(sorted(order[n_test + n_val:])), "validation": tuple(sorted(order[n_test:n_test + n_val])),
            "test": tuple(sorted(order[:n_test]))}


# -------------------------------------------------------------------------- interim face pairs


def face_windows(frame_count: int, subsequences: int, frames: int) -> list[list[int]]:
    """``subsequences`` windows of ``frames`` consecutive take indices spread evenly over a take of
    ``frame_count`` frames (first window at 0, last flush with the end; duplicates dropped). A
    take shorter than ``frames``: one window of the whole take."""
    n = min(frames, frame_count)
    last = frame_count - n
    starts = sorted({round(i * last / (subsequences - 1)) if subsequences > 1 else 0 for i in range(subsequences)})
    return [list(range(s, s + n)) for s in starts]


def square_window(alpha: np.ndarray) -> tuple[int, int, int]:
    """``(y0, x0, side)`` of the largest square of an ``[H, W]`` frame centred (as far as the frame
    allows) on the centre of the bounding box of ``alpha > 0.5``; the frame's centre without one."""
    h, w = alpha.shape
    side = min(h, w)
    mask = alpha > 0.5
    if mask.any():
        ys, xs = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        cy, cx = (ys[0] + ys[-1]) / 2.0, (xs[0] + xs[-1]) / 2.0
    else:
        cy, cx = (h - 1) / 2.0, (w - 1) / 2.0
    y0 = int(min(max(round(cy - (side - 1) / 2.0), 0), h - side))
    x0 = int(min(max(round(cx - (side - 1) / 2.0), 0), w - side))
    return y0, x0, side


def head_window(alpha: np.ndarray, side: int, below_top: int = -16) -> tuple[int, int]:
    """Top-left ``(y0, x0)`` of a ``side``-square window over the head of ``alpha [T, H, W]`` (a
    sub-sequence's performer coverage; ``side`` <= H, W): its top ``below_top`` px below the
    highest pixel covered (alpha >= 0.5) in any frame (negative: above it), centred on the covered
    columns inside the window. In a Face Rig the highest covered pixel is the top of the head, so
    the window holds head, face and collar at the capture's own pixels; without coverage, the
    frame's centre."""
    h, w = alpha.shape[-2:]
    cov = (np.asarray(alpha) >= 0.5).any(axis=0)
    rows = np.flatnonzero(cov.any(axis=1))
    y0 = int(rows[0]) + below_top if len(rows) else (h - side) // 2
    y0 = max(0, min(h - side, y0))
    cols = np.flatnonzero(cov[y0:y0 + side].any(axis=0))
    xc = float(cols.mean()) if len(cols) else w / 2
    x0 = max(0, min(w - side, int(round(xc - side / 2))))
    return y0, x0


def face_pairs_from_capture(capture, get_bytes: GetBytes, *, subsequences: int, subsequence_frames: int,
                            camera_paths: int, resolution: int, degradation: PairDegradation,
                            load_mask: Callable[[str, int], np.ndarray | None] | None = None,
                            window: Literal["performer", "head"] = "performer"
                            ) -> list[tuple[str, str, list[int], Any]]:
    """Interim LQ/HQ pairs of an ingested Face Rig capture (module docstring): a list of
    ``(name, camera, take indices, PairSet)``, ``name`` = ``w<window>-<camera>``.

    ``capture``: a :class:`~volcap_core.capture.Capture` record; ``load_mask(camera, take index)``:
    the performer coverage (synthetic captures' ground truth) or None: then the frame's own alpha
    channel, else 1. The square crop of a window's frames is fixed by its first frame (so the
    sequence does not jump). Degradation noise is seeded by ``degradation.seed``, the window and
    the camera. ``window``: ``"performer"``, that square; ``"head"``, a ``resolution``-square
    :func:`head_window` over the sub-sequence at the capture's own pixels (the enhancer bench's
    crop: no resampling, the face at the footage's detail; a frame narrower than ``resolution``
    gives its narrow side, then resized)."""
    from volcap_core.enhance.pairs import make_degraded_pairs
    from volcap_core.imageio.read import decode_exr

    cams = list(capture.cameras)
    if not cams:
        raise ValueError(f"capture {capture.name} has no cameras")
    windows = face_windows(capture.frame_count, subsequences, subsequence_frames)
    per_window = min(camera_paths, len(cams))
    out = []
    for wi, take in enumerate(windows):
        for k in range(per_window):
            cam = cams[(wi * per_window + k) % len(cams)]
            frames = []
            for f in take:
                pixels, channels = decode_exr(get_bytes(cam.frames[f]), name=f"{cam.id}/{f}")
                rgb = np.asarray(pixels[..., :3], np.float32)
                alpha = load_mask(cam.id, f) if load_mask is not None else None
                if alpha is None:
                    alpha = (np.clip(pixels[..., 3], 0.0, 1.0) if len(channels) > 3
                             else np.ones(rgb.shape[:2], np.float32))
                if alpha.shape != rgb.shape[:2]:
                    raise ValueError(f"camera {cam.id} frame {f}: mask {alpha.shape} vs frame {rgb.shape[:2]}")
                frames.append(np.concatenate([rgb * alpha[..., None], alpha[..., None]], axis=2))
            if window == "head":
                side = min(resolution, *frames[0].shape[:2])
                y0, x0 = head_window(np.stack([fr[..., 3] for fr in frames]), side)
            else:
                y0, x0, side = square_window(frames[0][..., 3])
            x = torch.from_numpy(np.stack([fr[y0:y0 + side, x0:x0 + side] for fr in frames])).permute(0, 3, 1, 2)
            x = x.float().contiguous()
            if side != resolution:
                x = F.interpolate(x, size=(resolution, resolution), mode="bilinear", antialias=side > resolution,
                                  align_corners=False)
                x = torch.cat([x[:, :3].clamp(min=0.0), x[:, 3:].clamp(0.0, 1.0)], dim=1)
            name = f"w{wi:03d}-{cam.id}"
            seed = zlib.crc32(f"{degradation.seed}/{name}".encode())
            pairs = make_degraded_pairs(x, degradation.scale, degradation.blur_sigma, seed,
                                        noise_sigma=degradation.noise_sigma, splat_sigma=degradation.splat_sigma,
                                        name=name)
            out.append((name, cam.id, take, pairs))
    return out


# ---------------------------------------------------------------------------- shot frames (EXR)

#: what an enhanced frame's header adds to the render-shot frame's (docs/enhancer.md)
ENHANCED_FRAME_ATTRIBUTES = ("volcap.enhanced", "volcap.enhancer", "volcap.enhanceSteps", "volcap.enhanceStrength",
                             "volcap.enhanceSeed", "volcap.enhanceFlow", "volcap.lqFrame")


def read_shot_frame(data: bytes, *, with_flow: bool = False):
    """A render-shot frame (cropped half RGBA EXR) as ``(header, rgba [H, W, 4] float32)`` over
    its whole display window (zeros outside the data window: the render is premultiplied over
    nothing there). With ``with_flow``: ``(header, rgba, flow)``, ``flow`` the frame's exact
    backward flow to the previous shot frame ``[H, W, 2]`` float32 in px (channels ``flow.x``,
    ``flow.y``, ``docs/shots.md``; zeros outside the data window) or None when the frame has none
    (the shot's first frame, a segment boundary, an empty frame)."""
    import OpenEXR

    f = OpenEXR.File(io.BytesIO(bytes(data)))
    header = dict(f.header())
    channels = f.channels()
    plane = channels.get("RGBA")
    if plane is None:
        planes = [channels.get(c) for c in "RGBA"]
        if any(p is None for p in planes):
            raise ValueError(f"not an RGBA frame (channels {', '.join(channels)})")
        pixels = np.stack([p.pixels for p in planes], axis=-1)
    else:
        pixels = plane.pixels
    (dx0, dy0), (dx1, dy1) = (tuple(int(v) for v in p) for p in header["displayWindow"])
    (x0, y0), (x1, y1) = (tuple(int(v) for v in p) for p in header["dataWindow"])
    size = (dy1 - dy0 + 1, dx1 - dx0 + 1)
    window = (slice(y0 - dy0, y1 - dy0 + 1), slice(x0 - dx0, x1 - dx0 + 1))
    full = np.zeros((*size, 4), np.float32)
    full[window] = np.asarray(pixels, np.float32)
    if not with_flow:
        return header, full
    fx, fy = channels.get("flow.x"), channels.get("flow.y")
    if fx is None or fy is None:
        return header, full, None
    flow = np.zeros((*size, 2), np.float32)
    flow[window] = np.stack([np.asarray(fx.pixels, np.float32), np.asarray(fy.pixels, np.float32)], axis=-1)
    return header, full, flow


def encode_enhanced_frame(rgba: np.ndarray, header: Mapping[str, Any],
                          attributes: Mapping[str, str | int | float]) -> bytes:
    """Half-float RGBA EXR of an enhanced shot frame: ``rgba [H, W, 4]`` over the display window
    of the render-shot frame whose ``header`` it keeps whole (every ``volcap.*`` attribute, the
    camera, chromaticities, compression, the data window: the crop stays the render's), plus
    ``attributes`` (``volcap.enhanced`` ...; a float is written as a double)."""
    import OpenEXR

    px = np.asarray(rgba, np.float32)
    (dx0, dy0), (dx1, dy1) = (tuple(int(v) for v in p) for p in header["displayWindow"])
    if px.shape != (dy1 - dy0 + 1, dx1 - dx0 + 1, 4):
        raise ValueError(f"rgba {px.shape} does not match the display window {dx1 - dx0 + 1}x{dy1 - dy0 + 1}")
    (x0, y0), (x1, y1) = (tuple(int(v) for v in p) for p in header["dataWindow"])
    half = np.clip(np.nan_to_num(px, nan=0.0), -65504.0, 65504.0).astype(np.float16)
    crop = half[y0 - dy0:y1 - dy0 + 1, x0 - dx0:x1 - dx0 + 1]
    skip = {"channels", "chunkCount", "version", "name", "type"}
    out_header: dict[str, Any] = {k: v for k, v in header.items() if k not in skip}
    out_header["type"] = OpenEXR.scanlineimage
    for key, value in attributes.items():
        out_header[key] = np.array([value], dtype=np.float64) if isinstance(value, float) else value
    planes = {c: np.ascontiguousarray(crop[..., i]) for i, c in enumerate("RGBA")}
    buf = io.BytesIO()
    OpenEXR.File(out_header, planes).write(buf)
    return buf.getvalue()


def shot_flow_backend(settings: EnhanceSettings, flow_weights=None, *, shot: str,
                      fingerprint: str | None = None, device: str | torch.device = "cpu"):
    """The flow back-end of a shot's frames that carry no exact flow (``settings.flow``), built and
    checked before any frame is enhanced: ``rendered`` / ``dis``: OpenCV DIS
    (:class:`~volcap_core.enhance.temporal.DisFlow`); ``zero``: None; ``raft`` / ``raft-small``:
    :class:`~volcap_core.enhance.temporal.RaftFlow` (large / small) on ``device`` with the weights
    file ``flow_weights`` (a torchvision ``raft_large`` / ``raft_small`` state dict on local disk;
    never downloaded). ``fingerprint``: when given, the :func:`directory_fingerprint` the caller's
    cache key holds for the file; a file changed since is refused (the key would not see it).

    Each refusal names the shot (and the file): ``ValueError`` without ``flow_weights`` or with a
    stale fingerprint, ``FileNotFoundError`` for a missing file,
    :class:`~volcap_core.enhance.temporal.FlowUnavailable` without torchvision or when the file does
    not load into the model."""
    from volcap_core.enhance import temporal

    if settings.flow in ("rendered", "dis"):
        return temporal.DisFlow()
    if settings.flow == "zero":
        return None
    what = f"shot {shot}: flow {settings.flow!r}"
    path = check_raft_weights(settings.flow, flow_weights, what=what, fingerprint=fingerprint)
    small = settings.flow == "raft-small"
    try:
        return temporal.RaftFlow(path, small=small, device=device)
    except Exception as exc:
        raise temporal.FlowUnavailable(f"{what}: the RAFT weights file {path} does not load into torchvision's "
                                       f"{'raft_small' if small else 'raft_large'}: {exc}") from exc


def check_raft_weights(flow: str, flow_weights, *, what: str, fingerprint: str | None = None,
                       knob: str = "flow_weights"):
    """What :func:`shot_flow_backend` checks before it loads RAFT (and a production before anything
    runs): ``flow_weights`` given, an existing file (its ``fingerprint`` unchanged when given),
    torchvision importable. Returns the file's path; each refusal starts with ``what``, and a missing
    path names ``knob``, the setting that gives it."""
    from pathlib import Path

    from volcap_core.enhance.temporal import FlowUnavailable

    small = flow == "raft-small"
    arch = "raft_small" if small else "raft_large"
    if flow_weights is None:
        raise ValueError(f"{what} needs a local RAFT weights file (torchvision's {arch} state dict, e.g. "
                         f"{'raft_small_C_T_V2-01064c6d.pth' if small else 'raft_large_C_T_SKHT_V2-ff5fadd5.pth'}; "
                         f"never downloaded): set {knob} (docs/enhancer.md)")
    path = Path(flow_weights).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"{what}: no RAFT weights file at {path}")
    if fingerprint is not None and fingerprint != directory_fingerprint(path):
        raise ValueError(f"{what}: the RAFT weights file {path} changed since it was fingerprinted "
                         f"({fingerprint}); fingerprint it again")
    try:
        import torchvision.models.optical_flow  # noqa: F401
    except ImportError as exc:
        raise FlowUnavailable(
            f"{what} needs torchvision, which is not installed here: install the torchvision release that "
            f"matches torch {torch.__version__} (pip install torchvision), or use flow 'rendered' or 'dis' "
            f"(RAFT weights {path})") from exc
    return path


def enhance_shot_frames(model, frames: Sequence[tuple[str, bytes]] | Iterable[tuple[str, bytes]],
                        settings: EnhanceSettings, *, group: str, model_digest: str,
                        progress: Callable[[int, str], None] | None = None, flow_backend=None,
                        shot: str = "?") -> Iterator[tuple[str, bytes]]:
    """Enhance a shot's render-shot frames **in order** (each frame is conditioned on the previous
    one's output): yields ``(name, EXR bytes)`` per input ``(name, EXR bytes)``.

    Frame ``t`` is :func:`~volcap_core.enhance.inference.enhance_frame` of the LQ frame over its
    display window, conditioned on output ``t-1`` warped by the flow between LQ ``t-1`` and ``t``
    (none for the first frame), noise seeded ``settings.seed + t``. The flow (``settings.flow``):
    ``rendered`` takes the exact flow the frame carries (``flow.x``/``flow.y``, written by
    render-shot) when it has one and its ``volcap.frame`` follows the previous frame's, OpenCV
    DIS otherwise (across a segment boundary); ``dis`` always DIS; ``zero`` no motion; ``raft`` /
    ``raft-small`` always RAFT. ``flow_backend``: :func:`shot_flow_backend` of ``settings`` (the
    task builds it before loading anything; left None it is built here for ``shot``, before the
    first frame, and RAFT then refuses for want of weights). Which one conditioned the frame is
    recorded as ``volcap.enhanceFlow`` (``rendered``, ``dis``, ``zero``, ``raft``, ``raft-small``,
    or ``none``: first frame, after an empty frame, temporal conditioning off). Output RGB is
    clamped to >= 0 (it is premultiplied, as the render is), alpha is in [0, 1]. An empty frame
    (``volcap.empty``: nothing in view) stays empty and restarts the temporal chain.
    Only one frame and its predecessor are held in memory."""
    from volcap_core.enhance.inference import enhance_frame

    backend = flow_backend if flow_backend is not None else shot_flow_backend(settings, shot=shot)
    label = "dis" if settings.flow == "rendered" else settings.flow
    prev_out = prev_lq = prev_frame = None
    for t, (name, data) in enumerate(frames):
        header, lq_np, flow_np = read_shot_frame(data, with_flow=True)
        lq = torch.from_numpy(lq_np).permute(2, 0, 1).contiguous()
        frame_no = header.get("volcap.frame")
        used = "none"
        if int(header.get("volcap.empty", 0)):
            out = lq.clone()
            prev_out = prev_lq = None
        else:
            flow = None
            if prev_out is not None and settings.temporal:
                follows = frame_no is None or prev_frame is None or int(frame_no) == int(prev_frame) + 1
                if settings.flow == "zero":
                    used = "zero"
                elif settings.flow == "rendered" and flow_np is not None and follows:
                    flow, used = torch.from_numpy(flow_np).permute(2, 0, 1).contiguous(), "rendered"
                else:
                    flow, used = backend, label
            out = enhance_frame(model, lq, prev_out, prev_lq if prev_out is not None else None, flow,
                                steps=settings.steps, strength=settings.strength, seed=settings.seed + t,
                                tile=settings.tile, overlap=settings.overlap, group=group, temporal=settings.temporal,
                                lowfreq_swap=settings.lowfreq_swap, vae_tiling=settings.vae_tiling)
            out = torch.cat([out[:3].clamp(min=0.0), out[3:].clamp(0.0, 1.0)])
            prev_out, prev_lq = out, lq
        prev_frame = frame_no
        attrs = {"volcap.enhanced": 1, "volcap.enhancer": model_digest, "volcap.enhanceSteps": settings.steps,
                 "volcap.enhanceStrength": settings.strength,
                 "volcap.enhanceSeed": settings.seed + t, "volcap.enhanceFlow": used, "volcap.lqFrame": name}
        yield name, encode_enhanced_frame(out.permute(1, 2, 0).numpy(), header, attrs)
        if progress is not None:
            progress(t + 1, name)


# ------------------------------------------------------------------------------ local weights


def directory_fingerprint(path) -> str:
    """What pins local weights' content in a cache key without reading their gigabytes: the
    BLAKE3 of every file's relative path, size and mtime (ns), sorted (the stat fingerprint
    ``fingerprint-camera`` uses for raw footage). ``path`` is a weights directory (a FLUX.1
    checkpoint) or a single weights file (RAFT's; its one row has the relative path ``""``, so
    neither its directory nor its name enters the key). Raises ``FileNotFoundError`` for neither."""
    from pathlib import Path

    from volcap_core.digest import digest_bytes

    root = Path(path)
    if root.is_file():
        st = root.stat()
        return digest_bytes(json.dumps([["", st.st_size, st.st_mtime_ns]], separators=(",", ":")).encode())
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such directory or file")
    rows = []
    for p in sorted(root.rglob("*")):
        if p.is_file():
            st = p.stat()
            rows.append([p.relative_to(root).as_posix(), st.st_size, st.st_mtime_ns])
    return digest_bytes(json.dumps(rows, separators=(",", ":")).encode())


def check_flux_directory(path) -> None:
    """A FLUX.1 directory must hold ``transformer/`` and ``vae/`` (``FileNotFoundError`` naming
    what is missing): checked before anything runs."""
    from pathlib import Path

    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"enhancer_weights {root}: no such directory (a local FLUX.1 checkpoint "
                                "directory with transformer/ and vae/; docs/enhancer.md)")
    missing = [d for d in ("transformer", "vae") if not (root / d).is_dir()]
    if missing:
        raise FileNotFoundError(f"enhancer_weights {root}: no {' or '.join(d + '/' for d in missing)} "
                                "subfolder (a local FLUX.1 checkpoint directory; docs/enhancer.md)")


def has_text_encoders(path) -> bool:
    """Whether a FLUX.1 directory holds the text encoders :func:`~volcap_core.enhance.model.encode_prompt`
    needs and ``transformers`` is installed."""
    import importlib.util
    from pathlib import Path

    root = Path(path)
    return (importlib.util.find_spec("transformers") is not None
            and all((root / d).is_dir() for d in ("tokenizer", "text_encoder", "tokenizer_2", "text_encoder_2")))
