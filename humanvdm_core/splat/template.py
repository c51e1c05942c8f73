"""Where the Gaussians start: the subject's own surface, and their colours in closed form.

The body template (the paper's) puts one Gaussian on each texel of the fitted body's UV map: whatever
lies off the naked body (a dress, a coat, long hair, a held object) has no Gaussian of its own. The
subject template starts from the subject's surface instead:

- the clothed proxy that ``diffuse`` wrote beside its orbit (``proxy.npz``, see
  :mod:`humanvdm_core.clothed_proxy`): points about ``spacing`` apart covering it evenly (random
  candidates thinned by a Poisson-disk pass), so their count follows the subject's surface
  (:func:`proxy_points`);
- else the visual hull of the training views' silhouettes (:func:`visual_hull_points`): a voxel grid
  around the body carved by every view's mask, its surface voxels, merged with the fitted body's
  points that lie deeper than :data:`HULL_CONCAVITY` voxels inside the hull (concavities no
  silhouette can carve, e.g. between the arms and the torso).

Where the input photo shows detail (:func:`detail_mask`: its luminance varies within a window of about
a spacing, inside the person -- a face, a print, a logo, a collar), the points are closer
(:func:`detail_points`: sampled ``detail_spacing`` x ``spacing`` apart, kept where the photo sees them on
its detail, thinned to ``spacing`` elsewhere), so the Gaussians can be as fine there as the photo is, and
the plain cloth and the unseen side keep the even spacing.

:func:`subject_anchor` turns such world points into a :class:`~humanvdm_core.splat.human.BodyAnchor`:
each point takes the skinning weights of its nearest fitted-body vertex and is un-posed with them
(inverse linear blend skinning), so pose refinement and LBS work as for the body template; its base
scale is the mean distance to its :data:`KNN` nearest neighbours.

:func:`project_colors` initialises every Gaussian's colour in closed form: each point is projected
into every training view, kept where it is visible (its depth within :data:`VISIBLE_TOLERANCE` of a
point z-buffer at :data:`ZBUFFER_SIZE` px) and inside the person's mask, and the frames' colours
there are averaged. Points no view sees are reported (``seen == 0``) and take their nearest seen
neighbour's colour.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from humanvdm_core.cameras import project_points, sample_bilinear
from humanvdm_core.workflow.errors import InputError

KNN = 4
NEAREST_CHUNK = 4096  # points measured against every reference point at once (nearest_index_brute)
NEAREST_LOCAL = 512  # points searched together in one box by nearest_index
NEAREST_BRUTE_PAIRS = 50_000_000  # up to this many point pairs nearest_index measures every pair
CANDIDATES = 6  # random candidates per kept point, thinned by a Poisson-disk pass ...
DISK = 0.75  # ... whose radius is this x the spacing (so the count stays about area / spacing²)
HULL_RESOLUTION = 128  # voxels along the longest side of the carving box
HULL_MARGIN = 0.25  # metres around the body's box that the hull may reach
HULL_MISSES = 0.1  # share of the views whose mask may disagree before a voxel is carved away
VOXEL_STAIRS = 0.85  # surface voxels per voxel-sized patch of a hull's area (measured: 1.7 m² body, 128 voxels)
HULL_CONCAVITY = 3  # body points deeper than this many voxels inside the hull are added to it
ZBUFFER_SIZE = 128  # largest z-buffer resolution of the visibility test ...
POINTS_PER_CELL = 3  # ... which aims at this many points of the near surface per cell
VISIBLE_TOLERANCE = 0.03  # metres behind the nearest point that still count as visible
DETAIL_WINDOW = 1.5  # the detail test's window, in spacings ...
DETAIL_STD = 0.08  # ... and the luminance standard deviation over it above which the photo shows detail
DETAIL_GROW = 1.0  # spacings by which the detail found is grown


def posed_body(anchor) -> tuple[np.ndarray, np.ndarray]:
    """The fitted body's posed vertices (V, 3) and skinning weights (V, J) from a body anchor."""
    if anchor.body_vertices is None or anchor.body_weights is None:
        raise InputError("the body fit holds no vertices/skinning weights: the subject template needs them")
    return np.asarray(anchor.body_vertices, np.float64), np.asarray(anchor.body_weights, np.float64)


def nearest_index_brute(points: np.ndarray, reference: np.ndarray, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Indices (P, k) of and distances (P, k) to the ``k`` nearest ``reference`` points of each point,
    every pair measured (the reference for :func:`nearest_index`)."""
    p = torch.as_tensor(points, dtype=torch.float32)
    r = torch.as_tensor(reference, dtype=torch.float32)
    idx, dist = [], []
    for chunk in p.split(NEAREST_CHUNK):
        d, i = torch.cdist(chunk, r).topk(k, dim=1, largest=False)
        idx.append(i)
        dist.append(d)
    return torch.cat(idx).numpy(), torch.cat(dist).numpy().astype(np.float64)


def nearest_index(points: np.ndarray, reference: np.ndarray, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Indices (P, k) of and distances (P, k) to the ``k`` nearest ``reference`` points of each point:
    :func:`nearest_index_brute`'s answer without measuring every pair when there are many (the ``full``
    preset's 100k points against themselves: 10^10 pairs). The points are taken in Morton order,
    :data:`NEAREST_LOCAL` at a time, against the reference points inside the chunk's box grown by a
    margin (twice the 99th percentile of the k-th neighbour distance of a sample); a point whose k-th
    neighbour there lies farther than the margin, which a point outside the grown box could beat, is
    measured against every reference point. Exact, and deterministic."""
    points = np.asarray(points, np.float64)
    reference = np.asarray(reference, np.float64)
    if len(points) * len(reference) <= NEAREST_BRUTE_PAIRS or len(reference) <= k:
        return nearest_index_brute(points, reference, k)
    sample = points[:: max(1, len(points) // 2048)]
    margin = 2.0 * float(np.percentile(nearest_index_brute(sample, reference, k)[1][:, -1], 99)) + 1e-9
    lo, hi = np.minimum(points.min(0), reference.min(0)), np.maximum(points.max(0), reference.max(0))
    cells = np.clip(((points - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.int64), 0, 1023)
    code = np.zeros(len(points), np.int64)
    for bit in range(10):  # interleave the three 10-bit coordinates: the Morton (Z-order) code
        for axis in range(3):
            code |= ((cells[:, axis] >> bit) & 1) << (3 * bit + axis)
    order = np.argsort(code, kind="stable")
    idx = np.empty((len(points), k), np.int64)
    dist = np.empty((len(points), k), np.float64)
    ref = torch.as_tensor(reference, dtype=torch.float32)
    for start in range(0, len(points), NEAREST_LOCAL):
        rows = order[start:start + NEAREST_LOCAL]
        chunk = points[rows]
        near = np.nonzero(np.all((reference >= chunk.min(0) - margin) & (reference <= chunk.max(0) + margin),
                                 axis=1))[0]
        if len(near) < k:
            i, d = nearest_index_brute(chunk, reference, k)
        else:
            dt, it = torch.cdist(torch.as_tensor(chunk, dtype=torch.float32), ref[near]).topk(
                k, dim=1, largest=False)
            i, d = near[it.numpy()], dt.numpy().astype(np.float64)
            far = d[:, -1] > margin
            if far.any():
                i[far], d[far] = nearest_index_brute(chunk[far], reference, k)
        idx[rows], dist[rows] = i, d
    return idx, dist


def neighbour_spacing(points: np.ndarray, k: int = KNN) -> np.ndarray:
    """(P,) mean distance of each point to its ``k`` nearest other points, clipped to [0.25, 3] x the median."""
    if len(points) <= k:
        return np.full(len(points), 0.01, np.float32)
    _, dist = nearest_index(points, points, k + 1)
    spacing = dist[:, 1:].mean(axis=1)
    median = float(np.median(spacing))
    return np.clip(spacing, 0.25 * median, 3.0 * median).astype(np.float32)


def surface_count(area: float, spacing: float) -> int:
    """Points that cover ``area`` (m²) at ``spacing`` (m) apart: ``area / spacing²``, at least 64."""
    return max(64, int(round(area / (spacing * spacing))))


def poisson_disk(candidates: np.ndarray, radius: float) -> np.ndarray:
    """Indices of a subset of ``candidates`` (N, 3), taken greedily in their order, no two closer than
    ``radius``: from candidates drawn at random on a surface, an even cover without clumps or gaps
    (random points alone leave holes that show between small Gaussians at a high viewing resolution)."""
    from numba import njit

    @njit(cache=True)
    def _greedy(p: np.ndarray, cell: np.ndarray, dims: np.ndarray, r2: float) -> np.ndarray:  # pragma: no cover
        head = np.full(dims[0] * dims[1] * dims[2], -1, np.int64)
        nxt = np.full(len(p), -1, np.int64)
        keep = np.zeros(len(p), np.bool_)
        for i in range(len(p)):
            ok = True
            for dx in range(-1, 2):
                for dy in range(-1, 2):
                    for dz in range(-1, 2):
                        cx, cy, cz = cell[i, 0] + dx, cell[i, 1] + dy, cell[i, 2] + dz
                        if cx < 0 or cy < 0 or cz < 0 or cx >= dims[0] or cy >= dims[1] or cz >= dims[2]:
                            continue
                        j = head[(cx * dims[1] + cy) * dims[2] + cz]
                        while j >= 0 and ok:
                            d = p[i] - p[j]
                            if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < r2:
                                ok = False
                            j = nxt[j]
                if not ok:
                    break
            if ok:
                keep[i] = True
                c = (cell[i, 0] * dims[1] + cell[i, 1]) * dims[2] + cell[i, 2]
                nxt[i] = head[c]
                head[c] = i
        return np.nonzero(keep)[0]

    p = np.ascontiguousarray(candidates, np.float64)
    lo = p.min(0)
    cell = np.floor((p - lo) / radius).astype(np.int64)
    dims = cell.max(0) + 1
    return _greedy(p, cell, dims.astype(np.int64), radius * radius)


def proxy_points(path: str | Path, spacing: float, seed: int = 0) -> np.ndarray:
    """Points about ``spacing`` apart, evenly covering the clothed proxy in ``path``: :data:`CANDIDATES` x
    :func:`surface_count` of its area drawn uniformly by area (seeded), thinned by :func:`poisson_disk`.
    A gown gets more than a T-shirt."""
    from humanvdm_core.clothed_proxy import SCHEMA
    from humanvdm_core.io import read_npz

    try:
        d = read_npz(path, SCHEMA, 1)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a clothed proxy ({exc})") from None
    v, f = np.asarray(d["vertices"], np.float64), np.asarray(d["faces"], np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if area.sum() <= 0:
        raise InputError(f"{path}: the clothed proxy has no area")
    rng = np.random.default_rng(seed)
    count = CANDIDATES * surface_count(float(area.sum()), spacing)
    tri = rng.choice(len(f), size=count, p=area / area.sum())
    u, w = rng.random(count), rng.random(count)
    flip = u + w > 1
    u, w = np.where(flip, 1 - u, u), np.where(flip, 1 - w, w)
    candidates = a[tri] + u[:, None] * (b[tri] - a[tri]) + w[:, None] * (c[tri] - a[tri])
    return candidates[poisson_disk(candidates, DISK * spacing)]


def visual_hull_points(views, body_vertices: np.ndarray, spacing: float, seed: int = 0,
                       resolution: int = HULL_RESOLUTION) -> np.ndarray:
    """Surface points of the training views' visual hull, merged with the body's concavities (see the
    module docstring), about ``spacing`` apart (:func:`surface_count` of the hull's area, estimated as
    its surface voxels / :data:`VOXEL_STAIRS`): :data:`CANDIDATES` times that many random places in
    randomly drawn surface voxels (seeded), thinned by :func:`poisson_disk`."""
    lo = body_vertices.min(0) - HULL_MARGIN
    hi = body_vertices.max(0) + HULL_MARGIN
    voxel = float((hi - lo).max()) / resolution
    dims = np.maximum(1, np.ceil((hi - lo) / voxel).astype(int))
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in dims], indexing="ij"), -1).reshape(-1, 3)
    centres = lo + (grid + 0.5) * voxel
    misses = np.zeros(len(centres), np.int32)
    alphas = views.alphas.cpu().numpy()
    w2c, K, S = views.w2c.cpu().numpy().astype(np.float64), views.K.cpu().numpy().astype(np.float64), views.size
    for i in range(len(alphas)):
        uv, z = project_points(centres, w2c[i], K[i])
        px = np.floor(uv).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 0] < S) & (px[:, 1] >= 0) & (px[:, 1] < S) & (z > 0)
        empty = np.ones(len(centres), bool)  # the frames show the whole person: outside a frame is empty
        empty[inside] = alphas[i][px[inside, 1], px[inside, 0]] < 0.5
        misses += empty
    solid = (misses <= int(HULL_MISSES * len(alphas))).reshape(*dims)
    if not solid.any():
        raise InputError("the visual hull of the frames' silhouettes is empty: the masks and cameras disagree")
    import cv2

    # surface: solid voxels with an empty 6-neighbour; depth inside: distance to the nearest empty voxel
    padded = np.pad(solid, 1)
    interior = solid.copy()
    for axis in range(3):
        for step in (-1, 1):
            interior &= np.roll(padded, step, axis=axis)[1:-1, 1:-1, 1:-1]
    surface = np.argwhere(solid & ~interior)
    rng = np.random.default_rng(seed)
    count = CANDIDATES * surface_count(len(surface) * voxel * voxel / VOXEL_STAIRS, spacing)
    surface = surface[rng.choice(len(surface), size=count, replace=True)]
    points = lo + (surface + rng.random(surface.shape)) * voxel
    points = points[poisson_disk(points, DISK * spacing)]
    # the body's points deep inside the hull: concavities the silhouettes cannot carve
    depth = np.stack([cv2.distanceTransform(s.astype(np.uint8), cv2.DIST_L2, 3) for s in solid.astype(np.uint8)])
    cell = np.floor((body_vertices - lo) / voxel).astype(np.int64)
    ok = np.all((cell >= 0) & (cell < dims), axis=1)
    deep = np.zeros(len(body_vertices), bool)
    deep[ok] = depth[cell[ok, 0], cell[ok, 1], cell[ok, 2]] > HULL_CONCAVITY
    return np.concatenate([points, body_vertices[deep]])


def subject_anchor(anchor, points: np.ndarray):
    """A :class:`~humanvdm_core.splat.human.BodyAnchor` of world ``points`` (P, 3) posed like ``anchor``'s
    body: canonical positions by inverse LBS with the nearest body vertex's skinning weights, base scales
    from the neighbour spacing; no UV map (``resolution`` 0, rows/cols -1)."""
    from humanvdm_core.body.model import blend_transforms

    verts, weights = posed_body(anchor)
    nearest, _ = nearest_index(points, verts)
    w = weights[nearest[:, 0]].astype(np.float32)
    bones = torch.as_tensor(anchor.bone_transforms, dtype=torch.float32)
    canon = torch.as_tensor(anchor.canonical_bone_transforms, dtype=torch.float32)
    wt = torch.as_tensor(w)
    posed_from_canonical = blend_transforms(wt, bones[None])[0] @ torch.linalg.inv(blend_transforms(wt, canon[None])[0])
    homo = torch.cat([torch.as_tensor(points, dtype=torch.float32), torch.ones(len(points), 1)], 1)
    canonical = (torch.linalg.inv(posed_from_canonical) @ homo[:, :, None])[:, :3, 0].numpy()
    n = len(points)
    return replace(anchor, resolution=0, rows=np.full(n, -1, np.int64), cols=np.full(n, -1, np.int64),
                   positions=canonical.astype(np.float32), weights=w, spacing=neighbour_spacing(points))


def zbuffer_size(points: int, coverage: float, size: int) -> int:
    """The z-buffer resolution at which the nearest surface puts about :data:`POINTS_PER_CELL` of
    ``points`` into each cell the subject covers (``coverage``: its share of the frame), at most
    :data:`ZBUFFER_SIZE` and ``size``: fine enough to keep the silhouette, coarse enough that no cell of the
    near surface is empty (where one is, the far surface behind it would count as visible)."""
    cells = points / 2.0 / POINTS_PER_CELL  # about half of a closed surface faces the camera
    return int(np.clip(np.sqrt(cells / max(coverage, 1e-3)), 8, min(ZBUFFER_SIZE, size)))


def visibility(points: np.ndarray, w2c: np.ndarray, K: np.ndarray, size: int,
               zbuffer_size: int = ZBUFFER_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """For one camera: which points are visible (P,) bool (in the image and within
    :data:`VISIBLE_TOLERANCE` of the nearest point in their z-buffer cell, ``zbuffer_size`` cells across)
    and their pixels (P, 2)."""
    uv, z = project_points(points, w2c, K)
    scale = zbuffer_size / size
    cell = np.floor(uv * scale).astype(np.int64)
    inside = (cell[:, 0] >= 0) & (cell[:, 0] < zbuffer_size) & (cell[:, 1] >= 0) & (cell[:, 1] < zbuffer_size) & (z > 0)
    flat = cell[:, 1] * zbuffer_size + cell[:, 0]
    zbuf = np.full(zbuffer_size * zbuffer_size, np.inf)
    np.minimum.at(zbuf, flat[inside], z[inside])
    visible = np.zeros(len(points), bool)
    visible[inside] = z[inside] <= zbuf[flat[inside]] + VISIBLE_TOLERANCE
    return visible, uv


def project_colors(points: np.ndarray, views) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form colours (P, 3) in [0, 1] of world points from the training views and how many views
    saw each (P,) (see the module docstring)."""
    images = views.images.cpu().numpy()
    alphas = views.alphas.cpu().numpy()
    w2c, K = views.w2c.cpu().numpy().astype(np.float64), views.K.cpu().numpy().astype(np.float64)
    total = np.zeros((len(points), 3))
    weight = np.zeros(len(points))
    seen = np.zeros(len(points), np.int32)
    zsize = zbuffer_size(len(points), float(alphas.mean()), views.size)
    for i in range(len(images)):
        vis, uv = visibility(points, w2c[i], K[i], views.size, zsize)
        a = sample_bilinear(alphas[i][..., None], uv[vis])[:, 0]
        w = np.where(a > 0.5, a, 0.0)
        total[vis] += w[:, None] * sample_bilinear(images[i], uv[vis])
        weight[vis] += w
        seen[vis] += w > 0
    colors = total / np.maximum(weight, 1e-8)[:, None]
    known = weight > 0
    if known.any() and not known.all():
        idx, _ = nearest_index(points[~known], points[known])
        colors[~known] = colors[known][idx[:, 0]]
    elif not known.any():
        colors[:] = 0.5
    return np.clip(colors, 0.0, 1.0).astype(np.float32), seen


def detail_mask(view, spacing: float) -> np.ndarray:
    """(S, S) bool: where the one-view ``view`` (the input photo's, a ``TrainingViews``) shows detail at
    the scale of ``spacing``: the luminance's standard deviation over a window of :data:`DETAIL_WINDOW`
    spacings (in that view's pixels at the subject's depth) above :data:`DETAIL_STD`, inside the person
    (the window whole inside its mask, so the silhouette's edge against the background does not count),
    then grown by :data:`DETAIL_GROW` spacings, so a face's skin between its eyes, brows and mouth counts
    too."""
    import cv2

    rgb = np.ascontiguousarray(view.images[0].cpu().numpy(), np.float32)
    alpha = view.alphas[0].cpu().numpy()
    w2c, K = view.w2c[0].cpu().numpy().astype(np.float64), view.K[0].cpu().numpy().astype(np.float64)
    depth = float(np.linalg.norm(w2c[:3, 3]))  # the camera's distance to the world origin (the subject)
    px = DETAIL_WINDOW * spacing * float(K[0, 0]) / max(depth, 1e-6)
    window = max(3, 2 * int(round(px / 2)) + 1)
    lum = rgb @ np.array([0.299, 0.587, 0.114], np.float32)
    mean = cv2.boxFilter(lum, -1, (window, window))
    std = np.sqrt(np.clip(cv2.boxFilter(lum * lum, -1, (window, window)) - mean * mean, 0.0, None))
    inside = cv2.erode((alpha > 0.5).astype(np.uint8), np.ones((window, window), np.uint8)).astype(bool)
    grow = np.ones((2 * int(round(DETAIL_GROW * px / DETAIL_WINDOW / 2)) + 1,) * 2, np.uint8)
    return cv2.dilate(((std > DETAIL_STD) & inside).astype(np.uint8), grow).astype(bool) & (alpha > 0.5)


def detail_points(points: np.ndarray, view, spacing: float) -> np.ndarray:
    """``points`` (dense, about ``detail_spacing`` x ``spacing`` apart) kept where the input view ``view``
    sees them on its :func:`detail_mask`, and thinned to ``spacing`` (:func:`poisson_disk`) elsewhere:
    Gaussians as fine as the photo's detail where it has some (a face, a print, a logo), the even
    spacing on plain cloth and on the unseen side."""
    mask = detail_mask(view, spacing)
    w2c, K = view.w2c[0].cpu().numpy().astype(np.float64), view.K[0].cpu().numpy().astype(np.float64)
    coverage = float((view.alphas > 0.5).float().mean())
    seen, uv = visibility(points, w2c, K, view.size, zbuffer_size(len(points), coverage, view.size))
    px = np.clip(np.floor(uv).astype(np.int64), 0, view.size - 1)
    fine = seen & mask[px[:, 1], px[:, 0]]
    coarse = points[~fine]
    return np.concatenate([points[fine], coarse[poisson_disk(coarse, DISK * spacing)]])


def start_anchor(anchor, views, template: str, spacing: float, proxy: Path | None, seed: int = 0,
                 detail_view=None, detail_spacing: float = 1.0):
    """(anchor, description) of the Gaussians' starting points: ``body``: the body anchor itself (UV texels);
    ``subject`` / ``auto``: points ``spacing`` apart on the clothed proxy ``proxy`` when that file exists,
    else on the visual hull of ``views`` merged with the body (:func:`subject_anchor`). With
    ``detail_view`` (the input photo's view) and ``detail_spacing`` < 1, the subject's points are
    ``detail_spacing`` x ``spacing`` apart where that view shows detail (:func:`detail_points`)."""
    if template == "body":
        return anchor, "body (UV texels)"
    if template not in ("subject", "auto"):
        raise ValueError(f"template must be auto, subject or body, got {template!r}")
    if not 0.0 < detail_spacing <= 1.0:
        raise ValueError(f"detail_spacing must be in (0, 1], got {detail_spacing}")
    fine = detail_view is not None and detail_spacing < 1.0
    step = spacing * detail_spacing if fine else spacing
    if proxy is not None and Path(proxy).is_file():
        points, what = proxy_points(proxy, step, seed), "subject (clothed proxy)"
    else:
        verts, _ = posed_body(anchor)
        points, what = visual_hull_points(views, verts, step, seed), "subject (visual hull + body)"
    if fine:
        points = detail_points(points, detail_view, spacing)
        what += f", {detail_spacing:g} x spacing where the photo shows detail"
    return subject_anchor(anchor, points), what


def init_colors(human, views) -> int:
    """Set ``human``'s colours in closed form (:func:`project_colors` at its posed centres) and prune the
    Gaussians no view sees (unless that would leave fewer than 16); returns how many were pruned."""
    with torch.no_grad():
        means = human().means.cpu().numpy().astype(np.float64)
    colors, seen = project_colors(means, views)
    human.set_colors(colors)
    if (seen > 0).sum() < 16:
        return 0
    return human.prune(torch.as_tensor(seen > 0))
