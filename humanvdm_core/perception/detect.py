"""Finding the person in a photo: silhouette mask, COCO-17 keypoints, bounding box, warnings.

Contract of :func:`detect_person`:

- Input: a :class:`~humanvdm_core.perception.image.Photo` (or a path, loaded with ``load_photo``).
- ``Detection.mask`` (H, W) float32 in [0, 1], in ``photo.rgb``'s pixels. Source (``mask_source``):
  ``"alpha"`` when the photo's alpha channel is meaningful (1%..99% of the pixels transparent),
  else ``"segmentation"``: MediaPipe Pose's person segmentation, edge-refined with a guided filter
  on the photo (measured better than the selfie-segmentation model on the fixtures; see the
  benchmark), then trimmed of the background it covers (:func:`trim_background`, unless
  ``trim=False``): the segmentation is soft and blurry, so it spans the narrow gaps between the arms
  and the body or between the legs, and a halo along its edge, where the photo shows the wall or the
  floor. ``Detection.untrimmed`` keeps the mask before the trim and ``Detection.fit_mask`` gives it
  to a body fit (its one-sided silhouette term needs only the person's extent, and a gap opened
  between a hand and the hip would push the fitted arm out of the image plane). The
  selfie-segmentation model is used only to count people.
- ``Detection.keypoints`` (17, 2) float32 pixel coordinates (x right, y down, origin at the
  top-left corner of the image, in ``photo.rgb``'s pixels) in :data:`COCO17_NAMES` order, and
  ``confidences`` (17,) float32 in [0, 1]: MediaPipe's visibility, set to 0 for a joint outside the
  frame (its coordinates are then MediaPipe's extrapolated guess). A keypoint is *confident* when its
  confidence is >= :data:`MIN_CONFIDENCE`. "left" is the person's left (on the image's right side
  in a frontal photo).
- ``Detection.world_keypoints`` (17, 3) float32: the same 17 joints in 3D, metres, from MediaPipe's
  ``pose_world_landmarks`` (GHUM), origin at the midpoint of BlazePose's hips, in the camera's axes
  (OpenCV: x right, y down, z forward away from the camera; checked on a frontal photo: the nose has
  negative z, the person's left shoulder positive x, the ankles positive y). Their confidences are
  ``confidences`` (the same visibilities). Only directions and relative depths are meaningful: the
  scale is GHUM's guess and the depth of a limb can be wrong, but it is the only depth cue a single
  photo gives (the body fit uses the bone directions, :mod:`humanvdm_core.body.fit`).
- BlazePose's 33 landmarks map to COCO-17 one to one (:data:`BLAZEPOSE_TO_COCO17`): nose 0,
  eyes 2/5 (the eye centres, not the inner/outer corners), ears 7/8, shoulders 11/12, elbows 13/14,
  wrists 15/16, hips 23/24, knees 25/26, ankles 27/28. BlazePose's hips sit a little higher and
  wider than COCO's annotated hips; hands, heels, feet toes and mouth corners are not used.
- MediaPipe runs on a copy scaled to at most :data:`WORK_SIDE` px on the long side (RGBA photos
  composited over mid-gray first); coordinates and masks are returned at the photo's resolution.
  The person's pose runs twice (:func:`_first_pose`): on that copy, and on it framed in a mid-gray
  border of :data:`FRAME_PAD` of its long side; the framed run is kept where the plain one finds
  nobody or the framed one is at least :data:`FRAME_GAIN` surer (the COCO-17 landmarks' mean
  visibility). MediaPipe misses or misreads a person whose silhouette fills the frame (a cut-out
  cropped to the person's own box) and a figure that shows no face (a helmet); on photos with room
  around the person the two runs agree and the plain one stays.
- ``bbox`` is (x0, y0, x1, y1) in pixels, the box around ``mask > 0.5``.
- Bad inputs:
  * no person: :class:`InputError` "no person found in <file>";
  * more than one person (separate silhouettes each confirmed by a pose run on that silhouette
    alone, or a second pose found once the chosen person is masked out, its torso upright as theirs,
    :data:`OTHER_TORSO_DEG`): by default the person with
    the largest silhouette is kept (for people touching each other, whose silhouettes merge, the one
    MediaPipe's pose detector picked), the mask is restricted to them, and a warning says how many
    people were found; ``refuse_multiple=True`` raises :class:`InputError` instead. Known limit:
    people who overlap heavily (one partly in front of the other) can be taken for one person.
  * body cut off by the frame or not visible: the required joints are both shoulders and both hips
    (:data:`REQUIRED_JOINTS`); if any is missing, :class:`InputError` names the missing joints and
    why (outside the frame / not visible); other missing joints are listed in a warning and in
    ``Detection.missing``, and detection goes on.
  * Notes from loading (e.g. a downscaled huge photo) are copied into ``warnings``.
- Held objects (a bag, a box, a binder held away from the body): MediaPipe's person segmentation
  leaves them out. On a plain background (:func:`background_colours`: at least :data:`PLAIN_SHARE` of
  the photo's border within :data:`BACKGROUND_DISTANCE` of one of at most :data:`BACKGROUND_COLOURS`
  colours: a studio backdrop, or a wall and the floor), whatever differs from those colours, lies
  outside the person's mask, touches it, reaches within
  :data:`HAND_REACH` of the person's height of a wrist (at least :data:`HELD_WRIST_CONFIDENCE` sure: the
  hand that holds it is often hidden by it) and covers at least
  :data:`HELD_MIN_AREA` of the mask is added to the mask, with a warning
  (:func:`held_objects`). Not with an alpha cut-out (the user's mask is the mask) nor on a busy
  background (the object cannot be told from it).
- A photo in which MediaPipe finds nobody (its detector sees the whole frame shrunk, so a person in a
  panorama, or one standing far off in a photo of the street, is too small for it): the search goes on
  in square windows, half overlapping, of the photo's short side (unless the photo is square), then of
  :data:`WINDOW_SCALES` of it (windows of at least :data:`MIN_WINDOW` px of MediaPipe's copy); of the
  largest windows that hold a pose with its torso and the whole of its silhouette, the surest, widened
  to the person's silhouette, is detected as a photo of its own and the result mapped back to the whole
  photo, with a warning that says so (and the person's height in pixels). A person who fills the photo
  is never cut up into windows.
- Runs offline: only MediaPipe's bundled ``pose_landmark_full.tflite`` (``model_complexity=1``),
  ``pose_detection.tflite`` and ``selfie_segmentation.tflite`` are used; nothing is downloaded.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from humanvdm_core.body.model import COCO17_NAMES
from humanvdm_core.perception.image import Photo, load_photo
from humanvdm_core.workflow.errors import HumanVDMError, InputError

# COCO-17 index -> BlazePose landmark index (see the module docstring).
BLAZEPOSE_TO_COCO17: tuple[int, ...] = (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)
REQUIRED_JOINTS: tuple[str, ...] = ("left_shoulder", "right_shoulder", "left_hip", "right_hip")
MIN_CONFIDENCE = 0.5  # a keypoint with confidence >= this is "confident"
WORK_SIDE = 1024  # MediaPipe runs at most at this long side
REFINE_SIDE = 2048  # the guided-filter mask refinement runs at most at this long side
ALPHA_MIN_TRANSPARENT = 0.01  # alpha is "meaningful" when this ..
ALPHA_MAX_TRANSPARENT = 0.99  # .. to this fraction of the pixels is transparent (alpha < 0.5)
MIN_PERSON_AREA = 0.002  # a silhouette smaller than this fraction of the image is not a person
OTHER_PERSON_AREA = 0.2  # another silhouette counts if at least this fraction of the largest one
# a pose found beside the chosen person, in their shared silhouette, counts as another person only if its
# torso (shoulders' centre -> hips' centre) points within this many degrees of the chosen one's: with the
# chosen person hidden, MediaPipe can put a "torso" lying across what its mask of them left out (an
# armoured figure's arm and legs)
OTHER_TORSO_DEG = 45.0
_TORSO = (11, 12, 23, 24)  # BlazePose shoulders and hips
BORDER = 0.02  # the photo's border band (share of the short side) that shows the background
BACKGROUND_DISTANCE = 0.12  # RGB distance within which a pixel has the background's colour
PLAIN_SHARE = 0.9  # the background is plain when at least this share of the border has one of its colours ...
BACKGROUND_COLOURS = 2  # ... of at most this many (a wall and the floor)
HAND_REACH = 0.08  # a held object comes this close to a wrist (share of the person's height) ...
# ... the wrist at least this sure: the hand that holds an object is often hidden by it (a binder held before
# the chest in profile: 0.21), and MediaPipe's guess of it still lies by the object
HELD_WRIST_CONFIDENCE = 0.1
HELD_MIN_AREA = 0.02  # a held object covers at least this share of the person's mask (else: an edge fringe)
SURE_PERSON = 0.97  # the segmentation at least this sure, and TRIM_INNER inside its edge, is the person ...
TRIM_INNER = 0.01  # ... share of the person's height
TRIM_OUTER = 0.02  # the ring outside the mask's edge that GrabCut learns the background from, share of the height
TRIM_LIKELIHOOD = 2.0  # a pixel leaves the mask only where the background explains its colour e^this times better
TRIM_MARGIN = 0.05  # GrabCut runs on the person's box widened by this share of their height ...
TRIM_SIDE = 768  # ... scaled to at most this long side ...
TRIM_ITERATIONS = 4  # ... for this many iterations
FB_MIN = 0.1  # RGB distance between the person's and the background's colours nearby that tells a cut pixel's share
FRAME_PAD = 0.1  # the pose also runs on the photo framed in a border this wide (share of its long side) ...
FRAME_GAIN = 0.05  # ... and that run counts where it is this much surer (mean COCO-17 visibility)
UPRIGHT_TOLERANCE = 30.0  # degrees from a quarter turn within which a person lying across the photo counts
WINDOW_SCALES = (0.5, 1.0 / 3.0)  # nobody found: windows of the short side, then of these shares of it ...
MIN_WINDOW = 160  # ... at least this many pixels of MediaPipe's copy
BOX_MARGIN = 0.1  # person_box: the silhouette's box widened by this share of its larger side
WINDOW_MARGIN = 0.3  # a window's person's silhouette box is widened by this share of its size
WINDOW_CUT = 0.02  # a window cuts its person where the silhouette covers more than this share of an inner edge

_INSTALL = ("pip install --no-deps mediapipe==0.10.21 && pip install absl-py attrs flatbuffers "
            "'protobuf>=4.25.3,<5' matplotlib")


class _NoPerson(InputError):
    """MediaPipe found nobody in the photo (the whole of it)."""


@dataclass
class Detection:
    """The person found in a photo; see the module docstring for the contract."""

    mask: np.ndarray  # (H, W) float32 in [0, 1]
    keypoints: np.ndarray  # (17, 2) float32 pixel x, y in COCO17_NAMES order
    confidences: np.ndarray  # (17,) float32 in [0, 1]; 0 outside the frame
    bbox: tuple[float, float, float, float]  # x0, y0, x1, y1 of mask > 0.5, pixels
    mask_source: str  # "alpha" or "segmentation"
    num_people: int  # people found (the detection describes the largest)
    missing: list[str] = field(default_factory=list)  # COCO joint names that are not confident
    outside: list[str] = field(default_factory=list)  # COCO joint names outside the frame
    warnings: list[str] = field(default_factory=list)  # human-readable
    names: tuple[str, ...] = COCO17_NAMES
    # (17, 3) float32 metres, camera axes (x right, y down, z away), origin at the hip centre; None only
    # when MediaPipe gave no 3D landmarks
    world_keypoints: np.ndarray | None = None
    # (H, W) float32: the mask before trim_background (the same as ``mask`` for an alpha cut-out or with
    # trim=False); None when not given
    untrimmed: np.ndarray | None = None

    @property
    def fit_mask(self) -> np.ndarray:
        """(H, W) float32: the mask a body is fitted to, the person's whole extent (``untrimmed`` when given)."""
        return self.mask if self.untrimmed is None else self.untrimmed

    def confident(self) -> np.ndarray:
        """(17,) bool: which keypoints are confident."""
        return self.confidences >= MIN_CONFIDENCE


@dataclass
class _Pose:
    landmarks: np.ndarray  # (33, 3) x, y in work pixels, visibility
    segmentation: np.ndarray  # (h, w) float32 in [0, 1], work resolution
    world: np.ndarray  # (33, 3) metres, x right, y down, z away from the camera, origin at the hip centre

    def torso_center(self) -> np.ndarray:
        return self.landmarks[list(_TORSO), :2].mean(axis=0)

    def torso_visible(self) -> bool:
        return bool(np.all(self.landmarks[list(_TORSO), 2] >= MIN_CONFIDENCE))

    def torso_axis(self) -> np.ndarray:
        """(2,) unit image direction from the shoulders' centre to the hips' centre."""
        shoulders, hips = self.landmarks[list(_TORSO[:2]), :2].mean(0), self.landmarks[list(_TORSO[2:]), :2].mean(0)
        d = (hips - shoulders).astype(np.float64)
        return d / max(float(np.linalg.norm(d)), 1e-9)

    def visibility(self) -> float:
        """The mean visibility of the COCO-17 landmarks: how sure the pose is of the body as a whole."""
        return float(self.landmarks[list(BLAZEPOSE_TO_COCO17), 2].mean())


def _mediapipe():
    """Import MediaPipe's legacy solutions, or explain how to install them."""
    os.environ.setdefault("GLOG_minloglevel", "2")  # MediaPipe's C++ logging: errors only
    try:
        from mediapipe.python.solutions import pose, selfie_segmentation
    except ImportError as exc:
        raise HumanVDMError(f"person detection needs MediaPipe ({exc}); install it with: {_INSTALL}") from exc
    root = Path(pose.__file__).resolve().parents[2] / "modules"
    for rel in ("pose_landmark/pose_landmark_full.tflite", "pose_detection/pose_detection.tflite",
                "selfie_segmentation/selfie_segmentation.tflite"):
        if not (root / rel).is_file():  # MediaPipe would try to download it: refuse instead
            raise HumanVDMError(f"MediaPipe's bundled model {root / rel} is missing; reinstall with: {_INSTALL}")
    return pose, selfie_segmentation


def _run_pose(pose_model, image: np.ndarray) -> _Pose | None:
    """One pose run on an (h, w, 3) uint8 RGB image; None when nobody is found."""
    result = pose_model.process(image)
    if result.pose_landmarks is None:
        return None
    h, w = image.shape[:2]
    lm = np.array([(p.x * w, p.y * h, p.visibility) for p in result.pose_landmarks.landmark], np.float32)
    lm[:, 2] = np.clip(lm[:, 2], 0.0, 1.0)
    seg = result.segmentation_mask
    seg = np.zeros((h, w), np.float32) if seg is None else np.clip(np.asarray(seg, np.float32), 0.0, 1.0)
    if result.pose_world_landmarks is not None:
        world = np.array([(p.x, p.y, p.z) for p in result.pose_world_landmarks.landmark], np.float32)
    else:
        world = np.full((len(lm), 3), np.nan, np.float32)
    return _Pose(lm, seg, world)


def _run_pose_framed(pose_model, image: np.ndarray, pad: float) -> _Pose | None:
    """:func:`_run_pose` on ``image`` framed in a mid-gray border of ``pad`` of its long side, the result
    in ``image``'s own pixels (landmarks shifted back, segmentation cut back)."""
    h, w = image.shape[:2]
    p = max(1, int(round(pad * max(h, w))))
    found = _run_pose(pose_model, cv2.copyMakeBorder(image, p, p, p, p, cv2.BORDER_CONSTANT, value=(128, 128, 128)))
    if found is None:
        return None
    landmarks = found.landmarks.copy()
    landmarks[:, :2] -= p
    return _Pose(landmarks, np.ascontiguousarray(found.segmentation[p:p + h, p:p + w]), found.world)


def _first_pose(pose_model, image: np.ndarray) -> _Pose | None:
    """The pose of the person in ``image``: of the image as it is, or of the image framed in a border
    (:data:`FRAME_PAD`) where that finds a person the first run missed or sees the body surer by
    :data:`FRAME_GAIN` (:meth:`_Pose.visibility`). MediaPipe misses or misreads people whose silhouette
    fills the frame: a cut-out cropped to the person (missed at 512 and 768 px, misread at 384 px with
    its knees and ankles unseen), a faceless figure."""
    plain = _run_pose(pose_model, image)
    if plain is not None and plain.visibility() + FRAME_GAIN >= 1.0:
        return plain  # no run can be surer by FRAME_GAIN (visibilities are at most 1)
    framed = _run_pose_framed(pose_model, image, FRAME_PAD)
    if framed is not None and (plain is None or framed.visibility() > plain.visibility() + FRAME_GAIN):
        return framed
    return plain


def _grey_out(image: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``image`` with everything where ``keep`` is False replaced by mid-gray."""
    out = image.copy()
    out[~keep] = 128
    return out


def _in_region(region: np.ndarray, xy: np.ndarray) -> bool:
    h, w = region.shape
    x, y = int(round(float(xy[0]))), int(round(float(xy[1])))
    return 0 <= x < w and 0 <= y < h and bool(region[y, x])


def _dilate(mask: np.ndarray, fraction: float) -> np.ndarray:
    r = max(1, int(round(fraction * max(mask.shape))))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(mask.astype(np.uint8), kernel) > 0


def _refine(mask: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """Upsample a coarse (h, w) mask to ``rgb``'s size with a guided filter that follows its edges."""
    h, w = rgb.shape[:2]
    s = min(1.0, REFINE_SIDE / max(h, w))
    rh, rw = max(1, round(h * s)), max(1, round(w * s))
    guide = cv2.resize(rgb, (rw, rh), interpolation=cv2.INTER_AREA) if s < 1 else rgb
    coarse = cv2.resize(mask, (rw, rh), interpolation=cv2.INTER_LINEAR)
    radius = max(2, round(max(rh, rw) / 256))
    fine = cv2.ximgproc.guidedFilter(np.ascontiguousarray(guide, np.float32), coarse.astype(np.float32),
                                     radius, 1e-2)
    fine = np.clip(fine, 0.0, 1.0)
    if (rh, rw) != (h, w):
        fine = cv2.resize(fine, (w, h), interpolation=cv2.INTER_LINEAR)
    return fine.astype(np.float32)


def _gmm_log_likelihood(model: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Log-likelihood (N,) of colours ``x`` (N, 3) under one of OpenCV GrabCut's colour models (1, 65):
    five Gaussians stored as their weights, then their means (5 x 3), then their covariances (5 x 9)."""
    m = model.reshape(-1)
    weights, means, covs = m[:5], m[5:20].reshape(5, 3), m[20:65].reshape(5, 3, 3)
    terms = []
    for w, mu, cov in zip(weights, means, covs, strict=True):
        if w <= 0:
            continue
        cov = cov + np.eye(3) * 1e-2
        d = x - mu
        terms.append(np.log(w) - 0.5 * np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d)
                     - 0.5 * np.log(np.linalg.det(cov)))
    return np.logaddexp.reduce(np.stack(terms), axis=0) if terms else np.full(len(x), -np.inf)


def trim_background(mask: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """``mask`` (H, W) float in [0, 1] with the background it covers taken out; ``rgb`` the photo.

    The mask is sure where it is at least :data:`SURE_PERSON` and :data:`TRIM_INNER` of the person's
    height inside its edge (the person), and far from it (more than :data:`TRIM_OUTER` outside: the
    background). In between, OpenCV's GrabCut (on the person's box widened by :data:`TRIM_MARGIN`, at
    most :data:`TRIM_SIDE` px) learns a colour model of each from the photo and cuts along the photo's
    edges. The mask only shrinks: a pixel is cut where GrabCut says background and the background's
    model explains its colour at least e^:data:`TRIM_LIKELIHOOD` times better than the person's (a light
    garment against a light wall is kept). A cut pixel keeps its share of the person: its colour ``c``
    taken as ``a f + (1 - a) b`` with ``f`` the sure person's and ``b`` the background's mean colour
    nearby (Gaussian weights, sigma :data:`TRIM_OUTER` of the height), so an edge pixel that mixes the
    two keeps alpha ``a``, a gap of wall gets 0; where ``f`` and ``b`` are less than :data:`FB_MIN` apart
    the share cannot be told and the cut stands. Elsewhere the mask is unchanged: the result is
    ``min(mask, kept share)``. Deterministic: OpenCV's generator is seeded before each cut."""
    person = mask > 0.5
    ys, xs = np.nonzero(person)
    if ys.size == 0:
        return mask
    h, w = mask.shape
    height = int(ys.max() - ys.min() + 1)
    pad = int(TRIM_MARGIN * height) + 2
    y0, y1 = max(0, ys.min() - pad), min(h, ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(w, xs.max() + pad + 1)
    crop_rgb, crop_mask = rgb[y0:y1, x0:x1], mask[y0:y1, x0:x1]
    s = min(1.0, TRIM_SIDE / max(crop_rgb.shape[:2]))
    size = (max(1, round(crop_rgb.shape[1] * s)), max(1, round(crop_rgb.shape[0] * s)))
    small_rgb = cv2.resize(crop_rgb, size, interpolation=cv2.INTER_AREA) if s < 1 else crop_rgb
    small = cv2.resize(crop_mask, size, interpolation=cv2.INTER_AREA) if s < 1 else crop_mask
    inside = small > 0.5

    def disc(fraction: float) -> np.ndarray:
        r = max(1, int(fraction * height * s))
        return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))

    sure = (cv2.erode(inside.astype(np.uint8), disc(TRIM_INNER)) > 0) & (small >= SURE_PERSON)
    near = cv2.dilate(inside.astype(np.uint8), disc(TRIM_OUTER)) > 0
    labels = np.full(inside.shape, cv2.GC_BGD, np.uint8)
    labels[near] = cv2.GC_PR_BGD
    labels[inside] = cv2.GC_PR_FGD
    labels[sure] = cv2.GC_FGD
    image = np.ascontiguousarray(np.clip(np.rint(small_rgb * 255.0), 0, 255).astype(np.uint8))
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)  # GrabCut seeds its colour models with k-means on OpenCV's global generator
    cv2.grabCut(image, labels, None, bgd, fgd, TRIM_ITERATIONS, cv2.GC_INIT_WITH_MASK)
    cut = inside & (labels != cv2.GC_FGD) & (labels != cv2.GC_PR_FGD)
    if cut.any():
        colours = image[cut].astype(np.float64)
        clear = _gmm_log_likelihood(bgd, colours) - _gmm_log_likelihood(fgd, colours) >= TRIM_LIKELIHOOD
        cut[cut] = clear
    if not cut.any():
        return mask
    # a cut pixel's share of the person from the colours nearby: c = a f + (1 - a) b (docstring)
    sigma = max(1.0, TRIM_OUTER * height * s)
    colour = small_rgb.astype(np.float32)

    def nearby(sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        weight = cv2.GaussianBlur(sel.astype(np.float32), (0, 0), sigma)
        total = cv2.GaussianBlur(colour * sel[..., None], (0, 0), sigma)
        return total / np.maximum(weight, 1e-6)[..., None], weight

    f, fw = nearby(labels == cv2.GC_FGD)
    b, bw = nearby(~inside)
    fb = f - b
    span = (fb ** 2).sum(-1)
    alpha = np.clip(((colour - b) * fb).sum(-1) / np.maximum(span, 1e-6), 0.0, 1.0)
    told = (span >= FB_MIN ** 2) & (fw > 1e-4) & (bw > 1e-4)
    keep = np.where(cut & told, alpha, np.where(cut, 0.0, 1.0)).astype(np.float32)
    if s < 1:  # only the shares are resized to the full crop: a 12,000-px photo stays in memory bounds
        keep = cv2.resize(keep, (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)
    out = mask.astype(np.float32, copy=True)
    out[y0:y1, x0:x1] = np.minimum(crop_mask, np.clip(keep, 0.0, 1.0))
    return out


def _describe(names: list[str]) -> str:
    return ", ".join(n.replace("_", " ") for n in names)


def background_colours(rgb: np.ndarray) -> np.ndarray | None:
    """The colours (k, 3), k <= :data:`BACKGROUND_COLOURS`, of a photo whose border is (nearly) that
    few colours: the fewest k-means centres of the border's pixels that leave at most
    1 - :data:`PLAIN_SHARE` of them farther than :data:`BACKGROUND_DISTANCE` from every centre; else None."""
    h, w = rgb.shape[:2]
    b = max(1, int(round(BORDER * min(h, w))))
    border = np.concatenate([rgb[:b].reshape(-1, 3), rgb[-b:].reshape(-1, 3),
                             rgb[:, :b].reshape(-1, 3), rgb[:, -b:].reshape(-1, 3)]).astype(np.float32)
    border = border[:: max(1, len(border) // 20000)]
    colour = np.median(border, axis=0, keepdims=True)
    if np.mean(np.linalg.norm(border - colour, axis=1) < BACKGROUND_DISTANCE) >= PLAIN_SHARE:
        return colour.astype(np.float32)
    for k in range(2, BACKGROUND_COLOURS + 1):
        cv2.setRNGSeed(k)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 1e-3)
        _, _, centres = cv2.kmeans(border, k, None, criteria, 3, cv2.KMEANS_PP_CENTERS)
        near = np.linalg.norm(border[:, None] - centres[None], axis=2).min(axis=1) < BACKGROUND_DISTANCE
        if near.mean() >= PLAIN_SHARE:
            return centres.astype(np.float32)
    return None


def held_objects(rgb: np.ndarray, mask: np.ndarray, keypoints: np.ndarray, confidences: np.ndarray) -> np.ndarray:
    """(H, W) bool: what the person holds outside their mask (module docstring); empty when the
    background is not plain or no wrist is detected."""
    none = np.zeros(mask.shape, bool)
    colours = background_colours(rgb)
    person = mask > 0.5
    wrists = [keypoints[i] for i in (9, 10) if confidences[i] >= HELD_WRIST_CONFIDENCE]
    if colours is None or not wrists or not person.any():
        return none
    ys = np.nonzero(person.any(axis=1))[0]
    reach = HAND_REACH * float(ys.max() - ys.min() + 1)
    differs = np.all([np.linalg.norm(rgb - c, axis=2) >= BACKGROUND_DISTANCE for c in colours], axis=0)
    differs = cv2.morphologyEx(differs.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
    candidates = differs & ~person
    n, labels, stats, _ = cv2.connectedComponentsWithStats(candidates.astype(np.uint8), connectivity=8)
    if n <= 1:
        return none
    big = np.nonzero(stats[:, cv2.CC_STAT_AREA] >= HELD_MIN_AREA * person.sum())[0]
    touching = np.unique(labels[_dilate(person, 0.004) & candidates])
    near_hand = np.zeros(mask.shape, np.uint8)
    for x, y in wrists:
        cv2.circle(near_hand, (int(round(float(x))), int(round(float(y)))), int(round(reach)), 1, thickness=-1)
    by_hand = np.unique(labels[(near_hand > 0) & candidates])
    keep = np.intersect1d(np.intersect1d(touching[touching > 0], by_hand[by_hand > 0]), big[big > 0])
    return np.isin(labels, keep) if keep.size else none


def _work_copy(photo: Photo) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """MediaPipe's copy of ``photo``: at most :data:`WORK_SIDE` px, uint8 RGB, an RGBA photo composited
    over mid-gray; its alpha at that size (or None) and whether the alpha is a real cut-out (the mask)."""
    H, W = photo.height, photo.width
    s = min(1.0, WORK_SIDE / max(H, W))
    wh, ww = max(1, round(H * s)), max(1, round(W * s))
    work = cv2.resize(photo.rgb, (ww, wh), interpolation=cv2.INTER_AREA) if s < 1 else photo.rgb
    alpha_ok, alpha_work = False, None
    if photo.alpha is not None:
        transparent = float(np.mean(photo.alpha < 0.5))
        alpha_ok = ALPHA_MIN_TRANSPARENT <= transparent <= ALPHA_MAX_TRANSPARENT
        alpha_work = cv2.resize(photo.alpha, (ww, wh), interpolation=cv2.INTER_AREA) if s < 1 else photo.alpha
        work = work * alpha_work[:, :, None] + 0.5 * (1.0 - alpha_work[:, :, None])
    return np.ascontiguousarray(np.clip(np.rint(work * 255.0), 0, 255).astype(np.uint8)), alpha_work, alpha_ok


def _crop(photo: Photo, box: tuple[int, int, int, int]) -> Photo:
    """``photo``'s pixels in ``box`` (x0, y0, x1, y1) as a photo of its own (same file name and scale)."""
    x0, y0, x1, y1 = box
    alpha = None if photo.alpha is None else photo.alpha[y0:y1, x0:x1]
    size = (max(1, round((x1 - x0) / photo.scale)), max(1, round((y1 - y0) / photo.scale)))
    return Photo(photo.rgb[y0:y1, x0:x1], alpha, photo.path, size, list(photo.notes))


def _windows(height: int, width: int) -> list[tuple[int, int, int]]:
    """The square search windows ``(x0, y0, side)`` of an image, in search order: of its short side
    (when it is not square), then of :data:`WINDOW_SCALES` of it, each size half overlapping and
    reaching the image's far edges; sizes under :data:`MIN_WINDOW` left out."""
    short = min(height, width)
    sides = ([short] if height != width else []) + [round(f * short) for f in WINDOW_SCALES]
    out = []
    for side in sides:
        if side < MIN_WINDOW:
            continue
        step = max(1, side // 2)
        for y0 in sorted({*range(0, height - side + 1, step), height - side}):
            out.extend((x0, y0, side) for x0 in sorted({*range(0, width - side + 1, step), width - side}))
    return out


def _person_window(photo: Photo) -> tuple[int, int, int, int] | None:
    """For a photo in which nobody is found: the box (photo pixels) around the person in the windows of
    :func:`_windows`, size by size from the largest: of the windows of one size that hold a pose with its
    torso and the whole of its silhouette (no more than :data:`WINDOW_CUT` of an edge of the window that is
    not the photo's covered by it), the surest (:meth:`_Pose.visibility`), widened by
    :data:`WINDOW_MARGIN`; None when no window holds one. A person whom no window holds whole (one who
    fills the photo) is not cut up into windows."""
    H, W = photo.height, photo.width
    work, _, _ = _work_copy(photo)
    wh, ww = work.shape[:2]
    mp_pose, _ = _mediapipe()
    best: tuple[float, int, int, int, np.ndarray] | None = None
    with mp_pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=True,
                      min_detection_confidence=0.5) as pose_model:
        for x0, y0, side in _windows(wh, ww):
            if best is not None and side != best[3]:
                break  # a larger window already holds the person
            found = _first_pose(pose_model, np.ascontiguousarray(work[y0:y0 + side, x0:x0 + side]))
            if found is None or not found.torso_visible():
                continue
            seg = found.segmentation > 0.5
            inner = [(x0 > 0, seg[:, 0]), (x0 + side < ww, seg[:, -1]), (y0 > 0, seg[0]), (y0 + side < wh, seg[-1])]
            if not seg.any() or any(edge and line.mean() > WINDOW_CUT for edge, line in inner):
                continue
            if best is None or found.visibility() > best[0]:
                best = (found.visibility(), x0, y0, side, seg)
    if best is None:
        return None
    _, x0, y0, _, seg = best
    ys, xs = np.nonzero(seg)
    pad = WINDOW_MARGIN * max(np.ptp(xs), np.ptp(ys))
    box = np.array([x0 + xs.min() - pad, y0 + ys.min() - pad, x0 + xs.max() + 1 + pad, y0 + ys.max() + 1 + pad])
    box = box * np.array([W / ww, H / wh, W / ww, H / wh])
    return (max(0, int(box[0])), max(0, int(box[1])), min(W, int(np.ceil(box[2]))), min(H, int(np.ceil(box[3]))))


def head_angle_deg(det: Detection) -> float | None:
    """The angle of the line from the detected person's feet (the sure ankles, else knees, else hips) to
    their head (the sure nose, eyes and ears), in degrees clockwise from the photo's up (90: the head to
    the right); None when a part is not sure (:data:`MIN_CONFIDENCE`)."""
    sure = det.confidences >= MIN_CONFIDENCE
    head = [j for j in (0, 1, 2, 3, 4) if sure[j]]
    feet = next(([a, b] for a, b in ((15, 16), (13, 14), (11, 12)) if sure[a] and sure[b]), None)
    if not head or feet is None:
        return None
    v = det.keypoints[head].mean(axis=0) - det.keypoints[feet].mean(axis=0)
    return float(np.degrees(np.arctan2(v[0], -v[1])))


def upright_turns(det: Detection) -> int:
    """The quarter turns counter-clockwise (``np.rot90``'s ``k``, 0..3) that stand the detected person
    upright in the photo: the line from their feet to their head (:func:`head_angle_deg`) lies within
    :data:`UPRIGHT_TOLERANCE` degrees of the photo's right (1), its bottom (2) or its left (3); 0 when
    it points up, lies in between, or a part is not sure. A phone photo whose orientation tag was lost
    shows its person on their side."""
    angle = head_angle_deg(det)
    if angle is None:
        return 0
    k = int(round(angle / 90.0))
    if k % 4 == 0 or abs(angle - 90.0 * k) > UPRIGHT_TOLERANCE:
        return 0
    return k % 4


def person_box(det: Detection, width: int, height: int, margin: float = BOX_MARGIN) -> tuple[int, int, int, int]:
    """The detected person's silhouette box (``det.bbox``) widened by ``margin`` of its larger side on
    every side, within a ``width`` x ``height`` photo: (x0, y0, x1, y1) pixels."""
    x0, y0, x1, y1 = det.bbox
    pad = margin * max(x1 - x0, y1 - y0)
    return (max(0, int(x0 - pad)), max(0, int(y0 - pad)), min(width, int(np.ceil(x1 + pad))),
            min(height, int(np.ceil(y1 + pad))))


def stands_upright(det: Detection) -> bool:
    """The detected person's feet-to-head line (:func:`head_angle_deg`) lies within
    :data:`UPRIGHT_TOLERANCE` degrees of the photo's up."""
    angle = head_angle_deg(det)
    return angle is not None and abs(angle) <= UPRIGHT_TOLERANCE


def detect_person(photo: Photo | str | Path, *, refuse_multiple: bool = False, trim: bool = True) -> Detection:
    """Find the person in ``photo``: mask, COCO-17 keypoints, bbox, warnings (module docstring);
    ``trim=False`` keeps the segmentation's mask as it is (no :func:`trim_background`)."""
    if not isinstance(photo, Photo):
        photo = load_photo(photo)
    try:
        return _detect(photo, refuse_multiple, trim)
    except _NoPerson:
        box = _person_window(photo)
        if box is None:
            raise
    det = detect_person_in(photo, box, refuse_multiple=refuse_multiple, trim=trim)
    x0, y0, x1, y1 = box
    det.warnings.append(f"the person fills little of the photo {photo.name} ({det.bbox[3] - det.bbox[1]:.0f} px "
                        f"tall); found in the part x {x0}-{x1}, y {y0}-{y1} px (people elsewhere in it are not counted)")
    return det


def detect_person_in(photo: Photo, box: tuple[int, int, int, int], *, refuse_multiple: bool = False,
                     trim: bool = True) -> Detection:
    """:func:`detect_person` run on the part ``box`` (x0, y0, x1, y1 pixels) of ``photo`` alone, the result
    in the whole photo's pixels (mask zero outside the box)."""
    x0, y0, x1, y1 = box
    det = _detect(_crop(photo, box), refuse_multiple, trim)
    mask = np.zeros((photo.height, photo.width), np.float32)
    mask[y0:y1, x0:x1] = det.mask
    untrimmed = np.zeros_like(mask)
    untrimmed[y0:y1, x0:x1] = det.untrimmed
    bx0, by0, bx1, by1 = det.bbox
    det.mask, det.untrimmed, det.bbox = mask, untrimmed, (bx0 + x0, by0 + y0, bx1 + x0, by1 + y0)
    det.keypoints = (det.keypoints + np.array([x0, y0], np.float32)).astype(np.float32)
    return det


def _detect(photo: Photo, refuse_multiple: bool, trim: bool) -> Detection:
    mp_pose, mp_selfie = _mediapipe()
    H, W = photo.height, photo.width
    warnings = list(photo.notes)
    work, alpha_work, alpha_ok = _work_copy(photo)
    wh, ww = work.shape[:2]

    no_person = InputError(f"no person found in {photo.name}: use a photo showing one person, "
                           "standing, from the hips up at least (a full-body photo works best)")
    with mp_pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=True,
                      min_detection_confidence=0.5) as pose_model, \
            mp_selfie.SelfieSegmentation(model_selection=0) as selfie_model:
        first = _first_pose(pose_model, work)
        if first is None:
            raise _NoPerson(str(no_person))
        # Everyone's silhouette, to count people: the alpha, or selfie segmentation plus the pose's mask.
        if alpha_ok:
            everyone = alpha_work > 0.5
        else:
            selfie = np.asarray(selfie_model.process(work).segmentation_mask, np.float32)
            everyone = np.maximum(selfie, first.segmentation) > 0.5
        _, labels, stats, _ = cv2.connectedComponentsWithStats(everyone.astype(np.uint8), connectivity=8)
        areas = stats[1:, cv2.CC_STAT_AREA]
        if areas.size == 0:
            raise no_person
        order = [int(i) + 1 for i in np.argsort(-areas)]
        big = [c for c in order if stats[c, cv2.CC_STAT_AREA] >= max(MIN_PERSON_AREA * wh * ww,
                                                                     OTHER_PERSON_AREA * areas.max())]
        if not big:
            raise no_person
        chosen_region = labels == big[0]
        person = first
        if len(big) > 1 and not _in_region(chosen_region, first.torso_center()):
            # The pose landed on someone else: run it again on the largest silhouette only.
            again = _run_pose(pose_model, _grey_out(work, _dilate(chosen_region, 0.02)))
            if again is not None:
                person = again
            else:  # keep the person the pose found, with their own silhouette
                big.sort(key=lambda c: not _in_region(labels == c, first.torso_center()))
                chosen_region = labels == big[0]
        # Other separate silhouettes count as people when a pose confirms them.
        others = 0
        counted = np.zeros_like(chosen_region)
        for c in big[1:4]:
            region = _dilate(labels == c, 0.02)
            other = _run_pose(pose_model, _grey_out(work, region))
            if other is not None and _in_region(region, other.torso_center()):
                others += 1
                counted |= region
        # People touching the chosen one share its silhouette: look again with the chosen one hidden.
        chosen_person = _dilate(person.segmentation > 0.5, 0.01) & ~counted
        hidden = _grey_out(work, ~(chosen_person | counted))
        extra = _run_pose(pose_model, hidden)
        if (extra is not None and extra.torso_visible() and _in_region(everyone, extra.torso_center())
                and not _in_region(chosen_person, extra.torso_center())
                and float(extra.torso_axis() @ person.torso_axis()) >= np.cos(np.radians(OTHER_TORSO_DEG))):
            others += 1

    num_people = 1 + others
    if num_people > 1:
        if refuse_multiple:
            raise InputError(f"{photo.name} shows {num_people} people; use a photo of one person "
                             "(or crop it to one person)")
        warnings.append(f"{photo.name} shows {num_people} people; using the largest one only")

    # Mask at full resolution, restricted to the chosen person when there are several.
    if alpha_ok:
        mask = untrimmed = photo.alpha.astype(np.float32, copy=True)
        source = "alpha"
    else:
        untrimmed = _refine(person.segmentation, photo.rgb)
        mask = trim_background(untrimmed, photo.rgb) if trim else untrimmed
        source = "segmentation"
    if len(big) > 1:
        keep = cv2.resize(_dilate(chosen_region, 0.01).astype(np.uint8), (W, H),
                          interpolation=cv2.INTER_NEAREST) > 0
        mask = np.where(keep, mask, 0.0).astype(np.float32)
        untrimmed = np.where(keep, untrimmed, 0.0).astype(np.float32)
    # Keypoints in photo pixels; joints outside the frame get confidence 0.
    lm = person.landmarks[list(BLAZEPOSE_TO_COCO17)]
    keypoints = (lm[:, :2] / np.array([ww / W, wh / H], np.float32)).astype(np.float32)
    inside = (keypoints[:, 0] >= 0) & (keypoints[:, 0] < W) & (keypoints[:, 1] >= 0) & (keypoints[:, 1] < H)
    confidences = np.where(inside, lm[:, 2], 0.0).astype(np.float32)
    if not alpha_ok:
        held = held_objects(photo.rgb, mask, keypoints, confidences)
        if held.any():
            mask = np.where(held, 1.0, mask).astype(np.float32)
            untrimmed = np.where(held, 1.0, untrimmed).astype(np.float32)
            warnings.append(f"{photo.name}: something the person holds lies outside their outline "
                            f"({held.sum() / max(1.0, float((mask > 0.5).sum())):.0%} of it); kept as part of "
                            "them, its depth guessed")

    ys, xs = np.nonzero(mask > 0.5)
    if xs.size < MIN_PERSON_AREA * H * W:
        raise no_person
    bbox = (float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1))
    world = person.world[list(BLAZEPOSE_TO_COCO17)].astype(np.float32)
    world = world if np.all(np.isfinite(world)) else None  # MediaPipe gave 2D landmarks only (not seen)
    outside = [n for n, ok in zip(COCO17_NAMES, inside, strict=True) if not ok]
    missing = [n for n, c in zip(COCO17_NAMES, confidences, strict=True) if c < MIN_CONFIDENCE]
    required_missing = [n for n in REQUIRED_JOINTS if n in missing]
    if required_missing:
        cut = [n for n in required_missing if n in outside]
        hidden_joints = [n for n in required_missing if n not in outside]
        why = []
        if cut:
            why.append(f"{_describe(cut)} outside the photo (cut off by the frame)")
        if hidden_joints:
            why.append(f"{_describe(hidden_joints)} not visible")
        raise InputError(f"too little of the body is visible in {photo.name}: {'; '.join(why)}. "
                         "Both shoulders and both hips must be visible; a full-body photo works best.")
    if outside:
        warnings.append(f"part of the body is outside {photo.name} (cut off by the frame): "
                        f"{_describe(outside)}; the body fit will have to guess them")
    low = [n for n in missing if n not in outside]
    if low:
        warnings.append(f"not clearly visible in {photo.name}: {_describe(low)}")
    return Detection(mask=mask, keypoints=keypoints, confidences=confidences, bbox=bbox, mask_source=source,
                     num_people=num_people, missing=missing, outside=outside, warnings=warnings,
                     world_keypoints=world, untrimmed=untrimmed)
