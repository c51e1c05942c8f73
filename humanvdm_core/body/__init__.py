"""Parametric body models in the project's world frame, LBS, and UV position maps.

``model`` holds the backend-neutral interface (``BodyModel``, ``BodyParams``, ``BodyOutput``,
``lbs``); ``anny_model`` the Anny backend (imports ``anny`` only when a model is built);
``uvmap`` the UV position map. See each module's docstring for its contract.
"""

from humanvdm_core.body.anny_model import TOPOLOGIES, AnnyBody, anny_cache_dir, cache_root
from humanvdm_core.body.model import (
    COCO17_NAMES,
    BodyModel,
    BodyOutput,
    BodyParams,
    axis_angle_to_matrix,
    blend_transforms,
    lbs,
)
from humanvdm_core.body.uvmap import UVPositionMap, rasterize_uv_triangles

__all__ = [
    "AnnyBody", "BodyModel", "BodyOutput", "BodyParams", "COCO17_NAMES", "TOPOLOGIES", "UVPositionMap",
    "anny_cache_dir", "axis_angle_to_matrix", "blend_transforms", "cache_root", "lbs", "rasterize_uv_triangles",
]
