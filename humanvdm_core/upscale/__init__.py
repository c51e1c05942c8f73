"""The ``upscale`` stage's library: :mod:`.core` upscales a frame set (the contract, the ``embedded``
backend, backend dispatch); the model backends beside it: :mod:`.backends` (``realesrgan``,
``codeformer``), :mod:`.rrdbnet` Real-ESRGAN's RRDBNet (``RealESRGAN_x4plus.pth``, ×4 / ×2 / ×1,
tiled inference), :mod:`.codeformer` CodeFormer (``codeformer.pth``, face restoration at 512² with
fidelity ``w``), :mod:`.faces` face detection (MediaPipe's bundled detector), 5-point alignment and
feathered paste-back. Shared checkpoint tools are in :mod:`humanvdm_core.models`."""
