"""The Detail Enhancer (the paper's "Detail Enhancement Model").

Modules (imported on demand: :mod:`~volcap_core.enhance.model` pulls in diffusers, seconds to import):

- :mod:`~volcap_core.enhance.model`: the widened Flux transformer + Flux VAE + per-group prompt
  embeddings (:class:`~volcap_core.enhance.model.Enhancer`, ``EnhancerConfig``), latents, packing,
  the noise schedule, persistence (diffusers directories, safetensors bytes).
- :mod:`~volcap_core.enhance.lora`: low-rank adapters for the transformer (add, merge).
- :mod:`~volcap_core.enhance.training`: rectified-flow fine-tuning (LoRA or full), checkpoints,
  exact resumption.
- :mod:`~volcap_core.enhance.inference`: Euler sampling, tiled latent inference, per-frame and
  per-sequence enhancement.
- :mod:`~volcap_core.enhance.temporal`: optical-flow back-ends, warping, the validity mask.
- :mod:`~volcap_core.enhance.pyramid`: Laplacian pyramid and the low-frequency swap.
- :mod:`~volcap_core.enhance.pairs`: LQ/HQ pair sequences.
- :mod:`~volcap_core.enhance.metrics`: PSNR and SSIM (:mod:`volcap_core.image_metrics`'s), TPSNR,
  flicker, warp error.
"""
