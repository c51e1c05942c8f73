"""Differentiable 3D Gaussian rasterizer: numba and pure-PyTorch tiled CPU paths, a dense reference, gsplat.

Contract (mirrors ``gsplat.rasterization``'s argument names and conventions):

- ``means`` (N, 3) world positions; ``quats`` (N, 4) wxyz rotations, normalised here; ``scales`` (N, 3)
  linear standard deviations; ``opacities`` (N,) in [0, 1]; ``colors`` (N, D) or (C, N, D) features.
- ``viewmats`` (C, 4, 4) world-to-camera, OpenCV axes (x right, y down, z forward); ``Ks`` (C, 3, 3).
- Projection: camera-space covariance ``W R S S^T R^T W^T`` pushed through the EWA Jacobian of the
  perspective projection, whose x/z, y/z are clamped to 1.3x the half field of view (as gsplat); the 2D
  mean is the unclamped ``K (R X + t)`` divided by z. ``eps2d`` is added to the 2D covariance diagonal.
- Culling: Gaussians with depth (camera z) <= ``near_plane`` or >= ``far_plane``, a non-positive 2D
  determinant, opacity below 1/255, or a screen box entirely outside the image are dropped (radius 0).
- Screen extent: per-axis radius ``ceil(k * sqrt(Sigma2d_ii))`` with ``k = min(3.33, sqrt(2 ln(255 o)))``
  (gsplat's opacity-tightened 3-sigma box): it encloses every pixel where the Gaussian's alpha can reach
  1/255, so the tiled result equals the dense one exactly.
- Pixel centres at (x + 0.5, y + 0.5). alpha = min(0.999, o * exp(-0.5 d^T Sigma2d^-1 d)) (gsplat's clamp;
  the original 3DGS code uses 0.99); alpha < 1/255 or a negative exponent is skipped. Front-to-back
  compositing in depth order with transmittance T; a pixel stops (exclusively) at the first Gaussian
  that would bring T to <= 1e-4. colour = sum_i c_i a_i T_i + T_final * background; alpha = 1 - T_final.
- Returns ``render_colors`` (C, H, W, D), ``render_alphas`` (C, H, W, 1) and ``meta`` with ``means2d``
  (C, N, 2; call ``retain_grad()`` on it before backward for densification statistics), ``conics``
  (C, N, 3: a, b, c of the inverse 2D covariance [[a, b], [b, c]]), ``depths`` (C, N), ``radii``
  (C, N, 2) int32, ``width``, ``height``, ``tile_size``, ``backend`` and, for the torch and numba paths,
  ``n_intersections`` (tile-Gaussian pairs per camera).

Backends:

- ``"numba"``: projection in torch; tile binning and the compositing forward and backward compiled for
  the CPU with numba (:mod:`humanvdm_core.splat.rasterize_numba`; tiles of ``NUMBA_TILE_SIZE``, float64
  arithmetic, outputs in the inputs' dtype; CUDA inputs are copied to the CPU and back). Same results
  and gradients as ``"torch"``, its test oracle, several times faster. Runs on
  ``min(torch.get_num_threads(), NUMBA_NUM_THREADS)`` threads. The kernels compile on first use (~5-10 s)
  and are cached on disk (then load in about a second).
- ``"torch"``: tiled pure PyTorch, differentiable w.r.t. means, quats, scales, opacities, colors, viewmats
  and backgrounds; the compositing step has an analytic backward that recomputes each depth chunk, so
  memory stays bounded: working tensors of ``CHUNK_ELEMENTS``, nothing of size intersections x pixels is
  kept. The reference for the numba kernels.
- ``"dense"``: every Gaussian x every pixel, a slow reference for tests.
- ``"gsplat"``: CUDA; gsplat imported lazily; outputs on the CUDA device.
- ``"auto"``: gsplat when the inputs are on a CUDA device and gsplat imports; else, for CPU inputs, numba
  when it imports; else torch.

``"numba"``, ``"torch"`` and ``"dense"`` are differentiable w.r.t. the same inputs (gsplat w.r.t. its own).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

ALPHA_MAX = 0.999  # gsplat's clamp (3DGS uses 0.99)
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
EXTEND_MAX = 3.33
FOV_CLAMP = 0.3  # clamp x/z, y/z to the image edge plus 0.3 * tan(half fov), as gsplat
# Elements per (tiles x Gaussians x pixels) working tensor in the torch path (~8 MB in float32).
CHUNK_ELEMENTS = 1 << 21
CHUNK_GAUSSIANS = 64  # depth-list entries per step (the granularity of early termination)
# The torch path's tile size. Its output does not depend on it (the screen boxes enclose every pixel a
# Gaussian can reach), only its speed: on CPU 8 px tiles waste fewer Gaussian x pixel evaluations than
# gsplat's 16 (about 3x faster on a 200k-Gaussian human at 576^2). ``tile_size`` is gsplat's.
TORCH_TILE_SIZE = 8
# The numba path's tile size (output independent of it). Its kernels visit only the pixels inside each
# Gaussian's screen box, so larger tiles cost little extra work and halve the binning.
NUMBA_TILE_SIZE = 16
BACKENDS = ("auto", "torch", "numba", "gsplat", "dense")


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(N, 4) wxyz (not necessarily unit) -> (N, 3, 3) rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariances_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariances R diag(s^2) R^T, (N, 3, 3)."""
    m = quat_to_rotmat(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


def project_gaussians(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor, Ks: Tensor,
    width: int, height: int, near_plane: float = 0.01, far_plane: float = 1e10, eps2d: float = 0.3,
) -> dict[str, Tensor]:
    """Project Gaussians into every camera: means2d (C,N,2), conics (C,N,3), depths (C,N), radii (C,N,2)."""
    rot = viewmats[:, :3, :3]
    trans = viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", rot, means) + trans[:, None, :]
    cov_c = torch.einsum("cij,njk,clk->cnil", rot, covariances_3d(quats, scales), rot)
    x, y, z = means_c.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
    zs = torch.where(in_depth, z, torch.ones_like(z))  # keeps culled entries finite (and their grads 0)

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + FOV_CLAMP * tan_fovx, cx / fx + FOV_CLAMP * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + FOV_CLAMP * tan_fovy, cy / fy + FOV_CLAMP * tan_fovy
    tx = zs * torch.minimum(torch.maximum(x / zs, -lim_x_neg), lim_x_pos)
    ty = zs * torch.minimum(torch.maximum(y / zs, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(zs)
    jac = torch.stack([
        torch.stack([fx / zs, zero, -fx * tx / (zs * zs)], dim=-1),
        torch.stack([zero, fy / zs, -fy * ty / (zs * zs)], dim=-1),
    ], dim=-2)  # (C, N, 2, 3)
    cov2d = jac @ cov_c @ jac.transpose(-1, -2)
    a = cov2d[..., 0, 0] + eps2d
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    valid = in_depth & (det > 0)
    det_s = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)

    with torch.no_grad():
        opac = opacities.detach().expand_as(z)
        extend = torch.sqrt(2.0 * torch.log((opac / ALPHA_MIN).clamp_min(1.0))).clamp_max(EXTEND_MAX)
        valid = valid & (opac >= ALPHA_MIN)
        rx = torch.ceil(extend * torch.sqrt(a.detach().clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(c.detach().clamp_min(0)))
        mx, my = means2d.detach().unbind(-1)
        on_screen = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        keep = valid & on_screen & (rx > 0) & (ry > 0)
        radii = torch.stack([rx, ry], dim=-1).nan_to_num(0.0) * keep[..., None]
    return {"means2d": means2d, "conics": conics, "depths": z, "radii": radii.to(torch.int32)}


def _check_inputs(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                  viewmats: Tensor, Ks: Tensor, backgrounds: Tensor | None) -> None:
    n = means.shape[0]
    if means.shape != (n, 3) or quats.shape != (n, 4) or scales.shape != (n, 3) or opacities.shape != (n,):
        raise ValueError(f"expected means (N,3), quats (N,4), scales (N,3), opacities (N,); got "
                         f"{tuple(means.shape)}, {tuple(quats.shape)}, {tuple(scales.shape)}, "
                         f"{tuple(opacities.shape)}")
    c = viewmats.shape[0]
    if viewmats.shape != (c, 4, 4) or Ks.shape != (c, 3, 3):
        raise ValueError(f"expected viewmats (C,4,4), Ks (C,3,3); got {tuple(viewmats.shape)}, {tuple(Ks.shape)}")
    if not (colors.dim() == 2 and colors.shape[0] == n) and not (colors.dim() == 3 and colors.shape[:2] == (c, n)):
        raise ValueError(f"expected colors (N,D) or (C,N,D); got {tuple(colors.shape)}")
    if backgrounds is not None and backgrounds.shape != (c, colors.shape[-1]):
        raise ValueError(f"expected backgrounds (C,D); got {tuple(backgrounds.shape)}")


def _numba_available() -> bool:
    """Whether the compiled CPU compositing imports (numba installed and working)."""
    try:
        from humanvdm_core.splat import rasterize_numba  # noqa: F401
    except ImportError:
        return False
    return True


def _gsplat_available() -> bool:
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def gsplat_missing_warning() -> str | None:
    """The run-summary warning for a CUDA device without gsplat (``auto`` then rasterizes with the
    ``"torch"`` path on the GPU, a ``full`` training step 28x slower on an H100: hours instead of minutes),
    or None when there is no CUDA device or gsplat imports."""
    if not torch.cuda.is_available() or _gsplat_available():
        return None
    return ("a CUDA GPU is present but gsplat does not import: the splats are rasterized by the PyTorch "
            "fallback, about 28x slower (the full preset: hours instead of ~9.5 min on an H100); "
            "install gsplat, the cuda extra: pip install -e '.[cuda]' (it compiles its kernels on first use: 90 s "
            "on 16 cores)")


def rasterize_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    backgrounds: Tensor | None = None,
    backend: str = "auto",
    tile_size: int = 16,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Render Gaussians into C cameras: (render_colors (C,H,W,D), render_alphas (C,H,W,1), meta).

    See the module docstring for the conventions. ``backend``: "auto" | "numba" | "torch" | "gsplat" |
    "dense". ``tile_size`` is passed to gsplat; the CPU paths tile at ``NUMBA_TILE_SIZE`` /
    ``TORCH_TILE_SIZE`` (same output).
    """
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds)
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}: expected one of {', '.join(BACKENDS)}")
    if backend == "auto":
        if means.is_cuda:
            backend = "gsplat" if _gsplat_available() else "torch"
        else:
            backend = "numba" if _numba_available() else "torch"
    if backend == "gsplat":
        return _rasterize_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                 near_plane, far_plane, eps2d, backgrounds, tile_size)
    if backend == "numba" and not _numba_available():
        raise RuntimeError("rasterizer backend 'numba' needs the numba package (pip install numba); "
                           "use backend='torch' (or 'auto') without it")
    proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height,
                             near_plane, far_plane, eps2d)
    tile = NUMBA_TILE_SIZE if backend == "numba" else TORCH_TILE_SIZE
    meta: dict[str, Any] = dict(proj, width=width, height=height, tile_size=tile, backend=backend)
    out_colors, out_alphas, n_isect = [], [], []
    for cam in range(viewmats.shape[0]):
        cols = colors if colors.dim() == 2 else colors[cam]
        args = (proj["means2d"][cam], proj["conics"][cam], proj["depths"][cam], proj["radii"][cam],
                opacities, cols, width, height)
        if backend == "dense":
            img, trans = _composite_dense(*args)
        elif backend == "numba":
            img, trans, n = _composite_numba(*args, tile_size=tile)
            n_isect.append(n)
        else:
            img, trans, n = _composite_tiled(*args, tile_size=tile)
            n_isect.append(n)
        if backgrounds is not None:
            img = img + trans[..., None] * backgrounds[cam]
        out_colors.append(img)
        out_alphas.append((1.0 - trans)[..., None])
    if backend != "dense":
        meta["n_intersections"] = n_isect
    return torch.stack(out_colors), torch.stack(out_alphas), meta


def _rasterize_gsplat(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                      viewmats: Tensor, Ks: Tensor, width: int, height: int, near_plane: float,
                      far_plane: float, eps2d: float, backgrounds: Tensor | None,
                      tile_size: int) -> tuple[Tensor, Tensor, dict[str, Any]]:
    if not torch.cuda.is_available():
        raise RuntimeError("rasterizer backend 'gsplat' needs CUDA, and torch.cuda.is_available() is False; "
                           "use backend='torch' (or 'auto') on this machine")
    try:
        import gsplat
    except ImportError as exc:
        raise RuntimeError("rasterizer backend 'gsplat' needs the gsplat package (pip install gsplat); "
                           "use backend='torch' (or 'auto') without it") from exc
    dev = torch.device("cuda")
    tensors = [t.to(dev) for t in (means, quats, scales, opacities, colors, viewmats, Ks)]
    bg = backgrounds.to(dev) if backgrounds is not None else None
    render_colors, render_alphas, meta = gsplat.rasterization(
        *tensors, width=width, height=height, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
        backgrounds=bg, tile_size=tile_size, packed=False, render_mode="RGB", rasterize_mode="classic",
        sh_degree=None,
    )
    meta = dict(meta, backend="gsplat")
    return render_colors, render_alphas, meta


# ----------------------------------------------------------------------------------------- dense reference


def _composite_dense(means2d: Tensor, conics: Tensor, depths: Tensor, radii: Tensor, opacities: Tensor,
                     colors: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Every kept Gaussian against every pixel, one Gaussian at a time in depth order (tiny scenes only)."""
    dtype, dev = means2d.dtype, means2d.device
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype, device=dev) + 0.5,
                            torch.arange(width, dtype=dtype, device=dev) + 0.5, indexing="ij")
    img = torch.zeros(height, width, colors.shape[-1], dtype=dtype, device=dev)
    trans = torch.ones(height, width, dtype=dtype, device=dev)
    done = torch.zeros(height, width, dtype=torch.bool, device=dev)
    kept = torch.nonzero((radii > 0).all(-1)).flatten()
    for g in kept[torch.argsort(depths.detach()[kept], stable=True)].tolist():
        dx, dy = means2d[g, 0] - xs, means2d[g, 1] - ys
        a, b, c = conics[g]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp_max(opacities[g] * torch.exp(-sigma), ALPHA_MAX)
        use = (sigma >= 0) & (alpha >= ALPHA_MIN) & ~done
        next_t = trans * (1.0 - alpha)
        stop = use & (next_t <= T_MIN)
        use = use & ~stop
        done = done | stop
        img = img + torch.where(use, alpha * trans, torch.zeros_like(trans))[..., None] * colors[g]
        trans = torch.where(use, next_t, trans)
    return img, trans


# ----------------------------------------------------------------------------------------- numba path


def _composite_numba(means2d: Tensor, conics: Tensor, depths: Tensor, radii: Tensor, opacities: Tensor,
                     colors: Tensor, width: int, height: int,
                     tile_size: int = 16) -> tuple[Tensor, Tensor, int]:
    """Bin Gaussians to tiles and composite them with the compiled kernels: (colour (H, W, D) without
    background, final T (H, W), intersections). Same contract as :func:`_composite_tiled`."""
    from humanvdm_core.splat import rasterize_numba

    bins = rasterize_numba.bin_gaussians(means2d, radii, depths, tile_size, width, height)
    img, trans = rasterize_numba.composite(means2d, conics, opacities.to(means2d.dtype), colors.to(means2d.dtype),
                                           bins)
    return img, trans, int(bins.gids.size)


# ----------------------------------------------------------------------------------------- tiled torch path


def _composite_tiled(means2d: Tensor, conics: Tensor, depths: Tensor, radii: Tensor, opacities: Tensor,
                     colors: Tensor, width: int, height: int,
                     tile_size: int = 16) -> tuple[Tensor, Tensor, int]:
    """Bin Gaussians to tiles, sort by depth per tile, composite batches of tiles in depth chunks."""
    dtype, dev = means2d.dtype, means2d.device
    n, dim = means2d.shape[0], colors.shape[-1]
    tiles_w, tiles_h = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n_tiles, n_pix = tiles_w * tiles_h, tile_size * tile_size

    with torch.no_grad():
        gids, tile_ids = _intersect_tiles(means2d.detach(), radii, depths.detach(), tile_size, tiles_w, tiles_h)
        counts = torch.bincount(tile_ids, minlength=n_tiles)
        starts = torch.cumsum(counts, 0) - counts
        busy = torch.nonzero(counts).flatten()
        busy = busy[torch.argsort(counts[busy], descending=True, stable=True)]

    # Per-Gaussian arrays with one transparent dummy row (index n) used to pad the per-tile lists.
    feats = torch.cat([means2d, conics, opacities[:, None].to(dtype)], dim=1)
    feats = torch.cat([feats, feats.new_zeros(1, feats.shape[1])])
    cols = torch.cat([colors.to(dtype), colors.new_zeros(1, dim).to(dtype)])
    local = torch.arange(n_pix, device=dev)
    tile_offset = torch.stack([local % tile_size, local // tile_size], dim=-1).to(dtype) + 0.5

    results, transes = [], []
    i = 0
    while i < busy.numel():
        kmax = int(counts[busy[i]])
        kc = min(kmax, CHUNK_GAUSSIANS)
        batch = max(1, CHUNK_ELEMENTS // (kc * n_pix))
        tiles = busy[i:i + batch]
        i += batch
        with torch.no_grad():
            k = torch.arange(kmax, device=dev)
            pos = starts[tiles, None] + k[None, :]
            inside = k[None, :] < counts[tiles, None]
            index = torch.where(inside, gids[pos.clamp_max(max(gids.numel() - 1, 0))], torch.full_like(pos, n))
            origin = torch.stack([tiles % tiles_w, tiles // tiles_w], dim=-1).to(dtype) * tile_size
            pix = origin[:, None, :] + tile_offset[None]  # (B, P, 2)
        if torch.is_grad_enabled() and (feats.requires_grad or cols.requires_grad):
            img, trans = _Composite.apply(feats, cols, index, pix, kc)
        else:
            img, trans = _composite_forward(feats, cols, index, pix, kc)
        results.append(img)
        transes.append(trans)

    img = torch.zeros(n_tiles, n_pix, dim, dtype=dtype, device=dev)
    trans = torch.ones(n_tiles, n_pix, dtype=dtype, device=dev)
    if results:
        img = img.index_copy(0, busy, torch.cat(results))
        trans = trans.index_copy(0, busy, torch.cat(transes))
    img = img.reshape(tiles_h, tiles_w, tile_size, tile_size, dim).permute(0, 2, 1, 3, 4)
    img = img.reshape(tiles_h * tile_size, tiles_w * tile_size, dim)[:height, :width]
    trans = trans.reshape(tiles_h, tiles_w, tile_size, tile_size).permute(0, 2, 1, 3)
    trans = trans.reshape(tiles_h * tile_size, tiles_w * tile_size)[:height, :width]
    return img, trans, int(gids.numel())


def _intersect_tiles(means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tiles_w: int,
                     tiles_h: int) -> tuple[Tensor, Tensor]:
    """Tile-Gaussian pairs sorted by (tile id, depth): (gaussian ids, tile ids), both (M,) int64."""
    dev = means2d.device
    kept = torch.nonzero((radii > 0).all(-1)).flatten()
    m, r = means2d[kept], radii[kept].to(means2d.dtype)
    x0 = torch.floor((m[:, 0] - r[:, 0]) / tile_size).clamp(0, tiles_w).long()
    x1 = torch.ceil((m[:, 0] + r[:, 0]) / tile_size).clamp(0, tiles_w).long()
    y0 = torch.floor((m[:, 1] - r[:, 1]) / tile_size).clamp(0, tiles_h).long()
    y1 = torch.ceil((m[:, 1] + r[:, 1]) / tile_size).clamp(0, tiles_h).long()
    span_x = x1 - x0
    count = span_x * (y1 - y0)
    total = int(count.sum())
    if total == 0:
        empty = torch.zeros(0, dtype=torch.long, device=dev)
        return empty, empty
    rep = torch.repeat_interleave(torch.arange(kept.numel(), device=dev), count)
    first = torch.cumsum(count, 0) - count
    local = torch.arange(total, device=dev) - first[rep]
    span = span_x[rep]
    tile_ids = (y0[rep] + local // span) * tiles_w + x0[rep] + local % span
    rank = torch.empty_like(kept)
    rank[torch.argsort(depths[kept], stable=True)] = torch.arange(kept.numel(), device=dev)
    order = torch.argsort(tile_ids * kept.numel() + rank[rep])
    return kept[rep[order]], tile_ids[order]


def _chunk_alpha(f: Tensor, px: Tensor, py: Tensor) -> tuple[Tensor, ...]:
    """Per (tile, Gaussian, pixel): dx, dy, exp(-sigma), o exp(-sigma), alpha (clamped, 0 where skipped)."""
    dx = f[..., 0, None] - px
    dy = f[..., 1, None] - py
    sigma = 0.5 * (f[..., 2, None] * dx * dx + f[..., 4, None] * dy * dy) + f[..., 3, None] * dx * dy
    vis = torch.exp(-sigma)
    raw = f[..., 5, None] * vis
    alpha = torch.where((sigma >= 0) & (raw >= ALPHA_MIN), raw.clamp_max(ALPHA_MAX), torch.zeros_like(raw))
    return dx, dy, vis, raw, alpha


def _chunk_weights(alpha: Tensor, trans: Tensor, done: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Apply the front-to-back stopping rule to one depth chunk.

    Returns (alpha of the Gaussians actually composited, T before each of them, T after the chunk, the
    pixels whose list ended in this chunk or before).
    """
    t_incl = trans[:, None, :] * torch.cumprod(1.0 - alpha, dim=1)
    stop = t_incl <= T_MIN  # monotone along the list: the first True ends the pixel (exclusively)
    alpha = torch.where(stop | done[:, None, :], torch.zeros_like(alpha), alpha)
    keep = torch.cumprod(1.0 - alpha, dim=1)
    t_excl = trans[:, None, :] * torch.cat([torch.ones_like(keep[:, :1]), keep[:, :-1]], dim=1)
    return alpha, t_excl, trans * keep[:, -1], done | stop[:, -1]


def _composite_forward(feats: Tensor, cols: Tensor, index: Tensor, pix: Tensor,
                       chunk: int) -> tuple[Tensor, Tensor]:
    """Composite tiles (B) x depth-sorted Gaussians (index (B, K)) over their pixels (pix (B, P, 2)).

    Walks the depth lists in chunks of ``chunk`` carrying (colour, T, done) per pixel; a tile leaves the
    working set as soon as all its pixels are done. Returns colour (B, P, D) without background and T (B, P).
    """
    nb, kmax = index.shape
    out_img = cols.new_zeros(nb, pix.shape[1], cols.shape[-1])
    out_trans = feats.new_ones(nb, pix.shape[1])
    rows = torch.arange(nb, device=feats.device)
    img, trans = out_img.clone(), out_trans.clone()
    done = torch.zeros(nb, pix.shape[1], dtype=torch.bool, device=feats.device)
    px, py = pix[..., 0][:, None, :], pix[..., 1][:, None, :]
    for k0 in range(0, kmax, chunk):
        idx = index[:, k0:k0 + chunk]
        alpha = _chunk_alpha(feats[idx], px, py)[-1]
        alpha, t_excl, trans, done = _chunk_weights(alpha, trans, done)
        img = img + torch.einsum("bkp,bkd->bpd", alpha * t_excl, cols[idx])
        finished = done.all(dim=1)
        if bool(finished.any()):
            out_img[rows[finished]] = img[finished]
            out_trans[rows[finished]] = trans[finished]
            alive = ~finished
            rows, img, trans, done = rows[alive], img[alive], trans[alive], done[alive]
            index, px, py = index[alive], px[alive], py[alive]
            if rows.numel() == 0:
                break
    out_img[rows] = img
    out_trans[rows] = trans
    return out_img, out_trans


class _Composite(torch.autograd.Function):
    """Tile compositing with an analytic backward that recomputes each depth chunk (bounded memory)."""

    @staticmethod
    def forward(ctx, feats: Tensor, cols: Tensor, index: Tensor, pix: Tensor, chunk: int):  # noqa: ANN205
        img, trans = _composite_forward(feats, cols, index, pix, chunk)
        ctx.save_for_backward(feats, cols, index, pix, img, trans)
        ctx.chunk = chunk
        return img, trans

    @staticmethod
    def backward(ctx, grad_img: Tensor, grad_trans: Tensor):  # noqa: ANN205
        feats, cols, index, pix, img, trans_final = ctx.saved_tensors
        nb, kmax = index.shape
        grad_feats = torch.zeros_like(feats)
        grad_cols = torch.zeros_like(cols)
        # dL/dalpha_i = T_i (c_i . g) - (sum_{j>i} w_j (c_j . g) + T_final dL/dT_final) / (1 - alpha_i), with
        # w_j = alpha_j T_j; the suffix sum is the total minus the running prefix, so the lists are walked
        # front to back again, recomputing each chunk.
        total = (img * grad_img).sum(-1)  # (B, P): sum_j w_j (c_j . g)
        tail_final = grad_trans * trans_final  # (B, P): dL/dT_final * T_final
        prefix = torch.zeros_like(total)
        trans = torch.ones_like(total)
        done = torch.zeros(total.shape, dtype=torch.bool, device=total.device)
        px, py = pix[..., 0][:, None, :], pix[..., 1][:, None, :]
        for k0 in range(0, kmax, ctx.chunk):
            idx = index[:, k0:k0 + ctx.chunk]
            f = feats[idx]
            c = cols[idx]
            dx, dy, vis, raw, alpha = _chunk_alpha(f, px, py)
            alpha, t_excl, trans, done = _chunk_weights(alpha, trans, done)
            weight = alpha * t_excl
            cg = torch.einsum("bkd,bpd->bkp", c, grad_img)
            prefix_incl = prefix[:, None, :] + torch.cumsum(weight * cg, dim=1)
            suffix = total[:, None, :] - prefix_incl
            d_alpha = torch.where(alpha > 0, t_excl * cg - (suffix + tail_final[:, None, :]) / (1.0 - alpha),
                                  torch.zeros_like(alpha))
            d_alpha = torch.where(raw < ALPHA_MAX, d_alpha, torch.zeros_like(d_alpha))  # clamped: no gradient
            d_sigma = -d_alpha * raw
            g = torch.stack([
                (d_sigma * (f[..., 2, None] * dx + f[..., 3, None] * dy)).sum(-1),
                (d_sigma * (f[..., 4, None] * dy + f[..., 3, None] * dx)).sum(-1),
                0.5 * (d_sigma * dx * dx).sum(-1),
                (d_sigma * dx * dy).sum(-1),
                0.5 * (d_sigma * dy * dy).sum(-1),
                (d_alpha * vis).sum(-1),
            ], dim=-1)  # (B, k, 6)
            grad_feats.index_add_(0, idx.reshape(-1), g.reshape(-1, g.shape[-1]))
            grad_cols.index_add_(0, idx.reshape(-1),
                                 torch.einsum("bkp,bpd->bkd", weight, grad_img).reshape(-1, cols.shape[-1]))
            prefix = prefix_incl[:, -1]
            alive = ~done.all(dim=1)
            if not bool(alive.all()):  # drop finished tiles from the working set, as the forward did
                if not bool(alive.any()):
                    break
                index, px, py, grad_img = index[alive], px[alive], py[alive], grad_img[alive]
                total, tail_final, prefix, trans, done = (total[alive], tail_final[alive], prefix[alive],
                                                          trans[alive], done[alive])
        return grad_feats, grad_cols, None, None, None
