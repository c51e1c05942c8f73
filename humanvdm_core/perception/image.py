"""Loading a user's photo into a clean, upright RGB(A) float image.

Contract of :func:`load_photo`:

- Reads every format OpenImageIO reads (PNG, JPEG, WebP, TIFF, EXR, BMP, ...), through one
  code path: the header is read first, then the pixels strip by strip.
- ``Photo.rgb`` is (H, W, 3) float32 in [0, 1], sRGB-encoded (display-referred), C-contiguous.
  8/16-bit integer files are normalised by their maximum (255, 65535). Float files (EXR, HDR)
  whose header does not say sRGB are taken as scene-linear: clipped to [0, 1] and sRGB-encoded.
- Grayscale (and gray+alpha) becomes RGB by repeating the channel.
- ``Photo.alpha`` is (H, W) float32 in [0, 1] when the file has an alpha channel, else ``None``.
  ``Photo.rgb`` is always *straight* (un-premultiplied) colour: PNG/WebP/TIFF with unassociated
  alpha are kept as stored; files with associated (premultiplied) alpha, which is what EXR stores,
  are divided by alpha where alpha > 1/255 (fully transparent pixels keep their stored colour).
- The EXIF/TIFF ``Orientation`` tag is applied, so a rotated phone JPEG comes out upright.
- Size limits (checked on the header, before any pixel is decoded):
  * short side < :data:`MIN_SIDE` (128 px): :class:`InputError` naming the size and the minimum;
  * more than :data:`MAX_FILE_PIXELS` pixels: :class:`InputError` (decoding would take too long);
  * long side > :data:`MAX_SIDE` (8192 px): the photo is *downscaled*, not refused. It is box-filtered
    by the smallest integer factor ``k`` that brings the long side to <= 8192 while it is decoded,
    strip by strip, so a 12,000-px (108-megapixel) photo never exists at full resolution in memory.
    The note is logged (logger ``humanvdm.perception``) and kept in ``Photo.notes``;
    ``Photo.original_size`` keeps the file's (upright) size and ``Photo.scale`` the factor.
- An unreadable, truncated or corrupt file raises :class:`InputError` naming the file.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from humanvdm_core.workflow.errors import InputError

log = logging.getLogger("humanvdm.perception")

MIN_SIDE = 128  # shortest accepted side, in pixels
MAX_SIDE = 8192  # longer photos are downscaled to at most this long side
MAX_FILE_PIXELS = 400_000_000  # refuse beyond this (a decompression bomb, or minutes of decoding)
_STRIP_ROWS = 256  # output rows decoded per strip


@dataclass
class Photo:
    """An upright photo: straight RGB float32 [0, 1] sRGB, optional alpha, where it came from."""

    rgb: np.ndarray  # (H, W, 3) float32 in [0, 1], sRGB-encoded, straight (not premultiplied)
    alpha: np.ndarray | None  # (H, W) float32 in [0, 1], or None when the file has no alpha channel
    path: Path
    original_size: tuple[int, int]  # (width, height) of the upright file, before any downscale
    notes: list[str] = field(default_factory=list)  # what loading changed (e.g. a downscale)

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def scale(self) -> float:
        """Pixels of ``rgb`` per pixel of the original file (1.0 unless downscaled)."""
        return self.width / self.original_size[0]

    @property
    def name(self) -> str:
        return self.path.name


def turned(photo: Photo, quarter_turns: int) -> Photo:
    """``photo`` turned by ``quarter_turns`` quarters counter-clockwise (``np.rot90``'s ``k``): its
    pixels, alpha and original size; the same file name."""
    k = quarter_turns % 4
    if k == 0:
        return photo
    alpha = None if photo.alpha is None else np.ascontiguousarray(np.rot90(photo.alpha, k))
    w, h = photo.original_size
    return Photo(np.ascontiguousarray(np.rot90(photo.rgb, k)), alpha, photo.path,
                 (h, w) if k % 2 else (w, h), list(photo.notes))


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values, clipped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def apply_orientation(image: np.ndarray, orientation: int) -> np.ndarray:
    """Turn an image stored with EXIF/TIFF ``Orientation`` 1..8 upright (rows, cols are axes 0, 1)."""
    if orientation == 2:  # mirrored left-right
        image = image[:, ::-1]
    elif orientation == 3:  # rotated 180
        image = image[::-1, ::-1]
    elif orientation == 4:  # mirrored top-bottom
        image = image[::-1]
    elif orientation == 5:  # transposed
        image = np.swapaxes(image, 0, 1)
    elif orientation == 6:  # stored rotated 90 counter-clockwise: turn 90 clockwise
        image = np.rot90(image, k=-1)
    elif orientation == 7:  # transverse
        image = np.rot90(image, k=1)[:, ::-1]
    elif orientation == 8:  # stored rotated 90 clockwise: turn 90 counter-clockwise
        image = np.rot90(image, k=1)
    return np.ascontiguousarray(image)


def _box_reduce(strip: np.ndarray, k: int) -> np.ndarray:
    """Average non-overlapping k x k blocks of an (h, w, c) strip whose h is a multiple of k."""
    if k == 1:
        return strip
    h, w, c = strip.shape
    w_out = w // k
    blocks = strip[:, : w_out * k].reshape(h // k, k, w_out, k, c)
    return blocks.mean(axis=(1, 3), dtype=np.float32)


def _strip_to_rgb(strip: np.ndarray, color_chs: list[int], alpha_ch: int, associated: bool,
                  linear: bool) -> np.ndarray:
    """Straight sRGB [0, 1] RGB of a decoded (h, w, nch) float strip."""
    color = strip[:, :, color_chs]
    if color.shape[2] < 3:  # grayscale (or an odd two-channel file): repeat the first channel
        color = np.repeat(color[:, :, :1], 3, axis=2)
    if associated:  # premultiplied: divide by alpha where it is not ~0
        a = np.clip(strip[:, :, alpha_ch:alpha_ch + 1], 0.0, 1.0)
        np.divide(color, a, out=color, where=a > 1.0 / 255.0)
    return srgb_encode(color) if linear else np.clip(color, 0.0, 1.0)


def load_photo(path: str | Path) -> Photo:
    """Load ``path`` as an upright :class:`Photo`; see the module docstring for the contract."""
    import OpenImageIO as oiio

    path = Path(path).expanduser()
    if not path.is_file():
        raise InputError(f"photo not found: {path}")
    hint = oiio.ImageSpec()
    hint.attribute("oiio:UnassociatedAlpha", 1)  # keep PNG/TIFF straight alpha as stored
    inp = oiio.ImageInput.open(str(path), hint)
    if inp is None:
        reason = oiio.geterror().strip() or "unknown format"
        raise InputError(f"cannot read {path.name}: not an image this program can read, or the file is "
                         f"corrupt ({reason}). Re-export it as PNG or JPEG.")
    try:
        spec = inp.spec()
        width, height, nch = int(spec.width), int(spec.height), int(spec.nchannels)
        orientation = spec.get_int_attribute("Orientation", 1)
        upright = (height, width) if orientation in (5, 6, 7, 8) else (width, height)
        if min(width, height) < MIN_SIDE:
            raise InputError(f"{path.name} is too small: {upright[0]}x{upright[1]} px; the shorter side must "
                             f"be at least {MIN_SIDE} px. Use a larger photo of the person.")
        if width * height > MAX_FILE_PIXELS:
            raise InputError(f"{path.name} is too large: {upright[0]}x{upright[1]} px "
                             f"({width * height / 1e6:.0f} megapixels; at most {MAX_FILE_PIXELS // 1_000_000} "
                             f"are accepted). Resize it to at most {MAX_SIDE} px on the long side.")
        k = max(1, math.ceil(max(width, height) / MAX_SIDE))
        alpha_ch = int(spec.alpha_channel)
        associated = alpha_ch >= 0 and spec.get_int_attribute("oiio:UnassociatedAlpha", 0) == 0
        colorspace = spec.get_string_attribute("oiio:ColorSpace", "").lower()
        is_float = spec.format.basetype in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE)
        linear = is_float and "srgb" not in colorspace

        out_h, out_w = height // k, width // k
        color_chs = [c for c in range(nch) if c != alpha_ch][:3]
        rgb = np.empty((out_h, out_w, 3), np.float32)
        alpha = np.empty((out_h, out_w), np.float32) if alpha_ch >= 0 else None
        rows = _STRIP_ROWS * k
        for y in range(0, out_h * k, rows):
            y_end = min(y + rows, out_h * k)
            strip = inp.read_scanlines(0, 0, y, y_end, 0, 0, nch, "float")
            if strip is None or inp.has_error:
                raise InputError(f"cannot read {path.name}: the file is truncated or corrupt "
                                 f"({inp.geterror().strip() or 'decode failed'}). Re-export it.")
            strip = _box_reduce(np.asarray(strip, np.float32).reshape(y_end - y, width, nch), k)
            rgb[y // k: y_end // k] = _strip_to_rgb(strip, color_chs, alpha_ch, associated, linear)
            if alpha is not None:
                alpha[y // k: y_end // k] = np.clip(strip[:, :, alpha_ch], 0.0, 1.0)
    finally:
        inp.close()

    rgb = apply_orientation(rgb, orientation)
    alpha = None if alpha is None else apply_orientation(alpha, orientation)
    notes: list[str] = []
    if k > 1:
        note = (f"{path.name}: {upright[0]}x{upright[1]} px is larger than {MAX_SIDE} px on the long side; "
                f"downscaled by {k} to {rgb.shape[1]}x{rgb.shape[0]} px while decoding")
        log.info(note)
        notes.append(note)
    return Photo(rgb=rgb, alpha=alpha, path=path, original_size=upright, notes=notes)
