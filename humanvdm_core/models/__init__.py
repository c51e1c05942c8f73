"""Real-model backends: pure-PyTorch architectures that load the official checkpoints' key layouts
(here SV3D's, for ``diffuse`` and ``finetune``, and the tools every backend shares).

Nothing here downloads anything and nothing needs torchvision.  Each architecture module builds
its network from the shapes stored in a checkpoint (so a tiny test model with the same key names
loads through the same path as the official weights) and refuses a checkpoint whose keys do not
match, listing the missing and unexpected ones (:class:`~humanvdm_core.models.checkpoint.CheckpointError`).

- :mod:`.checkpoint` loading official checkpoints (unwrap, strip prefixes, check keys, cache), and
  :mod:`.blocks` autoencoder layers: shared with the upscale and interpolate backends, which live
  beside their stage's module (:mod:`humanvdm_core.upscale`, :mod:`humanvdm_core.interpolate`).
- :mod:`.sv3d`       SV3D_u / SV3D_p (``sv3d_*.safetensors``, sgm layout): loading, EDM Euler sampling with
                     the triangle CFG, the ``diffuse`` backends; parts in :mod:`.sv3d_unet` (video UNet),
                     :mod:`.sv3d_vae` (conditioning encoder, temporal decoder), :mod:`.openclip_vision`
                     (OpenCLIP ViT-H/14 image tower).
- :mod:`.sv3d_finetune` fine-tuning the SV3D UNet on rendered orbits (the ``finetune`` stage), resumable.

Heavy imports (torch) happen when a backend runs, never when a stage's SPEC is imported.
"""
