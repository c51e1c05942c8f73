"""A small procedurally made, textured, person-like mesh: a test subject that ships as code, not files.

Contract: :func:`make_person` returns a :class:`humanvdm_core.scans.TexturedMesh` about 1.72 units
tall (feet at y = 0), Y up, facing +Z, in an A-pose, built from smooth tubes (head, nose, neck,
torso, arms, legs, feet) with one generated 1024x1024 texture. The texture makes orientation and
sharpness checkable:

- head: a face (two dark eyes, a red mouth) on the front, dark hair on the back and top;
- torso: a red/white checkerboard on the front, navy/cyan diagonal stripes on the back;
- arms: the subject's left arm (+X, on the image's right in the front view) is green, the right
  arm (-X) yellow, both with fine stripes; legs: denim blue with thin lines; feet: near black.

Front-view colours are exported as :data:`FRONT_TORSO_COLORS` / :data:`BACK_TORSO_COLORS` for tests.
:func:`write_person` writes it as OBJ + MTL + PNG into a folder. Everything is deterministic.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from humanvdm_core.scans import TexturedMesh, save_obj

TEXTURE_SIZE = 1024
SKIN = (224, 172, 140)
HAIR = (60, 38, 24)
FRONT_TORSO_COLORS = ((220, 30, 30), (245, 245, 245))  # checkerboard
BACK_TORSO_COLORS = ((20, 30, 120), (40, 200, 220))  # diagonal stripes
LEFT_ARM = (40, 170, 60)
RIGHT_ARM = (235, 200, 30)
DENIM = (40, 60, 110)
SHOE = (25, 25, 25)

# Texture tiles (row0, row1, col0, col1) in image pixels, top row first.
_TILES = {
    "torso": (0, 512, 0, 512),
    "head": (0, 256, 512, 768),
    "skin": (0, 256, 768, 1024),
    "left_arm": (256, 512, 512, 768),
    "right_arm": (256, 512, 768, 1024),
    "left_leg": (512, 1024, 0, 256),
    "right_leg": (512, 1024, 256, 512),
    "feet": (512, 768, 512, 768),
}


def _tile_grid(name: str) -> tuple[np.ndarray, np.ndarray, tuple[slice, slice]]:
    """(s, t) coordinates in [0, 1] of a tile's pixel centres (s around the part, t up) and its slices."""
    r0, r1, c0, c1 = _TILES[name]
    s = (np.arange(c1 - c0) + 0.5) / (c1 - c0)
    t = 1.0 - (np.arange(r1 - r0) + 0.5) / (r1 - r0)
    ss, tt = np.meshgrid(s, t)
    return ss, tt, (slice(r0, r1), slice(c0, c1))


def make_texture() -> np.ndarray:
    """The person's 1024x1024 RGB texture (see the module docstring)."""
    img = np.zeros((TEXTURE_SIZE, TEXTURE_SIZE, 3), dtype=np.uint8)

    def fill(name: str, colours: np.ndarray) -> None:
        img[_tile_grid(name)[2]] = colours

    def pick(mask: np.ndarray, a, b) -> np.ndarray:
        return np.where(mask[..., None], np.array(a, np.uint8), np.array(b, np.uint8))

    # torso: s = 0.5 is the front centre, s = 0 / 1 the back centre
    s, t, _ = _tile_grid("torso")
    front = np.abs(s - 0.5) < 0.25
    checker = ((np.floor(s * 32) + np.floor(t * 16)) % 2).astype(bool)
    stripes = (np.floor((s * 2.0 + t) * 12) % 2).astype(bool)
    fill("torso", np.where(front[..., None], pick(checker, *FRONT_TORSO_COLORS), pick(stripes, *BACK_TORSO_COLORS)))

    # head: face on the front, hair on the back and top
    s, t, _ = _tile_grid("head")
    head = pick(np.ones_like(s, dtype=bool), SKIN, SKIN)
    hair = (t > 0.8) | ((np.abs(s - 0.5) > 0.28) & (t > 0.3))
    head[hair] = HAIR
    for ex in (0.5 - 0.07, 0.5 + 0.07):
        head[((s - ex) / 0.028) ** 2 + ((t - 0.58) / 0.045) ** 2 < 1.0] = (20, 20, 20)
    head[((s - 0.5) / 0.06) ** 2 + ((t - 0.36) / 0.025) ** 2 < 1.0] = (190, 30, 40)
    fill("head", head)

    s, t, _ = _tile_grid("skin")
    fill("skin", pick(np.ones_like(s, dtype=bool), SKIN, SKIN))
    s, t, _ = _tile_grid("left_arm")
    fill("left_arm", pick((np.floor(t * 40) % 2).astype(bool), LEFT_ARM, (20, 90, 30)))
    s, t, _ = _tile_grid("right_arm")
    fill("right_arm", pick((np.floor(t * 40) % 2).astype(bool), RIGHT_ARM, (150, 110, 10)))
    for leg in ("left_leg", "right_leg"):
        s, t, _ = _tile_grid(leg)
        fill(leg, pick((np.floor(s * 48) % 4 == 0), (90, 110, 160), DENIM))
    s, t, _ = _tile_grid("feet")
    fill("feet", pick(np.ones_like(s, dtype=bool), SHOE, SHOE))
    return img


def _tile_uv_rect(name: str, inset_px: float = 2.0) -> tuple[float, float, float, float]:
    """(u0, v0, u1, v1) of a tile in OBJ UV convention (v up), inset so filtering stays inside."""
    r0, r1, c0, c1 = _TILES[name]
    n = float(TEXTURE_SIZE)
    return ((c0 + inset_px) / n, 1.0 - (r1 - inset_px) / n, (c1 - inset_px) / n, 1.0 - (r0 + inset_px) / n)


def _tube(p0, p1, rx: float, rz: float, power: float, tile: str, segments: int, rings: int):
    """A closed smooth tube from p0 to p1 with an elliptic cross-section (rx sideways, rz front-back).

    Radius profile ``(1 - |2t - 1|^power)^(1/power)`` (power 2: ellipsoid; larger: capsule-like).
    Texture s = 0.5 faces +Z (the front), s = 0.75 faces the tube's side axis (+X for upright parts).
    """
    p0, p1 = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    axis = (p1 - p0) / np.linalg.norm(p1 - p0)
    ref = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([0.0, -1.0, 0.0])
    front = ref - ref.dot(axis) * axis
    front /= np.linalg.norm(front)
    side = np.cross(axis, front)
    s = np.linspace(0.0, 1.0, segments + 1)
    t = np.linspace(0.0, 1.0, rings + 1)
    ss, tt = np.meshgrid(s, t)  # (rings+1, segments+1)
    theta = 2.0 * np.pi * ss + np.pi  # s = 0.5 -> front
    radius = np.clip(1.0 - np.abs(2.0 * tt - 1.0) ** power, 0.0, 1.0) ** (1.0 / power)
    centre = p0 + tt[..., None] * (p1 - p0)
    pts = centre + radius[..., None] * (rx * np.sin(theta)[..., None] * side + rz * np.cos(theta)[..., None] * front)
    u0, v0, u1, v1 = _tile_uv_rect(tile)
    uv = np.stack([u0 + ss * (u1 - u0), v0 + tt * (v1 - v0)], axis=-1)
    idx = np.arange((rings + 1) * (segments + 1)).reshape(rings + 1, segments + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return pts.reshape(-1, 3), faces, uv.reshape(-1, 2)


def make_person(segments: int = 48) -> TexturedMesh:
    """The procedural person (see the module docstring); ``segments`` sets the tessellation."""
    rings = max(4, segments * 2 // 3)
    parts = [
        ((0.0, 1.455, 0.0), (0.0, 1.705, 0.0), 0.095, 0.105, 2.0, "head"),
        ((0.0, 1.555, 0.085), (0.0, 1.615, 0.115), 0.018, 0.02, 2.0, "skin"),  # nose
        ((0.0, 1.38, 0.0), (0.0, 1.50, 0.0), 0.05, 0.05, 6.0, "skin"),  # neck
        ((0.0, 0.86, 0.0), (0.0, 1.48, 0.0), 0.175, 0.11, 4.0, "torso"),
        ((0.18, 1.43, 0.0), (0.31, 0.78, 0.03), 0.05, 0.05, 4.0, "left_arm"),
        ((-0.18, 1.43, 0.0), (-0.31, 0.78, 0.03), 0.05, 0.05, 4.0, "right_arm"),
        ((0.095, 0.04, 0.0), (0.09, 1.0, 0.0), 0.075, 0.075, 6.0, "left_leg"),
        ((-0.095, 0.04, 0.0), (-0.09, 1.0, 0.0), 0.075, 0.075, 6.0, "right_leg"),
        ((0.1, 0.045, -0.06), (0.1, 0.045, 0.16), 0.05, 0.045, 3.0, "feet"),
        ((-0.1, 0.045, -0.06), (-0.1, 0.045, 0.16), 0.05, 0.045, 3.0, "feet"),
    ]
    verts, faces, uvs = [], [], []
    offset = 0
    for p0, p1, rx, rz, power, tile in parts:
        v, f, uv = _tube(p0, p1, rx, rz, power, tile, segments, rings)
        verts.append(v)
        faces.append(f + offset)
        uvs.append(uv)
        offset += len(v)
    vertices = np.concatenate(verts)
    vertices[:, 1] -= vertices[:, 1].min()  # feet on y = 0
    return TexturedMesh(vertices, np.concatenate(faces), uvs=np.concatenate(uvs), texture=make_texture())


def write_person(folder: str | Path, name: str = "person", segments: int = 48) -> Path:
    """Write the procedural person as ``name.obj`` + ``name.mtl`` + ``name.png``; returns the OBJ path."""
    return save_obj(make_person(segments), folder, name)
