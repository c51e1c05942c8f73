"""Person perception: load a user's photo, find the person (mask, COCO-17 keypoints, bbox, warnings).

``image.load_photo`` reads any common image format into an upright straight-RGB float
:class:`Photo`; ``detect.detect_person`` runs MediaPipe (bundled models only, offline) on it and
returns a :class:`Detection`. Each module's docstring states its contract.
"""

from humanvdm_core.body.model import COCO17_NAMES
from humanvdm_core.perception.detect import (
    BLAZEPOSE_TO_COCO17,
    MIN_CONFIDENCE,
    REQUIRED_JOINTS,
    Detection,
    detect_person,
)
from humanvdm_core.perception.image import MAX_SIDE, MIN_SIDE, Photo, load_photo

__all__ = [
    "BLAZEPOSE_TO_COCO17", "COCO17_NAMES", "MAX_SIDE", "MIN_CONFIDENCE", "MIN_SIDE", "REQUIRED_JOINTS",
    "Detection", "Photo", "detect_person", "load_photo",
]
