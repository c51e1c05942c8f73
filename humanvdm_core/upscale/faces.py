"""Faces for CodeFormer: detection, 5-point alignment to the FFHQ template, feathered paste-back.

The official CodeFormer inference detects faces with facexlib's RetinaFace (which needs
torchvision and a separately downloaded ``detection_Resnet50_Final.pth``).  This module uses
**MediaPipe's full-range face detector** instead: its model (``face_detection_full_range_sparse.tflite``)
ships inside the ``mediapipe`` wheel the project already uses, so it runs offline with nothing to
download.  It gives six keypoints (both eyes, nose tip, mouth centre, both ear tragions); the five
points the FFHQ alignment needs are both eyes, the nose tip and the two mouth corners, the latter
placed at the mouth centre +- 0.444 x the eye-to-eye vector (the ratio of mouth width to eye
distance in the template).  The alignment is a similarity transform fitted with LMedS
(``cv2.estimateAffinePartial2D``), as in the official pipeline.

Paste-back: the restored crop is warped back with the inverse similarity, scaled to the upscaled
background with pixel centres kept aligned, and blended with a mask that is eroded and
Gaussian-feathered in proportion to the face's size (so no crop border or seam shows).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# FFHQ 5-point template for a 512² crop: eye (image left), eye (image right), nose tip, mouth
# corners (image left, image right).  Scaled by size / 512 for other crop sizes.
FFHQ_TEMPLATE_512 = np.array([[192.98138, 239.94708], [318.90277, 240.19360], [256.63416, 314.01935],
                              [201.26117, 371.41043], [313.08905, 371.15118]], np.float32)
MOUTH_HALF_WIDTH = 0.444  # mouth-corner half-distance / eye distance in the template
BORDER_RGB = (132 / 255, 133 / 255, 135 / 255)  # fill outside the frame, as the official alignment


@dataclass(frozen=True)
class Face:
    landmarks: np.ndarray  # (5, 2) pixel coordinates (x, y), template order
    score: float
    box: tuple[float, float, float, float]  # x, y, width, height in pixels


def detect_faces(rgb: np.ndarray, min_score: float = 0.5, min_size: float = 8.0) -> list[Face]:
    """Faces in an (H, W, 3) RGB image in [0, 1], largest first (faces narrower than ``min_size`` px dropped)."""
    try:
        from mediapipe.python.solutions import face_detection
    except ImportError as e:
        from humanvdm_core.workflow.errors import HumanVDMError

        raise HumanVDMError(f"the codeformer backend detects faces with MediaPipe, which does not import ({e}); "
                            "`make setup` installs it (mediapipe==0.10.21, --no-deps)") from None

    h, w = rgb.shape[:2]
    img = np.ascontiguousarray(np.clip(np.rint(rgb[..., :3] * 255.0), 0, 255).astype(np.uint8))
    with face_detection.FaceDetection(model_selection=1, min_detection_confidence=min_score) as fd:
        result = fd.process(img)
    faces = []
    for det in result.detections or []:
        kp = np.array([(k.x * w, k.y * h) for k in det.location_data.relative_keypoints], np.float32)
        bb = det.location_data.relative_bounding_box
        box = (bb.xmin * w, bb.ymin * h, bb.width * w, bb.height * h)
        if box[2] < min_size:
            continue
        eyes = kp[:2][np.argsort(kp[:2, 0])]  # image-left eye first
        half = MOUTH_HALF_WIDTH * (eyes[1] - eyes[0])
        lm = np.stack([eyes[0], eyes[1], kp[2], kp[3] - half, kp[3] + half]).astype(np.float32)
        faces.append(Face(lm, float(det.score[0]), box))
    return sorted(faces, key=lambda f: -f.box[2] * f.box[3])


def alignment(landmarks: np.ndarray, size: int) -> np.ndarray:
    """2x3 similarity mapping image pixels to the ``size``² aligned crop."""
    import cv2

    template = FFHQ_TEMPLATE_512 * (size / 512.0)
    matrix, _ = cv2.estimateAffinePartial2D(landmarks.astype(np.float32), template, method=cv2.LMEDS)
    if matrix is None:  # degenerate landmarks: least squares on all points
        matrix, _ = cv2.estimateAffinePartial2D(landmarks.astype(np.float32), template)
    return matrix.astype(np.float64)


def align_face(rgb: np.ndarray, matrix: np.ndarray, size: int) -> np.ndarray:
    """The aligned ``size``² crop of an RGB image (bilinear; outside the image: the border colour)."""
    import cv2

    return cv2.warpAffine(np.ascontiguousarray(rgb[..., :3], dtype=np.float32), matrix, (size, size),
                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=BORDER_RGB)


def paste_face(background: np.ndarray, face: np.ndarray, matrix: np.ndarray, scale: float) -> np.ndarray:
    """Blend a restored crop into ``background`` (the source image upscaled ``scale`` times).

    ``matrix`` maps source pixels to the crop; the crop is mapped back with its inverse, scaled to
    the background (pixel centres: x_bg = scale (x + 0.5) - 0.5).
    """
    import cv2

    bh, bw = background.shape[:2]
    inv = cv2.invertAffineTransform(matrix) * scale
    inv[:, 2] += 0.5 * scale - 0.5
    size = face.shape[0]
    warped = cv2.warpAffine(np.ascontiguousarray(face, dtype=np.float32), inv, (bw, bh), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE)
    mask = cv2.warpAffine(np.ones((size, size), np.float32), inv, (bw, bh), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    area = float(mask.sum())
    if area < 4:
        return background
    edge = max(1, int(area ** 0.5) // 20)  # feather width grows with the face
    kernel = np.ones((2 * edge + 1, 2 * edge + 1), np.uint8)
    mask = cv2.erode((mask > 0.999).astype(np.float32), kernel)
    mask = cv2.GaussianBlur(mask, (0, 0), max(edge / 1.5, 0.5))[..., None]
    return (mask * warped + (1.0 - mask) * background).astype(np.float32)
