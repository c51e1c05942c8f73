"""Image and geometry metrics (paper section 4): PSNR, SSIM, masked variants, silhouette IoU, Chamfer.

Contract (images):

- Images are channels-last float arrays in [0, ``data_range``]: ``(H, W, C)`` or batched
  ``(..., H, W, C)``; numpy arrays or torch tensors. Every image function returns a torch tensor of
  the leading batch shape (a 0-d tensor for one image); the torch functions are differentiable
  (SSIM and PSNR may serve as losses).
- ``psnr = 10 log10(data_range^2 / MSE)``, MSE over all pixels and channels; identical images
  give ``+inf``.
- ``ssim``: Wang et al. 2004 with the standard constants: an 11x11 Gaussian window (sigma 1.5),
  K1 = 0.01, K2 = 0.03, computed per channel over the 'valid' window positions (no padding; the
  map is ``(H - 10, W - 10)``), averaged over channels and positions. Identical images give 1.
- Masked variants (``mask=`` argument, or :func:`masked_psnr` / :func:`masked_ssim`): the mask is the
  UNION of the ground-truth and predicted silhouettes (:func:`union_mask`: alpha > 0.5 in either),
  so missing and spurious body parts both count while the empty background does not.
  Masked PSNR averages the squared error over the masked pixels (all channels); masked SSIM
  averages the full-image SSIM map over the masked window centres (each window still sees its
  11x11 neighbourhood, background included). An empty mask gives NaN.
- :func:`silhouette_iou`: ``|A and B| / |A or B|`` of alpha > 0.5; two empty silhouettes give 1.

Contract (geometry, numpy, world units):

- :func:`sample_surface` draws points uniformly by area (fixed seed: deterministic).
- :func:`point_to_surface`: for each query point, the exact distance to the triangle of its nearest
  surface sample (an upper bound of the true point-to-mesh distance, off by at most the sample
  spacing; exact for points whose nearest sample lies on the nearest triangle).
- :func:`geometry_errors`: ``p2s`` = mean point-to-surface distance of the predicted points (the
  Gaussian centres), ``s2p`` = mean distance from uniform surface samples to the nearest predicted
  point, ``chamfer = (p2s + s2p) / 2``; medians and a 90th percentile of p2s too; every value also
  divided by ``height`` (the subject's height) under ``*_rel``.
- Nearest neighbours are exact: a uniform grid search of the 27 neighbouring cells, with a chunked
  brute-force pass for queries farther than one cell from every reference point.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03
MASK_THRESHOLD = 0.5
BRUTE_FORCE_PAIRS = 50_000_000  # nearest neighbours by brute force below this many (query, ref) pairs
PAIRS_PER_BATCH = 2_000_000  # (query, reference) pairs per grid-search batch and cell offset


def _as_tensor(x) -> torch.Tensor:
    t = torch.as_tensor(x)
    return t if t.is_floating_point() else t.to(torch.float32)


def _pair(pred, target) -> tuple[torch.Tensor, torch.Tensor]:
    a, b = _as_tensor(pred), _as_tensor(target)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")
    if a.ndim < 3:
        raise ValueError(f"images must be (..., H, W, C), got {tuple(a.shape)}")
    dtype = torch.promote_types(a.dtype, b.dtype)
    return a.to(dtype), b.to(dtype)


def _mask_tensor(mask, shape: torch.Size, device) -> torch.Tensor:
    """A boolean (..., H, W) mask from a bool/float (..., H, W) or (..., H, W, 1) array."""
    m = torch.as_tensor(mask, device=device)
    if m.ndim == len(shape) and m.shape[-1] == 1:
        m = m[..., 0]
    if m.dtype != torch.bool:
        m = m > MASK_THRESHOLD
    if tuple(m.shape) != tuple(shape[:-1]):
        raise ValueError(f"mask shape {tuple(m.shape)} does not match images {tuple(shape)}")
    return m


def union_mask(alpha_a, alpha_b, threshold: float = MASK_THRESHOLD) -> np.ndarray:
    """Boolean union of two silhouettes (alpha ``(..., H, W)`` or ``(..., H, W, 1)``, > threshold)."""
    a, b = np.asarray(alpha_a), np.asarray(alpha_b)
    if a.shape != b.shape:
        raise ValueError(f"alpha shapes differ: {a.shape} vs {b.shape}")
    if a.ndim >= 3 and a.shape[-1] == 1:
        a, b = a[..., 0], b[..., 0]
    return (a > threshold) | (b > threshold)


# ----------------------------------------------------------------------------- PSNR

def mse(pred, target, mask=None) -> torch.Tensor:
    """Mean squared error over pixels and channels (over the masked pixels when ``mask`` is given)."""
    a, b = _pair(pred, target)
    err = (a - b).square().mean(dim=-1)  # (..., H, W)
    if mask is None:
        return err.mean(dim=(-2, -1))
    m = _mask_tensor(mask, a.shape, a.device).to(err.dtype)
    return (err * m).sum(dim=(-2, -1)) / m.sum(dim=(-2, -1))


def psnr(pred, target, mask=None, data_range: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB (``+inf`` for identical images); see the module docstring."""
    return 10.0 * torch.log10(data_range**2 / mse(pred, target, mask))


def masked_psnr(pred, target, pred_alpha, target_alpha, data_range: float = 1.0) -> torch.Tensor:
    """PSNR over the union of the two silhouettes."""
    return psnr(pred, target, union_mask(pred_alpha, target_alpha), data_range)


# ----------------------------------------------------------------------------- SSIM

def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, dtype=torch.float32) -> torch.Tensor:
    """Normalised 1-D Gaussian of ``size`` taps."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype)


def _blur_valid(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable 'valid' Gaussian filter of (B, C, H, W), per channel."""
    c = x.shape[1]
    k = g.numel()
    x = F.conv2d(x, g.view(1, 1, 1, k).expand(c, 1, 1, k), groups=c)
    return F.conv2d(x, g.view(1, 1, k, 1).expand(c, 1, k, 1), groups=c)


def ssim_map(pred, target, data_range: float = 1.0, window: int = SSIM_WINDOW,
             sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """SSIM map averaged over channels: ``(..., H - window + 1, W - window + 1)``."""
    a, b = _pair(pred, target)
    *batch, h, w, c = a.shape
    if h < window or w < window:
        raise ValueError(f"images of {h}x{w} are smaller than the {window}x{window} SSIM window")
    if not a.is_floating_point() or a.dtype == torch.float16:
        a, b = a.float(), b.float()
    x = a.reshape(-1, h, w, c).permute(0, 3, 1, 2)
    y = b.reshape(-1, h, w, c).permute(0, 3, 1, 2)
    g = gaussian_window(window, sigma, x.dtype).to(x.device)
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    mu_x, mu_y = _blur_valid(x, g), _blur_valid(y, g)
    sxx = _blur_valid(x * x, g) - mu_x * mu_x
    syy = _blur_valid(y * y, g) - mu_y * mu_y
    sxy = _blur_valid(x * y, g) - mu_x * mu_y
    num = (2.0 * mu_x * mu_y + c1) * (2.0 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)
    smap = (num / den).mean(dim=1)  # (B, h', w')
    return smap.reshape(*batch, *smap.shape[-2:])


def ssim(pred, target, mask=None, data_range: float = 1.0) -> torch.Tensor:
    """Structural similarity (1 for identical images); with ``mask``, averaged over masked window centres."""
    smap = ssim_map(pred, target, data_range)
    if mask is None:
        return smap.mean(dim=(-2, -1))
    a = _as_tensor(pred)
    m = _mask_tensor(mask, a.shape, smap.device)
    r = SSIM_WINDOW // 2
    m = m[..., r:m.shape[-2] - r, r:m.shape[-1] - r].to(smap.dtype)
    return (smap * m).sum(dim=(-2, -1)) / m.sum(dim=(-2, -1))


def masked_ssim(pred, target, pred_alpha, target_alpha, data_range: float = 1.0) -> torch.Tensor:
    """SSIM over the union of the two silhouettes (see the module docstring)."""
    return ssim(pred, target, union_mask(pred_alpha, target_alpha), data_range)


# ----------------------------------------------------------------------------- silhouettes

def silhouette_iou(pred_alpha, target_alpha, threshold: float = MASK_THRESHOLD) -> float:
    """Intersection over union of alpha > threshold (1.0 when both are empty)."""
    a, b = np.asarray(pred_alpha) > threshold, np.asarray(target_alpha) > threshold
    if a.shape != b.shape:
        raise ValueError(f"alpha shapes differ: {a.shape} vs {b.shape}")
    union = int(np.count_nonzero(a | b))
    return 1.0 if union == 0 else float(np.count_nonzero(a & b)) / union


# ----------------------------------------------------------------------------- geometry

def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int,
                   seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points uniform by area on the mesh, and the index of the face each lies on."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    areas = triangle_areas(v, f)
    total = areas.sum()
    if len(f) == 0 or not np.isfinite(total) or total <= 0:
        raise ValueError("mesh has no surface area to sample")
    rng = np.random.default_rng(seed)
    face_idx = rng.choice(len(f), size=count, p=areas / total)
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    u, w = 1.0 - s, s * r2
    a, b, c = v[f[face_idx, 0]], v[f[face_idx, 1]], v[f[face_idx, 2]]
    pts = u[:, None] * a + (s * (1.0 - r2))[:, None] * b + w[:, None] * c
    return pts, face_idx


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest point to ``p[i]`` on triangle ``(a[i], b[i], c[i])`` (all (N, 3)), by Voronoi region."""
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c

    def dot(x, y):
        return np.einsum("ij,ij->i", x, y)

    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        out = a + ab * (vb / denom)[:, None] + ac * (vc / denom)[:, None]  # inside the face
        # Edges and vertices, lowest priority first (later assignments win).
        cb = c - b
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        sel = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        out = np.where(sel[:, None], b + cb * t_bc[:, None], out)
        t_ac = d2 / (d2 - d6)
        sel = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out = np.where(sel[:, None], a + ac * t_ac[:, None], out)
        sel = (d6 >= 0) & (d5 <= d6)
        out = np.where(sel[:, None], c, out)
        t_ab = d1 / (d1 - d3)
        sel = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out = np.where(sel[:, None], a + ab * t_ab[:, None], out)
        sel = (d3 >= 0) & (d4 <= d3)
        out = np.where(sel[:, None], b, out)
        sel = (d1 <= 0) & (d2 <= 0)
        out = np.where(sel[:, None], a, out)
    bad = ~np.isfinite(out).all(axis=1)  # degenerate triangles: nearest vertex
    if bad.any():
        corners = np.stack([a[bad], b[bad], c[bad]], axis=1)
        k = np.argmin(np.linalg.norm(corners - p[bad, None], axis=2), axis=1)
        out[bad] = corners[np.arange(len(k)), k]
    return out


def _brute_nearest(query: np.ndarray, ref: np.ndarray, budget: int = 8_000_000) -> tuple[np.ndarray, np.ndarray]:
    q = torch.as_tensor(query, dtype=torch.float64)
    r = torch.as_tensor(ref, dtype=torch.float64)
    rows = max(1, budget // max(1, len(ref)))
    dist = np.empty(len(query))
    idx = np.empty(len(query), dtype=np.int64)
    for s in range(0, len(query), rows):
        d = torch.cdist(q[s:s + rows], r)
        m, i = d.min(dim=1)
        dist[s:s + rows], idx[s:s + rows] = m.numpy(), i.numpy()
    return dist, idx


def _grid_cell(ref: np.ndarray, per_cell: float = 8.0) -> float:
    """A cell size giving about ``per_cell`` reference points per occupied cell."""
    extent = float(np.max(np.ptp(ref, axis=0))) if len(ref) > 1 else 1.0
    h = max(extent, 1e-9) / 32.0
    for _ in range(4):
        c = np.floor((ref - ref.min(axis=0)) / h).astype(np.int64)
        dims = c.max(axis=0) + 1
        occupied = len(np.unique((c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]))
        avg = len(ref) / occupied
        h *= float(np.clip(np.sqrt(per_cell / avg), 0.25, 4.0))
    return h


def nearest_neighbors(query: np.ndarray, ref: np.ndarray, cell: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact nearest reference point of every query point: (distances (Q,), indices (Q,)).

    A uniform grid (cell ``cell``, default: about 8 reference points per occupied cell) searched over
    the 27 cells around each query; queries with no reference point within one cell are searched
    again with cells 3x larger (up to three times), then by chunked brute force. Small problems
    (Q x R <= ``BRUTE_FORCE_PAIRS``) go to brute force directly.
    """
    query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    ref = np.asarray(ref, dtype=np.float64).reshape(-1, 3)
    if len(ref) == 0:
        raise ValueError("no reference points")
    dist = np.full(len(query), np.inf)
    idx = np.full(len(query), -1, dtype=np.int64)
    if len(query) == 0:
        return dist, idx
    if len(query) * len(ref) <= BRUTE_FORCE_PAIRS:
        return _brute_nearest(query, ref)
    h = cell or _grid_cell(ref)
    todo = np.arange(len(query))
    lo, hi = np.minimum(query.min(axis=0), ref.min(axis=0)), np.maximum(query.max(axis=0), ref.max(axis=0))
    for _ in range(4):
        grid = _Grid(ref, h, lo, hi)
        per_cell = len(ref) / len(grid.uniq)
        chunk = max(64, int(PAIRS_PER_BATCH / per_cell))  # bounds the (query, reference) pairs in memory
        for s in range(0, len(todo), chunk):
            sel = todo[s:s + chunk]
            dist[sel], idx[sel] = grid.search(query[sel])
        todo = todo[~(dist[todo] <= h)]  # the true nearest may lie outside the 27 cells
        if len(todo) == 0:
            return dist, idx
        h *= 3.0
    dist[todo], idx[todo] = _brute_nearest(query[todo], ref)
    return dist, idx


class _Grid:
    """Reference points bucketed in cubic cells of size ``h`` (sorted by cell key)."""

    def __init__(self, ref: np.ndarray, h: float, lo: np.ndarray, hi: np.ndarray):
        """``lo``/``hi`` bound the reference and the query points."""
        self.ref, self.h = ref, h
        self.lo = lo - 2.0 * h
        self.dims = np.floor((hi - self.lo) / h).astype(np.int64) + 3
        cells = np.floor((ref - self.lo) / h).astype(np.int64)
        keys = self._key(cells)
        self.order = np.argsort(keys, kind="stable")
        self.uniq, self.start, self.counts = np.unique(keys[self.order], return_index=True, return_counts=True)

    def _key(self, c: np.ndarray) -> np.ndarray:
        return (c[:, 0] * self.dims[1] + c[:, 1]) * self.dims[2] + c[:, 2]

    def search(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cq = np.floor((query - self.lo) / self.h).astype(np.int64)
        inside = np.all((cq >= 1) & (cq <= self.dims - 2), axis=1)  # neighbours stay in the key range
        best_d2 = np.full(len(query), np.inf)
        best_i = np.full(len(query), -1, dtype=np.int64)
        for off in np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 3):
            nk = self._key(cq + off)
            pos = np.minimum(np.searchsorted(self.uniq, nk), len(self.uniq) - 1)
            qi = np.nonzero(inside & (self.uniq[pos] == nk))[0]
            if len(qi) == 0:
                continue
            ct = self.counts[pos[qi]]
            qrep = np.repeat(qi, ct)
            within = np.arange(len(qrep)) - np.repeat(np.cumsum(ct) - ct, ct)
            ridx = self.order[np.repeat(self.start[pos[qi]], ct) + within]
            diff = query[qrep] - self.ref[ridx]
            d2 = np.einsum("ij,ij->i", diff, diff)
            gmin = np.minimum.reduceat(d2, np.cumsum(ct) - ct)  # qrep is grouped by query
            hit = np.nonzero(d2 == np.repeat(gmin, ct))[0]  # a group's minimum (ties: any)
            q, r = qrep[hit], ridx[hit]
            better = d2[hit] < best_d2[q]
            best_d2[q[better]], best_i[q[better]] = d2[hit][better], r[better]
        return np.sqrt(best_d2), best_i


def point_to_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                     samples: np.ndarray | None = None, sample_faces: np.ndarray | None = None,
                     num_samples: int = 100_000, seed: int = 0) -> np.ndarray:
    """Distance of each point to the mesh surface (see the module docstring for the approximation)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if samples is None or sample_faces is None:
        samples, sample_faces = sample_surface(v, f, num_samples, seed)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d_sample, nn = nearest_neighbors(p, samples)
    tri = f[sample_faces[nn]]
    closest = closest_point_on_triangles(p, v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]])
    return np.minimum(np.linalg.norm(closest - p, axis=1), d_sample)


def geometry_errors(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, height: float | None = None,
                    num_samples: int = 100_000, seed: int = 0) -> dict[str, float]:
    """p2s, s2p and Chamfer of predicted ``points`` against a ground-truth mesh (world units and
    ``*_rel`` = divided by ``height``, default: the mesh's Y extent)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        raise ValueError("no predicted points")
    v = np.asarray(vertices, dtype=np.float64)
    h = float(height) if height else float(np.ptp(v[:, 1]))
    samples, sample_faces = sample_surface(v, faces, num_samples, seed)
    p2s = point_to_surface(p, v, faces, samples, sample_faces)
    s2p, _ = nearest_neighbors(samples, p)
    out = {
        "p2s": float(p2s.mean()),
        "p2s_median": float(np.median(p2s)),
        "p2s_p90": float(np.percentile(p2s, 90)),
        "s2p": float(s2p.mean()),
        "s2p_median": float(np.median(s2p)),
    }
    out["chamfer"] = 0.5 * (out["p2s"] + out["s2p"])
    out.update({f"{k}_rel": val / h for k, val in list(out.items())})
    out.update({"height": h, "num_points": int(len(p)), "num_surface_samples": int(num_samples)})
    return out


def load_lpips(heads_path, alexnet_path=None):
    """The LPIPS (AlexNet) module for losses: see :func:`humanvdm_core.perceptual.load_lpips`
    (``module(x, y)`` takes (N, 3, H, W) images in [-1, 1] and returns (N,) distances)."""
    from humanvdm_core.perceptual import load_lpips as _load

    return _load(heads_path, alexnet_path)


def finite_or_none(x: float) -> float | str | None:
    """A JSON-safe number: ``inf`` -> "inf", NaN -> None."""
    x = float(x)
    if math.isnan(x):
        return None
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return x
