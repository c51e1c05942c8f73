"""Frame interpolation of an orbit video (paper section 3.2): N key frames -> (N-1)*2**passes+1 frames.

Contract (input and output are frame sets, see :mod:`humanvdm_core.frames`):

- Input: at least 2 RGBA frames, all the same size, one camera per frame (cameras sized like the
  frames); anything else raises :class:`InputError`.  The orbit is an open sequence (no wrap from
  the last frame to the first), so the SV3D orbit's 21 frames become 41 after one ×2 pass and 81
  after two.
- Output: key frame ``i`` lands at index ``i * 2**passes`` with identical pixels; every in-between
  frame sits at fraction ``t = k / 2**passes`` of its key interval.  Cameras come from
  :func:`humanvdm_core.cameras.upsample_cameras` (slerp on the orbit), so in-between azimuths are
  the key azimuths interpolated along the shorter arc.  Each EXR carries ``humanvdm:keyframe`` (1 for
  a key frame, 0 for a synthesised one) and ``humanvdm:time`` (key-frame units).
- Optional ``depth/`` and ``normals/`` layers are **not** carried over: in-between depth and normals
  cannot be synthesised faithfully from 2D flow, and no downstream stage may take a guess for a
  measurement.
- Schedules: ``direct`` synthesises all in-between times of an interval from its two key frames (one
  flow pair per interval, no compounding of synthesis errors); ``recursive`` applies ×2 ``passes``
  times as the paper does with PerVFI (each pass sees the previous pass's outputs).

Backends are functions chosen by name (:data:`BACKENDS`) with the signature
``(frame0, frame1, times, opts) -> list of frames``; ``rife`` (RIFE v4.6, local weights,
:mod:`humanvdm_core.interpolate.rife`) takes any t.  ``pervfi`` (PerVFI v00 + RAFT, local weights,
:mod:`humanvdm_core.interpolate.pervfi`) is a ×2 model -- its released weights are trained on triplets
(t = 0.5) -- so it always runs with the ``recursive`` schedule, as the paper applies it (21 -> 41 ->
81): a ``direct`` schedule is overridden for it (:data:`RECURSIVE_ONLY`, :func:`effective_schedule`),
logged, and the schedule that ran is what the frames' ``interpolate_schedule`` attribute records.
The ``embedded`` backend has two methods:

- ``flow`` (default):
  1. bidirectional optical flow F_01, F_10 with OpenCV DIS on the luma, at ``flow_scale`` of the
     resolution (preset ``fine`` = DIS medium with finest scale 0 and patch stride 2);
  2. forward-backward consistency per key frame: the pixels of one frame that the other does not
     see (|F_01 + F_10(x + F_01)|^2 above 0.01 (|F_01|^2 + |F_10|^2) + 0.5, or leaving the image);
  3. time-``t`` backward flows F_t0, F_t1 by *flow reversal* (``time_flow="splat"``): every pixel of
     both key frames is splatted bilinearly to where it is at time t (x0 + t F_01, x1 + (1-t) F_10),
     carrying its flows to both key frames, weighted by exp(-inconsistency) so that occluded pixels
     lose collisions; holes take the Super SloMo approximation ``F_t0 = -(1-t) t F_01 + t^2 F_10``,
     ``F_t1 = (1-t)^2 F_01 - t (1-t) F_10`` (which ``time_flow="approx"`` uses everywhere);
  4. backward warping of both key frames (RGB and alpha together) at full resolution, and an
     occlusion-aware blend: where the frame-0 source of a pixel is hidden in frame 1 only frame 0 is
     used, and vice versa; elsewhere weights ``(1-t)`` and ``t``.
  Steps 1-3 run at the flow resolution; only the final warp is at full resolution.
  ``benchmarks/bench_interpolate.py`` measures these choices against true renders.
- ``crossfade``: ``(1-t) frame0 + t frame1`` (the baseline the benchmark compares against).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from humanvdm_core.cameras import Cameras, upsample_cameras
from humanvdm_core.frames import CAMERAS_FILE, FRAMES_DIR, frame_name, open_frame_set
from humanvdm_core.io import read_exr, write_exr
from humanvdm_core.workflow.errors import InputError

METHODS = ("flow", "crossfade")
SCHEDULES = ("direct", "recursive")
DIS_PRESETS = ("ultrafast", "fast", "medium", "fine")
TIME_FLOWS = ("splat", "approx")


@dataclass(frozen=True)
class InterpolateOptions:
    passes: int = 2
    method: str = "flow"
    schedule: str = "direct"
    flow_scale: float = 0.5
    preset: str = "fine"
    time_flow: str = "splat"
    rife_weights: str = ""  # RIFE v4.6 flownet.pkl (backend "rife", humanvdm_core.interpolate.rife)
    pervfi_weights: str = ""  # PerVFI generator v00.pth (backend "pervfi", humanvdm_core.interpolate.pervfi)
    pervfi_flow_weights: str = ""  # its RAFT flow estimator, raft-sintel.pth

    @property
    def factor(self) -> int:
        return 2 ** self.passes

    def check(self) -> None:
        if not 0 <= self.passes <= 6:
            raise InputError(f"passes must be in [0, 6], got {self.passes}")
        for name, value, allowed in (("method", self.method, METHODS), ("schedule", self.schedule, SCHEDULES),
                                     ("preset", self.preset, DIS_PRESETS), ("time_flow", self.time_flow, TIME_FLOWS)):
            if value not in allowed:
                raise InputError(f"unknown {name} {value!r}; choose from {allowed}")
        if not 0.0 < self.flow_scale <= 1.0:
            raise InputError(f"flow_scale must be in (0, 1], got {self.flow_scale}")


# ----------------------------------------------------------------------------- flow

def _luma_u8(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Rec. 601 luma as uint8, area-resampled to ``size`` = (width, height)."""
    import cv2

    rgb = np.clip(frame[..., :3], 0.0, 1.0)
    y = np.rint((rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114) * 255.0).astype(np.uint8)
    if (y.shape[1], y.shape[0]) != size:
        y = cv2.resize(y, size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(y)


def _dis(preset: str):
    import cv2

    base = {"ultrafast": cv2.DISOpticalFlow_PRESET_ULTRAFAST, "fast": cv2.DISOpticalFlow_PRESET_FAST,
            "medium": cv2.DISOpticalFlow_PRESET_MEDIUM, "fine": cv2.DISOpticalFlow_PRESET_MEDIUM}[preset]
    dis = cv2.DISOpticalFlow_create(base)
    if preset == "fine":  # patches down to the finest pyramid level, denser: measured +0.5 dB PSNR
        dis.setFinestScale(0)
        dis.setPatchStride(2)
    return dis


def flow_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """(width, height) of the flow grid for frames of ``height`` x ``width``."""
    return max(8, round(width * scale)), max(8, round(height * scale))


def optical_flows(frame0: np.ndarray, frame1: np.ndarray, size: tuple[int, int],
                  preset: str = "fine") -> tuple[np.ndarray, np.ndarray]:
    """(F_01, F_10) on a grid of ``size`` = (width, height), in that grid's pixels.

    frame0(x) corresponds to frame1(x + F_01(x)) and vice versa.
    """
    g0, g1 = _luma_u8(frame0, size), _luma_u8(frame1, size)
    dis = _dis(preset)
    return dis.calc(g0, g1, None).astype(np.float32), dis.calc(g1, g0, None).astype(np.float32)


def resize_flow(flow: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bilinearly resample a flow field to ``height`` x ``width``, rescaling its vectors."""
    import cv2

    if flow.shape[:2] == (height, width):
        return flow
    sx, sy = width / flow.shape[1], height / flow.shape[0]
    out = cv2.resize(flow, (width, height), interpolation=cv2.INTER_LINEAR)
    out[..., 0] *= sx
    out[..., 1] *= sy
    return out


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    return xs, ys


def backward_warp(image: np.ndarray, flow: np.ndarray, grid: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``out(x) = image(x + flow(x))`` with bilinear sampling, edges clamped."""
    import cv2

    out = cv2.remap(np.ascontiguousarray(image, dtype=np.float32), grid[0] + flow[..., 0], grid[1] + flow[..., 1],
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out[..., None] if out.ndim == 2 and image.ndim == 3 else out


def inconsistency(f_ab: np.ndarray, f_ba: np.ndarray, grid: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Forward-backward inconsistency of F_ab, in units of the consistency bound (> 1: occluded).

    ``|F_ab + F_ba(x + F_ab)|^2 / (0.01 (|F_ab|^2 + |F_ba(x + F_ab)|^2) + 0.5)``; pixels whose
    correspondence leaves the image get a large value.
    """
    back = backward_warp(f_ba, f_ab, grid)
    err2 = np.sum((f_ab + back) ** 2, axis=-1)
    bound = 0.01 * (np.sum(f_ab ** 2, axis=-1) + np.sum(back ** 2, axis=-1)) + 0.5
    h, w = f_ab.shape[:2]
    tx, ty = grid[0] + f_ab[..., 0], grid[1] + f_ab[..., 1]
    outside = (tx < 0) | (tx > w - 1) | (ty < 0) | (ty > h - 1)
    return np.where(outside, 100.0, err2 / bound).astype(np.float32)


def splat(values: np.ndarray, weights: np.ndarray, tx: np.ndarray, ty: np.ndarray,
          height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear forward splatting of ``values`` (n, c) to float positions (tx, ty).

    Returns (weighted sum (H, W, c), total weight (H, W)); divide for the weighted average.
    """
    x0, y0 = np.floor(tx).astype(np.int64), np.floor(ty).astype(np.int64)
    fx, fy = (tx - x0).astype(np.float64), (ty - y0).astype(np.float64)
    c = values.shape[1]
    acc = np.zeros((c, height * width))
    wsum = np.zeros(height * width)
    for dx, dy, wb in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xx, yy = x0 + dx, y0 + dy
        ok = (xx >= 0) & (xx < width) & (yy >= 0) & (yy < height)
        idx = (yy * width + xx)[ok]
        wt = (wb * weights)[ok]
        wsum += np.bincount(idx, wt, height * width)
        for k in range(c):
            acc[k] += np.bincount(idx, wt * values[ok, k], height * width)
    return acc.T.reshape(height, width, c), wsum.reshape(height, width)


def time_flows(f01: np.ndarray, f10: np.ndarray, inc0: np.ndarray, inc1: np.ndarray, t: float,
               mode: str = "splat") -> tuple[np.ndarray, np.ndarray]:
    """Backward flows (F_t0, F_t1) from the in-between time t to both key frames (same grid)."""
    approx0 = -(1.0 - t) * t * f01 + t * t * f10
    approx1 = (1.0 - t) ** 2 * f01 - t * (1.0 - t) * f10
    if mode == "approx":
        return approx0.astype(np.float32), approx1.astype(np.float32)
    h, w = f01.shape[:2]
    xs, ys = pixel_grid(h, w)
    a, b = f01.reshape(-1, 2), f10.reshape(-1, 2)
    # A frame-0 pixel x0 is at x0 + t F_01 at time t, with F_t0 = -t F_01 and F_t1 = (1-t) F_01;
    # a frame-1 pixel x1 is at x1 + (1-t) F_10, with F_t0 = t F_10 and F_t1 = -(1-t) F_10.
    values = np.concatenate([np.concatenate([-t * a, (1.0 - t) * a], axis=1),
                             np.concatenate([t * b, -(1.0 - t) * b], axis=1)])
    tx = np.concatenate([xs.ravel() + t * a[:, 0], xs.ravel() + (1.0 - t) * b[:, 0]])
    ty = np.concatenate([ys.ravel() + t * a[:, 1], ys.ravel() + (1.0 - t) * b[:, 1]])
    weights = np.exp(-np.minimum(np.concatenate([inc0.ravel(), inc1.ravel()]), 50.0)) + 1e-4
    acc, wsum = splat(values, weights, tx, ty, h, w)
    covered = (wsum > 1e-3)[..., None]
    flows = np.where(covered, acc / np.maximum(wsum, 1e-12)[..., None], np.concatenate([approx0, approx1], axis=-1))
    return (np.ascontiguousarray(flows[..., :2], dtype=np.float32),
            np.ascontiguousarray(flows[..., 2:], dtype=np.float32))


def flow_interpolate(frame0: np.ndarray, frame1: np.ndarray, times: Sequence[float],
                     opts: InterpolateOptions) -> list[np.ndarray]:
    """Occlusion-aware bidirectional flow interpolation of RGBA frames at each ``t`` in ``times``."""
    import cv2

    h, w = frame0.shape[:2]
    fw, fh = flow_size(h, w, opts.flow_scale)
    f01, f10 = optical_flows(frame0, frame1, (fw, fh), opts.preset)
    low = pixel_grid(fh, fw)
    inc0 = inconsistency(f01, f10, low)  # > 1: the frame-0 pixel is hidden in frame 1
    inc1 = inconsistency(f10, f01, low)
    occ0 = cv2.GaussianBlur((inc0 > 1.0).astype(np.float32), (0, 0), 1.0)
    occ1 = cv2.GaussianBlur((inc1 > 1.0).astype(np.float32), (0, 0), 1.0)
    full = pixel_grid(h, w)
    out = []
    for t in times:
        ft0, ft1 = time_flows(f01, f10, inc0, inc1, t, opts.time_flow)
        o0 = cv2.resize(backward_warp(occ0, ft0, low), (w, h), interpolation=cv2.INTER_LINEAR)
        o1 = cv2.resize(backward_warp(occ1, ft1, low), (w, h), interpolation=cv2.INTER_LINEAR)
        warped0 = backward_warp(frame0, resize_flow(ft0, h, w), full)
        warped1 = backward_warp(frame1, resize_flow(ft1, h, w), full)
        # o0: the frame-0 source of x is hidden in frame 1 -> trust frame 0 alone (and vice versa).
        w0 = (1.0 - t) * (1.0 - o1 * (1.0 - o0))
        w1 = t * (1.0 - o0 * (1.0 - o1))
        blend = (w0[..., None] * warped0 + w1[..., None] * warped1) / (w0 + w1)[..., None]
        out.append(np.clip(blend, 0.0, 1.0).astype(np.float32))
    return out


def crossfade_interpolate(frame0: np.ndarray, frame1: np.ndarray, times: Sequence[float],
                          opts: InterpolateOptions) -> list[np.ndarray]:
    """The baseline: a plain linear cross-fade."""
    return [((1.0 - t) * frame0 + t * frame1).astype(np.float32) for t in times]


def interpolate_embedded(frame0: np.ndarray, frame1: np.ndarray, times: Sequence[float],
                         opts: InterpolateOptions) -> list[np.ndarray]:
    fn = flow_interpolate if opts.method == "flow" else crossfade_interpolate
    return fn(frame0, frame1, times, opts)


# A backend synthesises frames between two RGBA key frames at the given fractions in (0, 1).
InterpolateBackend = Callable[[np.ndarray, np.ndarray, Sequence[float], InterpolateOptions], list[np.ndarray]]
def interpolate_rife(frame0: np.ndarray, frame1: np.ndarray, times: Sequence[float],
                     opts: InterpolateOptions) -> list[np.ndarray]:
    """RIFE v4.6 from local weights (:mod:`humanvdm_core.interpolate.rife`); any t (v4 takes t as input)."""
    from humanvdm_core.interpolate import rife

    return rife.interpolate_pair(rife.load(opts.rife_weights), frame0, frame1, list(times))


def interpolate_pervfi(frame0: np.ndarray, frame1: np.ndarray, times: Sequence[float],
                       opts: InterpolateOptions) -> list[np.ndarray]:
    """PerVFI (v00 generator + RAFT) from local weights (:mod:`humanvdm_core.interpolate.pervfi`).

    The network takes t, but its weights are trained at t = 0.5; :func:`interpolate_interval` only
    asks it for 0.5 (``recursive`` schedule).
    """
    from humanvdm_core.interpolate import pervfi

    model = pervfi.load(opts.pervfi_weights, opts.pervfi_flow_weights)
    return [pervfi.interpolate_pair(model, frame0, frame1, time=t) for t in times]


BACKENDS: dict[str, InterpolateBackend] = {"embedded": interpolate_embedded, "rife": interpolate_rife,
                                           "pervfi": interpolate_pervfi}
# Backends that synthesise only the midpoint: always run ×2 per pass (schedule "recursive").
RECURSIVE_ONLY = frozenset({"pervfi"})


def effective_schedule(opts: InterpolateOptions, backend: str) -> str:
    """The schedule that runs: ``recursive`` for the ×2-only backends, else ``opts.schedule``."""
    return "recursive" if backend in RECURSIVE_ONLY else opts.schedule


def interpolate_interval(frame0: np.ndarray, frame1: np.ndarray, opts: InterpolateOptions,
                         backend: str = "embedded") -> list[np.ndarray]:
    """The ``factor - 1`` in-between frames of one key interval, in order (key frames excluded)."""
    fn = BACKENDS[backend]
    if opts.factor == 1:
        return []
    if effective_schedule(opts, backend) == "direct":
        return fn(frame0, frame1, [k / opts.factor for k in range(1, opts.factor)], opts)
    seq = [frame0, frame1]
    for _ in range(opts.passes):
        nxt = [seq[0]]
        for a, b in zip(seq[:-1], seq[1:], strict=True):
            nxt += [fn(a, b, [0.5], opts)[0], b]
        seq = nxt
    return seq[1:-1]


# ----------------------------------------------------------------------------- frame sets

def check_frame_set(root: Path) -> tuple[list[Path], Cameras, int, int]:
    """Validate an RGBA frame set with >= 2 frames of one size; returns (paths, cameras, height, width)."""
    import OpenImageIO as oiio

    paths, cams = open_frame_set(root)
    if len(paths) < 2:
        raise InputError(f"frame set {root}: interpolation needs at least 2 frames, found {len(paths)}")
    shapes = []
    for p in paths:
        inp = oiio.ImageInput.open(str(p))
        if inp is None:
            raise InputError(f"cannot read frame {p}: {oiio.geterror()}")
        spec = inp.spec()
        shapes.append((spec.height, spec.width, spec.nchannels))
        inp.close()
    h, w, c = shapes[0]
    for p, s in zip(paths, shapes, strict=True):
        if s[:2] != (h, w):
            raise InputError(f"frame set {root}: {p.name} is {s[1]}x{s[0]} but {paths[0].name} is {w}x{h}; "
                             "all frames must have the same size")
        if s[2] != 4:
            raise InputError(f"frame set {root}: frames must be RGBA (4 channels), {p.name} has {s[2]}")
    if (cams.width, cams.height) != (w, h):
        raise InputError(f"frame set {root}: cameras are for {cams.width}x{cams.height} but frames are {w}x{h}")
    return paths, cams, h, w


def interpolate_frame_set(src: str | Path, dst: str | Path, opts: InterpolateOptions, backend: str = "embedded",
                          attrs: dict[str, str] | None = None, log=None) -> dict:
    """Interpolate the frame set ``src`` into the (empty or new) directory ``dst``; returns a summary."""
    src, dst = Path(src), Path(dst)
    opts.check()
    if backend not in BACKENDS:
        raise InputError(f"unknown interpolate backend {backend!r}; available: {sorted(BACKENDS)}")
    paths, cams, h, w = check_frame_set(src)
    factor = opts.factor
    schedule = effective_schedule(opts, backend)
    if log and schedule != opts.schedule:
        log.info("backend %s synthesises only t = 0.5: schedule %s instead of %s", backend, schedule, opts.schedule)
    base = {**(attrs or {}), "interpolate_method": opts.method, "interpolate_schedule": schedule}

    def put(index: int, frame: np.ndarray, key: bool, t: float) -> None:
        write_exr(dst / FRAMES_DIR / frame_name(index), frame,
                  attrs={**base, "frame_index": index, "keyframe": int(key), "time": float(t)})

    from humanvdm_core.workflow.progress import report

    prev = read_exr(paths[0])
    put(0, prev, True, 0.0)
    n_out = (len(paths) - 1) * factor + 1
    for i in range(1, len(paths)):
        cur = read_exr(paths[i])
        for k, frame in enumerate(interpolate_interval(prev, cur, opts, backend), start=1):
            put((i - 1) * factor + k, frame, False, i - 1 + k / factor)
        put(i * factor, cur, True, float(i))
        report(i * factor + 1, n_out, "frames", f"interpolate {len(paths)} -> {n_out} frames")
        prev = cur
    upsample_cameras(cams, factor).save(dst / CAMERAS_FILE)
    dropped = sorted(d.name for d in src.iterdir() if d.is_dir() and d.name != FRAMES_DIR)
    if log:
        log.info("interpolated %d -> %d frames (%dx%d, %s/%s, %s schedule)", len(paths), n_out, w, h, backend,
                 opts.method, schedule)
        if dropped:
            log.info("layers not carried over (cannot be interpolated faithfully): %s", dropped)
    return {"frames_in": len(paths), "frames_out": n_out, "factor": factor, "dropped_layers": dropped}
