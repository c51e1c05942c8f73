"""Backend-neutral parametric body model interface (batched, differentiable, torch).

World frame (the project's, see ``humanvdm_core.cameras``): metres, Y up, the body facing +Z at
zero ``global_orient``, the person's left side at +X. Every backend converts its native frame to
this one, so ``BodyOutput`` is always in world coordinates.

Parameters (:class:`BodyParams`, batch size B):

- ``pose`` (B, P, 3): axis-angle rotation of each posable joint (``BodyModel.pose_joint_names``)
  relative to its parent, the axis expressed in world-aligned axes of the zero pose (as SMPL's
  ``body_pose``). The root is not in ``pose``: ``global_orient`` rotates the whole body.
- ``shape`` (B, S): backend-specific shape coefficients (``BodyModel.shape_names``).
- ``global_orient`` (B, 3): axis-angle rotation of the body about the root joint (at the origin).
- ``transl`` (B, 3): translation added last.
- ``scale`` (B, 1): uniform scale about the root joint, applied before ``transl``.

So a posed point is ``x = scale * R(global_orient) @ x_local + transl`` where ``x_local`` is the
model posed by ``pose`` and ``shape`` with its root joint at the origin.

Outputs (:class:`BodyOutput`): posed ``vertices`` (B, V, 3), ``joints`` (B, J, 3) (the posed joint
centres, joint 0 being the root), ``coco17`` (B, 17, 3) keypoints in the COCO order of
:data:`COCO17_NAMES`, ``rest_vertices`` (B, V, 3) (the shaped mesh in the backend's bind pose, in
world axes with the root joint at the origin; not necessarily the zero pose) and
``bone_transforms`` (B, J, 4, 4) such that linear blend skinning of ``rest_vertices`` with
``BodyModel.skinning_weights`` and ``bone_transforms`` gives ``vertices``:
``vertices = lbs(rest_vertices, skinning_weights, bone_transforms)``.

Posing any other points with the body (e.g. Gaussians anchored in a canonical pose):
``lbs(points_canonical, weights, target.bone_transforms, source_transforms=canonical.bone_transforms)``
un-poses the points with the canonical transforms, then poses them with the target ones.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

COCO17_NAMES: tuple[str, ...] = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
)


@dataclass
class BodyParams:
    """A batch of body parameters; see the module docstring for shapes and meaning."""

    pose: torch.Tensor  # (B, P, 3) axis-angle per posable joint
    shape: torch.Tensor  # (B, S)
    global_orient: torch.Tensor  # (B, 3) axis-angle
    transl: torch.Tensor  # (B, 3)
    scale: torch.Tensor  # (B, 1)

    @property
    def batch_size(self) -> int:
        return int(self.pose.shape[0])

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> BodyParams:
        return BodyParams(**{f.name: getattr(self, f.name).to(device=device, dtype=dtype) for f in fields(self)})

    def detach(self) -> BodyParams:
        return BodyParams(**{f.name: getattr(self, f.name).detach() for f in fields(self)})

    def clone(self) -> BodyParams:
        return BodyParams(**{f.name: getattr(self, f.name).clone() for f in fields(self)})

    def requires_grad_(self, requires_grad: bool = True) -> BodyParams:
        """Make every tensor a leaf that requires grad (in place); returns self."""
        for f in fields(self):
            getattr(self, f.name).requires_grad_(requires_grad)
        return self

    def to_numpy(self) -> dict[str, np.ndarray]:
        """Named float arrays (for NPZ artifacts); :meth:`from_numpy` reads them back."""
        return {f.name: getattr(self, f.name).detach().cpu().numpy() for f in fields(self)}

    @classmethod
    def from_numpy(cls, arrays: dict[str, np.ndarray], dtype: torch.dtype = torch.float32) -> BodyParams:
        return cls(**{f.name: torch.as_tensor(np.asarray(arrays[f.name]), dtype=dtype) for f in fields(cls)})


@dataclass
class BodyOutput:
    """A posed batch, in world coordinates; see the module docstring."""

    vertices: torch.Tensor  # (B, V, 3)
    joints: torch.Tensor  # (B, J, 3)
    coco17: torch.Tensor  # (B, 17, 3)
    bone_transforms: torch.Tensor  # (B, J, 4, 4)
    rest_vertices: torch.Tensor  # (B, V, 3)


class BodyModel(torch.nn.Module):
    """Abstract parametric body model. Subclasses set the attributes and implement the methods.

    Attributes:
        name: backend and variant, e.g. ``"anny:anny"``.
        faces: (F, 3) int64 vertex indices of the triangles.
        uvs: (T, 2) texture coordinates (OBJ convention: v points up), or None without a UV layout.
        uv_faces: (F, 3) int64 indices into ``uvs`` per triangle (UV seams: one vertex may have
            several texture coordinates), or None.
        skinning_weights: (V, J) LBS weights, rows summing to 1.
        joint_names: the J joint names, root first.
        pose_joint_names: the P joints ``BodyParams.pose`` rotates, in its order.
        shape_names: the S shape coefficients of ``BodyParams.shape``.
    """

    name: str
    faces: torch.Tensor
    uvs: torch.Tensor | None
    uv_faces: torch.Tensor | None
    skinning_weights: torch.Tensor
    joint_names: list[str]
    pose_joint_names: list[str]
    shape_names: list[str]

    @property
    def num_vertices(self) -> int:
        return int(self.skinning_weights.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def dtype(self) -> torch.dtype:
        return self.skinning_weights.dtype

    @property
    def device(self) -> torch.device:
        return self.skinning_weights.device

    def default_shape(self, batch: int = 1) -> torch.Tensor:
        """(B, S) the backend's average body shape."""
        raise NotImplementedError

    def zero_params(self, batch: int = 1) -> BodyParams:
        """Zero pose, zero global orientation and translation, unit scale, the default shape."""
        kw = dict(dtype=self.dtype, device=self.device)
        return BodyParams(
            pose=torch.zeros(batch, len(self.pose_joint_names), 3, **kw),
            shape=self.default_shape(batch),
            global_orient=torch.zeros(batch, 3, **kw),
            transl=torch.zeros(batch, 3, **kw),
            scale=torch.ones(batch, 1, **kw),
        )

    def canonical_params(self, batch: int = 1) -> BodyParams:
        """The canonical pose Gaussians are anchored in (GaussianAvatar's "da-pose": legs spread
        about 30 degrees each, arms relaxed), default shape, zero global orientation."""
        raise NotImplementedError

    def forward(self, params: BodyParams) -> BodyOutput:
        raise NotImplementedError

    def pose_index(self, joint_name: str) -> int:
        """Index of a joint in ``BodyParams.pose``."""
        return self.pose_joint_names.index(joint_name)


# ----------------------------------------------------------------------------- rotations and LBS

def skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) vectors -> (..., 3, 3) cross-product matrices."""
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack([
        torch.stack([zero, -z, y], -1),
        torch.stack([z, zero, -x], -1),
        torch.stack([-y, x, zero], -1),
    ], -2)


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle -> (..., 3, 3) rotation matrices (Rodrigues; smooth and with finite
    gradients at zero, using Taylor expansions for small angles)."""
    theta2 = (rotvec * rotvec).sum(-1)[..., None, None]
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    K = skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def global_transform(params: BodyParams) -> torch.Tensor:
    """(B, 4, 4) ``x -> scale * R(global_orient) x + transl``."""
    R = axis_angle_to_matrix(params.global_orient) * params.scale[:, :, None]
    G = torch.zeros(params.batch_size, 4, 4, dtype=R.dtype, device=R.device)
    G[:, :3, :3] = R
    G[:, :3, 3] = params.transl
    G[:, 3, 3] = 1.0
    return G


def transform_points(transforms: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply (..., 4, 4) affine transforms to (..., 3) points (broadcasting)."""
    return (transforms[..., :3, :3] @ points[..., None])[..., 0] + transforms[..., :3, 3]


def blend_transforms(weights: torch.Tensor, bone_transforms: torch.Tensor) -> torch.Tensor:
    """Per-point LBS transforms: (N, J) or (B, N, J) weights, (B, J, 4, 4) -> (B, N, 4, 4)."""
    if weights.dim() == 2:
        return torch.einsum("nj,bjkl->bnkl", weights, bone_transforms)
    return torch.einsum("bnj,bjkl->bnkl", weights, bone_transforms)


def lbs(
    points: torch.Tensor,
    weights: torch.Tensor,
    bone_transforms: torch.Tensor,
    source_transforms: torch.Tensor | None = None,
) -> torch.Tensor:
    """Linear blend skinning of arbitrary points.

    Args:
        points: (N, 3) or (B, N, 3) points. Without ``source_transforms`` they are in the rest
            frame of ``BodyOutput.rest_vertices``; with it, they are posed by ``source_transforms``
            (e.g. points on the canonical da-pose body) and are un-posed first.
        weights: (N, J) or (B, N, J) skinning weights, rows summing to 1.
        bone_transforms: (B, J, 4, 4) target ``BodyOutput.bone_transforms``.
        source_transforms: optional (B, J, 4, 4) ``bone_transforms`` the points are posed by.
    Returns:
        (B, N, 3) posed points. With ``source_transforms`` the blended transform is
        ``(sum_j w_j T_j) @ inverse(sum_j w_j S_j)``, which maps the source body's mesh vertices
        exactly onto the target body's.
    """
    A = blend_transforms(weights, bone_transforms)
    if source_transforms is not None:
        A = A @ torch.linalg.inv(blend_transforms(weights, source_transforms))
    if points.dim() == 2:
        points = points[None]
    return transform_points(A, points)
