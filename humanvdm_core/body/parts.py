"""Body parts and sides of a rigged body, from its joint names and skinning weights.

:data:`PARTS` names the parts (torso, head, arms, hands, legs, feet); a joint belongs to the first part
one of whose name fragments its name holds (Anny's and SMPL/SMPL-X's rigs; the torso otherwise), and a
joint's side is the body's left (+1: Anny's ``.L``, SMPL's ``left_``), right (-1) or the midline (0).
A vertex takes the part that holds the largest sum of its skinning weights, and the side that holds
more than half of them (else the midline); the head's vertices in front of its ears are its face
(:func:`face_vertices`).
"""

from __future__ import annotations

import numpy as np

PARTS = ("torso", "head", "arms", "hands", "legs", "feet")

# joint-name fragments -> part (first match wins); Anny's and SMPL/SMPL-X's rigs
_PART_RULES = (
    ("head", ("head", "eye", "jaw")),
    ("hands", ("wrist", "finger", "metacarpal", "hand", "thumb", "index", "middle", "ring", "pinky")),
    ("arms", ("upperarm", "lowerarm", "shoulder", "elbow")),
    ("feet", ("foot", "toe", "ankle")),
    ("legs", ("upperleg", "lowerleg", "pelvis.", "hip", "knee")),
)


def part_of_joints(joint_names: list[str]) -> np.ndarray:
    """(J,) int index into :data:`PARTS` for each joint name (torso unless a rule matches)."""
    out = np.zeros(len(joint_names), np.int64)
    for j, name in enumerate(joint_names):
        low = name.lower()
        for part, keys in _PART_RULES:
            if any(k in low for k in keys):
                out[j] = PARTS.index(part)
                break
    return out


def vertex_parts(skinning_weights: np.ndarray, joint_names: list[str]) -> np.ndarray:
    """(V,) int part of each body vertex: the part with the largest summed skinning weight."""
    joint_part = part_of_joints(joint_names)
    per_part = np.zeros((skinning_weights.shape[0], len(PARTS)))
    for p in range(len(PARTS)):
        per_part[:, p] = skinning_weights[:, joint_part == p].sum(axis=1)
    return per_part.argmax(axis=1)


def side_of_joints(joint_names: list[str]) -> np.ndarray:
    """(J,) int: +1 for a joint on the body's left (Anny's ``.L``, SMPL's ``left_``), -1 on its right, 0
    on the midline."""
    out = np.zeros(len(joint_names), np.int64)
    for j, name in enumerate(joint_names):
        low = name.lower()
        if low.endswith(".l") or low.startswith("left"):
            out[j] = 1
        elif low.endswith(".r") or low.startswith("right"):
            out[j] = -1
    return out


def vertex_sides(skinning_weights: np.ndarray, joint_names: list[str]) -> np.ndarray:
    """(V,) int side of each body vertex (+1 left, -1 right, 0 midline): the side whose joints hold
    most of its skinning weight, when that is more than half of it."""
    side = side_of_joints(joint_names)
    left = skinning_weights[:, side == 1].sum(axis=1)
    right = skinning_weights[:, side == -1].sum(axis=1)
    return np.where(left > 0.5, 1, np.where(right > 0.5, -1, 0)).astype(np.int64)


FOREHEAD = 0.05  # metres above the ears' centre where the face ends and the hair begins (face_vertices)


def face_vertices(vertices: np.ndarray, parts: np.ndarray, coco17: np.ndarray) -> np.ndarray:
    """(V,) bool: the head's vertices (``parts``, :data:`PARTS`) in front of its ears, along the line from
    the ears' centre to the nose of ``coco17`` (17, 3, COCO joints in the vertices' space, world units
    metres), and at most :data:`FOREHEAD` above the ears' centre, along the line from the shoulders'
    centre to it: the face and the front of the neck's top, not the back of the head nor its top."""
    c = np.asarray(coco17, np.float64)
    ears = 0.5 * (c[3] + c[4])
    forward, up = c[0] - ears, ears - 0.5 * (c[5] + c[6])
    if np.linalg.norm(forward) < 1e-9 or np.linalg.norm(up) < 1e-9:
        return np.zeros(len(vertices), bool)
    rel = np.asarray(vertices, np.float64) - ears
    ahead = rel @ (forward / np.linalg.norm(forward))
    above = rel @ (up / np.linalg.norm(up))
    return (parts == PARTS.index("head")) & (ahead > 0.0) & (above < FOREHEAD)
