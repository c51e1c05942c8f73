"""Upscale a frame set to ``target_size`` x ``target_size`` (paper section 3.2, super-resolution).

Contract (input and output are frame sets, see :mod:`humanvdm_core.frames`):

- Input frames must be square RGBA and all the same size, with one camera per frame whose
  width/height match the frames; anything else raises :class:`InputError`.
- **Pass-through:** when the frames are already ``target_size`` x ``target_size`` the output
  directory becomes a byte-identical copy of the input (every file, same relative paths), so its
  content hash -- the artifact id -- is unchanged and downstream stages stay cached.
- Otherwise every frame is resampled by the chosen backend (a function picked by name from
  :data:`BACKENDS`), the cameras are rescaled with :meth:`Cameras.scaled`, and the optional
  per-pixel layers (``depth/``, ``normals/`` and any other folder of EXRs) are resampled with
  nearest-neighbour so that no depth or normal is ever averaged across the silhouette (a blend of
  foreground depth and the empty value 0 would invent geometry).  Other files are not carried over.

The ``embedded`` backend (no weights): Lanczos-4 (or bicubic) resampling of the colour, then an
unsharp mask whose result is clamped to the local range of the source pixels around each output
pixel.  The clamp removes every overshoot, so the sharpening restores edge contrast without
the bright/dark halos an unsharp mask otherwise draws along the subject's silhouette (the RGB is
composited over the background there).  Alpha is resampled with the same kernel, never sharpened,
and clamped to [0, 1].  Downscaling (input larger than the target) uses area averaging and no
sharpening.

Model backends (local weights, nothing downloaded; :mod:`humanvdm_core.upscale.backends`):
``realesrgan`` (Real-ESRGAN RRDBNet on the whole frame, then resized to the target) and
``codeformer`` (CodeFormer on detected faces, fidelity w, pasted onto a Real-ESRGAN background).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from humanvdm_core.cameras import Cameras
from humanvdm_core.frames import CAMERAS_FILE, FRAMES_DIR, frame_name, open_frame_set
from humanvdm_core.io import read_exr, write_exr
from humanvdm_core.workflow.errors import InputError

DEFAULT_TARGET_SIZE = 1080
# Chosen by measurement (benchmarks/bench_interpolate.py, "upscale_576_to_1080": 576 renders upscaled
# and compared with 1080 renders of the same views; also a photo and synthetic noise): +0.7 to +0.8 dB
# PSNR over plain Lanczos on renders, +1.5 dB on a photo, +2.6 dB on noise.  A wider sigma (1.3) gains
# another 0.3-0.5 dB on renders but loses 6.7 dB on the noise texture (it boosts mid frequencies the
# downscale never attenuated), so the narrow one is the robust default.
DEFAULT_SHARPEN = 0.8  # unsharp-mask amount
DEFAULT_SHARPEN_SIGMA = 0.55  # Gaussian sigma of the unsharp mask, in *input* pixels (1.03 output px at 576 -> 1080)
RESAMPLE_METHODS = ("lanczos", "bicubic")


@dataclass(frozen=True)
class UpscaleOptions:
    target_size: int = DEFAULT_TARGET_SIZE
    method: str = "lanczos"
    sharpen: float = DEFAULT_SHARPEN
    sharpen_sigma: float = DEFAULT_SHARPEN_SIGMA
    clamp: bool = True  # anti-halo clamp (off only to measure what it does)
    # model backends (humanvdm_core.upscale.backends): local weight files and their settings
    realesrgan_weights: str = ""  # Real-ESRGAN RRDBNet checkpoint (realesrgan; codeformer's background)
    codeformer_weights: str = ""  # CodeFormer checkpoint (codeformer)
    fidelity: float = 0.7  # CodeFormer's w: 0 = best quality, 1 = most faithful (paper: 0.7)
    tile: int = 384  # Real-ESRGAN tile size in input pixels (0: whole frame at once)
    max_faces: int = 4  # faces restored per frame, largest first


# A backend maps one RGBA frame (H, W, 4) float32 to (target, target, 4) float32.
UpscaleBackend = Callable[[np.ndarray, UpscaleOptions], np.ndarray]


def _interp_flag(method: str) -> int:
    import cv2

    if method not in RESAMPLE_METHODS:
        raise ValueError(f"unknown resample method {method!r}; choose from {RESAMPLE_METHODS}")
    return cv2.INTER_LANCZOS4 if method == "lanczos" else cv2.INTER_CUBIC


def resample_color(rgb: np.ndarray, size: int, method: str = "lanczos", sharpen: float = DEFAULT_SHARPEN,
                   sharpen_sigma: float = DEFAULT_SHARPEN_SIGMA, clamp: bool = True) -> np.ndarray:
    """Resample an (H, W, C) float image to ``size`` x ``size`` with halo-free sharpening.

    Upscaling: kernel resampling, then ``out = up + sharpen * (up - blur(up))`` (Gaussian blur of
    ``sharpen_sigma`` input pixels) clamped per channel to [min, max] of the 3x3 source neighbourhood
    (bilinearly carried to the output grid), so no output pixel leaves the range of the source
    pixels it came from (no ringing, no halos).
    """
    import cv2

    img = np.ascontiguousarray(rgb, dtype=np.float32)
    h, w = img.shape[:2]
    if size <= min(h, w):
        return cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    up = cv2.resize(img, (size, size), interpolation=_interp_flag(method))
    if sharpen > 0:
        blur = cv2.GaussianBlur(up, (0, 0), sharpen_sigma * size / min(h, w), borderType=cv2.BORDER_REFLECT)
        up = up + sharpen * (up - blur)
    if clamp:
        kernel = np.ones((3, 3), np.uint8)
        lo = cv2.resize(cv2.erode(img, kernel), (size, size), interpolation=cv2.INTER_LINEAR)
        hi = cv2.resize(cv2.dilate(img, kernel), (size, size), interpolation=cv2.INTER_LINEAR)
        up = np.clip(up, lo, hi)
    return np.clip(up, 0.0, 1.0)


def upscale_embedded(frame: np.ndarray, opts: UpscaleOptions) -> np.ndarray:
    """The embedded backend: halo-free sharpened resampling of RGB, plain resampling of alpha."""
    import cv2

    size = opts.target_size
    rgb = resample_color(frame[..., :3], size, opts.method, opts.sharpen, opts.sharpen_sigma, opts.clamp)
    a = np.ascontiguousarray(frame[..., 3], dtype=np.float32)
    if size <= min(a.shape):
        alpha = cv2.resize(a, (size, size), interpolation=cv2.INTER_AREA)
    else:
        alpha = cv2.resize(a, (size, size), interpolation=_interp_flag(opts.method))
    return np.concatenate([rgb, np.clip(alpha, 0.0, 1.0)[..., None]], axis=-1).astype(np.float32)


def upscale_realesrgan(frame: np.ndarray, opts: UpscaleOptions) -> np.ndarray:
    """Real-ESRGAN (local RRDBNet weights), see :mod:`humanvdm_core.upscale.backends`."""
    from humanvdm_core.upscale.backends import upscale_realesrgan as run

    return run(frame, opts)


def upscale_codeformer(frame: np.ndarray, opts: UpscaleOptions) -> np.ndarray:
    """CodeFormer faces on a Real-ESRGAN background, see :mod:`humanvdm_core.upscale.backends`."""
    from humanvdm_core.upscale.backends import upscale_codeformer as run

    return run(frame, opts)


BACKENDS: dict[str, UpscaleBackend] = {"embedded": upscale_embedded, "realesrgan": upscale_realesrgan,
                                       "codeformer": upscale_codeformer}


def resample_layer_nearest(image: np.ndarray, size: int) -> np.ndarray:
    """Nearest-neighbour resampling of a data layer (depth, normals): values are never mixed."""
    import cv2

    img = np.ascontiguousarray(image, dtype=np.float32)
    out = cv2.resize(img, (size, size), interpolation=cv2.INTER_NEAREST_EXACT)
    return out[..., None] if out.ndim == 2 and image.ndim == 3 else out


def _frame_shape(path: Path) -> tuple[int, int, int]:
    """(height, width, channels) of an EXR frame, read from its header."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"cannot read frame {path}: {oiio.geterror()}")
    try:
        spec = inp.spec()
        return spec.height, spec.width, spec.nchannels
    finally:
        inp.close()


def check_frame_set(root: Path) -> tuple[list[Path], Cameras, int]:
    """Validate a frame set of square RGBA frames of one size; returns (frame paths, cameras, size)."""
    root = Path(root)
    paths, cams = open_frame_set(root)
    h, w, c = _frame_shape(paths[0])
    if c != 4:
        raise InputError(f"frame set {root}: frames must be RGBA (4 channels), {paths[0].name} has {c}")
    if h != w:
        raise InputError(f"frame set {root}: frames must be square (orbit frames are), got {w}x{h}; "
                         "crop or pad them to a square first")
    for p in paths[1:]:
        if _frame_shape(p) != (h, w, c):
            hh, ww, cc = _frame_shape(p)
            raise InputError(f"frame set {root}: {p.name} is {ww}x{hh} with {cc} channels but {paths[0].name} is "
                             f"{w}x{h} with {c}; all frames must have the same size")
    if (cams.width, cams.height) != (w, h):
        raise InputError(f"frame set {root}: cameras are for {cams.width}x{cams.height} but frames are {w}x{h}")
    return paths, cams, w


def copy_tree(src: Path, dst: Path) -> int:
    """Copy every file of ``src`` to the same relative path under ``dst`` (byte for byte)."""
    n = 0
    for path in sorted(p for p in Path(src).rglob("*") if p.is_file()):
        target = Path(dst) / path.relative_to(src)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, target)
        n += 1
    return n


def upscale_frame_set(src: str | Path, dst: str | Path, opts: UpscaleOptions, backend: str = "embedded",
                      attrs: dict[str, str] | None = None, log=None) -> dict:
    """Upscale the frame set ``src`` into the (empty or new) directory ``dst``; returns a summary."""
    src, dst = Path(src), Path(dst)
    if backend not in BACKENDS:
        raise InputError(f"unknown upscale backend {backend!r}; available: {sorted(BACKENDS)}")
    if opts.target_size < 1:
        raise InputError(f"target_size must be positive, got {opts.target_size}")
    paths, cams, size = check_frame_set(src)
    if size == opts.target_size:
        n = copy_tree(src, dst)
        if log:
            log.info("frames already %dx%d: pass-through (copied %d files unchanged)", size, size, n)
        return {"passthrough": True, "frames": len(paths), "source_size": size, "target_size": size}

    from humanvdm_core.workflow.progress import report

    fn = BACKENDS[backend]
    for i, p in enumerate(paths):
        out = fn(read_exr(p), opts)
        write_exr(dst / FRAMES_DIR / frame_name(i), out, attrs={**(attrs or {}), "frame_index": i})
        report(i + 1, len(paths), "frames", f"upscale to {opts.target_size}²")
    cams.scaled(opts.target_size, opts.target_size).save(dst / CAMERAS_FILE)

    layers = sorted(d.name for d in src.iterdir() if d.is_dir() and d.name != FRAMES_DIR and any(d.glob("*.exr")))
    for layer in layers:
        for i, p in enumerate(sorted((src / layer).glob("*.exr"))):
            img, hdr = read_exr(p, with_attrs=True)
            write_exr(dst / layer / p.name, resample_layer_nearest(img, opts.target_size),
                      attrs={**(attrs or {}), "frame_index": i, "resample": "nearest"},
                      channels=hdr["channels"],
                      colorspace=str(hdr.get("oiio:ColorSpace", "Linear")))
    skipped = sorted(str(p.relative_to(src)) for p in src.rglob("*") if p.is_file()
                     and p.parts[len(src.parts)] not in (FRAMES_DIR, CAMERAS_FILE, *layers))
    if log:
        log.info("upscaled %d frames %d -> %d (%s); layers resampled nearest: %s", len(paths), size,
                 opts.target_size, backend, layers or "none")
        if skipped:  # e.g. diffuse's proxy.npz, which its readers take from diffuse itself: not doubtful
            log.info("not carried over: %s", skipped)
    return {"passthrough": False, "frames": len(paths), "source_size": size, "target_size": opts.target_size,
            "layers": layers, "skipped": skipped}
