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

Heavy imports (torch) happen when a backend runs, never when a stage's SPEC is imported.
"""
