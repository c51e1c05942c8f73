"""Gaussian splatting: the differentiable rasterizer (``rasterize_gaussians``; gsplat conventions)."""

from humanvdm_core.splat.rasterize import (
    covariances_3d,
    project_gaussians,
    quat_to_rotmat,
    rasterize_gaussians,
)

__all__ = ["covariances_3d", "project_gaussians", "quat_to_rotmat", "rasterize_gaussians"]
