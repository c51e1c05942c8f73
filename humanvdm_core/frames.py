"""Frame-set artifacts: an ordered video of RGBA frames with explicit cameras.

Layout of a frame-set directory::

    frames/0000.exr ...   RGBA half EXR; RGB is sRGB-encoded, already composited over the
                          background colour; A is the subject's coverage (mask)
    cameras.npz           :class:`humanvdm_core.cameras.Cameras` (one camera per frame)
    [depth/0000.exr ...]  optional: camera-space z (0 where empty)
    [normals/0000.exr ...] optional: world-space unit normals (0 where empty)

No stage guesses cameras: every frame set carries them.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from humanvdm_core.cameras import Cameras
from humanvdm_core.io import EXR_COLORSPACE, read_exr, write_exr

FRAMES_DIR = "frames"
CAMERAS_FILE = "cameras.npz"


def frame_name(index: int) -> str:
    return f"{index:04d}.exr"


def frame_paths(root: str | Path, layer: str = FRAMES_DIR) -> list[Path]:
    paths = sorted((Path(root) / layer).glob("*.exr"))
    if not paths:
        raise FileNotFoundError(f"no {layer}/*.exr in frame set {root}")
    return paths


def write_frames(
    root: str | Path,
    frames: Iterable[np.ndarray],
    cameras: Cameras | None,
    attrs: dict[str, str] | None = None,
    layer: str = FRAMES_DIR,
    colorspace: str | None = None,
) -> int:
    """Write frames (each (H, W, C) float) as ``layer/NNNN.exr`` and the cameras; returns the count.

    The colour space defaults to sRGB for the ``frames`` layer and ``Raw`` (data, not colour) for
    the others (depth, normals).
    """
    root = Path(root)
    space = colorspace or (EXR_COLORSPACE if layer == FRAMES_DIR else "Raw")
    n = 0
    for i, frame in enumerate(frames):
        write_exr(root / layer / frame_name(i), frame, attrs={**(attrs or {}), "frame_index": i}, colorspace=space)
        n += 1
    if cameras is not None:
        if len(cameras) != n:
            raise ValueError(f"{n} frames but {len(cameras)} cameras")
        cameras.save(root / CAMERAS_FILE)
    return n


def read_frame(path: str | Path) -> np.ndarray:
    return read_exr(path)


def read_frames(root: str | Path, layer: str = FRAMES_DIR, indices: Sequence[int] | None = None) -> np.ndarray:
    """All frames of a layer as one float32 array (N, H, W, C)."""
    paths = frame_paths(root, layer)
    if indices is not None:
        paths = [paths[i] for i in indices]
    return np.stack([read_exr(p) for p in paths])


def open_frame_set(root: str | Path) -> tuple[list[Path], Cameras]:
    """The frame paths and cameras of a frame set, checked to match; InputError when they cannot
    be read or do not match (the user-facing check every stage reading frames makes)."""
    from humanvdm_core.workflow.errors import InputError

    try:
        paths = frame_paths(root)
        cameras = read_cameras(root)
    except (FileNotFoundError, ValueError) as e:
        raise InputError(f"not a usable frame set: {e}") from None
    if len(paths) != len(cameras):
        raise InputError(f"frame set {root}: {len(paths)} frames but {len(cameras)} cameras")
    return paths, cameras


def read_cameras(root: str | Path) -> Cameras:
    path = Path(root) / CAMERAS_FILE
    if not path.exists():
        raise FileNotFoundError(f"frame set {root} has no {CAMERAS_FILE}: every frame set must carry its cameras")
    return Cameras.load(path)
