"""Fitting a parametric body model to a frame set (paper section 3.3: the body the Gaussians hang on).

Contract:

- Input: a :class:`~humanvdm_core.body.model.BodyModel` (any backend, see
  :func:`humanvdm_core.body.load_body_model`, re-exported here),
  the frames' cameras (:class:`~humanvdm_core.cameras.Cameras`) and one :class:`FrameObservation`
  per frame used (COCO-17 keypoints in pixels with confidences from
  :func:`humanvdm_core.perception.detect_person`, the person mask, and optionally the detector's
  3D keypoints ``world_keypoints`` in the frame's camera axes). :func:`observe_frames` builds them
  from RGBA frames.
- The person is static and the cameras move: ONE set of body parameters (pose, shape, global
  orientation, translation, scale) explains every frame. A single photo is the same problem with one
  camera. With ``FitOptions.refine_per_frame`` each frame also gets a small pose correction on top of
  the shared pose (for generated orbits whose person drifts); the shared pose stays the result.
- Objective (Adam, three phases): phase 1 fits global orientation, translation and scale to the
  torso keypoints (shoulders, hips) and the torso's 3D bones; phase 1b (only with 3D keypoints) sets
  the pose of the main limb/spine joints (:data:`FIT_JOINTS`; the others keep the model's zero pose)
  from the 3D bone directions alone, so each limb starts on the right side of the depth ambiguity a
  2D keypoint leaves (a thigh towards or away from the camera foreshortens the same); phase 2 fits
  everything, the shape too. Terms, each dimensionless and multiplied by its weight in
  :class:`FitOptions`:

  * keypoints: confidence-weighted robust (Cauchy, scale ``KEYPOINT_SIGMA`` of the image height)
    distance between the model's projected ``coco17`` and the detections. In a single photo the
    elbow and wrist of an arm held out to the side (:func:`held_out_arms`) bound the arm from inside
    only (``FitOptions.arm_reach_past_keypoints``): the model's joint may lie further out along the
    shoulder -> wrist line than the detection, free (a sleeve, a glove or armour hides the joint and
    the detector reads the arm short; the fit then swung it out of the image plane to shorten it),
    and the one-sided silhouette bounds how far;
  * bone directions (``bone_direction_weight``): for the bones of :data:`BONES` (upper arms,
    forearms, thighs, shins, shoulder and hip lines, spine, neck) the model's 3D bone turned into
    each frame's camera against the same bone of the detector's ``world_keypoints``: mean of
    (1 - cos) weighted by the lower confidence of the bone's joints. Only directions count (the
    detector's 3D scale and origin do not matter). This is what tells a single photo's limb depth:
    a seated person's thighs point at the camera, hands on the hips keep the elbows beside the body.
    In a single photo a joint inside it that the detector does not see clearly (the far leg of a
    person in profile, a hand behind the back) keeps its 3D landmark, the detector's guess, at
    :data:`HIDDEN_3D_CONFIDENCE`: with nothing else to hold it, the limb swung to wherever its vertices
    best moved the hip's or shoulder's keypoint (``coco17`` is regressed from the vertices), a far
    leg in profile raised horizontally 0.75 m behind the hips. A joint the photo cuts off keeps none
    (the unseen pixels below guard it).
    An arm the 2D keypoints show held out to the side is first turned into the body's frontal plane
    (:func:`frontal_arms`, ``FitOptions.frontal_arms``): the detector tilts such forearms 20-30 deg
    towards the camera; in a single photo whose 2D keypoints show both arms held out to the side (a
    T-pose, an A-pose: both arms at their length in the image plane, on the shoulder line) the
    detector's shoulders and arms turned a few degrees about the vertical from facing the camera are
    first turned to face it (:func:`facing_shoulders`, ``FitOptions.facing_shoulders``: on frontal
    renders it turns them 2-7 deg, and each arm follows the shoulder line, a hand 0.1 m before or
    behind the body), a clear turn is kept; in a single photo a wrist the 3D landmarks place on the
    head is first moved to the head's middle depth (:func:`onto_the_head`, ``FitOptions.hands_on_head``): a hand the photo
    shows on the face or the head touches it, where the detector often puts it 20-25 cm before the
    face (with more views their depths decide);
  * silhouette, one-sided by default: projected vertices (a fixed subsample) must fall inside the
    mask (the mask's outside distance transform sampled bilinearly at them; ``silhouette_weight``).
    Pixels a frame does not show (``FrameObservation.unseen``: beyond the edge of a photo that cuts
    the person off) cost nothing: the fit would otherwise fold the legs it cannot see behind the ones
    it can. The other side, the mask's contour covered by the body (each contour point's distance to
    the nearest projected vertex; ``silhouette_cover_weight``), is off by default: loose clothing is
    in the mask but is not body, and covering it widens the body. Both in units of
    ``SILHOUETTE_SIGMA`` of the image size;
  * priors: squared axis-angle of the fitted joints (stronger with fewer than five views:
    ``FitOptions.single_view_pose_prior_weight``, or the much weaker
    ``single_view_pose_prior_weight_3d`` when every view with keypoints has 3D keypoints); squared
    deviation of the shape from the backend's default; the scale from its initial estimate (only
    matters for one camera); the torso between upright and the detector's torso
    (``upright_weight`` / views², :meth:`_Problem.torso_term`): the hip centre -> shoulder centre line
    more than :data:`TORSO_FREE_DEG` off the arc from the world's +Y to the detector's torso line
    costs the excess angle squared. The other terms pull a single photo's fit 4-8 deg back (a seated
    person reclines); many views see the lean themselves. The detector's torso is taken as it is from
    :data:`TORSO_TRUSTED_DEG` off upright on (a bow), and as upright within :data:`TORSO_NOISE_DEG`
    (between the two the lean it counts grows from 0 to the whole): MediaPipe leans the torso of
    people who stand upright 3-13 deg forward (synthetic renders at 10 deg elevation), and a real
    photo's unknown camera height tilts it either way. In a single photo of a person not seated a
    lean backwards counts as upright within :data:`TORSO_BACK_NOISE_DEG` and whole from
    :data:`TORSO_BACK_TRUSTED_DEG` on: MediaPipe leans the torso behind arms crossed before the chest
    12-14 deg back, and people standing seldom lean back (a seated one reclines). A single photo of a
    seated person (:func:`~humanvdm_core.body.landmarks.seated`: both thighs point at the camera, hiding
    the pelvis) also gets the spine term (``spine_prior_weight``): the squared axis-angle of the spine's fitted
    joints (:data:`SPINE_JOINTS`), so the pelvis sits under the torso line rather than rolled some 13 deg
    forward under a spine bent 27 deg back (a slouch pushing the seat out from under the torso), and
    its 2D knees are first raised (:func:`~humanvdm_core.body.landmarks.raise_seated_knees`,
    ``FitOptions.seated_knees``): the detector puts them 0.06-0.14 of the torso too low (the more, the
    lower the camera), which sloped the thighs 15-20 deg down -- where a thigh points at the camera; a
    thigh seen at a slant (a seated person photographed from the side) keeps its knee where it is read.
    A single photo of a person standing still (:func:`standing_still`) also gets the stance term
    (``stance_weight``, :meth:`_Problem.stance_term`): each knee bent beyond
    :data:`STANCE_KNEE_FREE_DEG` and the ankles' centre more than
    :data:`STANCE_FEET_FREE` in front of or behind the hips' (along the camera's horizontal view)
    cost, squared. MediaPipe bends the knees of people who stand straight (its 3D knees 17-20 deg on
    every standing render; on real people in trousers its 2D shins come out a fifth short, so the
    2D keypoints alone bend them too) and the fit put their feet 0.1-0.2 m behind the hips. From the
    second half of phase 2 on, if the fitted torso is then within :data:`STANCE_HEAD_UPRIGHT_DEG` of
    upright, the ears' centre more than :data:`STANCE_HEAD_FREE` away from :data:`STANCE_HEAD_AHEAD`
    before the shoulders' (along the torso's own forward, its left shoulder x its spine, whichever way
    it faces the camera) costs too, so the ears stand between 2 cm behind and 3 cm before them (on the
    synthetic subjects the truth's stand 2-4 cm before; the three.js Soldier's helmet sits further back
    than a head: a zone centred on people's 3 cm cost it 0.6 dB). Where the photo's neck is short (a
    hood, a helmet, a high collar, raised shoulders hide it) the fit tilted the head towards the camera
    to foreshorten it (the three.js Soldier's ears 7.5 cm before its shoulders); where hands are held
    before the face or the chest it held the head 2 cm behind the shoulders (hands on the head, a hand
    at the face, clasped or crossed arms). Joining from the start, it knocked the heads of three
    synthetic subjects in headwear (a hat, a bun, a helmet: 2.4-3.5 cm before the shoulders, near the
    truth's) back; once the head has settled, such heads are left alone. A bow carries the head forward with the chest: a bowing torso
    is left to its head, and so is a head the photo's face shows bowed (``head_over_shoulders`` off:
    :attr:`~humanvdm_core.perception.facing.Facing.bowed`).
    A single photo also gets the turn term (``turn_weight``, :meth:`_Problem.turn_term`): where the
    detector's 3D shoulder (hip) line turns at least :data:`TURN_SEEN_DEG` out of the image plane, the
    model's may turn less by at most :data:`TURN_FREE_DEG` at no cost; beyond, the shortfall costs,
    squared. A turned person's shoulders look narrower in the photo, and the fit explained that by
    narrower shoulders as much as by a turn: it turned the shoulders of scans turned 20-35 deg 3-9 deg
    less than MediaPipe did (which itself reads them short), and the bone-direction term's ``1 - cos``
    hardly pulls at a few degrees. Only a shortfall costs: where the fit turns further (the hips of a
    stride), it keeps its own. Below :data:`TURN_SEEN_DEG` the detector's turn is noise as often as
    not (up to 10 deg on synthetic people facing the camera); beyond :data:`TURN_MAX_DEG` (near
    profile) the pull twisted the hips against the legs; a line is never pulled through facing the
    camera.

- The rules that read a single photo's landmarks before the fit (:func:`held_out_arms`,
  :func:`reach_directions`, :func:`frontal_arms`, :func:`facing_shoulders`, :func:`onto_the_head`,
  :func:`standing_still`, :func:`seated`, :func:`raise_seated_knees`) live in
  :mod:`humanvdm_core.body.landmarks`, with their thresholds.
- Left/right confusion: a keypoint detector often swaps the person's left and right on back and
  side views. Per frame and per group (face, arms, legs), the assignment (as detected or swapped)
  that better agrees with the current 3D estimate is used; it is decided after phase 1 and again
  during phase 2 (:data:`SWAP_GROUPS`). The 2D keypoints follow the assignment nearer the model's
  projection; the 3D keypoints are decided on their own, by which assignment's bones point more like
  the model's (in a side view the two hips project onto each other and the 2D decision is a coin
  toss, while the 3D hip line still tells left from right). Fitting a single photo, where the 3D
  decisions after phase 1 differ from those it was fitted with, phase 1 runs once more from the start
  with them (``FitOptions.refit_turn``): a body turned to mirrored shoulder and hip lines is turned the
  wrong way, and phase 2 cannot turn it back through facing the camera (a turned torso's 2D width is
  the same either way), so its hips stayed turned against its shoulders. The 2D decisions alone do not
  count (a coin toss in a side view), nor do an orbit's (its many views outvote one frame's labels).
- Initialisation: from the key frame (the one whose camera azimuth is nearest 0, the input view):
  the body faces that camera; its translation puts the torso centre on the ray through the detected
  torso centre at the camera's distance to the orbit centre; its scale matches the detected torso
  height at that depth.
- Output: :class:`FitResult` (parameters, posed :class:`~humanvdm_core.body.model.BodyOutput`,
  per-frame reprojection error in pixels and L/R decisions). :func:`silhouette_iou` rasterises the
  fitted mesh with :mod:`humanvdm_core.render` for an honest IoU against the masks;
  :func:`joint_error_mm` compares with known true joints.
- Deterministic: a fixed seed picks the silhouette vertex subsample; same inputs and options give
  the same result on one machine.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from humanvdm_core.body import load_body_model
from humanvdm_core.body.landmarks import (
    LEGS,
    facing_shoulders,
    frontal_arms,
    onto_the_head,
    raise_seated_knees,
    reach_directions,
    seated,
    standing_still,
    torso_length,
)
from humanvdm_core.body.model import COCO17_NAMES, BodyModel, BodyOutput, BodyParams
from humanvdm_core.cameras import Cameras
from humanvdm_core.workflow.errors import ConfigError, HumanVDMError, InputError
from humanvdm_core.workflow.progress import report

log = logging.getLogger("humanvdm.body.fit")

# The joints whose rotation is fitted (a subset of the rig; the rest keep the zero pose): Anny's names,
# then SMPL/SMPL-X's; the names a model has are used.
FIT_JOINTS: tuple[str, ...] = (
    "spine03", "spine01", "neck01", "head",
    "clavicle.L", "clavicle.R", "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R",
    "upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R", "foot.L", "foot.R",
    "spine1", "spine2", "spine3", "neck", "left_collar", "right_collar", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
)
# COCO-17 index pairs (left, right) per group whose detected L/R assignment is decided together.
SWAP_GROUPS: dict[str, tuple[tuple[int, int], ...]] = {
    "face": ((1, 2), (3, 4)),
    "arms": ((5, 6), (7, 8), (9, 10)),
    "legs": ((11, 12), (13, 14), (15, 16)),
}
TORSO = (5, 6, 11, 12)  # COCO shoulders and hips
# Bones of the bone-direction term, each (start, end) with an end a COCO-17 index or a tuple of indices
# (their mean): upper arms, forearms, thighs, shins, the shoulder and hip lines (right -> left), the
# spine (hip centre -> shoulder centre) and the neck (shoulder centre -> nose).
BONES: tuple[tuple[int | tuple[int, ...], int | tuple[int, ...]], ...] = (
    (5, 7), (7, 9), (6, 8), (8, 10),
    (11, 13), (13, 15), (12, 14), (14, 16),
    (6, 5), (12, 11), ((11, 12), (5, 6)), ((5, 6), 0),
)
SPINE_JOINTS = ("spine01", "spine03", "spine1", "spine2", "spine3")  # Anny's, SMPL's: the spine term
TORSO_BONES = (8, 9, 10)  # shoulder line, hip line, spine: fitted with the global orientation in phase 1
KEYPOINT_SIGMA = 0.02  # Cauchy scale of the keypoint residual, fraction of the image height
SILHOUETTE_SIGMA = 0.01  # silhouette distances are divided by this (fraction of the image size)
SILHOUETTE_SIZE = 160  # masks are compared at this resolution
OUTSIDE_DOUBT = 0.1  # a fitted body with more than this share outside the person's masks is doubtful ...
COVER_DOUBT = 0.5  # ... and one covering less than this share of them is said (silhouette_doubts)
CONTOUR_POINTS = 256  # contour samples per frame
MIN_KEYPOINT_CONFIDENCE = 0.3  # keypoints below this confidence are ignored ...
HIDDEN_3D_CONFIDENCE = 0.3  # ... but a single photo's 3D landmark of a joint inside it counts at least this much
BONE_DIRECTION_WEIGHT = 2.0  # default FitOptions.bone_direction_weight
SINGLE_VIEW_PRIOR_3D = 0.1  # default FitOptions.single_view_pose_prior_weight_3d
UPRIGHT_WEIGHT = 20.0  # default FitOptions.upright_weight
TORSO_FREE_DEG = 1.5  # a torso within this angle of the arc from upright to the detector's torso costs nothing
TORSO_NOISE_DEG = 10.0  # the detector's torso this close to upright counts as upright ...
TORSO_TRUSTED_DEG = 20.0  # ... and this far from it or more counts whole (between: a linear ramp)
# the same for a lean backwards in a single photo of a person not seated (MediaPipe leans the torso behind
# arms crossed before the chest 12-14 deg back; people standing seldom lean back, a seated one reclines)
TORSO_BACK_NOISE_DEG = 15.0
TORSO_BACK_TRUSTED_DEG = 25.0
SPINE_BONE = BONES.index(((11, 12), (5, 6)))  # hip centre -> shoulder centre
STANCE_WEIGHT = 10.0  # default FitOptions.stance_weight
SPINE_PRIOR_WEIGHT = 1.0  # default FitOptions.spine_prior_weight
STANCE_KNEE_FREE_DEG = 3.0  # a knee bent less than this costs nothing ..
STANCE_FEET_FREE = 0.01  # .. nor ankles this close (world units) to below the hips along the view ..
STANCE_FEET_UNIT = 0.05  # .. farther, the excess counts in units of this (the head's too) ..
STANCE_HEAD_AHEAD = 0.005  # .. nor the ears' centre this far before the shoulders' ..
STANCE_HEAD_FREE = 0.025  # .. give or take this (second half of phase 2, ..
STANCE_HEAD_UPRIGHT_DEG = 10.0  # .. a torso this close to upright then)
TURN_WEIGHT = 30.0  # default FitOptions.turn_weight
TURN_SEEN_DEG = 8.0  # the detector's shoulder (hip) line turned this far out of the image plane is a turn ...
TURN_FREE_DEG = 2.0  # ... the fit's may fall this far short of at no cost (turn_term) ...
TURN_MAX_DEG = 60.0  # ... up to this turn (nearer profile the fit keeps its own)
TURN_BONES = (BONES.index((6, 5)), BONES.index((12, 11)))  # the shoulder and the hip line


@dataclass
class FitOptions:
    """Knobs of :func:`fit_body` (the stage exposes them as params)."""

    iterations: int = 250  # phase-2 Adam steps (phase 1 takes a third of this, at least 30)
    keypoint_weight: float = 1.0
    # one-sided silhouette: the body's projected vertices must lie inside the mask
    silhouette_weight: float = 0.3
    # the other side: the mask's contour must be covered by the body. Off by default: clothing (a gown, a
    # coat, long hair) is in the mask but is not body, and covering it stretches the body
    silhouette_cover_weight: float = 0.0
    # 3D bone directions against the detector's world landmarks (FrameObservation.world_keypoints)
    bone_direction_weight: float = BONE_DIRECTION_WEIGHT
    pose_prior_weight: float = 0.05
    # with few views the pose prior grows: max(pose_prior_weight, this / views_with_keypoints**2), so a
    # single photo without 3D landmarks (depth of the limbs unobservable) stays near the rest pose ..
    single_view_pose_prior_weight: float = 1.0
    # .. and this replaces it when the views have 3D landmarks (the bone-direction term observes the depth)
    single_view_pose_prior_weight_3d: float = SINGLE_VIEW_PRIOR_3D
    shape_prior_weight: float = 0.05
    scale_prior_weight: float = 1.0
    refine_per_frame: bool = False
    refine_iterations: int = 60
    refine_prior_weight: float = 1.0
    silhouette_vertices: int = 1500
    seed: int = 0
    # the torso (hip centre -> shoulder centre) off the arc from upright to the detector's torso
    upright_weight: float = UPRIGHT_WEIGHT
    # the key frame shows the person's back (a photo from behind): start facing away from its camera
    facing_away: bool = False
    # the detector's 3D arms held out to the side are turned into the body's frontal plane (frontal_arms)
    frontal_arms: bool = True
    # a single photo: the detector's 3D wrists on the head are moved into the head's depth, the hand touches
    # it (onto_the_head)
    hands_on_head: bool = True
    # a single photo with both arms held out to the side: the detector's shoulders turned a few degrees
    # from facing the camera face it (facing_shoulders)
    facing_shoulders: bool = True
    # a single photo of a person standing still (standing_still): knees straight, feet below the hips
    stance_weight: float = STANCE_WEIGHT
    # ... and, an upright one, the head over the shoulders (off for a photo whose face is bowed)
    head_over_shoulders: bool = True
    # a single photo of a seated person (landmarks.seated): the spine's fitted joints (SPINE_JOINTS) held
    # near the rest pose ...
    spine_prior_weight: float = SPINE_PRIOR_WEIGHT
    # ... and its 2D knees raised first (raise_seated_knees)
    seated_knees: bool = True
    # a single photo: an arm held out to the side may reach past its 2D elbow and wrist (reach_directions)
    arm_reach_past_keypoints: bool = True
    # a single photo: the shoulder and hip lines turned at least as far as the detector's 3D ones, where
    # they clearly turn (_Problem.turn_term)
    turn_weight: float = TURN_WEIGHT
    # a single photo: phase 1 runs again from the start when its 3D left/right decisions change (fit_body)
    refit_turn: bool = True

    def check(self) -> None:
        if self.iterations < 1 or self.refine_iterations < 0:
            raise ConfigError("iterations must be >= 1 and refine_iterations >= 0")
        for name in ("keypoint_weight", "silhouette_weight", "silhouette_cover_weight", "bone_direction_weight",
                     "pose_prior_weight", "single_view_pose_prior_weight", "single_view_pose_prior_weight_3d",
                     "shape_prior_weight", "scale_prior_weight", "refine_prior_weight", "upright_weight",
                     "stance_weight", "spine_prior_weight", "turn_weight"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.keypoint_weight == 0 and self.silhouette_weight == 0 and self.silhouette_cover_weight == 0:
            raise ConfigError("keypoint_weight and silhouette_weight cannot both be 0")


@dataclass
class FrameObservation:
    """What one frame tells the fit. ``keypoints`` (17, 2) pixels, ``confidences`` (17,) (all 0 when
    only the silhouette is known), ``mask`` (H, W) float in [0, 1]; ``world_keypoints`` (17, 3) the
    detector's 3D joints in this frame's camera axes (x right, y down, z away from the camera; any
    origin and scale: only directions are used), with the same ``confidences``, or None; ``unseen``
    (H, W) bool: pixels the frame does not show, where the person may go on (beyond the edge of a
    photo that cuts them off), or None (every pixel shown)."""

    index: int  # frame index in the frame set
    keypoints: np.ndarray
    confidences: np.ndarray
    mask: np.ndarray
    warnings: list[str] = field(default_factory=list)
    world_keypoints: np.ndarray | None = None
    unseen: np.ndarray | None = None

    @property
    def has_keypoints(self) -> bool:
        return bool((self.confidences >= MIN_KEYPOINT_CONFIDENCE).sum() >= 4)

    @property
    def has_world_keypoints(self) -> bool:
        return self.has_keypoints and self.world_keypoints is not None


@dataclass
class FitResult:
    """A fitted body. Per-frame arrays follow ``frame_indices`` (the observations' order)."""

    params: BodyParams  # batch 1, detached
    output: BodyOutput  # posed with ``params``, detached
    frame_indices: list[int]
    reprojection_px: np.ndarray  # (N,) mean pixel distance over confident keypoints; nan without keypoints
    swapped: np.ndarray  # (N, 3) bool per SWAP_GROUPS group: the detection's left/right was swapped
    keypoints: np.ndarray  # (N, 17, 2) detections as used (after any swap)
    confidences: np.ndarray  # (N, 17)
    projected: np.ndarray  # (N, 17, 2) the fitted model's coco17 in each frame, pixels
    per_frame_pose: np.ndarray | None  # (N, P, 3) with refine_per_frame, else None
    loss_history: list[float]
    seconds: float
    warnings: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- observations

def observe_frames(
    frames: np.ndarray, indices: Sequence[int], names: Sequence[str] | None = None,
) -> tuple[list[FrameObservation], dict[int, str]]:
    """Detect the person in RGBA frames (N, H, W, 4) at ``indices``.

    Returns the observations and, per frame that gave nothing usable, the reason. A frame whose
    detection fails but whose alpha is a real mask (1%..99% covered) still gives a silhouette-only
    observation (confidences 0)."""
    from humanvdm_core.perception import Photo, detect_person

    observations: list[FrameObservation] = []
    failed: dict[int, str] = {}
    h, w = frames.shape[1:3]
    for j, i in enumerate(indices):
        rgba = frames[i]
        alpha = np.clip(rgba[..., 3], 0.0, 1.0) if rgba.shape[-1] == 4 else None
        name = names[j] if names is not None else f"frame {i:04d}"
        photo = Photo(rgb=np.ascontiguousarray(np.clip(rgba[..., :3], 0.0, 1.0)), alpha=alpha,
                      path=Path(name), original_size=(w, h))
        try:
            det = detect_person(photo)
        except InputError as exc:
            coverage = 0.0 if alpha is None else float(np.mean(alpha > 0.5))
            if alpha is not None and 0.01 <= coverage <= 0.99:
                observations.append(FrameObservation(i, np.zeros((17, 2), np.float32), np.zeros(17, np.float32),
                                                     alpha.astype(np.float32), [f"{name}: keypoints unusable ({exc})"]))
            else:
                failed[i] = str(exc)
            continue
        world = None if det.world_keypoints is None else det.world_keypoints.astype(np.float32)
        observations.append(FrameObservation(i, det.keypoints.astype(np.float32),
                                             det.confidences.astype(np.float32), det.fit_mask.astype(np.float32),
                                             list(det.warnings), world))
    return observations, failed


# ----------------------------------------------------------------------------- geometry helpers

def project(points: torch.Tensor, w2c: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (N, 3) or (F, N, 3) into F cameras: pixels (F, N, 2) and camera depth (F, N)."""
    if points.dim() == 2:
        points = points[None].expand(w2c.shape[0], -1, -1)
    cam = points @ w2c[:, :3, :3].transpose(1, 2) + w2c[:, None, :3, 3]
    z = cam[..., 2].clamp(min=1e-4)
    uv = cam[..., :2] / z[..., None]
    px = uv * torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None] + K[:, None, :2, 2]
    return px, cam[..., 2]


def _unit_angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angles (radians) between unit vectors along the last axis (broadcast), kept off 0 and pi."""
    return torch.acos((a * b).sum(-1).clamp(-1 + 1e-6, 1 - 1e-6))


def trusted_lean(seen: torch.Tensor, up: torch.Tensor, front: torch.Tensor | None = None) -> torch.Tensor:
    """The detector's torso directions ``seen`` (F, 3, unit) turned towards ``up`` (3,) in their own vertical
    plane: an angle to ``up`` within :data:`TORSO_NOISE_DEG` becomes 0, one of :data:`TORSO_TRUSTED_DEG`
    or more stays, and one between grows linearly from 0 to the whole. Given the person's ``front`` (3,),
    horizontal and unit, a lean away from it (backwards) has :data:`TORSO_BACK_NOISE_DEG` and
    :data:`TORSO_BACK_TRUSTED_DEG` instead."""
    angle = _unit_angle(seen, up[None])  # (F,)
    noise = torch.full_like(angle, np.radians(TORSO_NOISE_DEG))
    trusted = torch.full_like(angle, np.radians(TORSO_TRUSTED_DEG))
    if front is not None:
        back = (seen @ front) < 0
        noise = torch.where(back, np.radians(TORSO_BACK_NOISE_DEG), noise)
        trusted = torch.where(back, np.radians(TORSO_BACK_TRUSTED_DEG), trusted)
    kept = torch.where(angle >= trusted, angle, (angle - noise).clamp(min=0.0) * trusted / (trusted - noise))
    side = seen - (seen @ up)[:, None] * up[None]
    side = side / side.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    return torch.cos(kept)[:, None] * up[None] + torch.sin(kept)[:, None] * side


def _spine(coco17: torch.Tensor) -> torch.Tensor:
    """(3,) the unit hip centre -> shoulder centre direction of ``coco17`` (17, 3): :data:`SPINE_BONE`."""
    spine = (coco17[5] + coco17[6]) / 2 - (coco17[11] + coco17[12]) / 2
    return spine / spine.norm().clamp(min=1e-9)


def _spine_from_upright_deg(coco17: torch.Tensor) -> float:
    """The angle in degrees between :func:`_spine` of ``coco17`` and +Y."""
    return math.degrees(float(torch.arccos(_spine(coco17)[1].clamp(-1.0, 1.0))))


def horizontal_view(cams: Cameras, index: int) -> np.ndarray:
    """(3,) the unit horizontal direction camera ``index`` of ``cams`` looks along (world axes, +Y up)."""
    forward = cams.c2w[index][:3, 2] * np.array([1.0, 0.0, 1.0])
    return forward / max(float(np.linalg.norm(forward)), 1e-9)


def _swap_pairs(groups: Sequence[bool], *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Copies of per-keypoint ``arrays`` (17, ...) with the left/right pairs of the flagged groups exchanged."""
    out = tuple(a.copy() for a in arrays)
    for flag, pairs in zip(groups, SWAP_GROUPS.values(), strict=True):
        if flag:
            for a, b in pairs:
                for x in out:
                    x[[a, b]] = x[[b, a]]
    return out


def _bone_matrices() -> tuple[np.ndarray, np.ndarray]:
    """(B, 17) averaging matrices of the bones' start and end points (:data:`BONES`)."""
    start, end = np.zeros((len(BONES), 17)), np.zeros((len(BONES), 17))
    for k, (a, b) in enumerate(BONES):
        for m, ends in ((start, a), (end, b)):
            ids = (ends,) if isinstance(ends, int) else ends
            m[k, list(ids)] = 1.0 / len(ids)
    return start, end


def _silhouette_data(mask: np.ndarray, size: int, rng: np.random.Generator,
                     unseen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Outside distance transform (size, size) in units of the image size, 0 on the ``unseen`` pixels
    (the frame does not show them), and contour points (CONTOUR_POINTS, 2) in [0, 1] image coordinates."""
    import cv2

    small = cv2.resize(mask.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA) > 0.5
    dt = cv2.distanceTransform((~small).astype(np.uint8), cv2.DIST_L2, 5).astype(np.float32) / size
    if unseen is not None:
        dt[cv2.resize(unseen.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA) > 0.5] = 0.0
    contours, _ = cv2.findContours(small.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    pts = np.concatenate([c[:, 0, :] for c in contours], 0).astype(np.float32) if contours else np.zeros((0, 2))
    if len(pts) == 0:
        pts = np.full((1, 2), size / 2.0, np.float32)
    take = np.linspace(0, len(pts) - 1, CONTOUR_POINTS).round().astype(np.int64)  # repeats on a short contour
    return dt, (pts[take] + 0.5) / size


def _cauchy(r2: torch.Tensor, sigma: float) -> torch.Tensor:
    return torch.log1p(r2 / (sigma * sigma))


# ----------------------------------------------------------------------------- the fit

class _Problem:
    """Tensors shared by the fitting phases."""

    def __init__(self, model: BodyModel, cameras: Cameras, observations: list[FrameObservation],
                 options: FitOptions):
        self.model = model
        self.options = options
        self.obs = observations
        idx = [o.index for o in observations]
        cams = cameras.subset(idx)
        self.cams = cams
        dt = model.dtype
        self.w2c = torch.as_tensor(cams.w2c, dtype=dt)
        self.K = torch.as_tensor(cams.K, dtype=dt)
        self.size = torch.tensor([cams.width, cams.height], dtype=dt)
        self.height = float(cams.height)
        rng = np.random.default_rng(options.seed)
        dts, contours = zip(*[_silhouette_data(o.mask, SILHOUETTE_SIZE, rng, o.unseen) for o in observations],
                            strict=True)
        self.dt = torch.as_tensor(np.stack(dts)[:, None], dtype=dt)  # (F, 1, S, S)
        self.contours = torch.as_tensor(np.stack(contours), dtype=dt)  # (F, C, 2)
        nv = model.num_vertices
        self.sil_vertices = torch.as_tensor(
            np.sort(rng.choice(nv, size=min(options.silhouette_vertices, nv), replace=False)))
        self.raw_kp = np.stack([o.keypoints for o in observations]).astype(np.float32)
        self.raw_conf = np.stack([np.where(o.confidences >= MIN_KEYPOINT_CONFIDENCE, o.confidences, 0.0)
                                  for o in observations]).astype(np.float32)
        # 3D landmarks (camera axes) and their confidences; 0 for frames without them
        self.raw_world = np.stack([o.world_keypoints if o.world_keypoints is not None else np.zeros((17, 3))
                                   for o in observations]).astype(np.float32)
        has_world = np.array([o.world_keypoints is not None for o in observations], np.float32)[:, None]
        self.raw_world_conf = self.raw_conf * has_world
        # a single photo only: other views see the depth (in an orbit's side views an arm held out towards
        # the camera lies on the head across the image plane)
        single = sum(o.has_keypoints for o in observations) == 1
        if single:  # a joint the photo hides but does not cut off: the detector's 3D guess holds it
            inside = np.stack([o.confidences > 0 for o in observations])
            self.raw_world_conf = np.maximum(self.raw_world_conf, HIDDEN_3D_CONFIDENCE * has_world * inside
                                             ).astype(np.float32)
        if options.hands_on_head and single:
            for f, o in enumerate(observations):
                if o.world_keypoints is not None:
                    self.raw_world[f] = onto_the_head(self.raw_world[f], o.confidences)
        ups = cams.w2c[:, :3, :3] @ np.array([0.0, 1.0, 0.0])  # the world's up in each camera's axes
        if options.facing_shoulders and single:
            for f, o in enumerate(observations):
                if o.world_keypoints is not None:
                    self.raw_world[f] = facing_shoulders(self.raw_world[f], self.raw_kp[f], o.confidences, ups[f])
        if options.frontal_arms:
            for f, o in enumerate(observations):
                if o.world_keypoints is not None:
                    # a single photo's arms are judged in the plane of its turned body (an orbit's: as seen)
                    self.raw_world[f] = frontal_arms(self.raw_world[f], self.raw_kp[f], o.confidences, ups[f],
                                                     turned=single)
        # a single photo of a seated person: its 2D knees raised, its spine held straight (fit_body)
        self.seated = single and any(
            o.has_keypoints and seated(o.confidences, o.world_keypoints, ups[f]) for f, o in enumerate(observations))
        if self.seated and options.seated_knees:
            for f, o in enumerate(observations):
                self.raw_kp[f] = raise_seated_knees(self.raw_kp[f], o.confidences, o.world_keypoints, ups[f])
        self.reach_past = options.arm_reach_past_keypoints and single
        # a single photo of a person not seated: the person's front (horizontal, world), towards the camera
        # (away from it for a photo from behind), so trusted_lean tells a lean backwards
        self.front = None
        if single and not self.seated:
            key = next(f for f, o in enumerate(observations) if o.has_keypoints)
            self.front = torch.as_tensor(horizontal_view(cams, key) * (1.0 if options.facing_away else -1.0),
                                         dtype=dt)
        start, end = _bone_matrices()
        self.bone_start = torch.as_tensor(start, dtype=dt)
        self.bone_end = torch.as_tensor(end, dtype=dt)
        self.swapped = np.zeros((len(observations), len(SWAP_GROUPS)), dtype=bool)
        self.swapped_3d = self.swapped.copy()
        self.set_swaps(self.swapped)
        names = set(model.pose_joint_names)
        fitted = [n for n in FIT_JOINTS if n in names]
        self.fit_joint_ids = torch.as_tensor([model.pose_index(n) for n in fitted], dtype=torch.int64)
        self.spine_ids = torch.as_tensor([i for i, n in enumerate(fitted) if n in SPINE_JOINTS], dtype=torch.int64)

    def set_swaps(self, swapped: np.ndarray, swapped_3d: np.ndarray | None = None) -> None:
        """Use the detections with the flagged groups' left/right exchanged: ``swapped`` (F, G) for the
        2D keypoints, ``swapped_3d`` (default: the same) for the 3D landmarks."""
        self.swapped = swapped.copy()
        self.swapped_3d = (swapped if swapped_3d is None else swapped_3d).copy()
        kps, cfs = zip(*[_swap_pairs(s, k, c) for k, c, s in zip(self.raw_kp, self.raw_conf, swapped, strict=True)],
                       strict=True)
        dt = self.model.dtype
        self.kp = torch.as_tensor(np.stack(kps), dtype=dt)
        self.conf = torch.as_tensor(np.stack(cfs), dtype=dt)
        reach = [reach_directions(k, c) if self.reach_past else np.zeros((17, 2)) for k, c in zip(kps, cfs, strict=True)]
        self.reach = torch.as_tensor(np.stack(reach), dtype=dt)  # (F, 17, 2)
        dirs, confs = zip(*[self._observed_bones(*_swap_pairs(s, w, c)) for w, c, s in zip(
            self.raw_world, self.raw_world_conf, self.swapped_3d, strict=True)], strict=True)
        self.bone_dir = torch.as_tensor(np.stack(dirs), dtype=dt)  # (F, B, 3) unit
        self.bone_conf = torch.as_tensor(np.stack(confs), dtype=dt)  # (F, B)
        # (F, 3) the detector's torso for torso_term: each frame's camera axes turned into the world's,
        # then trusted_lean; +Y for a frame without 3D landmarks
        up = torch.tensor([0.0, 1.0, 0.0], dtype=dt)
        seen = torch.einsum("fi,fij->fj", self.bone_dir[:, SPINE_BONE], self.w2c[:, :3, :3])
        self.torso_seen = torch.where(self.bone_conf[:, SPINE_BONE, None] > 0, trusted_lean(seen, up, self.front), up)
        # (F, 2) for turn_term: the detector's shoulder and hip lines' turn, and their weights where it reads a
        # clear turn (both lines within the range, the same way)
        sel = list(TURN_BONES)
        lines = self.bone_dir[:, sel]
        self.turn_seen = torch.atan2(lines[..., 2], lines[..., 0].abs())
        turn = self.turn_seen.abs()
        clear = ((turn >= np.radians(TURN_SEEN_DEG)).all(-1) & (turn <= np.radians(TURN_MAX_DEG)).all(-1)
                 & (torch.sign(self.turn_seen[:, 0]) == torch.sign(self.turn_seen[:, 1])))
        self.turn_conf = self.bone_conf[:, sel] * clear[:, None]

    def _observed_bones(self, world: np.ndarray, conf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit bone directions (B, 3) of 3D landmarks (17, 3) and their weights (B,): the confidence
        of the least confident joint involved."""
        start, end = self.bone_start.numpy().astype(np.float64), self.bone_end.numpy().astype(np.float64)
        d = end @ world - start @ world
        d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-6)
        involved = (start + end) > 0
        return d, np.array([float(conf[m].min()) for m in involved])

    def decide_swaps(self, coco17: torch.Tensor) -> int:
        """Per frame and group, keep the L/R assignment nearer the model: for the 2D keypoints the one
        nearer its projection, for the 3D landmarks (decided on their own: where the keypoints of a
        side view overlap, the 2D decision is a coin toss but the 3D one is not) the one whose bones
        point more like the model's. Returns how many 2D decisions changed."""
        with torch.no_grad():
            proj, _ = project(coco17, self.w2c, self.K)
            model_cam = (coco17 @ self.w2c[:, :3, :3].transpose(1, 2)).numpy().astype(np.float64)  # (F, 17, 3)
        proj = proj.numpy()
        new = self.swapped.copy()
        new_3d = self.swapped_3d.copy()
        start, end = self.bone_start.numpy().astype(np.float64), self.bone_end.numpy().astype(np.float64)
        for f in range(len(self.obs)):
            model_dir = end @ model_cam[f] - start @ model_cam[f]
            model_dir /= np.maximum(np.linalg.norm(model_dir, axis=-1, keepdims=True), 1e-6)
            for g, pairs in enumerate(SWAP_GROUPS.values()):
                cost = [0.0, 0.0]
                for a, b in pairs:
                    ka, kb = self.raw_kp[f, a], self.raw_kp[f, b]
                    ca, cb = self.raw_conf[f, a], self.raw_conf[f, b]
                    pa, pb = proj[f, a], proj[f, b]
                    cost[0] += ca * np.linalg.norm(ka - pa) + cb * np.linalg.norm(kb - pb)
                    cost[1] += ca * np.linalg.norm(ka - pb) + cb * np.linalg.norm(kb - pa)
                new[f, g] = cost[1] < cost[0]
                if self.raw_world_conf[f].any():
                    only = np.arange(len(SWAP_GROUPS)) == g
                    cost3 = []
                    for flags in (np.zeros_like(only), only):
                        d, c = self._observed_bones(*_swap_pairs(flags, self.raw_world[f], self.raw_world_conf[f]))
                        cost3.append(float((c * (1.0 - (d * model_dir).sum(-1))).sum()))
                    new_3d[f, g] = cost3[1] < cost3[0]
                else:
                    new_3d[f, g] = new[f, g]
        changed = int((new != self.swapped).sum())
        self.set_swaps(new, new_3d)
        return changed

    # ----- loss terms
    def keypoint_term(self, coco17: torch.Tensor, joints: Sequence[int] | None = None) -> torch.Tensor:
        proj, _ = project(coco17, self.w2c, self.K)
        residual = proj - self.kp
        past = (residual * self.reach).sum(-1, keepdim=True).clamp(min=0.0)  # beyond the detection: free
        r2 = ((residual - past * self.reach) ** 2).sum(-1) / (self.height ** 2)
        conf = self.conf if joints is None else self.conf[:, list(joints)]
        r2 = r2 if joints is None else r2[:, list(joints)]
        total = conf.sum()
        if float(total) <= 0:
            return coco17.sum() * 0.0
        return (conf * _cauchy(r2, KEYPOINT_SIGMA)).sum() / total

    def bone_direction_term(self, coco17: torch.Tensor, bones: Sequence[int] | None = None) -> torch.Tensor:
        """Confidence-weighted mean of (1 - cos) between the model's bones in each camera and the
        detector's 3D bones (:data:`BONES`, or the ``bones`` among them); 0 without 3D landmarks."""
        sel = slice(None) if bones is None else list(bones)
        conf = self.bone_conf[:, sel]
        total = conf.sum()
        if float(total) <= 0:
            return coco17.sum() * 0.0
        if coco17.dim() == 2:
            coco17 = coco17[None].expand(self.w2c.shape[0], -1, -1)
        cam = coco17 @ self.w2c[:, :3, :3].transpose(1, 2)  # directions only: no translation
        d = self.bone_end[sel] @ cam - self.bone_start[sel] @ cam  # (F, B, 3)
        cos = (d * self.bone_dir[:, sel]).sum(-1) / d.norm(dim=-1).clamp(min=1e-6)
        return (conf * (1.0 - cos)).sum() / total

    def turn_term(self, coco17: torch.Tensor) -> torch.Tensor:
        """How much less the model's shoulder and hip lines (:data:`TURN_BONES`, ``coco17`` world axes) turn
        out of each camera's image plane, about its vertical, than the detector's do where it reads a
        clear turn: per line, with ``t = atan2(z, |x|)`` of the line in camera axes (0 in the image
        plane, facing the camera or away from it; +-90 deg in profile), ``(|t_seen| - |t_model| -
        TURN_FREE_DEG)`` where positive, in radians, squared, weighted by the line's confidence.

        Only where the model's line already turns the detector's way: it is never pulled through facing
        the camera (a turn's way is the 3D landmarks' least certain reading; the 2D keypoints and the
        face tell it). Only in frames where the detector turns both lines between :data:`TURN_SEEN_DEG`
        and :data:`TURN_MAX_DEG`, the same way (after the left/right decisions, :meth:`decide_swaps`).
        0 without 3D landmarks."""
        sel = list(TURN_BONES)
        if coco17.dim() == 2:
            coco17 = coco17[None].expand(self.w2c.shape[0], -1, -1)
        cam = coco17 @ self.w2c[:, :3, :3].transpose(1, 2)
        d = self.bone_end[sel] @ cam - self.bone_start[sel] @ cam  # (F, 2, 3)
        turn = torch.atan2(d[..., 2], d[..., 0].abs())
        turn_seen = self.turn_seen  # and where it is clear, self.turn_conf (set_swaps)
        same = torch.sign(turn.detach()) == torch.sign(turn_seen)  # never pulled across facing the camera
        conf = self.turn_conf * same
        if float(conf.sum()) <= 0:
            return coco17.sum() * 0.0
        short = torch.relu(turn_seen.abs() - turn.abs() - np.radians(TURN_FREE_DEG))
        return (conf * short.pow(2)).sum() / conf.sum()

    def torso_term(self, coco17: torch.Tensor) -> torch.Tensor:
        """How far the model's torso (hip centre -> shoulder centre of ``coco17``, world axes, +Y up) lies
        outside the arc from upright to the detector's torso (its 3D landmarks turned into the world,
        then :func:`trusted_lean`): ``(angle to +Y + angle to the detector's - the arc's length) / 2``, 0 on
        the arc, beyond :data:`TORSO_FREE_DEG`, squared (radians); mean over the frames (a frame without
        3D landmarks has the arc +Y alone). A bow the detector sees costs nothing; a lean it does not
        see does."""
        d = _spine(coco17)
        up = torch.tensor([0.0, 1.0, 0.0], dtype=d.dtype)
        seen = self.torso_seen
        outside = 0.5 * (_unit_angle(d, up) + _unit_angle(d[None], seen) - _unit_angle(up[None], seen))
        return torch.relu(outside - np.radians(TORSO_FREE_DEG)).pow(2).mean()

    @staticmethod
    def stance_term(coco17: torch.Tensor, forward: torch.Tensor, head: bool = False) -> torch.Tensor:
        """A person standing still: each knee's bend (thigh vs shin of ``coco17``, world axes) beyond
        :data:`STANCE_KNEE_FREE_DEG`, in radians, squared; plus the ankles' centre's offset from the
        hips' along ``forward`` (the key camera's horizontal view direction) beyond
        :data:`STANCE_FEET_FREE`, in units of :data:`STANCE_FEET_UNIT`, squared; with ``head``, plus
        the ears' centre's offset from the shoulders' along the torso's forward (``forward`` made
        perpendicular to the hip centre -> shoulder centre line) beyond :data:`STANCE_HEAD_FREE`, in
        the same units, squared."""
        hips, knees, ankles = (coco17[list(j)] for j in zip(*LEGS, strict=True))  # (2, 3) each: left, right
        thighs, shins = knees - hips, ankles - knees
        bends = _unit_angle(thighs / thighs.norm(dim=-1, keepdim=True).clamp(min=1e-9),
                            shins / shins.norm(dim=-1, keepdim=True).clamp(min=1e-9))
        offset = ((ankles.mean(0) - hips.mean(0)) * forward).sum()
        term = (torch.relu(bends - np.radians(STANCE_KNEE_FREE_DEG)).pow(2).sum()
                + (torch.relu(offset.abs() - STANCE_FEET_FREE) / STANCE_FEET_UNIT).pow(2))
        if head:  # along the torso's own forward (its left shoulder x its spine): a bow carries the head with it
            ahead = torch.linalg.cross(coco17[5] - coco17[6], _spine(coco17), dim=-1)
            ahead = ahead / ahead.norm().clamp(min=1e-9)
            ears = ((coco17[3] + coco17[4] - coco17[5] - coco17[6]) / 2 * ahead).sum()
            term = term + (torch.relu((ears - STANCE_HEAD_AHEAD).abs() - STANCE_HEAD_FREE) / STANCE_FEET_UNIT).pow(2)
        return term

    def silhouette_terms(self, vertices: torch.Tensor, cover: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """The one-sided term (vertices inside the mask) and, with ``cover``, the contour-coverage term
        (else 0)."""
        v = vertices[..., self.sil_vertices, :]
        px, _ = project(v, self.w2c, self.K)
        uv = px / self.size  # (F, n, 2) in [0, 1]
        grid = (uv * 2.0 - 1.0)[:, :, None, :]  # (F, n, 1, 2)
        outside = torch.nn.functional.grid_sample(self.dt, grid, mode="bilinear", padding_mode="border",
                                                  align_corners=False)[:, 0, :, 0]  # (F, n)
        inside_term = outside.mean() / SILHOUETTE_SIGMA
        if not cover:
            return inside_term, inside_term * 0.0
        with torch.no_grad():  # nearest projected vertex of each contour point (gradient as min's)
            nearest = torch.cdist(self.contours, uv.detach()).argmin(-1)  # (F, C)
        picked = torch.gather(uv, uv.dim() - 2, nearest[..., None].expand(-1, -1, 2))
        cover_term = ((picked - self.contours) ** 2).sum(-1).add(1e-12).sqrt().mean() / SILHOUETTE_SIGMA
        return inside_term, cover_term

    def silhouette_loss(self, vertices: torch.Tensor, factor: float = 1.0) -> torch.Tensor:
        """``silhouette_weight`` x inside + ``silhouette_cover_weight`` x cover, times ``factor``."""
        o = self.options
        inside, cover = self.silhouette_terms(vertices, o.silhouette_cover_weight > 0)
        return factor * (o.silhouette_weight * inside + o.silhouette_cover_weight * cover)

    @property
    def uses_silhouette(self) -> bool:
        return self.options.silhouette_weight > 0 or self.options.silhouette_cover_weight > 0


def _initial_params(problem: _Problem, key: int) -> BodyParams:
    """Face the key camera; place and scale the torso from the key frame's detections."""
    model = problem.model
    params = model.zero_params(1)
    cams = problem.cams
    az = math.radians(float(cams.azimuth_deg[key]) + (180.0 if problem.options.facing_away else 0.0))
    params.global_orient = torch.tensor([[0.0, az, 0.0]], dtype=model.dtype)
    with torch.no_grad():
        out = model(params)
    coco = out.coco17[0].numpy().astype(np.float64)
    kp, conf = problem.raw_kp[key], problem.raw_conf[key]
    w2c, K = cams.w2c[key], cams.K[key]
    depth = float(w2c[2, 3])  # camera z of the world origin (the orbit centre)
    if conf[list(TORSO)].min() > 0:
        centre_px = kp[list(TORSO)].mean(0)
        torso_px = torso_length(kp)
        model_torso = torso_length(coco)
        scale = torso_px * depth / float(K[1, 1]) / max(model_torso, 1e-6)
        scale = float(np.clip(scale, 0.2, 5.0))
    else:  # silhouette only: the mask's bounding box centre and height
        mask = problem.obs[key].mask > 0.5
        ys, xs = np.nonzero(mask)
        centre_px = np.array([xs.mean(), ys.mean()]) if len(xs) else K[:2, 2]
        extent = (ys.max() - ys.min() + 1) * depth / float(K[1, 1]) if len(ys) else 1.7
        model_h = float(out.vertices[0, :, 1].max() - out.vertices[0, :, 1].min())
        scale = float(np.clip(extent / model_h, 0.2, 5.0))
    ray = np.linalg.inv(K) @ np.array([centre_px[0], centre_px[1], 1.0])
    point_cam = ray / ray[2] * depth
    c2w = np.linalg.inv(w2c)
    point = c2w[:3, :3] @ point_cam + c2w[:3, 3]
    model_centre = coco[list(TORSO)].mean(0) * scale
    params.scale = torch.tensor([[scale]], dtype=model.dtype)
    params.transl = torch.as_tensor(point - model_centre, dtype=model.dtype)[None]
    return params


def _key_frame(problem: _Problem) -> int:
    """The observation nearest the input view (azimuth 0) that has torso keypoints, else the nearest."""
    az = np.abs((problem.cams.azimuth_deg + 180.0) % 360.0 - 180.0)
    order = np.argsort(az, kind="stable")
    for k in order:
        if problem.raw_conf[k][list(TORSO)].min() > 0:
            return int(k)
    return int(order[0])


def _cosine_lr(opt: torch.optim.Optimizer, base: list[float], step: int, total: int) -> None:
    f = 0.1 + 0.9 * 0.5 * (1.0 + math.cos(math.pi * step / max(total, 1)))
    for group, lr in zip(opt.param_groups, base, strict=True):
        group["lr"] = lr * f


def fit_body(model: BodyModel, cameras: Cameras, observations: list[FrameObservation],
             options: FitOptions | None = None, logger: logging.Logger | None = None) -> FitResult:
    """Fit one static body to the observations (see the module docstring)."""
    options = options or FitOptions()
    options.check()
    lg = logger or log
    if not observations:
        raise InputError("no usable frames to fit the body to")
    if not any(o.has_keypoints for o in observations):
        raise InputError("no frame has usable keypoints (the person's shoulders and hips must be visible in at "
                         "least one frame)")
    t0 = time.perf_counter()
    torch.manual_seed(options.seed)
    problem = _Problem(model, cameras, observations, options)
    key = _key_frame(problem)
    init = _initial_params(problem, key)
    dt = model.dtype
    history: list[float] = []

    # free variables
    orient = init.global_orient.clone().requires_grad_(True)
    transl = init.transl.clone().requires_grad_(True)
    log_scale = torch.log(init.scale).clone().requires_grad_(True)
    scale0 = init.scale.clone()
    default_shape = model.default_shape(1)
    # Anny's phenotypes live in [0, 1] (fitted through a sigmoid); other backends' coefficients are free
    bounded = model.name.startswith("anny")
    shape_var = (torch.logit(default_shape.clamp(1e-3, 1 - 1e-3)) if bounded else default_shape).clone()
    shape_var.requires_grad_(True)
    joint_rot = torch.zeros(len(problem.fit_joint_ids), 3, dtype=dt, requires_grad=True)
    base_pose = init.pose.clone()

    def make_params(rot: torch.Tensor) -> BodyParams:
        pose = base_pose.clone()
        pose[0, problem.fit_joint_ids] = rot
        return BodyParams(pose=pose, shape=torch.sigmoid(shape_var) if bounded else shape_var, global_orient=orient, transl=transl,
                          scale=torch.exp(log_scale))

    def scale_prior() -> torch.Tensor:
        return options.scale_prior_weight * (log_scale - torch.log(scale0)).pow(2).sum() / len(observations)

    # phase 1: global orientation, translation, scale on the torso (and silhouettes, lightly); for a single
    # photo once more from the start where its 3D left/right decisions change (module docstring)
    n_views = sum(o.has_keypoints for o in observations)
    n1 = max(30, options.iterations // 3)
    for _ in range(2 if options.refit_turn and n_views == 1 else 1):
        decided_3d = problem.swapped_3d.copy()
        with torch.no_grad():
            orient.copy_(init.global_orient)
            transl.copy_(init.transl)
            log_scale.copy_(torch.log(init.scale))
        opt = torch.optim.Adam([orient, transl, log_scale], lr=0.02)
        for step in range(n1):
            _cosine_lr(opt, [0.02], step, n1)
            opt.zero_grad()
            out = model(make_params(joint_rot))
            loss = options.keypoint_weight * problem.keypoint_term(out.coco17[0], TORSO) + scale_prior()
            if options.bone_direction_weight > 0:
                loss = loss + options.bone_direction_weight * problem.bone_direction_term(out.coco17[0], TORSO_BONES)
            if problem.uses_silhouette:
                loss = loss + problem.silhouette_loss(out.vertices[0], 0.3)
            loss.backward()
            opt.step()
            history.append(float(loss.detach()))
        changed = problem.decide_swaps(out.coco17[0].detach())
        lg.debug("phase 1: loss %.4f, %d left/right decisions changed", history[-1], changed)
        if (problem.swapped_3d == decided_3d).all():
            break

    depth_seen = options.bone_direction_weight > 0 and all(o.has_world_keypoints for o in observations
                                                           if o.has_keypoints)
    few_views = options.single_view_pose_prior_weight_3d if depth_seen else options.single_view_pose_prior_weight
    pose_prior = max(options.pose_prior_weight, few_views / n_views ** 2)
    upright = options.upright_weight / n_views ** 2  # a prior for few views: many views see the lean
    spine = options.spine_prior_weight if problem.seated else 0.0
    lg.debug("pose prior %.3g (%d view(s) with keypoints, 3D landmarks: %s)", pose_prior, n_views, depth_seen)

    # phase 1b: the limbs' rotations from the 3D bone directions alone. The 2D keypoints cannot tell a
    # thigh pointing at the camera from one pointing away (both foreshorten the same); started from the
    # rest pose, phase 2 would keep whichever side it first slid to
    if options.bone_direction_weight > 0 and float(problem.bone_conf.sum()) > 0:
        n1b = max(20, options.iterations // 5)
        opt = torch.optim.Adam([joint_rot], lr=0.05)
        for step in range(n1b):
            _cosine_lr(opt, [0.05], step, n1b)
            opt.zero_grad()
            out = model(make_params(joint_rot))
            loss = (options.bone_direction_weight * problem.bone_direction_term(out.coco17[0])
                    + pose_prior * joint_rot.pow(2).sum(-1).mean())
            loss.backward()
            opt.step()
            history.append(float(loss.detach()))
        lg.debug("phase 1b: bone-direction loss %.4f", history[-1])

    # a single photo of a person standing still: knees straight, feet below the hips (the key camera's view),
    # an upright one's head over the shoulders
    stance_forward, head = None, False
    if n_views == 1 and options.stance_weight > 0 and standing_still(
            problem.raw_kp[key], problem.raw_conf[key], observations[key].world_keypoints, observations[key].mask):
        stance_forward = torch.as_tensor(horizontal_view(problem.cams, key), dtype=model.dtype)
        lg.debug("standing still: stance term on")

    # phase 2: pose and shape too
    n2 = options.iterations
    groups = [[orient, transl, log_scale], [joint_rot], [shape_var]]
    base_lr = [0.01, 0.03, 0.05]
    opt = torch.optim.Adam([{"params": g, "lr": lr} for g, lr in zip(groups, base_lr, strict=True)])
    decide_at = {n2 // 4, n2 // 2}
    for step in range(n2):
        report(step, n2, "it", "fit the body")
        _cosine_lr(opt, base_lr, step, n2)
        opt.zero_grad()
        params = make_params(joint_rot)
        out = model(params)
        loss = options.keypoint_weight * problem.keypoint_term(out.coco17[0])
        if options.bone_direction_weight > 0:
            loss = loss + options.bone_direction_weight * problem.bone_direction_term(out.coco17[0])
        if problem.uses_silhouette:
            loss = loss + problem.silhouette_loss(out.vertices[0])
        loss = loss + pose_prior * joint_rot.pow(2).sum(-1).mean()
        if spine > 0:
            loss = loss + spine * joint_rot[problem.spine_ids].pow(2).sum()
        if upright > 0:
            loss = loss + upright * problem.torso_term(out.coco17[0])
        if options.turn_weight > 0 and n_views == 1:
            loss = loss + options.turn_weight * problem.turn_term(out.coco17[0])
        if stance_forward is not None:
            if step == n2 // 2 and options.head_over_shoulders:  # the head joins once the torso has settled,
                head = _spine_from_upright_deg(out.coco17[0].detach()) < STANCE_HEAD_UPRIGHT_DEG  # if upright
            loss = loss + options.stance_weight * problem.stance_term(out.coco17[0], stance_forward, head=head)
        loss = loss + options.shape_prior_weight * (params.shape - default_shape).pow(2).sum() / 0.25
        loss = loss + scale_prior()
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
        if step in decide_at:
            changed = problem.decide_swaps(out.coco17[0].detach())
            if changed:
                lg.debug("phase 2 step %d: %d left/right decisions changed", step, changed)

    with torch.no_grad():
        final = make_params(joint_rot).detach()
        final.pose = final.pose.clone()
        output = model(final)
    problem.decide_swaps(output.coco17[0])

    per_frame_pose = None
    if options.refine_per_frame and options.refine_iterations > 0:
        per_frame_pose = _refine_per_frame(problem, final, options, history)

    with torch.no_grad():
        proj, _ = project(output.coco17[0], problem.w2c, problem.K)
    proj = proj.numpy()
    kp, conf = problem.kp.numpy(), problem.conf.numpy()
    err = np.linalg.norm(proj - kp, axis=-1)
    reproj = np.array([float(np.sum(e * (c > 0)) / max(1, int(np.sum(c > 0)))) if np.any(c > 0) else np.nan
                       for e, c in zip(err, conf, strict=True)])
    warnings = [w for o in observations for w in o.warnings]
    seconds = time.perf_counter() - t0
    lg.info("fitted %s to %d frame(s) in %.1f s: reprojection %.1f px (mean), %d left/right swaps",
            model.name, len(observations), seconds, float(np.nanmean(reproj)) if np.any(np.isfinite(reproj))
            else float("nan"), int(problem.swapped.sum()))
    return FitResult(
        params=final, output=_detach(output), frame_indices=[o.index for o in observations],
        reprojection_px=reproj, swapped=problem.swapped.copy(), keypoints=kp, confidences=conf, projected=proj,
        per_frame_pose=per_frame_pose, loss_history=history, seconds=seconds, warnings=warnings,
    )


def _refine_per_frame(problem: _Problem, shared: BodyParams, options: FitOptions,
                      history: list[float]) -> np.ndarray:
    """Per-frame pose corrections (fitted joints only) on top of the shared fit, pulled towards it."""
    model = problem.model
    n = len(problem.obs)
    ids = problem.fit_joint_ids
    delta = torch.zeros(n, len(ids), 3, dtype=model.dtype, requires_grad=True)
    opt = torch.optim.Adam([delta], lr=0.02)
    batch = BodyParams(pose=shared.pose.expand(n, -1, -1).clone(), shape=shared.shape.expand(n, -1),
                       global_orient=shared.global_orient.expand(n, -1), transl=shared.transl.expand(n, -1),
                       scale=shared.scale.expand(n, -1))
    for step in range(options.refine_iterations):
        _cosine_lr(opt, [0.02], step, options.refine_iterations)
        opt.zero_grad()
        pose = batch.pose.clone()
        pose[:, ids] = pose[:, ids] + delta
        out = model(BodyParams(pose=pose, shape=batch.shape, global_orient=batch.global_orient,
                               transl=batch.transl, scale=batch.scale))
        # frame f sees body f: project each body into its own camera only
        loss = options.keypoint_weight * problem.keypoint_term(out.coco17)
        if options.bone_direction_weight > 0:
            loss = loss + options.bone_direction_weight * problem.bone_direction_term(out.coco17)
        if problem.uses_silhouette:
            loss = loss + problem.silhouette_loss(out.vertices)
        loss = loss + options.refine_prior_weight * delta.pow(2).sum(-1).mean()
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
    pose = batch.pose.clone()
    pose[:, ids] = pose[:, ids] + delta.detach()
    return pose.numpy()


def _detach(out: BodyOutput) -> BodyOutput:
    return BodyOutput(vertices=out.vertices.detach(), joints=out.joints.detach(), coco17=out.coco17.detach(),
                      bone_transforms=out.bone_transforms.detach(), rest_vertices=out.rest_vertices.detach())


# ----------------------------------------------------------------------------- evaluation

def render_masks(vertices: np.ndarray, faces: np.ndarray, cameras: Cameras, max_size: int = 512) -> np.ndarray:
    """(N, h, w) coverage of the mesh rasterised by :mod:`humanvdm_core.render` in each camera, at
    most ``max_size`` px on the long side (cameras rescaled)."""
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import TexturedMesh

    s = min(1.0, max_size / max(cameras.width, cameras.height))
    cams = cameras.scaled(max(1, round(cameras.width * s)), max(1, round(cameras.height * s))) if s < 1 else cameras
    mesh = TexturedMesh(vertices=np.asarray(vertices, np.float32), faces=np.asarray(faces, np.int32))
    return render_views(mesh, cams, (0.0, 0.0, 0.0)).rgba[..., 3]


def silhouette_scores(vertices: np.ndarray, faces: np.ndarray, cameras: Cameras, masks: Sequence[np.ndarray],
                      max_size: int = 512) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per camera, the rasterised mesh (coverage > 0.5) against each mask (> 0.5): (N,) their IoU, (N,) the
    share of the mesh's silhouette outside the mask and (N,) the share of the mask the mesh covers. A body
    fitted inside a clothed person (a dress, a coat, long hair) has a low IoU and nothing outside; a wrong
    pose or size has both."""
    import cv2

    rendered = render_masks(vertices, faces, cameras, max_size)
    iou, outside, cover = [], [], []
    for r, m in zip(rendered, masks, strict=True):
        m = cv2.resize(np.asarray(m, np.float32), (r.shape[1], r.shape[0]), interpolation=cv2.INTER_AREA)
        a, b = r > 0.5, m > 0.5
        both, union = int(np.sum(a & b)), int(np.sum(a | b))
        iou.append(both / union if union else 1.0)
        outside.append(float(np.sum(a & ~b)) / max(int(np.sum(a)), 1))
        cover.append(both / max(int(np.sum(b)), 1))
    return np.array(iou), np.array(outside), np.array(cover)


def silhouette_doubts(outside: np.ndarray, cover: np.ndarray) -> list[str]:
    """What the fitted body's silhouettes make doubtful, as warnings (:func:`silhouette_scores`' per-frame
    share of the body outside the person's mask, ``outside``, and of the mask the body covers, ``cover``).
    The fit is one-sided (the body lies inside the person; clothing does not stretch it), so a low IoU
    alone is a clothed person, not a bad fit: a body more than :data:`OUTSIDE_DOUBT` outside the person
    is (a wrong pose or size); one covering less than :data:`COVER_DOUBT` of the person is said too (a
    ball gown, a big coat, or a body fitted too small)."""
    out_share, cover = float(np.mean(outside)), float(np.mean(cover))
    doubts = []
    if out_share > OUTSIDE_DOUBT:
        doubts.append(f"poor silhouette fit: {out_share:.0%} of the fitted body lies outside the person's "
                      "silhouette (mean over the frames)")
    if cover < COVER_DOUBT:
        doubts.append(f"the fitted body covers only {cover:.0%} of the person's silhouette (loose clothing, long "
                      "hair or a held object, which the body is not stretched to fill; or a body fitted too small)")
    return doubts


def silhouette_iou(vertices: np.ndarray, faces: np.ndarray, cameras: Cameras, masks: Sequence[np.ndarray],
                   max_size: int = 512) -> np.ndarray:
    """(N,) IoU of the rasterised mesh (coverage > 0.5) and each mask (> 0.5), per camera."""
    return silhouette_scores(vertices, faces, cameras, masks, max_size)[0]


def joint_error_mm(fitted: np.ndarray, truth: np.ndarray, truth_height_m: float | None = None,
                   fitted_height: float | None = None) -> float:
    """Mean Euclidean distance in mm between corresponding 3D points (K, 3).

    Both sets are in the same frame. When ``truth_height_m``/``fitted_height`` are given (the true
    subject's height in metres, the frame's height of the subject), distances are rescaled from the
    frame's units to metres of the true subject (the orbit frame normalises every subject to one
    height), i.e. the error is scale-normalised to the true body size."""
    d = np.linalg.norm(np.asarray(fitted, np.float64) - np.asarray(truth, np.float64), axis=-1)
    factor = 1.0 if truth_height_m is None or fitted_height is None else truth_height_m / fitted_height
    return float(d.mean() * factor * 1000.0)


def coco_indices(names: Sequence[str]) -> list[int]:
    return [COCO17_NAMES.index(n) for n in names]


__all__ = [
    "FIT_JOINTS", "FitOptions", "FitResult", "FrameObservation", "HumanVDMError", "SWAP_GROUPS",
    "coco_indices", "fit_body", "joint_error_mm", "load_body_model", "observe_frames", "project", "render_masks",
    "silhouette_doubts", "silhouette_iou", "silhouette_scores",
]
