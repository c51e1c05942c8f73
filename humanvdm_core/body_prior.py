"""The ``body-prior`` backend of the ``diffuse`` stage: a photo -> an orbit of the person, WITHOUT a
learned video model.

This is a deterministic, geometric STAND-IN for the learned multi-view prior (SV3D, fine-tuned on
humans; paper section 3.1). It keeps the pipeline runnable end to end on a CPU and gives the later
stages a frame set in exactly the contract the learned backend will produce. Its unseen views are
rendered from a clothed proxy of the person (the photo's silhouette given depth and thickness), not
learned: plausible in shape, plain in colour.

Contract of :func:`synthesize_orbit` (``photo_path`` -> ``(frames, cameras)``):

1. Input view (:func:`prepare_input_view`, SV3D-style preprocessing): the photo is loaded and the
   person detected (:func:`humanvdm_core.perception.detect_person`; :class:`InputError` when there is
   no usable person); a person lying across the photo (on their side or upside down:
   :func:`humanvdm_core.perception.detect.upright_turns`, a photo whose orientation was lost) is stood
   upright by turning the photo in quarter turns, with a warning, when the turned photo's own detection
   stands upright (:func:`humanvdm_core.perception.detect.stands_upright`); a pose misread across a
   person who stands upright is not confirmed: the photo stays as it is, and the person's keypoints are
   detected again within their own box (:func:`~humanvdm_core.perception.detect.person_box`), where the
   detector reads them standing. The photo is scaled so the person's bounding box spans ``fill`` of the frame
   height (or 0.95 of its width if that is smaller), the box centre is moved to the frame centre,
   and the result is composited over ``background`` through the person mask: a ``size``² RGBA image
   (A = the mask) plus the keypoints in its pixels, and what lies past an edge of the photo that cuts
   the person off (at the knees, at the thighs) marked unseen (:func:`beyond_the_frame`): the fit's
   silhouette says nothing there. ``fill`` is the orbit's framing: a subject
   :data:`SUBJECT_HEIGHT` tall at the origin spans ``fill`` of the frame at the orbit radius
   (:func:`humanvdm_core.scans.framing_radius`).
2. Cameras: ``orbit_cameras(num_frames, size, FOV_DEG, elevation, framing_radius(...))`` (the
   SV3D_p orbit; the last frame, azimuth 0, is the input view); ``extra["background"]`` and
   ``extra["fill"]`` are set. ``elevation`` is ``elevation_deg``, raised for a photo taken from above
   (``raise_from_above``, :func:`orbit_elevation`: MediaPipe's 3D body, torso and legs, leaning towards
   the camera further than people photographed from ``elevation_deg`` show it), with a warning.
3. Facing (:func:`humanvdm_core.perception.facing.estimate_facing`: a face found, the left/right
   order of shoulders and hips, MediaPipe's 3D nose vs ears): a photo taken from behind is built
   facing away from the camera and says so in a warning; a doubtful case is assumed to face the
   camera, with a warning. A face found while the pose model's left/right order and its 3D depth both
   read a back (:attr:`~humanvdm_core.perception.facing.Facing.mirrored`: it mirrored the whole skeleton,
   as it can for a person turned with raised arms) has its keypoints set right before the fit
   (:func:`~humanvdm_core.perception.facing.unmirrored`), else the body turns the wrong way. A person the
   fit shows in profile (the shoulders' line turned at least :data:`PROFILE_DEG` out of the image plane,
   :func:`~humanvdm_core.body.landmarks.shoulder_turn_deg`) gets a warning that says so instead: their
   front and back are seen edge-on and both are guessed.
4. Body: Anny is fitted to the input view alone (:func:`humanvdm_core.body.fit.fit_body` with the
   azimuth-0 camera and one observation: 2D keypoints, MediaPipe's 3D world landmarks as bone
   directions, the mask one-sided so clothing never stretches the body, the torso leaning no further
   than the landmarks show (a lean of theirs under 10 deg counts as upright, under 15 deg backwards when the
   person is not seated), an arm held out to the
   side kept in the body's plane, a hand the photo shows on the head touching it, a person standing
   still kept on straight legs with the feet below the hips and, upright and its face not bowed
   (:attr:`humanvdm_core.perception.facing.Facing.bowed`), the head over the shoulders). An arm whose 2D keypoints the detector's
   own in-plane 3D landmarks contradict (far shorter: :func:`humanvdm_core.body.landmarks.arms_read_short`,
   armour or a drawn figure) is first redrawn along those landmarks (:func:`~humanvdm_core.body.landmarks.rebuild_arms`),
   with a warning.
5. Geometry ``clothed`` (default): the clothed proxy (:func:`humanvdm_core.clothed_proxy.build_clothed_proxy`)
   -- a closed surface whose input view is the person's whole mask, the body's depth carried out to
   the silhouette and inflated where the body does not reach (loose clothing, hair, hats, held
   objects), textured with the photo on the seen side and, on the unseen side, each body part's own
   visible colour, print-free, hair on the back of the head (in profile the head's far side is
   its near side mirrored). Geometry ``body`` (the ablation): the
   naked body coloured per vertex (:func:`colour_body`: seen vertices from the photo, hidden ones
   mirrored from the front, hair on the back of the head).
6. Centring: the proxy (and the fitted joints) are scaled about the input camera's centre so that the
   middle of the proxy's bounding box lies on the orbit's axis (:func:`centring_transform`): the
   input view does not change, and the orbit turns about the person's middle -- as SV3D's orbits and
   the scans' renders do -- whatever size the fit gave the body (a seated person's knees no longer
   swing round an axis through their back).
7. Frames: the proxy rendered at every orbit camera over ``background`` (RGBA, A = coverage); the
   azimuth-0 frame is then REPLACED by the preprocessed input view itself, so the input view is exact.
8. Warnings (``BodyProxy.warnings``, each naming the photo): what the stand-in had to guess -- legs or
   hands hidden, a seated pose (the seat is not in the mask), a hand on the head (placed touching it;
   its arm then keeps its fitted depth in the proxy), a forearm reaching towards or away from
   the camera (its depth, and what it holds), an arm the pose model read short, much of the silhouette
   outside the body, the facing --
   plus the detector's own (e.g. a second person).

``frames`` is (N, size, size, 4) float32 (RGB sRGB values over ``background``), ``cameras`` a
:class:`~humanvdm_core.cameras.Cameras`. Deterministic: same photo and arguments, same output (on one
machine). Known limits: the proxy is 2.5D (one front and one back surface per input-view pixel), so
what the photo hides between a limb and the torso is filled; the unseen side is plain (no folds, no
print, no face); the limbs' depth is a single-view estimate.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from humanvdm_core.body.landmarks import shoulder_turn_deg
from humanvdm_core.body.model import COCO17_NAMES
from humanvdm_core.cameras import Cameras, orbit_cameras, project_points, sample_bilinear
from humanvdm_core.clothed_proxy import ClothedProxy
from humanvdm_core.image_fill import nearest_fill
from humanvdm_core.perception.detect import MIN_CONFIDENCE
from humanvdm_core.proxy_colours import hair_colour
from humanvdm_core.scans import TexturedMesh, framing_radius

log = logging.getLogger("humanvdm.body_prior")

FOV_DEG = 33.8  # SV3D_p's vertical field of view
SUBJECT_HEIGHT = 1.7  # the framing assumes a subject this tall (world units) at the origin
DEFAULT_FILL = 0.85
MAX_WIDTH_FILL = 0.95  # a wide pose (arms out) may span at most this fraction of the frame width
EDGE_TOUCH_PX = 2  # the person's mask touches an edge of the photo with at least this many pixels (beyond_the_frame)
DEPTH_TOLERANCE = 0.02  # world units: a vertex this close behind the rendered surface is visible
MAX_CENTRING_SCALE = 1.5  # centring_transform scales the proxy by at most this (or its inverse)
HEAD_JOINTS = ("head", "eye.L", "eye.R")
BOUNDARY_SMOOTHING = 3  # neighbour-average passes on the visible/hidden weight
BACK_SMOOTHING = 2  # neighbour-average passes on the hidden vertices' colours
# A photo from above (orbit_elevation): the detector's 3D body tilting towards the camera beyond
FROM_ABOVE_TILT_DEG = 20.0  # this (standing) ...
SEATED_TILT_DEG = 12.0  # ... or this (seated: its 3D thighs lean back THIGHS_AT_CAMERA_DEG or more) ...
THIGHS_AT_CAMERA_DEG = 30.0
RAISE_PER_TILT = 2.5  # ... raises the orbit by this many degrees per degree beyond it ...
MAX_RAISE_DEG = 20.0  # ... by at most this, and, standing, only where the photo foreshortens the legs at least
LEGS_FORESHORTENED = 0.95  # this much as the torso (foreshortening(): a bow foreshortens the torso instead)


@dataclass
class InputView:
    """The preprocessed input view: ``rgba`` (S, S, 4) float32 (RGB over the background, A = mask),
    ``keypoints`` (17, 2) pixels and ``confidences`` (17,) in its pixels, the scale applied to the photo."""

    rgba: np.ndarray
    keypoints: np.ndarray
    confidences: np.ndarray
    scale: float
    warnings: list[str] = field(default_factory=list)
    world_keypoints: np.ndarray | None = None  # (17, 3) MediaPipe's 3D joints, metres, camera axes
    # (S, S) float32: the mask the body is fitted to (:attr:`humanvdm_core.perception.Detection.fit_mask`,
    # the segmentation before its trim); None: the same as ``mask``
    fit_mask: np.ndarray | None = None
    # (S, S) bool: pixels past an edge of the photo that cuts the person off (see beyond_the_frame); None: none
    unseen: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        return self.rgba[..., 3]


@dataclass
class BodyProxy:
    """A coloured body fitted to one photo, with the orbit it is rendered along."""

    input_view: InputView
    mesh: TexturedMesh  # posed body with vertex colours, in the orbit's world
    cameras: Cameras  # the orbit (extra: background, fill)
    front_index: int  # the orbit frame at azimuth 0 (the input view)
    background: tuple[float, float, float]
    reprojection_px: float  # mean keypoint reprojection error of the single-view fit
    warnings: list[str] = field(default_factory=list)
    clothed: ClothedProxy | None = None  # the clothed proxy the orbit is rendered from (geometry "clothed")
    facing_away: bool = False  # the photo shows the person's back
    coco17: np.ndarray | None = None  # (17, 3) the fitted body's COCO joints in the orbit's world

    def render(self, cameras: Cameras | None = None) -> np.ndarray:
        """(N, H, W, 4) float32 renders of the coloured body (default: the orbit), no replacement."""
        from humanvdm_core.render import render_views

        return render_views(self.mesh, self.cameras if cameras is None else cameras, self.background).rgba

    def orbit_frames(self) -> np.ndarray:
        """The orbit's frames with the azimuth-0 frame replaced by the input view (contract step 7)."""
        frames = self.render()
        frames[self.front_index] = self.input_view.rgba
        return frames


def resolve_photo(path: str | Path) -> Path:
    """The photo a ``photo`` artifact names: the file itself, or a folder's ``input.*`` (else its one file)."""
    from humanvdm_core.workflow.errors import InputError

    path = Path(path)
    if path.is_file():
        return path
    if not path.is_dir():
        raise InputError(f"photo not found: {path}")
    candidates = sorted(p for p in path.glob("input.*") if p.is_file())
    if not candidates:
        candidates = sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
    if len(candidates) != 1:
        raise InputError(f"photo folder {path} must hold one photo (input.<ext>); found {len(candidates)} files")
    return candidates[0]


def beyond_the_frame(mask: np.ndarray, keypoints: np.ndarray, box: tuple[float, float, float, float],
                     size: int) -> np.ndarray:
    """(size, size) bool: the pixels past each edge of the photo that cuts the person off -- their
    ``mask`` (the photo's pixels) touches it with at least :data:`EDGE_TOUCH_PX` pixels and one of the
    detector's ``keypoints`` (17, 2, the photo's pixels; a joint outside the photo has the detector's
    guess) lies past it -- where the photo, placed at ``box`` (x0, y0, x1, y1, pixels of the ``size``²
    frame), ends: the person goes on there unseen. A photo cropped tight around the whole person
    touches its edges with every joint inside: nothing is unseen."""
    person = mask > 0.5
    h, w = person.shape
    x, y = keypoints[:, 0], keypoints[:, 1]
    x0, y0, x1, y1 = box
    centres = np.arange(size) + 0.5
    cols, rows = centres[None, :], centres[:, None]
    out = np.zeros((size, size), bool)
    for edge, joint_past, past in ((person[:, 0], x < 0, cols < x0), (person[0], y < 0, rows < y0),
                                   (person[:, -1], x >= w, cols > x1), (person[-1], y >= h, rows > y1)):
        if edge.sum() >= EDGE_TOUCH_PX and joint_past.any():
            out |= np.broadcast_to(past, out.shape)
    return out


def prepare_input_view(photo_path: str | Path, size: int, fill: float = DEFAULT_FILL,
                       background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> InputView:
    """Load and detect the person, then crop/scale/centre/composite (contract step 1)."""
    from humanvdm_core.perception import detect_person, load_photo
    from humanvdm_core.perception.detect import detect_person_in, person_box, stands_upright, upright_turns
    from humanvdm_core.perception.image import turned

    photo = load_photo(resolve_photo(photo_path))
    det = detect_person(photo)
    turns = upright_turns(det)
    if turns:  # the person lies across the photo: stand them up (a photo whose orientation tag was lost) --
        # if the turned photo's own detection confirms it
        turned_photo = turned(photo, turns)
        turned_det = detect_person(turned_photo)
        if not stands_upright(turned_det):  # a pose misread across a person who stands: their pose again
            turns = 0                       # from their own box, where the detector reads them standing
            again = detect_person_in(photo, person_box(det, photo.width, photo.height))
            if stands_upright(again):
                det = replace(det, keypoints=again.keypoints, confidences=again.confidences,  # the mask stays
                              world_keypoints=again.world_keypoints, missing=again.missing, outside=again.outside,
                              num_people=again.num_people, warnings=again.warnings)  # as read in the box
    if turns:
        photo, det = turned_photo, turned_det
        seen, how = {1: ("on their side, the head to the right", "90 deg counter-clockwise"), 2: ("upside down", "180 deg"),
                     3: ("on their side, the head to the left", "90 deg clockwise")}[turns]
        det.warnings.insert(0, f"{photo.name} shows the person {seen}: the photo is turned {how} so they stand "
                               "upright (its orientation was lost?); someone who really lies down is built standing")
    x0, y0, x1, y1 = det.bbox
    scale = min(fill * size / max(y1 - y0, 1.0), MAX_WIDTH_FILL * size / max(x1 - x0, 1.0))
    rgb = photo.rgb
    h, w = rgb.shape[:2]
    new_w, new_h = max(1, round(w * scale)), max(1, round(h * scale))
    interp = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_LINEAR
    rgb = cv2.resize(rgb, (new_w, new_h), interpolation=interp)
    sx, sy = new_w / w, new_h / h  # the scale actually applied per axis (rounding)
    cx, cy = 0.5 * (x0 + x1) * sx, 0.5 * (y0 + y1) * sy
    shift = np.array([[1.0, 0.0, size / 2.0 - cx], [0.0, 1.0, size / 2.0 - cy]])
    rgb = cv2.warpAffine(rgb, shift, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def framed(m: np.ndarray) -> np.ndarray:
        m = cv2.resize(m.astype(np.float32), (new_w, new_h), interpolation=interp)
        m = cv2.warpAffine(m, shift, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=0.0)
        return np.clip(m, 0.0, 1.0)

    mask = framed(det.mask)
    fit_mask = None if det.fit_mask is det.mask else framed(det.fit_mask)
    unseen = beyond_the_frame(det.fit_mask, det.keypoints, (shift[0, 2], shift[1, 2], shift[0, 2] + new_w,
                                                            shift[1, 2] + new_h), size)
    bg = np.asarray(background, np.float32)
    rgba = np.empty((size, size, 4), np.float32)
    rgba[..., :3] = np.clip(rgb, 0.0, 1.0) * mask[..., None] + bg * (1.0 - mask[..., None])
    rgba[..., 3] = mask
    keypoints = det.keypoints.astype(np.float64) * np.array([sx, sy]) + shift[:, 2]
    return InputView(rgba=rgba, keypoints=keypoints.astype(np.float32),
                     confidences=det.confidences.astype(np.float32), scale=float(scale),
                     warnings=list(det.warnings), world_keypoints=det.world_keypoints, fit_mask=fit_mask,
                     unseen=unseen if unseen.any() else None)


# ----------------------------------------------------------------------------- colouring helpers

def _lookup(image: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Nearest-pixel values of ``image`` (H, W[, C]) at pixel coordinates ``px`` (V, 2), clamped inside."""
    h, w = image.shape[:2]
    col = np.clip(np.floor(px[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor(px[:, 1]).astype(np.int64), 0, h - 1)
    return image[row, col]


def fill_from_nearest(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A copy of ``rgb`` whose pixels outside the (slightly eroded) person mask take the colour of the
    nearest person pixel, so samples near the silhouette never pick up the background."""
    person = mask > 0.5
    inner = cv2.erode(person.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    if inner.sum() >= 16:
        person = inner
    return nearest_fill(rgb, person)


def _smooth(values: np.ndarray, faces: np.ndarray, passes: int, update: np.ndarray | None = None) -> np.ndarray:
    """``passes`` rounds of averaging each vertex with its mesh neighbours (only ``update`` vertices change)."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.concatenate([edges, edges[:, ::-1]])
    out = values.astype(np.float64, copy=True)
    counts = np.bincount(edges[:, 0], minlength=len(values)).astype(np.float64) + 1.0
    shape = (-1,) + (1,) * (out.ndim - 1)
    for _ in range(passes):
        acc = out.copy()
        np.add.at(acc, edges[:, 0], out[edges[:, 1]])
        new = acc / counts.reshape(shape)
        out = new if update is None else np.where(update.reshape(shape), new, out)
    return out


def colour_body(vertices: np.ndarray, faces: np.ndarray, camera: Cameras, image: np.ndarray, mask: np.ndarray,
                head_weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex colours (V, 3) of a body seen in one view (contract step 5) and the visibility (V,) bool.

    ``camera`` holds one camera; ``image`` (H, W, 3) and ``mask`` (H, W) are that view's photo and
    person mask; ``head_weight`` (V,) in [0, 1] marks the head (None: no hair handling)."""
    from humanvdm_core.render import render_views

    v = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    depth = render_views(TexturedMesh(v.astype(np.float32), faces), camera, (0.0, 0.0, 0.0), samples=1).depth[0]
    depth = np.where(depth > 0, depth, np.inf)
    px, z = project_points(v, camera.w2c[0], camera.K[0])
    visible = z <= _lookup(depth, px) + DEPTH_TOLERANCE

    filled = fill_from_nearest(image, mask)
    front = sample_bilinear(filled, px)

    # the front point at the same world (x, y): z_front by two fixed-point steps on the rendered depth
    c2w, K_inv = camera.c2w[0], np.linalg.inv(camera.K[0])
    z_front = v[:, 2].copy()
    mirror_px = px
    for _ in range(2):
        q = np.stack([v[:, 0], v[:, 1], z_front], axis=1)
        q_px, _ = project_points(q, camera.w2c[0], camera.K[0])
        d = _lookup(depth, q_px)
        hit = np.isfinite(d)
        rays = np.concatenate([q_px, np.ones((len(q_px), 1))], axis=1) @ K_inv.T
        surface = (rays * np.where(hit, d, 0.0)[:, None]) @ c2w[:3, :3].T + c2w[:3, 3]
        z_front = np.where(hit, np.maximum(surface[:, 2], v[:, 2]), z_front)
        mirror_px = np.where(hit[:, None], q_px, mirror_px)
    back = sample_bilinear(filled, mirror_px)

    if head_weight is not None and np.any(head_weight > 0.5):
        hair = hair_colour(image, mask, px[head_weight > 0.5])
        if hair is not None:
            hw = np.clip(head_weight, 0.0, 1.0)[:, None]
            back = hw * hair[None] + (1.0 - hw) * back

    seen = _smooth(visible.astype(np.float64), faces, BOUNDARY_SMOOTHING)[:, None]
    colours = seen * front + (1.0 - seen) * back
    colours = _smooth(colours, faces, BACK_SMOOTHING, update=~visible)
    return np.clip(colours, 0.0, 1.0).astype(np.float32), visible


# ----------------------------------------------------------------------------- the backend

GEOMETRIES = ("clothed", "body")  # what the orbit is rendered from: the clothed proxy, or the naked body (ablation)
LOOSE_FRACTION = 0.8  # the body covering less of the silhouette than this: clothing/hair/objects are guessed
HIDDEN_CONFIDENCE = MIN_CONFIDENCE  # a keypoint less sure than the detector's "confident" is hidden
SEATED_THIGH_DEG = 50.0  # both thighs this far from vertical: a seated (or crouching) pose
REACH_DEG = 45.0  # a fitted forearm this far out of the photo's plane reaches towards (or away from) the camera
FOREARMS = {"left": (7, 9), "right": (8, 10)}  # COCO-17 elbow, wrist per side (the person's own)
PROFILE_DEG = 60.0  # the fitted shoulders' line this far out of the image plane: the person is in profile


def _ankles_hidden(confidences: np.ndarray) -> bool:
    """Both ankles inside the photo but not seen (a long dress or coat; :func:`_hidden_joints`)."""
    return {15, 16} <= _hidden_joints(confidences)


def reaching_forearms(coco17: np.ndarray, w2c: np.ndarray) -> list[tuple[str, float]]:
    """The forearms of the fitted body's COCO joints ``coco17`` (17, 3, world) that point at least
    :data:`REACH_DEG` out of the image plane of the camera ``w2c`` (4, 4): ``("left" | "right"`` (the
    person's own), the angle in degrees, positive towards the camera``)``. Such an arm is held before the
    body (a cup, a binder, a hand pointing at the camera) or behind it, and a single photo does not show
    how far it reaches. Hanging forearms come out 8-39 deg towards the camera (MediaPipe's lean), an
    arm holding a binder against the chest 48-52."""
    out = []
    rotation = np.asarray(w2c, np.float64)[:3, :3]
    for side, (elbow, wrist) in FOREARMS.items():
        forearm = (np.asarray(coco17[wrist], np.float64) - coco17[elbow]) @ rotation.T  # camera axes, +z away
        length = float(np.linalg.norm(forearm))
        if length < 1e-6:
            continue
        angle = float(np.degrees(np.arcsin(np.clip(-forearm[2] / length, -1.0, 1.0))))
        if abs(angle) >= REACH_DEG:
            out.append((side, angle))
    return out


def _pose_warnings(name: str, view: InputView, coco17: np.ndarray, w2c: np.ndarray | None = None,
                   on_head: tuple[str, ...] = ()) -> list[str]:
    """What the photo cannot tell the stand-in, from the detections and the fitted body's COCO joints
    (17, 3; world, Y up): hidden legs or hands, a seated pose, the hands ``on_head`` (``"left"`` /
    ``"right"``, placed touching it) and, with the input camera ``w2c``, any other forearm reaching
    towards or away from the camera (:func:`reaching_forearms`)."""
    out = []
    conf = view.confidences
    hidden_ids = _hidden_joints(conf)
    hidden_legs = []
    for joint, (left, right) in (("knee", (13, 14)), ("ankle", (15, 16))):
        hidden = [side for side, i in (("left", left), ("right", right)) if i in hidden_ids]
        if hidden:
            hidden_legs.append(f"{joint}s" if len(hidden) == 2 else f"{hidden[0]} {joint}")
    if hidden_legs:
        verb = "is" if len(hidden_legs) == 1 and not hidden_legs[0].endswith("s") else "are"
        out.append(f"{name}: the {' and '.join(hidden_legs)} {verb} hidden (behind the other leg, or under a long "
                   "dress or coat): the legs' pose is guessed")
    if hidden_ids & {9, 10}:
        out.append(f"{name}: a hand is hidden (behind the body or in a pocket): its pose is guessed")
    thighs = coco17[[13, 14]] - coco17[[11, 12]]
    angle = np.degrees(np.arccos(np.clip(-thighs[:, 1] / np.maximum(np.linalg.norm(thighs, axis=1), 1e-9), -1, 1)))
    if np.all(angle > SEATED_THIGH_DEG):
        out.append(f"{name}: the person is seated or crouching (thighs {angle.min():.0f}-{angle.max():.0f} deg from "
                   "vertical): the seat is not in the photo's mask, so the person floats; what is under them is guessed")
    for side in on_head:
        out.append(f"{name}: the {side} hand is on the head (the face, an ear or the hair): placed touching it; the "
                   "photo does not show whether it touches, and the forearm's depth follows from that guess")
    for side, angle in reaching_forearms(coco17, w2c) if w2c is not None else []:
        # a hidden hand has its own warning, a hand on the head the one above
        if view.confidences[FOREARMS[side][1]] >= HIDDEN_CONFIDENCE and side not in on_head:
            out.append(f"{name}: the {side} forearm points {'towards' if angle > 0 else 'away from'} the camera "
                       f"({abs(angle):.0f} deg out of the photo's plane): how far it, and anything it holds, "
                       "stands out from the body is guessed")
    return out


def _hidden_joints(confidences: np.ndarray) -> set[int]:
    """The COCO-17 wrists, knees and ankles the photo hides: seen less surely than :data:`HIDDEN_CONFIDENCE`,
    not cut off by the frame (confidence 0, which the detector says itself)."""
    return {i for i in (9, 10, 13, 14, 15, 16) if 0 < confidences[i] < HIDDEN_CONFIDENCE}


def _pose_told(confidences: np.ndarray) -> set[str]:
    """The joints (COCO-17 names, spaced) whose hiding :func:`_pose_warnings` says in words of its own: the
    knees and ankles of hidden legs, the wrists of hidden hands (:func:`_hidden_joints`)."""
    return {COCO17_NAMES[i].replace("_", " ") for i in _hidden_joints(confidences)}


def _without_told(warnings: list[str], name: str, told: set[str]) -> list[str]:
    """``warnings`` with the detector's "not clearly visible in ``name``: ..." line listing only the joints
    not in ``told`` (gone when none is left): a long dress's hidden ankles are said once, with what
    was guessed."""
    prefix = f"not clearly visible in {name}: "
    out = []
    for w in warnings:
        if w.startswith(prefix):
            rest = [j for j in w[len(prefix):].split(", ") if j not in told]
            if not rest:
                continue
            w = prefix + ", ".join(rest)
        out.append(w)
    return out


def lean_deg(world: np.ndarray | None, confidences: np.ndarray, lower: list[int], upper: list[int]) -> float | None:
    """Degrees the detector's 3D segment from the centre of the COCO-17 joints ``lower`` to the centre of
    ``upper`` (in ``world`` (17, 3), metres, camera axes: y down, z away from the camera) leans towards the
    camera from the image's up, in the plane of the image's vertical and the view; None without 3D
    landmarks or with one of those joints not sure (:data:`MIN_CONFIDENCE` in ``confidences``)."""
    if world is None or float(np.min(confidences[lower + upper])) < MIN_CONFIDENCE:
        return None
    segment = np.asarray(world, np.float64)[upper].mean(axis=0) - np.asarray(world, np.float64)[lower].mean(axis=0)
    return float(np.degrees(np.arctan2(-segment[2], -segment[1])))


def body_tilt_deg(world: np.ndarray | None, confidences: np.ndarray) -> tuple[float, bool] | None:
    """How far the whole detected body leans towards the camera, and whether the person is seated.

    Standing: the smaller of the torso's lean (hip centre -> shoulder centre) and the whole body's (ankle
    centre -> shoulder centre), :func:`lean_deg`. A camera above the person tilts both; a person leaning
    or bowing forward tilts the torso alone. Seated (the thighs, knee centre -> hip centre, pointing at
    the camera: leaning back :data:`THIGHS_AT_CAMERA_DEG` or more): the smaller of the torso's lean and the
    shins' (ankle centre -> knee centre), which stand as a standing person's legs do. None without 3D
    landmarks or with a shoulder, hip, knee or ankle not sure."""
    torso = lean_deg(world, confidences, [11, 12], [5, 6])
    thighs = lean_deg(world, confidences, [13, 14], [11, 12])
    if torso is None or thighs is None:
        return None
    seated = thighs <= -THIGHS_AT_CAMERA_DEG
    legs = lean_deg(world, confidences, [15, 16], [13, 14] if seated else [5, 6])
    return None if legs is None else (min(torso, legs), seated)


def foreshortening(view: InputView) -> float | None:
    """How much more the photo foreshortens the legs than the torso: the 2D keypoints' torso (hip centre
    -> shoulder centre) over legs (hip centre -> ankle centre), divided by the same ratio of the
    detector's 3D landmarks. About 1 for a person standing square to the camera, above 1 seen from
    above (the legs lie further below the camera), below 1 for a torso bowing towards it; None without
    3D landmarks or with a shoulder, hip or ankle not sure (:data:`MIN_CONFIDENCE`)."""
    world, kp = view.world_keypoints, np.asarray(view.keypoints, np.float64)
    if world is None or float(np.min(view.confidences[[5, 6, 11, 12, 15, 16]])) < MIN_CONFIDENCE:
        return None
    world = np.asarray(world, np.float64)

    def ratio(p: np.ndarray) -> float:
        hips = p[[11, 12]].mean(axis=0)
        legs = float(np.linalg.norm(hips - p[[15, 16]].mean(axis=0)))
        return float(np.linalg.norm(p[[5, 6]].mean(axis=0) - hips)) / max(legs, 1e-9)

    return ratio(kp) / max(ratio(world), 1e-9)


def orbit_elevation(view: InputView, elevation_deg: float) -> tuple[float, float | None]:
    """The elevation (degrees) to build the orbit at, and the body tilt that raised it (None: not raised).

    A photo taken from above shows an upright person leaning towards the camera. MediaPipe's 3D body
    (:func:`body_tilt_deg`) tilts 3-18 deg towards the camera on renders of five synthetic standing
    subjects (standing, walking, an A-pose, hands on the hips, a hand on the face) and the two fixture
    scans photographed from 10 deg above, 11-22 from 20 deg, 16-30 from 30 deg and 15-38 from 40 deg,
    and -17 to 18.5 on the other photos of the benchmarks and the fixtures (from 10 deg or level):
    about half the elevation, 10 deg apart between subjects. Seated people tilt less: 3-11 deg from 10
    deg above (four synthetic subjects), 12-15 from 20, 17-23 from 30, 19-36 from 40. Built at
    ``elevation_deg`` (10), the scans photographed from 30 deg came out bowing with their legs swept
    behind them (side IoU 0.28 / 0.44; built at 20 deg, 0.59 / 0.70), seated subjects leaning over
    their knees (0.25-0.50; built at 20 or 30, 0.73-0.77). The wrong way costs as much: the scans'
    photos from 10 deg built at 20 fall from 0.83 / 0.72 to 0.58 / 0.47. So only a tilt beyond
    :data:`FROM_ABOVE_TILT_DEG` (seated: :data:`SEATED_TILT_DEG`), above every photo from 10 deg
    measured, raises the orbit, by :data:`RAISE_PER_TILT` degrees per degree beyond it, at most
    :data:`MAX_RAISE_DEG`; a standing person's photo must also foreshorten the legs at least as much
    as the torso (:func:`foreshortening`: a deep bow towards the camera foreshortens the torso
    instead). A person who really leans towards the camera as a whole is stood upright too."""
    measured = body_tilt_deg(view.world_keypoints, view.confidences)
    if measured is None:
        return float(elevation_deg), None
    tilt, seated = measured
    beyond = tilt - (SEATED_TILT_DEG if seated else FROM_ABOVE_TILT_DEG)
    if beyond <= 0.0:
        return float(elevation_deg), None
    if not seated:
        legs = foreshortening(view)
        if legs is None or legs < LEGS_FORESHORTENED:  # a bow: nothing tells it from above
            return float(elevation_deg), None
    return float(elevation_deg) + min(RAISE_PER_TILT * beyond, MAX_RAISE_DEG), tilt


def centring_transform(points: np.ndarray, camera_c2w: np.ndarray) -> np.ndarray:
    """4x4 scaling about the camera centre that moves the middle of ``points``' (N, 3) bounding box onto
    the vertical axis through the orbit centre (the world origin), along the camera's horizontal
    direction. Every point stays on its ray, so the camera's view of them does not change. A camera
    straight above the origin has no horizontal direction: the identity."""
    centre = np.asarray(camera_c2w, np.float64)[:3, 3]
    towards = centre * np.array([1.0, 0.0, 1.0])
    if np.linalg.norm(towards) < 1e-6 * max(float(np.linalg.norm(centre)), 1e-9):
        return np.eye(4)
    towards /= np.linalg.norm(towards)
    pts = np.asarray(points, np.float64)
    middle = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    scale = float(centre @ towards) / max(float((centre - middle) @ towards), 1e-9)
    scale = float(np.clip(scale, 1.0 / MAX_CENTRING_SCALE, MAX_CENTRING_SCALE))
    m = np.eye(4)
    m[:3, :3] *= scale
    m[:3, 3] = (1.0 - scale) * centre
    return m


def build_body_proxy(photo_path: str | Path, num_frames: int = 21, size: int = 576, elevation_deg: float = 10.0,
                     background: tuple[float, float, float] = (1.0, 1.0, 1.0), iterations: int = 150,
                     fill: float = DEFAULT_FILL, seed: int = 0, geometry: str = "clothed",
                     raise_from_above: bool = True, logger: logging.Logger | None = None) -> BodyProxy:
    """Steps 1-6 of the contract: the input view, the orbit, the fitted body and the coloured, centred proxy."""
    import torch

    from humanvdm_core.body import load_body_model
    from humanvdm_core.body.fit import FitOptions, FrameObservation, fit_body
    from humanvdm_core.body.landmarks import arms_read_short, hands_on_head, rebuild_arms
    from humanvdm_core.perception.facing import estimate_facing, unmirrored
    from humanvdm_core.workflow.errors import ConfigError

    if geometry not in GEOMETRIES:
        raise ConfigError(f"geometry must be one of {GEOMETRIES}, got {geometry!r}")
    lg = logger or log
    name = resolve_photo(photo_path).name
    view = prepare_input_view(photo_path, size, fill, background)
    warnings = list(view.warnings)
    elevation, tilt = orbit_elevation(view, elevation_deg) if raise_from_above else (float(elevation_deg), None)
    if tilt is not None:
        warnings.append(f"{name} looks taken from above (the body's 3D landmarks lean {tilt:.0f} deg towards the "
                        f"camera): the orbit is raised to {elevation:.0f} deg elevation (from {elevation_deg:.0f}) so "
                        "the person stands or sits upright; if they lean or bow towards the camera instead, set "
                        "diffuse.raise_from_above=false")
    cameras = orbit_cameras(num_frames, size, FOV_DEG, elevation, framing_radius(SUBJECT_HEIGHT, FOV_DEG, fill))
    cameras.extra.update({"background": np.asarray(background, np.float64), "fill": np.float64(fill)})
    front = int(np.argmin(np.abs((cameras.azimuth_deg + 180.0) % 360.0 - 180.0)))
    front_cam = cameras.subset([front])

    facing = estimate_facing(view.rgba[..., :3], view.keypoints, view.confidences, view.world_keypoints)
    if facing.mirrored:
        keypoints, confidences, world = unmirrored(view.keypoints, view.confidences, view.world_keypoints)
        view = replace(view, keypoints=keypoints, confidences=confidences, world_keypoints=world)
        lg.info("body prior: the pose model mirrored the skeleton of a person facing the camera; set right")
    facing_warning = None
    if facing.away:
        facing_warning = (f"{name} shows the person from behind: built facing away from the camera; their front "
                          "(face included) is not in the photo and is filled with plain colours")
    elif facing.ambiguous:
        facing_warning = f"{name}: no face found and the body's facing is unclear: assumed facing the camera"

    model = load_body_model("anny")
    torch.manual_seed(seed)
    fit_mask = view.mask if view.fit_mask is None else view.fit_mask
    keypoints = view.keypoints
    short = [] if view.world_keypoints is None else arms_read_short(keypoints, view.confidences, view.world_keypoints)
    if short:  # the detector's 2D arm contradicts its own 3D one: the 3D direction (and the mask) decide
        keypoints = rebuild_arms(keypoints, view.world_keypoints, short)
        sides = " and ".join(("left", "right")[a] for a in short)
        warnings.append(f"{name}: the pose model's 2D {sides} arm{'s' if len(short) > 1 else ''} "
                        f"{'are' if len(short) > 1 else 'is'} much shorter than its 3D landmarks show (a costume, "
                        "armour or a drawn figure?): fitted along the 3D landmarks and the silhouette instead, "
                        "at the body's own proportions")
    obs = FrameObservation(0, keypoints, view.confidences, fit_mask.copy(), list(view.warnings),
                           world_keypoints=view.world_keypoints, unseen=view.unseen)
    options = FitOptions(iterations=iterations, seed=seed, facing_away=facing.away,
                         head_over_shoulders=not facing.bowed)
    fit = fit_body(model, front_cam, [obs], options, logger=lg)
    vertices = fit.output.vertices[0].numpy().astype(np.float64)
    coco17 = fit.output.coco17[0].numpy().astype(np.float64)
    faces = model.faces.numpy().astype(np.int64)
    turn = shoulder_turn_deg(coco17, front_cam.w2c[0])
    if turn >= PROFILE_DEG:  # front or back means little for a person seen from the side
        facing_warning = (f"{name} shows the person in profile (shoulders turned {turn:.0f} deg from the camera): "
                          "their front and back are seen edge-on, so both are guessed")
    warnings += [facing_warning] if facing_warning else []
    # the hands the fit placed on the head (FitOptions.hands_on_head): the contact fixes their arms' depth
    on_head = tuple(side for side, (_, wrist) in FOREARMS.items() if view.world_keypoints is not None
                    and wrist in hands_on_head(view.world_keypoints, view.confidences))
    warnings += _pose_warnings(name, view, coco17, front_cam.w2c[0], on_head)

    weights = model.skinning_weights.numpy()
    head_ids = [model.joint_names.index(n) for n in HEAD_JOINTS if n in model.joint_names]
    head_weight = weights[:, head_ids].sum(axis=1) if head_ids else None
    lg.info("body prior: fitted in %.1f s (reprojection %.1f px)", fit.seconds, float(np.nanmean(fit.reprojection_px)))
    clothed = None
    if geometry == "clothed":
        from humanvdm_core.clothed_proxy import build_clothed_proxy

        hair = None
        if head_weight is not None and np.any(head_weight > 0.5) and not facing.away:
            px, _ = project_points(vertices[head_weight > 0.5], front_cam.w2c[0], front_cam.K[0])
            hair = hair_colour(view.rgba[..., :3], view.mask, px)
        clothed = build_clothed_proxy(vertices, faces, weights, list(model.joint_names), front_cam,
                                      view.rgba[..., :3], view.mask, head_colour=hair,
                                      legs_hidden=_ankles_hidden(view.confidences), profile=turn >= PROFILE_DEG,
                                      placed_arms=tuple(1 if side == "left" else -1 for side in on_head),
                                      coco17=coco17, facing_away=facing.away)
        lg.info("clothed proxy: %d vertices, %d faces; the body covers %.0f%% of the silhouette",
                len(clothed.mesh.vertices), len(clothed.mesh.faces), 100 * clothed.body_fraction)
        if clothed.body_fraction < LOOSE_FRACTION:
            warnings.append(f"{name}: {100 * (1 - clothed.body_fraction):.0f}% of the person's silhouette lies outside "
                            "the fitted body (loose clothing, long hair, a hat or a held object): its depth and "
                            "thickness are guessed")
        mesh = clothed.mesh
    else:
        colours, _ = colour_body(vertices, faces, front_cam, view.rgba[..., :3], view.mask, head_weight)
        mesh = TexturedMesh(vertices.astype(np.float32), faces, vertex_colors=colours)
    to_centre = centring_transform(mesh.vertices, front_cam.c2w[0])  # step 6 of the contract
    mesh = mesh.transformed(to_centre)
    if clothed is not None:
        clothed = replace(clothed, mesh=mesh)
    coco17 = coco17 @ to_centre[:3, :3].T + to_centre[:3, 3]
    return BodyProxy(input_view=view, mesh=mesh, cameras=cameras, front_index=front,
                     background=tuple(float(c) for c in background),
                     reprojection_px=float(np.nanmean(fit.reprojection_px)),
                     warnings=_without_told(list(dict.fromkeys(warnings + fit.warnings)), name,
                                            _pose_told(view.confidences)), clothed=clothed,
                     facing_away=facing.away, coco17=coco17)


def synthesize_orbit(photo_path: str | Path, num_frames: int = 21, size: int = 576, elevation_deg: float = 10.0,
                     background: tuple[float, float, float] = (1.0, 1.0, 1.0), iterations: int = 150,
                     fill: float = DEFAULT_FILL, seed: int = 0, raise_from_above: bool = True,
                     logger: logging.Logger | None = None) -> tuple[np.ndarray, Cameras]:
    """A photo -> (frames (N, size, size, 4) float32, cameras); see the module docstring."""
    proxy = build_body_proxy(photo_path, num_frames, size, elevation_deg, background, iterations, fill, seed,
                             raise_from_above=raise_from_above, logger=logger)
    return proxy.orbit_frames(), proxy.cameras
