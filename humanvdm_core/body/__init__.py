"""Parametric body models in the project's world frame, LBS, and UV position maps.

``model`` holds the backend-neutral interface (``BodyModel``, ``BodyParams``, ``BodyOutput``,
``lbs``); ``anny_model`` the Anny backend (imports ``anny`` only when a model is built);
``smpl_model`` the SMPL / SMPL-X backend (user-supplied model files); ``uvmap`` the UV position map.
See each module's docstring for its contract. :func:`load_body_model` builds a backend by name.
"""

from __future__ import annotations

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
from humanvdm_core.body.smpl_model import SMPLBody, load_model_file
from humanvdm_core.body.uvmap import UVPositionMap, rasterize_uv_triangles
from humanvdm_core.workflow.errors import ConfigError

BACKENDS = ("anny", "smpl", "smplx")


def load_body_model(backend: str, **kw) -> BodyModel:
    """A body model by backend name: ``"anny"`` -> ``AnnyBody(**kw)`` (e.g. ``topology``);
    ``"smpl"``/``"smplx"`` -> ``SMPLBody(kind=backend, **kw)`` (needs ``model_dir``; e.g. ``gender``,
    ``num_betas``). ``dtype``/``device`` are accepted by all. Raises ConfigError for an unknown backend,
    MissingWeightsError when SMPL's files are not where ``model_dir`` says."""
    if backend == "anny":
        return AnnyBody(**kw)
    if backend in ("smpl", "smplx"):
        if "model_dir" not in kw:
            raise ConfigError(f"the {backend} body model needs model_dir (the folder holding {backend}/ with "
                              f"the model files you downloaded)")
        return SMPLBody(kind=backend, **kw)
    raise ConfigError(f"unknown body model backend {backend!r}; choose one of {list(BACKENDS)}")


__all__ = [
    "BACKENDS", "AnnyBody", "BodyModel", "BodyOutput", "BodyParams", "COCO17_NAMES", "SMPLBody", "TOPOLOGIES",
    "UVPositionMap", "anny_cache_dir", "axis_angle_to_matrix", "blend_transforms", "cache_root", "lbs",
    "load_body_model", "load_model_file", "rasterize_uv_triangles",
]
