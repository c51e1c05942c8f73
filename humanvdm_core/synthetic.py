"""Synthetic textured human subjects whose true body parameters are known (tests and benchmarks).

Contract:

- :class:`SubjectSpec` describes one subject: Anny phenotype (``gender, age, muscle, weight,
  height, proportions``, each in [0, 1]; see :mod:`humanvdm_core.body.anny_model`), a pose name from
  :data:`POSES`, skin tone, hair, clothing (shirt colours/pattern/sleeves/printed text, lower
  garment kind/colours/pattern, shoes) and a ``seed``. Everything :func:`make_subject` writes is a
  deterministic function of the spec: the same spec gives byte-identical files on one machine.
- :func:`pose_params` builds the pose from joint rotations on Anny's rig (``AnnyBody``, 104 bones):
  the upper/lower arm and leg bones (``upperarm01``, ``lowerarm01``, ``upperleg01``,
  ``lowerleg01``, ``.L``/``.R``; ``shoulder01`` too for arms-raised) are turned so that each
  points along a target direction in the world frame (the smallest rotation from its zero-pose
  direction; the comment at :data:`POSES` lists them); all other bones keep Anny's zero pose.
- :func:`make_subject` writes into ``out_dir``:

  - ``subject.obj`` + ``subject.mtl`` + ``albedo.png``: the posed Anny mesh (full ``"anny"``
    topology, 13718 vertices incl. eyeballs and tongue, in Anny's vertex order) with Anny's own UV
    layout (``vt``, seams kept) and an unlit sRGB albedo of :data:`TEXTURE_SIZE` squared texels.
  - ``truth.npz`` (:func:`humanvdm_core.io.write_npz`, schema :data:`TRUTH_SCHEMA` version 1), see
    :func:`make_subject` for the arrays. ``BodyParams.from_numpy(truth)`` fed to ``AnnyBody()``
    reproduces the OBJ's vertices (to float32 round-off).

- World frame: the project's (metres, Y up, facing +Z, the person's left at +X). The subject stands
  on the ground: its lowest vertex is at y = 0; the root joint (pelvis) is at x = z = 0. The
  ``render-training-orbits`` stage normalises scans (bounding-box centre to the origin, Y extent to
  1.7, :func:`humanvdm_core.scans.normalization_transform`); ``truth.npz`` records the same 4x4
  ``normalized_from_world`` so truth joints can be mapped into the normalised scan frame.
- Texture: coloured per body part in Anny's UV layout. Body parts come from Anny's shipped
  UV segmentation map (``anny/data/segmentation/body_parts_segmentation.png``: head, hands, feet,
  eyeballs, mouth cavity, tongue; the rest is "body") split further by Anny's skinning weights
  (torso / neck / arms / legs by dominant bone group). Garment borders (waist, neckline, sleeve
  and trouser hems, shoe tops) are cut geometrically on the subject's zero-pose surface, so they
  follow the body into any pose. The face (brows, lined eyes with irises, lips) is painted on the
  front of the head only; the back of the head is hair. The shirt carries a printed badge with
  ``shirt_text`` on the front and a contrasting yoke on the back.
- :func:`random_specs` draws varied, reproducible specs for benchmarks.
"""

from __future__ import annotations

import functools
import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch

from humanvdm_core.body.anny_model import AnnyBody
from humanvdm_core.body.model import COCO17_NAMES, BodyParams
from humanvdm_core.body.uvmap import UVPositionMap
from humanvdm_core.errors import ConfigError
from humanvdm_core.io import atomic_write_text, write_npz, write_png
from humanvdm_core.scans import DEFAULT_SUBJECT_HEIGHT, TexturedMesh, normalization_transform

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
#   degrees), forearms forward onto the thighs; no seat.
POSES: tuple[str, ...] = ("standing", "a-pose", "walking", "hands-on-hips", "arms-raised", "seated")

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
_PALETTE: tuple[RGB, ...] = (
    (200, 30, 40), (30, 80, 180), (240, 200, 40), (30, 140, 70), (240, 240, 235), (25, 25, 30),
    (120, 40, 140), (240, 120, 30), (40, 170, 190), (150, 150, 155), (90, 50, 30), (230, 110, 150),
)

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

    def __post_init__(self) -> None:
        for name in _PHENOTYPE:
            value = getattr(self, name)
            if not 0.0 <= float(value) <= 1.0:
                raise ConfigError(f"SubjectSpec.{name} must be in [0, 1], got {value}")
        for name, allowed in (("pose", POSES), ("hair_style", HAIR_STYLES), ("shirt_pattern", SHIRT_PATTERNS),
                              ("sleeves", SLEEVES), ("lower", LOWER_GARMENTS), ("lower_pattern", LOWER_PATTERNS)):
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

    @property
    def shape_values(self) -> list[float]:
        """Anny phenotype values in ``AnnyBody.shape_names`` order."""
        return [float(getattr(self, name)) for name in _PHENOTYPE]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> SubjectSpec:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"unknown SubjectSpec fields {unknown}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


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

    sides = ((1.0, "L"), (-1.0, "R"))
    # arms hang clear of the hips: a heavier body needs them further out
    relaxed_out = 7.0 + 14.0 * max(0.0, spec_weight - 0.5) / 0.5
    if name == "standing":
        for s, side in sides:
            arm(s, side, _deg_dir(3.0, relaxed_out), _deg_dir(18.0, relaxed_out - 2.0))
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
            shoulder = joint[f"upperarm01.{side}"]
            elbow, wrist = joint[f"lowerarm01.{side}"], joint[f"wrist.{side}"]
            l1, l2 = np.linalg.norm(elbow - shoulder), np.linalg.norm(wrist - elbow)
            target = np.array([s * (body_half_width + 0.035), joint["root"][1] + 0.07, joint["root"][2] - 0.01])
            upper, lower = _two_bone(shoulder, l1, l2, target, np.array([s * 1.0, 0.0, -0.6]))
            aims[f"upperarm01.{side}"] = (f"lowerarm01.{side}", upper)
            aims[f"lowerarm01.{side}"] = (f"wrist.{side}", lower)
            leg(s, side, _deg_dir(0.0, 7.0), _deg_dir(0.0, 7.0))
    elif name == "arms-raised":
        for s, side in sides:
            extra[f"shoulder01.{side}"] = np.array([0.0, 0.0, s * np.radians(20.0)])
            arm(s, side, _deg_dir(5.0, 22.0, up=True), _deg_dir(5.0, 12.0, up=True))
            leg(s, side, _deg_dir(0.0, 4.0), _deg_dir(0.0, 4.0))
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
    return Subject(
        spec=spec, params=params.detach(), vertices=vertices, faces=model.faces.numpy().copy(),
        uvs=model.uvs.numpy().astype(np.float32), uv_faces=model.uv_faces.numpy().copy(),
        joints=posed.joints[0].numpy().astype(np.float32), coco17=posed.coco17[0].numpy().astype(np.float32),
        joint_names=list(model.joint_names), albedo=albedo,
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
    return "\n".join(lines) + "\n"


def make_subject(spec: SubjectSpec, out_dir: str | Path, texture_size: int = TEXTURE_SIZE) -> Path:
    """Write one subject into ``out_dir``; returns the path of ``subject.obj``.

    ``truth.npz`` holds: ``pose``, ``shape``, ``global_orient``, ``transl``, ``scale`` (the
    ``BodyParams`` arrays, batch 1, for ``AnnyBody(topology="anny")``), ``body_model``,
    ``shape_names``/``shape_values``, ``pose_name``, ``joint_names`` + ``joints`` (J, 3) posed joint
    centres, ``coco17_names`` + ``coco17`` (17, 3), ``num_vertices``, ``num_faces``,
    ``world_convention``, ``bbox_min``/``bbox_max`` (3,) of the vertices, ``normalized_from_world``
    (4, 4, see :func:`normalized_from_world`) and ``spec_json`` (the spec as JSON). Coordinates are
    float32 metres in the world frame of the module docstring.
    """
    subject = build_subject(spec, texture_size)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_png(out / "albedo.png", subject.albedo)
    atomic_write_text(out / "subject.mtl", "newmtl albedo\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\n"
                                           "map_Kd albedo.png\n")
    obj_path = out / "subject.obj"
    atomic_write_text(obj_path, _obj_text(subject, "subject.mtl"))
    model = body_model()
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
        bbox_min=subject.vertices.min(axis=0),
        bbox_max=subject.vertices.max(axis=0),
        normalized_from_world=normalized_from_world(subject.vertices).astype(np.float32),
        spec_json=np.array(json.dumps(spec.to_dict(), sort_keys=True)),
    )
    write_npz(out / "truth.npz", arrays, schema=TRUTH_SCHEMA, version=TRUTH_VERSION)
    return obj_path


def random_specs(n: int, seed: int = 0) -> list[SubjectSpec]:
    """``n`` varied, reproducible specs: adults of both sexes and varied build, about 15% children,
    skin tones and poses cycling through shuffled :data:`SKIN_TONES` and :data:`POSES` (so any
    ``len(POSES)`` consecutive specs hold every pose), random hair and clothing."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5BEC]))
    tones = [list(SKIN_TONES.values())[i] for i in rng.permutation(len(SKIN_TONES))]
    poses = [POSES[i] for i in rng.permutation(len(POSES))]
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
