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

- The pose model can mirror a whole skeleton (seen on a person turned 45-60 deg with raised arms): its left
  and right swapped and its 3D depth turned inside out, as for a person seen from behind, while the face
  faces the camera. :attr:`Facing.mirrored` says so (a face found, ``order`` and ``depth`` both at most
  ``-MIRROR_VOTE``); :func:`unmirrored` sets the keypoints right.
- The person faces away when ``face`` found nothing and the sum of the votes is below
  :data:`AWAY_THRESHOLD`; a detected face always means facing the camera.
- :class:`Facing` reports the decision, the votes, and ``ambiguous`` (no face found but the other
  votes disagree or are weak: the decision is a guess, the caller should say so).
- A face found is also pitched: MediaPipe's bundled face mesh on the same head box, the forehead
  (landmark 10) -> chin (152) line's tilt out of the image plane, positive with the forehead nearer
  the camera (``pitch_deg``; ``None`` without a face or a mesh). ``bowed``: beyond :data:`BOWED_DEG`.
  Upright real faces photographed from 10 deg above read -2 to +13 deg; a head bowed to read or to
  look at a phone reads more.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

FACE_SCORE = 0.5
AWAY_THRESHOLD = -0.5
BOWED_DEG = 15.0  # a face pitched this far towards the camera (forehead nearer than the chin) is bowed
MIRROR_VOTE = 0.5  # a face found, and the pose's order and depth votes both at or below minus this: mirrored
_HEAD = (0, 1, 2, 3, 4)  # COCO nose, eyes, ears
# COCO-17 with each left joint and its right one swapped (eyes, ears, shoulders, elbows, wrists, hips, knees, ankles)
SWAPPED_SIDES = (0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15)


@dataclass
class Facing:
    away: bool  # the person faces away from the camera (the photo shows their back)
    ambiguous: bool  # no face found and the pose evidence is weak or contradictory
    votes: dict[str, float] = field(default_factory=dict)
    pitch_deg: float | None = None  # the face's tilt towards the camera (forehead nearer), from the face mesh

    @property
    def mirrored(self) -> bool:
        """A face is found, yet the pose model's 2D left/right order and its own 3D depth (the nose behind the
        ears) both read a person seen from behind (each vote at most ``-MIRROR_VOTE``): the model mirrored
        the whole skeleton, its left and right swapped and its depth turned inside out."""
        return (self.votes.get("face", 0.0) > 0 and self.votes.get("order", 0.0) <= -MIRROR_VOTE
                and self.votes.get("depth", 0.0) <= -MIRROR_VOTE)

    @property
    def bowed(self) -> bool:
        """The face is pitched beyond :data:`BOWED_DEG` towards the camera: the head is bowed."""
        return self.pitch_deg is not None and self.pitch_deg > BOWED_DEG


def _head_crop(rgb: np.ndarray, keypoints: np.ndarray, confidences: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8: the box of a shoulder width around the head keypoints (the whole image without them)."""
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
    return np.ascontiguousarray((np.clip(crop, 0.0, 1.0) * 255 + 0.5).astype(np.uint8))


def _face_found(image: np.ndarray) -> bool:
    """Whether MediaPipe's full-range face detector finds a face in the head crop ``image``."""
    os.environ.setdefault("GLOG_minloglevel", "2")
    from mediapipe.python.solutions import face_detection

    with face_detection.FaceDetection(model_selection=1, min_detection_confidence=FACE_SCORE) as detector:
        result = detector.process(image)
    return bool(result.detections)


def face_pitch_deg(image: np.ndarray) -> float | None:
    """The pitch (module docstring) of the face MediaPipe's face mesh finds in the head crop ``image``
    (its shorter side upscaled to 256 px first when under 192), or ``None``."""
    os.environ.setdefault("GLOG_minloglevel", "2")
    import cv2
    from mediapipe.python.solutions import face_mesh

    h, w = image.shape[:2]
    if min(h, w) < 192:
        k = 256.0 / min(h, w)
        image = cv2.resize(image, (round(w * k), round(h * k)), interpolation=cv2.INTER_CUBIC)
    with face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1) as mesh:
        result = mesh.process(image)
    if not result.multi_face_landmarks:
        return None
    marks = result.multi_face_landmarks[0].landmark
    h, w = image.shape[:2]  # MediaPipe's z is in units of the image width, as x
    up = np.array([(marks[10].y - marks[152].y) * h, (marks[10].z - marks[152].z) * w])  # chin -> forehead
    return float(np.degrees(np.arctan2(-up[1], -up[0])))


def estimate_facing(rgb: np.ndarray, keypoints: np.ndarray, confidences: np.ndarray,
                    world_keypoints: np.ndarray | None = None) -> Facing:
    """Facing of the person (see the module docstring)."""
    votes: dict[str, float] = {}
    head = _head_crop(rgb, keypoints, confidences)
    face = _face_found(head)
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
    return Facing(away=away, ambiguous=ambiguous, votes=votes, pitch_deg=face_pitch_deg(head) if face else None)


def unmirrored(keypoints: np.ndarray, confidences: np.ndarray,
               world_keypoints: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The COCO-17 ``keypoints`` (17, 2), ``confidences`` (17,) and 3D ``world_keypoints`` (17, 3, camera axes)
    of a skeleton the pose model mirrored (:attr:`Facing.mirrored`) set right: left and right swapped, and the
    3D landmarks' depth reflected about that of their hips' centre (a reflection in depth keeps the 2D
    projection and turns a person seen from behind into one facing the camera)."""
    order = list(SWAPPED_SIDES)
    world = None
    if world_keypoints is not None:
        world = np.asarray(world_keypoints, np.float32)[order].copy()
        world[:, 2] = 2.0 * world[[11, 12], 2].mean() - world[:, 2]
    return np.asarray(keypoints)[order].copy(), np.asarray(confidences)[order].copy(), world
