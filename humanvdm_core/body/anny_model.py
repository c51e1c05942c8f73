"""Anny body model backend (PyPI ``anny``, Apache-2.0, MakeHuman-based; ships all its data).

:class:`AnnyBody` wraps ``anny.Anny`` (rig ``"anny"``: 104 bones; dense linear blend skinning; pose
parameterization ``"local-ref"``) behind :class:`~humanvdm_core.body.model.BodyModel`:

- ``pose`` (B, 103, 3): axis-angle per bone except the root (``pose_joint_names`` = Anny's bone
  labels after ``"root"``), in world-aligned axes of the zero pose. Anny's zero pose is its
  reference pose: arms relaxed in an A-pose, legs slightly apart.
- ``shape`` (B, 6): Anny's phenotype values ``gender, age, muscle, weight, height, proportions``,
  each nominally in [0, 1], 0.5 being the average (gender 0 male, 1 female; age anchors newborn
  -1/3, baby 0, child 1/3, young adult 2/3, old 1).
- Anny's native frame (Z up, facing -Y, left at +X) is rotated to the world frame (Y up, facing +Z).
  The root bone (at the pelvis) sits at the origin at zero ``global_orient``/``transl``.
- ``coco17`` comes from Anny's COCO-WholeBody keypoint regressor (its first 17 keypoints).

Topologies (:data:`TOPOLOGIES`): ``"anny"`` (default, full resolution, with a UV layout) and the
lower-resolution retopologies Anny ships (no UV layout). Building a retopology the first time needs
``warp-lang`` (Anny projects the new mesh onto the full one with Warp kernels, on CPU too); after
that the built data is read from the cache. Their COCO keypoints are transferred from the full
mesh's regressor by nearest vertex at rest (an approximation: within about 1 cm of the full mesh's
keypoints for ``notoes``, ``notoes_collapse10pc`` and ``notoes_collapse5pc``, 4 cm for
``notoes_collapse3pc``). Anny's SMPL and SMPL-X topologies need non-free files and are refused.

``rest_vertices``/``bone_transforms`` refer to Anny's rest (bind) mesh, whose pose differs slightly
from the zero pose, so ``bone_transforms`` are not the identity at zero parameters.

Anny builds its model data on first use (about a minute on one CPU core) and caches it, several
hundred MB, under :func:`anny_cache_dir` (``$HUMANVDM_CACHE/anny``, by default
``~/.cache/humanvdm/anny``, shared by every checkout on the machine). Nothing is downloaded.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from humanvdm_core.body.model import (
    COCO17_NAMES,
    BodyModel,
    BodyOutput,
    BodyParams,
    axis_angle_to_matrix,
    global_transform,
    transform_points,
)
from humanvdm_core.workflow.errors import ConfigError

# topology -> (vertex count, has UVs, what it is)
TOPOLOGIES: dict[str, tuple[int, bool, str]] = {
    "anny": (13718, True, "full MakeHuman-based mesh with eyes and tongue, UV layout (default)"),
    "notoes": (12272, False, "retopology without separate toes"),
    "notoes_collapse10pc": (1229, False, "decimated to 10% of the vertices"),
    "notoes_collapse5pc": (615, False, "decimated to 5%"),
    "notoes_collapse3pc": (369, False, "decimated to 3%"),
}
DEFAULT_TOPOLOGY = "anny"
SHAPE_NAMES = ["gender", "age", "muscle", "weight", "height", "proportions"]

# Anny's native frame (Z up, facing -Y) -> world (Y up, facing +Z): x' = x, y' = z, z' = -y.
ANNY_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

# The canonical da-pose: each upper leg rotated outward by this much about the forward axis,
# on top of Anny's zero pose (whose legs are already about 6 degrees apart): about 29 degrees each.
CANONICAL_LEG_SPREAD_DEG = 22.5


def cache_root() -> Path:
    """The user-level cache folder, shared by every checkout on the machine: ``$HUMANVDM_CACHE``,
    else ``$XDG_CACHE_HOME/humanvdm``, else ``~/.cache/humanvdm``."""
    env = os.environ.get("HUMANVDM_CACHE")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "humanvdm"


def anny_cache_dir() -> Path:
    """Where Anny's built model data is cached (``cache_root() / "anny"``)."""
    return cache_root() / "anny"


def _import_anny():
    try:
        import anny
    except ImportError as exc:
        raise ConfigError(
            "the Anny body model needs the 'anny' package: pip install --no-deps anny==0.6.2 roma safetensors"
        ) from exc
    return anny


def _build_anny(topology: str):
    """Construct ``anny.Anny`` (float64, CPU) with its cache under :func:`anny_cache_dir`."""
    anny = _import_anny()
    from anny.paths import set_anny_cache_path

    set_anny_cache_path(anny_cache_dir())
    if topology != "anny":
        # Retopologies need Warp on their first build; keep its kernel cache with ours, quiet.
        os.environ.setdefault("WARP_CACHE_PATH", str(cache_root() / "warp"))
        try:
            import warp

            warp.config.quiet = True
        except ImportError:
            pass
    try:
        return anny.Anny(rig="anny", topology=topology, skinning_method="lbs", pose_parameterization="local-ref",
                         phenotypes="default", local_changes="none")
    except ModuleNotFoundError as exc:
        if "warp" in str(exc).lower():
            raise ConfigError(
                f"building Anny topology {topology!r} the first time needs warp-lang: pip install --no-deps "
                f"warp-lang (or use topology='anny')"
            ) from exc
        raise


def _nearest(src: np.ndarray, dst: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Index of the nearest ``dst`` point for each ``src`` point (brute force, chunked)."""
    out = np.empty(len(src), dtype=np.int64)
    dst_sq = (dst * dst).sum(1)
    for i in range(0, len(src), chunk):
        s = src[i:i + chunk]
        d = dst_sq[None, :] - 2.0 * s @ dst.T
        out[i:i + chunk] = np.argmin(d, axis=1)
    return out


class AnnyBody(BodyModel):
    """The Anny body model in the project's conventions (see the module docstring)."""

    def __init__(self, topology: str = DEFAULT_TOPOLOGY, dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu"):
        super().__init__()
        if topology not in TOPOLOGIES:
            hint = " (Anny's SMPL/SMPL-X topologies need non-free files; not supported)" \
                if topology.startswith("smpl") else ""
            raise ConfigError(f"unknown Anny topology {topology!r}{hint}; choose one of {sorted(TOPOLOGIES)}")
        anny = _import_anny()
        model = _build_anny(topology)
        self.topology = topology
        self.name = f"anny:{topology}"
        self.joint_names = list(model.bone_labels)
        self.pose_joint_names = self.joint_names[1:]
        self.shape_names = list(SHAPE_NAMES)
        if list(model.phenotype_labels) != self.shape_names:
            raise RuntimeError(f"unexpected Anny phenotypes {model.phenotype_labels}")

        coco = self._coco_regressor(anny, model, topology)
        self.anny = model.to(dtype=dtype)
        self.register_buffer("faces", model.faces.to(torch.int64).clone(), persistent=False)
        if model.texture_coordinates is not None and model.face_texture_coordinate_indices is not None:
            self.register_buffer("uvs", model.texture_coordinates.to(dtype).clone(), persistent=False)
            self.register_buffer("uv_faces", model.face_texture_coordinate_indices.to(torch.int64).clone(),
                                 persistent=False)
        else:
            self.uvs = None
            self.uv_faces = None
        self.register_buffer("skinning_weights", model.dense_vertex_bone_weights.to(dtype).clone(), persistent=False)
        self.register_buffer("coco_weights", coco.to(dtype), persistent=False)
        self.register_buffer("to_world", torch.as_tensor(ANNY_TO_WORLD, dtype=dtype), persistent=False)
        self.to(device)

    @staticmethod
    def _coco_regressor(anny, model, topology: str) -> torch.Tensor:
        """(17, V) COCO-17 regression weights on this topology's vertices."""
        if topology == "anny":
            return anny.KeypointsRegressor.coco(model, labels=list(COCO17_NAMES)).regression_weights.clone()
        # Retopology: move the full mesh's weights to the nearest vertex of this mesh, both at rest.
        full = _build_anny("anny")
        full_weights = anny.KeypointsRegressor.coco(full, labels=list(COCO17_NAMES)).regression_weights
        with torch.no_grad():
            full_rest = full()["rest_vertices"][0].numpy()
            rest = model()["rest_vertices"][0].numpy()
        used = np.flatnonzero(full_weights.abs().sum(0).numpy() > 0)
        nearest = torch.as_tensor(_nearest(full_rest[used], rest))
        weights = torch.zeros(len(COCO17_NAMES), len(rest), dtype=full_weights.dtype)
        weights.index_add_(1, nearest, full_weights[:, used])
        return weights

    def default_shape(self, batch: int = 1) -> torch.Tensor:
        return torch.full((batch, len(self.shape_names)), 0.5, dtype=self.dtype, device=self.device)

    def canonical_params(self, batch: int = 1) -> BodyParams:
        params = self.zero_params(batch)
        angle = np.radians(CANONICAL_LEG_SPREAD_DEG)
        # A positive rotation about +Z (forward) swings a downward leg towards +X (the left side).
        params.pose[:, self.pose_index("upperleg01.L"), 2] = angle
        params.pose[:, self.pose_index("upperleg01.R"), 2] = -angle
        return params

    def forward(self, params: BodyParams) -> BodyOutput:
        B = params.batch_size
        C = self.to_world
        C4 = torch.eye(4, dtype=C.dtype, device=C.device)
        C4[:3, :3] = C
        # Anny's local-ref deltas are rotations in native world-aligned axes: D = C^T R C.
        rot = C.T @ axis_angle_to_matrix(params.pose) @ C
        deltas = torch.eye(4, dtype=rot.dtype, device=rot.device).repeat(B, self.num_joints, 1, 1)
        deltas[:, 1:, :3, :3] = rot  # the root's delta stays identity: global_orient is applied after
        out = self.anny(pose_parameters=deltas, phenotype_kwargs=params.shape)
        W = out["bone_poses"]  # (B, J, 4, 4) posed bone frames, native
        P = out["rest_bone_poses"]  # (B, J, 4, 4) rest bone frames, native
        P_inv = _rigid_inverse(P)
        P0 = P[:, 0]
        # world transform of a native posed point, and world rest frame (root's rest frame at origin)
        G = global_transform(params) @ C4  # (B, 4, 4)
        rest_to_native = P0 @ C4.T  # world rest point -> native rest point
        bone_transforms = G[:, None] @ W @ P_inv @ rest_to_native[:, None]
        vertices = transform_points(G[:, None], out["vertices"])
        rest_vertices = transform_points((C4 @ _rigid_inverse(P0))[:, None], out["rest_vertices"])
        joints = transform_points(G[:, None], W[..., :3, 3])
        coco17 = torch.einsum("kv,bvd->bkd", self.coco_weights, vertices)
        return BodyOutput(vertices=vertices, joints=joints, coco17=coco17, bone_transforms=bone_transforms,
                          rest_vertices=rest_vertices)


def _rigid_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 4, 4) rigid transforms."""
    R_t = T[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -(R_t @ T[..., :3, 3:])[..., 0]
    out[..., 3, 3] = 1.0
    return out
