"""Real-model backends: pure-PyTorch architectures that load the official checkpoints' key layouts.

Nothing here downloads anything and nothing needs torchvision.  Each architecture module builds
its network from the shapes stored in a checkpoint (so a tiny test model with the same key names
loads through the same path as the official weights) and refuses a checkpoint whose keys do not
match, listing the missing and unexpected ones (:class:`~humanvdm_core.models.checkpoint.CheckpointError`).

- :mod:`.rrdbnet`    Real-ESRGAN's RRDBNet (``RealESRGAN_x4plus.pth``, ×4 / ×2 / ×1), tiled inference.
- :mod:`.codeformer` CodeFormer (``codeformer.pth``), face restoration at 512² with fidelity ``w``.
- :mod:`.faces`      face detection (MediaPipe's bundled detector), 5-point alignment, feathered paste-back.
- :mod:`.rife`       RIFE v4.6 IFNet (Practical-RIFE ``flownet.pkl``), arbitrary-time interpolation.
- :mod:`.upscalers`  the ``realesrgan`` and ``codeformer`` backends of :mod:`humanvdm_core.upscale`.
- :mod:`.sv3d`       SV3D_u / SV3D_p (``sv3d_*.safetensors``, sgm layout): loading, EDM Euler sampling with
                     the triangle CFG, the ``diffuse`` backends; parts in :mod:`.sv3d_unet` (video UNet),
                     :mod:`.sv3d_vae` (conditioning encoder, temporal decoder), :mod:`.openclip_vision`
                     (OpenCLIP ViT-H/14 image tower).
- :mod:`.sv3d_finetune` fine-tuning the SV3D UNet on rendered orbits (the ``finetune`` stage), resumable.

Heavy imports (torch) happen when a backend runs, never when a stage's SPEC is imported.
"""
