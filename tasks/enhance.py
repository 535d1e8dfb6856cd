"""Detail Enhancer tasks: face pairs, actor prompts, enhancer training, shot enhancement.

Each loads its inputs from the store, calls :mod:`volcap_core.enhance` (the production side is
:mod:`volcap_core.enhance.production`) and stores what comes back (``docs/enhancer.md``).

- ``face-pairs``: an actor's **interim** LQ/HQ pair sequences (``pair_method: interim``; the
  Gaussian-splat pairs are the ``facerig_pairs`` flow's, ``tasks/facerig.py``), made from the
  actor's ingested Face Rig capture frames: HQ = the frames, LQ = ``make_degraded_pairs`` of them.
- ``actor-prompt``: an actor group's prompt embedding. Without text encoders (the tiny model, or a
  FLUX.1 directory without them, or no ``transformers``) it is a zero embedding.
- ``train-enhancer``: one enhancer trained on every pair set, checkpointed in the store under
  ``checkpoints/<this run's cache key>`` and resumed from there (as ``train-segment`` does).
- ``enhance-shot``: a shot's render-shot frames enhanced in order, as 16-bit RGBA EXRs keeping the
  render's header (the shot's metadata).

Local weights (a FLUX.1 directory, its text encoders, enhance-shot's RAFT weights file) are
*locations*: their path is not in the key, their stat fingerprint
(:func:`~volcap_core.enhance.production.directory_fingerprint`) is.
"""

from __future__ import annotations

from prefect import get_run_logger

from tasks.artifacts import ProgressArtifact, artifact_key
from tasks.contract import current_run_key, volcap_task
from volcap_core.capture import Capture
from volcap_core.enhance.model import EnhancerConfig
from volcap_core.enhance.production import (EnhancerModel, EnhanceSettings, FacePairSet, PairDegradation,
                                            PairSequence)
from volcap_core.enhance.training import EnhancerTrainConfig
from volcap_core.records import MEDIA_EXR, MEDIA_SAFETENSORS, ArtifactRef
from volcap_core.store import ArtifactStore, MissingRefError

#: the enhancer's numerics: torch and diffusers (the model), OpenCV (DIS flow), numpy
ENHANCER_LIBRARIES = ("torch", "diffusers", "cv2", "numpy")

INTERIM_PAIRS = "degraded capture frames (interim pairs, not Gaussian-splat renders: pair_method splat makes those)"


@volcap_task(name="face-pairs", version="2", libraries=("torch", "numpy"))
def face_pairs(store: str, capture: ArtifactRef, actor: str, subsequences: int, subsequence_frames: int,
               camera_paths: int, resolution: int, degradation: PairDegradation = PairDegradation(),
               lq_gaussians: list[int] | None = None, hq_gaussians_per_frame: int | None = None,
               window: str = "performer") -> ArtifactRef:
    """An actor's LQ/HQ pair sequences from the actor's ingested Face Rig ``capture`` (interim
    pairs: :func:`~volcap_core.enhance.production.face_pairs_from_capture`): ``subsequences`` windows
    of ``subsequence_frames`` frames, ``camera_paths`` cameras each, ``resolution`` px square. A
    :class:`~volcap_core.enhance.production.FacePairSet` record, one safetensors per sequence.
    ``lq_gaussians``/``hq_gaussians_per_frame`` (the pair renders' budgets) are only recorded.
    ``window``: the crop, ``"performer"`` or ``"head"`` (version 2: the parameter is new)."""
    from volcap_core.enhance.production import encode_pair_sequence, face_pairs_from_capture
    from volcap_core.synth import ground_truth

    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    load_mask = None
    if cap.ground_truth is not None:
        tree = s.get_tree(cap.ground_truth)
        files = ground_truth.GroundTruthFiles(cap.name, {p: e.digest for p, e in tree.items()}, s.get_bytes)
        load_mask = ground_truth.mask_loader(files)
    made = face_pairs_from_capture(cap, s.get_bytes, subsequences=subsequences,
                                   subsequence_frames=subsequence_frames, camera_paths=camera_paths,
                                   resolution=resolution, degradation=degradation, load_mask=load_mask,
                                   window=window)
    seqs = []
    for name, camera, take, pairs in made:
        meta = {"actor": actor, "camera": camera, "frames": take, "capture": capture.digest}
        data = s.put_bytes(encode_pair_sequence(pairs.lq, pairs.hq, pairs.flow, meta), MEDIA_SAFETENSORS)
        seqs.append(PairSequence(name=name, camera=camera, frames=tuple(take), width=int(pairs.lq.shape[-1]),
                                 height=int(pairs.lq.shape[-2]), data=data))
    get_run_logger().info("face pairs of %s: %d sequence(s) of %d frame(s) at %d px from capture %s (%s)", actor,
                          len(seqs), len(seqs[0].frames), resolution, cap.name, INTERIM_PAIRS)
    return s.put_record(FacePairSet(
        actor=actor, group=actor, capture=capture, method=INTERIM_PAIRS,
        parameters={"subsequences": subsequences, "subsequence_frames": subsequence_frames,
                    "camera_paths": camera_paths, "resolution": resolution, "window": window,
                    "degradation": degradation.model_dump(mode="json"),
                    "lq_gaussians": lq_gaussians, "hq_gaussians_per_frame": hq_gaussians_per_frame},
        sequences=tuple(seqs)))


@volcap_task(name="actor-prompt", version="1", locations=("encoders",), libraries=("torch",))
def actor_prompt(store: str, group: str, config: EnhancerConfig, text: str | None = None,
                 encoders: str | None = None, encoders_fingerprint: str | None = None) -> ArtifactRef:
    """An actor group's prompt embedding (:class:`~volcap_core.enhance.model.PromptEmbedding`
    safetensors). ``text`` embedded with the FLUX.1 text encoders in the local directory
    ``encoders`` (its content pinned by ``encoders_fingerprint``); without text or encoders, the
    zero embedding of ``config``'s shape (what the tiny model always gets)."""
    from volcap_core.enhance.model import PromptEmbedding, encode_prompt

    s = ArtifactStore(store)
    if text and encoders:
        emb = encode_prompt(text, encoders, max_sequence_length=config.prompt_tokens)
    else:
        if text:
            get_run_logger().warning("actor group %s: no text encoders, a zero prompt embedding stands for %r",
                                     group, text)
        emb = PromptEmbedding.zeros(config)
    return s.put_bytes(emb.to_bytes(), MEDIA_SAFETENSORS)


@volcap_task(name="train-enhancer", version="2", retries=1, locations=("base_weights",),
             libraries=ENHANCER_LIBRARIES)
def train_enhancer_task(store: str, pair_sets: list[ArtifactRef], prompts: dict[str, ArtifactRef],
                        config: EnhancerTrainConfig, architecture: EnhancerConfig | None = None,
                        base_weights: str | None = None, base_fingerprint: str | None = None,
                        seed: int = 0) -> ArtifactRef:
    """Train one enhancer on every pair set (interim ``FacePairSet`` s whole, a ``PairDataset``'s
    train split: :func:`~volcap_core.enhance.production.load_pair_sets`; each set's sequences
    carry its actor's prompt group;
    ``prompts`` maps group -> ``actor-prompt`` output). The model starts from ``architecture`` with
    random weights (seeded ``seed``; the tiny CPU model) or from the local FLUX.1 directory
    ``base_weights`` (content pinned by ``base_fingerprint``). Every ``config.checkpoint_every``
    steps the training state is stored and named ``checkpoints/<this run's cache key>``; a killed or
    retried run resumes from it. An :class:`~volcap_core.enhance.production.EnhancerModel` record."""
    from volcap_core.enhance.model import Enhancer, PromptEmbedding, build_enhancer, enhancer_to_bytes
    from volcap_core.enhance.production import load_pair_sets, pair_record
    from volcap_core.enhance.training import train_enhancer

    if (architecture is None) == (base_weights is None):
        raise ValueError("train-enhancer: give exactly one of architecture (random weights) and base_weights")
    s = ArtifactStore(store)
    log = get_run_logger()
    sets = [pair_record(r, s.get_bytes) for r in pair_sets]   # interim FacePairSets or PairDatasets
    pairs = load_pair_sets(sets, s.get_bytes)                # a PairDataset's training split only
    if base_weights is not None:
        import torch

        # bfloat16 frozen weights: loaded so, never 48 GB of float32 in host or GPU memory
        model = Enhancer.from_pretrained(base_weights, torch_dtype=torch.bfloat16 if config.frozen_dtype == "bfloat16"
                                         else None)
        base = base_fingerprint or "unpinned"
    else:
        model = build_enhancer(architecture, seed=seed)
        base = "random"
    for group, ref in sorted(prompts.items()):
        model.set_prompt(group, PromptEmbedding.from_bytes(s.get_bytes(ref)))

    ckpt_name = f"checkpoints/{current_run_key()}"
    try:
        resume = s.get_bytes(s.get_ref(ckpt_name))
        log.warning("enhancer: resuming from %s", ckpt_name)
    except MissingRefError:
        resume = None
    bar = ProgressArtifact(artifact_key("enhancer", "training"), "Training of the detail enhancer: steps done")
    every = max(1, config.steps // 10)

    def progress(step: int, total: int, info: dict) -> None:
        bar.update(step, total)
        if step % every == 0 or step == total:
            log.info("enhancer: step %d/%d, loss %.4f, %.0f s", step, total, info["loss"], info["wall_s"])

    log.info("enhancer: %d pair sequence(s) of %d actor group(s), %d steps (%s, VAE pre-training %d steps)",
             len(pairs), len({s_.group for s_ in sets}), config.steps, config.finetune, config.vae_steps)
    result = train_enhancer(model, pairs, config, checkpoint=lambda blob, step: s.set_ref(ckpt_name, s.put_bytes(blob)),
                            resume_from=resume, progress=progress)
    bar.finish()
    weights = s.put_bytes(enhancer_to_bytes(result.model), MEDIA_SAFETENSORS)
    ref = s.put_record(EnhancerModel(
        model=weights, config=result.model.config.model_dump(mode="json"), train_config=config.model_dump(mode="json"),
        groups=tuple(result.model.groups), pair_sets=tuple(pair_sets), steps=result.steps, wall_s=result.wall_s,
        losses=tuple(result.losses), base=base))
    try:  # the model is stored: its checkpoint has done its job (gc may take it)
        s.delete_ref(ckpt_name)
    except MissingRefError:
        pass
    return ref


@volcap_task(name="enhance-shot", version="4", locations=("flow_weights",),
             libraries=(*ENHANCER_LIBRARIES, "OpenEXR"))
def enhance_shot(store: str, frames: ArtifactRef, enhancer: ArtifactRef, group: str,
                 settings: EnhanceSettings = EnhanceSettings(), flow_weights: str | None = None,
                 flow_weights_fingerprint: str | None = None) -> ArtifactRef:
    """Enhance a shot: ``frames`` (a ``render-shot`` tree of ``<frame:06d>.exr``) frame by frame
    in order with the ``train-enhancer`` model ``enhancer`` and prompt ``group``
    (:func:`~volcap_core.enhance.production.enhance_shot_frames`), conditioned through the exact
    flow the frames carry (``settings.flow = "rendered"``, DIS where a frame has none; v3). A tree
    of the same names: half RGBA EXRs with the render's header (shot metadata, camera, crop) plus
    ``volcap.enhanced``. Version 4: the low-frequency swap's RGB change is weighted by the swapped
    alpha (no colour added outside the matte; ``swap_low_frequency_encoded``).

    ``settings.flow = "raft"`` / ``"raft-small"``: torchvision's RAFT with the local weights file
    ``flow_weights`` (a location: its path is not in the key), its content pinned by
    ``flow_weights_fingerprint`` (:func:`~volcap_core.enhance.production.directory_fingerprint`,
    required with it). The back-end is built before anything is loaded or stored: no torchvision,
    no weights or weights that do not load fail naming the shot and the file
    (:func:`~volcap_core.enhance.production.shot_flow_backend`)."""
    from volcap_core.enhance.model import enhancer_from_bytes
    from volcap_core.enhance.production import enhance_shot_frames, shot_flow_backend

    s = ArtifactStore(store)
    log = get_run_logger()
    tree = s.get_tree(frames)
    names = sorted(tree)
    raft = settings.flow in ("raft", "raft-small")
    shot = _shot_name(s, tree, names, frames) if raft or flow_weights is not None else f"of frames {frames.digest}"
    if flow_weights is not None and not raft:
        raise ValueError(f"shot {shot}: flow_weights {flow_weights} given but settings.flow is {settings.flow!r} "
                         "(RAFT weights are for flow 'raft' / 'raft-small')")
    if flow_weights is not None and flow_weights_fingerprint is None:
        raise ValueError(f"shot {shot}: flow_weights {flow_weights} without flow_weights_fingerprint: the cache "
                         "key would not see the file's content (directory_fingerprint(path))")
    # before the enhancer is loaded (on the CPU, as RAFT then is) and before any frame is stored
    backend = shot_flow_backend(settings, flow_weights, shot=shot, fingerprint=flow_weights_fingerprint)
    rec = s.get_record(enhancer, EnhancerModel)
    model = enhancer_from_bytes(s.get_bytes(rec.model))
    bar = ProgressArtifact(artifact_key("enhance", group), f"Enhancing {len(names)} frame(s): frames done")

    def inputs():
        for name in names:
            yield name, s.get_bytes(tree[name].digest)

    def progress(done: int, name: str) -> None:
        bar.update(done, len(names))
        log.info("enhanced %s (%d/%d)", name, done, len(names))

    out = {name: s.put_bytes(data, MEDIA_EXR)
           for name, data in enhance_shot_frames(model, inputs(), settings, group=group,
                                                 model_digest=rec.model.digest, progress=progress,
                                                 flow_backend=backend, shot=shot)}
    bar.finish()
    return s.put_tree(out)


def _shot_name(s: ArtifactStore, tree, names: list[str], frames: ArtifactRef) -> str:
    """The shot a render-shot tree holds (its first frame's ``volcap.shot``), for messages."""
    from volcap_core.enhance.production import read_shot_frame

    if names:
        shot = read_shot_frame(s.get_bytes(tree[names[0]].digest))[0].get("volcap.shot")
        if shot:
            return str(shot)
    return f"of frames {frames.digest}"


__all__ = ["actor_prompt", "enhance_shot", "face_pairs", "train_enhancer_task"]
