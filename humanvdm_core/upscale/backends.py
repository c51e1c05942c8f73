"""The model backends of :mod:`humanvdm_core.upscale.core`: ``realesrgan`` and ``codeformer``.

Both map one RGBA frame (H, W, 4) float32 to (target, target, 4) float32, like every upscale
backend:

- ``realesrgan``: the RGB goes through Real-ESRGAN's RRDBNet (×4 or ×2, from the checkpoint;
  tiled, see :func:`humanvdm_core.upscale.rrdbnet.upscale_rgb`), then is resized to the target
  (area averaging when the model overshoots, e.g. 576 -> 2304 -> 1080; Lanczos without sharpening
  when it falls short).  Alpha is resampled with the embedded backend's kernel and never goes
  through the model.
- ``codeformer``: as CodeFormer's official inference with a Real-ESRGAN background: faces are
  detected on the source frame (:mod:`humanvdm_core.upscale.faces`), aligned to the FFHQ template
  at CodeFormer's crop size (512² for the official model), restored with fidelity ``w``
  (paper: 0.7) and pasted back with a feathered mask onto the Real-ESRGAN-upscaled frame, which
  is then resized to the target.  A frame without a detectable face (the back of an orbit) gets
  the Real-ESRGAN result alone.  CodeFormer's weights are under the S-Lab License 1.0
  (non-commercial use only).

Models are loaded once per process per weight file; a missing file raises
:class:`~humanvdm_core.errors.MissingWeightsError` naming it and where to get it.
"""

from __future__ import annotations

import numpy as np

from humanvdm_core.upscale.core import UpscaleOptions, resample_color

TILE_PAD = 24  # context pixels around each Real-ESRGAN tile


def _alpha(frame: np.ndarray, opts: UpscaleOptions) -> np.ndarray:
    import cv2

    a = np.ascontiguousarray(frame[..., 3], dtype=np.float32)
    size = opts.target_size
    flag = cv2.INTER_AREA if size <= min(a.shape) else (cv2.INTER_LANCZOS4 if opts.method == "lanczos"
                                                        else cv2.INTER_CUBIC)
    return np.clip(cv2.resize(a, (size, size), interpolation=flag), 0.0, 1.0)


def _finish(rgb_up: np.ndarray, frame: np.ndarray, opts: UpscaleOptions) -> np.ndarray:
    rgb = resample_color(rgb_up, opts.target_size, opts.method, sharpen=0.0, clamp=opts.clamp)
    return np.concatenate([rgb, _alpha(frame, opts)[..., None]], axis=-1).astype(np.float32)


def upscale_realesrgan(frame: np.ndarray, opts: UpscaleOptions) -> np.ndarray:
    """Real-ESRGAN on the whole frame's RGB, then resized to the target; alpha resampled."""
    from humanvdm_core.upscale import rrdbnet

    net = rrdbnet.load(opts.realesrgan_weights)
    return _finish(rrdbnet.upscale_rgb(net, frame[..., :3], opts.tile, TILE_PAD), frame, opts)


def restore_faces(rgb: np.ndarray, background: np.ndarray, scale: float,
                  opts: UpscaleOptions) -> tuple[np.ndarray, int]:
    """CodeFormer on every face of ``rgb`` (source frame), pasted into ``background`` (``scale`` x larger)."""
    from humanvdm_core.upscale import codeformer, faces

    net = codeformer.load(opts.codeformer_weights)
    found = faces.detect_faces(rgb)[:opts.max_faces]
    out = background
    for face in found:
        matrix = faces.alignment(face.landmarks, net.size)
        crop = faces.align_face(rgb, matrix, net.size)
        out = faces.paste_face(out, codeformer.restore_face(net, crop, opts.fidelity), matrix, scale)
    return out, len(found)


def upscale_codeformer(frame: np.ndarray, opts: UpscaleOptions) -> np.ndarray:
    """Real-ESRGAN background + CodeFormer faces, then resized to the target; alpha resampled."""
    from humanvdm_core.upscale import codeformer, rrdbnet

    codeformer.load(opts.codeformer_weights)  # both files are checked before any work
    bg_net = rrdbnet.load(opts.realesrgan_weights)
    rgb = np.clip(frame[..., :3], 0.0, 1.0).astype(np.float32)
    background = rrdbnet.upscale_rgb(bg_net, rgb, opts.tile, TILE_PAD)
    restored, _ = restore_faces(rgb, background, float(bg_net.scale), opts)
    return _finish(np.clip(restored, 0.0, 1.0), frame, opts)
