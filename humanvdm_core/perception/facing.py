"""Which way the person in a photo faces: towards the camera, or away from it (a photo from behind).

Contract of :func:`estimate_facing` (an RGB image, the person's COCO-17 keypoints and confidences in
its pixels, and optionally MediaPipe's 3D world keypoints in the camera's axes):

- Evidence, each a vote in [-1, 1] (positive = facing the camera):

  * ``face``: MediaPipe's bundled full-range face detector (``face_detection_full_range_sparse``)
    run on the head's box; a face found (score >= :data:`FACE_SCORE`) votes +1, none votes -0.5
    (hats, masks, hair and small faces also hide a face, so its absence weighs less);
  * ``order``: the person's left shoulder and hip lie on the image's right in a frontal photo and on
    its left in a photo from behind: ``(x_left - x_right) / torso height`` of shoulders and hips,
    scaled and clipped to [-1, 1];
  * ``depth``: in the 3D world keypoints, the nose in front of the ears (smaller z) faces the
    camera: ``(ears z - nose z) / 0.05 m`` clipped to [-1, 1].

- The person faces away when ``face`` found nothing and the sum of the votes is below
  :data:`AWAY_THRESHOLD`; a detected face always means facing the camera.
- :class:`Facing` reports the decision, the votes, and ``ambiguous`` (no face found but the other
  votes disagree or are weak: the decision is a guess, the caller should say so).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

FACE_SCORE = 0.5
AWAY_THRESHOLD = -0.5
_HEAD = (0, 1, 2, 3, 4)  # COCO nose, eyes, ears


@dataclass
class Facing:
    away: bool  # the person faces away from the camera (the photo shows their back)
    ambiguous: bool  # no face found and the pose evidence is weak or contradictory
    votes: dict[str, float] = field(default_factory=dict)


def _face_found(rgb: np.ndarray, keypoints: np.ndarray, confidences: np.ndarray) -> bool:
    """Whether MediaPipe's full-range face detector finds a face around the head keypoints."""
    os.environ.setdefault("GLOG_minloglevel", "2")
    from mediapipe.python.solutions import face_detection

    h, w = rgb.shape[:2]
    head = keypoints[list(_HEAD)][confidences[list(_HEAD)] > 0.3]
    shoulders = keypoints[[5, 6]]
    if len(head):
        span = max(float(np.linalg.norm(shoulders[0] - shoulders[1])), 20.0)
        cx, cy = head.mean(axis=0)
        x0, x1 = int(max(0, cx - span)), int(min(w, cx + span))
        y0, y1 = int(max(0, cy - span)), int(min(h, cy + span))
        crop = rgb[y0:y1, x0:x1] if x1 - x0 > 8 and y1 - y0 > 8 else rgb
    else:
        crop = rgb
    image = np.ascontiguousarray((np.clip(crop, 0.0, 1.0) * 255 + 0.5).astype(np.uint8))
    with face_detection.FaceDetection(model_selection=1, min_detection_confidence=FACE_SCORE) as detector:
        result = detector.process(image)
    return bool(result.detections)


def estimate_facing(rgb: np.ndarray, keypoints: np.ndarray, confidences: np.ndarray,
                    world_keypoints: np.ndarray | None = None) -> Facing:
    """Facing of the person (see the module docstring)."""
    votes: dict[str, float] = {}
    face = _face_found(rgb, keypoints, confidences)
    votes["face"] = 1.0 if face else -0.5
    torso_h = float(np.linalg.norm(keypoints[[5, 6]].mean(0) - keypoints[[11, 12]].mean(0)))
    order = []
    for left, right in ((5, 6), (11, 12)):
        if min(confidences[left], confidences[right]) >= 0.5:
            order.append((keypoints[left, 0] - keypoints[right, 0]) / max(torso_h, 1.0))
    votes["order"] = float(np.clip(4.0 * np.mean(order), -1.0, 1.0)) if order else 0.0
    if world_keypoints is not None and np.all(np.isfinite(world_keypoints[[0, 3, 4]])):
        votes["depth"] = float(np.clip((world_keypoints[[3, 4], 2].mean() - world_keypoints[0, 2]) / 0.05, -1, 1))
    total = sum(votes.values())
    away = (not face) and total < AWAY_THRESHOLD
    pose_votes = [v for k, v in votes.items() if k != "face"]
    ambiguous = (not face) and (not away or any(v > 0.2 for v in pose_votes) or not pose_votes)
    return Facing(away=away, ambiguous=ambiguous, votes=votes)
