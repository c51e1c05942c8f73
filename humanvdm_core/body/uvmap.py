"""UV position maps: one surface sample per texel of a body model's UV layout (GaussianAvatar style).

For a resolution R, texel (row, col) has its centre at ``u = (col + 0.5) / R``,
``v = 1 - (row + 0.5) / R`` (OBJ convention, v up; row 0 is the top of the image, as texture images
are stored). A texel is *valid* when its centre lies in a UV triangle (closed, with a 1e-9
barycentric tolerance). Each valid texel belongs to exactly one triangle: on shared edges and
overlaps the triangle holding the centre most inside (largest smallest barycentric coordinate)
wins, ties going to the lower face id. Degenerate UV triangles own no texel.

The M valid texels are ordered row-major (by ``row * R + col``); sample m has ``face_ids[m]``,
``barycentrics[m]`` (three non-negative weights summing to 1 over the triangle's vertices
``faces[face_ids[m]]``), ``rows[m]``, ``cols[m]``. Because barycentrics interpolate the triangle's
3D vertices (not its UV corners), UV seams are handled: a texel on either side of a seam gives a
point on the same 3D surface.

Building is numpy-only and deterministic (the same layout and resolution give identical arrays).
:meth:`UVPositionMap.positions` and :meth:`UVPositionMap.interpolate` accept numpy arrays or torch
tensors (differentiable) with optional leading batch dimensions.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from humanvdm_core.io import read_npz, write_npz

UVMAP_SCHEMA = "humanvdm.uvmap"
UVMAP_VERSION = 1
_INSIDE_EPS = 1e-9
_CHUNK_PAIRS = 1 << 21  # candidate (texel, triangle) pairs processed at once


def rasterize_uv_triangles(
    uvs: np.ndarray, uv_faces: np.ndarray, resolution: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Assign texels to UV triangles.

    Args:
        uvs: (T, 2) texture coordinates, v up.
        uv_faces: (F, 3) indices into ``uvs``.
        resolution: R, the map is R x R.
    Returns:
        texel ids (M,) = ``row * R + col`` (sorted ascending), face ids (M,), barycentrics (M, 3)
        (float64, non-negative, summing to 1).
    """
    R = int(resolution)
    if R <= 0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    uvs = np.asarray(uvs, dtype=np.float64)
    uv_faces = np.asarray(uv_faces, dtype=np.int64)
    # Pixel coordinates in which texel (row, col) has its centre at (x, y) = (col, row).
    px = np.stack([uvs[:, 0] * R - 0.5, (1.0 - uvs[:, 1]) * R - 0.5], axis=1)
    tri = px[uv_faces]  # (F, 3, 2)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area2 = _cross(b - a, c - a)  # twice the signed area, in texels
    lo = np.ceil(tri.min(axis=1)).astype(np.int64)
    hi = np.floor(tri.max(axis=1)).astype(np.int64)
    lo = np.clip(lo, 0, R - 1)
    hi = np.clip(hi, -1, R - 1)
    nx = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0)
    ny = np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    counts = np.where(np.abs(area2) > 1e-12, nx * ny, 0)

    texels, faces, barys, scores = [], [], [], []
    face_order = np.flatnonzero(counts)
    start = 0
    while start < len(face_order):
        # a run of faces whose candidate texels fit in one chunk (at least one face)
        csum = np.cumsum(counts[face_order[start:]])
        stop = start + max(1, int(np.searchsorted(csum, _CHUNK_PAIRS, side="right")))
        f = face_order[start:stop]
        start = stop
        n = counts[f]
        fid = np.repeat(f, n)
        local = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        col = lo[fid, 0] + local % nx[fid]
        row = lo[fid, 1] + local // nx[fid]
        p = np.stack([col, row], axis=1).astype(np.float64)
        wb = _cross(p - a[fid], c[fid] - a[fid]) / area2[fid]
        wc = _cross(b[fid] - a[fid], p - a[fid]) / area2[fid]
        w = np.stack([1.0 - wb - wc, wb, wc], axis=1)
        score = w.min(axis=1)
        keep = score >= -_INSIDE_EPS
        texels.append(row[keep] * R + col[keep])
        faces.append(fid[keep])
        barys.append(w[keep])
        scores.append(score[keep])
    if not texels:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    texel = np.concatenate(texels)
    face = np.concatenate(faces)
    bary = np.concatenate(barys)
    score = np.concatenate(scores)
    # One triangle per texel: sort by texel, then most-inside first, then lowest face id.
    order = np.lexsort((face, -score, texel))
    texel, face, bary = texel[order], face[order], bary[order]
    first = np.ones(len(texel), dtype=bool)
    first[1:] = texel[1:] != texel[:-1]
    texel, face, bary = texel[first], face[first], bary[first]
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    return texel, face, bary


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


@dataclass(frozen=True)
class UVPositionMap:
    """Surface samples at the valid texels of a UV layout; see the module docstring."""

    resolution: int
    faces: np.ndarray  # (F, 3) int64 vertex indices of the mesh triangles
    face_ids: np.ndarray  # (M,) int64
    barycentrics: np.ndarray  # (M, 3) float64
    rows: np.ndarray  # (M,) int64
    cols: np.ndarray  # (M,) int64

    @classmethod
    def build(cls, faces, uvs, uv_faces, resolution: int) -> UVPositionMap:
        """From a mesh's vertex faces (F, 3), texture coordinates (T, 2) and UV faces (F, 3)."""
        faces = _numpy(faces).astype(np.int64)
        uv_faces = _numpy(uv_faces).astype(np.int64)
        if faces.shape != uv_faces.shape or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces {faces.shape} and uv_faces {uv_faces.shape} must both be (F, 3)")
        texel, face, bary = rasterize_uv_triangles(_numpy(uvs), uv_faces, resolution)
        R = int(resolution)
        return cls(R, faces, face, bary, texel // R, texel % R)

    @classmethod
    def from_model(cls, model, resolution: int) -> UVPositionMap:
        """For a :class:`~humanvdm_core.body.model.BodyModel` with a UV layout (a backend whose layout
        comes from a user file names that file when it is missing)."""
        if hasattr(model, "require_uv_layout"):
            model.require_uv_layout()
        if model.uvs is None or model.uv_faces is None:
            raise ValueError(f"body model {model.name} has no UV layout; use a topology with UVs")
        return cls.build(model.faces, model.uvs, model.uv_faces, resolution)

    @property
    def num_samples(self) -> int:
        """M, the number of valid texels (one Gaussian each in a GaussianAvatar-style model)."""
        return int(len(self.face_ids))

    @property
    def mask(self) -> np.ndarray:
        """(R, R) bool, True at valid texels."""
        m = np.zeros((self.resolution, self.resolution), dtype=bool)
        m[self.rows, self.cols] = True
        return m

    @property
    def vertex_ids(self) -> np.ndarray:
        """(M, 3) the vertices each sample interpolates."""
        return self.faces[self.face_ids]

    def interpolate(self, values):
        """Barycentric interpolation of per-vertex values (..., V, C) -> (..., M, C).

        numpy in, numpy out; torch in, torch out (differentiable, on the values' device)."""
        ids, bary = self.vertex_ids, self.barycentrics
        if isinstance(values, torch.Tensor):
            ids = torch.as_tensor(ids, device=values.device)
            bary = torch.as_tensor(bary, dtype=values.dtype, device=values.device)
        else:
            values = np.asarray(values)
            bary = bary.astype(values.dtype) if np.issubdtype(values.dtype, np.floating) else bary
        # one gather per triangle corner keeps the peak memory at a few (..., M, C) arrays
        return sum(values[..., ids[:, k], :] * bary[:, k, None] for k in range(3))

    def positions(self, vertices):
        """Surface points (..., M, 3) of a mesh posed as ``vertices`` (..., V, 3)."""
        return self.interpolate(vertices)

    def weights(self, skinning):
        """Skinning weights (M, J) interpolated from per-vertex weights (V, J); rows sum to 1."""
        return self.interpolate(skinning)

    def to_image(self, samples, fill: float = 0.0):
        """Scatter per-sample values (..., M, C) into (..., R, R, C) maps, ``fill`` elsewhere."""
        R = self.resolution
        if isinstance(samples, torch.Tensor):
            out = samples.new_full(samples.shape[:-2] + (R, R, samples.shape[-1]), fill)
            out[..., torch.as_tensor(self.rows), torch.as_tensor(self.cols), :] = samples
            return out
        samples = np.asarray(samples)
        out = np.full(samples.shape[:-2] + (R, R, samples.shape[-1]), fill, dtype=samples.dtype)
        out[..., self.rows, self.cols, :] = samples
        return out

    def save(self, path: str | Path) -> None:
        write_npz(path, {
            "resolution": np.int64(self.resolution), "faces": self.faces, "face_ids": self.face_ids,
            "barycentrics": self.barycentrics, "rows": self.rows, "cols": self.cols,
        }, UVMAP_SCHEMA, UVMAP_VERSION)

    @classmethod
    def load(cls, path: str | Path) -> UVPositionMap:
        d = read_npz(path, UVMAP_SCHEMA, UVMAP_VERSION)
        return cls(int(d["resolution"]), d["faces"], d["face_ids"], d["barycentrics"], d["rows"], d["cols"])


def _numpy(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)
