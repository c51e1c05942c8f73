"""What one photo's pose landmarks say, read with the detector's known errors in mind.

The single-photo body fit (:mod:`humanvdm_core.body.fit`) takes MediaPipe's COCO-17 landmarks: 2D
``keypoints`` (17, 2 pixels) with ``confidences`` (17,), and the 3D ``world`` landmarks (17, 3, in the
photo's camera axes: x right, y down, z away from the camera; metres, any origin). Before fitting, a
single photo's landmarks pass these rules; each reads what the photo shows and either corrects a
systematic error of the detector or says which term of the fit applies:

- :func:`held_out_arms`: the arms the 2D keypoints show held out to the side (a T-pose, an A-pose, a wave);
  :func:`reach_directions`: along which image direction their elbow and wrist may lie past the detection;
- :func:`frontal_arms`: those arms turned into the body's frontal plane (the detector tilts them 18-29 deg
  towards the camera); :func:`facing_shoulders`: with both arms held out, a shoulder line read a few
  degrees turned from facing the camera faces it;
- :func:`arms_read_short` / :func:`rebuild_arms`: an arm whose 2D keypoints its own 3D landmarks
  contradict (a wrist read on the elbow under armour or a sleeve) is redrawn along the 3D directions;
- :func:`hands_on_head` / :func:`onto_the_head`: a wrist on the head is moved to the head's middle depth
  (the detector often puts a palm on the cheek 20-25 cm before the face);
- :func:`standing_still`: whether the photo shows a person standing still on both legs (the fit's stance
  term then keeps the knees straight and the feet below the hips);
- :func:`seated`: whether the photo shows a seated (or crouching) person, both thighs pointing at the
  camera (the fit then holds the spine straight); :func:`raise_seated_knees`: such a person's 2D knees,
  which the detector puts 0.06-0.14 of the torso too low against its other joints (the more, the lower
  the camera), are raised by that much.

Every function is pure (numpy in, numpy out) and leaves everything it does not name unchanged. The
thresholds are module constants, each documented where it is defined.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from humanvdm_core.body.model import axis_angle_to_matrix

# A single photo's shoulder line turned about the vertical (see facing_shoulders): this close to facing the
# camera counts as facing it, this far or more counts whole (between: a linear ramp)
TURN_NOISE_DEG = 6.0
TURN_TRUSTED_DEG = 12.0
# An arm held out to the side (see held_out_arms): in the image, the upper arm at least ARM_OUT_DEG from
# hanging straight down, the forearm within ARM_STRAIGHT_DEG of the upper arm's line, the upper arm at
# least ARM_SEEN_LENGTH of the torso's length (not pointing at the camera), its three joints at least
# ARM_CONFIDENCE sure.
ARM_OUT_DEG = 30.0
ARM_STRAIGHT_DEG = 35.0
ARM_SEEN_LENGTH = 0.4
ARM_CONFIDENCE = 0.5
# frontal_arms reads a turned body's arms in its own plane (held_out_arms' turn_cos) up to this turn ...
TURN_READ_MAX_DEG = 60.0
# ... and where a bone of the detector's, laid into that plane, points more than ARM_LIFT_DEG from where the
# photo shows it, takes the photo's direction lifted into the plane (a plane seen at least ARM_LIFT_FACING
# face on: the determinant of its horizontal and vertical directions' image components)
ARM_LIFT_DEG = 10.0
ARM_LIFT_FACING = 0.3
# An arm the detector reads short (see arms_read_short): a bone whose 3D landmarks lie at least
# ARM_IN_PLANE in the image plane (the in-plane share of its unit direction) while its 2D keypoints
# show less than ARM_READ_SHORT of the length that direction implies, the bone's length taken as
# UPPER_ARM_TORSO (FOREARM_TORSO) of the 2D torso's (typical adult proportions).
ARM_IN_PLANE = 0.7
ARM_READ_SHORT = 0.6
UPPER_ARM_TORSO = 0.6
FOREARM_TORSO = 0.5
ARMS = ((5, 7, 9), (6, 8, 10))  # COCO-17 shoulder, elbow, wrist: left, right
# A hand on the head (see hands_on_head): the wrist's 3D landmark within HEAD_TOUCH (metres, across the
# image plane) of the centre of the nose and the ears, all of them at least HEAD_CONFIDENCE sure.
HEAD_TOUCH = 0.2
HEAD_CONFIDENCE = 0.5
# ... or, its elbow raised at least ELBOW_RAISED (metres) above its shoulder and at least HEAD_CONFIDENCE
# sure, the wrist within HEAD_REACH of that centre, however sure: a hand on the head seen at a slant, the
# far one hidden behind the head (MediaPipe's 3D wrists there lie 0.22-0.27 m from the head's centre).
ELBOW_RAISED = 0.05
HEAD_REACH = 0.3
# A person standing still (see standing_still): in the photo both legs' hips, knees and ankles at least
# STANCE_CONFIDENCE sure, each thigh within STANCE_THIGH_DEG and shin within STANCE_SHIN_DEG of straight
# down and the thigh at least STANCE_THIGH_LENGTH of the torso's length (not foreshortened: a seated or
# crouching person's thighs point at the camera), the two ankles' rows within STANCE_ROWS of the
# person's height (no stride), and the detector's 3D knees bent at most STANCE_BEND_DEG.
STANCE_CONFIDENCE = 0.5
STANCE_THIGH_DEG = 35.0
STANCE_SHIN_DEG = 55.0
STANCE_THIGH_LENGTH = 0.6
STANCE_ROWS = 0.015
STANCE_BEND_DEG = 50.0
LEGS = ((11, 13, 15), (12, 14, 16))  # COCO-17 hip, knee, ankle: left, right
# A seated person (see seated): both thighs' 3D landmarks point at the camera, more than SEATED_TOWARDS of
# their unit direction along the world's horizontal towards it (so a camera above, which sees a level thigh
# point down and away, reads it the same), their hips and knees at least STANCE_CONFIDENCE sure. Their 2D knees are raised by
# KNEE_RAISE_LEVEL - KNEE_RAISE_PER_DEG x the camera's elevation (degrees; at least 0) of the 2D torso's
# length (raise_seated_knees). Measured (benchmarks/bench_landmarks.py: seven seated synthetic subjects,
# 576²), the detector's 2D knees lie, against its hips and shoulders (which stand within 0.04 of the
# true joints, as on standing subjects, whose knees do too), 0.138 of the torso too low (mean) from 10
# deg above, 0.111 from 20 and 0.063 from 30, so the thighs came out sloping 15-20 deg down. That error is
# a thigh's that points at the camera; seen at a slant its knee is read where it is or higher (the same
# subjects photographed from 45 deg to their side: 0.01-0.07 of the torso above the joint), so each knee
# gets the whole raise while its 2D thigh is at most KNEE_RAISE_FULL of the 2D torso (seated people
# facing the camera: 0.31-0.47), none from KNEE_RAISE_NONE on (from 45 deg: 0.52-0.76), linearly between.
SEATED_TOWARDS = 0.6
KNEE_RAISE_LEVEL = 0.175
KNEE_RAISE_PER_DEG = 0.0035
KNEE_RAISE_FULL = 0.48
KNEE_RAISE_NONE = 0.62
IMAGE_DOWN = np.array([0.0, 1.0])  # straight down in the image (pixel y grows downwards)


def torso_length(points: np.ndarray) -> float:
    """Distance from the hip centre to the shoulder centre of COCO-17 ``points`` (17, 2 or 3)."""
    return float(np.linalg.norm(points[[5, 6]].mean(0) - points[[11, 12]].mean(0)))


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-9)
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def facing_shoulders(world: np.ndarray, keypoints: np.ndarray, confidences: np.ndarray,
                     up: np.ndarray) -> np.ndarray:
    """The detector's 3D landmarks ``world`` (17, 3, camera axes) of a photo whose 2D ``keypoints``
    (17, 2 pixels, ``confidences`` (17,)) show both arms held out to the side (:func:`held_out_arms`: a
    T-pose, an A-pose, both arms at their length in the image plane, on the shoulder line), with the
    shoulders and arms (COCO-17 5-10) turned about the vertical (``up``, the world's up in the camera's
    axes) through the shoulders' middle, so the shoulder line's turn away from facing the camera is what
    :data:`TURN_NOISE_DEG` / :data:`TURN_TRUSTED_DEG` keep of it: none within the first, all of it from
    the second on, a linear ramp between. MediaPipe turns the shoulders of people who face the camera by
    a few degrees (synthetic frontal renders, truth 0: 2.1 to 6.9 on the stability suite's, -1.2 to 3.1
    on six walkers; the three.js Soldier 4.7), and an arm held out to the side, which follows the
    shoulder line, then stands 0.1 m in front of or behind the body at the hand. Any other photo (an arm
    that hangs or bends: a hand on the face is where the turn tells its depth), and a shoulder line read
    turned more than 90 deg (a photo from behind), is left alone. Nothing else moves."""
    out = np.asarray(world, np.float64).copy()
    if len(held_out_arms(keypoints, confidences)) < 2:
        return out.astype(np.float32)
    up = np.asarray(up, np.float64) / max(float(np.linalg.norm(up)), 1e-12)
    across = np.array([1.0, 0.0, 0.0]) - up[0] * up  # the camera's horizontal, in the horizontal plane
    line = out[5] - out[6]
    line = line - (line @ up) * up
    if np.linalg.norm(across) < 1e-6 or np.linalg.norm(line) < 1e-6:
        return out.astype(np.float32)
    across /= np.linalg.norm(across)
    turn = float(np.arctan2(np.cross(across, line) @ up, across @ line))
    if abs(turn) > np.pi / 2:  # the shoulders read left-right swapped: their turn is not small
        return out.astype(np.float32)
    noise, trusted = np.radians(TURN_NOISE_DEG), np.radians(TURN_TRUSTED_DEG)
    kept = abs(turn) if abs(turn) >= trusted else max(abs(turn) - noise, 0.0) * trusted / (trusted - noise)
    rotation = axis_angle_to_matrix(torch.as_tensor((np.sign(turn) * kept - turn) * up)).numpy()
    centre = 0.5 * (out[5] + out[6])
    out[5:11] = (out[5:11] - centre) @ rotation.T + centre
    return out.astype(np.float32)


def shoulder_turn_deg(joints: np.ndarray, w2c: np.ndarray | None = None) -> float:
    """Degrees the shoulders' line (COCO-17 5 and 6 of ``joints`` (17, 3): in the world seen by the camera
    ``w2c`` (4, 4), or in camera axes without it) is turned out of the image plane about the vertical: 0
    facing the camera or away from it, 90 in profile."""
    line = np.asarray(joints[5], np.float64) - np.asarray(joints[6], np.float64)
    if w2c is not None:
        line = line @ np.asarray(w2c, np.float64)[:3, :3].T
    return float(np.degrees(np.arctan2(abs(line[2]), abs(line[0]))))


def held_out_arms(keypoints: np.ndarray, confidences: np.ndarray, turn_cos: float = 1.0) -> list[int]:
    """The arms (indices into :data:`ARMS`: 0 left, 1 right) that the 2D ``keypoints`` (17, 2 pixels,
    ``confidences`` (17,)) show held out to the side: the upper arm at least :data:`ARM_OUT_DEG` from
    hanging straight down, the forearm within :data:`ARM_STRAIGHT_DEG` of the upper arm's line, the
    upper arm at least :data:`ARM_SEEN_LENGTH` of the torso's length (not pointing at the camera) and
    its three joints at least :data:`ARM_CONFIDENCE` sure. A T-pose, an A-pose, raised arms, a wave.

    ``turn_cos``: the cosine of the body's turn from the camera about the vertical. A turned body's
    frontal plane shows its sideways extents that much narrower, so the two angles are read with the
    arm's horizontal image components divided by it (an A-pose's far arm, 39 deg from hanging in the
    body's plane, shows 34 deg from 45 deg to the side); the length is read as the photo shows it."""
    torso = torso_length(keypoints)
    widen = np.array([1.0 / max(turn_cos, 1e-6), 1.0])
    out = []
    for arm, (shoulder, elbow, wrist) in enumerate(ARMS):
        upper_2d, fore_2d = keypoints[elbow] - keypoints[shoulder], keypoints[wrist] - keypoints[elbow]
        if (angle_deg(upper_2d * widen, IMAGE_DOWN) >= ARM_OUT_DEG
                and angle_deg(upper_2d * widen, fore_2d * widen) <= ARM_STRAIGHT_DEG
                and np.linalg.norm(upper_2d) >= ARM_SEEN_LENGTH * torso
                and min(confidences[[shoulder, elbow, wrist]]) >= ARM_CONFIDENCE):
            out.append(arm)
    return out


def reach_directions(keypoints: np.ndarray, confidences: np.ndarray) -> np.ndarray:
    """(17, 2) per COCO-17 joint the image direction along which the model's joint may lie past its
    detection at no cost (see the module docstring): for the elbow and the wrist of each arm held out
    to the side (:func:`held_out_arms`) the unit vector from the shoulder to the wrist in ``keypoints``
    (17, 2 pixels); zero for every other joint."""
    out = np.zeros((17, 2), np.float64)
    for arm in held_out_arms(keypoints, confidences):
        shoulder, elbow, wrist = ARMS[arm]
        line = np.asarray(keypoints[wrist], np.float64) - np.asarray(keypoints[shoulder], np.float64)
        if np.linalg.norm(line) > 1e-6:
            out[[elbow, wrist]] = line / np.linalg.norm(line)
    return out


def frontal_arms(world: np.ndarray, keypoints: np.ndarray, confidences: np.ndarray,
                 up: np.ndarray, turned: bool = True) -> np.ndarray:
    """The detector's 3D landmarks ``world`` (17, 3, camera axes) with every arm held out to the side
    (:func:`held_out_arms` of the 2D ``keypoints`` (17, 2 pixels) and ``confidences``; with ``turned``, read
    in the plane of a body turned as the 3D shoulder line is, up to :data:`TURN_READ_MAX_DEG`) turned into
    the body's frontal plane (the plane through the 3D shoulder line and ``up``, the world's up in the
    camera's axes): each bone laid into the plane, or, with ``turned`` (a single photo: an orbit's other
    views see the arm's depth), where laid so it points more than :data:`ARM_LIFT_DEG` from the photo's
    bone, the photo's bone lifted into the plane (the direction in the plane that the camera sees along
    it); bone lengths are kept and nothing else moves.

    MediaPipe tilts such forearms 18-29 deg towards the camera (synthetic A-pose renders at 10 deg
    elevation: true -8 deg, theirs +18 to +21), while people hold an arm out sideways in that plane (a
    T-pose, an A-pose, a wave). The far arm of a turned body it can point at the camera where the arm
    points away: laid into the plane, that forearm hung down beside the hip while the photo shows it
    held out. Arms that hang, bend (hands on the hips, holding a cup) or point at the camera keep their
    depth, and so, in a single photo (``turned``), do a :func:`seated` person's: a straight arm of
    someone seated reaches for the lap or the knees, not out to the side."""
    out = np.asarray(world, np.float64).copy()
    if turned and seated(confidences, out, np.asarray(up, np.float64)):
        return out.astype(np.float32)
    up = np.asarray(up, np.float64) / max(float(np.linalg.norm(up)), 1e-9)
    normal = np.cross(out[5] - out[6], up)
    if np.linalg.norm(normal) < 1e-6:
        return out.astype(np.float32)
    normal /= np.linalg.norm(normal)
    side = np.cross(up, normal)  # the plane's horizontal
    to_image = np.stack([side[:2], up[:2]], axis=1)  # (x, y) of side and up: a plane direction's image direction
    facing = abs(float(np.linalg.det(to_image))) >= ARM_LIFT_FACING
    turn_cos = np.cos(np.radians(min(shoulder_turn_deg(out), TURN_READ_MAX_DEG))) if turned else 1.0
    for arm in held_out_arms(keypoints, confidences, turn_cos):
        joints = ARMS[arm]
        bones = []
        for a, b in zip(joints[:-1], joints[1:], strict=True):
            bone = out[b] - out[a]
            seen = np.asarray(keypoints[b], np.float64) - np.asarray(keypoints[a], np.float64)
            flat = bone - (bone @ normal) * normal
            if turned and facing and np.linalg.norm(flat[:2]) > 1e-9 and angle_deg(flat[:2], seen) > ARM_LIFT_DEG:
                along, rise = np.linalg.solve(to_image, seen)
                flat = along * side + rise * up
            bones.append(flat / max(float(np.linalg.norm(flat)), 1e-9) * np.linalg.norm(bone))
        if min(np.linalg.norm(b) for b in bones) < 1e-6:
            continue
        out[joints[1]] = out[joints[0]] + bones[0]
        out[joints[2]] = out[joints[1]] + bones[1]
    return out.astype(np.float32)


def arms_read_short(keypoints: np.ndarray, confidences: np.ndarray, world: np.ndarray) -> list[int]:
    """The arms (indices into :data:`ARMS`: 0 left, 1 right) whose 2D ``keypoints`` (17, 2 pixels) the
    detector's own 3D landmarks ``world`` (17, 3, camera axes) contradict: an upper arm or forearm
    whose 3D direction lies in the image plane (:data:`ARM_IN_PLANE`) while its 2D length is under
    :data:`ARM_READ_SHORT` of what that direction and the torso's 2D length imply, its joints at least
    :data:`ARM_CONFIDENCE` sure (``confidences``). On the photos and renders here the ratio is 0.71 or
    more; on an armoured game character in a T-pose MediaPipe puts a 2D wrist half way along the
    forearm (0.54) or the wrists on the elbows (0.08-0.38, another render size), while its 3D arms and
    the person's mask reach out sideways."""
    torso = torso_length(keypoints)
    out = []
    for arm, (shoulder, elbow, wrist) in enumerate(ARMS):
        if min(confidences[[shoulder, elbow, wrist]]) < ARM_CONFIDENCE or torso <= 0:
            continue
        for (a, b), share in (((shoulder, elbow), UPPER_ARM_TORSO), ((elbow, wrist), FOREARM_TORSO)):
            d = np.asarray(world[b], np.float64) - np.asarray(world[a], np.float64)
            in_plane = float(np.hypot(d[0], d[1]) / max(np.linalg.norm(d), 1e-9))
            seen = float(np.linalg.norm(keypoints[b] - keypoints[a]))
            if in_plane >= ARM_IN_PLANE and seen < ARM_READ_SHORT * share * torso * in_plane:
                out.append(arm)
                break
    return out


def rebuild_arms(keypoints: np.ndarray, world: np.ndarray, arms: Sequence[int]) -> np.ndarray:
    """``keypoints`` (17, 2 pixels) with the elbow and wrist of each of ``arms`` (indices into
    :data:`ARMS`) redrawn from the shoulder along the detector's 3D bone directions (``world``, camera
    axes, their x and y), the upper arm :data:`UPPER_ARM_TORSO` and the forearm :data:`FOREARM_TORSO`
    of the torso's 2D length (a bone out of the image plane shows shorter, as its direction says)."""
    out = np.asarray(keypoints, np.float64).copy()
    torso = torso_length(out)
    for arm in arms:
        shoulder, elbow, wrist = ARMS[arm]
        for (a, b), share in (((shoulder, elbow), UPPER_ARM_TORSO), ((elbow, wrist), FOREARM_TORSO)):
            d = np.asarray(world[b], np.float64) - np.asarray(world[a], np.float64)
            out[b] = out[a] + share * torso * d[:2] / max(np.linalg.norm(d), 1e-9)
    return out.astype(np.asarray(keypoints).dtype)


def _sure_ears(confidences: np.ndarray) -> list[int]:
    """The COCO-17 ears (3, 4) at least :data:`HEAD_CONFIDENCE` sure."""
    return [e for e in (3, 4) if confidences[e] >= HEAD_CONFIDENCE]


def hands_on_head(world: np.ndarray, confidences: np.ndarray) -> list[int]:
    """The COCO-17 wrists (9 left, 10 right) that the detector's 3D landmarks ``world`` (17, 3, camera
    axes, metres, y down) place on the head: within :data:`HEAD_TOUCH` of the centre of the nose and the
    ears across the image plane (x, y), the wrist, the nose and an ear at least :data:`HEAD_CONFIDENCE`
    sure (``confidences`` (17,)) -- a palm on the cheek, a hand on the chin, at the ear or on top of the
    head -- or, under an elbow raised :data:`ELBOW_RAISED` above its shoulder and sure, within
    :data:`HEAD_REACH` of it, the wrist however sure: hands on the head seen at a slant, the far one
    behind the head."""
    ears = _sure_ears(confidences)
    if confidences[0] < HEAD_CONFIDENCE or not ears:
        return []
    world = np.asarray(world, np.float64)
    centre = world[[0] + ears, :2].mean(axis=0)
    on_head = []
    for shoulder, elbow, wrist in ARMS:
        near = float(np.linalg.norm(world[wrist, :2] - centre))
        raised = confidences[elbow] >= HEAD_CONFIDENCE and world[elbow, 1] <= world[shoulder, 1] - ELBOW_RAISED
        if (confidences[wrist] >= HEAD_CONFIDENCE and near <= HEAD_TOUCH) or (raised and near <= HEAD_REACH):
            on_head.append(wrist)
    return on_head


def onto_the_head(world: np.ndarray, confidences: np.ndarray) -> np.ndarray:
    """The detector's 3D landmarks ``world`` (17, 3, camera axes) with each wrist on the head
    (:func:`hands_on_head`) moved along the view to the head's middle depth (halfway between the nose
    and the ears); nothing else moves.

    A forearm raised to the head is foreshortened in the photo, and which way it points in depth is
    the one thing the photo does not tell: MediaPipe often takes the wrong way, putting a palm that
    rests on the cheek 20-25 cm before the nose (synthetic hand-to-face renders), and the fitted hand
    then stands before the face; hands resting on the crown it puts level with the face. A hand the
    photo shows on the head is taken as touching it: at the jaw, an ear or the crown the wrist lies
    about the head's middle."""
    out = np.asarray(world, np.float64).copy()
    on_head = hands_on_head(out, confidences)
    if on_head:
        out[on_head, 2] = 0.5 * (out[0, 2] + out[_sure_ears(confidences), 2].mean())
    return out.astype(np.float32)


def thighs_towards(world: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(2,) left and right: the share of each thigh's unit direction in the 3D landmarks ``world`` (17, 3)
    that points at the camera along the world's horizontal (``up``: the world's up in the camera's
    axes); 1 for a level thigh aimed at the camera, 0 for one hanging straight down."""
    up = up / np.linalg.norm(up)
    towards = np.array([0.0, 0.0, -1.0]) + up[2] * up  # -z without its vertical part
    towards /= max(float(np.linalg.norm(towards)), 1e-9)
    thighs = world[[13, 14]] - world[[11, 12]]
    return thighs @ towards / np.maximum(np.linalg.norm(thighs, axis=1), 1e-9)


def seated(confidences: np.ndarray, world: np.ndarray | None, up: np.ndarray) -> bool:
    """Whether the detector's 3D landmarks ``world`` (17, 3, or None) show both thighs pointing at the camera
    (:func:`thighs_towards` above :data:`SEATED_TOWARDS`): a person seated or crouching, facing it."""
    if world is None or min(confidences[[11, 12, 13, 14]]) < STANCE_CONFIDENCE:
        return False
    return bool(np.all(thighs_towards(world, up) > SEATED_TOWARDS))


def raise_seated_knees(keypoints: np.ndarray, confidences: np.ndarray, world: np.ndarray | None,
                       up: np.ndarray) -> np.ndarray:
    """2D ``keypoints`` (17, 2 pixels) with a :func:`seated` person's knees raised by ``KNEE_RAISE_LEVEL -
    KNEE_RAISE_PER_DEG`` x the camera's elevation (read off ``up``, the world's up in the camera's axes) of
    the 2D torso's length, each knee by all of it while its 2D thigh is at most :data:`KNEE_RAISE_FULL` of
    the 2D torso (the thigh points at the camera) and by none from :data:`KNEE_RAISE_NONE` on (seen at a
    slant); a copy, unchanged for anyone else."""
    out = keypoints.copy()
    if seated(confidences, world, up):
        elevation = float(np.degrees(np.arcsin(np.clip(-up[2] / np.linalg.norm(up), -1.0, 1.0))))
        torso = torso_length(keypoints)
        share = max(KNEE_RAISE_LEVEL - KNEE_RAISE_PER_DEG * elevation, 0.0)
        for hip, knee, _ in LEGS:
            thigh = float(np.linalg.norm(keypoints[knee] - keypoints[hip])) / max(torso, 1e-9)
            pointing = float(np.clip((KNEE_RAISE_NONE - thigh) / (KNEE_RAISE_NONE - KNEE_RAISE_FULL), 0.0, 1.0))
            out[knee, 1] -= share * pointing * torso
    return out


def standing_still(keypoints: np.ndarray, confidences: np.ndarray, world: np.ndarray | None,
                   mask: np.ndarray) -> bool:
    """Whether a photo shows a person standing still on both legs: 2D ``keypoints`` (17, 2 pixels) and
    ``confidences``, the detector's 3D landmarks ``world`` (17, 3, or None: no 3D check) and the person's
    ``mask``, with the thresholds of :data:`STANCE_CONFIDENCE` .. :data:`STANCE_BEND_DEG`. A stride
    (ankles at different rows), a seated or crouching person (short or bent thighs), hidden legs (a
    gown) or a leg raised sideways are not."""
    legs = [j for leg in LEGS for j in leg]
    if min(confidences[legs]) < STANCE_CONFIDENCE:
        return False
    torso = torso_length(keypoints)
    for hip, knee, ankle in LEGS:
        thigh, shin = keypoints[knee] - keypoints[hip], keypoints[ankle] - keypoints[knee]
        if (angle_deg(thigh, IMAGE_DOWN) > STANCE_THIGH_DEG or angle_deg(shin, IMAGE_DOWN) > STANCE_SHIN_DEG
                or np.linalg.norm(thigh) < STANCE_THIGH_LENGTH * torso):
            return False
        if world is not None and angle_deg(world[knee] - world[hip], world[ankle] - world[knee]) > STANCE_BEND_DEG:
            return False
    rows = np.flatnonzero((mask > 0.5).any(axis=1))
    height = float(rows[-1] - rows[0] + 1) if len(rows) else 0.0
    return abs(float(keypoints[15, 1] - keypoints[16, 1])) <= STANCE_ROWS * height

