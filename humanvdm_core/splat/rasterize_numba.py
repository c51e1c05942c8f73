"""Compiled CPU kernels for the Gaussian rasterizer (numba): the ``"numba"`` backend's binning and compositing.

Projection stays in torch (:func:`humanvdm_core.splat.rasterize.project_gaussians`, differentiable by
autograd); tile binning (a counting sort: the torch path's ``_intersect_tiles`` pairs, in the same order)
and the compositing forward and backward are compiled. The semantics are exactly those of the torch path
(:func:`humanvdm_core.splat.rasterize._composite_tiled`), which is this module's test oracle: pixel
centres at +0.5, ``alpha = min(ALPHA_MAX, o exp(-sigma))`` with ``sigma = 0.5 d^T Sigma^-1 d``, skipped
when ``sigma < 0`` or ``o exp(-sigma) < ALPHA_MIN``, front-to-back in depth order, a pixel stopping
(exclusively) at the first Gaussian that would bring T to ``<= T_MIN``.

Layout: one parallel loop over the busy tiles (in row-major order, handed out dynamically in small chunks);
each tile walks its depth-sorted list once, Gaussian by Gaussian, over only the tile pixels inside that
Gaussian's screen box (which encloses every pixel where its alpha can reach ``ALPHA_MIN``; a half-pixel
margin absorbs rounding) and the bounding box of its ellipse ``sigma <= log(o / ALPHA_MIN)`` (slightly
widened; every visited pixel is still tested exactly as the torch path does), keeping per-pixel (colour, T,
done) state, and leaves as soon as every pixel is done. The forward records per tile the end of the list
prefix that contributed anything. The backward walks that prefix front to back again (unlike 3DGS's
back-to-front pass, which divides by ``1 - alpha`` to recover each T), recomputing alpha and T exactly as
the forward did, with ``dL/dalpha_i = T_i (c_i . g) - (S_i + T_final dL/dT_final) / (1 - alpha_i)``
where the suffix sum ``S_i = sum_{j>i} alpha_j T_j (c_j . g)`` is the pixel's total ``img . g`` minus the
running prefix (the torch path's formula). Per-intersection gradients go to a (intersections, 6 + D) buffer (each intersection
belongs to one tile, so the parallel loop never races) and are summed per Gaussian afterwards.

All arithmetic is float64 whatever the input dtype (inputs are converted, outputs cast back), so one
compiled specialisation serves float32 and float64. Kernels are compiled on first use and cached on disk
(``cache=True``: numba's ``__pycache__`` beside this file, or ``NUMBA_CACHE_DIR``). Threads: each call runs
on ``min(torch.get_num_threads(), NUMBA_NUM_THREADS)`` threads, so a process's thread budget
(:mod:`humanvdm_core.workflow.threads`, ``torch.set_num_threads``) holds for the kernels too.
"""

from __future__ import annotations

import math
import os
import threading
from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from humanvdm_core.splat import rasterize as _rz

PARALLEL_CHUNK = 2  # tiles handed to a thread at a time (dynamic scheduling)
SIGMA_MARGIN = 1e-9  # skip exp() where sigma exceeds log(o / ALPHA_MIN) by this much (alpha surely < ALPHA_MIN)

# numba's default OpenMP threading layer busy-waits between parallel loops unless OMP_WAIT_POLICY=PASSIVE
# is set before it loads: measured 15x slower (0.6 s instead of 0.04 s per view) on a 2-core machine shared
# with other work (and libgomp is not fork-safe). The workqueue layer's workers sleep instead; it must not
# be entered from two threads at once, which _LOCK ensures for these kernels. An explicit
# NUMBA_THREADING_LAYER is respected, as is a layer that other code in the process already started.
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"
_LOCK = threading.Lock()


@dataclass(frozen=True)
class TileBins:
    """Tile-Gaussian intersections of one camera, as the kernels take them.

    ``gids`` (M,) int64: Gaussian ids grouped by tile, each tile's run sorted front to back; ``starts``
    (n_tiles + 1,) int64: tile t's run is ``gids[starts[t]:starts[t + 1]]``; ``order`` (B,) int64: the busy
    tiles in row-major order (neighbours share Gaussians, so their rows stay in cache; measured 15 % faster
    than longest-first at 200k Gaussians); ``radii`` (N, 2) int32 screen half-extents; the image and tile
    geometry.
    """

    gids: np.ndarray
    starts: np.ndarray
    order: np.ndarray
    radii: np.ndarray
    tile_size: int
    tiles_w: int
    width: int
    height: int


def bin_gaussians(means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, width: int,
                  height: int) -> TileBins:
    """Tile-Gaussian intersections: every Gaussian with both radii > 0 joins the tiles its screen box
    ``means2d +- radii`` overlaps; each tile's run is sorted by depth (stable: ties keep index order).
    The same pairs, in the same order, as the torch path's ``_intersect_tiles``."""
    tiles_w, tiles_h = math.ceil(width / tile_size), math.ceil(height / tile_size)
    rad = np.ascontiguousarray(radii.detach().cpu().numpy(), dtype=np.int32)
    kept = np.flatnonzero((rad > 0).all(axis=1))
    by_depth = kept[np.argsort(_f64(depths)[kept], kind="stable")].astype(np.int64)
    gids, starts = _bin_kernel(_f64(means2d), rad, by_depth, tile_size, tiles_w, tiles_h)
    order = np.flatnonzero(np.diff(starts)).astype(np.int64)
    return TileBins(gids=gids, starts=starts, order=order, radii=rad, tile_size=tile_size, tiles_w=tiles_w,
                    width=width, height=height)


def _thresholds() -> tuple[float, float, float]:
    """(ALPHA_MIN, ALPHA_MAX, T_MIN), passed at call time: numba's disk cache would not notice a change of
    constants imported from another module."""
    return float(_rz.ALPHA_MIN), float(_rz.ALPHA_MAX), float(_rz.T_MIN)


def _f64(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)


class _Threads:
    """Run numba's parallel loops on the caller's torch thread budget, dynamically scheduled, one call at a
    time per process; restores numba's settings after."""

    def __enter__(self) -> _Threads:
        _LOCK.acquire()
        try:
            self._threads = numba.get_num_threads()
            numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
            self._chunk = numba.set_parallel_chunksize(PARALLEL_CHUNK)
        except BaseException:
            _LOCK.release()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        numba.set_parallel_chunksize(self._chunk)
        numba.set_num_threads(self._threads)
        _LOCK.release()


# ----------------------------------------------------------------------------------------------- kernels


@numba.njit(cache=True, inline="always")
def _tile_range(mx: float, my: float, rx: int, ry: int, tile_size: int, tiles_w: int,
                tiles_h: int) -> tuple[int, int, int, int]:
    """Tiles [tx0, tx1) x [ty0, ty1) overlapped by the screen box (as ``_intersect_tiles``)."""
    tx0 = min(max(int(math.floor((mx - rx) / tile_size)), 0), tiles_w)
    tx1 = min(max(int(math.ceil((mx + rx) / tile_size)), 0), tiles_w)
    ty0 = min(max(int(math.floor((my - ry) / tile_size)), 0), tiles_h)
    ty1 = min(max(int(math.ceil((my + ry) / tile_size)), 0), tiles_h)
    return tx0, tx1, ty0, ty1


@numba.njit(cache=True)
def _bin_kernel(means2d: np.ndarray, radii: np.ndarray, by_depth: np.ndarray, tile_size: int, tiles_w: int,
                tiles_h: int) -> tuple[np.ndarray, np.ndarray]:
    """Counting sort of (tile, Gaussian) pairs: Gaussians visited front to back, so each tile's run comes
    out depth-sorted. Returns (gids (M,), starts (n_tiles + 1,))."""
    starts = np.zeros(tiles_w * tiles_h + 1, dtype=np.int64)
    for g in by_depth:
        tx0, tx1, ty0, ty1 = _tile_range(means2d[g, 0], means2d[g, 1], radii[g, 0], radii[g, 1], tile_size,
                                         tiles_w, tiles_h)
        for ty in range(ty0, ty1):
            for tx in range(tx0, tx1):
                starts[ty * tiles_w + tx + 1] += 1
    for t in range(1, starts.shape[0]):
        starts[t] += starts[t - 1]
    fill = starts[:-1].copy()
    gids = np.empty(starts[-1], dtype=np.int64)
    for g in by_depth:
        tx0, tx1, ty0, ty1 = _tile_range(means2d[g, 0], means2d[g, 1], radii[g, 0], radii[g, 1], tile_size,
                                         tiles_w, tiles_h)
        for ty in range(ty0, ty1):
            for tx in range(tx0, tx1):
                t = ty * tiles_w + tx
                gids[fill[t]] = g
                fill[t] += 1
    return gids, starts


@numba.njit(cache=True, inline="always")
def _tile_box(t: int, tiles_w: int, tile_size: int, width: int, height: int) -> tuple[int, int, int, int]:
    ty = t // tiles_w
    tx = t - ty * tiles_w
    x0, y0 = tx * tile_size, ty * tile_size
    return x0, min(x0 + tile_size, width), y0, min(y0 + tile_size, height)


@numba.njit(cache=True, inline="always")
def _gauss_box(mx: float, my: float, rx: float, ry: float, ca: float, cb: float, cc: float, sigma_cut: float,
               x0: int, x1: int, y0: int, y1: int) -> tuple[int, int, int, int]:
    """Pixels (x in [bx0, bx1), y in [by0, by1)) of the tile [x0, x1) x [y0, y1) where sigma can be
    <= ``sigma_cut``: centres within the screen box widened by 0.5 px, and within the bounding box of the
    ellipse ``0.5 d^T conic d <= sigma_cut`` (half-extents ``sqrt(2 sigma_cut Sigma_ii)``, widened by
    1e-6 relative + 1e-3 px) when the conic is positive definite. A superset: callers test every pixel."""
    bx0 = max(x0, int(math.ceil(mx - rx - 1.0)))
    bx1 = min(x1, int(math.floor(mx + rx)) + 1)
    by0 = max(y0, int(math.ceil(my - ry - 1.0)))
    by1 = min(y1, int(math.floor(my + ry)) + 1)
    det = ca * cc - cb * cb
    if ca > 0.0 and cc > 0.0 and det > 0.0:
        ex = math.sqrt(2.0 * sigma_cut * cc / det) * (1.0 + 1e-6) + 1e-3
        ey = math.sqrt(2.0 * sigma_cut * ca / det) * (1.0 + 1e-6) + 1e-3
        bx0 = max(bx0, int(math.ceil(mx - 0.5 - ex)))
        bx1 = min(bx1, int(math.floor(mx - 0.5 + ex)) + 1)
        by0 = max(by0, int(math.ceil(my - 0.5 - ey)))
        by1 = min(by1, int(math.floor(my - 0.5 + ey)) + 1)
    return bx0, bx1, by0, by1


# Columns of the per-Gaussian table the kernels read (one row = one or two cache lines per visit).
MX, MY, CA, CB, CC, OPACITY, SIGMA_CUT, RX, RY, COLOR = range(10)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _forward_kernel(table: np.ndarray, gids: np.ndarray, starts: np.ndarray, order: np.ndarray, tile_size: int,
                    tiles_w: int, width: int, height: int, alpha_min: float, alpha_max: float, t_min: float,
                    img: np.ndarray, trans: np.ndarray, done: np.ndarray, tile_end: np.ndarray) -> None:
    """Composite every busy tile. ``table`` (N, COLOR + D): see :func:`_gaussian_table`. ``img`` (H, W, D)
    zeros, ``trans`` (H, W) ones and ``done`` (H, W) False on entry; on exit colour without background,
    final T, and per tile ``tile_end[t]``: one past the last list entry that contributed to any of its
    pixels (``starts[t]`` when none did)."""
    dim = table.shape[1] - COLOR
    for i in numba.prange(order.shape[0]):
        t = order[i]
        x0, x1, y0, y1 = _tile_box(t, tiles_w, tile_size, width, height)
        alive = (x1 - x0) * (y1 - y0)
        end = starts[t]
        for k in range(starts[t], starts[t + 1]):
            row = table[gids[k]]
            mx, my, ca, cb, cc, o, sigma_cut = (row[MX], row[MY], row[CA], row[CB], row[CC], row[OPACITY],
                                                row[SIGMA_CUT])
            bx0, bx1, by0, by1 = _gauss_box(mx, my, row[RX], row[RY], ca, cb, cc, sigma_cut, x0, x1, y0, y1)
            for y in range(by0, by1):
                dy = my - (y + 0.5)
                for x in range(bx0, bx1):
                    if done[y, x]:
                        continue
                    dx = mx - (x + 0.5)
                    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if not (sigma >= 0.0 and sigma <= sigma_cut):
                        continue
                    raw = o * math.exp(-sigma)
                    if not raw >= alpha_min:
                        continue
                    alpha = min(raw, alpha_max)
                    t_here = trans[y, x]
                    t_next = t_here * (1.0 - alpha)
                    if t_next <= t_min:
                        done[y, x] = True
                        alive -= 1
                        continue
                    w = alpha * t_here
                    for d in range(dim):
                        img[y, x, d] += w * row[COLOR + d]
                    trans[y, x] = t_next
                    end = k + 1
            if alive == 0:
                break
        tile_end[t] = end


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _backward_kernel(table: np.ndarray, gids: np.ndarray, starts: np.ndarray, order: np.ndarray,
                     tile_end: np.ndarray, tile_size: int, tiles_w: int, width: int, height: int,
                     alpha_min: float, alpha_max: float, t_min: float, grad_img: np.ndarray, total: np.ndarray,
                     tail: np.ndarray, trans: np.ndarray, prefix: np.ndarray, done: np.ndarray,
                     grads: np.ndarray) -> None:
    """Per-intersection gradients into ``grads`` (M, 6 + D), zeros on entry: d/d(mean x, mean y, conic a, b,
    c, opacity, colour_0..D-1). ``total`` (H, W): img . grad_img; ``tail`` (H, W): T_final dL/dT_final;
    ``trans`` ones, ``prefix`` zeros, ``done`` False (H, W): scratch state, overwritten."""
    dim = table.shape[1] - COLOR
    for i in numba.prange(order.shape[0]):
        t = order[i]
        x0, x1, y0, y1 = _tile_box(t, tiles_w, tile_size, width, height)
        for k in range(starts[t], tile_end[t]):
            row = table[gids[k]]
            mx, my, ca, cb, cc, o, sigma_cut = (row[MX], row[MY], row[CA], row[CB], row[CC], row[OPACITY],
                                                row[SIGMA_CUT])
            bx0, bx1, by0, by1 = _gauss_box(mx, my, row[RX], row[RY], ca, cb, cc, sigma_cut, x0, x1, y0, y1)
            g_mx = g_my = g_a = g_b = g_c = g_o = 0.0
            for y in range(by0, by1):
                dy = my - (y + 0.5)
                for x in range(bx0, bx1):
                    if done[y, x]:
                        continue
                    dx = mx - (x + 0.5)
                    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if not (sigma >= 0.0 and sigma <= sigma_cut):
                        continue
                    vis = math.exp(-sigma)
                    raw = o * vis
                    if not raw >= alpha_min:
                        continue
                    alpha = min(raw, alpha_max)
                    t_here = trans[y, x]
                    t_next = t_here * (1.0 - alpha)
                    if t_next <= t_min:
                        done[y, x] = True
                        continue
                    trans[y, x] = t_next
                    w = alpha * t_here
                    cg = 0.0
                    for d in range(dim):
                        gd = grad_img[y, x, d]
                        cg += row[COLOR + d] * gd
                        grads[k, 6 + d] += w * gd
                    pre = prefix[y, x] + w * cg
                    prefix[y, x] = pre
                    if raw < alpha_max:  # clamped alphas pass no gradient to sigma or opacity
                        d_alpha = t_here * cg - (total[y, x] - pre + tail[y, x]) / (1.0 - alpha)
                        d_sigma = -d_alpha * raw
                        g_mx += d_sigma * (ca * dx + cb * dy)
                        g_my += d_sigma * (cc * dy + cb * dx)
                        g_a += 0.5 * d_sigma * dx * dx
                        g_b += d_sigma * dx * dy
                        g_c += 0.5 * d_sigma * dy * dy
                        g_o += d_alpha * vis
            grads[k, 0] = g_mx
            grads[k, 1] = g_my
            grads[k, 2] = g_a
            grads[k, 3] = g_b
            grads[k, 4] = g_c
            grads[k, 5] = g_o


@numba.njit(cache=True)
def _sum_per_gaussian(gids: np.ndarray, grads: np.ndarray, out: np.ndarray) -> None:
    """out[gids[k]] += grads[k] for every intersection k (serial: ids repeat across tiles)."""
    for k in range(gids.shape[0]):
        g = gids[k]
        for j in range(grads.shape[1]):
            out[g, j] += grads[k, j]


# ------------------------------------------------------------------------------------------------ driver


def _tensor(array: np.ndarray, like: Tensor) -> Tensor:
    """A new tensor (never sharing memory with ``array``, which backward may still read) in ``like``'s dtype
    and device."""
    return torch.from_numpy(array).to(dtype=like.dtype, device=like.device, copy=True)


def _gaussian_table(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,
                    bins: TileBins) -> np.ndarray:
    """(N, COLOR + D) float64 rows [mean x, mean y, conic a, b, c, opacity, sigma cut-off, radius x, radius y,
    colour...]: everything a kernel reads per visited Gaussian, side by side in memory. The cut-off
    ``log(o / ALPHA_MIN) + SIGMA_MARGIN`` lets the kernels skip exp() where alpha is surely below
    ALPHA_MIN (they still test alpha itself)."""
    n, dim = means2d.shape[0], colors.shape[1]
    table = np.empty((n, COLOR + dim))
    table[:, MX:MY + 1] = _f64(means2d)
    table[:, CA:CC + 1] = _f64(conics)
    table[:, OPACITY] = _f64(opacities)
    with np.errstate(divide="ignore", invalid="ignore"):  # culled Gaussians (never visited) may have o <= 0
        table[:, SIGMA_CUT] = np.log(table[:, OPACITY] / _rz.ALPHA_MIN) + SIGMA_MARGIN
    table[:, RX:RY + 1] = bins.radii
    table[:, COLOR:] = _f64(colors)
    return table


def _forward(table: np.ndarray, bins: TileBins) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (img (H, W, D) without background, T_final (H, W), tile_end (n_tiles,)), float64."""
    h, w = bins.height, bins.width
    img = np.zeros((h, w, table.shape[1] - COLOR))
    trans = np.ones((h, w))
    tile_end = bins.starts[:-1].copy()
    if bins.order.size:
        with _Threads():
            _forward_kernel(table, bins.gids, bins.starts, bins.order, bins.tile_size, bins.tiles_w, w, h,
                            *_thresholds(), img, trans, np.zeros((h, w), dtype=np.bool_), tile_end)
    return img, trans, tile_end


class _NumbaComposite(torch.autograd.Function):
    """Compiled compositing with an analytic backward (see the module docstring)."""

    @staticmethod
    def forward(ctx, means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,  # noqa: ANN001
                bins: TileBins) -> tuple[Tensor, Tensor]:
        table = _gaussian_table(means2d, conics, opacities, colors, bins)
        img, trans, tile_end = _forward(table, bins)
        ctx.table, ctx.bins, ctx.tile_end, ctx.img, ctx.trans = table, bins, tile_end, img, trans
        ctx.like = [(t.dtype, t.device) for t in (means2d, conics, opacities, colors)]  # of each gradient
        return _tensor(img, means2d), _tensor(trans, means2d)

    @staticmethod
    def backward(ctx, grad_img: Tensor, grad_trans: Tensor):  # noqa: ANN001, ANN205
        table, bins = ctx.table, ctx.bins
        h, w, dim = ctx.img.shape
        g_img = _f64(grad_img)
        total = np.einsum("hwd,hwd->hw", ctx.img, g_img)
        tail = _f64(grad_trans) * ctx.trans
        per_isect = np.zeros((bins.gids.size, 6 + dim))
        if bins.order.size:
            with _Threads():
                _backward_kernel(table, bins.gids, bins.starts, bins.order, ctx.tile_end, bins.tile_size,
                                 bins.tiles_w, w, h, *_thresholds(), g_img, total, tail, np.ones((h, w)),
                                 np.zeros((h, w)), np.zeros((h, w), dtype=np.bool_), per_isect)
        per_gauss = np.zeros((table.shape[0], 6 + dim))
        _sum_per_gaussian(bins.gids, per_isect, per_gauss)
        out = torch.from_numpy(per_gauss)
        parts = (out[:, 0:2], out[:, 2:5], out[:, 5], out[:, 6:])
        return (*(p.to(dtype=dt, device=dev) for p, (dt, dev) in zip(parts, ctx.like, strict=True)), None)


def composite(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,
              bins: TileBins) -> tuple[Tensor, Tensor]:
    """Composite one camera: means2d (N, 2), conics (N, 3), opacities (N,), colors (N, D) -> (colour (H, W, D)
    without background, final transmittance (H, W)), both in means2d's dtype and on its device.

    Differentiable w.r.t. the four tensors when grad mode is on and any of them requires grad.
    """
    if torch.is_grad_enabled() and any(t.requires_grad for t in (means2d, conics, opacities, colors)):
        return _NumbaComposite.apply(means2d, conics, opacities, colors, bins)
    img, trans, _ = _forward(_gaussian_table(means2d, conics, opacities, colors, bins), bins)
    return _tensor(img, means2d), _tensor(trans, means2d)
