"""Synthetic textured human subjects whose true body parameters are known (tests and benchmarks).

Contract:

- :class:`SubjectSpec` describes one subject: Anny phenotype (``gender, age, muscle, weight,
  height, proportions``, each in [0, 1]; see :mod:`humanvdm_core.body.anny_model`), a pose name from
  :data:`POSES`, skin tone, hair, clothing (shirt colours/pattern/sleeves/printed text, lower
  garment kind/colours/pattern, shoes) and a ``seed``; all of that is painted on the body. Loose
  garments that are not the body are separate meshes (see "Garment meshes" below): ``dress``
  (:data:`DRESSES`: ``"none"``, ``"skirt"`` waist to knee, ``"long"`` waist to ankle, a gown,
  ``"coat"`` shoulders to mid-calf) with
  ``dress_flare`` (the hem's half-width in metres, 0 = automatic: 1.5x (skirt) / 2x (long) / 1.3x (coat) the
  hip half-width), ``dress_color``/``dress_color2``/``dress_pattern`` (:data:`DRESS_PATTERNS`),
  and ``long_hair`` (bool). They default to off; :meth:`SubjectSpec.to_dict` (and so truth
  ``spec_json``) leaves them out while at their defaults, so specs without garments give the same
  files as before garments existed. :data:`GARMENT_EXAMPLES` names ready-made specs wearing them.
  Everything :func:`make_subject` writes is a deterministic function of the spec: the same spec
  gives byte-identical files on one machine.
- :func:`pose_params` builds the pose from joint rotations on Anny's rig (``AnnyBody``, 104 bones):
  the upper/lower arm and leg bones (``upperarm01``, ``lowerarm01``, ``upperleg01``,
  ``lowerleg01``, ``.L``/``.R``; ``shoulder01`` too for arms-raised) are turned so that each
  points along a target direction in the world frame (the smallest rotation from its zero-pose
  direction; the comment at :data:`POSES` lists them); all other bones keep Anny's zero pose.
- :func:`make_subject` writes into ``out_dir``:

  - ``subject.obj`` + ``subject.mtl`` + ``albedo.png``: the posed Anny mesh (full ``"anny"``
    topology, 13718 vertices incl. eyeballs and tongue, in Anny's vertex order) with Anny's own UV
    layout (``vt``, seams kept) and an unlit sRGB albedo of :data:`TEXTURE_SIZE` squared texels
    (OBJ object ``subject``, material ``albedo``).
  - with garments, after the body in the same OBJ: the objects ``dress`` and/or ``hair`` (in that
    order; their ``v``/``vt`` lines follow the body's, so the body's indices stay Anny's), material
    ``garments`` (a second ``newmtl`` in ``subject.mtl``) with its own :data:`GARMENT_TEXTURE`
    (``garments.png``, as large as ``albedo.png``). :func:`humanvdm_core.scans.load_scan` reads
    both materials into one mesh (packing the two textures into one atlas); ``trimesh.load`` gives
    a Scene of two geometries.
  - ``truth.npz`` (:func:`humanvdm_core.io.write_npz`, schema :data:`TRUTH_SCHEMA` version 1), see
    :func:`make_subject` for the arrays. ``BodyParams.from_numpy(truth)`` fed to ``AnnyBody()``
    reproduces the OBJ's vertices (to float32 round-off).

- World frame: the project's (metres, Y up, facing +Z, the person's left at +X). The subject stands
  on the ground: its lowest vertex (a body vertex: garments end above the ground) is at y = 0; the
  root joint (pelvis) is at x = z = 0. The ``render-training-orbits`` stage normalises scans
  (bounding-box centre to the origin, Y extent to 1.7,
  :func:`humanvdm_core.scans.normalization_transform`); ``truth.npz`` records the same 4x4
  ``normalized_from_world`` (of all the OBJ's vertices, garments included, as the stage sees them)
  so truth joints can be mapped into the normalised scan frame.
- Texture: coloured per body part in Anny's UV layout. Body parts come from Anny's shipped
  UV segmentation map (``anny/data/segmentation/body_parts_segmentation.png``: head, hands, feet,
  eyeballs, mouth cavity, tongue; the rest is "body") split further by Anny's skinning weights
  (torso / neck / arms / legs by dominant bone group). Garment borders (waist, neckline, sleeve
  and trouser hems, shoe tops) are cut geometrically on the subject's zero-pose surface, so they
  follow the body into any pose. The face (brows, lined eyes with irises, lips) is painted on the
  front of the head only; the back of the head is hair. The shirt carries a printed badge with
  ``shirt_text`` on the front and a contrasting yoke on the back.
- Garment meshes (:func:`build_garments`), built around the posed body in the world frame; the body
  under them is unchanged (its truth parameters hold; its painted clothes stay as the spec says).
  Each is a closed, watertight, consistently wound shell with a thickness (its outside and an
  inside joined by rims), so it renders from any side (the renderer does not cull) and has an
  inside for volume tests.

  - The dress: a flared surface of revolution about a vertical axis, rings of 96 vertices from the
    painted waist (``spine04`` joint + 1 cm) down to the hem (skirt: just below the knee joints,
    12% of the way to the ankles; long: half the ankle joints' height; a coat: from 1 cm below the
    shoulder joints to 45% of the way from the knees to the ankles, 1.3x the hip half-width at the
    hem, shallow folds near the hem only). Each ring is an ellipse
    growing from the waist's cross-section (+1.2 cm) to the hem's ellipse (half-width
    ``dress_flare``, half-depth 0.85 of it; the body and the folds may push the hem further out,
    truth ``dress_hem_half_width`` is measured on the mesh) along ``s ** 1.2`` (s = 0 at the
    waist, 1 at the hem); wherever the torso, legs or feet (points sampled on their triangles, not only the
    vertices) come within 1.2 cm of it, it is pushed out (beyond the body's support in each
    direction), it is never narrower than the ring above (cloth hangs), and soft folds (outward
    only, growing towards the hem) ripple it. The arms are not avoided: hanging hands may rest
    on or sink into the cloth. The ring centre moves linearly from the waist's centre to the centre
    of the legs at the hem, so the dress follows a walking stride (stretched over the leading
    leg). Only the upright poses :data:`GARMENT_POSES` take a dress; ``seated`` raises
    :class:`ConfigError`. The texture: the pattern (stripes by height; tartan checks that widen
    towards the hem; dots where the surface cuts jittered 3D balls) with fold valleys shaded, a
    waistband and a hem band in ``dress_color2``, the inside/lining in a dark ``dress_color``.
  - Long hair (any pose): strands fan from the front hairline (a pole 40 degrees forward of the
    top of the head) over the top, back and sides of the head (95 degrees either side of the
    back, so the face stays clear), 6 mm beyond the skull, each leaving the head where it is
    furthest from the head's vertical axis and hanging from there to 3 cm below the ``spine01``
    joint (about the shoulder blades), splaying out 30%, leaning back (at most 50 degrees) to pass
    6 mm behind the neck, shoulders and back. 1.6 cm thick; ``hair_color`` with strands, a darker
    underside.
- :func:`random_specs` draws varied, reproducible specs for benchmarks (no garment meshes).
"""

from __future__ import annotations

import functools
import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from humanvdm_core.body.anny_model import AnnyBody
from humanvdm_core.body.model import COCO17_NAMES, BodyParams
from humanvdm_core.body.uvmap import UVPositionMap
from humanvdm_core.io import write_npz, write_png
from humanvdm_core.scans import DEFAULT_SUBJECT_HEIGHT, TexturedMesh, normalization_transform
from humanvdm_core.workflow.atomic import atomic_write_text
from humanvdm_core.workflow.errors import ConfigError

TRUTH_SCHEMA = "humanvdm.synthetic_truth"
TRUTH_VERSION = 1
TEXTURE_SIZE = 1024
NORMALIZED_HEIGHT = DEFAULT_SUBJECT_HEIGHT
WORLD_CONVENTION = ("metres; Y up; facing +Z; person's left at +X; lowest vertex at y=0; "
                    "root joint (pelvis) at x=z=0")

# Poses (see _pose_aims; "out" = away from the body's midline, "forward" = +Z):
# - standing: arms hanging 7-21 degrees out (more for heavier bodies), elbows bent 15 degrees forward;
# - a-pose: straight arms 45 degrees below horizontal, legs 6 degrees out;
# - walking: left thigh 24 degrees forward with the shin 8 degrees forward (heel strike), right thigh
#   14 degrees back with the shin 42 degrees back (toe off); right arm swung forward, left arm back;
# - hands-on-hips: two-bone IK puts each wrist just outside the hip, 7 cm above the pelvis joint,
#   elbows out and slightly back;
# - arms-raised: shoulders lifted 20 degrees, arms up and 22 (upper) / 12 (fore) degrees out;
# - seated: thighs horizontal forward (hips flexed 90 degrees), shins near vertical (knees 84
#   degrees), forearms forward onto the thighs; no seat;
# - hand-to-face: two-bone IK puts the right wrist 7 cm outside and 12 cm below the right eye, the
#   palm against the cheek and jaw, the elbow down in front of the chest; the left arm hangs;
# - hands-on-head: two-bone IK puts each wrist beside the top of the head (8 cm out from the eyes'
#   middle, 9 cm above and 7 cm behind it), the hands over the crown, the elbows out to the sides;
# - hands-clasped: two-bone IK puts both wrists 2 cm either side of the midline, 5 cm above the
#   pelvis joint and just before the lower belly: the hands cross there, one over the other;
# - arms-crossed: two-bone IK puts each wrist across the midline before the lower chest, 30 cm above the
#   pelvis joint, so the hand reaches the other arm's elbow (the right forearm over the left, 3 cm
#   nearer the camera and 3 cm higher), the elbows down beside the ribs;
# - head-bowed: standing, the neck bent 45 degrees forward (reading, looking at a phone).
POSES: tuple[str, ...] = ("standing", "a-pose", "walking", "hands-on-hips", "arms-raised", "seated", "hand-to-face",
                          "hands-on-head", "hands-clasped", "arms-crossed", "head-bowed")
# the poses random_specs cycles through (fixed, so its subjects stay those of the recorded benchmarks)
RANDOM_POSES: tuple[str, ...] = POSES[:6]

RGB = tuple[int, int, int]
SKIN_TONES: dict[str, RGB] = {
    "porcelain": (246, 214, 196),
    "light": (234, 192, 164),
    "medium-light": (214, 166, 128),
    "medium": (190, 138, 98),
    "tan": (160, 108, 72),
    "brown": (122, 80, 52),
    "dark": (84, 54, 38),
    "deep": (58, 38, 28),
}
HAIR_COLORS: dict[str, RGB] = {
    "black": (28, 24, 22), "dark-brown": (62, 40, 26), "brown": (104, 70, 42), "auburn": (128, 56, 32),
    "blonde": (206, 170, 108), "grey": (168, 166, 160),
}
IRIS_COLORS: tuple[RGB, ...] = ((70, 45, 25), (50, 90, 140), (60, 110, 70), (100, 80, 50))
SHIRT_PATTERNS = ("solid", "stripes", "checks")
SLEEVES = ("short", "long")
LOWER_GARMENTS = ("trousers", "shorts", "skirt")
LOWER_PATTERNS = ("solid", "denim", "checks")
HAIR_STYLES = ("short", "long")
# a loose garment mesh: none, waist to knee, waist to ankle (a gown), shoulders to mid-calf (a long coat)
DRESSES = ("none", "skirt", "long", "coat")
DRESS_PATTERNS = ("solid", "stripes", "checks", "dots")
GARMENT_POSES: tuple[str, ...] = ("standing", "a-pose", "walking", "hands-on-hips", "arms-raised",  # dress poses
                                  "hand-to-face", "hands-on-head", "hands-clasped", "arms-crossed", "head-bowed")
GARMENT_TEXTURE = "garments.png"
_PALETTE: tuple[RGB, ...] = (
    (200, 30, 40), (30, 80, 180), (240, 200, 40), (30, 140, 70), (240, 240, 235), (25, 25, 30),
    (120, 40, 140), (240, 120, 30), (40, 170, 190), (150, 150, 155), (90, 50, 30), (230, 110, 150),
)

# the fields added with garments: left out of SubjectSpec.to_dict (and so of truth ``spec_json``) while
# at their defaults, so subjects without garments are written byte-identically to before
_GARMENT_FIELDS = ("dress", "dress_flare", "dress_color", "dress_color2", "dress_pattern", "long_hair")

_SEGMENTATION = "data/segmentation/body_parts_segmentation"
_PHENOTYPE = ("gender", "age", "muscle", "weight", "height", "proportions")


@dataclass(frozen=True)
class SubjectSpec:
    """One synthetic subject (see the module docstring). Colours are sRGB 0-255 triples."""

    gender: float = 0.5  # 0 male, 1 female
    age: float = 2 / 3  # Anny anchors: baby 0, child 1/3, young adult 2/3, old 1
    muscle: float = 0.5
    weight: float = 0.5
    height: float = 0.5
    proportions: float = 0.5
    pose: str = "standing"
    skin_tone: RGB = SKIN_TONES["medium-light"]
    hair_color: RGB = HAIR_COLORS["dark-brown"]
    hair_style: str = "short"
    eye_color: RGB = IRIS_COLORS[0]
    shirt_color: RGB = (200, 30, 40)
    shirt_color2: RGB = (240, 240, 235)  # second colour of stripes/checks, the back yoke, the badge text
    shirt_pattern: str = "stripes"
    sleeves: str = "short"
    shirt_text: str = "7"  # printed on the shirt front (a few characters)
    lower: str = "trousers"
    lower_color: RGB = (40, 60, 110)
    lower_color2: RGB = (25, 35, 70)
    lower_pattern: str = "denim"
    shoe_color: RGB = (25, 25, 30)
    seed: int = 0
    # garments that are not the body (separate meshes, see the module docstring); off by default
    dress: str = "none"  # one of DRESSES
    dress_flare: float = 0.0  # half-width of the hem in metres; 0 = automatic (1.5x / 2x the hip half-width)
    dress_color: RGB = (128, 36, 84)
    dress_color2: RGB = (236, 214, 170)  # second colour of the pattern, the waistband and the hem band
    dress_pattern: str = "solid"  # one of DRESS_PATTERNS
    long_hair: bool = False  # a hair mesh down to the shoulder blades (hair_style only paints the body)

    def __post_init__(self) -> None:
        for name in _PHENOTYPE:
            value = getattr(self, name)
            if not 0.0 <= float(value) <= 1.0:
                raise ConfigError(f"SubjectSpec.{name} must be in [0, 1], got {value}")
        for name, allowed in (("pose", POSES), ("hair_style", HAIR_STYLES), ("shirt_pattern", SHIRT_PATTERNS),
                              ("sleeves", SLEEVES), ("lower", LOWER_GARMENTS), ("lower_pattern", LOWER_PATTERNS),
                              ("dress", DRESSES), ("dress_pattern", DRESS_PATTERNS)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f"SubjectSpec.{name} must be one of {allowed}, got {getattr(self, name)!r}")
        for f in fields(self):
            if f.name.endswith(("_color", "_color2", "_tone")):
                value = tuple(int(c) for c in getattr(self, f.name))
                if len(value) != 3 or min(value) < 0 or max(value) > 255:
                    raise ConfigError(f"SubjectSpec.{f.name} must be an RGB triple in 0..255, got {value}")
                object.__setattr__(self, f.name, value)
        if len(self.shirt_text) > 4:
            raise ConfigError(f"SubjectSpec.shirt_text holds at most 4 characters, got {self.shirt_text!r}")
        flare = float(self.dress_flare)
        if flare != 0.0 and not 0.1 <= flare <= 0.8:
            raise ConfigError(f"SubjectSpec.dress_flare must be 0 (automatic) or in [0.1, 0.8] m, got {flare}")
        object.__setattr__(self, "dress_flare", flare)
        if self.dress != "none" and self.pose not in GARMENT_POSES:
            raise ConfigError(f"SubjectSpec.dress {self.dress!r} needs an upright pose {GARMENT_POSES}, "
                              f"got {self.pose!r}")
        if not isinstance(self.long_hair, (bool, np.bool_)):
            raise ConfigError(f"SubjectSpec.long_hair must be a bool, got {self.long_hair!r}")
        object.__setattr__(self, "long_hair", bool(self.long_hair))

    @property
    def shape_values(self) -> list[float]:
        """Anny phenotype values in ``AnnyBody.shape_names`` order."""
        return [float(getattr(self, name)) for name in _PHENOTYPE]

    @property
    def has_garments(self) -> bool:
        """Whether the subject wears a garment mesh (a dress or long hair)."""
        return self.dress != "none" or self.long_hair

    def to_dict(self) -> dict:
        """The spec as a dict; the garment fields are left out while at their defaults."""
        data = asdict(self)
        defaults = {f.name: f.default for f in fields(self)}
        for name in _GARMENT_FIELDS:
            if data[name] == defaults[name]:
                del data[name]
        return data

    @classmethod
    def from_dict(cls, data: dict) -> SubjectSpec:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"unknown SubjectSpec fields {unknown}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


# Example subjects wearing garment meshes (tests, benchmarks, the contact sheet
# benchmarks/results/synthetic_garments.png); build one with make_subject(GARMENT_EXAMPLES[name], out_dir).
GARMENT_EXAMPLES: dict[str, SubjectSpec] = {
    # a knee-length skirt over bare legs (painted shorts under it), long auburn hair
    "skirt_long_hair": SubjectSpec(
        gender=0.9, weight=0.45, pose="standing", skin_tone=SKIN_TONES["light"], hair_color=HAIR_COLORS["auburn"],
        hair_style="long", shirt_color=(240, 240, 235), shirt_color2=(30, 80, 180), shirt_pattern="solid",
        shirt_text="", lower="shorts", lower_pattern="solid", lower_color=(30, 80, 180), shoe_color=(150, 30, 40),
        dress="skirt", dress_color=(30, 80, 180), dress_color2=(240, 200, 40), dress_pattern="checks",
        long_hair=True, seed=11),
    # an ankle-length gown (hem half-width 0.35 m), long dark hair
    "gown": SubjectSpec(
        gender=0.85, age=0.7, pose="standing", skin_tone=SKIN_TONES["brown"], hair_color=HAIR_COLORS["black"],
        hair_style="long", shirt_color=(128, 36, 84), shirt_color2=(236, 214, 170), shirt_pattern="solid",
        shirt_text="", sleeves="long", lower="skirt", lower_pattern="solid", lower_color=(128, 36, 84),
        dress="long", dress_flare=0.35, dress_color=(128, 36, 84), dress_color2=(236, 214, 170), long_hair=True,
        seed=12),
    # a polka-dot skirt on a walking subject with short (painted) hair: the skirt drapes over the legs
    "walking_skirt": SubjectSpec(
        gender=0.7, weight=0.6, pose="walking", skin_tone=SKIN_TONES["tan"], hair_color=HAIR_COLORS["dark-brown"],
        shirt_color=(30, 140, 70), shirt_pattern="stripes", lower="shorts", lower_color=(25, 25, 30),
        dress="skirt", dress_color=(240, 120, 30), dress_color2=(250, 245, 235), dress_pattern="dots", seed=13),
    # a long camel coat (shoulders to mid-calf, its sleeves painted on the arms) over dark trousers
    "long_coat": SubjectSpec(
        gender=0.35, weight=0.55, pose="standing", skin_tone=SKIN_TONES["light"], hair_color=HAIR_COLORS["black"],
        shirt_color=(176, 132, 84), shirt_color2=(176, 132, 84), shirt_pattern="solid", shirt_text="",
        sleeves="long", lower="trousers", lower_pattern="solid", lower_color=(45, 45, 55),
        shoe_color=(70, 40, 25), dress="coat", dress_color=(176, 132, 84), dress_color2=(120, 84, 50), seed=14),
}


@dataclass
class Subject:
    """What :func:`build_subject` computes (in memory); :func:`make_subject` writes it."""

    spec: SubjectSpec
    params: BodyParams  # batch 1; reproduces ``vertices`` through AnnyBody()
    vertices: np.ndarray  # (V, 3) float32, posed, world frame, lowest vertex at y = 0
    faces: np.ndarray  # (F, 3) int64
    uvs: np.ndarray  # (T, 2) float32, v up
    uv_faces: np.ndarray  # (F, 3) int64
    joints: np.ndarray  # (J, 3) float32
    coco17: np.ndarray  # (17, 3) float32
    joint_names: list[str]
    albedo: np.ndarray  # (R, R, 3) uint8, top row first
    garments: list[Garment] = field(default_factory=list)  # the dress, the hair (when the spec has them)
    garment_albedo: np.ndarray | None = None  # (R, R, 3) uint8, the garments' texture
    garment_truth: dict = field(default_factory=dict)  # the garments' truth arrays (see make_subject)

    @property
    def all_vertices(self) -> np.ndarray:
        """(N, 3) the body's vertices followed by every garment's (the OBJ's ``v`` lines)."""
        return np.concatenate([self.vertices, *(g.vertices for g in self.garments)])


# ----------------------------------------------------------------------------- body model

@functools.lru_cache(maxsize=1)
def body_model() -> AnnyBody:
    """The shared full-topology Anny model (built once per process, float32, CPU)."""
    return AnnyBody(topology="anny")


@functools.lru_cache(maxsize=2)
def _uv_position_map(resolution: int) -> UVPositionMap:
    return UVPositionMap.from_model(body_model(), resolution)


def _forward(model: AnnyBody, params: BodyParams):
    with torch.no_grad():
        return model(params)


# ----------------------------------------------------------------------------- poses

def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation matrix taking direction ``a`` to direction ``b``."""
    a, b = _unit(a), _unit(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        helper = np.eye(3)[int(np.argmin(np.abs(a)))]  # antiparallel: turn about any perpendicular axis
        return _axis_angle(_unit(np.cross(a, helper)), np.pi)
    return _axis_angle(axis / s, float(np.arctan2(s, c)))


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix about a unit ``axis`` (Rodrigues)."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def _rotvec(R: np.ndarray) -> np.ndarray:
    """Axis-angle of a rotation matrix."""
    import roma

    return roma.rotmat_to_rotvec(torch.as_tensor(R, dtype=torch.float64)).numpy()


def _side(d, s: float) -> np.ndarray:
    """A left-side direction mirrored to side ``s`` (+1 left, -1 right)."""
    return _unit([s * d[0], d[1], d[2]])


def _deg_dir(forward_deg: float, out_deg: float, up: bool = False) -> np.ndarray:
    """Left-side limb direction: hanging down (or pointing up), swung ``forward_deg`` towards +Z and
    ``out_deg`` out to the side (+X)."""
    f, o = np.radians(forward_deg), np.radians(out_deg)
    y = np.cos(f) * np.cos(o)
    return _unit([np.sin(o), y if up else -y, np.sin(f) * np.cos(o)])


def _two_bone(shoulder: np.ndarray, l1: float, l2: float, target: np.ndarray, pole: np.ndarray):
    """Directions of the upper and lower segment of a two-bone chain reaching for ``target`` with the
    middle joint bending towards ``pole``."""
    d = target - shoulder
    dist = float(np.clip(np.linalg.norm(d), abs(l1 - l2) + 1e-4, l1 + l2 - 1e-4))
    dhat = _unit(d)
    cos_a = (l1 * l1 + dist * dist - l2 * l2) / (2 * l1 * dist)
    perp = _unit(pole - np.dot(pole, dhat) * dhat)
    elbow = shoulder + l1 * (cos_a * dhat + np.sqrt(max(0.0, 1 - cos_a * cos_a)) * perp)
    return _unit(elbow - shoulder), _unit(shoulder + dist * dhat - elbow)


def _pose_aims(name: str, joint: dict[str, np.ndarray], body_half_width: float,
               spec_weight: float) -> tuple[dict[str, tuple[str, np.ndarray]], dict[str, np.ndarray]]:
    """Per pose: ``aims`` bone -> (child joint, world direction) and ``extra`` bone -> local rotvec."""
    aims: dict[str, tuple[str, np.ndarray]] = {}
    extra: dict[str, np.ndarray] = {}

    def arm(s: float, side: str, upper, lower) -> None:
        aims[f"upperarm01.{side}"] = (f"lowerarm01.{side}", _side(upper, s))
        aims[f"lowerarm01.{side}"] = (f"wrist.{side}", _side(lower, s))

    def leg(s: float, side: str, upper, lower) -> None:
        aims[f"upperleg01.{side}"] = (f"lowerleg01.{side}", _side(upper, s))
        aims[f"lowerleg01.{side}"] = (f"foot.{side}", _side(lower, s))

    # arms hang clear of the hips: a heavier body needs them further out
    relaxed_out = 7.0 + 14.0 * max(0.0, spec_weight - 0.5) / 0.5

    def hang(s: float, side: str) -> None:
        arm(s, side, _deg_dir(3.0, relaxed_out), _deg_dir(18.0, relaxed_out - 2.0))

    def reach(side: str, target: np.ndarray, pole: np.ndarray) -> None:
        """The arm's wrist on ``target``, the elbow bending towards ``pole`` (two-bone IK)."""
        shoulder = joint[f"upperarm01.{side}"]
        elbow, wrist = joint[f"lowerarm01.{side}"], joint[f"wrist.{side}"]
        l1, l2 = np.linalg.norm(elbow - shoulder), np.linalg.norm(wrist - elbow)
        upper, lower = _two_bone(shoulder, l1, l2, target, pole)
        aims[f"upperarm01.{side}"] = (f"lowerarm01.{side}", upper)
        aims[f"lowerarm01.{side}"] = (f"wrist.{side}", lower)

    sides = ((1.0, "L"), (-1.0, "R"))
    if name == "standing":
        for s, side in sides:
            hang(s, side)
            leg(s, side, _deg_dir(0.0, 3.0), _deg_dir(0.0, 3.0))
    elif name == "a-pose":
        for s, side in sides:
            arm(s, side, _deg_dir(0.0, 45.0), _deg_dir(0.0, 45.0))
            leg(s, side, _deg_dir(0.0, 6.0), _deg_dir(0.0, 6.0))
    elif name == "walking":
        # left leg forward (heel strike), right leg back (toe off); arms swing opposite
        leg(1.0, "L", _deg_dir(24.0, 2.0), _deg_dir(8.0, 2.0))
        leg(-1.0, "R", _deg_dir(-14.0, 2.0), _deg_dir(-42.0, 2.0))
        arm(-1.0, "R", _deg_dir(22.0, relaxed_out), _deg_dir(50.0, relaxed_out))
        arm(1.0, "L", _deg_dir(-20.0, relaxed_out), _deg_dir(-8.0, relaxed_out))
    elif name == "hands-on-hips":
        for s, side in sides:
            target = np.array([s * (body_half_width + 0.035), joint["root"][1] + 0.07, joint["root"][2] - 0.01])
            reach(side, target, np.array([s * 1.0, 0.0, -0.6]))
            leg(s, side, _deg_dir(0.0, 7.0), _deg_dir(0.0, 7.0))
    elif name == "arms-raised":
        for s, side in sides:
            extra[f"shoulder01.{side}"] = np.array([0.0, 0.0, s * np.radians(20.0)])
            arm(s, side, _deg_dir(5.0, 22.0, up=True), _deg_dir(5.0, 12.0, up=True))
            leg(s, side, _deg_dir(0.0, 4.0), _deg_dir(0.0, 4.0))
    elif name == "hand-to-face":
        # the right palm against the right cheek and jaw (a phone call, a thoughtful pose), the elbow down
        # in front of the chest; the left arm hangs
        reach("R", joint["eye.R"] + np.array([-0.065, -0.12, 0.0]), np.array([-0.2, -1.0, 0.8]))
        hang(1.0, "L")
        for s, side in sides:
            leg(s, side, _deg_dir(0.0, 4.0), _deg_dir(0.0, 4.0))
    elif name == "hands-on-head":
        # both hands resting on the crown, the elbows out to the sides
        eyes = 0.5 * (joint["eye.L"] + joint["eye.R"])
        for s, side in sides:
            reach(side, eyes + np.array([s * 0.08, 0.09, -0.07]), np.array([s * 1.0, 0.0, 0.3]))
            leg(s, side, _deg_dir(0.0, 4.0), _deg_dir(0.0, 4.0))
    elif name == "hands-clasped":
        # the hands held together before the lower belly, one over the other
        for s, side in sides:
            target = np.array([s * 0.02, joint["root"][1] + 0.05, joint["root"][2] + body_half_width * 0.9 + 0.04])
            reach(side, target, np.array([s * 1.0, -0.5, -0.3]))
            leg(s, side, _deg_dir(0.0, 4.0), _deg_dir(0.0, 4.0))
    elif name == "arms-crossed":
        # the forearms folded across the lower chest, each hand reaching the other arm's elbow
        for s, side in sides:
            over = 1.0 if side == "R" else 0.0  # the right forearm lies over the left
            target = np.array([-s * (body_half_width * 0.4), joint["root"][1] + 0.30 + 0.03 * over,
                               joint["root"][2] + body_half_width * 0.9 + 0.05 + 0.03 * over])
            reach(side, target, np.array([s * 0.6, -1.0, 0.2]))
            leg(s, side, _deg_dir(0.0, 4.0), _deg_dir(0.0, 4.0))
    elif name == "head-bowed":
        for s, side in sides:
            hang(s, side)
            leg(s, side, _deg_dir(0.0, 3.0), _deg_dir(0.0, 3.0))
        aims["neck01"] = ("head", np.array([0.0, np.cos(np.radians(45.0)), np.sin(np.radians(45.0))]))
    elif name == "seated":
        for s, side in sides:
            leg(s, side, _deg_dir(90.0, 6.0), _deg_dir(6.0, 3.0))
            arm(s, side, _deg_dir(22.0, relaxed_out), _deg_dir(68.0, relaxed_out - 10.0))
    else:
        raise ConfigError(f"unknown pose {name!r}; choose one of {POSES}")
    return aims, extra


def pose_params(model: AnnyBody, name: str, shape: torch.Tensor) -> BodyParams:
    """Body parameters (batch 1) of the named pose for a shape (1, 6), global orientation zero,
    translation zero (see :func:`make_subject` for the ground placement)."""
    params = model.zero_params(1)
    params.shape = torch.as_tensor(shape, dtype=model.dtype).reshape(1, -1).clone()
    zero = _forward(model, params)
    names = model.joint_names
    joint = {n: zero.joints[0, i].double().numpy() for i, n in enumerate(names)}
    weight = float(params.shape[0, model.shape_names.index("weight")])
    aims, extra = _pose_aims(name, joint, _hip_half_width(model, zero.vertices[0].numpy(), joint), weight)
    parents = list(model.anny.bone_parents)
    glob: list[np.ndarray] = [np.eye(3)] * len(names)
    pose = np.zeros((len(names) - 1, 3))
    for i in range(1, len(names)):
        parent_g = glob[parents[i]]
        if names[i] in aims:
            child, target = aims[names[i]]
            target_g = _rotation_between(joint[child] - joint[names[i]], target)
            local = parent_g.T @ target_g
        elif names[i] in extra:
            local = _rotation_matrix(extra[names[i]])
        else:
            local = np.eye(3)
        pose[i - 1] = _rotvec(local)
        glob[i] = parent_g @ local
    params.pose = torch.as_tensor(pose[None], dtype=model.dtype)
    return params


def _rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(rotvec))
    return np.eye(3) if angle < 1e-12 else _axis_angle(np.asarray(rotvec) / angle, angle)


def _hip_half_width(model: AnnyBody, vertices: np.ndarray, joint: dict[str, np.ndarray]) -> float:
    """Half the width of the torso/leg surface just above the hip joints (zero pose)."""
    groups = _vertex_groups(model)
    y0 = joint["root"][1] + 0.07
    near = (np.abs(vertices[:, 1] - y0) < 0.02) & np.isin(groups, [_TORSO, _LEG_L, _LEG_R])
    return float(np.abs(vertices[near, 0]).max())


# ----------------------------------------------------------------------------- body parts

# skinning-weight groups (dominant bone group per vertex / texel)
_TORSO, _NECK, _HEAD, _ARM_L, _ARM_R, _HAND_L, _HAND_R, _LEG_L, _LEG_R, _FOOT_L, _FOOT_R = range(11)
# Anny segmentation labels of the eyeballs and the inside of the head (not painted as skin or hair)
_INNER_PARTS = ("mouth_cavity", "tongue", "eye_front.L", "eye_back.L", "eye_front.R", "eye_back.R",
                "eye_cavity.L", "eye_cavity.R")


def _bone_group(bone: str) -> int:
    side_l = bone.endswith(".L")
    if bone.startswith(("neck",)):
        return _NECK
    if bone.startswith(("head", "eye")):
        return _HEAD
    if bone.startswith(("upperarm", "lowerarm")):
        return _ARM_L if side_l else _ARM_R
    if bone.startswith(("wrist", "finger", "metacarpal")):
        return _HAND_L if side_l else _HAND_R
    if bone.startswith(("upperleg", "lowerleg")):
        return _LEG_L if side_l else _LEG_R
    if bone.startswith(("foot", "toe")):
        return _FOOT_L if side_l else _FOOT_R
    return _TORSO  # root, pelvis, spine, clavicle, shoulder


def _group_matrix(model: AnnyBody) -> np.ndarray:
    """(J, 11) one-hot bone -> group."""
    m = np.zeros((model.num_joints, 11))
    for j, name in enumerate(model.joint_names):
        m[j, _bone_group(name)] = 1.0
    return m


def _vertex_groups(model: AnnyBody) -> np.ndarray:
    """(V,) dominant skinning group of each vertex."""
    w = model.skinning_weights.double().numpy() @ _group_matrix(model)
    return np.argmax(w, axis=1)


def _face_segments(model: AnnyBody) -> tuple[np.ndarray, list[str]]:
    """Anny's UV segmentation label per face (sampled at the face's UV centroid, as Anny does)."""
    import cv2
    import yaml
    from anny.paths import get_anny_root_dir

    root = Path(get_anny_root_dir())
    with open(root / f"{_SEGMENTATION}.yaml") as f:
        colors = yaml.safe_load(f)["colors"]
    image = cv2.imread(str(root / f"{_SEGMENTATION}.png"), cv2.IMREAD_COLOR)[:, :, ::-1]
    h, w = image.shape[:2]
    centre = model.uvs.double().numpy()[model.uv_faces.numpy()].mean(axis=1)
    col = np.clip(np.round(centre[:, 0] * w).astype(np.int64), 0, w - 1)
    row = np.clip(np.round((1.0 - centre[:, 1]) * h).astype(np.int64), 0, h - 1)
    face_rgb = image[row, col].astype(np.int64)
    labels = list(colors)
    seg = np.zeros(len(face_rgb), dtype=np.int64)  # 0 = "body" (black) or unmatched
    for k, name in enumerate(labels):
        seg[np.all(face_rgb == np.asarray(colors[name]), axis=1)] = k
    return seg, labels


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


# ----------------------------------------------------------------------------- texture

def _col(rgb) -> np.ndarray:
    return np.asarray(rgb, dtype=np.float64) / 255.0


def _shade(rgb, factor: float) -> np.ndarray:
    return np.clip(_col(rgb) * factor, 0.0, 1.0)


def _smooth(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _badge(text: str, ring, fill, ink, size: int = 128) -> np.ndarray:
    """(size, size, 3) float badge: a disc with ``text`` centred on it; black outside the disc."""
    import cv2

    img = np.zeros((size, size, 3), np.uint8)
    c = size // 2
    cv2.circle(img, (c, c), c - 2, tuple(int(v) for v in ring), -1, lineType=cv2.LINE_AA)
    cv2.circle(img, (c, c), int(c * 0.82), tuple(int(v) for v in fill), -1, lineType=cv2.LINE_AA)
    if text:
        font = cv2.FONT_HERSHEY_DUPLEX
        scale = 1.0
        (tw, th), _ = cv2.getTextSize(text, font, scale, 3)
        scale *= min(size * 0.55 / max(tw, 1), size * 0.45 / max(th, 1))
        (tw, th), _ = cv2.getTextSize(text, font, scale, max(2, int(scale * 2.5)))
        cv2.putText(img, text, (c - tw // 2, c + th // 2), font, scale, tuple(int(v) for v in ink),
                    max(2, int(scale * 2.5)), lineType=cv2.LINE_AA)
    return img.astype(np.float64) / 255.0


def _sample_image(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Nearest sample of a float image at normalised (u right, v down) coordinates in [0, 1]."""
    h, w = img.shape[:2]
    col = np.clip((u * w).astype(np.int64), 0, w - 1)
    row = np.clip((v * h).astype(np.int64), 0, h - 1)
    return img[row, col]


def _fill_gutters(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Give every texel outside the UV islands the colour of the nearest island texel (no dark seams
    under bilinear filtering or mipmapping)."""
    import cv2

    _, labels = cv2.distanceTransformWithLabels((~valid).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    flat_valid = np.flatnonzero(valid.ravel())
    lut = np.zeros(int(labels.max()) + 1, dtype=np.int64)
    lut[labels.ravel()[flat_valid]] = flat_valid
    src = lut[labels.ravel()]
    return image.reshape(-1, 3)[src].reshape(image.shape)


class _AlbedoPainter:
    """Colours the valid texels of Anny's UV layout for one subject, region by region.

    Every texel carries its point ``P`` and unit normal ``N`` on the subject's zero-pose surface
    (world axes, root at the origin), its dominant skinning ``group``, its Anny segmentation label
    ``seg`` and one standard-normal ``noise`` value (fabric/skin grain, from the spec's seed).
    Later regions paint over earlier ones.
    """

    def __init__(self, spec: SubjectSpec, model: AnnyBody, rest_vertices: np.ndarray,
                 rest_joints: dict[str, np.ndarray], resolution: int):
        self.spec = spec
        self.uvm = _uv_position_map(resolution)
        faces = model.faces.numpy()
        tri = faces[self.uvm.face_ids]
        bary = self.uvm.barycentrics
        self.P = np.einsum("mk,mkd->md", bary, rest_vertices[tri])
        N = np.einsum("mk,mkd->md", bary, _vertex_normals(rest_vertices, faces)[tri])
        self.N = N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
        group_weights = model.skinning_weights.double().numpy() @ _group_matrix(model)
        self.group = np.argmax(np.einsum("mk,mkg->mg", bary, group_weights[tri]), axis=1)
        face_seg, seg_names = _face_segments(model)
        self.seg = np.asarray(seg_names)[face_seg[self.uvm.face_ids]]
        self.x, self.y, self.z = self.P[:, 0], self.P[:, 1], self.P[:, 2]
        self.rng = np.random.default_rng(np.random.SeedSequence([int(spec.seed), 0x5EED]))
        self.noise = self.rng.standard_normal(len(self.P))
        self.colour = np.tile(_col(spec.skin_tone), (len(self.P), 1)) * (1.0 + 0.025 * self.noise)[:, None]

        # landmarks on the zero-pose body
        J = self.J = rest_joints

        def centroid(labels: list[str]) -> np.ndarray:
            ids = [seg_names.index(label) for label in labels]
            return rest_vertices[np.unique(faces[np.isin(face_seg, ids)])].mean(axis=0)

        self.eye_l = centroid(["eye_front.L", "eye_back.L"])
        self.eye_r = centroid(["eye_front.R", "eye_back.R"])
        mouth_v = rest_vertices[np.unique(faces[face_seg == seg_names.index("mouth_cavity")])]
        self.mouth = np.array([0.0, float(mouth_v[:, 1].mean()), float(mouth_v[:, 2].max())])
        self.k = float(np.linalg.norm(self.eye_l - self.eye_r)) / 0.06  # face scale: about 1 for an adult
        self.waist_y = J["spine04"][1] + 0.01
        self.neck_y = J["neck01"][1]
        self.shoulder_y = 0.5 * (J["shoulder01.L"][1] + J["shoulder01.R"][1])
        self.shoulder_w = float(J["upperarm01.L"][0] - J["upperarm01.R"][0])  # about 0.33 m for an adult
        self.ankle_y = 0.5 * (J["foot.L"][1] + J["foot.R"][1])
        self.knee_y = 0.5 * (J["lowerleg01.L"][1] + J["lowerleg01.R"][1])
        self.spine_z = J["spine01"][2]
        self.floor_y = float(rest_vertices[:, 1].min())

    def paint(self, mask: np.ndarray, colours) -> None:
        """Set ``mask``'s texels to one colour (3,) or to their rows of a per-texel array (M, 3)."""
        colours = np.asarray(colours, dtype=np.float64)
        self.colour[mask] = colours[mask] if colours.ndim == 2 else colours

    def _per_side(self, left: str, right: str) -> np.ndarray:
        """(M, 3) joint ``left`` for texels at x >= 0 (the person's left), else joint ``right``."""
        return np.where((self.x >= 0)[:, None], self.J[left], self.J[right])

    def eyes_and_mouth(self) -> None:
        seg, P = self.seg, self.P
        for centre, side in ((self.eye_l, "L"), (self.eye_r, "R")):
            eyeball = (seg == f"eye_front.{side}") | (seg == f"eye_back.{side}")
            d = P - centre
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
            self.paint(eyeball, _col((238, 236, 230)))
            iris = _col(self.spec.eye_color)[None] * (1 + 0.1 * self.noise[:, None])
            self.paint(eyeball & (d[:, 2] > np.cos(np.radians(38))), iris)
            self.paint(eyeball & (d[:, 2] > np.cos(np.radians(16))), _col((10, 10, 12)))
        self.paint(np.isin(seg, ["mouth_cavity", "eye_cavity.L", "eye_cavity.R"]), _col((90, 30, 35)))
        self.paint(seg == "tongue", _col((190, 90, 100)))

    def head(self) -> None:
        """Lips, brows and lined eyes on the front of the head; hair on the top and back."""
        spec, x, y, z, k, J = self.spec, self.x, self.y, self.z, self.k, self.J
        head = ((self.seg == "head") | (self.group == _HEAD)) & ~np.isin(self.seg, _INNER_PARTS)
        eye_y, eye_z = 0.5 * (self.eye_l[1] + self.eye_r[1]), 0.5 * (self.eye_l[2] + self.eye_r[2])
        front = head & (z > eye_z - 0.03 * k) & (self.N[:, 2] > 0.15)
        mouth = self.mouth
        lips = front & ((x / (0.026 * k)) ** 2 + ((y - mouth[1]) / (0.0095 * k)) ** 2 < 1.0) \
            & (z > mouth[2] - 0.02 * k)
        self.paint(lips, 0.55 * _col(spec.skin_tone) + 0.45 * _col((170, 50, 60)))
        self.paint(lips & (np.abs(y - mouth[1]) < 0.0018 * k), _col((70, 20, 25)))
        for e in (self.eye_l, self.eye_r):
            dx = (x - e[0]) / (0.02 * k)
            brow_y = e[1] + (0.024 + 0.006 * (1.0 - dx ** 2)) * k
            self.paint(front & (np.abs(dx) < 1.0) & (np.abs(y - brow_y) < 0.0035 * k) & (z > e[2]),
                       _shade(spec.hair_color, 0.8))
            liner = ((x - e[0]) / (0.0175 * k)) ** 2 + ((y - e[1]) / (0.0095 * k)) ** 2
            self.paint(front & (liner < 1.0) & (liner > 0.6) & (z > e[2]), _col((35, 25, 25)))
        # the hairline: over the forehead, dropping at the temples, then behind the ears to the nape
        ear_z = 0.5 * (J["head"][2] + eye_z) - 0.045 * k
        front_line = eye_y + 0.055 * k - 0.025 * k * _smooth((np.abs(x) - 0.03 * k) / (0.04 * k))
        nape_y = J["head"][1] - 0.03 * k
        behind = _smooth((ear_z - 0.005 * k - z) / (0.03 * k))  # 0 in front of the ears, 1 behind them
        hair = head & (y > front_line + (nape_y - front_line) * behind)
        if spec.hair_style == "long":
            sides = (np.abs(x) > 0.05 * k) & (y > mouth[1]) & (z < eye_z - 0.025 * k)
            hair |= head & ((behind > 0.5) | sides)
            hair |= (self.group == _NECK) & (z < J["neck01"][2] - 0.01) & (y > self.neck_y + 0.01)
        theta = np.arctan2(x - J["head"][0], z - J["head"][2])
        strands = 0.93 + 0.09 * np.sin(theta * 90.0 + 4.0 * np.sin(y * 60.0)) + 0.04 * self.noise
        self.paint(hair, _col(spec.hair_color)[None] * strands[:, None])

    def lower_body(self) -> None:
        """Trousers / shorts / skirt over the torso below the waist and the legs, with a belt."""
        spec, P, x, y, z, noise = self.spec, self.P, self.x, self.y, self.z, self.noise
        legs = np.isin(self.group, [_LEG_L, _LEG_R]) & (self.seg == "body")
        hip = self._per_side("upperleg01.L", "upperleg01.R")
        axis = self._per_side("foot.L", "foot.R") - hip
        t_leg = np.einsum("md,md->m", P - hip, axis) / np.einsum("md,md->m", axis, axis)  # 0 hip, 1 ankle
        torso_low = (self.group == _TORSO) & (y < self.waist_y)
        lower_body = torso_low | legs
        if spec.lower == "trousers":
            garment = lower_body & (y > self.ankle_y + 0.03)
            hem = garment & (y < self.ankle_y + 0.045)
        elif spec.lower == "shorts":
            garment = torso_low | (legs & (t_leg < 0.42))
            hem = garment & legs & (t_leg > 0.38)
        else:  # skirt: one hem height across both legs
            garment = lower_body & (y > self.knee_y + 0.05)
            hem = garment & (y < self.knee_y + 0.065)
        c1, c2 = _col(spec.lower_color), _col(spec.lower_color2)
        if spec.lower_pattern == "denim":
            twill = 0.5 + 0.5 * np.sin((x + z + y * 1.6) * 2 * np.pi / 0.006)
            cloth = c1[None] * (0.9 + 0.1 * twill + 0.05 * noise)[:, None]
            off_axis = P - (hip + t_leg[:, None] * axis)  # from the hip-ankle line
            cloth[legs & (np.sign(x) * off_axis[:, 0] > 0) & (np.abs(off_axis[:, 2]) < 0.0025)] = \
                _col((200, 140, 60))  # outer side seam
        elif spec.lower_pattern == "checks":
            cloth = _checks(P, 0.045, c1, c2, 0.06) * (1.0 + 0.04 * noise)[:, None]
        else:
            cloth = c1[None] * (1.0 + 0.04 * noise)[:, None]
        if spec.lower == "skirt":  # pleats: alternating shade by the angle around the vertical axis
            cloth *= (0.85 + 0.15 * (np.floor(np.arctan2(x, z) * 18 / np.pi) % 2))[:, None]
        cloth[hem] = c2 * 0.9
        belt = torso_low & (y > self.waist_y - 0.035)
        cloth[belt] = _col((60, 38, 24)) * (1.0 + 0.05 * noise[belt])[:, None]
        cloth[belt & (np.abs(x) < 0.022) & (z > 0)] = _col((200, 190, 150))  # buckle
        self.paint(garment, cloth)

    def shoes(self) -> None:
        """Shoes over the feet and ankles: white sole, a side stripe."""
        spec, y = self.spec, self.y
        feet = np.isin(self.seg, ["foot.L", "foot.R"]) | np.isin(self.group, [_FOOT_L, _FOOT_R]) \
            | (np.isin(self.group, [_LEG_L, _LEG_R]) & (y < self.ankle_y + 0.03))
        shoe = np.tile(_col(spec.shoe_color), (len(y), 1)) * (1.0 + 0.05 * self.noise)[:, None]
        shoe[y < self.floor_y + 0.022] = _col((235, 235, 230))
        ankle_z = self._per_side("foot.L", "foot.R")[:, 2]
        stripe = (np.abs(self.N[:, 0]) > 0.6) & (np.abs(y - self.floor_y - 0.045 + 0.25 * (self.z - ankle_z)) < 0.008)
        shoe[stripe] = _col(spec.shirt_color2)
        self.paint(feet, shoe)

    def shirt(self) -> None:
        """A shirt over the torso above the waist and the arms down to the sleeve hem: collar, cuffs,
        a printed badge on the chest front, a contrasting yoke on the back."""
        spec, P, x, y, z = self.spec, self.P, self.x, self.y, self.z
        neck_z = self.J["neck01"][2]
        dip = np.where(z > neck_z, 0.07, 0.02) * np.clip(1.0 - (x / 0.075) ** 2, 0.0, 1.0)  # neckline
        torso = (self.group == _TORSO) & (y >= self.waist_y) & (self.seg == "body") & (y < self.neck_y - 0.015 - dip)
        arms = np.isin(self.group, [_ARM_L, _ARM_R]) & (self.seg == "body")
        sh = self._per_side("upperarm01.L", "upperarm01.R")
        el = self._per_side("lowerarm01.L", "lowerarm01.R")
        wr = self._per_side("wrist.L", "wrist.R")
        t_up = np.einsum("md,md->m", P - sh, el - sh) / np.einsum("md,md->m", el - sh, el - sh)
        t_fore = np.einsum("md,md->m", P - el, wr - el) / np.einsum("md,md->m", wr - el, wr - el)
        if spec.sleeves == "short":
            sleeve = arms & (t_up < 0.5)
            cuff = sleeve & (t_up > 0.44)
        else:
            sleeve = arms & (t_fore < 0.9)
            cuff = sleeve & (t_fore > 0.8)
        s1, s2 = _col(spec.shirt_color), _col(spec.shirt_color2)
        if spec.shirt_pattern == "stripes":
            period = 0.03 + 0.015 * float(self.rng.random())
            fabric = np.where(((y / period) % 1.0 < 0.45)[:, None], s2, s1)
        elif spec.shirt_pattern == "checks":
            fabric = _checks(P, 0.035 + 0.015 * float(self.rng.random()), s1, 0.6 * s1 + 0.4 * s2, 0.05, s2)
        else:
            fabric = np.tile(s1, (len(P), 1))
        fabric *= (1.0 + 0.04 * self.noise)[:, None]
        fabric[torso & (z < self.spine_z) & (y > self.shoulder_y - 0.06 * self.shoulder_w / 0.33)] = s2 * 0.92
        fabric[cuff | (torso & (y > self.neck_y - 0.03 - dip))] = s1 * 0.7
        # the badge: centred on the chest front between the waist and the shoulders
        size = 0.15 * self.shoulder_w / 0.33
        centre_y = self.waist_y + 0.62 * (self.shoulder_y - self.waist_y)
        bu, bv = (x + size / 2) / size, (centre_y + size / 2 - y) / size
        on_badge = torso & (z > self.spine_z) & (self.N[:, 2] > 0.3) & (bu >= 0) & (bu < 1) & (bv >= 0) & (bv < 1)
        solid = spec.shirt_pattern == "solid"
        badge = _badge(spec.shirt_text, ring=spec.shirt_color2, fill=spec.shirt_color2 if solid else (25, 25, 30),
                       ink=spec.shirt_color if solid else (245, 245, 240))
        sample = _sample_image(badge, bu[on_badge], bv[on_badge])
        inside = sample.sum(axis=1) > 0  # the badge image is black outside its disc
        fabric[np.flatnonzero(on_badge)[inside]] = sample[inside]
        self.paint(torso | sleeve, fabric)

    def image(self) -> np.ndarray:
        """The (R, R, 3) uint8 albedo, gutters filled."""
        R = self.uvm.resolution
        image = np.zeros((R, R, 3), dtype=np.float64)
        valid = np.zeros((R, R), dtype=bool)
        image[self.uvm.rows, self.uvm.cols] = self.colour
        valid[self.uvm.rows, self.uvm.cols] = True
        return np.clip(np.rint(_fill_gutters(image, valid) * 255.0), 0, 255).astype(np.uint8)


def _checks(P: np.ndarray, period: float, c1, c2, line_width: float, line_colour=None) -> np.ndarray:
    """(M, 3) a 3D checkerboard of ``period`` alternating ``c1``/``c2``, with thin lines (``line_width``
    of a period, colour ``line_colour``, default lighter than both) through the middle of the checks."""
    x, y, z = P[:, 0] / period, P[:, 1] / period, P[:, 2] / period
    odd = ((np.floor(x) + np.floor(y) + np.floor(z)) % 2).astype(bool)
    out = np.where(odd[:, None], np.asarray(c1, float), np.asarray(c2, float))
    lines = (np.abs(y % 1.0 - 0.5) < line_width) | (np.abs(x % 1.0 - 0.5) < line_width)
    out[lines] = 0.5 * (np.asarray(c1) + np.asarray(c2)) + 0.3 if line_colour is None else line_colour
    return out


def make_albedo(spec: SubjectSpec, model: AnnyBody, rest_vertices: np.ndarray, rest_joints: dict[str, np.ndarray],
                resolution: int = TEXTURE_SIZE) -> np.ndarray:
    """The subject's (R, R, 3) uint8 albedo in Anny's UV layout (see the module docstring).

    ``rest_vertices`` (V, 3) and ``rest_joints`` are the subject's zero-pose surface and joints
    (world axes, root at the origin): patterns and garment borders are laid out on them.
    """
    painter = _AlbedoPainter(spec, model, rest_vertices, rest_joints, resolution)
    painter.eyes_and_mouth()
    painter.head()
    painter.lower_body()
    painter.shoes()
    painter.shirt()
    return painter.image()


# ----------------------------------------------------------------------------- garments

@dataclass
class Garment:
    """A garment that is not the body: its own closed mesh and OBJ object, textured from
    :data:`GARMENT_TEXTURE` (see the module docstring)."""

    name: str  # the OBJ object: "dress" or "hair"
    vertices: np.ndarray  # (V, 3) float32, world frame
    faces: np.ndarray  # (F, 3) int64 into vertices: closed, consistently wound, normals outward
    uvs: np.ndarray  # (T, 2) float32 into the garment texture, v up
    uv_faces: np.ndarray  # (F, 3) int64 into uvs


# UV rectangles (u0, v0, u1, v1) in the garment texture: outside and lining (inside, rims) of each
_UV_DRESS = (0.01, 0.42, 0.99, 0.99)
_UV_DRESS_LINING = (0.01, 0.35, 0.99, 0.39)
_UV_HAIR = (0.01, 0.08, 0.99, 0.31)
_UV_HAIR_INNER = (0.01, 0.01, 0.99, 0.05)
_DRESS_SEGMENTS = 96  # vertices around a ring
_DRESS_MARGIN = 0.012  # from the body (its support in each direction) to the dress's outside
_DRESS_THICKNESS = 0.006


@dataclass(frozen=True)
class _Cut:
    """How one kind of dress (:data:`DRESSES`) is cut; see the module docstring."""

    from_shoulders: bool  # its top 1 cm below the shoulder joints, else 1 cm above the painted waist
    hem: float | None  # the hem this fraction of the way from the knees to the ankles; None: half the ankles' height
    flare: float  # the automatic hem half-width, times the hip half-width
    folds: int  # around a ring
    fold_depth: float  # metres at the hem for a hem half-width of 0.3 m
    fold_power: float  # the folds grow towards the hem as s ** this (s = 0 at the top, 1 at the hem)


_CUTS = {"skirt": _Cut(False, 0.12, 1.5, 12, 0.018, 1.5), "long": _Cut(False, None, 2.0, 16, 0.026, 1.5),
         "coat": _Cut(True, 0.45, 1.3, 8, 0.008, 3.0)}
_HAIR_CLEARANCE = 0.006  # from the body to the hair's inside
_HAIR_THICKNESS = 0.016


def _closed_shell(outer: np.ndarray, inner: np.ndarray, wrap: bool, rect_outer, rect_inner) -> tuple:
    """A closed, consistently wound shell between two (R, C, 3) grids of the same layout: both
    grids' quads, and rims joining them along the grid's border (the first and last rows; the first
    and last columns too unless ``wrap``, where column C-1 joins column 0). Returns
    ``(vertices, faces, uvs, uv_faces)``: the outer grid's UVs span ``rect_outer``, the inner grid's
    and the rims' ``rect_inner`` (rows top to bottom, columns left to right, one seam column when
    wrapping). Faces are wound so that the enclosed volume is positive (normals outward)."""
    R, C = outer.shape[:2]
    CU = C + 1 if wrap else C

    def vid(layer: int, r, c):
        return layer * R * C + r * C + (c % C)

    def tid(layer: int, r, c):
        return layer * R * CU + r * CU + c

    r, c = (g.ravel() for g in np.meshgrid(np.arange(R - 1), np.arange(CU - 1), indexing="ij"))
    a, b, cc, d = (r, c), (r + 1, c), (r + 1, c + 1), (r, c + 1)
    faces, uv_faces = [], []
    for layer, tris in ((0, ((a, b, cc), (a, cc, d))), (1, ((a, cc, b), (a, d, cc)))):
        for tri in tris:
            faces.append(np.stack([vid(layer, *p) for p in tri], axis=1))
            uv_faces.append(np.stack([tid(layer, *p) for p in tri], axis=1))
    # the outer grid's border as its triangles run it (p -> q); each edge gets a rim quad to its twin
    cols, rows = np.arange(CU - 1), np.arange(R - 1)
    top, bottom = np.zeros_like(cols), np.full_like(cols, R - 1)
    edges = [((top, cols + 1), (top, cols)), ((bottom, cols), (bottom, cols + 1))]
    if not wrap:
        left, right = np.zeros_like(rows), np.full_like(rows, C - 1)
        edges += [((rows, left), (rows + 1, left)), ((rows + 1, right), (rows, right))]
    for p, q in edges:
        faces += [np.stack([vid(0, *q), vid(0, *p), vid(1, *p)], axis=1),
                  np.stack([vid(0, *q), vid(1, *p), vid(1, *q)], axis=1)]
        uv_faces += [np.stack([tid(1, *q), tid(1, *p), tid(1, *p)], axis=1),
                     np.stack([tid(1, *q), tid(1, *p), tid(1, *q)], axis=1)]
    vertices = np.concatenate([outer.reshape(-1, 3), inner.reshape(-1, 3)])
    faces_a, uv_a = np.concatenate(faces).astype(np.int64), np.concatenate(uv_faces).astype(np.int64)
    tri = vertices[faces_a]
    if np.einsum("fd,fd->f", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0:
        faces_a, uv_a = faces_a[:, [0, 2, 1]], uv_a[:, [0, 2, 1]]
    uvs = np.concatenate([_grid_uvs(R, CU, rect_outer), _grid_uvs(R, CU, rect_inner)])
    return vertices, faces_a, uvs, uv_a


def _grid_uvs(rows: int, cols: int, rect) -> np.ndarray:
    u0, v0, u1, v1 = rect
    uu, vv = np.meshgrid(np.linspace(u0, u1, cols), np.linspace(v1, v0, rows))
    return np.stack([uu, vv], axis=-1).reshape(-1, 2)


def _circular_smooth(values: np.ndarray, width: int) -> np.ndarray:
    """Box filter of ``width`` (odd) along the last axis, wrapping around."""
    half = width // 2
    return np.mean([np.roll(values, k, axis=-1) for k in range(-half, half + 1)], axis=0)


def slice_extent(vertices: np.ndarray, faces: np.ndarray, y: float) -> np.ndarray | None:
    """``[x_min, x_max, z_min, z_max]`` of a mesh's cross-section by the horizontal plane at height
    ``y`` (the edge crossings), or None when the plane misses the mesh."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    points = []
    for i, j in ((0, 1), (1, 2), (2, 0)):
        a, b = tri[:, i], tri[:, j]
        da, db = a[:, 1] - y, b[:, 1] - y
        cross = da * db < 0
        t = (da[cross] / (da[cross] - db[cross]))[:, None]
        points.append(a[cross] + t * (b[cross] - a[cross]))
    p = np.concatenate(points)
    if not len(p):
        return None
    return np.array([p[:, 0].min(), p[:, 0].max(), p[:, 2].min(), p[:, 2].max()])


def _surface_samples(vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray, n: int = 4) -> np.ndarray:
    """Points on the faces whose three vertices are all in ``keep`` (V,) bool: a barycentric grid of
    ``n`` steps per edge on each (corners included; some body triangles are 5 cm long)."""
    f = faces[keep[faces].all(axis=1)]
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    ok = i + j <= n
    w = np.stack([i[ok], j[ok], n - i[ok] - j[ok]], axis=1) / n
    return np.unique(np.einsum("bk,fkd->fbd", w, vertices[f]).reshape(-1, 3), axis=0)  # shared corners/edges once


def _dress_mesh(spec: SubjectSpec, vertices: np.ndarray, faces: np.ndarray, groups: np.ndarray,
                J: dict[str, np.ndarray], rng: np.random.Generator) -> tuple[Garment, dict, np.ndarray, np.ndarray]:
    """The dress around the posed body, cut as :data:`_CUTS` says: rings of :data:`_DRESS_SEGMENTS` vertices from its top down
    to the hem, each an ellipse widening from the waist's to the hem's, pushed out wherever the
    torso, legs or feet (not the arms) come closer than :data:`_DRESS_MARGIN` (in each direction of a
    ring, beyond the body's support in that direction), never narrower than the ring above (cloth
    hangs), with soft folds growing towards the hem. Returns the garment, its truth scalars, the
    outside grid (rows, segments, 3) and a per-vertex fold shade for the texture."""
    pts = _surface_samples(vertices, faces, np.isin(groups, [_TORSO, _LEG_L, _LEG_R, _FOOT_L, _FOOT_R]))
    cut = _CUTS[spec.dress]
    shoulder_y = 0.5 * float(J["upperarm01.L"][1] + J["upperarm01.R"][1])
    # from the shoulders, or from the painted waist (the belt's top)
    y_top = shoulder_y - 0.01 if cut.from_shoulders else float(J["spine04"][1]) + 0.01
    knee_y = 0.5 * float(J["lowerleg01.L"][1] + J["lowerleg01.R"][1])
    ankle_y = 0.5 * float(J["foot.L"][1] + J["foot.R"][1])
    y_hem = max(0.5 * ankle_y, 0.015) if cut.hem is None else knee_y - cut.hem * (knee_y - ankle_y)
    rows = max(16, int(np.ceil((y_top - y_hem) / 0.02))) + 1
    ys = np.linspace(y_top, y_hem, rows)
    s = (y_top - ys) / (y_top - y_hem)  # 0 at the waist, 1 at the hem
    dy = max(0.6 * (ys[0] - ys[1]), 0.012)
    theta = 2.0 * np.pi * np.arange(_DRESS_SEGMENTS) / _DRESS_SEGMENTS
    dirs = np.stack([np.cos(theta), np.sin(theta)], axis=1)  # (x, z)

    def band(y: float) -> np.ndarray:
        return pts[np.abs(pts[:, 1] - y) < dy][:, [0, 2]]

    top, hem = band(y_top), band(y_hem)
    c_top = 0.5 * (top.min(axis=0) + top.max(axis=0))
    c_hem = 0.5 * (hem.min(axis=0) + hem.max(axis=0)) if len(hem) else c_top
    centres = c_top + (c_hem - c_top) * s[:, None]
    a_top, b_top = 0.5 * (top.max(axis=0) - top.min(axis=0)) + _DRESS_MARGIN
    hips = band(float(J["root"][1]) - 0.03)
    hip_half_width = 0.5 * float(hips[:, 0].max() - hips[:, 0].min())
    a_hem = float(spec.dress_flare) or cut.flare * hip_half_width
    a_hem = max(a_hem, a_top)
    b_hem = max(0.85 * a_hem, b_top)
    f = s ** 1.2
    a = (a_top + (a_hem - a_top) * f)[:, None]
    b = (b_top + (b_hem - b_top) * f)[:, None]
    r_ellipse = a * b / np.sqrt((b * dirs[:, 0]) ** 2 + (a * dirs[:, 1]) ** 2)
    support = np.zeros((rows, _DRESS_SEGMENTS))
    for i, y in enumerate(ys):
        q = band(float(y))
        if len(q):
            support[i] = ((q - centres[i]) @ dirs.T).max(axis=0)
    need = support + _DRESS_MARGIN
    r = np.maximum.accumulate(np.maximum(r_ellipse, need), axis=0)  # never narrower further down
    r = np.maximum(_circular_smooth(_circular_smooth(r, 7), 7), need)
    phase = rng.uniform(0.0, 2.0 * np.pi, size=2)
    fold = 0.5 + 0.5 * np.sin(cut.folds * theta + phase[0] + 0.6 * np.sin(3 * theta + phase[1]))
    amplitude = cut.fold_depth * (a_hem / 0.3) * s ** cut.fold_power
    r = r + amplitude[:, None] * fold[None]  # folds only push outwards

    def ring_points(radius: np.ndarray) -> np.ndarray:
        x = centres[:, :1] + radius * dirs[:, 0]
        z = centres[:, 1:] + radius * dirs[:, 1]
        return np.stack([x, np.broadcast_to(ys[:, None], x.shape), z], axis=-1)

    outer, inner = ring_points(r), ring_points(r - _DRESS_THICKNESS)
    v, faces, uvs, uv_faces = _closed_shell(outer, inner, True, _UV_DRESS, _UV_DRESS_LINING)
    shade = 1.0 - 0.18 * (1.0 - fold[None]) * np.sqrt(s)[:, None]
    garment = Garment("dress", v.astype(np.float32), faces, uvs.astype(np.float32), uv_faces)
    gv = garment.vertices.astype(np.float64)
    hem_ring = gv[(rows - 1) * _DRESS_SEGMENTS:rows * _DRESS_SEGMENTS]  # the outside's last ring
    knee = slice_extent(gv, faces, knee_y)
    info = {
        "dress_kind": np.array(spec.dress),
        "dress_top_y": np.float32(y_top),
        "dress_hem_y": np.float32(y_hem),
        "dress_hem_half_width": np.float32(0.5 * (hem_ring[:, 0].max() - hem_ring[:, 0].min())),
        "dress_hem_half_depth": np.float32(0.5 * (hem_ring[:, 2].max() - hem_ring[:, 2].min())),
        "dress_knee_y": np.float32(knee_y),
        "dress_knee_half_width": np.float32(0.5 * (knee[1] - knee[0])),
        "dress_knee_half_depth": np.float32(0.5 * (knee[3] - knee[2])),
    }
    return garment, info, outer, shade


def _min_filter(grid: np.ndarray, radius: int) -> np.ndarray:
    """Minimum over a (2 radius + 1)^2 window (inf padding)."""
    padded = np.pad(grid, radius, constant_values=np.inf)
    h, w = grid.shape
    out = np.full_like(grid, np.inf)
    for i in range(2 * radius + 1):
        for j in range(2 * radius + 1):
            out = np.minimum(out, padded[i:i + h, j:j + w])
    return out


def _hair_mesh(vertices: np.ndarray, faces: np.ndarray, groups: np.ndarray,
               J: dict[str, np.ndarray]) -> tuple[Garment, dict, np.ndarray]:
    """Long hair: strands fanning from the front hairline over the top, back and sides of the head
    (:data:`_HAIR_CLEARANCE` beyond the skull), each leaving the head where it is widest and hanging
    from there to the shoulder blades, leaning back (at most 50 degrees) to pass behind the neck,
    shoulders and back (not the hands), splaying out a little. The strands are the columns of the
    inside grid; the outside lies :data:`_HAIR_THICKNESS` further out along the grid's normals.
    Returns the garment, its truth scalars and the outside grid (rows, columns, 3)."""
    head = _surface_samples(vertices, faces, groups == _HEAD, 2)
    lo, hi = head.min(axis=0), head.max(axis=0)
    centre = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (float(J["head"][1]) + hi[1]), float(J["head"][2])])
    # strand directions from the centre: polar angle beta from the hairline axis a (up, 40 degrees
    # forward), azimuth phi about it from e1 (up and back) towards e2 (the person's left)
    tilt = np.radians(40.0)
    a = np.array([0.0, np.cos(tilt), np.sin(tilt)])
    e1 = np.array([0.0, np.sin(tilt), -np.cos(tilt)])
    e2 = np.array([1.0, 0.0, 0.0])
    beta = np.radians(np.linspace(6.0, 178.0, 87))[:, None, None]
    phi = np.radians(np.linspace(-95.0, 95.0, 39))[None, :, None]
    U = np.cos(beta) * a + np.sin(beta) * (np.cos(phi) * e1 + np.sin(phi) * e2)  # (B, C, 3)
    d = head - centre
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    radius = np.empty(U.shape[:2])
    for k in range(U.shape[1]):
        proj, cos = U[:, k] @ d.T, U[:, k] @ dn.T
        r = np.where(cos > np.cos(np.radians(12.0)), proj, -np.inf).max(axis=1)
        radius[:, k] = np.where(np.isfinite(r), r, np.where(cos > 0.8, proj, -np.inf).max(axis=1))
    padded = np.pad(radius, 1, mode="edge")
    smooth = np.mean([padded[i:i + radius.shape[0], j:j + radius.shape[1]] for i in range(3) for j in range(3)], axis=0)
    scalp = centre + (np.maximum(radius, smooth) + _HAIR_CLEARANCE)[..., None] * U
    # each strand leaves the head where it lies furthest from the head's vertical axis (past the crown)
    rho = np.linalg.norm((scalp - centre)[..., [0, 2]], axis=-1)
    crown = np.argmin(rho, axis=0)
    leave = np.array([c0 + int(np.argmax(rho[c0:, k])) for k, c0 in enumerate(crown)])

    # below that it hangs, behind the body's back-most point near it
    body = _surface_samples(vertices, faces, ~np.isin(groups, [_HAND_L, _HAND_R]))
    cell = 0.01
    origin = body[:, [0, 1]].min(axis=0)
    ij = np.floor((body[:, [0, 1]] - origin) / cell).astype(np.int64)
    back = np.full(ij.max(axis=0) + 1, np.inf)
    np.minimum.at(back, (ij[:, 0], ij[:, 1]), body[:, 2])
    back = _min_filter(back, 3)

    def z_back(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        i = np.floor((x - origin[0]) / cell).astype(np.int64)
        j = np.floor((y - origin[1]) / cell).astype(np.int64)
        ok = (i >= 0) & (i < back.shape[0]) & (j >= 0) & (j < back.shape[1])
        out = np.full(x.shape, np.inf)
        out[ok] = back[i[ok], j[ok]]
        return out

    y_bottom = float(J["spine01"][1]) - 0.03
    rows = 56
    inner = np.empty((rows, U.shape[1], 3))
    for k in range(U.shape[1]):
        start = scalp[leave[k], k]
        n = max(4, int(np.ceil((start[1] - y_bottom) / 0.01)))
        t = np.linspace(0.0, 1.0, n + 1)[1:]
        y = start[1] + (y_bottom - start[1]) * t
        x = centre[0] + (start[0] - centre[0]) * (1.0 + 0.3 * t)
        need = z_back(x, y) - _HAIR_CLEARANCE
        ahead = need[None, :] + 1.2 * (y[:, None] - y[None, :])  # [row, lower row]
        ahead = np.where(np.triu(np.ones((n, n), dtype=bool)), ahead, np.inf).min(axis=1)
        z = np.minimum.accumulate(np.minimum(start[2], ahead))
        strand = np.concatenate([scalp[:leave[k] + 1, k], np.stack([x, y, z], axis=1)])
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(strand, axis=0), axis=1))])
        at = np.linspace(0.0, arc[-1], rows)
        inner[:, k] = np.stack([np.interp(at, arc, strand[:, i]) for i in range(3)], axis=1)
    # the outside: along the inside grid's normals, turned away from the head's vertical axis
    normal = np.cross(np.gradient(inner, axis=1), np.gradient(inner, axis=0))
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    away = inner - centre
    away[..., 1] = 0.0
    normal *= np.where(np.einsum("rcd,rcd->rc", normal, away) < 0, -1.0, 1.0)[..., None]
    outer = inner + _HAIR_THICKNESS * normal
    v, faces, uvs, uv_faces = _closed_shell(outer, inner, False, _UV_HAIR, _UV_HAIR_INNER)
    garment = Garment("hair", v.astype(np.float32), faces, uvs.astype(np.float32), uv_faces)
    info = {"hair_bottom_y": np.float32(garment.vertices[:, 1].min()),
            "hair_top_y": np.float32(garment.vertices[:, 1].max()),
            "hair_back_z": np.float32(garment.vertices[:, 2].min())}
    return garment, info, outer


def _grid_sample(grid: np.ndarray, rf: np.ndarray, cf: np.ndarray) -> np.ndarray:
    """Bilinear sample of a (R, C, K) grid at fractional rows ``rf`` in [0, 1] (top to bottom) and
    columns ``cf`` in [0, 1]."""
    R, C = grid.shape[:2]
    r, c = rf * (R - 1), cf * (C - 1)
    r0 = np.clip(np.floor(r).astype(np.int64), 0, R - 2)
    c0 = np.clip(np.floor(c).astype(np.int64), 0, C - 2)
    wr, wc = (r - r0)[..., None], (c - c0)[..., None]
    return ((1 - wr) * ((1 - wc) * grid[r0, c0] + wc * grid[r0, c0 + 1])
            + wr * ((1 - wc) * grid[r0 + 1, c0] + wc * grid[r0 + 1, c0 + 1]))


def _garment_albedo(spec: SubjectSpec, resolution: int, dress: tuple | None, hair: np.ndarray | None,
                    rng: np.random.Generator) -> np.ndarray:
    """The (R, R, 3) uint8 garment texture: the dress's outside (pattern laid out on its 3D surface,
    fold valleys shaded, a waistband and a hem band in ``dress_color2``) and lining, the hair's
    outside (strands) and underside; gutters filled."""
    R = resolution
    image = np.zeros((R, R, 3))
    valid = np.zeros((R, R), dtype=bool)
    noise = rng.standard_normal((R, R))
    centre_u = (np.arange(R) + 0.5) / R
    centre_v = 1.0 - (np.arange(R) + 0.5) / R  # row 0 is the top of the image

    def region(rect):
        u0, v0, u1, v1 = rect
        cols = np.flatnonzero((centre_u >= u0) & (centre_u <= u1))
        rows = np.flatnonzero((centre_v >= v0) & (centre_v <= v1))
        rr, cc = np.meshgrid(rows, cols, indexing="ij")
        rf = (v1 - centre_v[rr]) / (v1 - v0)
        cf = (centre_u[cc] - u0) / (u1 - u0)
        valid[rr, cc] = True
        return rr, cc, rf, cf

    if dress is not None:
        outer, shade = dress
        grid = np.concatenate([outer, outer[:, :1]], axis=1)  # the seam column
        shade = np.concatenate([shade, shade[:, :1]], axis=1)[..., None]
        c1, c2 = _col(spec.dress_color), _col(spec.dress_color2)
        rr, cc, rf, cf = region(_UV_DRESS)
        P = _grid_sample(grid, rf, cf)
        y = P[..., 1]
        if spec.dress_pattern == "stripes":
            cloth = np.where(((y / 0.07) % 1.0 < 0.3)[..., None], c2, c1)
        elif spec.dress_pattern == "checks":  # a tartan cut on the round: checks widen towards the hem
            waist = float(np.linalg.norm(np.diff(grid[0], axis=0), axis=-1).sum())
            across = cf * max(8, 2 * round(waist / 0.12))  # about 6 cm checks at the waist
            down = y / 0.06
            odd = ((np.floor(across) + np.floor(down)) % 2).astype(bool)[..., None]
            cloth = np.where(odd, c1, 0.6 * c1 + 0.4 * c2)
            cloth[(np.abs(across % 1.0 - 0.5) < 0.06) | (np.abs(down % 1.0 - 0.5) < 0.06)] = c2
        elif spec.dress_pattern == "dots":  # where the surface cuts balls jittered about a 3D grid
            cell = np.floor(P / 0.06)
            jitter = np.stack([(np.sin(cell @ np.array(w)) * 43758.5453) % 1.0 for w in
                               ((12.9898, 78.233, 37.719), (39.346, 11.135, 83.155), (73.156, 52.235, 9.151))], axis=-1)
            centre = (cell + 0.5) * 0.06 + 0.02 * (jitter - 0.5)
            cloth = np.where((np.linalg.norm(P - centre, axis=-1) < 0.024)[..., None], c2, c1)
        else:
            cloth = np.broadcast_to(c1, P.shape).copy()
        cloth = cloth * _grid_sample(shade, rf, cf) * (1.0 + 0.03 * noise[rr, cc])[..., None]
        y_top, y_hem = grid[0, 0, 1], grid[-1, 0, 1]
        band = (y > y_top - 0.03) | (y < y_hem + 0.025)
        cloth[band] = c2 * 0.9 * (1.0 + 0.03 * noise[rr, cc][band])[:, None]
        image[rr, cc] = cloth
        rr, cc, _, _ = region(_UV_DRESS_LINING)
        image[rr, cc] = c1 * 0.6
    if hair is not None:
        colour = _col(spec.hair_color)
        rr, cc, rf, cf = region(_UV_HAIR)
        strands = 0.9 + 0.08 * np.sin(2 * np.pi * (cf * 70.0 + 0.6 * np.sin(rf * 9.0 + cf * 25.0))) \
            + 0.05 * np.sin(2 * np.pi * cf * 23.0) + 0.04 * noise[rr, cc]
        image[rr, cc] = colour * strands[..., None]
        rr, cc, _, _ = region(_UV_HAIR_INNER)
        image[rr, cc] = colour * 0.7
    return np.clip(np.rint(_fill_gutters(image, valid) * 255.0), 0, 255).astype(np.uint8)


def build_garments(spec: SubjectSpec, vertices: np.ndarray, joints: dict[str, np.ndarray],
                   texture_size: int = TEXTURE_SIZE) -> tuple[list[Garment], np.ndarray, dict]:
    """The garment meshes of a spec around its posed body (``vertices`` (V, 3) and ``joints`` in the
    world frame), the garment texture and the truth arrays (see :func:`make_subject`)."""
    if not spec.has_garments:
        return [], np.zeros((0, 0, 3), np.uint8), {}
    model = body_model()
    groups, faces = _vertex_groups(model), model.faces.numpy()
    v = np.asarray(vertices, dtype=np.float64)
    rng = np.random.default_rng(np.random.SeedSequence([int(spec.seed), 0x6A2]))
    garments, truth = [], {}
    dress = hair = None
    if spec.dress != "none":
        garment, info, outer, shade = _dress_mesh(spec, v, faces, groups, joints, rng)
        garments.append(garment)
        truth.update(info, dress_vertices=garment.vertices, dress_faces=garment.faces)
        dress = (outer, shade)
    if spec.long_hair:
        garment, info, hair = _hair_mesh(v, faces, groups, joints)
        garments.append(garment)
        truth.update(info, hair_vertices=garment.vertices, hair_faces=garment.faces)
    truth["garments"] = np.array([g.name for g in garments])
    return garments, _garment_albedo(spec, texture_size, dress, hair, rng), truth



# ----------------------------------------------------------------------------- subjects

def build_subject(spec: SubjectSpec, texture_size: int = TEXTURE_SIZE) -> Subject:
    """Pose, place and texture one subject in memory (see :func:`make_subject`)."""
    model = body_model()
    shape = torch.tensor([spec.shape_values], dtype=model.dtype)
    zero = model.zero_params(1)
    zero.shape = shape
    rest = _forward(model, zero)
    rest_vertices = rest.vertices[0].double().numpy()
    rest_joints = {n: rest.joints[0, i].double().numpy() for i, n in enumerate(model.joint_names)}
    params = pose_params(model, spec.pose, shape)
    posed = _forward(model, params)
    lift = -float(posed.vertices[0, :, 1].min())
    params.transl = torch.tensor([[0.0, lift, 0.0]], dtype=model.dtype)
    posed = _forward(model, params)
    vertices = posed.vertices[0].numpy().astype(np.float32)
    if not np.isfinite(vertices).all():
        raise RuntimeError(f"non-finite vertices for pose {spec.pose!r}")
    albedo = make_albedo(spec, model, rest_vertices, rest_joints, texture_size)
    joints = posed.joints[0].numpy().astype(np.float32)
    garments, garment_albedo, garment_truth = build_garments(
        spec, vertices, {n: joints[i].astype(np.float64) for i, n in enumerate(model.joint_names)}, texture_size)
    return Subject(
        spec=spec, params=params.detach(), vertices=vertices, faces=model.faces.numpy().copy(),
        uvs=model.uvs.numpy().astype(np.float32), uv_faces=model.uv_faces.numpy().copy(),
        joints=joints, coco17=posed.coco17[0].numpy().astype(np.float32),
        joint_names=list(model.joint_names), albedo=albedo,
        garments=garments, garment_albedo=garment_albedo if garments else None, garment_truth=garment_truth,
    )


def normalized_from_world(vertices: np.ndarray, height: float = NORMALIZED_HEIGHT) -> np.ndarray:
    """4x4 map of world points into the normalised scan frame the renderer uses
    (:func:`humanvdm_core.scans.normalization_transform`)."""
    return normalization_transform(TexturedMesh(np.asarray(vertices, dtype=np.float32),
                                                np.zeros((0, 3), dtype=np.int32)), height)


def _obj_text(subject: Subject, mtl_name: str) -> str:
    lines = ["# Human-VDM synthetic subject: Anny 'anny' topology; " + WORLD_CONVENTION,
             f"mtllib {mtl_name}", "o subject", "usemtl albedo"]
    lines += [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in subject.vertices.tolist()]
    lines += [f"vt {a:.6f} {b:.6f}" for a, b in subject.uvs.tolist()]
    f, t = subject.faces + 1, subject.uv_faces + 1
    lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for (a, b, c), (ta, tb, tc) in zip(f.tolist(), t.tolist(), strict=True)]
    v_offset, t_offset = len(subject.vertices), len(subject.uvs)
    for g in subject.garments:  # after the body: the body's indices stay Anny's
        lines += [f"o {g.name}", "usemtl garments"]
        lines += [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in g.vertices.tolist()]
        lines += [f"vt {a:.6f} {b:.6f}" for a, b in g.uvs.tolist()]
        f, t = g.faces + 1 + v_offset, g.uv_faces + 1 + t_offset
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}"
                  for (a, b, c), (ta, tb, tc) in zip(f.tolist(), t.tolist(), strict=True)]
        v_offset, t_offset = v_offset + len(g.vertices), t_offset + len(g.uvs)
    return "\n".join(lines) + "\n"


def make_subject(spec: SubjectSpec, out_dir: str | Path, texture_size: int = TEXTURE_SIZE) -> Path:
    """Write one subject into ``out_dir``; returns the path of ``subject.obj``.

    ``truth.npz`` holds: ``pose``, ``shape``, ``global_orient``, ``transl``, ``scale`` (the
    ``BodyParams`` arrays, batch 1, for ``AnnyBody(topology="anny")``), ``body_model``,
    ``shape_names``/``shape_values``, ``pose_name``, ``joint_names`` + ``joints`` (J, 3) posed joint
    centres, ``coco17_names`` + ``coco17`` (17, 3), ``num_vertices``, ``num_faces``,
    ``world_convention``, ``bbox_min``/``bbox_max`` (3,) of the vertices, ``normalized_from_world``
    (4, 4, see :func:`normalized_from_world`) and ``spec_json`` (the spec as JSON). Coordinates are
    float32 metres in the world frame of the module docstring. ``num_vertices``/``num_faces`` count
    the body; ``bbox_*`` and ``normalized_from_world`` cover all the OBJ's vertices (garments too).

    With garments it also holds ``garments`` (the object names in OBJ order) and, per garment, its
    mesh in the world frame (faces index that garment's own vertices from 0; each garment's
    ``v`` lines follow the previous object's in the OBJ):

    - dress: ``dress_vertices`` (N, 3) float32, ``dress_faces`` (M, 3) int64, ``dress_kind``,
      ``dress_top_y``/``dress_hem_y`` (waist and hem heights), ``dress_hem_half_width``/
      ``dress_hem_half_depth`` (half the X / Z extent of the hem's outside ring),
      ``dress_knee_y`` (the knee joints' mean height) and ``dress_knee_half_width``/
      ``dress_knee_half_depth`` (half the X / Z extent of the dress's cross-section there);
    - hair: ``hair_vertices``, ``hair_faces``, ``hair_top_y``, ``hair_bottom_y``, ``hair_back_z``
      (its highest and lowest point, its back-most z).
    """
    subject = build_subject(spec, texture_size)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_png(out / "albedo.png", subject.albedo)
    mtl = "newmtl albedo\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd albedo.png\n"
    if subject.garments:
        write_png(out / GARMENT_TEXTURE, subject.garment_albedo)
        mtl += f"newmtl garments\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {GARMENT_TEXTURE}\n"
    atomic_write_text(out / "subject.mtl", mtl)
    obj_path = out / "subject.obj"
    atomic_write_text(obj_path, _obj_text(subject, "subject.mtl"))
    model = body_model()
    everything = subject.all_vertices
    arrays = dict(subject.params.to_numpy())
    arrays.update(
        body_model=np.array(model.name),
        shape_names=np.array(model.shape_names),
        shape_values=np.array(spec.shape_values, dtype=np.float32),
        pose_name=np.array(spec.pose),
        joint_names=np.array(subject.joint_names),
        joints=subject.joints,
        coco17_names=np.array(COCO17_NAMES),
        coco17=subject.coco17,
        num_vertices=np.array(len(subject.vertices), dtype=np.int64),
        num_faces=np.array(len(subject.faces), dtype=np.int64),
        world_convention=np.array(WORLD_CONVENTION),
        bbox_min=everything.min(axis=0),
        bbox_max=everything.max(axis=0),
        normalized_from_world=normalized_from_world(everything).astype(np.float32),
        spec_json=np.array(json.dumps(spec.to_dict(), sort_keys=True)),
    )
    arrays.update(subject.garment_truth)
    write_npz(out / "truth.npz", arrays, schema=TRUTH_SCHEMA, version=TRUTH_VERSION)
    return obj_path


def random_specs(n: int, seed: int = 0) -> list[SubjectSpec]:
    """``n`` varied, reproducible specs: adults of both sexes and varied build, about 15% children,
    skin tones and poses cycling through shuffled :data:`SKIN_TONES` and :data:`RANDOM_POSES` (so any
    ``len(RANDOM_POSES)`` consecutive specs hold each of them), random hair and clothing."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5BEC]))
    tones = [list(SKIN_TONES.values())[i] for i in rng.permutation(len(SKIN_TONES))]
    poses = [RANDOM_POSES[i] for i in rng.permutation(len(RANDOM_POSES))]
    hairs = list(HAIR_COLORS.values())  # the last one, grey, only for the old

    def pick(options):
        return options[int(rng.integers(len(options)))]

    def uniform(lo: float, hi: float) -> float:
        return round(float(rng.uniform(lo, hi)), 3)

    specs = []
    for i in range(n):
        child = rng.random() < 0.15
        gender = uniform(0.0, 1.0)
        age = uniform(0.38, 0.55) if child else uniform(0.58, 1.0)
        shirt, shirt2 = (_PALETTE[int(j)] for j in rng.choice(len(_PALETTE), size=2, replace=False))
        lower, lower2 = (_PALETTE[int(j)] for j in rng.choice(len(_PALETTE), size=2, replace=False))
        specs.append(SubjectSpec(
            gender=gender, age=age, muscle=uniform(0.2, 0.8), weight=uniform(0.15, 0.9),
            height=uniform(0.2, 0.8), proportions=uniform(0.3, 0.7),
            pose=poses[i % len(poses)], skin_tone=tones[i % len(tones)],
            hair_color=hairs[int(rng.integers(len(hairs) - (0 if age > 0.85 else 1)))],
            hair_style="long" if rng.random() < 0.3 + 0.4 * gender else "short",
            eye_color=pick(IRIS_COLORS),
            shirt_color=shirt, shirt_color2=shirt2, shirt_pattern=pick(SHIRT_PATTERNS), sleeves=pick(SLEEVES),
            shirt_text=str(int(rng.integers(1, 100))),
            lower=pick(LOWER_GARMENTS if gender > 0.5 else ("trousers", "trousers", "shorts")),
            lower_color=lower, lower_color2=lower2, lower_pattern=pick(LOWER_PATTERNS),
            shoe_color=pick(_PALETTE), seed=int(rng.integers(2**31)),
        ))
    return specs
