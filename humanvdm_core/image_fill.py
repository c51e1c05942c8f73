"""Filling an image's unknown pixels from its known ones.

- :func:`nearest_fill`: every pixel takes the value of the nearest known pixel (Euclidean);
  :func:`row_nearest`: of the nearest known pixel in its own row.
- :func:`harmonic_extension`: the known values extended over a domain by the Laplace equation (free at
  the domain's border), solved coarse to fine by Jacobi steps over the 4-neighbours (:data:`CROSS`).
- :func:`outside_of`: the pixels outside a region that reach the image border, so not its holes.
"""

from __future__ import annotations

import cv2
import numpy as np

CROSS = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], np.float32)


def _jacobi(x: np.ndarray, free: np.ndarray, weight: np.ndarray, iterations: int) -> np.ndarray:
    """Jacobi steps of ``x_i = sum_j w_j x_j / sum_j w_j`` over 4-neighbours, on ``free`` pixels."""
    den = np.maximum(cv2.filter2D(weight, -1, CROSS, borderType=cv2.BORDER_CONSTANT), 1e-6)
    x = x.astype(np.float32)
    for _ in range(iterations):
        x = np.where(free, cv2.filter2D(x * weight, -1, CROSS, borderType=cv2.BORDER_CONSTANT) / den, x)
    return x


def _pyramid_solve(x0: np.ndarray, free: np.ndarray, weight: np.ndarray, iterations: int = 60,
                   coarsest: int = 24) -> np.ndarray:
    """Laplace equation by coarse-to-fine Jacobi: the problem is restricted to halved grids down to
    ``coarsest`` px, solved there first, and each solution seeds the next finer level."""
    h, w = free.shape
    if min(h, w) <= coarsest:
        return _jacobi(x0, free, weight, iterations * 8)
    half = (max(1, w // 2), max(1, h // 2))
    c_free = cv2.resize(free.astype(np.float32), half, interpolation=cv2.INTER_AREA) > 0.5
    c_weight = cv2.resize(weight, half, interpolation=cv2.INTER_AREA)
    # fixed values at the coarse level: the average of the fixed fine pixels under each coarse pixel
    fine_fixed = (~free).astype(np.float32)
    num = cv2.resize(x0 * fine_fixed, half, interpolation=cv2.INTER_AREA)
    den = cv2.resize(fine_fixed, half, interpolation=cv2.INTER_AREA)
    c_x0 = np.where(~c_free & (den > 0), num / np.maximum(den, 1e-6), cv2.resize(x0, half, interpolation=cv2.INTER_AREA))
    coarse = _pyramid_solve(c_x0.astype(np.float32), c_free, c_weight.astype(np.float32), iterations, coarsest)
    up = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR)
    return _jacobi(np.where(free, up, x0), free, weight, iterations)


def harmonic_extension(values: np.ndarray, known: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """``values`` on ``known`` pixels, extended over ``domain`` by the Laplace equation (free at the
    domain's border); pixels of the domain unreachable from ``known`` take the nearest known value."""
    start = nearest_fill(values, known)
    free = domain & ~known
    return _pyramid_solve(start.astype(np.float32), free, domain.astype(np.float32)).astype(np.float64)


def nearest_fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``values`` (H, W[, C]) with every pixel taking the value of the nearest ``known`` pixel."""
    if not known.any():
        return values.copy()
    src = np.where(known, 0, 1).astype(np.uint8)
    _, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    rows, cols = np.nonzero(known)
    by_label = np.zeros((int(labels.max()) + 1, 2), np.int64)
    by_label[labels[rows, cols]] = np.stack([rows, cols], axis=1)
    where = by_label[labels]
    return values[where[..., 0], where[..., 1]]


def row_nearest(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``values`` (H, W) with every pixel taking the value of the nearest ``known`` pixel in its own row
    (rows without one: the nearest known pixel anywhere)."""
    out = nearest_fill(values, known)
    for y in np.nonzero(known.any(axis=1))[0]:
        cols = np.nonzero(known[y])[0]
        x = np.arange(values.shape[1])
        right = np.clip(np.searchsorted(cols, x), 0, len(cols) - 1)
        left = np.clip(right - 1, 0, len(cols) - 1)
        pick = np.where(np.abs(cols[left] - x) <= np.abs(cols[right] - x), cols[left], cols[right])
        out[y] = values[y, pick]
    return out


def outside_of(region: np.ndarray) -> np.ndarray:
    """Pixels not in ``region`` (H, W bool) that connect to the image border without crossing it (4-connected):
    everything but ``region`` and the holes it encloses."""
    free = (~region).astype(np.uint8)
    padded = np.pad(free, 1, constant_values=1)
    _, labels = cv2.connectedComponents(padded, connectivity=4)
    return (labels == labels[0, 0])[1:-1, 1:-1]
