"""Artifact file formats: EXR images (OpenImageIO), NPZ arrays, PNG exports.

Contracts:
- Every write is atomic (:mod:`humanvdm_core.workflow.atomic`): data goes to a temporary file in
  the destination folder, then ``os.replace`` puts it in place, so a killed process never leaves a
  half-written file under the final name.
- Writes are deterministic: the same arrays and attributes give the same bytes (NPZ members get a
  fixed timestamp, EXR headers carry no time), so content hashes are stable across reruns.
- EXR: half-float channels, ZIP compression, ``oiio:ColorSpace`` stated, a ``humanvdm:pixel_hash``
  of the stored pixels and caller-supplied ``humanvdm:*`` attributes (what produced it). Attributes
  must not hold run-specific values (times, run keys): they would change the artifact's id.
- NPZ: named arrays plus ``__schema__`` (name) and ``__schema_version__``; readers check both.
- A write that fails because the disk is full raises ``OSError`` with errno ENOSPC (OpenImageIO
  reports only "File output failed": an EXR write that fails while the destination's file system
  has less room than the image's pixels is reported as ENOSPC), and leaves no temporary file.
"""

from __future__ import annotations

import errno
import hashlib
import io
import os
import shutil
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from humanvdm_core.workflow.atomic import atomic_path, atomic_write_bytes

EXR_COLORSPACE = "sRGB"  # frames hold display-referred sRGB-encoded values, as SV3D/CodeFormer expect
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


# ----------------------------------------------------------------------------- EXR

def _channel_names(n: int) -> list[str]:
    return {1: ["Y"], 2: ["Y", "A"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}[n]


def write_exr(
    path: str | os.PathLike,
    image: np.ndarray,
    attrs: Mapping[str, str | int | float] | None = None,
    channels: list[str] | None = None,
    colorspace: str = EXR_COLORSPACE,
) -> None:
    """Write an (H, W) or (H, W, C) float image as a half-float EXR, atomically."""
    import OpenImageIO as oiio

    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    h, w, c = img.shape
    names = channels or _channel_names(c)
    if len(names) != c:
        raise ValueError(f"{len(names)} channel names for {c} channels")
    half = np.ascontiguousarray(img.astype(np.float16))
    spec = oiio.ImageSpec(w, h, c, "half")
    spec.channelnames = tuple(names)
    if "A" in names:
        spec.alpha_channel = names.index("A")
    spec.attribute("compression", "zip")
    spec.attribute("oiio:ColorSpace", colorspace)
    spec.attribute("DateTime", "1980:01:01 00:00:00")  # fixed: OIIO would stamp the write time (capDate)
    spec.attribute("humanvdm:pixel_hash", hashlib.sha256(half.tobytes()).hexdigest()[:32])
    for key, value in (attrs or {}).items():
        spec.attribute(key if ":" in key else f"humanvdm:{key}", value)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise _write_error(path, f"cannot write EXR {path}: {oiio.geterror()}", half.nbytes)
        ok = out.write_image(half)
        out.close()
        if not ok:
            raise _write_error(path, f"cannot write EXR {path}: {out.geterror()}", half.nbytes)


def _write_error(path: str | os.PathLike, message: str, nbytes: int) -> OSError:
    """The error for a failed write of ``nbytes`` to ``path`` by a library that does not say why:
    ENOSPC when its file system has less room than that (checked while the partial file is there)."""
    try:
        free = shutil.disk_usage(Path(path).parent).free
    except OSError:
        free = nbytes
    if free < nbytes:
        return OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({message})", str(path))
    return OSError(message)


def read_exr(path: str | os.PathLike, with_attrs: bool = False):
    """Read an EXR as float32 (H, W, C); with ``with_attrs`` also return its header attributes."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot read EXR {path}: {oiio.geterror()}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise OSError(f"cannot read EXR {path}: {inp.geterror()}")
        img = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
        if not with_attrs:
            return img
        attrs = {p.name: p.value for p in spec.extra_attribs}
        attrs["channels"] = list(spec.channelnames)
        return img, attrs
    finally:
        inp.close()


# ----------------------------------------------------------------------------- NPZ

def write_npz(path: str | os.PathLike, arrays: Mapping[str, np.ndarray], schema: str, version: int = 1) -> None:
    """Write named arrays with a schema name and version; byte-identical for identical input."""
    members = dict(arrays)
    members["__schema__"] = np.array(schema)
    members["__schema_version__"] = np.array(version, dtype=np.int64)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(members):
            arr = np.asarray(members[name])
            if arr.dtype == object:
                raise TypeError(f"array {name!r} has dtype object; store strings as np.str_ arrays")
            data = io.BytesIO()
            np.lib.format.write_array(data, arr if arr.flags.c_contiguous else arr.copy(order="C"), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, data.getvalue())
    atomic_write_bytes(path, buf.getvalue())


def read_npz(path: str | os.PathLike, schema: str | None = None, version: int | None = None) -> dict[str, np.ndarray]:
    """Read an NPZ written by :func:`write_npz`, checking its schema name and version when given."""
    with np.load(path, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    found = str(data.pop("__schema__", ""))
    found_version = int(data.pop("__schema_version__", -1))
    if schema is not None and found != schema:
        raise ValueError(f"{path}: expected schema {schema!r}, found {found!r}")
    if version is not None and found_version != version:
        raise ValueError(f"{path}: {schema} schema version {found_version}, this code reads version {version}")
    return data


# ----------------------------------------------------------------------------- PNG (exports for people)

def to_uint8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype == np.uint8:
        return img
    return np.clip(np.rint(img.astype(np.float32) * 255.0), 0, 255).astype(np.uint8)


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB(A) image (float in [0, 1] or uint8) as PNG, atomically."""
    import cv2

    img = to_uint8(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    ok, encoded = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"cannot encode PNG {path}")
    atomic_write_bytes(path, encoded.tobytes())
