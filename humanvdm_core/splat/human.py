"""The skinned Gaussian human (paper section 3.3 + supplement; GaussianAvatar-style) and its fitting.

Model (:class:`GaussianHuman`):

- Gaussians start on a template (:class:`BodyAnchor`): the paper's one per valid texel of the fitted
  body's UV position map (resolution R), or points on the subject's own surface
  (:mod:`humanvdm_core.splat.template`: the clothed proxy or the visual hull). Each has a *canonical*
  anchor (da-pose, fitted shape), skinning weights (the body's, interpolated to the texel or copied
  from the nearest body vertex) and a base scale (its 3D spacing to its neighbours);
- per Gaussian an optimisable feature vector (C), concatenated with its normalised canonical position,
  goes through a small decoder (a per-Gaussian MLP, as 1x1 convolutions over a UV map) that predicts an
  offset (3, metres), a colour residual (3: colour = sigmoid(colour logit + residual), the logit set in
  closed form from the frames by :meth:`GaussianHuman.set_colors`) and a scale (1 isotropic or 3
  anisotropic; ``base * exp(out)``, ``out`` clamped to [log(min_scale), 3]: with ``min_scale`` 0.5
  neighbouring Gaussians keep overlapping, so the surface stays closed when viewed at a higher
  resolution than it was trained at);
- opacity: a learned per-Gaussian logit (``learn_opacity``), or fixed to 1 as the paper; the canonical
  rotation is the identity (as GaussianAvatar);
- canonical Gaussians ``x_c = anchor + offset`` are posed by linear blend skinning with the body's
  bone transforms at the refined pose (``pose + delta_pose``, ``transl + delta_transl``, both
  optimised jointly with the Gaussians), un-posed from the canonical transforms; each Gaussian is
  rotated by its blended bone rotation and scaled by the body's scale.

Fitting (:func:`fit_gaussians`): Adam (lr 3e-3) on batches of ``batch_views`` training views in a
seeded, fixed order (``input_view_share`` of the batches hold ``input_view``, the photo's own view,
optionally at a finer resolution than the others: ``photo``); loss ``0.8 L1 + 0.2 (1 - SSIM) [+ 0.2 LPIPS]
+ 10 |offset|^2 + 1 |scale|^2 + 1 |feature|^2`` (means over Gaussians / feature entries; offsets and scales in world units),
renders composited over the frame set's background colour. Coarse to fine: the first
``coarse_fraction`` of the steps train on half-resolution views. At each ``densify_at`` share of the
steps the set adapts to the scene (:func:`densify`): Gaussians whose learned opacity fell below
``prune_opacity`` are dropped and those whose render error (|colour| + |alpha| where they are visible)
exceeds ``split_residual`` are split in two, up to ``max_gaussians``. Deterministic for a seed on one
machine (single-threaded torch gives identical bytes).

Export: :func:`gaussians_arrays` (the ``humanvdm.gaussians`` v1 NPZ members, in our world: y up, the
subject facing +z, metres) and :func:`write_ply` / :func:`read_ply` (the standard 3DGS binary PLY:
``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3``; ``f_dc = (rgb - 0.5) / C0``, log
scales, logit opacity, unit wxyz quaternions), by default in the 3DGS/COLMAP axes (y down, z forward:
see :data:`PLY_AXES`), and :func:`write_splat` (the compact web ``.splat``).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from humanvdm_core import metrics
from humanvdm_core.body.model import BodyParams, blend_transforms
from humanvdm_core.workflow.errors import ConfigError, InputError

GAUSSIANS_SCHEMA = "humanvdm.gaussians"
GAUSSIANS_VERSION = 1
BODY_SCHEMA = "humanvdm.body_fit"
SH_C0 = 0.28209479177387814
INITIAL_SCALE = 0.6  # a Gaussian's starting scale as a fraction of its base spacing (crisp, still overlapping)
OPACITY_EPS = 1e-6  # opacity 1 is stored as logit(1 - eps) in the PLY

# preset -> settings; Gaussians on Anny's UV layout: R=64 -> 2,558, 128 -> 10,253, 569 -> 202,521 (paper: 202,738)
PRESETS: dict[str, dict[str, Any]] = {
    "tiny": {"uv_resolution": 64, "subject_spacing": 0.028, "train_resolution": 64, "iterations": 100, "tile_size": 4,
             "input_view_resolution": 0, "coarse_fraction": 0.0, "densify_at": (0.5,), "max_gaussians": 5000},
    "cpu": {"uv_resolution": 128, "subject_spacing": 0.016, "train_resolution": 192, "iterations": 500, "tile_size": 8,
            "input_view_resolution": 384, "coarse_fraction": 0.3, "densify_at": (0.3, 0.6), "max_gaussians": 30000},
    "full": {"uv_resolution": 569, "subject_spacing": 0.0045, "train_resolution": 1080, "iterations": 30000,
             "tile_size": 16, "input_view_resolution": 0, "coarse_fraction": 0.1, "densify_at": (0.1, 0.2, 0.3, 0.4, 0.5), "max_gaussians": 500000},
}


# ----------------------------------------------------------------------------- the body anchor

@dataclass
class BodyAnchor:
    """What the Gaussian human needs from a body fit: the UV samples on the canonical body, their
    skinning weights, the fitted params and the canonical bone transforms."""

    resolution: int
    rows: np.ndarray  # (M,) texel rows
    cols: np.ndarray  # (M,)
    positions: np.ndarray  # (M, 3) canonical surface points
    weights: np.ndarray  # (M, J) skinning weights
    params: BodyParams  # fitted params (batch 1)
    bone_transforms: np.ndarray  # (J, 4, 4) fitted (posed) bone transforms
    canonical_bone_transforms: np.ndarray  # (J, 4, 4)
    backend: str = "anny"
    topology: str = "anny"
    model: Any = None  # the body model (for pose refinement), or None
    spacing: np.ndarray | None = None  # (M,) base scale per point; None: the UV texel spacing
    body_vertices: np.ndarray | None = None  # (V, 3) the fitted body, posed (for the subject template)
    body_weights: np.ndarray | None = None  # (V, J) its skinning weights


def load_body_anchor(path: str | Path, uv_resolution: int | None = None, load_model: bool = True) -> BodyAnchor:
    """Read ``body.npz`` (schema ``humanvdm.body_fit`` v1). With ``uv_resolution`` different from the
    file's (or the file holding no UV map) the UV position map is rebuilt from the body model's UV
    layout on the file's canonical vertices. ``load_model`` builds the body model (needed for pose
    refinement and for rebuilding the UV map)."""
    from humanvdm_core.io import read_npz

    path = Path(path)
    if not path.is_file():
        raise InputError(f"body fit not found: {path}")
    try:
        d = read_npz(path, BODY_SCHEMA, 1)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    need = ("pose", "shape", "global_orient", "transl", "scale", "bone_transforms", "canonical_bone_transforms",
            "canonical_vertices", "skinning_weights")
    missing = [k for k in need if k not in d]
    if missing:
        raise InputError(f"{path} lacks {missing}: not a complete body fit")
    backend = str(d.get("backend", "anny"))
    topology = str(d.get("topology", "anny"))
    has_map = "uv_positions" in d and bool(d.get("has_uv_map", True))
    R = int(uv_resolution) if uv_resolution else (int(d["uv_resolution"]) if has_map else 0)
    model = None
    if load_model or not has_map or R != int(d.get("uv_resolution", -1)):
        if backend != "anny":
            raise InputError(f"{path}: body backend {backend!r}; the splat stage rebuilds/refines only Anny bodies")
        from humanvdm_core.body import load_body_model

        model = load_body_model("anny", topology=topology)
    if has_map and R == int(d["uv_resolution"]):
        rows, cols = d["uv_rows"].astype(np.int64), d["uv_cols"].astype(np.int64)
        positions, weights = d["uv_positions"].astype(np.float32), d["uv_weights"].astype(np.float32)
    else:
        if model is None or model.uvs is None:
            raise InputError(f"{path}: body topology {topology!r} has no UV layout (use topology 'anny')")
        if not 8 <= R <= 4096:
            raise ConfigError(f"uv_resolution must be in [8, 4096], got {R}")
        from humanvdm_core.body.uvmap import UVPositionMap

        uvm = UVPositionMap.from_model(model, R)
        rows, cols = uvm.rows.astype(np.int64), uvm.cols.astype(np.int64)
        positions = uvm.positions(d["canonical_vertices"].astype(np.float64)).astype(np.float32)
        weights = uvm.weights(d["skinning_weights"].astype(np.float64)).astype(np.float32)
    return BodyAnchor(
        resolution=R, rows=rows, cols=cols, positions=positions, weights=weights,
        params=BodyParams.from_numpy(d), bone_transforms=d["bone_transforms"].astype(np.float32),
        canonical_bone_transforms=d["canonical_bone_transforms"].astype(np.float32),
        backend=backend, topology=topology, model=model,
        body_vertices=d["vertices"].astype(np.float32) if "vertices" in d else None,
        body_weights=d["skinning_weights"].astype(np.float32))


def texel_spacing(rows: np.ndarray, cols: np.ndarray, positions: np.ndarray, resolution: int) -> np.ndarray:
    """(M,) mean 3D distance from each texel's point to its valid 4-neighbours in the UV grid (the
    median spacing where a texel has none)."""
    R = int(resolution)
    index = np.full(R * R, -1, dtype=np.int64)
    index[rows * R + cols] = np.arange(len(rows))
    total = np.zeros(len(rows))
    count = np.zeros(len(rows))
    for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        r2, c2 = rows + dr, cols + dc
        inside = (r2 >= 0) & (r2 < R) & (c2 >= 0) & (c2 < R)
        nb = np.full(len(rows), -1, dtype=np.int64)
        nb[inside] = index[r2[inside] * R + c2[inside]]
        ok = nb >= 0
        dist = np.linalg.norm(positions[nb[ok]] - positions[ok], axis=1)
        total[ok] += dist
        count[ok] += 1
    spacing = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    median = float(np.nanmedian(spacing)) if np.isfinite(spacing).any() else 0.01
    # UV seams make some neighbours far apart in 3D: cap at a few median spacings
    return np.clip(np.nan_to_num(spacing, nan=median), 0.25 * median, 3.0 * median).astype(np.float32)


# ----------------------------------------------------------------------------- rotations

def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) (near-)rotation matrices -> (..., 4) unit quaternions wxyz, w >= 0 (Shepperd's
    method: each quaternion is computed from its largest component; differentiable)."""
    m = R
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    sq = torch.stack([1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22,
                      1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], -1)  # 4 w^2, 4 x^2, 4 y^2, 4 z^2
    r = torch.sqrt(sq.clamp(min=1e-12))  # 2|w|, 2|x|, 2|y|, 2|z|
    cands = torch.stack([
        torch.stack([r[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1) / (2 * r[..., 0:1]),
        torch.stack([m21 - m12, r[..., 1] ** 2, m01 + m10, m02 + m20], -1) / (2 * r[..., 1:2]),
        torch.stack([m02 - m20, m01 + m10, r[..., 2] ** 2, m12 + m21], -1) / (2 * r[..., 2:3]),
        torch.stack([m10 - m01, m02 + m20, m12 + m21, r[..., 3] ** 2], -1) / (2 * r[..., 3:4]),
    ], -2)  # (..., 4 candidates, 4)
    best = sq.argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)
    return q / q.norm(dim=-1, keepdim=True)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) wxyz -> (..., 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


# ----------------------------------------------------------------------------- the model

@dataclass
class GaussianSet:
    """Posed Gaussians (world frame) and the decoder's raw outputs used by the regularisers."""

    means: torch.Tensor  # (M, 3)
    quats: torch.Tensor  # (M, 4) wxyz
    scales: torch.Tensor  # (M, 3) linear
    opacities: torch.Tensor  # (M,)
    colors: torch.Tensor  # (M, 3) sRGB in [0, 1]
    canonical_means: torch.Tensor  # (M, 3)
    offsets: torch.Tensor  # (M, 3)


class GaussianHuman(torch.nn.Module):
    """Body-skinned Gaussians with per-Gaussian features + an MLP decoder and a refinable body pose.

    Per Gaussian: a canonical anchor, skinning weights, a base scale, a feature vector, a colour logit
    (the decoder's colour output is added to it: :meth:`set_colors` initialises it in closed form) and,
    with ``learn_opacity``, an opacity logit (else the opacity is fixed to 1, as the paper).
    :meth:`prune` and :meth:`split` change the set; an optimiser must be rebuilt afterwards."""

    PER_GAUSSIAN_BUFFERS = ("rows", "cols", "anchors", "weights", "base_scale", "canonical_inverse")
    PER_GAUSSIAN_PARAMS = ("features", "color_logit", "opacity_logit")

    def __init__(self, anchor: BodyAnchor, feature_dim: int = 16, hidden: int = 64, layers: int = 3,
                 scale_mode: str = "isotropic", refine_pose: bool = True, seed: int = 0, min_scale: float = 0.5,
                 learn_opacity: bool = False, initial_opacity: float = 0.95):
        super().__init__()
        if scale_mode not in ("isotropic", "anisotropic"):
            raise ConfigError(f"scale_mode must be 'isotropic' or 'anisotropic', got {scale_mode!r}")
        if not 0.0 <= min_scale <= 1.0:
            raise ConfigError(f"min_scale must be in [0, 1] (a fraction of the texel spacing), got {min_scale}")
        if not 0.0 < initial_opacity < 1.0:
            raise ConfigError(f"initial_opacity must be in (0, 1), got {initial_opacity}")
        # the decoder's log-scale is kept in [log(min_scale), 3]: a Gaussian cannot shrink below
        # min_scale x its base spacing, so neighbours keep overlapping at any viewing resolution
        self.min_log_scale = math.log(min_scale) if min_scale > 0 else -6.0
        if refine_pose and anchor.model is None:
            raise ConfigError("pose refinement needs the body model (load_body_anchor(load_model=True))")
        self.scale_mode = scale_mode
        self.refine_pose = refine_pose
        self.learn_opacity = learn_opacity
        self.body_model = anchor.model if refine_pose else None
        self.resolution = int(anchor.resolution)  # the UV map's size (0: not on a UV map)
        gen = torch.Generator().manual_seed(int(seed))
        self._gen = gen
        self.register_buffer("rows", torch.as_tensor(anchor.rows, dtype=torch.int64))
        self.register_buffer("cols", torch.as_tensor(anchor.cols, dtype=torch.int64))
        self.register_buffer("anchors", torch.as_tensor(anchor.positions, dtype=torch.float32))
        self.register_buffer("weights", torch.as_tensor(anchor.weights, dtype=torch.float32))
        spacing = anchor.spacing if anchor.spacing is not None else texel_spacing(
            anchor.rows, anchor.cols, anchor.positions, anchor.resolution)
        self.register_buffer("base_scale", torch.as_tensor(np.asarray(spacing, np.float32))[:, None])
        # per-Gaussian inverse of the blended canonical transform (constant)
        canon = torch.as_tensor(anchor.canonical_bone_transforms, dtype=torch.float32)
        self.register_buffer("canonical_bones", canon)
        self.register_buffer("canonical_inverse", torch.linalg.inv(blend_transforms(self.weights, canon[None])[0]))
        self.register_buffer("fitted_transforms", torch.as_tensor(anchor.bone_transforms, dtype=torch.float32))
        self.params0 = anchor.params.to(dtype=torch.float32)
        # normalised canonical positions as decoder input (centred, unit-ish range; fixed at construction)
        centre = self.anchors.mean(0)
        extent = float((self.anchors - centre).abs().max())
        self.register_buffer("position_centre", centre)
        self.position_extent = max(extent, 1e-6)
        m = self.anchors.shape[0]
        self.features = torch.nn.Parameter(torch.randn(m, feature_dim, generator=gen) * 0.01)
        self.color_logit = torch.nn.Parameter(torch.zeros(m, 3))
        logit = math.log(initial_opacity / (1.0 - initial_opacity))
        self.opacity_logit = torch.nn.Parameter(torch.full((m,), logit), requires_grad=learn_opacity)
        n_out = 3 + 3 + (1 if scale_mode == "isotropic" else 3)
        dims = [feature_dim + 3] + [hidden] * (layers - 1) + [n_out]
        mlp: list[torch.nn.Module] = []
        for i in range(len(dims) - 1):
            lin = torch.nn.Linear(dims[i], dims[i + 1])
            bound = 1.0 / math.sqrt(dims[i])
            with torch.no_grad():
                lin.weight.uniform_(-bound, bound, generator=gen)
                lin.bias.zero_()
            mlp.append(lin)
            if i < len(dims) - 2:
                mlp.append(torch.nn.ReLU())
        self.decoder = torch.nn.Sequential(*mlp)
        with torch.no_grad():  # start small: offsets ~0, colour = the colour logit's, scale ~ INITIAL_SCALE x spacing
            self.decoder[-1].weight.mul_(0.1)
            self.decoder[-1].bias[6:] = math.log(max(INITIAL_SCALE, min_scale))
        n_pose = int(anchor.params.pose.shape[1])
        self.delta_pose = torch.nn.Parameter(torch.zeros(n_pose, 3))
        self.delta_transl = torch.nn.Parameter(torch.zeros(3))
        if not refine_pose:
            self.delta_pose.requires_grad_(False)
            self.delta_transl.requires_grad_(False)

    @property
    def num_gaussians(self) -> int:
        return int(self.anchors.shape[0])

    @property
    def position_input(self) -> torch.Tensor:
        """(M, 3) the decoder's position input: canonical anchors centred and scaled."""
        return (self.anchors - self.position_centre) / self.position_extent

    def bone_transforms(self) -> torch.Tensor:
        """(J, 4, 4) bone transforms at the refined pose."""
        if not self.refine_pose:
            return self.fitted_transforms
        p = self.params0.to(device=self.delta_pose.device)
        params = BodyParams(pose=p.pose + self.delta_pose[None], shape=p.shape, global_orient=p.global_orient,
                            transl=p.transl + self.delta_transl[None], scale=p.scale)
        return self.body_model(params).bone_transforms[0]

    def forward(self) -> GaussianSet:
        out = self.decoder(torch.cat([self.features, self.position_input], dim=1))
        offsets = out[:, 0:3]
        colors = torch.sigmoid(self.color_logit + out[:, 3:6])
        log_scale = out[:, 6:].clamp(self.min_log_scale, 3.0)
        canonical = self.anchors + offsets
        A = blend_transforms(self.weights, self.bone_transforms()[None])[0] @ self.canonical_inverse  # (M, 4, 4)
        means = (A[:, :3, :3] @ canonical[:, :, None])[:, :, 0] + A[:, :3, 3]
        linear = A[:, :3, :3]
        body_scale = torch.linalg.det(linear).clamp(min=1e-12) ** (1.0 / 3.0)
        scales = (self.base_scale * torch.exp(log_scale) * body_scale[:, None]).expand(-1, 3)
        if self.scale_mode == "isotropic":
            quats = torch.zeros(self.num_gaussians, 4, dtype=means.dtype, device=means.device)
            quats[:, 0] = 1.0  # rotation is irrelevant for isotropic Gaussians
        else:
            quats = matrix_to_quat(linear / body_scale[:, None, None])
        if self.learn_opacity:
            opacities = torch.sigmoid(self.opacity_logit)
        else:
            opacities = torch.ones(self.num_gaussians, dtype=means.dtype, device=means.device)
        return GaussianSet(means=means, quats=quats, scales=scales.contiguous(), opacities=opacities,
                           colors=colors, canonical_means=canonical, offsets=offsets)

    def set_colors(self, colors: np.ndarray | torch.Tensor) -> None:
        """Initialise the colour logits so that, with the decoder's colour output near 0, the Gaussians
        show ``colors`` (M, 3) in [0, 1]."""
        c = torch.as_tensor(colors, dtype=torch.float32, device=self.anchors.device).clamp(0.02, 0.98)
        with torch.no_grad():
            self.color_logit.copy_(torch.log(c / (1.0 - c)))

    def _reindex(self, index: torch.Tensor) -> None:
        """Keep (and repeat) the Gaussians at ``index``: every per-Gaussian buffer and parameter."""
        index = index.to(self.anchors.device)
        for name in self.PER_GAUSSIAN_BUFFERS:
            setattr(self, name, getattr(self, name)[index].clone())
        for name in self.PER_GAUSSIAN_PARAMS:
            old = getattr(self, name)
            setattr(self, name, torch.nn.Parameter(old.detach()[index].clone(), requires_grad=old.requires_grad))

    def prune(self, keep: torch.Tensor) -> int:
        """Drop the Gaussians where ``keep`` (M,) is False; returns how many were dropped."""
        keep = keep.to(self.anchors.device)
        dropped = int((~keep).sum())
        if dropped:
            self._reindex(torch.nonzero(keep)[:, 0])
        return dropped

    def split(self, selected: torch.Tensor, shrink: float = 0.7) -> int:
        """Replace each selected Gaussian (``selected`` (M,) bool) by two, half a base spacing either side
        of it along a seeded random direction, their base scales ``shrink`` times its; returns how many
        were added."""
        idx = torch.nonzero(selected.to(self.anchors.device))[:, 0]
        if len(idx) == 0:
            return 0
        n = self.num_gaussians
        self._reindex(torch.cat([torch.arange(n, device=idx.device), idx]))
        direction = torch.randn(len(idx), 3, generator=self._gen).to(self.anchors.device)
        direction = direction / direction.norm(dim=1, keepdim=True).clamp_min(1e-9)
        step = 0.5 * self.base_scale[idx] * direction
        children = torch.arange(n, n + len(idx), device=idx.device)
        with torch.no_grad():
            self.anchors[idx] += step
            self.anchors[children] -= step
            self.base_scale[idx] *= shrink
            self.base_scale[children] *= shrink
        return int(len(idx))


# ----------------------------------------------------------------------------- image losses

def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of (B, C, H, W) images in [0, 1] (:func:`humanvdm_core.metrics.ssim`)."""
    return metrics.ssim(a.permute(0, 2, 3, 1), b.permute(0, 2, 3, 1)).mean()


def psnr(a: np.ndarray | torch.Tensor, b: np.ndarray | torch.Tensor) -> float:
    """PSNR in dB over all pixels of all the images given (one number for a batch)."""
    mse = float(((torch.as_tensor(a, dtype=torch.float64) - torch.as_tensor(b, dtype=torch.float64)) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def load_lpips_loss(path: str) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """The LPIPS (AlexNet) loss from local weight files (:func:`humanvdm_core.metrics.load_lpips`).
    Raises MissingWeightsError when the file is missing."""
    from humanvdm_core.errors import require_weights

    weights = require_weights(path, "LPIPS (AlexNet) weights for the splat loss",
                              "the LPIPS project's released weights (see README: model weights)")
    net = metrics.load_lpips(weights)
    for prm in net.parameters():
        prm.requires_grad_(False)

    def lpips_loss(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:  # (B, 3, H, W) in [0, 1]
        return net.to(x.device)(x * 2 - 1, y * 2 - 1).mean()

    return lpips_loss


# ----------------------------------------------------------------------------- rendering

def render(gs: GaussianSet, w2c: torch.Tensor, K: torch.Tensor, width: int, height: int,
           background: torch.Tensor, tile_size: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """Render posed Gaussians into C views -> colours (C, H, W, 3) over ``background`` and alphas (C, H, W)
    (:func:`humanvdm_core.splat.rasterize.rasterize_gaussians`, backend "auto": gsplat on CUDA)."""
    from humanvdm_core.splat.rasterize import rasterize_gaussians

    C = w2c.shape[0]
    colors, alphas, _ = rasterize_gaussians(
        gs.means, gs.quats, gs.scales, gs.opacities, gs.colors, w2c, K, width, height,
        backgrounds=background.expand(C, 3), tile_size=tile_size)
    return colors, alphas[..., 0]


# ----------------------------------------------------------------------------- training data

@dataclass
class TrainingViews:
    """Frames resampled to the training resolution, with matching cameras (torch, float32)."""

    images: torch.Tensor  # (N, S, S, 3) sRGB
    alphas: torch.Tensor  # (N, S, S)
    w2c: torch.Tensor  # (N, 4, 4)
    K: torch.Tensor  # (N, 3, 3)
    size: int
    background: torch.Tensor  # (3,)

    def to(self, device: torch.device | str) -> TrainingViews:
        return TrainingViews(self.images.to(device), self.alphas.to(device), self.w2c.to(device), self.K.to(device),
                             self.size, self.background.to(device))

    def subset(self, index: list[int]) -> TrainingViews:
        ids = torch.as_tensor(index, dtype=torch.int64)
        return TrainingViews(self.images[ids], self.alphas[ids], self.w2c[ids], self.K[ids], self.size,
                             self.background)


def background_of(cameras, frames: np.ndarray) -> np.ndarray:
    """The frame set's background colour: ``cameras.extra['background']`` when present, else the mean
    colour of (nearly) uncovered pixels, else white."""
    if "background" in cameras.extra:
        return np.asarray(cameras.extra["background"], dtype=np.float32).reshape(3)
    empty = frames[..., 3] < 0.01
    if empty.any():
        return frames[..., :3][empty].mean(0).astype(np.float32)
    return np.ones(3, dtype=np.float32)


def resample(frame: np.ndarray, size: int) -> np.ndarray:
    """A square (H, H, C) frame resampled to ``size``² (area filter down, bilinear up)."""
    import cv2

    if frame.shape[0] == size and frame.shape[1] == size:
        return frame
    interp = cv2.INTER_AREA if size < frame.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(frame, (size, size), interpolation=interp)


def load_views(root: str | Path, size: int, indices: list[int] | None = None) -> TrainingViews:
    """Read a frame set (one frame at a time, progress reported) at ``size``² with matching cameras."""
    from humanvdm_core.frames import open_frame_set, read_frame
    from humanvdm_core.workflow.progress import report

    paths, cameras = open_frame_set(root)
    if cameras.width != cameras.height:
        raise InputError(f"frames must be square, got {cameras.width}x{cameras.height}")
    idx = list(range(len(paths))) if indices is None else list(indices)
    frames = []
    for k, i in enumerate(idx):
        f = read_frame(paths[i])
        if f.shape[2] < 4:
            raise InputError(f"{paths[i]}: frames must be RGBA")
        frames.append(resample(f[..., :4].astype(np.float32), size))
        report(k + 1, len(idx), "frames", "read the training views")
    return prepare_views(np.stack(frames), cameras.subset(idx), size)


def load_input_view(root: str | Path, views: TrainingViews, size: int,
                    ) -> tuple[int, TrainingViews | None, TrainingViews | None]:
    """The input photo's view of the frame set ``root`` whose training views are ``views``:
    ``(index, photo, finest)``: its index (:func:`input_view_index`, -1 when no frame lies at azimuth 0);
    ``photo``, that frame at ``size``² (at most the frames' own) when that is finer than ``views``, else
    None; ``finest``, the finest copy of it there is (``photo``, else its training view; None without one)."""
    from humanvdm_core.frames import read_cameras

    cameras = read_cameras(root)
    index = input_view_index(cameras.azimuth_deg)
    if index < 0:
        return index, None, None
    size = min(size, cameras.width)
    photo = load_views(root, size, [index]) if size > views.size else None
    return index, photo, photo if photo is not None else views.subset([index])


def prepare_views(frames: np.ndarray, cameras, size: int) -> TrainingViews:
    """Resample (N, H, W, 4) frames to ``size``² (area filter) and scale the cameras to match."""
    n, h, w = frames.shape[:3]
    if h != w:
        raise InputError(f"frames must be square, got {w}x{h}")
    frames = np.stack([resample(f, size) for f in frames])
    bg = background_of(cameras, frames)
    cams = cameras.scaled(size, size)
    return TrainingViews(
        images=torch.as_tensor(np.clip(frames[..., :3], 0, 1), dtype=torch.float32),
        alphas=torch.as_tensor(np.clip(frames[..., 3], 0, 1), dtype=torch.float32),
        w2c=torch.as_tensor(cams.w2c, dtype=torch.float32), K=torch.as_tensor(cams.K, dtype=torch.float32),
        size=size, background=torch.as_tensor(bg, dtype=torch.float32))


# ----------------------------------------------------------------------------- fitting

@dataclass
class FitConfig:
    """Fitting hyper-parameters (the paper's loss weights as defaults)."""

    iterations: int = 100
    lr: float = 3e-3
    pose_lr: float = 3e-4
    batch_views: int = 2
    l1_weight: float = 0.8
    ssim_weight: float = 0.2
    lpips_weight: float = 0.2
    lpips_weights: str = ""
    offset_weight: float = 10.0
    scale_weight: float = 1.0
    feature_weight: float = 1.0
    mask_weight: float = 0.0
    seed: int = 0
    tile_size: int = 16
    log_every: int = 25
    coarse_fraction: float = 0.0  # the first share of the iterations trains on half-resolution views
    densify_at: tuple[float, ...] = ()  # shares of the iterations after which to prune and split
    prune_opacity: float = 0.05  # Gaussians below this opacity are pruned (learned opacity only)
    split_residual: float = 0.1  # mean |render - frame| (colour + alpha) above which a Gaussian is split
    max_gaussians: int = 0  # cap on the count after splitting (0: none)
    densify_views: int = 8  # evenly spaced views whose residuals decide the splits
    input_view: int = -1  # index of the input photo's view among the training views (-1: none)
    input_view_share: float = 0.0  # share of the batches that hold the input view (0: uniform, as the paper)

    def check(self) -> None:
        if self.iterations < 0:
            raise ConfigError(f"iterations must be >= 0, got {self.iterations}")
        if not 0.0 <= self.coarse_fraction < 1.0:
            raise ConfigError(f"coarse_fraction must be in [0, 1), got {self.coarse_fraction}")
        if any(not 0.0 < f < 1.0 for f in self.densify_at):
            raise ConfigError(f"densify_at must hold shares in (0, 1), got {self.densify_at}")
        if self.batch_views < 1:
            raise ConfigError(f"batch_views must be >= 1, got {self.batch_views}")
        if self.lr <= 0 or self.pose_lr < 0:
            raise ConfigError("lr must be > 0 and pose_lr >= 0")
        if not 0.0 <= self.input_view_share <= 1.0:
            raise ConfigError(f"input_view_share must be in [0, 1], got {self.input_view_share}")


@dataclass
class FitResult:
    losses: list[float] = field(default_factory=list)  # every logged iteration's total loss
    logged_iterations: list[int] = field(default_factory=list)
    wall_s: float = 0.0
    train_psnr: float = float("nan")
    config: dict = field(default_factory=dict)
    counts: list[dict] = field(default_factory=list)  # per densify step: iteration, pruned, split, count


def view_order(n_views: int, iterations: int, batch: int, seed: int, input_view: int = -1,
               input_view_share: float = 0.0) -> list[list[int]]:
    """Per-iteration view batches: seeded permutations of all views, consumed ``batch`` at a time. With
    ``input_view`` >= 0, an evenly spread ``input_view_share`` of the batches start with that view
    (the photo itself: the one view that is not generated)."""
    gen = torch.Generator().manual_seed(int(seed) + 1)
    order: list[int] = []
    need = iterations * batch
    while len(order) < need:
        order += torch.randperm(n_views, generator=gen).tolist()
    batches = [order[i * batch:(i + 1) * batch] for i in range(iterations)]
    if 0 <= input_view < n_views and input_view_share > 0:
        for i, b in enumerate(batches):
            if math.floor((i + 1) * input_view_share) > math.floor(i * input_view_share) and input_view not in b:
                b[0] = input_view
    return batches


def input_view_index(azimuth_deg: np.ndarray, tolerance_deg: float = 1.0) -> int:
    """The training view of the input photo: the orbit's frame at azimuth 0 (DESIGN.md: its last), or
    -1 when no frame lies within ``tolerance_deg`` of it."""
    az = np.asarray(azimuth_deg, dtype=np.float64) % 360.0
    off = np.minimum(az, 360.0 - az)
    i = int(np.argmin(off)) if len(off) else -1
    return i if i >= 0 and off[i] <= tolerance_deg else -1


def image_loss(gs: GaussianSet, views: TrainingViews, ids: list[int], config: FitConfig,
               lpips: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """The photometric loss of the posed Gaussians ``gs`` against the views ``ids``: ``l1_weight`` L1 +
    ``ssim_weight`` (1 - SSIM) [+ ``lpips_weight`` LPIPS] [+ ``mask_weight`` alpha L1]."""
    S = views.size
    idx = torch.as_tensor(ids, dtype=torch.int64)
    pred, alpha = render(gs, views.w2c[idx], views.K[idx], S, S, views.background, config.tile_size)
    target = views.images[idx]
    p_nchw, t_nchw = pred.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
    loss = config.l1_weight * (pred - target).abs().mean()
    loss = loss + config.ssim_weight * (1.0 - ssim(p_nchw, t_nchw))
    if lpips is not None and config.lpips_weight > 0:
        loss = loss + config.lpips_weight * lpips(p_nchw, t_nchw)
    if config.mask_weight > 0:
        loss = loss + config.mask_weight * (alpha - views.alphas[idx]).abs().mean()
    return loss


def training_loss(human: GaussianHuman, views: TrainingViews, ids: Sequence[int], config: FitConfig,
                  lpips: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
                  photo: TrainingViews | None = None) -> torch.Tensor:
    """The loss of one batch of views ``ids`` (see the module docstring). With ``photo`` (the input view
    ``config.input_view`` alone, at a finer resolution) a batch holding the input view scores it there;
    each view of the batch weighs the same."""
    gs = human()
    ids = [int(i) for i in ids]
    if photo is not None and config.input_view in ids:
        rest = [i for i in ids if i != config.input_view]
        loss = image_loss(gs, photo, [0], config, lpips)
        if rest:
            loss = (loss + len(rest) * image_loss(gs, views, rest, config, lpips)) / len(ids)
    else:
        loss = image_loss(gs, views, ids, config, lpips)
    loss = loss + config.offset_weight * (gs.offsets ** 2).sum(1).mean()
    loss = loss + config.scale_weight * (gs.scales ** 2).sum(1).mean()
    return loss + config.feature_weight * (human.features ** 2).mean()


def half_views(views: TrainingViews) -> TrainingViews:
    """``views`` at half resolution (2x2 box filter; intrinsics halved, so pixel centres stay aligned)."""
    import torch.nn.functional as F

    if views.size % 2:
        return views
    K = views.K.clone()
    K[:, :2, :] *= 0.5
    return TrainingViews(F.avg_pool2d(views.images.permute(0, 3, 1, 2), 2).permute(0, 2, 3, 1).contiguous(),
                         F.avg_pool2d(views.alphas[:, None], 2)[:, 0], views.w2c, K, views.size // 2, views.background)


def make_optimizer(human: GaussianHuman, config: FitConfig) -> torch.optim.Optimizer:
    """Adam over the per-Gaussian parameters and the decoder (``lr``) and the pose refinement (``pose_lr``)."""
    params = [human.features, human.color_logit, *human.decoder.parameters()]
    if human.learn_opacity:
        params.append(human.opacity_logit)
    groups = [{"params": params, "lr": config.lr}]
    if human.refine_pose and config.pose_lr > 0:
        groups.append({"params": [human.delta_pose, human.delta_transl], "lr": config.pose_lr})
    return torch.optim.Adam(groups)


def gaussian_residuals(human: GaussianHuman, views: TrainingViews, ids: list[int], tile_size: int) -> torch.Tensor:
    """(M,) each Gaussian's mean render error over the views ``ids`` where it is visible: |colour| (mean
    over channels) + |alpha| at the pixel its centre projects to; 0 where no view sees it."""
    from humanvdm_core.splat.template import visibility, zbuffer_size

    S = views.size
    zsize = zbuffer_size(human.num_gaussians, float(views.alphas[ids].mean()), S)
    with torch.no_grad():
        gs = human()
        means = gs.means.cpu().numpy().astype(np.float64)
        total = np.zeros(len(means))
        count = np.zeros(len(means))
        for i in ids:
            pred, alpha = render(gs, views.w2c[i:i + 1], views.K[i:i + 1], S, S, views.background, tile_size)
            err = ((pred[0] - views.images[i]).abs().mean(-1) + (alpha[0] - views.alphas[i]).abs()).cpu().numpy()
            vis, uv = visibility(means, views.w2c[i].cpu().numpy().astype(np.float64),
                                 views.K[i].cpu().numpy().astype(np.float64), S, zsize)
            px = np.clip(np.floor(uv[vis]).astype(np.int64), 0, S - 1)
            total[vis] += err[px[:, 1], px[:, 0]]
            count[vis] += 1
    return torch.as_tensor(total / np.maximum(count, 1), dtype=torch.float32)


def densify(human: GaussianHuman, views: TrainingViews, config: FitConfig,
            photo: TrainingViews | None = None) -> dict:
    """Prune transparent Gaussians (learned opacity below ``prune_opacity``) and split those whose render
    error exceeds ``split_residual`` (worst first, up to ``max_gaussians``); returns the counts. A
    Gaussian's error is its mean over ``densify_views`` evenly spaced views, or its error in ``photo``
    (the input view at a finer resolution) where that is larger."""
    pruned = 0
    if human.learn_opacity:
        with torch.no_grad():
            keep = torch.sigmoid(human.opacity_logit) >= config.prune_opacity
        if keep.sum() >= 16:
            pruned = human.prune(keep)
    n_views = len(views.images)
    ids = sorted({int(round(i * n_views / config.densify_views)) % n_views for i in range(config.densify_views)})
    residual = gaussian_residuals(human, views, ids, config.tile_size).to(human.anchors.device)
    if photo is not None:
        residual = torch.maximum(residual, gaussian_residuals(human, photo, [0], config.tile_size).to(residual.device))
    selected = residual > config.split_residual
    if config.max_gaussians > 0:
        room = max(0, config.max_gaussians - human.num_gaussians)
        if int(selected.sum()) > room:
            order = torch.argsort(residual, descending=True)
            selected = torch.zeros_like(selected)
            selected[order[:room]] = True
    split = human.split(selected)
    return {"pruned": pruned, "split": split, "count": human.num_gaussians}


def fit_gaussians(human: GaussianHuman, views: TrainingViews, config: FitConfig,
                  log: Callable[[str], None] | None = None, photo: TrainingViews | None = None) -> FitResult:
    """Optimise ``human`` (in place) against ``views``; returns the loss curve, the counts after each
    densify step and timings. The first ``coarse_fraction`` of the iterations train on half-resolution
    views; after each share in ``densify_at`` the set is pruned and split (:func:`densify`) and the
    optimiser restarts. ``photo``: the input view (``config.input_view``) alone at a finer resolution than
    ``views``, where batches holding it train it and densifying looks for detail (the photo is the one
    view that is not generated). Progress goes to the stage's progress channel (:func:`humanvdm_core.workflow.progress.report`)."""
    from humanvdm_core.workflow.progress import report

    config.check()
    torch.manual_seed(config.seed)
    views = views.to(human.anchors.device)
    coarse = half_views(views) if config.coarse_fraction > 0 else views
    if photo is not None:
        if not 0 <= config.input_view < len(views.images):
            raise ConfigError("a finer input view needs config.input_view")
        photo = photo.to(human.anchors.device)
    coarse_photo = half_views(photo) if photo is not None and config.coarse_fraction > 0 else photo
    coarse_until = int(round(config.coarse_fraction * config.iterations))
    densify_its = {int(round(f * config.iterations)) for f in config.densify_at}
    lpips = load_lpips_loss(config.lpips_weights) if config.lpips_weights else None
    opt = make_optimizer(human, config)
    result = FitResult(config=asdict(config))
    batches = view_order(len(views.images), config.iterations, min(config.batch_views, len(views.images)),
                         config.seed, config.input_view, config.input_view_share)
    t0 = time.perf_counter()
    S, ts = views.size, config.tile_size
    for it, idx in enumerate(batches):
        if it in densify_its and it > 0:
            counts = {"iteration": it, **densify(human, views, config, photo)}
            result.counts.append(counts)
            opt = make_optimizer(human, config)
            if log is not None:
                log(f"iter {it:5d}: pruned {counts['pruned']}, split {counts['split']} -> {counts['count']} Gaussians")
        fine = it >= coarse_until
        loss = training_loss(human, views if fine else coarse, idx, config, lpips, photo if fine else coarse_photo)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        report(it + 1, len(batches), "it", "optimise Gaussians")
        if it % config.log_every == 0 or it == len(batches) - 1:
            result.losses.append(float(loss.detach()))
            result.logged_iterations.append(it)
            if log is not None:
                log(f"iter {it:5d}/{len(batches)}  loss {result.losses[-1]:.4f}  {time.perf_counter() - t0:.1f} s")
    result.wall_s = time.perf_counter() - t0
    with torch.no_grad():  # training PSNR on up to 16 evenly spaced views
        gs = human()
        scores = []
        n = len(views.images)
        ids = sorted({int(i * n / min(n, 16)) for i in range(min(n, 16))})
        for k, i in enumerate(ids):
            pred, _ = render(gs, views.w2c[i:i + 1], views.K[i:i + 1], S, S, views.background, ts)
            scores.append(psnr(pred[0], views.images[i]))
            report(k + 1, len(ids), "views", "training PSNR")
    result.train_psnr = float(np.mean(scores)) if scores else float("nan")
    return result


# ----------------------------------------------------------------------------- export

def gaussians_arrays(human: GaussianHuman, background: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The ``humanvdm.gaussians`` v1 members: posed ``means`` (M, 3), ``quats`` (M, 4) wxyz unit,
    ``scales`` (M, 3) linear, ``opacities`` (M,), ``colors`` (M, 3) sRGB in [0, 1],
    ``canonical_means`` (M, 3), ``skinning_weights`` (M, J), ``uv_rows``/``uv_cols`` (M,),
    ``uv_resolution``, the refined ``pose`` (1, P, 3) / ``transl`` (1, 3), ``bone_transforms`` (J, 4, 4),
    ``background`` (3,) when known."""
    with torch.no_grad():
        gs = human()
        bones = human.bone_transforms()
    f32 = np.float32
    p = human.params0
    gs = GaussianSet(**{k: v.detach().cpu() for k, v in vars(gs).items()})
    bones = bones.cpu()
    out = {
        "means": gs.means.numpy().astype(f32), "quats": gs.quats.numpy().astype(f32),
        "scales": gs.scales.numpy().astype(f32), "opacities": gs.opacities.numpy().astype(f32),
        "colors": gs.colors.clamp(0, 1).numpy().astype(f32), "canonical_means": gs.canonical_means.numpy().astype(f32),
        "skinning_weights": human.weights.cpu().numpy().astype(f32),
        "uv_rows": human.rows.cpu().numpy(), "uv_cols": human.cols.cpu().numpy(),
        "uv_resolution": np.int64(human.resolution),
        "pose": (p.pose + human.delta_pose.detach().cpu()[None]).numpy().astype(f32),
        "transl": (p.transl + human.delta_transl.detach().cpu()[None]).numpy().astype(f32),
        "bone_transforms": bones.numpy().astype(f32),
    }
    if background is not None:
        out["background"] = np.asarray(background, dtype=f32).reshape(3)
    return out


PLY_PROPERTIES: tuple[str, ...] = (
    ("x", "y", "z", "nx", "ny", "nz") + tuple(f"f_dc_{i}" for i in range(3)) + tuple(f"f_rest_{i}" for i in range(45))
    + ("opacity",) + tuple(f"scale_{i}" for i in range(3)) + tuple(f"rot_{i}" for i in range(4)))

# Axes of the exported files. Our own world (the NPZ, the cameras): x right, y up, the subject facing +z.
# "y-down" (the default) is the 3DGS/COLMAP convention that splat viewers built for captures assume
# (SuperSplat turns such files 180 degrees about z on load): x right, y down, z forward, so a camera at
# the identity rotation behind -z sees the subject upright and from the front. It is our world rotated
# 180 degrees about x: (x, y, z) -> (x, -y, -z), rotations q -> (0, 1, 0, 0) * q. "y-up" keeps our axes
# (what gaussian-splats-3d shows upright with its default camera up, +y).
PLY_AXES = ("y-down", "y-up")
DEFAULT_PLY_AXES = "y-down"
PLY_AXES_COMMENT = {
    "y-down": "axes y-down: x right, y down, z forward (3DGS/COLMAP convention; the subject faces -z)",
    "y-up": "axes y-up: x right, y up, z toward the viewer (OpenGL convention; the subject faces +z)",
}


def to_axes(means: np.ndarray, quats: np.ndarray, axes: str, inverse: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Our world's ``means`` (M, 3) and wxyz ``quats`` (M, 4) in ``axes``; ``inverse``: from ``axes`` to ours."""
    if axes not in PLY_AXES:
        raise ConfigError(f"axes {axes!r}: choose from {list(PLY_AXES)}")
    means, quats = np.asarray(means), np.asarray(quats)
    if axes == "y-up":
        return means, quats
    m = means * np.array([1.0, -1.0, -1.0], dtype=means.dtype)
    w, x, y, z = (quats[:, i] for i in range(4))
    if inverse:  # (0, -1, 0, 0) * q
        return m, np.stack([x, -w, z, -y], axis=1)
    return m, np.stack([-x, w, -z, y], axis=1)  # (0, 1, 0, 0) * q: 180 degrees about x, then q


def write_ply(path: str | Path, means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
              colors: np.ndarray, axes: str = DEFAULT_PLY_AXES) -> None:
    """Write the standard 3DGS binary little-endian PLY (degree-0 colour, zero normals and f_rest) from our
    world's arrays, in ``axes`` (:data:`PLY_AXES`; stated in a header comment). Units: our world's (metres)."""
    from humanvdm_core.workflow.atomic import atomic_write_bytes

    means, quats = to_axes(np.asarray(means, dtype=np.float64), np.asarray(quats, dtype=np.float64), axes)
    n = len(means)
    data = np.zeros(n, dtype=[(name, "<f4") for name in PLY_PROPERTIES])
    for i, axis in enumerate("xyz"):
        data[axis] = means[:, i]
    dc = (np.asarray(colors, dtype=np.float64) - 0.5) / SH_C0
    for i in range(3):
        data[f"f_dc_{i}"] = dc[:, i]
    op = np.clip(np.asarray(opacities, dtype=np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    data["opacity"] = np.log(op / (1.0 - op))
    log_s = np.log(np.maximum(np.asarray(scales, dtype=np.float64), 1e-12))
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    for i in range(3):
        data[f"scale_{i}"] = log_s[:, i]
    for i in range(4):
        data[f"rot_{i}"] = q[:, i]
    header = ("ply\nformat binary_little_endian 1.0\ncomment Human-VDM splat-optimize\n"
              f"comment {PLY_AXES_COMMENT[axes]}\ncomment units: metres\n"
              f"element vertex {n}\n" + "".join(f"property float {name}\n" for name in PLY_PROPERTIES) + "end_header\n")
    atomic_write_bytes(path, header.encode("ascii") + data.tobytes())


def ply_axes(path: str | Path) -> str:
    """The axes a PLY states in its header comment; a PLY that states none is taken as 3DGS's (y-down)."""
    with open(path, "rb") as f:
        head = f.read(4096)
    for line in head.split(b"end_header")[0].decode("ascii", "replace").splitlines():
        if line.startswith("comment axes "):
            name = line.split()[2].rstrip(":")
            if name in PLY_AXES:
                return name
    return "y-down"


def read_ply(path: str | Path, world: bool = True) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY (binary little endian, float properties) -> ``means``, ``quats`` (unit wxyz),
    ``scales`` (linear), ``opacities`` (sigmoid), ``colors`` (0.5 + C0 f_dc), ``properties`` (names),
    ``axes`` (the file's). ``world``: means and quats converted to our world's axes (y up), else as stored."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise InputError(f"{path} is not a PLY file")
    lines = raw[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise InputError(f"{path}: only binary little-endian PLY is supported")
    count = next(int(ln.split()[2]) for ln in lines if ln.startswith("element vertex"))
    props = [ln.split()[2] for ln in lines if ln.startswith("property float")]
    if len(props) != sum(ln.startswith("property") for ln in lines):
        raise InputError(f"{path}: only float properties are supported")
    data = np.frombuffer(raw, dtype=[(p, "<f4") for p in props], count=count, offset=end + len(b"end_header\n"))

    def cols(names: list[str]) -> np.ndarray:
        return np.stack([data[n].astype(np.float64) for n in names], axis=1)

    q = cols([f"rot_{i}" for i in range(4)])
    means, q = cols(["x", "y", "z"]), q / np.linalg.norm(q, axis=1, keepdims=True)
    axes = ply_axes(path)
    if world:
        means, q = to_axes(means, q, axes, inverse=True)
    return {
        "means": means, "quats": q,
        "scales": np.exp(cols([f"scale_{i}" for i in range(3)])),
        "opacities": 1.0 / (1.0 + np.exp(-data["opacity"].astype(np.float64))),
        "colors": 0.5 + SH_C0 * cols([f"f_dc_{i}" for i in range(3)]), "properties": np.array(props),
        "axes": np.array(axes),
    }


SPLAT_RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def write_splat(path: str | Path, means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
                colors: np.ndarray, axes: str = DEFAULT_PLY_AXES) -> None:
    """The compact web ``.splat`` format (antimatter15's, read by SuperSplat, gaussian-splats-3d and most web
    viewers): 32 bytes a Gaussian, no header: position 3 x float32, linear scale 3 x float32, sRGB colour
    and opacity 4 x uint8, wxyz rotation 4 x uint8 (``q * 128 + 128``); largest, most opaque Gaussians
    first. Same ``axes`` as the PLY; about 7x smaller than it (no spherical harmonics)."""
    from humanvdm_core.workflow.atomic import atomic_write_bytes

    means, quats = to_axes(np.asarray(means, dtype=np.float64), np.asarray(quats, dtype=np.float64), axes)
    scales = np.asarray(scales, dtype=np.float64)
    opac = np.clip(np.asarray(opacities, dtype=np.float64).reshape(-1), 0.0, 1.0)
    order = np.argsort(-(np.prod(scales, axis=1) * opac), kind="stable")
    rec = np.zeros(len(means), dtype=SPLAT_RECORD)
    rec["position"] = means[order]
    rec["scale"] = scales[order]
    rgba = np.concatenate([np.asarray(colors, dtype=np.float64), opac[:, None]], axis=1)[order]
    rec["rgba"] = np.clip(np.rint(rgba * 255), 0, 255).astype(np.uint8)
    q = quats[order] / np.linalg.norm(quats[order], axis=1, keepdims=True)
    rec["rot"] = np.clip(np.rint(q * 128 + 128), 0, 255).astype(np.uint8)
    atomic_write_bytes(path, rec.tobytes())


def read_splat(path: str | Path) -> dict[str, np.ndarray]:
    """A ``.splat`` file's records as stored: ``means``, ``scales``, ``colors``, ``opacities``, ``quats`` (unit wxyz)."""
    raw = Path(path).read_bytes()
    if len(raw) % SPLAT_RECORD.itemsize:
        raise InputError(f"{path}: not a .splat file (size {len(raw)} is not a multiple of 32)")
    rec = np.frombuffer(raw, dtype=SPLAT_RECORD)
    q = (rec["rot"].astype(np.float64) - 128.0) / 128.0
    return {"means": rec["position"].astype(np.float64), "scales": rec["scale"].astype(np.float64),
            "colors": rec["rgba"][:, :3] / 255.0, "opacities": rec["rgba"][:, 3] / 255.0,
            "quats": q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)}


def turntable_cameras(cameras, views: int, size: int):
    """``views`` cameras evenly around the frame set's orbit (its mean radius, elevation and field of view)."""
    from humanvdm_core.cameras import orbit_cameras

    fov = float(np.mean(cameras.fov_y_deg))
    az = np.arange(views) * 360.0 / views
    return orbit_cameras(views, size, fov, float(np.mean(cameras.elevation_deg)), float(np.mean(cameras.radius)),
                         azimuths_deg=az)


def render_views_np(human: GaussianHuman, cameras, background: np.ndarray, chunk: int = 1,
                    tile_size: int = 16) -> np.ndarray:
    """(N, H, W, 3) float renders of the human from ``cameras``, in [0, 1]."""
    from humanvdm_core.workflow.progress import report

    dev = human.anchors.device
    bg = torch.as_tensor(np.asarray(background, dtype=np.float32), device=dev)
    w2c = torch.as_tensor(cameras.w2c, dtype=torch.float32, device=dev)
    K = torch.as_tensor(cameras.K, dtype=torch.float32, device=dev)
    out = []
    with torch.no_grad():
        gs = human()
        for i in range(0, len(w2c), chunk):
            img, _ = render(gs, w2c[i:i + chunk], K[i:i + chunk], cameras.width, cameras.height, bg, tile_size)
            out.append(img.clamp(0, 1).cpu().numpy())
            report(min(i + chunk, len(w2c)), len(w2c), "views", "render turntable")
    return np.concatenate(out)


def write_train_log(path: str | Path, result: FitResult, extra: dict) -> None:
    from humanvdm_core.workflow.atomic import atomic_write_text

    # results only: the wall time is the lockfile's (an artifact holding timings would change on every
    # rerun and defeat the early cutoff of the stages after it)
    doc = {"schema": "humanvdm.splat_train_log", "version": 1, "iterations": result.logged_iterations,
           "loss": [round(v, 6) for v in result.losses],
           "train_psnr": round(result.train_psnr, 3), "config": result.config, **extra}
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")


# ----------------------------------------------------------------------------- oracle bodies (tests, benchmarks)

def write_oracle_body(path: str | Path, params: BodyParams, world_from_body: np.ndarray | None = None,
                      uv_resolution: int = 64, topology: str = "anny") -> None:
    """Write a ``body.npz`` (the ``fit-smpl`` schema's members the splat stage reads) for known body
    params, e.g. a synthetic subject's truth; ``world_from_body`` (4x4 uniform scale + translation,
    such as a frame set's ``world_from_scan``) moves the body into the frame set's world."""
    from humanvdm_core.body import load_body_model
    from humanvdm_core.body.uvmap import UVPositionMap
    from humanvdm_core.io import write_npz

    model = load_body_model("anny", topology=topology)
    p = params.clone().to(dtype=torch.float32)
    if world_from_body is not None:
        m = np.asarray(world_from_body, dtype=np.float64)
        s = float(np.cbrt(np.linalg.det(m[:3, :3])))
        if not np.allclose(m[:3, :3], s * np.eye(3), atol=1e-6 * max(s, 1.0)):
            raise ValueError("world_from_body must be a uniform scale + translation")
        p.scale = p.scale * s
        p.transl = p.transl * s + torch.as_tensor(m[:3, 3], dtype=torch.float32)[None]
    with torch.no_grad():
        out = model(p)
        canon_params = model.canonical_params(1)
        canon_params.shape = p.shape.clone()
        canon = model(canon_params)
    uvm = UVPositionMap.from_model(model, uv_resolution)
    f32 = np.float32
    arrays = {
        "model_name": np.array(model.name), "backend": np.array("anny"), "topology": np.array(topology),
        **{k: v.astype(f32) for k, v in p.to_numpy().items()},
        "vertices": out.vertices[0].numpy().astype(f32), "faces": model.faces.numpy().astype(np.int64),
        "bone_transforms": out.bone_transforms[0].numpy().astype(f32),
        "skinning_weights": model.skinning_weights.numpy().astype(f32),
        "canonical_pose": canon_params.pose.numpy().astype(f32),
        "canonical_vertices": canon.vertices[0].numpy().astype(f32),
        "canonical_bone_transforms": canon.bone_transforms[0].numpy().astype(f32),
        "has_uv_map": np.array(True), "uv_resolution": np.int64(uv_resolution), "uv_face_ids": uvm.face_ids,
        "uv_barycentrics": uvm.barycentrics.astype(f32), "uv_rows": uvm.rows, "uv_cols": uvm.cols,
        "uv_mask": uvm.mask, "uv_positions": uvm.positions(canon.vertices[0].numpy()).astype(f32),
        "uv_weights": uvm.weights(model.skinning_weights.numpy()).astype(f32),
    }
    write_npz(path, arrays, BODY_SCHEMA, 1)
