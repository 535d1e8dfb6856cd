"""Face Rig pair tasks: one camera path's LQ/HQ renders, and the pair dataset of an actor.

The HQ and LQ models themselves are ``train-segment`` runs (``tasks/reconstruct.py``): the same
segment training a production's Scene Rig segments get. ``face-paths`` draws a sub-sequence's
camera paths around the head its HQ model holds (:mod:`volcap_core.production.face_paths`);
``render-pairs`` renders both models along each of its camera paths (:mod:`volcap_core.splat_pairs`);
``lq-range`` measures the LQ range in an actor's Scene Rig segments
(:mod:`volcap_core.production.lq_range`); ``pair-dataset`` gathers every path's sequences into
a :class:`~volcap_core.enhance.production.PairDataset` with its split by sub-sequence
(``docs/enhancer.md``, "Gaussian-splat pairs").
"""

from __future__ import annotations

from typing import Any

from tasks.contract import volcap_task
from volcap_core import reconstruction
from volcap_core.calibration.colour_step import ColourMatrixRecord
from volcap_core.enhance.production import SPLAT_PAIRS, PairDataset, SplatPairSequence, split_subsequences
from volcap_core.records import MEDIA_EXR, ArtifactRef
from volcap_core.view import ViewSpec
from volcap_core.store import ArtifactStore


@volcap_task(name="face-paths", version="2", libraries=("torch", "numpy"))
def face_paths(store: str, hq: ArtifactRef, times_s: list[float], count: int, width: int, height: int, seed: int,
               around_m: list[float], facing: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> ArtifactRef:
    """``count`` camera paths around the head of a sub-sequence's HQ model (``hq``, a SegmentModel
    record) at ``times_s`` (the sub-sequence's frame times), ``width`` × ``height`` px, seeded
    ``seed``: the head per frame from the model's Gaussians at that time
    (:func:`~volcap_core.production.face_paths.head_from_model`, looking within 0.5 m of
    ``around_m``, where the rig's cameras aim), its radius the median over the frames, the face
    looking along ``facing``; then :func:`~volcap_core.production.face_paths.face_camera_paths` (each
    view with its near plane: nothing between the camera and the head is rendered). A JSON
    artifact: ``{"head": {"centres_m", "radius_m"}, "paths": [{"views": [ViewSpec...], "params"}]}``.
    Version 2: the views carry ``near_m``."""
    import numpy as np

    from volcap_core.production.face_paths import face_camera_paths, head_from_model
    from volcap_core.splat import evaluate, load_model

    s = ArtifactStore(store)
    seg = s.get_record(hq, reconstruction.SegmentModel)
    model = load_model(s.get_bytes(seg.model))
    heads = []
    for t in times_s:
        g = evaluate(model, t)
        try:
            heads.append(head_from_model(g.means.detach(), g.opacities.detach().reshape(-1), around_m=around_m))
        except ValueError as exc:
            raise ValueError(f"face paths of segment {hq.digest} (frames {seg.frames[0]}:{seg.frames[1]}) at "
                             f"{t:.3f} s: {exc}") from None
    centres = np.stack([h.centre_m for h in heads])
    radius = float(np.median([h.radius_m for h in heads]))
    paths = face_camera_paths(centres, radius, times_s, count, width=width, height=height, seed=seed, facing=facing)
    return s.put_json({"head": {"centres_m": centres.tolist(), "radius_m": radius},
                       "paths": [{"views": [v.model_dump(mode="json") for v in p.views], "params": p.params}
                                 for p in paths]})


@volcap_task(name="render-pairs", version="2", libraries=("torch", "numpy", "OpenEXR"))
def render_pairs(store: str, hq: ArtifactRef, lq: ArtifactRef, paths: ArtifactRef, subsequence: int,
                 frames: list[int], lq_gaussians: int, hq_gaussians: int,
                 colour: ArtifactRef | None = None) -> list[ArtifactRef]:
    """The HQ and LQ segment models of one sub-sequence (``hq``, ``lq``: SegmentModel records,
    take indices ``frames``, per-frame budgets ``hq_gaussians``, ``lq_gaussians``) rendered along
    each of its camera paths (``paths``: a ``face-paths`` artifact, one view per frame at the
    frames' times): half RGBA EXRs, linear and premultiplied, with the ``colour`` matrix (a
    ``calibrate-colour`` record, Face Rig -> Scene Rig; None: none) applied, and the LQ's exact
    backward flow per consecutive frame pair (float EXR ``flow.x``, ``flow.y``). One
    :class:`~volcap_core.enhance.production.SplatPairSequence` record per path, named
    ``s<subsequence>-p<path>``; each model is loaded once for all the paths. Version 2: each view's
    ``near_m`` clips the colour and the flow (:func:`~volcap_core.splat_pairs.render_path`). The
    colour matrix is applied on the models' device and a path's EXRs are encoded on the host's
    threads (:func:`~volcap_core.splat_pairs.encode_frames`): the same bytes, stored in the same
    order, as one thread's."""
    import torch

    from volcap_core.splat import load_model
    from volcap_core.splat_pairs import encode_flow_frame, encode_frames, encode_pair_frame, render_path

    s = ArtifactStore(store)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    matrix = s.get_record(colour, ColourMatrixRecord) if colour is not None else None
    drawn = s.get_json(paths)["paths"]
    models = {label: load_model(s.get_bytes(s.get_record(ref, reconstruction.SegmentModel).model), device)
              for label, ref in (("hq", hq), ("lq", lq))}
    out = []
    for k, path in enumerate(drawn):
        name = f"s{subsequence:03d}-p{k:03d}"
        views = [ViewSpec.model_validate(v) for v in path["views"]]
        if len(views) != len(frames):
            raise ValueError(f"pair sequence {name}: {len(views)} views for {len(frames)} frames")
        refs: dict[str, tuple[ArtifactRef, ...]] = {}
        flows = None
        for label in ("hq", "lq"):
            rgba, flow = render_path(models[label], views, colour=matrix, flow=label == "lq")
            attributes = [{"volcap.pair": label, "volcap.sequence": name, "volcap.frame": int(f)} for f in frames]
            refs[label] = tuple(s.put_bytes(exr, MEDIA_EXR) for exr in encode_frames(encode_pair_frame, rgba, views,
                                                                                     attributes))
            del rgba                  # one model's frames on the host at a time
            flows = flow if flow is not None else flows
        attributes = [{"volcap.sequence": name, "volcap.frame": int(f)} for f in frames[1:]]
        flow_refs = tuple(s.put_bytes(exr, MEDIA_EXR) for exr in encode_frames(encode_flow_frame, flows, attributes))
        out.append(s.put_record(SplatPairSequence(
            name=name, subsequence=subsequence, path=k, frames=tuple(frames), width=views[0].width,
            height=views[0].height, lq=refs["lq"], hq=refs["hq"], flow=flow_refs, path_params=path["params"],
            lq_gaussians=lq_gaussians, hq_gaussians=hq_gaussians, lq_model=lq, hq_model=hq)))
    return out


@volcap_task(name="lq-range", version="1", libraries=("torch", "numpy"))
def measured_lq_range(store: str, segments: list[ArtifactRef], cores: list[list[int]],
                      actor_index: int | None) -> ArtifactRef:
    """The LQ range of one actor, measured in Scene Rig segments (``segments``: SegmentModel
    records of synthetic captures; ``cores``: each one's ``[a, b)`` take indices it owns, so a
    frame two segments share counts once): per frame the Gaussians alive then inside the actor's
    upper body (:func:`~volcap_core.production.lq_range.upper_body_gaussian_counts`, the default
    :class:`~volcap_core.production.lq_range.UpperBody`) around its true head
    (:func:`~volcap_core.production.lq_range.ground_truth_heads`, actor ``actor_index`` of each
    capture's ground truth; None: its only actor), then their minimum and maximum. A JSON artifact:
    ``{"low", "high", "frames", "actor_index", "heads", "region", "segments": [{"segment",
    "frames", "counts"}]}``. A frame with no Gaussian there (the wrong actor, or one off stage) is
    refused, naming the capture, the segment and the take indices: a range from 0 cannot be drawn from."""
    import dataclasses
    import json

    import numpy as np

    from volcap_core.capture import Capture
    from volcap_core.production.lq_range import UpperBody, ground_truth_heads, lq_range, upper_body_gaussian_counts
    from volcap_core.splat import load_model

    if len(segments) != len(cores) or not segments:
        raise ValueError(f"LQ range: {len(segments)} segment(s) for {len(cores)} core(s): give one core per segment, "
                         "at least one")
    s = ArtifactStore(store)
    region = UpperBody()
    counts, measured = [], []
    for ref, (a, b) in zip(segments, cores):
        seg = s.get_record(ref, reconstruction.SegmentModel)
        if not seg.frames[0] <= a < b <= seg.frames[1]:
            raise ValueError(f"LQ range: core [{a}, {b}) is not inside segment {ref.digest}'s frames "
                             f"[{seg.frames[0]}, {seg.frames[1]})")
        cap = s.get_record(seg.capture, Capture)
        gt = s.get_tree(cap.ground_truth) if cap.ground_truth is not None else {}
        if "scene.json" not in gt:
            raise ValueError(f"LQ range: capture {cap.name} (segment {ref.digest}) has no ground-truth scene.json: "
                             "its head positions are not known (only synthetic captures carry them)")
        times = [cap.frame_time(f) for f in range(a, b)]
        heads = ground_truth_heads(json.loads(s.get_bytes(gt["scene.json"].digest)), actor_index, times,
                                   where=f"capture {cap.name}")
        n = upper_body_gaussian_counts(load_model(s.get_bytes(seg.model)), heads, times, region=region)
        if not n.all():
            empty = [a + int(k) for k in np.flatnonzero(n == 0)]
            raise ValueError(f"LQ range: capture {cap.name}, segment {ref.digest}: no Gaussian in actor "
                             f"{actor_index if actor_index is not None else 0}'s upper body at take indices {empty}: "
                             "is it the actor's index there (actors[].index), and in the frames?")
        counts.append(n)
        measured.append({"segment": ref.digest, "frames": [a, b], "counts": n.tolist()})
    r = lq_range(counts)
    return s.put_json({**r.to_json(), "actor_index": actor_index, "heads": "ground truth (synthetic capture)",
                       "region": dataclasses.asdict(region), "segments": measured})


@volcap_task(name="pair-dataset", version="1")
def pair_dataset(store: str, sequences: list[ArtifactRef], actor: str, capture: ArtifactRef,
                 calibration: ArtifactRef, subsequences: int, lq_range: list[int], lq_range_source: str,
                 resolution: int, parameters: dict[str, Any], seed: int, colour: ArtifactRef | None = None,
                 validation: float = 0.1, test: float = 0.1) -> ArtifactRef:
    """An actor's :class:`~volcap_core.enhance.production.PairDataset`: the ``render-pairs``
    sequences, the split of its ``subsequences`` sub-sequences into train / validation / test
    (:func:`~volcap_core.enhance.production.split_subsequences`, seeded ``seed``, fractions
    ``validation`` and ``test``), the LQ range and where it came from (``preset`` or ``measured``)."""
    s = ArtifactStore(store)
    seqs = tuple(s.get_record(r, SplatPairSequence) for r in sequences)
    bad = [q.name for q in seqs if not 0 <= q.subsequence < subsequences]
    if bad:
        raise ValueError(f"pair dataset of {actor}: sequences {', '.join(bad)} name a sub-sequence outside "
                         f"0..{subsequences - 1}")
    split = split_subsequences(subsequences, seed, validation=validation, test=test)
    return s.put_record(PairDataset(
        actor=actor, group=actor, capture=capture, calibration=calibration, colour=colour, method=SPLAT_PAIRS,
        lq_range=(int(lq_range[0]), int(lq_range[1])), lq_range_source=lq_range_source, resolution=resolution,
        parameters={**parameters, "seed": seed, "validation": validation, "test": test}, split=split,
        sequences=seqs))


__all__ = ["face_paths", "measured_lq_range", "pair_dataset", "render_pairs"]
